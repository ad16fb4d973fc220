"""AU-direction check of a released AU(+pose) -> mesh model against FACS.

For each AU the model's displacement at intensity 1 (pose 0) is the AU's ``coef``
row, reshaped from the axis-major layout to (478, 3). It is expressed in the
face frame of the release's ``mean_aligned_mesh`` (see :func:`aumesh.geometry.face.face_frame`:
orientation recovered from the mesh itself, so pixel / y-down, y-up, rotated or
scaled releases all give the same answer) in inter-ocular units, then:

* each region of :data:`aumesh.geometry.face.REGIONS` gets its mean displacement vector
  and mean displacement magnitude; the region with the largest mean magnitude
  is reported with its dominant direction;
* the AU's rows of :data:`FACS_EXPECTATIONS` are checked: for each expected
  (region group, direction), the cosine between the group's mean displacement
  and the expected direction, and the group's magnitude relative to the top
  region.

Face terms
----------
``up``/``down`` (along forehead 10 - chin 152), ``left``/``right`` (the
**subject's**: along 33 -> 263), ``toward``/``away`` (the camera; the nose tip is
toward), and for bilateral groups (``brow_inner`` = ``brow_inner_left`` +
``brow_inner_right`` ...) ``outward``/``inward`` relative to the face midline,
measured per side and averaged.

Verdicts (per check; the AU's verdict is its worst check)
---------------------------------------------------------
``fail``      cosine <= ``FAIL_COSINE`` (moves against FACS), or no displacement;
``doubtful``  cosine < ``PASS_COSINE`` or the group moves < ``PASS_RELATIVE`` x the
              top region's magnitude;
``pass``      otherwise.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.data import schema
from aumesh.data.schema import AU_COLUMNS, AU_NAMES, N_TARGETS
from aumesh.geometry import face
from aumesh.utils.io import atomic_write_json

PASS_COSINE = 0.6
FAIL_COSINE = 0.0
PASS_RELATIVE = 0.5
MIN_MAGNITUDE = 1e-6  # inter-ocular units; below this an AU "does not move"

# Face-term unit vectors in local coordinates (lateral, up, toward). "lateral" is
# subject's left for midline groups and outward for bilateral groups.
_TERMS: dict[str, tuple[float, float, float]] = {
    "up": (0, 1, 0),
    "down": (0, -1, 0),
    "toward": (0, 0, 1),
    "away": (0, 0, -1),
    "outward": (1, 0, 0),
    "inward": (-1, 0, 0),
    "left": (1, 0, 0),
    "right": (-1, 0, 0),
}

# The FACS expectation table (data). Each check: (region group, {term: weight}).
# A group without a side suffix that names REGIONS "<group>_left/_right" is bilateral.
FACS_EXPECTATIONS: dict[str, dict[str, Any]] = {
    "AU01": {"name": AU_NAMES["AU01"], "checks": [("brow_inner", {"up": 1.0})]},
    "AU02": {"name": AU_NAMES["AU02"], "checks": [("brow_outer", {"up": 1.0})]},
    "AU04": {"name": AU_NAMES["AU04"], "checks": [("brow_inner", {"down": 1.0, "inward": 0.6})]},
    "AU05": {"name": AU_NAMES["AU05"], "checks": [("upper_eyelid", {"up": 1.0})]},
    "AU06": {"name": AU_NAMES["AU06"], "checks": [("cheek", {"up": 1.0})]},
    "AU07": {"name": AU_NAMES["AU07"], "checks": [("lower_eyelid", {"up": 1.0})]},
    "AU09": {"name": AU_NAMES["AU09"], "checks": [("nose", {"up": 1.0})]},
    "AU10": {"name": AU_NAMES["AU10"], "checks": [("upper_lip", {"up": 1.0})]},
    "AU11": {"name": AU_NAMES["AU11"], "checks": [("nasolabial", {"up": 1.0, "outward": 0.5})]},
    "AU12": {"name": AU_NAMES["AU12"], "checks": [("lip_corner", {"up": 1.0, "outward": 1.0})]},
    "AU14": {"name": AU_NAMES["AU14"], "checks": [("lip_corner", {"away": 1.0, "inward": 0.3})]},
    "AU15": {"name": AU_NAMES["AU15"], "checks": [("lip_corner", {"down": 1.0})]},
    "AU17": {"name": AU_NAMES["AU17"], "checks": [("chin", {"up": 1.0})]},
    "AU20": {"name": AU_NAMES["AU20"], "checks": [("lip_corner", {"outward": 1.0})]},
    "AU23": {"name": AU_NAMES["AU23"], "checks": [("lip_corner", {"inward": 1.0})]},
    "AU24": {"name": AU_NAMES["AU24"], "checks": [("upper_lip", {"down": 1.0}), ("lower_lip", {"up": 1.0})]},
    "AU25": {"name": AU_NAMES["AU25"], "checks": [("lower_lip", {"down": 1.0})]},
    "AU26": {"name": AU_NAMES["AU26"], "checks": [("jaw", {"down": 1.0}), ("lower_lip", {"down": 1.0})]},
    "AU28": {"name": AU_NAMES["AU28"], "checks": [("upper_lip", {"away": 1.0}), ("lower_lip", {"away": 1.0})]},
    "AU43": {"name": AU_NAMES["AU43"], "checks": [("upper_eyelid", {"down": 1.0})]},
}

_RANK = {"pass": 0, "doubtful": 1, "fail": 2}


def _group_regions(group: str) -> list[str]:
    if group in face.REGIONS:
        return [group]
    sides = [f"{group}_left", f"{group}_right"]
    if all(s in face.REGIONS for s in sides):
        return sides
    raise KeyError(f"unknown region group {group!r}; known regions: {sorted(face.REGIONS)}")


def _local(vec: np.ndarray, region: str) -> np.ndarray:
    """Face-frame vector (x left, y down, z away) -> (lateral, up, toward)."""
    side = face.region_side(region)
    lateral = vec[..., 0] * side if side else vec[..., 0]
    return np.stack([lateral, -vec[..., 1], -vec[..., 2]], axis=-1)


def _direction_word(local: np.ndarray, bilateral: bool) -> str:
    lat = ("outward", "inward") if bilateral else ("left", "right")
    words = (lat, ("up", "down"), ("toward", "away"))
    k = int(np.argmax(np.abs(local)))
    return words[k][0 if local[k] >= 0 else 1]


def _group_stats(disp: np.ndarray, group: str) -> tuple[np.ndarray, float, bool]:
    regions = _group_regions(group)
    locs = [_local(disp[face.REGIONS[r]].mean(axis=0), r) for r in regions]
    mags = [float(np.linalg.norm(disp[face.REGIONS[r]], axis=1).mean()) for r in regions]
    return np.mean(locs, axis=0), float(np.mean(mags)), len(regions) == 2


def au_direction_from_displacement(disp: np.ndarray, au: str) -> dict[str, Any]:
    """Check one AU's displacement field against :data:`FACS_EXPECTATIONS`.

    Parameters
    ----------
    disp : np.ndarray, shape (478, 3)
        Displacement at intensity 1 in the face frame (x subject's left, y down,
        z away), inter-ocular units.
    au : str
        AU name, a key of :data:`FACS_EXPECTATIONS`.

    Returns
    -------
    dict
        JSON-serialisable entry of :func:`au_direction_report`'s ``"aus"``.
    """
    if au not in FACS_EXPECTATIONS:
        raise KeyError(f"no FACS expectation for {au!r}; known: {sorted(FACS_EXPECTATIONS)}")
    exp = FACS_EXPECTATIONS[au]
    region_mag = {r: float(np.linalg.norm(disp[idx], axis=1).mean()) for r, idx in face.REGIONS.items()}
    top = max(region_mag, key=lambda r: region_mag[r])
    top_mag = region_mag[top]
    top_local = _local(disp[face.REGIONS[top]].mean(axis=0), top)
    checks = []
    for group, terms in exp["checks"]:
        want = sum(w * np.asarray(_TERMS[t], dtype=float) for t, w in terms.items())
        want = want / np.linalg.norm(want)
        local, mag, bilateral = _group_stats(disp, group)
        norm = float(np.linalg.norm(local))
        cos = float(local @ want / norm) if norm > MIN_MAGNITUDE else 0.0
        rel = mag / top_mag if top_mag > MIN_MAGNITUDE else 0.0
        expected = " + ".join(terms)
        if top_mag <= MIN_MAGNITUDE:
            verdict, reason = "fail", "no displacement"
        elif cos <= FAIL_COSINE:
            verdict, reason = (
                "fail",
                f"{group} moves {_direction_word(local, bilateral)}, against expected {expected} (cos {cos:+.2f})",
            )
        elif cos < PASS_COSINE:
            verdict, reason = "doubtful", f"{group} direction only loosely matches {expected} (cos {cos:+.2f})"
        elif rel < PASS_RELATIVE:
            verdict, reason = "doubtful", f"{group} moves {expected} but weakly ({rel:.2f} x top region {top})"
        else:
            verdict, reason = "pass", f"{group} moves {expected} (cos {cos:+.2f})"
        checks.append(
            {
                "region": group,
                "expected": expected,
                "observed_direction": _direction_word(local, bilateral),
                "mean_displacement_local": [round(float(v), 6) for v in local],
                "cosine": round(cos, 4),
                "magnitude": round(mag, 6),
                "relative_to_top": round(rel, 4),
                "verdict": verdict,
                "reason": reason,
            }
        )
    worst = max(checks, key=lambda c: _RANK[c["verdict"]])
    return {
        "name": exp["name"],
        "expected": "; ".join(f"{c['region']}: {c['expected']}" for c in checks),
        "top_region": top,
        "top_region_direction": _direction_word(top_local, face.region_side(top) != 0),
        "magnitude": round(top_mag, 6),
        "max_vertex_displacement": round(float(np.linalg.norm(disp, axis=1).max()), 6),
        "checks": checks,
        "verdict": worst["verdict"],
        "reason": "; ".join(c["reason"] for c in checks),
    }


def _load_arrays(src: str | os.PathLike | Mapping[str, Any]) -> tuple[dict[str, Any], str]:
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
        ``aumesh.data.schema.AU_COLUMNS`` order, face frame, inter-ocular units.
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
    origin, axes, scale = face.face_frame(mean)
    rows = coef[[names.index(a) for a in AU_COLUMNS]]
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
        ``thresholds``, ``summary`` (counts per verdict) and ``aus``
        (AU -> entry of :func:`au_direction_from_displacement`).
    """
    arrays, where = _load_arrays(npz_path_or_arrays)
    disp, _, cols = au_displacements(arrays, where)
    mean = np.asarray(arrays["mean_aligned_mesh"], dtype=np.float64)
    aus = {au: au_direction_from_displacement(disp[k], au) for k, au in enumerate(cols)}
    summary = {v: sum(1 for e in aus.values() if e["verdict"] == v) for v in _RANK}
    return {
        "source": where,
        "units": "inter-ocular distance (33-263) of mean_aligned_mesh; directions in the subject's face terms",
        "interocular_distance": float(np.linalg.norm(mean[263] - mean[33])),
        "thresholds": {"pass_cosine": PASS_COSINE, "fail_cosine": FAIL_COSINE, "pass_relative": PASS_RELATIVE},
        "summary": summary,
        "aus": aus,
    }


def write_report(report: Mapping[str, Any], path: str | os.PathLike) -> Path:
    """Write a report as JSON atomically (temp file in the same folder, then ``os.replace``)."""
    return atomic_write_json(os.fspath(path), report)


def report_markdown_table(report: Mapping[str, Any]) -> str:
    """Markdown table of a report for the model card (one row per AU)."""
    lines = [
        "| AU | Name | Expected (FACS) | Top region | Direction | Magnitude (IOD) | Verdict | Reason |",
        "|---|---|---|---|---|---:|---|---|",
    ]
    from aumesh.card.markdown import md_text

    for au, e in report["aus"].items():  # names come from the NPZ (`aumesh render` takes any): shown as text
        reason = md_text(str(e["reason"]).replace("|", "/"))
        lines.append(
            f"| {md_text(au)} | {md_text(e['name'])} | {md_text(e['expected'])} | {md_text(e['top_region'])} | "
            f"{md_text(e['top_region_direction'])} | {e['magnitude']:.4f} | {md_text(e['verdict'])} | {reason} |"
        )
    s = report.get("summary", {})
    lines.append("")
    lines.append(f"{s.get('pass', 0)} pass, {s.get('doubtful', 0)} doubtful, {s.get('fail', 0)} fail.")
    return "\n".join(lines) + "\n"
