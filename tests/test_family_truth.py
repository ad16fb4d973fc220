"""The synthetic family truth (aumesh.synthetic.family_truth): fields with the shapes' meanings, recoverable from the
py-feat tables written with ``family_truth=True`` by a plain least-squares fit of the aligned meshes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from aumesh.core import families
from aumesh.core.schema import ANCHOR_INDICES, AU_COLUMNS, POSE_COLUMNS, flatten_axis_major, unflatten_axis_major
from aumesh.geometry.align import umeyama_batch
from aumesh.geometry.face import face_frame
from aumesh.geometry.landmarks import REGIONS
from aumesh.synthetic import family_truth
from aumesh.synthetic import tables as synth
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from aumesh.synthetic.pyfeat_faces import synth_setup, video_rows

# less unexplained expression and landmark jitter than the default, so that 1,200 frames pin the fields down (at the
# default a fit needs ~10k frames or more for the same precision)
SPEC = synth.SynthSpec(
    n_frames=1200, n_videos=3, seed=11, landmark_failure_rate=0.0, unexplained_scale=0.001, noise_px=0.02
)


def _up(field_flat: np.ndarray, template: np.ndarray, vertices) -> float:
    """Mean upward displacement (face frame: y down, so minus y) of ``vertices``, in inter-ocular units."""
    _, axes, scale = face_frame(template)
    d = unflatten_axis_major(field_flat)[list(vertices)] @ axes.T / scale
    return float(-d[:, 1].mean())


def test_fields_carry_the_shapes_meanings():
    """Independent of the table: the truth's fields move the face as the names say (the direction a later check must
    find), and a Left/Right pair sums to its AU's field."""
    arrays = family_truth.family_truth_arrays(*synth.true_coefficients(SPEC)[:2])
    bs, emo, t = arrays["blendshape_fields"], arrays["emotion_fields"], arrays["template_px"]
    b = {n: bs[k] for k, n in enumerate(families.BLENDSHAPE_COLUMNS)}
    e = {n: emo[k] for k, n in enumerate(families.EMOTION_COLUMNS)}
    left, right = REGIONS["lip_corner_left"], REGIONS["lip_corner_right"]
    assert _up(b["mouthSmileLeft"], t, left) > 0.05 and abs(_up(b["mouthSmileLeft"], t, right)) < 0.005
    assert _up(b["mouthSmileRight"], t, right) > 0.05 and abs(_up(b["mouthSmileRight"], t, left)) < 0.005
    assert _up(b["jawOpen"], t, REGIONS["jaw"]) < -0.1  # the chin drops
    assert _up(b["eyeBlinkLeft"], t, REGIONS["upper_eyelid_left"]) < -0.05  # the subject's left lid closes
    assert abs(_up(b["eyeBlinkLeft"], t, REGIONS["upper_eyelid_right"])) < 0.005
    assert _up(b["browInnerUp"], t, np.r_[REGIONS["brow_inner_left"], REGIONS["brow_inner_right"]]) > 0.05
    assert _up(e["happiness"], t, np.r_[left, right]) > 0.05
    assert _up(e["surprise"], t, REGIONS["jaw"]) < -0.1
    assert _up(e["surprise"], t, REGIONS["brow_inner_left"]) > 0.05
    assert not e["neutral"].any() and not b["eyeLookUpLeft"].any()
    coef, _, _ = synth.true_coefficients(SPEC)
    np.testing.assert_allclose(b["mouthSmileLeft"] + b["mouthSmileRight"], coef[AU_COLUMNS.index("AU12")], atol=1e-12)
    assert not bs[:, np.r_[ANCHOR_INDICES, np.add(ANCHOR_INDICES, 478)]].any()  # rigid anchors stay rigid


@pytest.fixture(scope="module")
def truth_table(tmp_path_factory) -> tuple[pd.DataFrame, np.ndarray]:
    """A ``family_truth=True`` MPDetector table: its columns and its (n, 478, 3) pixel meshes (the split layout, the
    meshes in a .npy beside the parquet: the quickest to write and read)."""
    folder = tmp_path_factory.mktemp("family-truth")
    summary = write_pyfeat_tables(folder, SPEC, fmt="split", no_face_rate=0.0, extra_face_rate=0.0, family_truth=True)
    path = Path(summary["files"][0])
    return pd.read_parquet(path), np.load(path.with_suffix(".npy")).astype(np.float64)


def test_fit_of_the_written_table_recovers_the_family_fields(truth_table):
    """Align each frame's mesh onto the template's anchors, fit it on the table's own columns (a constant per video,
    AUs, pose, pose x AU, blendshapes, emotions but neutral) by least squares: each family field comes back, the zero
    fields stay near 0."""
    df, mesh = truth_table
    arrays = family_truth.family_truth_arrays(*synth.true_coefficients(SPEC)[:2])
    template = arrays["template_px"]
    anchors = list(ANCHOR_INDICES)
    R, s, t = umeyama_batch(mesh[:, anchors], template[anchors])
    aligned = s[:, None, None] * np.einsum("fvj,fij->fvi", mesh, R) + t[:, None, :]
    au = df[list(AU_COLUMNS)].to_numpy()
    pose = df[list(POSE_COLUMNS)].to_numpy()
    emo_cols = families.family_columns(df.columns, "emotions")
    emo = df[[emo_cols[e] for e in families.EMOTION_COLUMNS if e != "neutral"]].to_numpy()
    bs = df[list(families.BLENDSHAPE_COLUMNS)].to_numpy()
    videos = pd.get_dummies(df["input"]).to_numpy(float)  # one intercept per video: its identity, its scale
    x = np.column_stack([videos, au, pose, (pose[:, :, None] * au[:, None, :]).reshape(len(df), -1), bs, emo])
    beta, *_ = np.linalg.lstsq(x, flatten_axis_major(aligned), rcond=None)
    k0 = videos.shape[1] + len(AU_COLUMNS) + 3 + 3 * len(AU_COLUMNS)
    est_bs, est_emo = beta[k0 : k0 + 52], beta[k0 + 52 :]
    true_bs = arrays["blendshape_fields"]
    true_emo = arrays["emotion_fields"][[families.EMOTION_COLUMNS.index(e) for e in emo_cols if e != "neutral"]]

    def cos(a, b):
        return np.einsum("kj,kj->k", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))

    moving = np.linalg.norm(true_bs, axis=1) > 0
    c_bs, c_emo = cos(est_bs[moving], true_bs[moving]), cos(est_emo, true_emo)
    assert c_bs.min() > 0.9 and np.median(c_bs) > 0.97, np.round(c_bs, 3)
    scale = np.linalg.norm(true_bs[moving], axis=1).mean()
    assert np.linalg.norm(est_bs[~moving], axis=1).max() < 0.15 * scale
    assert c_emo.min() > 0.95, np.round(c_emo, 3)
    # a wrong label is caught: each estimated emotion field is closest to its own true field
    unit_est = est_emo / np.linalg.norm(est_emo, axis=1, keepdims=True)
    unit_true = true_emo / np.linalg.norm(true_emo, axis=1, keepdims=True)
    assert (np.argmax(unit_est @ unit_true.T, axis=1) == np.arange(len(true_emo))).all()
    # the amplitudes too, not only the directions (least squares is unbiased here: the family is drawn independently)
    np.testing.assert_allclose(np.linalg.norm(est_emo, axis=1) / np.linalg.norm(true_emo, axis=1), 1.0, atol=0.1)


def test_truth_off_draws_nothing():
    """Without family_truth the blendshapes follow the AUs and the mesh is the AU truth's (the default tables,
    byte-identical to before); with it the blendshapes are independent of the AUs and the mesh moves by them."""
    counts, gen_args = synth_setup(SPEC)
    n = int(counts[0])
    fields = family_truth.family_truth_fields(*synth.true_coefficients(SPEC)[:2])
    off = video_rows(SPEC, 0, n, gen_args, "mp", 0.0, 0.0, 0)
    on = video_rows(SPEC, 0, n, gen_args, "mp", 0.0, 0.0, 0, family_fields=fields)
    a, b = on["blocks"], off["blocks"]
    smile, au12 = families.BLENDSHAPE_COLUMNS.index("mouthSmileLeft"), AU_COLUMNS.index("AU12")
    assert np.corrcoef(b["blend"][:, smile], b["au"][:, au12])[0, 1] > 0.8
    assert abs(np.corrcoef(a["blend"][:, smile], a["au"][:, au12])[0, 1]) < 0.15
    np.testing.assert_array_equal(a["au"], b["au"])  # the same AUs, poses, ... : only the families differ
    np.testing.assert_array_equal(a["pose"][:, :3], b["pose"][:, :3])  # (X, Y, Z after them follow the mesh)
    assert not np.array_equal(a["mesh"], b["mesh"])
