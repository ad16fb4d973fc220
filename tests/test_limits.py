"""The release says what its data supports: ``warnings`` in model_card.json, "Limits of this release" in the card."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from aumesh.card import limits
from aumesh.card.model_card import model_card_markdown
from aumesh.core.schema import AU_COLUMNS
from test_release import _card


def _large_card() -> dict:
    """The reference card's scale: 344,418 frames of 9,978 videos, 83 features, tight folds, every AU reliable."""
    card = _card()
    card["data"] |= {"n_frames": 344_418, "n_videos": 9_978, "people": {"identity_labels": 5000, "note": ""}}
    card["data"]["counts"] |= {"frames_in": 360_000, "dropped_pose": 12_000}
    card["cv"] |= {"r2_folds": [0.2395, 0.2472, 0.2463], "r2_mean": 0.2443, "r2_std": 0.0034}
    card["cv"] |= {"au_reliability": {au: 0.9 for au in AU_COLUMNS}, "au_reliability_median": 0.9}
    card["cv"]["au_reliability_min"] = 0.9
    card["au_directions"] = {au: "pass" for au in AU_COLUMNS}
    return card


def _small_card() -> dict:
    """Issue 41's real clips: 472 frames of one presenter, AU09 never above 0.035, folds 0.37 +- 0.40."""
    card = _large_card()
    card["data"] |= {
        "n_frames": 472,
        "n_videos": 12,
        "people": {"identity_labels": 1, "note": "py-feat Identity"},
        "unsupported_inputs": ["AU09", "AU43"],
        "input_ranges": {"AU09": {"p99": 0.035}, "AU43": {"p99": 0.01}, "AU12": {"p99": 0.9}},
    }
    card["data"]["counts"] |= {"frames_in": 800, "dropped_pose": 320, "dropped_pose_fraction": 0.4}
    card["cv"] |= {"r2_folds": [0.6, 0.7, -0.19], "r2_mean": 0.37, "r2_std": 0.40}
    card["cv"]["au_reliability"] = {au: (0.3 if au == "AU24" else 0.9) for au in AU_COLUMNS}
    card["au_directions"] = {au: {"AU02": "fail", "AU05": "doubtful"}.get(au, "pass") for au in AU_COLUMNS}
    return card


def test_a_release_at_the_reference_scale_has_no_warning_and_says_so_in_one_line():
    card = _large_card()
    warnings = limits.release_warnings(card, au_field_iod={au: 0.05 + 0.005 * i for i, au in enumerate(AU_COLUMNS)})
    assert warnings == []
    text = model_card_markdown(card | {"warnings": warnings}, None, [])
    section = text[text.index("## Limits of this release") :].split("\n## ")[0].strip().splitlines()
    assert [line for line in section[1:] if line] == [section[-1]] and section[-1].startswith("No limit found")


def test_a_small_single_person_release_gets_each_warning_with_its_numbers():
    card = _small_card()
    sizes = {au: 0.05 for au in AU_COLUMNS} | {"AU09": 1.3}  # issue 41: AU09 moves vertices by 1.3 IOD
    warnings = limits.release_warnings(card, au_field_iod=sizes)
    by_code = {w["code"]: w for w in warnings}
    assert set(by_code) == {
        "small_data_frames",
        "few_videos",
        "few_people",
        "unsupported_inputs",
        "low_au_reliability",
        "au_direction_fail",
        "au_direction_doubtful",
        "implausible_fields",
        "fold_spread",
        "pose_filter_dropped",
    }
    assert by_code["small_data_frames"]["frames_per_feature"] == pytest.approx(472 / 83, abs=0.01)
    assert by_code["few_people"]["identity_labels"] == 1 and "one person" in by_code["few_people"]["message"]
    assert by_code["unsupported_inputs"]["aus"] == ["AU09", "AU43"]
    assert by_code["unsupported_inputs"]["p99"] == {"AU09": 0.035, "AU43": 0.01}
    assert by_code["low_au_reliability"]["aus"] == ["AU24"]
    assert by_code["au_direction_fail"]["aus"] == ["AU02"] and by_code["au_direction_doubtful"]["aus"] == ["AU05"]
    assert by_code["implausible_fields"]["aus"] == ["AU09"]
    assert by_code["fold_spread"]["r2_folds"][2] == -0.19 and "-0.190" in by_code["fold_spread"]["message"]
    assert by_code["pose_filter_dropped"]["fraction"] == 0.4
    for w in warnings:  # every warning says what was found and what not to use the release for
        assert w["message"] and w["do_not"], w
    text = model_card_markdown(card | {"warnings": warnings}, None, [])
    start, training = text.index("## Limits of this release"), text.index("## Training data")
    assert text.index("Linear PLS regression") < start < training  # after the summary, before Training data
    section = text[start:training]
    assert section.count("\n- **") == len(warnings) and section.count("Do not use this release") == len(warnings)
    assert "to drive or interpret AU09, AU43" in section


def test_thresholds_are_edges_not_guesses():
    card = _large_card()
    card["data"] |= {"n_frames": limits.MIN_FRAMES_PER_FEATURE * 83, "n_videos": limits.MIN_VIDEOS}
    card["data"]["people"] = {"identity_labels": limits.MIN_PEOPLE}
    assert limits.release_warnings(card) == []
    card["data"] |= {"n_frames": limits.MIN_FRAMES_PER_FEATURE * 83 - 1, "n_videos": limits.MIN_VIDEOS - 1}
    card["data"]["people"] = {"identity_labels": limits.MIN_PEOPLE - 1}
    assert [w["code"] for w in limits.release_warnings(card)] == ["small_data_frames", "few_videos", "few_people"]
    tight, loose = [0.22, 0.24, 0.26], [0.2, 0.3, 0.4]  # std 6.8 % and 27 % of the mean
    for folds, warned in ((tight, False), (loose, True)):
        spread = _large_card()
        spread["cv"] |= {"r2_folds": folds, "r2_mean": float(np.mean(folds)), "r2_std": float(np.std(folds))}
        assert [w["code"] for w in limits.release_warnings(spread)] == (["fold_spread"] if warned else [])


def test_fields_of_other_parts_absent_give_no_warning_of_their_kind():
    card = _small_card()
    for key in ("people", "unsupported_inputs", "input_ranges", "detector"):
        card["data"].pop(key, None)
    codes = {w["code"] for w in limits.release_warnings(card)}
    assert not codes & {"few_people", "unsupported_inputs", "detector_mixed", "detector_unknown", "implausible_fields"}
    card["data"]["people"] = {"identity_labels": None, "note": "no Identity column"}
    card["data"]["detector"] = {"name": "mixed"}
    codes = {w["code"] for w in limits.release_warnings(card)}
    assert "few_people" not in codes and "detector_mixed" in codes


def test_implausible_fields_compare_with_the_median_of_the_moving_aus():
    sizes = np.full(20, 0.05)
    assert not limits.implausible_fields(sizes).any()
    sizes[6] *= 40
    assert np.flatnonzero(limits.implausible_fields(sizes)).tolist() == [6]
    sizes[:] = 0.0  # constant inputs have no field: the median is over the AUs that move
    sizes[[3, 8, 12]] = [0.05, 0.05, 2.0]
    assert np.flatnonzero(limits.implausible_fields(sizes)).tolist() == [12]
    sizes[3] = 0.0  # two AUs that move: no median to judge by
    assert not limits.implausible_fields(sizes).any()
    disp = np.zeros((2, 478, 3))
    disp[0, 7] = [3.0, 4.0, 0.0]
    assert limits.au_field_sizes(disp).tolist() == [5.0, 0.0]


def test_reliability_section_says_what_reliability_does_not_detect():
    card = copy.deepcopy(_large_card())
    text = model_card_markdown(card, None, [])
    assert "stability across video subsets" in text and "does not detect detector-noise bias" in text


def test_a_constant_input_is_one_warning_not_also_unreliable_and_failing_facs():
    card = _large_card()
    card["data"]["degenerate"] = {"constant_inputs": {"AU07": 0.0}}
    card["cv"]["au_reliability"]["AU07"] = 0.0  # a zero field: cosine 0 between folds
    card["au_directions"]["AU07"] = "fail"  # "no displacement"
    warnings = limits.release_warnings(card)
    assert [(w["code"], w["inputs"]) for w in warnings] == [("constant_inputs", ["AU07"])]
    card["cv"]["au_reliability"]["AU24"] = 0.2  # a real AU is still judged
    assert [w["code"] for w in limits.release_warnings(card)] == ["low_au_reliability", "constant_inputs"]
