"""aumesh.load_release / aumesh.predict_mesh: the card's snippet as the reference, and every input error."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest

import aumesh
from aumesh.core.families import feature_set_columns
from aumesh.core.io import atomic_savez
from aumesh.core.schema import AU_COLUMNS, N_TARGETS
from aumesh.model.input_columns import PredictionInputError
from aumesh.model.release import release_arrays
from aumesh.model.release_check import ReleaseError
from conftest import face_reference, in_card_frame


def _release(tmp_path, features: str, seed: int = 0):
    """A release NPZ from a random raw coefficient matrix (sklearn layout (1434, p)) and intercept; both returned
    in the card's frame, as the release holds them."""
    rng = np.random.default_rng(seed)
    columns = feature_set_columns(features)
    coef = rng.normal(size=(N_TARGETS, len(columns)))
    intercept = rng.normal(size=N_TARGETS) + 300.0
    reference = face_reference(rng)
    path = tmp_path / f"{features}.npz"
    atomic_savez(path, **release_arrays(coef, intercept, columns, len(columns), reference, "card", {}))
    return path, *in_card_frame(coef, intercept, reference)


def _card_snippet(path, au: np.ndarray, pose: np.ndarray | None = None) -> np.ndarray:
    """The card's inference snippet, verbatim (raw NPZ, x @ coef + intercept, axis-major unflatten)."""
    m = np.load(path, allow_pickle=False)
    x = np.concatenate([au, np.zeros(3) if pose is None else pose])
    flat = x @ m["coef"] + m["intercept"]
    return np.stack([flat[:478], flat[478:956], flat[956:]], axis=1)


@pytest.fixture
def card_release(tmp_path):
    return _release(tmp_path, "au_pose_interactions")


def test_one_row_in_every_form_matches_the_cards_snippet(card_release):
    path, _, _ = card_release
    au = np.zeros(20)
    au[AU_COLUMNS.index("AU12")], au[AU_COLUMNS.index("AU26")] = 1.0, 0.4
    expected = _card_snippet(path, au)
    m = aumesh.load_release(path)
    for aus in (au, list(au), {"AU12": 1.0, "AU26": 0.4}, np.concatenate([au, np.zeros(3)])):
        for release in (path, str(path), m, np.load(path, allow_pickle=False)):
            got = aumesh.predict_mesh(release, aus)
            assert got.shape == (478, 3)
            np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(aumesh.predict_mesh(path), _card_snippet(path, np.zeros(20)), rtol=1e-6, atol=1e-4)


def test_batches_and_dataframes_give_one_mesh_per_row(card_release):
    path, _, _ = card_release
    rng = np.random.default_rng(1)
    au = rng.uniform(0, 3, size=(5, 20))
    expected = np.stack([_card_snippet(path, row) for row in au])
    got = aumesh.predict_mesh(path, au)
    assert got.shape == (5, 478, 3)
    np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-4)
    # a DataFrame names its columns: any order, AUs it lacks are 0
    df = pd.DataFrame(au, columns=list(AU_COLUMNS))
    sub = df[["AU26", "AU12", "AU01"]]
    au_sub = np.zeros_like(au)
    for name in sub.columns:
        au_sub[:, AU_COLUMNS.index(name)] = au[:, AU_COLUMNS.index(name)]
    np.testing.assert_allclose(
        aumesh.predict_mesh(path, sub), np.stack([_card_snippet(path, r) for r in au_sub]), rtol=1e-6, atol=1e-4
    )
    assert aumesh.predict_mesh(path, df.iloc[:1]).shape == (1, 478, 3)  # a DataFrame is a batch, even of one


def test_pose_conditioned_prediction_uses_the_interactions(card_release):
    path, coef, intercept = card_release
    rng = np.random.default_rng(2)
    au, pose = rng.uniform(0, 2, size=(4, 20)), rng.uniform(-0.5, 0.5, size=(4, 3))
    # independent reference from the float64 training coefficients: [AU | pose | pose-major pose x AU]
    x_full = np.stack([np.concatenate([a, p, np.outer(p, a).ravel()]) for a, p in zip(au, pose, strict=True)])
    expected = (x_full @ coef.T + intercept).reshape(4, 3, 478).transpose(0, 2, 1)
    np.testing.assert_allclose(aumesh.predict_mesh(path, au, pose), expected, rtol=1e-5, atol=1e-3)
    df = pd.DataFrame(au, columns=list(AU_COLUMNS)).assign(
        Pitch=pose[:, 0], Roll=pose[:, 2], Yaw=pose[:, 1]
    )  # py-feat's order
    np.testing.assert_allclose(aumesh.predict_mesh(path, df), expected, rtol=1e-5, atol=1e-3)
    # one pose row applies to every AU row; pose as a mapping by name
    one = aumesh.predict_mesh(path, au, {"Yaw": pose[0, 1], "Roll": pose[0, 2], "Pitch": pose[0, 0]})
    np.testing.assert_allclose(one[0], expected[0], rtol=1e-5, atol=1e-3)
    # without interactions the 23-row coef with pose is the model: the card's snippet with a pose
    path23, _, _ = _release(path.parent, "au_pose", seed=3)
    np.testing.assert_allclose(
        aumesh.predict_mesh(path23, au[0], pose[0]), _card_snippet(path23, au[0], pose[0]), rtol=1e-6, atol=1e-4
    )


def test_a_missing_file_names_the_path_and_the_fix(tmp_path):
    missing = tmp_path / "release" / "au_to_mesh_pls.npz"
    with pytest.raises(FileNotFoundError, match=re.escape(str(missing))) as exc:
        aumesh.predict_mesh(missing, {"AU12": 1.0})
    assert "dvc repro" in str(exc.value)
    junk = tmp_path / "junk.npz"
    junk.write_text("not a zip")
    with pytest.raises(ReleaseError, match=r"junk\.npz: not a release NPZ"):
        aumesh.load_release(junk)


def test_a_release_without_a_key_is_named(card_release):
    arrays = dict(np.load(card_release[0], allow_pickle=False))
    del arrays["intercept"]
    with pytest.raises(ReleaseError, match="missing key 'intercept'"):
        aumesh.predict_mesh(arrays, {"AU12": 1.0})


@pytest.mark.parametrize(
    "aus, message",
    [
        (
            {"AU12": 1.0, "AU13": 0.5},
            r"unknown name\(s\) \['AU13'\]; the model takes AU01, AU02, .*AU43 and Pitch, Yaw, Roll",
        ),
        (
            pd.DataFrame({"AU12": [1.0], "smile": [1.0]}),
            r"aus \(DataFrame\): no column 'AU01' \(no column has a name close "
            r"to it\); 18 more missing",
        ),  # other columns: a whole table
        (
            np.zeros(19),
            r"aus has shape \(19,\); expected \(20,\) or \(N, 20\) in the release's AU order \[AU01, AU02, .*AU43\]",
        ),
        (np.zeros((4, 22)), r"aus has shape \(4, 22\); expected"),
        (np.zeros((2, 2, 20)), r"aus has shape \(2, 2, 20\)"),
        ({"AU12": np.nan}, r"aus: 1 NaN/inf value\(s\), first in 'AU12' at row 0"),
        (pd.DataFrame({"AU04": [0.0, np.inf]}), r"first in 'AU04' at row 1"),
        ({"AU12": [1.0, 2.0]}, r"values must be single numbers \(one row\), not \['AU12'\]"),
        ({"AU12": "high"}, r"aus\['AU12'\]: not numeric"),
        (pd.DataFrame({"AU12": [1.0], "Pitch": [0.1]}), r"has \['Pitch'\] but not \['Yaw', 'Roll'\]"),
    ],
)
def test_bad_aus_are_refused_with_a_message_naming_the_problem(card_release, aus, message):
    with pytest.raises(PredictionInputError, match=message):
        aumesh.predict_mesh(card_release[0], aus)


@pytest.mark.parametrize(
    "pose, message",
    [
        (
            [10.0, 20.0, 0.0],
            r"pose: Yaw reaches 20, more than pi/2: pose looks like degrees\. "
            r"Pose is in radians, in the order Pitch, Yaw, Roll\. Fix: np\.deg2rad\(pose\)",
        ),
        ([0.0, 0.0, -45.0], r"Roll reaches 45"),
        ([0.1, 0.2], r"pose has shape \(2,\); expected \(3,\) or \(N, 3\): Pitch, Yaw, Roll in radians"),
        ([0.1, np.inf, 0.0], r"pose: 1 NaN/inf value\(s\), first in 'Yaw' at row 0"),
        ({"pitch": 0.1, "Yaw": 0.0, "Roll": 0.0}, r"pose: keys must be \['Pitch', 'Yaw', 'Roll'\]"),
        (np.zeros((3, 3)), r"aus has 2 rows but pose has 3"),
    ],
)
def test_bad_pose_is_refused_with_a_message_naming_the_problem(card_release, pose, message):
    with pytest.raises(PredictionInputError, match=message):
        aumesh.predict_mesh(card_release[0], np.zeros((2, 20)), pose)


def test_radians_up_to_a_quarter_turn_are_accepted_and_pose_is_not_given_twice(card_release):
    path = card_release[0]
    assert aumesh.predict_mesh(path, {"AU12": 1.0}, [1.5, -1.5, 0.7]).shape == (478, 3)
    with pytest.raises(PredictionInputError, match="pose given twice"):
        aumesh.predict_mesh(path, np.zeros(23), [0.1, 0.0, 0.0])


# --------------------------------------------------------------------------- aumesh predict
def test_cli_predict_writes_one_mesh_per_table_row(card_release, tmp_path, capsys):
    from aumesh import cli

    path, coef, intercept = card_release
    rng = np.random.default_rng(4)
    au, pose = rng.uniform(0, 2, size=(3, 20)), rng.uniform(-0.4, 0.4, size=(3, 3))
    table = pd.DataFrame(au, columns=list(AU_COLUMNS)).assign(
        Pitch=pose[:, 0], Roll=pose[:, 2], Yaw=pose[:, 1], frame=[7, 8, 9]
    )
    table.to_csv(tmp_path / "rows.csv", index=False)
    out = tmp_path / "meshes.npz"
    assert (
        cli.main(
            ["predict", str(tmp_path / "rows.csv"), "--release", str(path), "--out", str(out), "--ignore", "frame"]
        )
        == 0
    )
    assert "wrote 3 mesh(es)" in capsys.readouterr().out
    x_full = np.stack([np.concatenate([a, p, np.outer(p, a).ravel()]) for a, p in zip(au, pose, strict=True)])
    expected = (x_full @ coef.T + intercept).reshape(3, 3, 478).transpose(0, 2, 1)
    with np.load(out, allow_pickle=False) as z:
        assert z["meshes"].shape == (3, 478, 3) and z["meshes"].dtype == np.float32
        np.testing.assert_allclose(z["meshes"], expected, rtol=1e-5, atol=1e-2)
        np.testing.assert_array_equal(z["pose"], pose)
    # the table's own errors name the table; OBJ/PLY hold one mesh; each is one line on stderr and exit 2
    for extra, message in (
        [["--strict"], r"rows\.csv: unknown name\(s\) \['frame'\]"],
        [["--out", str(tmp_path / "m.obj"), "--ignore", "frame"], r"rows\.csv has 3 rows; \.obj holds one mesh"],
        [["--ignore", "video_id"], r"--ignore names column\(s\) \['video_id'\]"],
        [["--release", str(tmp_path / "none.npz")], r"release NPZ not found: .*none\.npz"],
    ):
        assert cli.main(["predict", str(tmp_path / "rows.csv"), "--release", str(path), "--out", str(out), *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith("aumesh predict: error: ") and re.search(message, err), err


@pytest.mark.parametrize("suffix", [".obj", ".ply"])
def test_cli_predict_one_row_as_a_mesh_file_facing_out_of_the_face(tmp_path, suffix):
    from aumesh import cli
    from aumesh.geometry import face
    from aumesh.synthetic import truth

    release = tmp_path / "face.npz"
    np.savez(release, **truth.synthetic_release_arrays())
    pd.DataFrame({"AU12": [1.0]}).to_parquet(tmp_path / "smile.parquet")
    out = tmp_path / f"smile{suffix}"
    assert cli.main(["predict", str(tmp_path / "smile.parquet"), "--release", str(release), "--out", str(out)]) == 0
    lines = out.read_text().splitlines()
    if suffix == ".obj":
        verts = np.array([[float(v) for v in ln.split()[1:]] for ln in lines if ln.startswith("v ")])
        tris = np.array([[int(v) - 1 for v in ln.split()[1:]] for ln in lines if ln.startswith("f ")])
    else:
        assert lines[:2] == ["ply", "format ascii 1.0"]
        n_v = int(next(ln for ln in lines if ln.startswith("element vertex")).split()[-1])
        n_f = int(next(ln for ln in lines if ln.startswith("element face")).split()[-1])
        body = lines[lines.index("end_header") + 1 :]
        assert len(body) == n_v + n_f
        verts = np.array([[float(v) for v in ln.split()] for ln in body[:n_v]])
        faces = np.array([[int(v) for v in ln.split()] for ln in body[n_v:]])
        assert (faces[:, 0] == 3).all()
        tris = faces[:, 1:]
    expected = _card_snippet(release, np.eye(20)[AU_COLUMNS.index("AU12")])
    np.testing.assert_allclose(verts, expected, atol=1e-5)
    assert len(tris) == len(face.triangulate(expected)) and tris.min() >= 0 and tris.max() < 478
    # front faces: normals point from the eyes toward the nose tip's side (out of the face)
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    outward = verts[1] - 0.5 * (verts[33] + verts[263])
    assert (np.cross(b - a, c - a) @ outward > 0).mean() > 0.9
