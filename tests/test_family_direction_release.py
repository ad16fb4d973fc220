"""The release's direction check of a family (issue 46, item 4): a family release NPZ written per the contract
(``coef`` (p, 1434) with the family's k inputs first, ``feature_columns``, ``mean_aligned_mesh``, ...) from a fit of
synthetic frames whose truth is known (:mod:`aumesh.synthetic.family_mixing`), read back by
:func:`aumesh.card.family_directions.family_direction_report` and refused by ``check_family_directions``.

The fit is ordinary least squares with an intercept on softmax emotions / [0, 1] blendshapes (numpy, another route
than aumesh's PLS), in a frame turned, scaled and flipped to y-up against the truth's, so the report must recover the
face frame itself. A table whose columns were swapped before the fit is what a detector's mislabelled export gives.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from aumesh.card import family_directions as fd
from aumesh.core.errors import DirectionCheckError, UserError
from aumesh.core.families import BLENDSHAPE_COLUMNS, EMOTION_COLUMNS, PYFEAT_FEATURE, feature_set_columns
from aumesh.core.schema import POSE_COLUMNS, flatten_axis_major, unflatten_axis_major
from aumesh.synthetic import family_mixing as fm
from aumesh.synthetic.family_truth import draw_family_values

# a release frame unlike the truth's: turned 20 degrees about z, y up (py-feat draws y-up), 300 units per IOD
_A = np.deg2rad(20.0)
_R = np.array([[np.cos(_A), -np.sin(_A), 0.0], [np.sin(_A), np.cos(_A), 0.0], [0.0, 0.0, 1.0]]) @ np.diag([1, -1, -1])
_S = 300.0


@pytest.fixture(scope="module")
def truth():
    return fm.truth_fields()


def _write_release(folder, family: str, columns: list[str], coef: np.ndarray, mean: np.ndarray, **extra):
    """A family release NPZ as the contract has it: design rows (inputs, pose, pose x input) (p, 1434) float32."""
    design = feature_set_columns(f"{family}_pose_interactions")
    k = len(columns)
    rows = np.vstack([coef, np.random.default_rng(0).normal(scale=1e-3, size=(len(design) - k, coef.shape[1]))])
    path = folder / f"{PYFEAT_FEATURE[family][1]}.npz"
    np.savez(
        path,
        coef=rows.astype(np.float32),
        intercept=flatten_axis_major(mean).astype(np.float32),
        feature_columns=np.array(columns),
        pose_columns=np.array(POSE_COLUMNS),
        mean_aligned_mesh=mean.astype(np.float32),
        feature_p99=np.ones(k, dtype=np.float32),
        unsupported_features=np.array(extra.pop("unsupported", []), dtype=str),
        mean_neutral_mesh=mean.astype(np.float32),
        family=np.array(family),
        input_columns=np.array(design),
        n_components=np.array(k),
    )
    return path


def _emotion_release(tmp_path, truth, swap: tuple[str, str] | None = None):
    rng = np.random.default_rng(4)
    _, emotions = draw_family_values(rng, 3000)
    table = emotions.copy()
    if swap:  # the table's columns swapped before the fit: the fit's rows are labelled wrong
        i, j = EMOTION_COLUMNS.index(swap[0]), EMOTION_COLUMNS.index(swap[1])
        table[:, [i, j]] = table[:, [j, i]]
    # the meshes move by the true emotions; the fit sees the table's columns under the family's names
    n = len(emotions)
    y = emotions @ truth["emotions"] + rng.normal(scale=0.002, size=(n, truth["emotions"].shape[1]))
    x = np.hstack([np.ones((n, 1)), table])
    beta = np.linalg.lstsq(x, y, rcond=None)[0][1:]
    turn = lambda f: flatten_axis_major(unflatten_axis_major(f) @ _R.T * _S)  # noqa: E731
    mean = unflatten_axis_major(turn(flatten_axis_major(truth["mesh"])))
    return _write_release(tmp_path, "emotions", list(EMOTION_COLUMNS), turn(beta), mean)


def test_a_correctly_labelled_emotion_release_passes(tmp_path, truth):
    path = _emotion_release(tmp_path, truth)
    report = fd.family_direction_report(path)
    assert report["family"] == "emotions" and report["source"] == str(path)
    assert report["verdict"] == "pass", report["message"]
    assert report["summary"] == {n: "pass" for n in EMOTION_COLUMNS}
    fd.check_family_directions(report, path)  # no refusal
    written = fd.write_report(report, tmp_path)
    assert written.name == "emotions_directions.json"
    assert json.loads(written.read_text())["summary"] == report["summary"]


def test_an_emotion_table_swapped_before_the_fit_is_refused_naming_the_swap(tmp_path, truth):
    path = _emotion_release(tmp_path, truth, swap=("happiness", "surprise"))
    report = fd.family_direction_report(path)
    assert report["verdict"] == "fail"
    assert {n: v for n, v in report["summary"].items() if v != "pass"} == {"happiness": "fail", "surprise": "fail"}
    with pytest.raises(DirectionCheckError) as err:
        fd.check_family_directions(report, "releases/emotions/emotion_to_mesh_pls.npz")
    msg = str(err.value)
    assert isinstance(err.value, UserError)  # the CLI prints it on one line, exit 2
    assert "\n" not in msg
    assert msg.startswith(
        "releases/emotions/emotion_to_mesh_pls.npz: emotion columns labelled happiness and surprise look swapped: "
        "'happiness' moves like surprise, 'surprise' moves like happiness"
    )
    assert "check the detector's column names and order" in msg and "by name" in msg


def _blendshape_release(tmp_path, truth, swap: tuple[str, str] | None = None, unsupported=()):
    rng = np.random.default_rng(6)
    blend, _ = draw_family_values(rng, 2500)
    cols = list(BLENDSHAPE_COLUMNS)
    if swap:
        i, j = cols.index(swap[0]), cols.index(swap[1])
        blend_table = blend.copy()
        blend_table[:, [i, j]] = blend_table[:, [j, i]]
    else:
        blend_table = blend
    n = len(blend)
    y = blend @ truth["blendshapes"] + rng.normal(scale=0.002, size=(n, truth["blendshapes"].shape[1]))
    beta = np.linalg.lstsq(np.hstack([np.ones((n, 1)), blend_table]), y, rcond=None)[0][1:]
    turn = lambda f: flatten_axis_major(unflatten_axis_major(f) @ _R.T * _S)  # noqa: E731
    mean = unflatten_axis_major(turn(flatten_axis_major(truth["mesh"])))
    return _write_release(tmp_path, "blendshapes", cols, turn(beta), mean, unsupported=list(unsupported))


def test_a_blendshape_release_passes_and_an_eyeblink_swap_is_refused(tmp_path, truth):
    good = fd.family_direction_report(_blendshape_release(tmp_path, truth, unsupported=["cheekPuff"]))
    assert good["family"] == "blendshapes" and good["verdict"] != "fail", good["message"]
    s = good["summary"]
    assert s["cheekPuff"] == "unchecked" and s["_neutral"] == "unchecked"
    # the shapes the synthetic truth moves pass; those it leaves still (gaze, jawLeft, ...) are doubtful, not failed
    moving = [n for n, f in zip(BLENDSHAPE_COLUMNS, truth["blendshapes"], strict=True) if np.any(f) and n in s]
    assert all(s[n] == "pass" for n in moving), {n: s[n] for n in moving if s[n] != "pass"}
    assert all(v in ("pass", "doubtful", "unchecked") for v in s.values())
    fd.check_family_directions(good)

    (tmp_path / "bad").mkdir()
    bad = fd.family_direction_report(
        _blendshape_release(tmp_path / "bad", truth, swap=("eyeBlinkLeft", "eyeBlinkRight"))
    )
    assert bad["verdict"] == "fail"
    assert {n for n, v in bad["summary"].items() if v == "fail"} == {"eyeBlinkLeft", "eyeBlinkRight"}
    with pytest.raises(
        DirectionCheckError,
        match=r"bs_to_mesh_pls\.npz: blendshape left/right look swapped: "
        r"eyeBlinkLeft/Right\. Fix: check the detector's column names",
    ):
        fd.check_family_directions(bad)
    # the same swapped release, from tables whose eyeBlinkLeft and Right moved together: the fit could not tell the
    # sides apart, so the side is doubtful (a card warning), not a refusal
    npz = tmp_path / "bad" / "bs_to_mesh_pls.npz"
    together = fd.family_direction_report(npz, together=["eyeBlinkLeft/Right"])
    assert together["check"]["pairs"]["eyeBlinkLeft/Right"]["verdict"] == "doubtful"
    assert together["summary"]["eyeBlinkLeft"] == "doubtful" and together["verdict"] != "fail"
    fd.check_family_directions(together)


def test_a_release_of_no_family_is_a_one_line_error(tmp_path, truth):
    path = _write_release(tmp_path, "emotions", list(EMOTION_COLUMNS), truth["emotions"], truth["mesh"])
    arrays = dict(np.load(path))
    arrays.pop("family")
    arrays["feature_columns"] = np.array([f"x{i}" for i in range(7)])
    with pytest.raises(KeyError, match="not a blendshape or emotion release"):
        fd.family_direction_report(arrays)
