"""Direction check of the blendshape and emotion families (issue 46, item 4) against a known ground truth.

The truth is built by another route than the check's expectations: each emotion is its EMFACS prototype's AU
combination (Friesen & Ekman, EMFACS-7) of :mod:`aumesh.synthetic.truth`'s FACS fields, each blendshape the FACS field
of its AU counterpart restricted to its side (or a Gaussian bump of an area where no AU of the 20 matches), on the
canonical template. Pure numpy, fast.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from aumesh.card import family_directions as fd
from aumesh.card.family_expectations import BLENDSHAPE_EXPECTATIONS, EMOTION_PROTOTYPES, blendshape_checks
from aumesh.core.families import BLENDSHAPE_COLUMNS, EMOTION_COLUMNS
from aumesh.core.schema import AU_COLUMNS, flatten_axis_major
from aumesh.geometry import landmarks, measures
from aumesh.geometry.face import canonical_template
from aumesh.synthetic import family_mixing as fm
from aumesh.synthetic.truth import facs_displacement_fields

LABELS = list(EMOTION_COLUMNS)
# EMFACS prototypes (the AUs of each emotion), neutral moves nothing
EMFACS = {
    "anger": ("AU04", "AU05", "AU07", "AU23"),
    "disgust": ("AU09", "AU10", "AU15"),
    "fear": ("AU01", "AU02", "AU04", "AU05", "AU07", "AU20", "AU26"),
    "happiness": ("AU06", "AU12"),
    "sadness": ("AU01", "AU04", "AU15"),
    "surprise": ("AU01", "AU02", "AU05", "AU26"),
    "neutral": (),
}
# blendshape stem -> its FACS counterpart (sided stems take the AU's field on that side only)
SIDED_AU = {
    "browDown": "AU04",
    "browOuterUp": "AU02",
    "cheekSquint": "AU06",
    "eyeBlink": "AU43",
    "eyeSquint": "AU07",
    "eyeWide": "AU05",
    "mouthDimple": "AU14",
    "mouthFrown": "AU15",
    "mouthLowerDown": "AU25",
    "mouthPress": "AU24",
    "mouthSmile": "AU12",
    "mouthStretch": "AU20",
    "mouthUpperUp": "AU10",
    "noseSneer": "AU09",
}
BOTH_AU = {
    "browInnerUp": "AU01",
    "jawOpen": "AU26",
    "mouthShrugLower": "AU17",
    "mouthRollLower": "AU28",
    "mouthRollUpper": "AU28",
}
# the rest: (area, (lateral, up, toward)) bumps, lateral = outward on a sided area, subject's left on a midline one
BUMPS = {
    "cheekPuff": [("cheek", (0.05, 0.0, 0.05))],
    "jawForward": [("jaw", (0.0, 0.0, 0.06))],
    "jawLeft": [("jaw", (0.06, 0.0, 0.0))],
    "jawRight": [("jaw", (-0.06, 0.0, 0.0))],
    "mouthFunnel": [("upper_lip", (0.0, 0.0, 0.04)), ("lower_lip", (0.0, 0.0, 0.04))],
    "mouthLeft": [("upper_lip", (0.05, 0.0, 0.0)), ("lower_lip", (0.05, 0.0, 0.0))],
    "mouthRight": [("upper_lip", (-0.05, 0.0, 0.0)), ("lower_lip", (-0.05, 0.0, 0.0))],
    "mouthPucker": [("lip_corner", (-0.05, 0.0, 0.03))],
    **{
        f"eyeLook{d}{s.capitalize()}": [(f"iris_{s}", v)]
        for s in ("left", "right")
        for d, v in {"Down": (0, -0.03, 0), "Up": (0, 0.03, 0), "In": (-0.03, 0, 0), "Out": (0.03, 0, 0)}.items()
    },
}


@pytest.fixture(scope="module")
def mesh():
    return canonical_template()


@pytest.fixture(scope="module")
def au_fields(mesh):
    return facs_displacement_fields()


def _au(au_fields, name):
    return au_fields[AU_COLUMNS.index(name)]


def _bump(mesh, area, vec, sigma=0.03):
    """The area's vertices moved by ``vec`` (face terms), a Gaussian falloff around them (canonical face frame)."""
    names = [a for a in landmarks.AREA_SEEDS if a == area or landmarks.region_group(a) == area]
    areas = measures.face_areas(mesh)
    out = np.zeros_like(mesh)
    for a in names:
        side = landmarks.region_side(a)
        v = np.array([vec[0] * (side or 1), -vec[1], -vec[2]])  # face frame: x left, y down, z away
        idx = np.flatnonzero(areas == list(landmarks.AREA_SEEDS).index(a))
        d = np.min(np.linalg.norm(mesh[:, None, :2] - mesh[idx][None, :, :2], axis=2), axis=1)
        out += np.exp(-(d**2) / (2 * sigma**2))[:, None] * v
    return out


def _blendshape_fields(mesh, au_fields):
    x = mesh[:, 0] - 0.5 * (mesh[33, 0] + mesh[263, 0])
    on = {"Left": 1 / (1 + np.exp(-x / 0.03)), "Right": 1 / (1 + np.exp(x / 0.03))}
    fields = np.zeros((len(BLENDSHAPE_COLUMNS), *mesh.shape))
    for k, name in enumerate(BLENDSHAPE_COLUMNS):
        stem, side = (
            (name[:-4], "Left")
            if name.endswith("Left")
            else (name[:-5], "Right")
            if name.endswith("Right")
            else (name, "")
        )
        if stem in SIDED_AU:
            fields[k] = _au(au_fields, SIDED_AU[stem]) * on[side][:, None]
        elif name in BOTH_AU:
            fields[k] = _au(au_fields, BOTH_AU[name])
        elif name in BUMPS:
            fields[k] = sum(_bump(mesh, a, v) for a, v in BUMPS[name])
    return fields


@pytest.fixture(scope="module")
def emotion_coef(au_fields, mesh):
    fields = np.stack([sum((_au(au_fields, a) for a in aus), np.zeros_like(mesh)) for aus in EMFACS.values()])
    return flatten_axis_major(fields)


@pytest.fixture(scope="module")
def blendshape_coef(au_fields, mesh):
    return flatten_axis_major(_blendshape_fields(mesh, au_fields))


def test_the_families_names_are_pyfeats_in_order():
    assert list(BLENDSHAPE_EXPECTATIONS) == list(BLENDSHAPE_COLUMNS)
    assert list(EMOTION_PROTOTYPES) == list(EMOTION_COLUMNS)
    assert all(n in BUMPS or n in BOTH_AU or n[:-4] in SIDED_AU or n[:-5] in SIDED_AU for n in blendshape_checks())


def test_emotions_correctly_labelled_pass(emotion_coef, mesh):
    report = fd.emotion_direction_check(emotion_coef, LABELS, mesh)
    assert report["verdict"] == "pass", report["message"]
    assert report["assignment"] == {n: n for n in LABELS} and report["assignment_gain"] == 0
    s = np.array(report["scores"])  # each column's own prototype scores highest in its row
    assert np.array_equal(s.argmax(axis=1), np.arange(7))


def _permuted(perm):
    """feature_columns whose label k names the row of emotion perm[k]: the row labelled LABELS[perm[k]] is k's."""
    labels = [""] * 7
    for k, p in enumerate(perm):
        labels[k] = LABELS[p]
    return labels


@pytest.mark.parametrize("a, b", list(itertools.combinations(range(7), 2)))
def test_every_transposition_fails_naming_it(emotion_coef, mesh, a, b):
    perm = list(range(7))
    perm[a], perm[b] = b, a
    report = fd.emotion_direction_check(emotion_coef, _permuted(perm), mesh, where="emo.npz")
    assert report["verdict"] == "fail" and report["assignment_gain"] > 0
    moved = {n: m for n, m in report["assignment"].items() if n != m}
    assert moved == {LABELS[a]: LABELS[b], LABELS[b]: LABELS[a]}
    msg = report["message"]
    want = f"emo.npz: emotion columns labelled {LABELS[min(a, b)]} and {LABELS[max(a, b)]} look swapped: "
    assert "\n" not in msg and msg.startswith(want), msg
    assert f"'{LABELS[a]}' moves like {LABELS[b]}" in msg and f"'{LABELS[b]}' moves like {LABELS[a]}" in msg
    assert msg.count("moves like") == 2


def test_a_three_cycle_and_detectorv2s_order_under_pyfeat_labels_fail(emotion_coef, mesh):
    # happiness -> surprise -> sadness -> happiness
    h, su, sa = (LABELS.index(n) for n in ("happiness", "surprise", "sadness"))
    perm = list(range(7))
    perm[h], perm[su], perm[sa] = su, sa, h
    report = fd.emotion_direction_check(emotion_coef, _permuted(perm), mesh)
    assert {n: m for n, m in report["assignment"].items() if n != m} == {
        "surprise": "happiness",
        "sadness": "surprise",
        "happiness": "sadness",
    }
    # v5's bug: rows in Detectorv2's order (Neutral, Happy, Sad, Surprise, Fear, Disgust, Anger) labelled anger..neutral
    v2 = ["neutral", "happiness", "sadness", "surprise", "fear", "disgust", "anger"]
    rows = emotion_coef[[LABELS.index(n) for n in v2]]
    report = fd.emotion_direction_check(rows, LABELS, mesh)
    assert report["verdict"] == "fail"
    assert report["assignment"] == dict(zip(LABELS, v2, strict=True))


def test_emotions_pass_with_a_common_row_and_at_snr_1(emotion_coef, mesh):
    # softmax inputs: every row + c predicts the same meshes; PLS's rows carry such a c (neutral = -mean of the rest)
    shifted = emotion_coef - emotion_coef.mean(axis=0)
    assert fd.emotion_direction_check(shifted, LABELS, mesh)["verdict"] == "pass"
    # SNR 1: white noise per row with the norm of the mean emotion field (stated SNR = field norm / noise norm)
    rng = np.random.default_rng(7)
    size = np.linalg.norm(emotion_coef[:6], axis=1).mean()
    for _ in range(5):
        noise = rng.normal(size=emotion_coef.shape)
        noise *= size / np.linalg.norm(noise, axis=1, keepdims=True)
        report = fd.emotion_direction_check(emotion_coef + noise, LABELS, mesh)
        assert report["verdict"] == "pass", report["message"]


def test_rows_are_picked_by_name_and_pose_rows_may_follow(emotion_coef, mesh):
    order = [6, 3, 0, 1, 2, 5, 4]
    coef = np.vstack([emotion_coef[order], np.zeros((3, emotion_coef.shape[1]))])
    assert fd.emotion_direction_check(coef, [LABELS[k] for k in order], mesh)["verdict"] == "pass"
    with pytest.raises(KeyError, match="emo.npz: 'feature_columns' lacks \\['neutral'\\]"):
        fd.emotion_direction_check(emotion_coef[:6], LABELS[:6], mesh, where="emo.npz")


def test_blendshapes_truth_passes_and_unchecked_have_reasons(blendshape_coef, mesh):
    report = fd.blendshape_direction_check(blendshape_coef, BLENDSHAPE_COLUMNS, mesh)
    bad = {n: e["checks"] for n, e in report["blendshapes"].items() if e["verdict"] != "pass"}
    assert not bad, bad
    assert set(report["blendshapes"]) == set(blendshape_checks())
    assert report["verdict"] == "pass", report["message"]
    assert all(e["verdict"] == "pass" for e in report["pairs"].values())
    assert len(report["pairs"]) == 18
    assert set(report["unchecked"]) == {"_neutral", "mouthClose", "mouthShrugUpper"}
    assert all(len(r) > 10 for r in report["unchecked"].values())


def test_blendshape_left_right_swap_fails_naming_the_pair(blendshape_coef, mesh):
    cols = list(BLENDSHAPE_COLUMNS)
    i, j = cols.index("eyeBlinkLeft"), cols.index("eyeBlinkRight")
    cols[i], cols[j] = cols[j], cols[i]
    report = fd.blendshape_direction_check(blendshape_coef, cols, mesh, where="bs.npz")
    assert report["pairs"]["eyeBlinkLeft/Right"]["verdict"] == "fail"
    assert [p for p, e in report["pairs"].items() if e["verdict"] != "pass"] == ["eyeBlinkLeft/Right"]
    assert report["verdict"] == "fail"
    assert report["message"] == "bs.npz: blendshape left/right look swapped: eyeBlinkLeft/Right"


def test_a_blendshape_moving_against_its_meaning_fails(blendshape_coef, mesh):
    coef = blendshape_coef.copy()
    for name in ("jawOpen", "mouthSmileLeft", "browInnerUp"):
        coef[BLENDSHAPE_COLUMNS.index(name)] *= -1
    report = fd.blendshape_direction_check(coef, BLENDSHAPE_COLUMNS, mesh)
    assert [n for n, e in report["blendshapes"].items() if e["verdict"] != "pass"] == [
        "browInnerUp",
        "jawOpen",
        "mouthSmileLeft",
    ]
    assert report["message"].endswith("move against their meaning: browInnerUp, jawOpen, mouthSmileLeft")


def test_blendshapes_pass_at_snr_2(blendshape_coef, mesh):
    # SNR 2: each row's white noise has half its field's norm (the iris bumps move few vertices: small areas)
    rng = np.random.default_rng(3)
    for _ in range(3):
        noise = rng.normal(size=blendshape_coef.shape)
        noise *= (
            np.linalg.norm(blendshape_coef, axis=1, keepdims=True) / 2 / np.linalg.norm(noise, axis=1, keepdims=True)
        )
        report = fd.blendshape_direction_check(blendshape_coef + noise, BLENDSHAPE_COLUMNS, mesh)
        assert report["verdict"] == "pass", report["message"]


# --- calibration (docs/families-directions.md, benchmarks/bench_family_directions.py): the family truth of the
# synthetic tables (aumesh.synthetic.family_mixing), mixed and noised as a fit's rows are


@pytest.fixture(scope="module")
def family_truth():
    return fm.truth_fields()


def test_every_transposition_and_three_cycle_is_named_at_snr_1(family_truth):
    # (a) on the synthetic tables' truth (disgust = AU09 + AU15, not the EMFACS sums above) with white noise at SNR 1
    # (the benchmark: 100 % named; with mixing 0.1 on top 97.6 % of transpositions, 100 % of 3-cycles)
    e, mesh = family_truth["emotions"], family_truth["mesh"]
    rng = np.random.default_rng(11)
    perms = fm.transpositions() + fm.three_cycles()
    assert len(perms) == 21 + 70
    for perm in perms:
        report = fd.emotion_direction_check(fm.relabelled(fm.mixed(e, rng, 0.0, 1.0), perm), LABELS, mesh)
        named = {LABELS[k]: LABELS[p] for k, p in enumerate(perm) if p != k}
        assert report["verdict"] == "fail", (perm, report["message"])
        assert {n: m for n, m in report["assignment"].items() if n != m} == named, report["message"]
        assert report["assignment_gain"] >= fd.PERMUTATION_MARGIN


def test_a_correct_labelling_passes_under_realistic_mixing_and_noise(family_truth):
    # (b) mixing 0.2 and 0.3 with SNR 1 (rows at cosine ~0.85 / ~0.75 to their truth). The benchmark (200 draws):
    # 0 % refused at 0.2, 2.5 % at 0.3; the rule without the margin (any non-identity labelling fails) fails this
    # test (seen: a draw at 0.2 refused), the centred-cosine assignment before it refuses 7 % / 30.5 %
    e, mesh = family_truth["emotions"], family_truth["mesh"]
    rng = np.random.default_rng(5)
    mild = [fd.emotion_direction_check(fm.mixed(e, rng, 0.2, 1.0), LABELS, mesh)["verdict"] for _ in range(30)]
    strong = [fd.emotion_direction_check(fm.mixed(e, rng, 0.3, 1.0), LABELS, mesh)["verdict"] for _ in range(30)]
    assert mild.count("fail") == 0 and mild.count("pass") >= 27  # mostly a clean pass, not a wall of warnings
    assert strong.count("fail") <= 2


def test_pyfeat_v5s_bug_is_caught_under_mixing(family_truth):
    # (c) Detectorv2's rows (Neutral, Happy, Sad, Surprise, Fear, Disgust, Anger) under FEAT_EMOTION_COLUMNS labels
    e, mesh = family_truth["emotions"], family_truth["mesh"]
    assert [LABELS[k] for k in fm.V5_PERMUTATION] == [
        "neutral",
        "happiness",
        "sadness",
        "surprise",
        "fear",
        "disgust",
        "anger",
    ]
    rng = np.random.default_rng(2)
    for alpha in (0.0, 0.2, 0.3):
        report = fd.emotion_direction_check(
            fm.relabelled(fm.mixed(e, rng, alpha, 1.0), fm.V5_PERMUTATION), LABELS, mesh
        )
        assert report["verdict"] == "fail", report["message"]
        # every label moves: the row labelled anger holds neutral's field, disgust happiness's, ... neutral anger's;
        # under mixing the seven-label permutation is refused but may be named only in part (the benchmark: 100 %
        # refused at mixing <= 0.4, named exactly at <= 0.3 in most draws)
        truth = {n: LABELS[k] for n, k in zip(LABELS, fm.V5_PERMUTATION, strict=True)}
        right = sum(report["assignment"][n] == truth[n] for n in LABELS)
        assert right == 7 if alpha == 0.0 else right >= 4, (alpha, report["message"])


def test_within_the_margin_a_suspected_permutation_is_doubtful(family_truth, monkeypatch):
    # a labelling that wins by less than the margin is reported (doubtful: a card warning), not refused
    e, mesh = family_truth["emotions"], family_truth["mesh"]
    perm = fm.transpositions()[0]
    report = fd.emotion_direction_check(fm.relabelled(e, perm), LABELS, mesh)
    monkeypatch.setattr(fd, "PERMUTATION_MARGIN", report["assignment_gain"] + 0.01)
    doubtful = fd.emotion_direction_check(fm.relabelled(e, perm), LABELS, mesh, where="emo.npz")
    assert doubtful["verdict"] == "doubtful" and doubtful["inputs"]["anger"] == "doubtful"
    assert doubtful["message"].startswith("emo.npz: emotion columns labelled anger and disgust may be permuted")
