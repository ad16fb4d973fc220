"""The card's canonical frame: y up, x to the subject's left, z out of the face, from the anatomy alone."""

from __future__ import annotations

import glob
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from scipy.spatial.transform import Rotation

from aumesh.core.schema import AU_COLUMNS, N_VERTICES, unflatten_axis_major
from aumesh.data import tables
from aumesh.geometry import face
from aumesh.geometry.frame import canonical_frame, rotate_axis_major, to_canonical
from aumesh.model.inference import predict_mesh
from aumesh.model.release import release_arrays
from aumesh.pipeline import evaluate as ev
from aumesh.pipeline import prepare
from aumesh.pipeline.evaluate.prepared_data import load_prepared
from aumesh.synthetic import tables as synth
from aumesh.synthetic import truth
from conftest import default_config

EYES = [33, 263, 133, 362]


def _assert_card_orientation(mesh: np.ndarray, exact: bool = True) -> None:
    """Anatomy read off the raw coordinates: x to the subject's left, y up, z out of the face.

    ``exact``: the mesh the frame was found from; its canthi lie on x and chin -> forehead in the x-y plane.
    """
    assert mesh[263, 0] > mesh[33, 0] and mesh[362, 0] > mesh[133, 0]  # subject's left has larger x
    assert mesh[10, 1] > mesh[152, 1] and mesh[0, 1] > mesh[17, 1]  # forehead above chin, upper lip above lower
    assert mesh[1, 2] > mesh[EYES, 2].mean()  # the nose tip is in front of the eyes
    if exact:
        tol = 1e-5 * np.ptp(mesh)
        assert abs(mesh[263, 1] - mesh[33, 1]) < tol and abs(mesh[263, 2] - mesh[33, 2]) < tol
        assert abs(mesh[10, 2] - mesh[152, 2]) < tol


def test_template_in_image_convention_maps_to_the_half_turn_about_x():
    tpl = face.canonical_template()  # image convention: y down, z away from the camera
    rotation, origin = canonical_frame(tpl)
    np.testing.assert_allclose(rotation, np.diag([1.0, -1.0, -1.0]), atol=1e-12)  # known rotation: 180 deg about x
    np.testing.assert_allclose(origin, tpl.mean(axis=0), atol=1e-12)
    _assert_card_orientation(to_canonical(tpl, rotation, origin))


@pytest.mark.parametrize("seed", range(4))
def test_any_rotation_of_the_face_comes_back_to_the_same_canonical_mesh(seed):
    tpl = face.canonical_template() * 60.0 + 300.0
    rot = Rotation.random(random_state=seed).as_matrix()
    moved = tpl @ rot.T + np.array([5.0, -7.0, 11.0])
    r1, o1 = canonical_frame(tpl)
    r2, o2 = canonical_frame(moved)
    assert np.linalg.det(r2) == pytest.approx(1.0)
    np.testing.assert_allclose(to_canonical(moved, r2, o2), to_canonical(tpl, r1, o1), atol=1e-9)


def test_a_mirrored_mesh_is_refused_not_reflected():
    mirrored = face.canonical_template() * np.array([1.0, 1.0, -1.0])  # left-handed: z toward the camera
    with pytest.raises(ValueError, match="mirrored.*right-handed"):
        canonical_frame(mirrored)


def test_axis_major_rotation_matches_per_vertex_rotation():
    rng = np.random.default_rng(0)
    rot, origin = Rotation.random(random_state=1).as_matrix(), rng.normal(size=3)
    flat = rng.normal(size=(5, 3 * N_VERTICES))
    expected = (unflatten_axis_major(flat) - origin) @ rot.T
    np.testing.assert_allclose(unflatten_axis_major(rotate_axis_major(flat, rot, origin)), expected, atol=1e-12)
    np.testing.assert_allclose(
        unflatten_axis_major(rotate_axis_major(flat, rot)), unflatten_axis_major(flat) @ rot.T, atol=1e-12
    )


def test_release_predicts_the_aligned_model_rotated_exactly():
    rng = np.random.default_rng(3)
    tpl = face.canonical_template() * 60.0 + 300.0
    reference = {
        "mean_aligned_mesh": tpl,
        "mean_low_au_mesh": tpl,
        "reference_anchors": tpl[:12],
        "anchor_indices": np.arange(12),
    }
    columns = [*AU_COLUMNS, "Pitch", "Yaw", "Roll"]
    coef, intercept = rng.normal(size=(3 * N_VERTICES, 23)), rng.normal(size=3 * N_VERTICES)
    arrays = release_arrays(coef, intercept, columns, 23, reference, "", {})
    rotation, origin = canonical_frame(tpl)
    x = np.concatenate([rng.normal(size=20), rng.uniform(-0.5, 0.5, size=3)])  # pose in radians
    aligned = unflatten_axis_major(x @ coef.T + intercept)
    np.testing.assert_allclose(
        predict_mesh(arrays, x[:20], x[20:]), to_canonical(aligned, rotation, origin), rtol=1e-5, atol=1e-3
    )
    np.testing.assert_allclose(arrays["mean_aligned_mesh"].mean(axis=0), 0.0, atol=1e-3)  # origin: its centroid
    _assert_card_orientation(arrays["mean_aligned_mesh"])


# --------------------------------------------------------------------------- tables in other conventions
def _convert_tables(src: Path, dst: Path, rotation: np.ndarray) -> None:
    """The same tables with every mesh point turned by ``rotation`` (e.g. y-down image pixels -> y up)."""
    import pyarrow as pa

    dst.mkdir(parents=True)
    for path in sorted(glob.glob(str(src / "*.parquet"))):
        table = pq.read_table(path)
        cols = {name: table.column(name).to_numpy() for name in table.column_names}
        pts = np.stack([np.stack([cols[f"{a}_{i}"] for a in "xyz"], axis=-1) for i in range(N_VERTICES)], axis=1)
        pts = pts.astype(np.float64) @ rotation.T
        for i in range(N_VERTICES):
            for a, axis in enumerate("xyz"):
                cols[f"{axis}_{i}"] = pts[:, i, a].astype(np.float32)
        pq.write_table(pa.table(cols), dst / Path(path).name)


def _release_from(data_dir: Path, work: Path):
    cfg = default_config(**{"paths.data_dir": str(data_dir)})
    prepare.run(tables.discover(data_dir, cfg.data.tables, cfg.data.mesh_npy), cfg, work)
    prepared = load_prepared(work)
    cv, final = ev.cross_validate_and_fit(prepared, cfg)
    arrays = release_arrays(
        final.coef, final.mesh_intercept, final.feature_columns, final.n_components, prepared.reference, "", {}
    )
    return cv, arrays


@pytest.fixture(scope="module")
def three_conventions(tmp_path_factory):
    """One synthetic set (image pixels: y down, z into the image), the same in y-up, and generically rotated."""
    root = tmp_path_factory.mktemp("conventions")
    synth.write_tables(root / "image", synth.SynthSpec(n_frames=600, n_videos=60, seed=11))
    y_up = np.diag([1.0, -1.0, -1.0])  # proper: a half turn about x
    generic = Rotation.from_euler("xyz", [0.4, -0.7, 1.1]).as_matrix()
    _convert_tables(root / "image", root / "y_up", y_up)
    _convert_tables(root / "image", root / "generic", generic)
    return {name: _release_from(root / name, root / f"prepared_{name}") for name in ("image", "y_up", "generic")}


@pytest.mark.parametrize("name", ["image", "y_up", "generic"])
@pytest.mark.slow
def test_release_is_in_the_card_frame_whatever_the_tables_convention(three_conventions, name):
    _, arrays = three_conventions[name]
    _assert_card_orientation(arrays["mean_aligned_mesh"].astype(np.float64))
    _assert_card_orientation(arrays["mean_low_au_mesh"].astype(np.float64), exact=False)
    neutral = predict_mesh(arrays, np.zeros(20))
    assert (
        neutral[263, 0] > neutral[33, 0]
        and neutral[10, 1] > neutral[152, 1]
        and neutral[1, 2] > neutral[EYES, 2].mean()
    )
    # AU12 (lip corner puller) pulls the corners up and outward: the subject's left corner toward +x, both toward +y
    smile = predict_mesh(arrays, np.eye(20)[AU_COLUMNS.index("AU12")]) - neutral
    assert smile[291, 0] > 0 > smile[61, 0] and smile[291, 1] > 0 and smile[61, 1] > 0
    # reference anchors are the same anatomical points of the released mean face (same frame)
    anchors = arrays["reference_anchors"].astype(np.float64)
    assert anchors[list(arrays["anchor_indices"]).index(263), 0] > anchors[list(arrays["anchor_indices"]).index(33), 0]


@pytest.mark.parametrize("name", ["y_up", "generic"])
@pytest.mark.slow
def test_same_release_and_cv_metrics_from_every_convention(three_conventions, name):
    cv_ref, ref = three_conventions["image"]
    cv, arrays = three_conventions[name]
    scale = np.abs(ref["intercept"]).max()
    for key in ("coef", "intercept", "coef_full", "mean_aligned_mesh", "mean_low_au_mesh", "reference_anchors"):
        np.testing.assert_allclose(arrays[key], ref[key], atol=2e-4 * scale, err_msg=key)
    # rotation-invariant metrics are the same (the generic rotation re-rounds the float32 tables: ~1e-7);
    # the per-coordinate MAE too when the rotation only permutes axes with signs (y-down -> y-up is exact)
    tol = 1e-9 if name == "y_up" else 1e-5
    np.testing.assert_allclose(cv.r2_folds, cv_ref.r2_folds, rtol=0, atol=tol)
    np.testing.assert_allclose(cv.vertex_error_folds, cv_ref.vertex_error_folds, rtol=tol)
    if name == "y_up":
        np.testing.assert_allclose(cv.mae_folds, cv_ref.mae_folds, rtol=tol)


# --------------------------------------------------------------------------- the card's pose snippet
@pytest.fixture(scope="module")
def canonical_face():
    arrays = truth.synthetic_release_arrays()  # through release_arrays: the card frame
    return predict_mesh(arrays, np.zeros(20))


def _posed(mesh, pitch=0.0, yaw=0.0, roll=0.0):
    """The card's render-time rotation, verbatim: posed = canonical_mesh @ R.T."""
    R = Rotation.from_euler("xyz", [pitch, yaw, roll]).as_matrix()
    return mesh @ R.T


def test_positive_yaw_turns_the_nose_toward_the_subjects_left(canonical_face):
    m = _posed(canonical_face, yaw=0.4)
    centre = m[EYES].mean(axis=0)
    assert m[1, 0] - centre[0] > 0.1 * np.linalg.norm(m[263] - m[33])  # +x = the subject's left
    assert m[263, 2] < m[33, 2]  # the left eye turns away from the viewer


def test_positive_pitch_tips_the_nose_down(canonical_face):
    m, rest = _posed(canonical_face, pitch=0.4), canonical_face
    assert (m[1, 1] - m[EYES, 1].mean()) < (rest[1, 1] - rest[EYES, 1].mean()) - 0.05
    assert m[152, 2] < rest[152, 2] - 0.05  # the chin goes back


def test_positive_roll_raises_the_subjects_left_eye(canonical_face):
    m = _posed(canonical_face, roll=0.3)
    assert m[263, 1] > m[33, 1] + 0.2 * np.linalg.norm(m[263] - m[33])
