"""AU-direction checker: synthetic FACS truth passes, wrong directions fail, any orientation works."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aumesh.card import directions
from aumesh.data import schema, truth
from aumesh.data.schema import AU_COLUMNS
from aumesh.geometry import face


def _verdicts(report):
    return {au: e["verdict"] for au, e in report["aus"].items()}


@pytest.fixture(scope="module")
def truth_npz(tmp_path_factory):
    path = tmp_path_factory.mktemp("rel") / "truth.npz"
    np.savez(path, **truth.synthetic_release_arrays())
    return path


def test_synthetic_truth_npz_all_20_aus_pass(truth_npz):
    report = directions.au_direction_report(truth_npz)
    assert list(report["aus"]) == list(AU_COLUMNS)
    assert _verdicts(report) == {au: "pass" for au in AU_COLUMNS}, directions.report_markdown_table(report)
    assert report["summary"] == {"pass": 20, "doubtful": 0, "fail": 0}
    json.dumps(report)  # JSON-serialisable


def test_negated_au12_field_fails_only_au12():
    arrays = truth.synthetic_release_arrays()
    k = AU_COLUMNS.index("AU12")
    arrays["coef"][k] *= -1
    v = _verdicts(directions.au_direction_report(arrays))
    assert v["AU12"] == "fail"
    assert all(verdict == "pass" for au, verdict in v.items() if au != "AU12")


def test_swapped_brow_raiser_and_lowerer_both_fail():
    arrays = truth.synthetic_release_arrays()
    i, j = AU_COLUMNS.index("AU01"), AU_COLUMNS.index("AU04")
    arrays["coef"][[i, j]] = arrays["coef"][[j, i]]
    v = _verdicts(directions.au_direction_report(arrays))
    assert v["AU01"] == "fail" and v["AU04"] == "fail"


def test_zero_field_fails_with_reason():
    arrays = truth.synthetic_release_arrays()
    arrays["coef"][AU_COLUMNS.index("AU26")] = 0.0
    e = directions.au_direction_report(arrays)["aus"]["AU26"]
    assert e["verdict"] == "fail" and "no displacement" in e["reason"]


def test_rotated_scaled_translated_release_still_all_pass():
    R = Rotation.from_euler("xyz", [0.5, -0.9, 2.5]).as_matrix()
    tpl = 180.0 * face.canonical_template() @ R.T + np.array([320.0, 240.0, -15.0])
    v = _verdicts(directions.au_direction_report(truth.synthetic_release_arrays(tpl)))
    assert v == {au: "pass" for au in AU_COLUMNS}


@pytest.mark.parametrize(
    "flip",
    [(1.0, -1.0, -1.0), (1.0, -1.0, 1.0)],
    ids=["y_up_z_out_mediapipe_canonical", "y_up_only_mirrored_handedness"],
)
def test_y_up_convention_release_still_all_pass(flip):
    flip = np.array(flip)
    tpl = face.canonical_template() * flip
    arrays = truth.synthetic_release_arrays()
    fields = truth.facs_displacement_fields() * flip  # same physical motion in the flipped frame
    arrays["mean_aligned_mesh"] = tpl.astype(np.float32)
    arrays["coef"][: len(AU_COLUMNS)] = schema.flatten_axis_major(fields)
    v = _verdicts(directions.au_direction_report(arrays))
    assert v == {au: "pass" for au in AU_COLUMNS}


def test_rows_are_selected_by_name_not_position():
    arrays = truth.synthetic_release_arrays()
    order = np.r_[np.arange(20)[::-1], 20, 21, 22]
    arrays["coef"] = arrays["coef"][order]
    arrays["input_columns"] = arrays["input_columns"][order]
    assert set(_verdicts(directions.au_direction_report(arrays)).values()) == {"pass"}


def test_missing_key_error_names_the_key():
    arrays = truth.synthetic_release_arrays()
    del arrays["mean_aligned_mesh"]
    with pytest.raises(KeyError, match="mean_aligned_mesh"):
        directions.au_direction_report(arrays)


def test_write_report_and_markdown(tmp_path, truth_npz):
    report = directions.au_direction_report(truth_npz)
    out = directions.write_report(report, tmp_path / "au_directions.json")
    assert json.loads(out.read_text())["summary"]["pass"] == 20
    assert not list(tmp_path.glob(".*tmp"))
    md = directions.report_markdown_table(report)
    assert md.count("\n| AU") == 20 and "| AU12 | Lip corner puller |" in md
