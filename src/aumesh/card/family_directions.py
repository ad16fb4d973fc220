"""Direction check of the blendshape and emotion families (issue 46, item 4): does each input move the face the way
its name says? The check that would have caught ``emotion_to_mesh_pls_v5``'s permuted emotion labels.

Pure functions on arrays: ``coef`` (n_inputs, 1434) in the card's axis-major layout ``[x_0..x_477 | y_0..y_477 |
z_0..z_477]`` (docs/conventions.md, "Output layout"), rows named by ``feature_columns`` (py-feat's key), and the
release's ``mean_aligned_mesh`` (478, 3). Each input's row is its displacement at value 1; it is put in the face
frame of the mean mesh in inter-ocular units exactly as the AU check does (:mod:`aumesh.card.directions`:
:func:`aumesh.geometry.face.face_frame`, so y-up, pixel or rotated releases give the same answer), on the same
facial areas (:data:`aumesh.geometry.landmarks.AREA_SEEDS`, :func:`aumesh.geometry.measures.face_areas`).

Emotions (:func:`emotion_direction_check`)
------------------------------------------
Each emotion row and each prototype of :data:`aumesh.card.family_expectations.EMOTION_PROTOTYPES` becomes an *area
descriptor*: per area (27, sides apart) the mean displacement of its vertices in face terms (outward / up / toward;
subject's left for midline areas). A prototype's descriptor holds its unit direction in each area it names.
Emotion probabilities sum to 1 (both detectors write a softmax), so a fit's rows are only defined up to a common
vector (adding ``c`` to every row leaves every prediction unchanged); descriptors of the rows, and of the prototypes,
are therefore centred across the seven before the cosine. The score matrix S (features x prototypes) holds these
cosines; the labelling passes when the assignment that maximises the summed score
(:func:`scipy.optimize.linear_sum_assignment`) is the identity and every own score is positive. Otherwise the
one-line message names the permutation: "columns look permuted: 'happiness' moves like surprise, ...".

Blendshapes (:func:`blendshape_direction_check`)
------------------------------------------------
Each checked blendshape (:data:`aumesh.card.family_expectations.BLENDSHAPE_EXPECTATIONS`) is judged per check as the
AU check judges a FACS region: cosine of the area's displacement-weighted mean direction to the expected one, pass
at >= ``PASS_COSINE``, fail at <= ``FAIL_COSINE`` (:mod:`aumesh.card.directions`' thresholds). A Left/Right pair is
also judged side by side: the motion of each in the pair's first area group (both sides) has a lateral centroid
(energy-weighted x of the vertices, subject's left positive, inter-ocular units); the Left one must lie left of the
Right one. A pair whose Left lies right of its Right by more than ``SIDE_MARGIN`` fails ("looks swapped"), within
the margin it is doubtful (the two move alike: the sides cannot be told apart).
"""

from __future__ import annotations

import functools
import itertools
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.card import directions
from aumesh.card.directions import (
    AREA_NAMES,
    FAIL_COSINE,
    MIN_MAGNITUDE,
    PASS_COSINE,
    Areas,
    load_arrays,
    local_terms,
    weighted_direction,
)
from aumesh.card.facs_regions import FACE_TERMS
from aumesh.card.family_expectations import EMOTION_PROTOTYPES, Checks, blendshape_checks, unchecked_blendshapes
from aumesh.core import schema
from aumesh.core.errors import DirectionCheckError
from aumesh.core.families import FAMILIES, PYFEAT_FEATURE
from aumesh.core.schema import N_TARGETS
from aumesh.geometry import face, landmarks, measures

#: inter-ocular units: a Left/Right pair whose motions' lateral centroids differ by less cannot be told apart
SIDE_MARGIN = 0.05
#: summed pair cosines (of 21): how much the best labelling must beat the written one to fail the check
#: (calibrated in docs/families-directions.md and benchmarks/bench_family_directions.py)
PERMUTATION_MARGIN = 1.0
#: inter-ocular units: a pair fails as swapped only when its Left lies right of its Right by more (the truth's pairs
#: differ by 0.14-1.0, a weak fit's leaked fields of an unexpressed pair by 0.07: docs/families-directions.md)
SIDE_FAIL = 0.1
#: a blendshape moving against its meaning fails only with this focus (its area's share of the motion over the area's
#: share of the vertices) or more: a fitted field of a shape the data does not express (leakage, noise) is diffuse
FAIL_FOCUS = 2.0
#: a blendshape field under this fraction of the median checked field (rms) barely moves: doubtful, never failed
STILL_FIELD = 0.1


def family_displacements(
    coef: np.ndarray, feature_columns: Sequence[str], mean_mesh: np.ndarray, names: Sequence[str], where: str
) -> tuple[np.ndarray, np.ndarray]:
    """The displacement fields of the named inputs, in the face frame of the mean mesh.

    Parameters
    ----------
    coef : np.ndarray, shape (n_rows, 1434)
        Axis-major coefficients; its first ``len(feature_columns)`` rows are named by ``feature_columns`` (pose rows
        may follow, as in py-feat's NPZ).
    feature_columns : sequence of str
        The names of ``coef``'s leading rows.
    mean_mesh : np.ndarray, shape (478, 3)
        The release's ``mean_aligned_mesh``.
    names : sequence of str
        The inputs to return, in this order (rows are picked by name, never by position).
    where : str
        The file (or ``"<arrays>"``) named in errors.

    Returns
    -------
    disp : np.ndarray, shape (len(names), 478, 3)
        Face frame (x subject's left, y down, z away), inter-ocular units.
    mesh : np.ndarray, shape (478, 3)
        ``mean_mesh`` in the same frame.
    """
    c = np.asarray(coef, dtype=np.float64)
    cols = [str(s) for s in feature_columns]
    if c.ndim != 2 or c.shape[1] != N_TARGETS or c.shape[0] < len(cols):
        raise ValueError(
            f"{where}: 'coef' must be (n_inputs, {N_TARGETS}) axis-major with a row per feature_columns name "
            f"({len(cols)}), got {c.shape}"
        )
    missing = [n for n in names if n not in cols]
    if missing:
        raise KeyError(f"{where}: 'feature_columns' lacks {missing}; the family's inputs are named, not positional")
    rows = c[[cols.index(n) for n in names]]
    mean = np.asarray(mean_mesh, dtype=np.float64)
    if not (np.all(np.isfinite(rows)) and np.all(np.isfinite(mean))):
        raise ValueError(f"{where}: 'coef' or 'mean_aligned_mesh' hold NaN or inf; fit the release again")
    origin, axes, scale = face.face_frame(mean)
    return schema.unflatten_axis_major(rows) @ axes.T / scale, (mean - origin) @ axes.T / scale


def _areas_of(area: str) -> list[int]:
    """AREA_NAMES indices an expectation's area stands for: itself (sided), or every side of a group."""
    if area in AREA_NAMES:
        return [AREA_NAMES.index(area)]
    hits = [k for k, a in enumerate(AREA_NAMES) if landmarks.region_group(a) == area]
    if not hits:
        raise KeyError(f"unknown area {area!r}; known: {list(AREA_NAMES)} or their groups")
    return hits


def _unit(terms: dict[str, float]) -> np.ndarray:
    v = sum(w * np.asarray(FACE_TERMS[t], dtype=np.float64) for t, w in terms.items())
    return np.asarray(v) / np.linalg.norm(v)


def area_descriptors(disp: np.ndarray, mesh: np.ndarray) -> np.ndarray:
    """Per area, the mean displacement of its vertices in face terms.

    Parameters
    ----------
    disp : np.ndarray, shape (n, 478, 3)
        Face-frame fields (x subject's left, y down, z away).
    mesh : np.ndarray, shape (478, 3)
        The face-frame mesh the areas are found on.

    Returns
    -------
    np.ndarray, shape (n, 27, 3)
        ``AREA_SEEDS`` order; (lateral, up, toward), lateral = outward on a sided area, subject's left on a midline one.
    """
    area = measures.face_areas(mesh)
    side = np.array([landmarks.region_side(a) for a in AREA_NAMES])[area]
    local = local_terms(np.asarray(disp, dtype=np.float64), side)
    counts = np.bincount(area, minlength=len(AREA_NAMES)).astype(np.float64)
    out = np.stack(
        [np.stack([np.bincount(area, weights=f[:, j], minlength=len(AREA_NAMES)) for j in range(3)], 1) for f in local]
    )
    return out / np.maximum(counts, 1.0)[None, :, None]


def prototype_descriptors(prototypes: Sequence[Checks]) -> np.ndarray:
    """Descriptors (n, 27, 3) of expected motions: each check's unit direction in each area it names."""
    out = np.zeros((len(prototypes), len(AREA_NAMES), 3))
    for k, checks in enumerate(prototypes):
        for area, terms in checks:
            out[k, _areas_of(area)] += _unit(terms)
    return out


def _cosines(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a2, b2 = a.reshape(len(a), -1), b.reshape(len(b), -1)
    na, nb = np.linalg.norm(a2, axis=1), np.linalg.norm(b2, axis=1)
    return (a2 @ b2.T) / np.maximum(np.outer(na, nb), 1e-300)


def emotion_score_matrix(disp: np.ndarray, mesh: np.ndarray) -> np.ndarray:
    """Cosines (7, 7) of each emotion field (rows, ``EMOTION_PROTOTYPES`` order) to each prototype (columns).

    Descriptors are centred across the seven on both sides (the rows of a softmax family are defined up to a common
    vector; see the module docstring). Descriptive (the report's ``scores``); the decision is
    :func:`emotion_permutation_scores`'.
    """
    d = area_descriptors(disp, mesh)
    p = prototype_descriptors(list(EMOTION_PROTOTYPES.values()))
    return _cosines(d - d.mean(axis=0), p - p.mean(axis=0))


_PAIRS = np.array([(i, j) for i in range(7) for j in range(i + 1, 7)])  # the 21 unordered pairs of the seven


@functools.cache
def _permutations(n: int) -> np.ndarray:
    """All n! permutations of range(n), (n!, n), the identity first (5040 for the seven emotions)."""
    return np.array(list(itertools.permutations(range(n))), dtype=np.intp)


def emotion_permutation_scores(disp: np.ndarray, mesh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pairwise score of every labelling of the seven emotion fields.

    For a labelling pi (field k is emotion ``pi[k]``) the score is the sum over the 21 pairs (i, j) of the cosine
    between the descriptor of ``field_i - field_j`` and that of ``prototype_pi[i] - prototype_pi[j]``. Differences
    are what a softmax family defines (a common vector added to every row cancels), so no centring is needed, and
    each pair is judged on its own difference: a weak field (disgust's is the smallest) is not swamped by the strong
    ones, as it is in a centred cosine assignment (:func:`emotion_score_matrix`; measured in
    docs/families-directions.md: 31 % against 18 % non-identity assignments at mixing 0.3).

    Parameters
    ----------
    disp : np.ndarray, shape (7, 478, 3)
        The fields as labelled, ``EMOTION_PROTOTYPES`` order, face frame (:func:`family_displacements`).
    mesh : np.ndarray, shape (478, 3)
        The face-frame mean mesh.

    Returns
    -------
    scores : np.ndarray, shape (5040,)
        The score of each permutation of ``perms``; at most 21.
    perms : np.ndarray, shape (5040, 7)
        The permutations, the identity (the labelling as written) first.
    """
    d = area_descriptors(disp, mesh).reshape(7, -1)
    p = prototype_descriptors(list(EMOTION_PROTOTYPES.values())).reshape(7, -1)
    i, j = _PAIRS[:, 0], _PAIRS[:, 1]
    fd = d[i] - d[j]
    pd = p[:, None, :] - p[None, :, :]  # (7, 7, D): prototype a minus prototype b
    fd = fd / np.maximum(np.linalg.norm(fd, axis=1, keepdims=True), 1e-300)
    pd = pd / np.maximum(np.linalg.norm(pd, axis=2, keepdims=True), 1e-300)
    cos = np.einsum("kd,abd->kab", fd, pd)  # (21, 7, 7): pair k's field difference against a - b
    perms = _permutations(7)
    scores = cos[np.arange(len(_PAIRS))[None, :], perms[:, i], perms[:, j]].sum(axis=1)
    return scores, perms


def _names(labels: Sequence[str]) -> str:
    return " and ".join(labels) if len(labels) == 2 else ", ".join(labels[:-1]) + " and " + labels[-1]


def emotion_direction_check(
    coef: np.ndarray, feature_columns: Sequence[str], mean_mesh: np.ndarray, where: str = "<arrays>"
) -> dict[str, Any]:
    """Check that each emotion column moves the face like its prototype; name the permutation when not.

    The labelling with the highest pairwise score (:func:`emotion_permutation_scores`, all 5040 labellings) is the
    suspected one. It **fails** the check when it is not the labelling as written and beats it by at least
    ``PERMUTATION_MARGIN``; below the margin it is **doubtful** (fields mixed with each other, as a real fit's are,
    can make a close labelling win by a little: docs/families-directions.md, "Calibration"). A label whose own
    pairwise score is <= 0 (it moves against its prototype relative to the others) is doubtful too.

    Parameters
    ----------
    coef, feature_columns, mean_mesh, where
        As in :func:`family_displacements`; ``feature_columns`` must hold the 7 ``FEAT_EMOTION_COLUMNS`` names.

    Returns
    -------
    dict
        ``verdict`` ("pass" / "doubtful" / "fail"), ``message`` (one line), ``labels`` (the 7 names), ``inputs``
        (label -> verdict), ``scores`` (7 x 7 centred cosines, rows = columns as labelled, columns = prototypes;
        descriptive), ``assignment`` (label -> the prototype it moves like under the best labelling), ``moved``
        (the labels it moves), ``own_score`` (label -> mean pair cosine with its own prototype), ``labelled_score``
        and ``best_score`` (pairwise scores, of 21), ``assignment_gain`` (their difference), ``margin``.
    """
    labels = list(EMOTION_PROTOTYPES)
    disp, mesh = family_displacements(coef, feature_columns, mean_mesh, labels, where)
    scores, perms = emotion_permutation_scores(disp, mesh)
    best = int(np.argmax(scores))
    gain = float(scores[best] - scores[0])
    like = {labels[k]: labels[int(c)] for k, c in enumerate(perms[best])}
    moved = [n for n in labels if like[n] != n]
    own = _own_scores(disp, mesh)
    weak = [n for n in labels if own[n] <= FAIL_COSINE]
    named = ", ".join(f"'{n}' moves like {like[n]}" for n in moved)
    scored = f"pairwise score {scores[best]:.2f} against {scores[0]:.2f} as labelled, margin {PERMUTATION_MARGIN}"
    if moved and gain >= PERMUTATION_MARGIN:
        verdict = "fail"
        what = "look swapped" if len(moved) == 2 else "look permuted"
        message = f"{where}: emotion columns labelled {_names(moved)} {what}: {named} ({scored})"
    elif moved:
        verdict = "doubtful"
        message = (
            f"{where}: emotion columns labelled {_names(moved)} may be permuted: {named} ({scored}: within the "
            f"margin, fields this mixed cannot be told apart)"
        )
    elif weak:
        verdict = "doubtful"
        message = f"{where}: emotion columns {weak} do not move like their prototypes (own score <= {FAIL_COSINE})"
    else:
        verdict = "pass"
        message = f"{where}: emotion columns move like their prototypes (lowest own score {min(own.values()):.2f})"
    inputs = {n: verdict if n in moved else "doubtful" if n in weak else "pass" for n in labels}
    return {
        "verdict": verdict,
        "message": message,
        "labels": labels,
        "inputs": inputs,
        "scores": np.round(emotion_score_matrix(disp, mesh), 4).tolist(),
        "assignment": like,
        "moved": moved,
        "own_score": {n: round(v, 4) for n, v in own.items()},
        "labelled_score": round(float(scores[0]), 4),
        "best_score": round(float(scores[best]), 4),
        "assignment_gain": round(gain, 4),
        "margin": PERMUTATION_MARGIN,
    }


def _own_scores(disp: np.ndarray, mesh: np.ndarray) -> dict[str, float]:
    """Per label, the mean over the six others of cos(field_i - field_j, prototype_i - prototype_j)."""
    labels = list(EMOTION_PROTOTYPES)
    d = area_descriptors(disp, mesh).reshape(7, -1)
    p = prototype_descriptors(list(EMOTION_PROTOTYPES.values())).reshape(7, -1)
    pair = np.array([[_cosines((d[i] - d[j])[None], (p[i] - p[j])[None])[0, 0] for j in range(7)] for i in range(7)])
    return {n: float((pair[i].sum() - pair[i, i]) / 6) for i, n in enumerate(labels)}


def _lateral_centroid(field: np.ndarray, mesh: np.ndarray, group_mask: np.ndarray) -> float:
    """Energy-weighted x (subject's left positive, from the midline of the eye corners 33/263) of a field's motion."""
    e = (field[group_mask] ** 2).sum(axis=1)
    if e.sum() <= MIN_MAGNITUDE**2:
        return 0.0
    x = mesh[group_mask, 0] - 0.5 * (mesh[33, 0] + mesh[263, 0])
    return float((e * x).sum() / e.sum())


def _focus(field: np.ndarray, areas: Areas, group: str, side: int = 0) -> float:
    """Share of the field's displacement energy in the area (group, side) over the area's share of the vertices:
    > 1 when the field moves there more than on average over the face, ~0 when its motion is elsewhere."""
    energy = (field**2).sum(axis=1)
    mask = areas.mask(group) & ((areas.side == side) if side else True)
    if energy.sum() <= MIN_MAGNITUDE**2 or not mask.any():
        return 0.0
    return float(energy[mask].sum() / energy.sum() / mask.mean())


def _judge_checks(field: np.ndarray, checks: Checks, areas: Areas, strong: bool) -> list[dict[str, Any]]:
    """Each (area, expected) check of one blendshape: cosine, focus, verdict.

    "fail" needs evidence, not noise: the motion clearly opposite (cos <= ``-PASS_COSINE``), concentrated in the
    area (focus >= ``FAIL_FOCUS``) and the field no smaller than the family's median (``strong``); a cosine <=
    ``FAIL_COSINE`` without that is doubtful. A field whose motion is not in its area (focus < 1) is doubtful.
    """
    out = []
    for area, terms in checks:
        group, side = landmarks.region_group(area), landmarks.region_side(area)
        local, mag = weighted_direction(field, areas, group, side)
        norm = float(np.linalg.norm(local))
        cos = float(local @ _unit(terms) / norm) if norm > MIN_MAGNITUDE else 0.0
        focus = _focus(field, areas, group, side)
        verdict = "fail" if cos <= FAIL_COSINE else "doubtful" if cos < PASS_COSINE else "pass"
        if verdict == "fail" and not (cos <= -PASS_COSINE and focus >= FAIL_FOCUS and strong):
            verdict = "doubtful"
        if focus < 1.0 and verdict == "pass":
            verdict = "doubtful"
        out.append(
            {
                "area": area,
                "expected": terms,
                "cosine": round(cos, 4),
                "focus": round(focus, 3),
                "magnitude": round(mag, 6),
                "verdict": verdict,
            }
        )
    return out


def blendshape_direction_check(
    coef: np.ndarray,
    feature_columns: Sequence[str],
    mean_mesh: np.ndarray,
    where: str = "<arrays>",
    unsupported: Sequence[str] = (),
    together: Sequence[str] = (),
) -> dict[str, Any]:
    """Check each blendshape with an expected motion, and each Left/Right pair's sides.

    A blendshape whose field is under ``STILL_FIELD`` of the median checked field (root mean square over the mesh)
    barely moves: its direction is noise, so it is doubtful ("barely moves"), never failed, and its pair is not
    judged by side (the data rarely expressed it; py-feat's v6 blendshape model lists such shapes as
    ``unsupported_features``). The ``unsupported`` ones (the release's ``unsupported_features``) are left unchecked.

    Parameters
    ----------
    coef, feature_columns, mean_mesh, where
        As in :func:`family_displacements`; the checked names present in ``feature_columns`` are judged.
    unsupported : sequence of str
        Inputs the data never expressed (the release's ``unsupported_features``): unchecked.
    together : sequence of str
        Left/Right pairs (``"<stem>Left/Right"``) whose two inputs moved together in the training data
        (:func:`aumesh.pipeline.release_family.sides_together`): their sides are unidentified, so doubtful, never failed.

    Returns
    -------
    dict
        ``verdict`` (worst of the entries), ``message`` (one line), ``inputs`` (name -> verdict, "unchecked" for
        the unchecked), ``blendshapes`` (name -> ``verdict``, ``rms`` (IOD) and ``checks``: area, expected, cosine,
        magnitude, verdict), ``pairs`` ("<stem>Left/Right" -> the two lateral centroids (IOD), verdict),
        ``unchecked`` (name -> reason).
    """
    skip = {str(n) for n in unsupported}
    expected = {n: c for n, c in blendshape_checks().items() if n in list(feature_columns) and n not in skip}
    names = list(expected)
    disp, mesh = family_displacements(coef, feature_columns, mean_mesh, names, where)
    areas = Areas(mesh)
    rms = np.sqrt((disp**2).sum(axis=2).mean(axis=1)) if names else np.zeros(0)
    still = {n for n, r in zip(names, rms, strict=True) if r < STILL_FIELD * float(np.median(rms))}
    rank = {"pass": 0, "doubtful": 1, "fail": 2}
    entries: dict[str, dict[str, Any]] = {}
    for n, field, r in zip(names, disp, rms, strict=True):
        checks = _judge_checks(field, expected[n], areas, bool(r >= np.median(rms)))
        verdict = "doubtful" if n in still else max((c["verdict"] for c in checks), key=rank.__getitem__)
        entries[n] = {"verdict": verdict, "rms": round(float(r), 6), "checks": checks}
        if n in still:
            entries[n]["reason"] = f"barely moves (rms {r:.2g} IOD, under {STILL_FIELD} of the median checked field)"
    pairs: dict[str, dict[str, Any]] = {}
    for n in names:
        partner = n[: -len("Left")] + "Right"
        if not n.endswith("Left") or partner not in expected or {"left", "right"} & set(expected[n][0][1]):
            continue  # jawLeft/Right, mouthLeft/Right: a direction, judged by their checks, not a side
        mask = areas.mask(landmarks.region_group(expected[n][0][0]))
        left = _lateral_centroid(disp[names.index(n)], mesh, mask)
        right = _lateral_centroid(disp[names.index(partner)], mesh, mask)
        verdict = "fail" if left - right < -SIDE_FAIL else "doubtful" if left - right < SIDE_MARGIN else "pass"
        group = landmarks.region_group(expected[n][0][0])
        focused = min(_focus(disp[names.index(m)], areas, group) for m in (n, partner)) >= 1.0
        pair = f"{n[: -len('Left')]}Left/Right"
        if verdict == "fail" and ({n, partner} & still or not focused or pair in together):
            verdict = "doubtful"  # noise, motion elsewhere, or sides the data never told apart: its centroid is no side
        pairs[pair] = {"left_x": round(left, 4), "right_x": round(right, 4), "verdict": verdict}
        if pair in together:
            pairs[pair]["reason"] = "the two inputs moved together in the training data: their sides are unidentified"
    swapped = [p for p, e in pairs.items() if e["verdict"] == "fail"]
    failed = [n for n, e in entries.items() if e["verdict"] == "fail"]
    worst = max(
        [e["verdict"] for e in entries.values()] + [e["verdict"] for e in pairs.values()] + ["pass"],
        key=rank.__getitem__,
    )
    parts = []
    if swapped:
        parts.append("left/right look swapped: " + ", ".join(swapped))
    if failed:
        parts.append("move against their meaning: " + ", ".join(failed))
    if not parts and worst == "doubtful":
        loose = [n for n, e in entries.items() if e["verdict"] == "doubtful"]
        alike = [p for p, e in pairs.items() if e["verdict"] == "doubtful"]
        parts.append("doubtful: " + ", ".join(loose + [f"{p} (sides alike)" for p in alike]))
    message = f"{where}: blendshape " + ("; ".join(parts) if parts else f"directions {worst} ({len(names)} checked)")
    unchecked = unchecked_blendshapes()
    unchecked.update({n: "never expressed in the training data (unsupported_features)" for n in sorted(skip)})
    inputs = {
        n: entries[n]["verdict"] if n in entries else "unchecked"
        for n in feature_columns
        if n in expected or n in unchecked
    }
    for p, e in pairs.items():  # a swapped pair fails both of its shapes
        stem = p[: -len("Left/Right")]
        for side in ("Left", "Right"):
            if rank[e["verdict"]] > rank[inputs[stem + side]]:
                inputs[stem + side] = e["verdict"]
    return {
        "verdict": worst,
        "message": message,
        "inputs": inputs,
        "blendshapes": entries,
        "pairs": pairs,
        "unchecked": unchecked,
    }


# ----------------------------------------------------------------------------------------------------------------
# The release's check: a family release NPZ -> report, JSON, refusal (stages/release_family.py calls these)
# ----------------------------------------------------------------------------------------------------------------

#: the fix every refusal ends with
DIRECTION_FIX = (
    "Fix: check the detector's column names and order in the source tables (aumesh matches the family's columns by "
    "name: aumesh.core.families.family_columns), correct them and run `dvc repro` again"
)


def family_of(arrays: Mapping[str, Any], where: str = "<arrays>") -> str:
    """The family of a release's arrays: its ``family`` key, else the family whose inputs ``feature_columns`` are."""
    if "family" in arrays:
        family = str(np.asarray(arrays["family"]).item())
        if family in PYFEAT_FEATURE:
            return family
    cols = [str(s) for s in np.asarray(arrays.get("feature_columns", [])).tolist()]
    for family in PYFEAT_FEATURE:
        if set(FAMILIES[family]) <= set(cols):
            return family
    raise KeyError(
        f"{where}: not a blendshape or emotion release: 'feature_columns' holds neither family's names "
        f"({', '.join(PYFEAT_FEATURE)}; aumesh.core.families.FAMILIES)"
    )


def family_direction_report(
    npz_path_or_arrays: str | os.PathLike | Mapping[str, Any], where: str | None = None, together: Sequence[str] = ()
) -> dict[str, Any]:
    """Direction report of a blendshape or emotion release (the family's ``<family>_directions.json``).

    Parameters
    ----------
    npz_path_or_arrays : path or mapping
        A family release NPZ (issue 46's contract: ``coef`` (p, 1434) axis-major with the family's k inputs first,
        ``feature_columns`` (k,), ``mean_aligned_mesh`` (478, 3), optional ``unsupported_features`` and ``family``),
        or a mapping with those keys.
    where : str, optional
        The name messages use (default: the path, or ``"<arrays>"`` for a mapping).
    together : sequence of str
        Blendshape Left/Right pairs the training data never told apart (:func:`blendshape_direction_check`).

    Returns
    -------
    dict
        JSON-serialisable: ``source``, ``family``, ``units``, ``thresholds``, ``verdict`` (pass / doubtful / fail),
        ``message`` (one line), ``summary`` (input -> verdict, the card's table), ``counts`` (per verdict) and the
        family's check (:func:`emotion_direction_check` or :func:`blendshape_direction_check`) under ``check``.
    """
    arrays, loaded_from = load_arrays(npz_path_or_arrays)
    where = loaded_from if where is None else str(where)
    family = family_of(arrays, where)
    for key in ("coef", "feature_columns", "mean_aligned_mesh"):
        if key not in arrays:
            raise KeyError(
                f"{where}: missing key {key!r}; a {family} release NPZ needs coef, feature_columns, "
                "mean_aligned_mesh (issue 46's contract)"
            )
    coef = np.asarray(arrays["coef"])
    cols = [str(s) for s in np.asarray(arrays["feature_columns"]).tolist()]
    mean = np.asarray(arrays["mean_aligned_mesh"])
    unsupported = [str(s) for s in np.asarray(arrays.get("unsupported_features", [])).tolist()]
    if family == "emotions":
        check = emotion_direction_check(coef, cols, mean, where)
        thresholds = {"permutation_margin": PERMUTATION_MARGIN, "fail_cosine": FAIL_COSINE}
    else:
        check = blendshape_direction_check(coef, cols, mean, where, unsupported, together)
        thresholds = {
            "pass_cosine": PASS_COSINE,
            "fail_cosine": FAIL_COSINE,
            "side_margin": SIDE_MARGIN,
            "side_fail": SIDE_FAIL,
            "fail_focus": FAIL_FOCUS,
            "still_field": STILL_FIELD,
        }
    summary = dict(check["inputs"])
    return {
        "source": where,
        "family": family,
        "units": "face frame of mean_aligned_mesh, inter-ocular distance (33-263); directions in the subject's terms",
        "thresholds": thresholds,
        "verdict": check["verdict"],
        "message": check["message"],
        "summary": summary,
        "counts": {v: sum(1 for x in summary.values() if x == v) for v in ("pass", "doubtful", "fail", "unchecked")},
        "check": check,
    }


def report_filename(family: str) -> str:
    """``<family>_directions.json``, the report's name in ``releases/<family>/``."""
    return f"{family}_directions.json"


def write_report(report: Mapping[str, Any], path: str | os.PathLike) -> Path:
    """Write a family report as JSON atomically (:func:`aumesh.card.directions.write_report`); ``path`` a folder
    writes ``<folder>/<family>_directions.json``."""
    target = Path(path)
    if target.is_dir():
        target = target / report_filename(str(report["family"]))
    return directions.write_report(report, target)


def check_family_directions(report: Mapping[str, Any], source: str | os.PathLike | None = None) -> None:
    """Refuse a release whose report fails: a one-line :class:`aumesh.core.errors.DirectionCheckError`.

    Parameters
    ----------
    report : mapping
        :func:`family_direction_report`'s output.
    source : path or str, optional
        The file named in the message (default: the report's ``source``).

    Raises
    ------
    DirectionCheckError
        When ``report["verdict"] == "fail"``: the suspected permutation ("emotion columns labelled happiness and
        surprise look swapped: ...") or the blendshapes moving the wrong way / side, then :data:`DIRECTION_FIX`.
        A doubtful report passes (its message goes to the card's warnings).
    """
    if report.get("verdict") != "fail":
        return
    where = str(report.get("source", "<arrays>"))
    message = str(report["message"])
    if source is not None and message.startswith(where + ": "):
        message = f"{source}: {message[len(where) + 2 :]}"
    raise DirectionCheckError(f"{message}. {DIRECTION_FIX}".replace("\n", " "))
