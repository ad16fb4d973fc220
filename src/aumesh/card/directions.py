"""AU-direction check of a released AU(+pose) -> mesh model against FACS: where each AU moves the face, and which way.

For each AU the model's displacement at intensity 1 (pose 0) is the AU's ``coef``
row, reshaped from the axis-major layout to (478, 3). It is expressed in the
face frame of the release's ``mean_aligned_mesh`` (see :func:`aumesh.geometry.face.face_frame`:
orientation recovered from the mesh itself, so pixel / y-down, y-up, rotated or
scaled releases all give the same answer) in inter-ocular units (IOD), then judged twice.

Where the motion is
-------------------
The face is cut into areas (:data:`aumesh.geometry.landmarks.AREA_SEEDS`, :func:`aumesh.geometry.measures.face_areas`:
every vertex belongs to the area of its nearest seed landmark on the release's own mean mesh; 17 groups once
left and right are joined: forehead, temple, glabella, brow_inner, brow_outer, upper_eyelid, lower_eyelid, iris,
nose, nasolabial, cheek, face_side, lip_corner, upper_lip, lower_lip, chin, jaw). The field's **share of motion** in
an area is its displacement energy there, ``sum |d_v|^2`` over the area's vertices, over the whole face's. Each
AU has FACS region(s) (``FACS_EXPECTATIONS[au]["regions"]``, by default the groups of its direction checks) and
nearby areas where FACS also describes appearance changes (``"nearby"``). ``top_region`` is the area group with
the largest share. Shares count vertices, so they follow MediaPipe's vertex density (dense at the eyes and lips).

Which way
---------
For each (region, expected direction) of the AU's ``"checks"``: the displacement-weighted mean of the region's
vertices' displacements (weights ``|d_v|``: the vertices that move most decide, still vertices do not dilute it),
and its cosine to the expected direction in face terms (below). A bilateral region is also judged **side by side**
(the subject's left and right halves alone, outward taken on each side): a half moving against FACS fails the AU even
when the two halves' mean looks plausible (one half reversed, e.g. a mirrored or mis-signed half), and a half with
under ``UNILATERAL_SHARE`` (20 %) of the region's motion is left out, since FACS codes unilateral actions (R12, L12).

Verdicts (the AU's verdict is the worse of "where" and its worst direction check)
-------------------------------------------------------------------------------
where:  ``pass`` when the top region is a FACS region, or the FACS region(s) hold >= ``PASS_SHARE`` (50 %) of
        the motion, or the top region is a nearby area and the FACS region(s) hold >= ``NEARBY_SHARE`` (40 %);
        ``fail`` when the AU does not move, or the top region is elsewhere and the FACS region(s) hold <
        ``FAIL_SHARE`` (10 %, "barely moves"); ``doubtful`` otherwise.
which way:  ``fail`` at cosine <= ``FAIL_COSINE`` (0: against FACS), on the region or on one of its moving sides,
        or when the region has no net motion;
        ``doubtful`` at cosine < ``PASS_COSINE`` (0.7, about 45 degrees), or when the region holds <
        ``FAIL_SHARE`` of the motion; ``pass`` otherwise.

Calibration (measured on the synthetic truth, :mod:`aumesh.synthetic.truth`; ``tests/test_directions.py`` checks
the same properties on fewer seeds). The truth's own 20 fields pass in every tested frame (rotated, scaled,
translated, y-up, mirrored, pixel units, anchors held rigid as ``aumesh.synthetic.tables.true_coefficients`` does, on a
mean mesh shifted by mean AU activity, on the fallback template); their FACS-region shares are 0.45-0.99
(lowest: AU12's lip corners). Fields perturbed to cosine 0.9 with the truth (smooth random
perturbations: global quadratic fields, 1-3 local Gaussian bumps, leakage of other AUs' fields; 100 seeds each per
AU) pass 99.6 % (worst AU12 and AU15 97 %, none fails); at cosine 0.8, 97 % (worst AU12 83 %). A negated field
fails (20/20); another AU's field in the slot of an AU with no FACS region in common fails 319 / 332 times and is
doubtful otherwise, never passes; AU02's slot holding AU12's field plus alpha x AU02's fails up to alpha 0.8 and is
doubtful at 1-1.5 (the lip corners still move most), passing from alpha 2 (the brows move most). On 10 releases
fitted to synthetic tables (absolute and within targets, with and without AR(1) AU noise correlated across AUs,
co-activated AUs, identity-AU coupling), the 180 fields with cosine >= 0.5 to the truth pass; of the 20 with
cosine < 0.5 (identity leaking into the fields), 8 fail, 7 are doubtful. Thresholds: the fields at cosine 0.9 have a
FACS-region cosine >= 0.78 (1 % quantile 0.90) and keep >= 24 % of their motion in the FACS region (1 % quantile
36 %), so PASS_COSINE 0.7 and FAIL_SHARE 0.1 leave them room; PASS_COSINE 0.7 rather than 0.6 because AU20's field
(corners straight outward) in AU12's slot scores 0.62; NEARBY_SHARE 0.4 rather than 1/3 because AU11's field in
AU09's slot (35 % in the nose) and AU14's in AU28's (39 % in the lips) would pass. The thresholds and this rule are
the project's reading of FACS, not a FACS-certified coding.

Side by side (issue 43): each of 10 bilateral AUs' truth field with one half reversed (left or right) fails; before the
side check 4 of these 20 passed (AU02, AU06, AU07, AU11: the two halves' mean still pointed the FACS way). Every truth field reversed by ``SynthSpec.reversed_aus`` fails, the other 19
pass; each truth field turned by 180 degrees across its FACS direction fails, by 90 degrees does not pass. Truth
fields judged on the mean mesh of a fit (within-video OLS, AR(1) AU noise correlated across AUs, mean AU activity
moving the mean mesh) and in a release fitted by the pipeline (anchors' similarity into its frame) pass 20/20.

FACS regions (the regions and nearby areas of :data:`FACS_EXPECTATIONS`, :mod:`aumesh.card.facs_regions`) follow
the appearance changes described for each action unit in the FACS manual: Ekman, P., Friesen, W. V., & Hager, J. C.
(2002). *Facial Action Coding System: The Manual*. Salt Lake City: Research Nexus (first edition Ekman & Friesen,
1978, Consulting Psychologists Press); e.g. AU02 raises the lateral part of the brows, AU12 pulls the lip corners up
and back obliquely and deepens the nasolabial furrow, AU17 pushes the chin boss and the lower lip up. Only the gross
region and direction are checked; FACS's subtler signs (wrinkles, bulges) are not visible in a 478-vertex mesh.

Face terms
----------
``up``/``down`` (along forehead 10 - chin 152), ``left``/``right`` (the
**subject's**: along 33 -> 263), ``toward``/``away`` (the camera; the nose tip is
toward), and for bilateral groups (``brow_inner`` = ``brow_inner_left`` +
``brow_inner_right`` ...) ``outward``/``inward`` relative to the face midline,
taken on each side.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.card.facs_regions import FACE_TERMS, FACS_EXPECTATIONS
from aumesh.core import schema
from aumesh.core.io import atomic_write_json
from aumesh.core.schema import AU_COLUMNS, N_TARGETS, N_VERTICES
from aumesh.geometry import face, landmarks, measures

PASS_COSINE = 0.7
FAIL_COSINE = 0.0
PASS_SHARE = 0.5
NEARBY_SHARE = 0.4
FAIL_SHARE = 0.1
UNILATERAL_SHARE = 0.2  # a side of a bilateral region with less of its motion is "still" (a unilateral action)
MIN_MAGNITUDE = 1e-6  # inter-ocular units; below this an AU "does not move"

_RANK = {"pass": 0, "doubtful": 1, "fail": 2}
AREA_NAMES: tuple[str, ...] = tuple(landmarks.AREA_SEEDS)
AREA_GROUPS: tuple[str, ...] = tuple(dict.fromkeys(landmarks.region_group(a) for a in AREA_NAMES))


def local_terms(vec: np.ndarray, side: np.ndarray | int) -> np.ndarray:
    """Face-frame vectors (..., 3) (x left, y down, z away) -> (lateral, up, toward); ``side`` +1/-1 for bilateral
    areas (lateral = outward), 0 for midline (lateral = subject's left)."""
    side = np.asarray(side)
    lateral = np.where(side == 0, vec[..., 0], vec[..., 0] * side)
    return np.stack([lateral, -vec[..., 1], -vec[..., 2]], axis=-1)


def _direction_word(local: np.ndarray, bilateral: bool) -> str:
    lat = ("outward", "inward") if bilateral else ("left", "right")
    words = (lat, ("up", "down"), ("toward", "away"))
    k = int(np.argmax(np.abs(local)))
    return words[k][0 if local[k] >= 0 else 1]


class Areas:
    """The area partition of one mesh: per vertex its area group and side (+1 left, -1 right, 0 midline).

    Parameters
    ----------
    mesh : np.ndarray, shape (478, 3)
        Face-frame mesh (:func:`aumesh.geometry.face.face_frame`); areas by :func:`aumesh.geometry.measures.face_areas`.
    """

    def __init__(self, mesh: np.ndarray):
        area = measures.face_areas(mesh)
        self.group = np.array([AREA_GROUPS.index(landmarks.region_group(a)) for a in AREA_NAMES])[area]
        self.side = np.array([landmarks.region_side(a) for a in AREA_NAMES])[area]
        self.bilateral = {g: any(landmarks.region_group(a) == g and a != g for a in AREA_NAMES) for g in AREA_GROUPS}

    def mask(self, group: str) -> np.ndarray:
        if group not in AREA_GROUPS:
            raise KeyError(f"unknown area group {group!r}; known: {list(AREA_GROUPS)}")
        return self.group == AREA_GROUPS.index(group)


def weighted_direction(disp: np.ndarray, areas: Areas, group: str, side: int = 0) -> tuple[np.ndarray, float]:
    """Displacement-weighted mean of the group's vertices' displacements in local terms, and their mean magnitude.

    Weights are the vertices' displacement magnitudes, so vertices that move most decide the direction and a few
    near-still vertices of the area do not dilute it (bilateral areas: lateral = outward on each side). ``side`` +1 / -1
    keeps only the subject's left / right half of a bilateral group (0: both)."""
    m = areas.mask(group) & ((areas.side == side) if side else True)
    local = local_terms(disp[m], areas.side[m])
    w = np.linalg.norm(disp[m], axis=1)
    mean_mag = float(w.mean()) if w.size else 0.0
    if w.sum() <= MIN_MAGNITUDE:
        return np.zeros(3), mean_mag
    return (w[:, None] * local).sum(axis=0) / w.sum(), mean_mag


def au_direction_from_displacement(disp: np.ndarray, au: str, mesh: np.ndarray | None = None) -> dict[str, Any]:
    """Check one AU's displacement field against :data:`FACS_EXPECTATIONS`: where it moves and which way.

    Parameters
    ----------
    disp : np.ndarray, shape (478, 3)
        Displacement at intensity 1 in the face frame (x subject's left, y down,
        z away), inter-ocular units.
    au : str
        AU name, a key of :data:`FACS_EXPECTATIONS`.
    mesh : np.ndarray, shape (478, 3), optional
        The neutral (mean) mesh the areas are found on (:func:`aumesh.geometry.measures.face_areas`);
        defaults to :func:`aumesh.geometry.face.canonical_template`.

    Returns
    -------
    dict
        JSON-serialisable entry of :func:`au_direction_report`'s ``"aus"``.
    """
    return judge_fields(np.asarray(disp)[None], [au], mesh)[0]


def judge_fields(disp: np.ndarray, aus: list[str], mesh: np.ndarray | None = None) -> list[dict[str, Any]]:
    """:func:`au_direction_from_displacement` for many fields on one mesh (its areas found once).

    Parameters
    ----------
    disp : np.ndarray, shape (n, 478, 3)
        Displacement fields in the face frame, inter-ocular units.
    aus : list of str, length n
        The AU each field is judged as (keys of :data:`FACS_EXPECTATIONS`; repeats allowed).
    mesh : np.ndarray, shape (478, 3), optional
        As in :func:`au_direction_from_displacement`.

    Returns
    -------
    list of dict
        One entry per field, in order.
    """
    fields = np.asarray(disp, dtype=np.float64)
    if fields.ndim != 3 or fields.shape[1:] != (N_VERTICES, 3) or len(fields) != len(aus):
        raise ValueError(
            f"disp must be (n, {N_VERTICES}, 3) with one AU name per field, got {fields.shape}, {len(aus)}"
        )
    unknown = sorted(set(aus) - set(FACS_EXPECTATIONS))
    if unknown:
        raise KeyError(f"no FACS expectation for {unknown}; known: {sorted(FACS_EXPECTATIONS)}")
    areas = Areas(face.canonical_template() if mesh is None else mesh)
    return [_judge(d, au, areas) for d, au in zip(fields, aus, strict=True)]


def _side_checks(
    disp: np.ndarray, areas: Areas, group: str, want: np.ndarray, energy: np.ndarray
) -> dict[str, dict[str, Any]]:
    """Each side of a bilateral group judged alone (outward = away from the midline on that side).

    A side holding under ``UNILATERAL_SHARE`` of the group's motion is left out (FACS codes unilateral actions, e.g.
    R12: a still side is not against FACS); the other sides get the cosine of their displacement-weighted mean to
    ``want`` and a verdict by the same cosine thresholds as the whole group. Catches a field whose two halves move
    opposite ways (a mirrored or rotated half), which the group's mean can average into a plausible direction.
    """
    in_group = areas.mask(group)
    total = float(energy[in_group].sum())
    out: dict[str, dict[str, Any]] = {}
    for name, side in (("left", 1), ("right", -1)):
        share = float(energy[in_group & (areas.side == side)].sum()) / total if total > 0 else 0.0
        local, _ = weighted_direction(disp, areas, group, side)
        norm = float(np.linalg.norm(local))
        if share < UNILATERAL_SHARE or norm <= MIN_MAGNITUDE:
            continue
        cos = float(local @ want / norm)
        verdict = "fail" if cos <= FAIL_COSINE else "doubtful" if cos < PASS_COSINE else "pass"
        out[name] = {"cosine": round(cos, 4), "share_of_region": round(share, 4), "verdict": verdict}
    return out


def _judge(disp: np.ndarray, au: str, areas: Areas) -> dict[str, Any]:
    exp = FACS_EXPECTATIONS[au]
    groups = list(exp.get("regions", [g for g, _ in exp["checks"]]))
    nearby = list(exp["nearby"])
    energy = (disp**2).sum(axis=1)
    total = float(energy.sum())
    moves = float(np.sqrt(energy.max())) > MIN_MAGNITUDE
    shares_arr = np.bincount(areas.group, weights=energy, minlength=len(AREA_GROUPS)) / (total if moves else 1.0)
    shares = {g: float(shares_arr[k]) for k, g in enumerate(AREA_GROUPS)}
    ranked = sorted(AREA_GROUPS, key=lambda g: -shares[g])
    top = ranked[0]
    facs_share = sum(shares[g] for g in groups)
    nearby_share = facs_share + sum(shares[g] for g in nearby)
    top_local, top_mag = weighted_direction(disp, areas, top)

    # where: the largest motion in the FACS region, or a majority of the energy there
    if not moves:
        where, where_reason = "fail", "no displacement"
    elif top in groups:
        where, where_reason = "pass", f"largest motion in {top} ({shares[top]:.0%} of the motion)"
    elif facs_share >= PASS_SHARE:
        where, where_reason = "pass", f"{facs_share:.0%} of the motion in {'+'.join(groups)}"
    elif top in nearby and facs_share >= NEARBY_SHARE:
        where, where_reason = (
            "pass",
            f"largest motion in {top} ({shares[top]:.0%}, FACS: moves with {au}), {facs_share:.0%} in {'+'.join(groups)}",
        )
    elif facs_share < FAIL_SHARE:
        where, where_reason = (
            "fail",
            f"largest motion in {top} ({shares[top]:.0%}); {'+'.join(groups)} barely moves ({facs_share:.0%})",
        )
    else:
        where, where_reason = (
            "doubtful",
            f"largest motion in {top} ({shares[top]:.0%}), only {facs_share:.0%} in {'+'.join(groups)}",
        )

    checks = []
    for group, terms in exp["checks"]:
        want = sum(w * np.asarray(FACE_TERMS[t], dtype=float) for t, w in terms.items())
        want = want / np.linalg.norm(want)
        local, mag = weighted_direction(disp, areas, group)
        norm = float(np.linalg.norm(local))
        cos = float(local @ want / norm) if norm > MIN_MAGNITUDE else 0.0
        expected = " + ".join(terms)
        observed = _direction_word(local, areas.bilateral[group])
        if not moves:
            verdict, reason = "fail", "no displacement"
        elif norm <= MIN_MAGNITUDE:
            verdict, reason = "fail", f"{group} has no net motion"
        elif cos <= FAIL_COSINE:
            verdict, reason = "fail", f"{group} moves {observed}, against expected {expected} (cos {cos:+.2f})"
        elif cos < PASS_COSINE:
            verdict, reason = "doubtful", f"{group} direction only loosely matches {expected} (cos {cos:+.2f})"
        elif shares[group] < FAIL_SHARE:
            verdict, reason = "doubtful", f"{group} moves {expected} but barely ({shares[group]:.0%} of the motion)"
        else:
            verdict, reason = "pass", f"{group} moves {expected} (cos {cos:+.2f})"
        sides = _side_checks(disp, areas, group, want, energy) if areas.bilateral[group] and moves else {}
        for name, sc in sides.items():  # each side of a bilateral region on its own: a side against FACS fails
            if sc["verdict"] != "pass" and _RANK[sc["verdict"]] > _RANK[verdict]:
                verdict = sc["verdict"]
                reason = f"{group} on the subject's {name} moves against expected {expected} (cos {sc['cosine']:+.2f})"
                if sc["verdict"] == "doubtful":
                    reason = (
                        f"{group} on the subject's {name} only loosely matches {expected} (cos {sc['cosine']:+.2f})"
                    )
        checks.append(
            {
                "region": group,
                "expected": expected,
                "observed_direction": observed,
                "mean_displacement_local": [round(float(v), 6) for v in local],
                "cosine": round(cos, 4),
                "magnitude": round(mag, 6),
                "share": round(shares[group], 4),
                "sides": sides,
                "verdict": verdict,
                "reason": reason,
            }
        )
    direction = max((c["verdict"] for c in checks), key=lambda v: _RANK[v])
    verdict = max(where, direction, key=lambda v: _RANK[v])
    reasons = [where_reason] if not moves else [where_reason] + [c["reason"] for c in checks]
    return {
        "name": exp["name"],
        "expected": "; ".join(f"{c['region']}: {c['expected']}" for c in checks),
        "facs_regions": groups,
        "nearby_regions": nearby,
        "top_region": top,
        "top_region_direction": _direction_word(top_local, areas.bilateral[top]),
        "top_regions": [{"region": g, "share": round(shares[g], 4)} for g in ranked[:3]],
        "facs_share": round(facs_share, 4),
        "nearby_share": round(nearby_share, 4),
        "region_shares": {g: round(shares[g], 4) for g in ranked},
        "magnitude": round(top_mag, 6),
        "rms_displacement": round(float(np.sqrt(total / len(disp))), 6),
        "max_vertex_displacement": round(float(np.sqrt(energy.max())), 6),
        "checks": checks,
        "where": where,
        "direction": direction,
        "verdict": verdict,
        "reason": "; ".join(reasons),
    }


def load_arrays(src: str | os.PathLike | Mapping[str, Any]) -> tuple[dict[str, Any], str]:
    """A release's arrays and the name errors use: a mapping as is (``"<arrays>"``), a path read by
    :func:`aumesh.model.release.load_npz` (named by its path)."""
    if isinstance(src, Mapping):
        return dict(src), "<arrays>"
    from aumesh.model.release import load_npz

    return load_npz(os.fspath(src)), str(src)


def _require(arrays: Mapping[str, Any], key: str, where: str) -> np.ndarray:
    if key not in arrays:
        raise KeyError(
            f"{where}: missing key {key!r} (has {sorted(arrays)}); a release NPZ needs the card's keys "
            f"coef, intercept, input_columns, au_columns, mean_aligned_mesh"
        )
    return np.asarray(arrays[key])


def au_displacements(arrays: Mapping[str, Any], where: str = "<arrays>") -> tuple[np.ndarray, np.ndarray, list[str]]:
    """AU displacement fields of a release, in the face frame of its mean mesh.

    Parameters
    ----------
    arrays : mapping
        Release arrays with ``coef`` (23, 1434), ``mean_aligned_mesh`` (478, 3)
        and ``au_columns`` or ``input_columns`` (rows are selected by name).
    where : str
        File name used in error messages.

    Returns
    -------
    disp : np.ndarray, shape (20, 478, 3)
        ``aumesh.core.schema.AU_COLUMNS`` order, face frame, inter-ocular units.
    mesh : np.ndarray, shape (478, 3)
        ``mean_aligned_mesh`` in the face frame.
    columns : list of str
        The AU names (``AU_COLUMNS``).
    """
    coef = _require(arrays, "coef", where).astype(np.float64)
    if coef.ndim != 2 or coef.shape[1] != N_TARGETS:
        raise ValueError(f"{where}: 'coef' must be (n_inputs, {N_TARGETS}) axis-major as in the card, got {coef.shape}")
    names_key = "input_columns" if "input_columns" in arrays else "au_columns"
    names = [str(s) for s in _require(arrays, names_key, where).tolist()]
    if names_key == "au_columns" and len(names) != coef.shape[0] and coef.shape[0] >= len(names):
        names = names + [f"_extra{i}" for i in range(coef.shape[0] - len(names))]
    if len(names) != coef.shape[0]:
        raise ValueError(f"{where}: {names_key!r} has {len(names)} names but 'coef' has {coef.shape[0]} rows")
    missing = [a for a in AU_COLUMNS if a not in names]
    if missing:
        raise KeyError(f"{where}: {names_key!r} lacks AUs {missing}")
    mean = _require(arrays, "mean_aligned_mesh", where).astype(np.float64)
    rows = coef[[names.index(a) for a in AU_COLUMNS]]
    broken = [a for a, row in zip(AU_COLUMNS, rows, strict=True) if not np.all(np.isfinite(row))]
    if broken or not np.all(np.isfinite(mean)):
        what = f"'coef' rows {broken}" if broken else "'mean_aligned_mesh'"
        raise ValueError(f"{where}: {what} hold NaN or inf; the release is broken: fit it again (dvc repro)")
    origin, axes, scale = face.face_frame(mean)
    disp = schema.unflatten_axis_major(rows) @ axes.T / scale
    return disp, (mean - origin) @ axes.T / scale, list(AU_COLUMNS)


def au_direction_report(npz_path_or_arrays: str | os.PathLike | Mapping[str, Any]) -> dict[str, Any]:
    """Region, direction, magnitude and FACS verdict for each of the 20 AUs.

    Parameters
    ----------
    npz_path_or_arrays : path or mapping
        A release NPZ (card format) or a mapping with at least ``coef``,
        ``mean_aligned_mesh`` and ``input_columns`` / ``au_columns``.

    Returns
    -------
    dict
        JSON-serialisable: ``units``, ``interocular_distance`` (input units),
        ``area_vertices`` (area group -> number of vertices in it on this mesh),
        ``thresholds``, ``summary`` (counts per verdict) and ``aus``
        (AU -> entry of :func:`au_direction_from_displacement`: ``verdict`` in pass / doubtful / fail,
        ``where`` and ``direction`` (the two halves of the verdict), ``facs_regions``, ``facs_share``,
        ``nearby_regions``, ``nearby_share``, ``top_region``, ``top_regions`` (the three largest shares),
        ``region_shares`` (every area group, largest first), ``checks`` (per FACS region: expected and observed
        direction, cosine, share, verdict), ``reason``).
    """
    arrays, where = load_arrays(npz_path_or_arrays)
    disp, face_mesh, cols = au_displacements(arrays, where)
    mean = np.asarray(arrays["mean_aligned_mesh"], dtype=np.float64)
    aus = dict(zip(cols, judge_fields(disp, cols, face_mesh), strict=True))
    summary = {v: sum(1 for e in aus.values() if e["verdict"] == v) for v in _RANK}
    area_groups = Areas(face_mesh).group
    return {
        "source": where,
        "units": "inter-ocular distance (33-263) of mean_aligned_mesh; directions in the subject's face terms; "
        "shares: fraction of the field's displacement energy (sum of squared vertex displacements) per area group",
        "interocular_distance": float(np.linalg.norm(mean[263] - mean[33])),
        "area_vertices": {g: int((area_groups == k).sum()) for k, g in enumerate(AREA_GROUPS)},
        "thresholds": {
            "pass_cosine": PASS_COSINE,
            "fail_cosine": FAIL_COSINE,
            "pass_share": PASS_SHARE,
            "nearby_share": NEARBY_SHARE,
            "fail_share": FAIL_SHARE,
            "unilateral_share": UNILATERAL_SHARE,
        },
        "summary": summary,
        "aus": aus,
    }


def write_report(report: Mapping[str, Any], path: str | os.PathLike) -> Path:
    """Write a report as JSON atomically (temp file in the same folder, then ``os.replace``)."""
    return atomic_write_json(os.fspath(path), report)


def report_markdown_table(report: Mapping[str, Any]) -> str:
    """Markdown table of a report for the model card (one row per AU).

    Columns: the AU, its FACS name and expected direction(s), the FACS region(s) with the share of the field's
    displacement energy inside them, the top region (largest share) with its share and direction, the top region's
    mean displacement (inter-ocular units), the verdict and its reasons.
    """
    lines = [
        "| AU | Name | Expected (FACS) | FACS region: share of motion | Top region (share) | Direction "
        "| Magnitude (IOD) | Verdict | Reason |",
        "|---|---|---|---|---|---|---:|---|---|",
    ]
    from aumesh.card.markdown import md_text

    for au, e in report["aus"].items():  # names come from the NPZ (`aumesh render` takes any): shown as text
        reason = md_text(str(e["reason"]).replace("|", "/"))
        top_share = e.get("region_shares", {}).get(e["top_region"])
        top = e["top_region"] if top_share is None else f"{e['top_region']} ({top_share:.0%})"
        facs = "+".join(e.get("facs_regions", []))
        facs_cell = f"{facs}: {e['facs_share']:.0%}" if "facs_share" in e else ""
        lines.append(
            f"| {md_text(au)} | {md_text(e['name'])} | {md_text(e['expected'])} | {md_text(facs_cell)} | "
            f"{md_text(top)} | {md_text(e['top_region_direction'])} | {e['magnitude']:.4f} | "
            f"{md_text(e['verdict'])} | {reason} |"
        )
    s = report.get("summary", {})
    t = report.get("thresholds", {})
    lines.append("")
    lines.append(f"{s.get('pass', 0)} pass, {s.get('doubtful', 0)} doubtful, {s.get('fail', 0)} fail.")
    if "pass_share" in t:
        lines.append("")
        lines.append(
            "Share of motion: the AU field's squared vertex displacements (face frame, inter-ocular units) summed per "
            "facial area, as a fraction of the whole face. An AU passes when its largest motion is in its FACS region "
            f"(the top region, or at least {t['pass_share']:.0%} of the motion there, or the top region is one FACS "
            f"names for the AU with at least {t['nearby_share']:.0%} in the FACS region) and the displacement-weighted "
            "mean direction there (and on each moving side of a bilateral region) is within "
            f"cos {t['pass_cosine']:.2f} of FACS; it fails when that direction opposes "
            f"FACS (cos <= {t['fail_cosine']:.2f}) or the largest motion is elsewhere with under "
            f"{t['fail_share']:.0%} in the FACS region (aumesh.card.directions)."
        )
    return "\n".join(lines) + "\n"
