"""A family release (blendshapes, emotions; issue 46 item 5) predicted, rigged and animated.

The release is contract item 3's NPZ with known coefficients (tests/family_release_fixture.py: the synthetic family
truth's fields, random pose terms); predictions are checked against the NPZ's own arithmetic in numpy
(``numpy_prediction``, written from the contract, not aumesh's code), the GLBs with a parser written from the glTF
spec (tests/test_gltf.py's) and the Khronos glTF-Validator, the clip's weights against the table read by pandas.
"""

from __future__ import annotations

import json
import subprocess
import warnings

import numpy as np
import pandas as pd
import pytest

import aumesh
from aumesh.cli import main
from aumesh.core.errors import UserError
from aumesh.export import gltf
from aumesh.model.input_checks import InputRangeWarning, NoFaceWarning
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from aumesh.synthetic.tables import SynthSpec
from conftest import REPO, upright_truth_release
from family_release_fixture import POSE_FILTER, SUPPORTED_P99, family_release, numpy_prediction
from test_animate import sample_linear
from test_gltf import parse_glb

FAMILIES = ("blendshapes", "emotions")
EPS32 = np.finfo(np.float32).eps
# Detectorv2's emotion columns -> py-feat's FEAT_EMOTION_COLUMNS names (feat/plotting.py _EMOTION_ALIASES), written
# out here, not taken from aumesh
V2_EMOTIONS = {
    "Anger": "anger",
    "Disgust": "disgust",
    "Fear": "fear",
    "Happy": "happiness",
    "Sad": "sadness",
    "Surprise": "surprise",
    "Neutral": "neutral",
}


@pytest.fixture(scope="module")
def releases(tmp_path_factory):
    d = tmp_path_factory.mktemp("family")
    return {f: family_release(d / f"{f}.npz", f) for f in FAMILIES}


def _npz(path):
    return dict(np.load(path, allow_pickle=False))


def _names(npz):
    return [str(c) for c in npz["feature_columns"]]


def _within(npz, n, rng):
    """``n`` rows of inputs inside the training support (below each p99; unsupported inputs 0)."""
    p99 = npz["feature_p99"].astype(np.float64)
    x = rng.uniform(0, 1, (n, len(p99))) * p99 * 0.9
    x[:, p99 < 0.05] = 0.0
    return x


# ------------------------------------------------------------------------------------------------------ predict_mesh
@pytest.mark.parametrize("family", FAMILIES)
def test_predict_mesh_is_the_npz_arithmetic(releases, family):
    npz = _npz(releases[family])
    names = _names(npz)
    rng = np.random.default_rng(1)
    x = _within(npz, 6, rng)
    pose = rng.uniform(-0.3, 0.3, (6, 3))
    expected = numpy_prediction(npz, x, pose)
    df = pd.DataFrame(x, columns=names).assign(Pitch=pose[:, 0], Yaw=pose[:, 1], Roll=pose[:, 2])
    if family == "emotions":  # Detectorv2's names, by name (never by position)
        df = df.rename(columns={v: k for k, v in V2_EMOTIONS.items()})
    df = df[list(rng.permutation(df.columns))]  # any column order
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # inside the support: nothing to warn of
        got = aumesh.predict_mesh(releases[family], df)
    assert got.shape == (6, 478, 3)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9 * np.abs(expected).max())
    # one row by name (the others 0) and an array in the family's order, at pose 0: py-feat's own prediction
    # (PLSFeatMeshModel.predict: x @ coef[:k] + intercept)
    one = aumesh.predict_mesh(releases[family], {names[3]: 0.5})
    flat = 0.5 * npz["coef"][3].astype(np.float64) + npz["intercept"].astype(np.float64)
    np.testing.assert_allclose(one, np.stack([flat[:478], flat[478:956], flat[956:]], 1), atol=1e-9 * 1e3)
    single = aumesh.predict_mesh(releases[family], x[0])  # (k,) in the family's order, pose 0
    np.testing.assert_allclose(single, numpy_prediction(npz, x[0])[0], rtol=0, atol=1e-9 * np.abs(expected).max())


def test_a_whole_table_without_a_family_column_is_one_line(releases):
    df = pd.DataFrame({**{k: [0.1] for k in V2_EMOTIONS if k != "Happy"}, "AU01": [0.2], "FaceScore": [0.9]})
    with pytest.raises(UserError) as err:
        aumesh.predict_mesh(releases["emotions"], df)
    message = str(err.value)
    assert "\n" not in message and "'happiness'" in message and "'Happy'" in message and "Fix:" in message


def test_beyond_the_support_warns_once_by_the_familys_names(releases):
    npz = _npz(releases["blendshapes"])
    names = _names(npz)
    unsupported = [str(u) for u in npz["unsupported_features"]]
    assert unsupported and "jawOpen" not in unsupported
    row = {"jawOpen": 0.9, unsupported[0]: 0.3, "Pitch": 0.0, "Yaw": np.deg2rad(POSE_FILTER["max_abs_yaw_deg"] + 5),
           "Roll": 0.0}  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mesh = aumesh.predict_mesh(releases["blendshapes"], pd.DataFrame([row]))
    (w,) = caught
    assert w.category is InputRangeWarning and w.filename == __file__  # points at the caller's line
    text = str(w.message)
    assert text.startswith("blendshapes: ") and "jawOpen up to 0.9 (training p99 0.6)" in text, text
    assert f"{unsupported[0]} was never expressed" in text and "pose: Yaw" in text and "aus" not in text
    x = np.zeros(len(names))
    x[names.index("jawOpen")], x[names.index(unsupported[0])] = 0.9, 0.3
    np.testing.assert_allclose(mesh[0], numpy_prediction(npz, x, [0.0, row["Yaw"], 0.0])[0], atol=1e-9 * 1e3)
    assert SUPPORTED_P99 == 0.6


def test_a_row_without_a_face_is_nan(releases):
    npz = _npz(releases["emotions"])
    df = pd.DataFrame({**{k: [0.1, np.nan] for k in V2_EMOTIONS}, "AU01": [0.1, np.nan], "FaceScore": [0.9, 0.0]})
    df["Pitch"], df["Yaw"], df["Roll"] = [0.0, np.nan], [0.0, np.nan], [0.0, np.nan]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        meshes = aumesh.predict_mesh(releases["emotions"], df)
    assert [w.category for w in caught] == [InputRangeWarning, NoFaceWarning]  # neutral 0.1: never expressed
    assert "emotions: 1 of 2 row(s) without a face" in str(caught[1].message)
    assert np.isnan(meshes[1]).all()
    np.testing.assert_allclose(meshes[0], numpy_prediction(npz, np.full(7, 0.1))[0], atol=1e-6)


def test_an_au_release_is_predicted_as_before(tmp_path):
    au = upright_truth_release(tmp_path / "au.npz")
    m = _npz(au)
    flat = m["coef"][list(m["input_columns"]).index("AU12")].astype(np.float64) + m["intercept"].astype(np.float64)
    np.testing.assert_allclose(aumesh.predict_mesh(au, {"AU12": 1.0}), np.stack([flat[:478], flat[478:956], flat[956:]], 1), atol=1e-4)  # fmt: skip


# -------------------------------------------------------------------------------------------------------- the rig
@pytest.fixture(scope="module")
def rigs(releases, tmp_path_factory):
    d = tmp_path_factory.mktemp("rigs")
    out = {}
    for family, path in releases.items():
        npz = _npz(path)
        assert gltf.glb_name(npz) == f"{family}_to_mesh.glb"  # contract item 3's name
        out[family] = gltf.write_glb(npz, d / gltf.glb_name(npz), source=path.name)
    return out


@pytest.mark.parametrize("family", FAMILIES)
def test_family_rig_is_the_model_at_pose_zero(releases, rigs, family):
    npz = _npz(releases[family])
    doc, accessor = parse_glb(rigs[family])
    mesh = doc["meshes"][0]
    prim = mesh["primitives"][0]
    names = _names(npz)
    assert mesh["extras"]["targetNames"] == names and len(prim["targets"]) == len(names)
    if family == "blendshapes":  # MediaPipe's ARKit-style names, _neutral first and kept
        assert names[0] == "_neutral" and names[25] == "jawOpen" and len(names) == 52
        assert "ARKit" in doc["asset"]["extras"]["neutral_target"]
    base = accessor(prim["attributes"]["POSITION"]).astype(np.float64)
    targets = np.stack([accessor(t["POSITION"]) for t in prim["targets"]]).astype(np.float64)
    rng = np.random.default_rng(2)
    for w in [np.zeros(len(names)), np.eye(len(names))[1], rng.uniform(0, 1, len(names))]:
        expected = numpy_prediction(npz, w)[0]
        bound = 4 * EPS32 * (np.abs(base) + np.tensordot(np.abs(w), np.abs(targets), 1))
        assert (np.abs(base + np.tensordot(w, targets, 1) - expected) <= bound).all()
    extras = doc["asset"]["extras"]
    assert extras["family"] == family and extras["unsupported_targets"] == [str(u) for u in npz["unsupported_features"]]
    assert extras["training_range"][names[1]]["p99"] == pytest.approx(float(npz["feature_p99"][1]))


def _validate(glb):
    proc = subprocess.run(
        ["node", str(REPO / "tests" / "tools" / "validate_gltf.cjs"), str(glb)],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )
    report = json.loads(proc.stdout)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]
    assert report["issues"]["numWarnings"] == 0, report["issues"]["messages"]
    return report


@pytest.mark.parametrize("family", FAMILIES)
def test_family_rig_passes_the_khronos_gltf_validator(rigs, node_tools, family):
    report = _validate(rigs[family])
    assert report["info"]["hasMorphTargets"] and report["info"]["totalVertexCount"] == 478


# ----------------------------------------------------------------------------------------------------- animation
@pytest.fixture(scope="module")
def v2_table(tmp_path_factory):
    """A Detectorv2 CSV of one video (emotions under Detectorv2's names), with no-face rows and background faces."""
    d = tmp_path_factory.mktemp("v2")
    summary = write_pyfeat_tables(
        d, SynthSpec(n_frames=50, n_videos=1, seed=4), detector="v2", no_face_rate=0.06, extra_face_rate=0.2
    )
    return summary["files"][0]


def _largest_faces(path) -> pd.DataFrame:
    """The table's face rows, the largest face of each frame, by frame (pandas, from the table alone)."""
    df = pd.read_csv(path)
    face = df[df["FaceScore"].fillna(0) > 0].copy()
    face["area"] = face["FaceRectWidth"] * face["FaceRectHeight"]
    return face.sort_values("area", ascending=False).drop_duplicates("frame").sort_values("frame")


@pytest.mark.parametrize("family", FAMILIES)
def test_family_animation_samples_are_the_model(releases, v2_table, tmp_path, node_tools, family):
    out = tmp_path / f"{family}.glb"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["animate", str(v2_table), "--out", str(out), "--release", str(releases[family]),
                     "--family", family]) == 0  # fmt: skip
    npz = _npz(releases[family])
    names = _names(npz)
    doc, accessor = parse_glb(out)
    anim = doc["animations"][0]
    (channel,) = anim["channels"]
    sampler = anim["samplers"][channel["sampler"]]
    times = accessor(sampler["input"]).astype(np.float64)
    weights = accessor(sampler["output"]).reshape(len(times), -1).astype(np.float64)
    prim = doc["meshes"][0]["primitives"][0]
    assert doc["meshes"][0]["extras"]["targetNames"] == names and weights.shape[1] == len(names)
    base = accessor(prim["attributes"]["POSITION"]).astype(np.float64)
    targets = np.stack([accessor(t["POSITION"]) for t in prim["targets"]]).astype(np.float64)
    faces = _largest_faces(v2_table)
    columns = [{v: k for k, v in V2_EMOTIONS.items()}.get(n, n) for n in names]  # the table's names
    table_weights = faces[columns].to_numpy(np.float64)
    first = pd.read_csv(v2_table, usecols=["frame"])["frame"].min()
    t = ((faces["frame"].to_numpy() - first) / 25.0).astype(np.float32).astype(np.float64)
    w = np.stack([sample_linear(times, weights, s) for s in t])
    np.testing.assert_allclose(w, table_weights, rtol=0, atol=2 * EPS32)  # float32 keyframes of the table's values
    sampled = base + np.tensordot(w, targets, 1)
    expected = numpy_prediction(npz, table_weights)
    bound = 8 * EPS32 * (np.abs(base) + np.tensordot(np.abs(w), np.abs(targets), 1)) + 4 * EPS32 * np.abs(
        np.tensordot(np.ones_like(w), np.abs(targets), 1)
    )
    assert (np.abs(sampled - expected) <= bound).all(), np.abs(sampled - expected).max()
    assert doc["asset"]["extras"]["family"] == family
    report = _validate(out)
    assert report["info"]["animationCount"] == 1


def _error(capsys, *argv) -> str:
    assert main(["animate", *map(str, argv)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    return err


def test_a_clip_without_a_family_column_is_one_line(releases, v2_table, tmp_path, capsys):
    bad = tmp_path / "no_jaw.csv"
    pd.read_csv(v2_table).drop(columns=["jawOpen"]).to_csv(bad, index=False)
    err = _error(capsys, bad, "--out", tmp_path / "x.glb", "--release", releases["blendshapes"], "--family",
                 "blendshapes")  # fmt: skip
    assert str(bad) in err and "'jawOpen'" in err and "Fix:" in err
    # the family the release is not: named, with the release to use
    err = _error(capsys, v2_table, "--out", tmp_path / "x.glb", "--release", releases["emotions"], "--family",
                 "blendshapes")  # fmt: skip
    assert "the emotions release" in err and "releases/blendshapes/bs_to_mesh_pls.npz" in err


# ---------------------------------------------------------------------------------------------- aumesh predict
def test_aumesh_predict_streams_a_family_release(releases, v2_table, tmp_path):
    """``aumesh predict --release <family NPZ>`` on Detectorv2's whole table: its emotion columns by name, its pose
    (the pose x input terms), no-face rows NaN; the meshes are the NPZ's arithmetic on the table read by pandas."""
    out = tmp_path / "meshes.npz"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["predict", str(v2_table), "--out", str(out), "--release", str(releases["emotions"])]) == 0
    got = np.load(out, allow_pickle=False)
    npz = _npz(releases["emotions"])
    assert [str(c) for c in got["au_columns"]] == _names(npz) and str(got["family"]) == "emotions"
    df = pd.read_csv(v2_table)
    x = df.rename(columns=V2_EMOTIONS)[_names(npz)].to_numpy(np.float64)
    expected = numpy_prediction(npz, x, df[["Pitch", "Yaw", "Roll"]].to_numpy(np.float64))
    face = ~got["no_face"]
    assert (~face).any() and face.any() and np.isnan(got["meshes"][~face]).all()
    assert (df["FaceScore"].fillna(0).to_numpy() > 0).tolist() == face.tolist()
    np.testing.assert_allclose(
        got["meshes"][face], expected[face], rtol=0, atol=4 * EPS32 * np.abs(expected[face]).max()
    )


@pytest.mark.parametrize("design", ["", "_pose"])
def test_designs_without_interactions_predict_and_rig(tmp_path, design):
    """``emotions`` (no pose: pose has no effect) and ``emotions_pose`` (pose rows, no products): the prediction is
    the NPZ's arithmetic and the rig its pose-0 case."""
    path = family_release(tmp_path / "e.npz", "emotions", design=design)
    npz = _npz(path)
    assert len(npz["input_columns"]) == 7 + (3 if design else 0)
    x, pose = np.full(7, 0.05), np.array([0.1, -0.2, 0.05])
    got = aumesh.predict_mesh(path, x, pose)
    expected = numpy_prediction(npz, x, pose)[0] if design else numpy_prediction(npz, x)[0]
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9 * np.abs(expected).max())
    doc, accessor = parse_glb(gltf.write_glb(npz, tmp_path / "e.glb"))
    prim = doc["meshes"][0]["primitives"][0]
    targets = np.stack([accessor(t["POSITION"]) for t in prim["targets"]]).astype(np.float64)
    base = accessor(prim["attributes"]["POSITION"]).astype(np.float64)
    np.testing.assert_allclose(base + np.tensordot(x, targets, 1), numpy_prediction(npz, x)[0], atol=1e-3)
