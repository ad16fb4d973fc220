"""What a release's training data supports: each input's range in training, the AUs the data never expressed, the
detector whose AU space the model lives in, and the one-line warnings for inputs beyond them.

Learnt from py-feat 2.1.5's own AU/blendshape -> mesh releases (``feat/plotting.py``: ``PLSFeatMeshModel``,
``predict_face_mesh_from_features``): their v6 NPZs carry ``feature_p99`` (each input's 99th percentile in training)
and ``unsupported_features`` (inputs the detector never expressed, "whose coefficients are unconstrained"), and
py-feat warns when such an input is given above 0.02. aumesh records more (min, p1, p50, p99, max and the share of
frames where an AU is active, per input: :func:`range_record`) and warns instead of clipping: the mesh it returns is
the model's, and the caller is told where it stops being supported by data.

Pure functions on arrays and dicts; the prepare stage computes the ranges (:mod:`aumesh.pipeline.prepare`), the
release stage records them (``model_card.json`` ``data``; the NPZ's ``feature_p99`` and ``unsupported_features``),
and :mod:`aumesh.model.input_checks` warns from them.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from aumesh.core.schema import AU_COLUMNS, INPUT_COLUMNS

#: An AU whose training p99 is below this was "never expressed" by the data: its field is the fit's guess, not
#: something the data showed (py-feat's ``unsupported_features``).
UNSUPPORTED_P99 = 0.05
#: An unsupported AU given above this warns (py-feat's threshold in ``predict_face_mesh_from_features``).
UNSUPPORTED_GIVEN = 0.02
#: An AU is "active" in a frame above this (the range record's ``active_fraction``).
ACTIVE_AU = 0.1
#: The quantiles a range record holds, by name (``min`` and ``max`` are the 0 and 1 quantiles: the exact extremes).
RANGE_QUANTILES: dict[str, float] = {"min": 0.0, "p1": 0.01, "p50": 0.5, "p99": 0.99, "max": 1.0}
#: Float32 rounding of a value equal to the training max (tables hold float32; the ranges are float64 of them).
_SLACK = 1e-6

#: What each detector's AU columns mean (the card's ``data.detector.au_meaning``).
AU_MEANING: dict[str, str] = {
    "Detectorv2": (
        "AU presence probabilities in [0, 1] from py-feat's multitask network (feat/multitask/inference.py: "
        "MultitaskOutput.au, 'probabilities in [0, 1]'; py-feat's model pages for its v4-v6 AU-to-mesh models "
        "describe these AUs so): how likely the AU is present, not how intense it is"
    ),
    "MPDetector": (
        "a linear map of MediaPipe's 52 blendshapes clipped to [0, 1] (feat/utils/blendshape_to_au.py: "
        "pls_predict_batch, a PLS fit to Detectorv1's xgb AU intensities, out-of-sample R2 0.24): an estimate of "
        "FACS intensity with MediaPipe's blendshapes' limits, not a FACS coding"
    ),
    "mixed": (
        "tables from different detectors pooled: their AUs mean different things (Detectorv2's presence "
        "probabilities, MPDetector's blendshape map), so one AU value is not one expression across the data"
    ),
    "unknown": (
        "not a py-feat detector export (the split layout or an interleaved table): the AUs mean what the tool that "
        "wrote them means; aumesh assumes py-feat's 0..1 scale"
    ),
}
#: The py-feat detectors whose AU space :data:`AU_MEANING` names (``split`` and ``table`` are layouts, not detectors).
DETECTORS = ("Detectorv2", "MPDetector")


# --------------------------------------------------------------------------------------------- training side
def range_record(quantiles: Sequence[float], active_fraction: float | None) -> dict[str, float | None]:
    """One input's range record: ``{"min", "p1", "p50", "p99", "max", "active_fraction"}``.

    Parameters
    ----------
    quantiles : sequence of float, length 5
        The input's :data:`RANGE_QUANTILES` over the training frames, in that order (``np.quantile``'s linear method).
    active_fraction : float or None
        Share of those frames with the value above :data:`ACTIVE_AU` (AUs); None for pose.
    """
    record: dict[str, float | None] = {k: float(v) for k, v in zip(RANGE_QUANTILES, quantiles, strict=True)}
    record["active_fraction"] = None if active_fraction is None else float(active_fraction)
    return record


def unsupported_inputs(input_ranges: Mapping[str, Mapping[str, Any]], columns: Sequence[str] = AU_COLUMNS) -> list[str]:
    """The inputs of ``columns`` (the AUs by default; a family's inputs for its release, in that order) whose training
    p99 is below :data:`UNSUPPORTED_P99`: inputs the data never expressed (one of 100 frames or fewer shows them at
    0.05 or more, whatever their scale's top: AU presence, blendshape scores and emotion probabilities all lie in
    [0, 1])."""
    return [a for a in columns if a in input_ranges and float(input_ranges[a]["p99"]) < UNSUPPORTED_P99]


def detector_counts(manifest: Mapping[str, Any]) -> dict[str, int]:
    """``{detector: n_sources}`` of an ingest manifest: its ``detectors`` when recorded, else counted from
    ``sources[].detector`` (manifests written before the ingest recorded ``detectors``)."""
    recorded = manifest.get("detectors")
    if isinstance(recorded, Mapping):
        return {str(k): int(v) for k, v in recorded.items() if int(v)}
    counts: dict[str, int] = {}
    for source in manifest.get("sources") or []:
        name = str(source.get("detector") or "unknown")
        counts[name] = counts.get(name, 0) + 1
    return counts


def detector_summary(counts: Mapping[str, int]) -> dict[str, Any]:
    """The card's ``data.detector``: ``{"name", "sources", "au_meaning"}`` from ``{detector: n_sources}``.

    ``name`` is the one py-feat detector of every source (``Detectorv2`` or ``MPDetector``), ``mixed`` when the
    sources come from more than one kind (a detector and another detector or layout), ``unknown`` when none is a
    py-feat detector export.
    """
    kinds = {k for k, n in counts.items() if n}
    detectors = kinds & set(DETECTORS)
    if len(detectors) == 1 and kinds == detectors:
        name = next(iter(detectors))
    elif detectors:
        name = "mixed"
    else:
        name = "unknown"
    return {"name": name, "sources": dict(counts), "au_meaning": AU_MEANING[name]}


def people_summary(counts: Mapping[str, Any], n_videos: int) -> dict[str, Any]:
    """The card's ``data.people``: py-feat's ``Identity`` labels where the tables have them (the ingest's
    ``identity_labels``), with what the number means."""
    labels = counts.get("identity_labels")
    if labels is None:
        note = f"unknown: the tables have no py-feat Identity column; {n_videos:,} video(s) may show one person or many"
    else:
        note = (
            f"{int(labels):,} distinct py-feat Identity label(s) among the kept face rows, summed over sources: py-feat "
            "labels identities per detection run, so one person in several files counts once per file (an upper "
            "bound on people), and its face clustering can also split or merge people"
        )
    return {"identity_labels": None if labels is None else int(labels), "note": note}


def data_support(summary: Mapping[str, Any]) -> dict[str, Any]:
    """What the training data supports, for the card's ``data`` (and, through ``training_metadata``, the NPZ's
    ``feature_p99`` / ``unsupported_features``: :func:`aumesh.model.release.release_arrays`): ``input_ranges``,
    ``unsupported_inputs``, ``detector`` and ``people``, from prepare's summary. A summary prepared before they were
    recorded gives no ranges, ``detector`` ``unknown`` and ``people`` unknown."""
    ranges = summary.get("input_ranges") or {}
    return {
        **({"input_ranges": ranges, "unsupported_inputs": unsupported_inputs(ranges)} if ranges else {}),
        "detector": summary.get("detector") or detector_summary({}),
        "people": people_summary(summary.get("counts") or {}, int(summary.get("n_videos", 0))),
    }


def feature_p99(input_ranges: Mapping[str, Mapping[str, Any]], columns: Sequence[str] = INPUT_COLUMNS) -> np.ndarray:
    """(len(columns),) float32 p99 of each input in ``columns`` order (default the 23
    :data:`~aumesh.core.schema.INPUT_COLUMNS`; a family's inputs for its release): the NPZ's ``feature_p99``,
    py-feat's name; NaN for an input the ranges lack."""
    return np.array([float(input_ranges[c]["p99"]) if c in input_ranges else np.nan for c in columns], np.float32)


# --------------------------------------------------------------------------------------------- inference side
@dataclass(frozen=True)
class Support:
    """What a release says its training data supports (:func:`release_support`).

    Attributes
    ----------
    upper : dict of str -> float
        Per AU, the largest value training saw (``max``; ``p99`` when only ``feature_p99`` is recorded).
    p99 : dict of str -> float
        Per AU, the training p99 (NaN when not recorded).
    bound : str
        ``"max"`` or ``"p99"``: what ``upper`` holds.
    unsupported : tuple of str
        AUs the data never expressed (:data:`UNSUPPORTED_P99`).
    detector : str or None
        The detector of the training tables (``data.detector.name``), None when not recorded.
    """

    upper: dict[str, float]
    p99: dict[str, float]
    bound: str
    unsupported: tuple[str, ...]
    detector: str | None


def training_metadata(release: Mapping[str, Any]) -> dict[str, Any]:
    """The release's ``training_metadata`` JSON as a dict (``{}`` when absent or not a JSON object)."""
    if "training_metadata" not in release:
        return {}
    try:
        meta = json.loads(str(np.asarray(release["training_metadata"])))
    except ValueError:
        return {}
    return meta if isinstance(meta, dict) else {}


def release_support(release: Mapping[str, Any]) -> Support | None:
    """What release arrays record of their training data's support; None when they record nothing (releases made
    before it was recorded: no ``feature_p99``, no ``data.input_ranges``), so nothing is checked.

    The ranges come from ``training_metadata``'s ``data.input_ranges`` (the card JSON) when present, else from the
    NPZ's ``feature_p99`` (py-feat's key); the unsupported AUs from ``unsupported_features``, else the card's
    ``data.unsupported_inputs``.
    """
    data = training_metadata(release).get("data") or {}
    ranges = data.get("input_ranges") if isinstance(data, Mapping) else None
    columns = [str(c) for c in np.asarray(release.get("input_columns", INPUT_COLUMNS)).tolist()]
    p99: dict[str, float] = {}
    upper: dict[str, float] = {}
    bound = "max"
    if isinstance(ranges, Mapping) and ranges:
        for name, record in ranges.items():
            p99[str(name)] = float(record.get("p99", np.nan))
            upper[str(name)] = float(record.get("max", np.nan))
    elif "feature_p99" in release:
        values = np.asarray(release["feature_p99"], dtype=np.float64).reshape(-1)
        p99 = {c: float(v) for c, v in zip(columns, values, strict=False)}
        upper, bound = dict(p99), "p99"
    if "unsupported_features" in release:
        unsupported = tuple(str(u) for u in np.asarray(release["unsupported_features"]).reshape(-1).tolist())
    else:
        unsupported = tuple(str(u) for u in (data.get("unsupported_inputs") or []))
    detector = (data.get("detector") or {}).get("name") if isinstance(data.get("detector"), Mapping) else None
    if not p99 and not unsupported and detector is None:
        return None
    return Support(upper, p99, bound, unsupported, detector)


def beyond_training(au: np.ndarray, au_names: Sequence[str], face: np.ndarray, support: Support) -> str | None:
    """One phrase on the AU values of ``au`` beyond what training saw, or None.

    Parameters
    ----------
    au : ndarray, shape (N, 20)
        AU values in ``au_names`` order (NaN on no-face rows).
    au_names : sequence of str, length 20
    face : ndarray of bool, shape (N,)
        The rows with a face (the others are not checked).
    support : Support

    Returns
    -------
    str or None
        Names each AU above its training max (``support.upper``, with a float32 slack) with the largest value given,
        the training max and p99, and the rows beyond; and each unsupported AU given above :data:`UNSUPPORTED_GIVEN`
        (py-feat's rule). None when every value is within.
    """
    largest, rows = au_extent(au, au_names, face, support)
    return beyond_phrase(largest, rows, au_names, support)


def au_extent(au: np.ndarray, au_names: Sequence[str], face: np.ndarray, support: Support) -> tuple[np.ndarray, int]:
    """What :func:`beyond_phrase` needs of a block of rows, summable over blocks (``np.maximum`` and ``+``): each AU's
    largest value over the face rows (shape (20,), ``-inf`` where there is none) and the number of face rows with an AU
    above its training max (``support.upper``, with a float32 slack)."""
    values = np.where(face[:, None], au, np.nan)
    largest = np.nanmax(values, axis=0, initial=-np.inf) if len(values) else np.full(len(au_names), -np.inf)
    rows = np.zeros(len(au), bool)
    for j, name in enumerate(au_names):
        limit = support.upper.get(name, np.nan)
        if np.isfinite(limit) and largest[j] > limit + _SLACK:
            rows |= face & (au[:, j] > limit + _SLACK)
    return largest, int(rows.sum())


def beyond_phrase(largest: np.ndarray, rows: int, au_names: Sequence[str], support: Support) -> str | None:
    """:func:`beyond_training`'s phrase from the AUs' largest values and the count of rows above a training max
    (:func:`au_extent`, over one call or summed over a streamed table's chunks), or None."""
    above = []
    for j, name in enumerate(au_names):
        limit = support.upper.get(name, np.nan)
        if np.isfinite(limit) and largest[j] > limit + _SLACK:
            p99 = support.p99.get(name, np.nan)
            detail = f"training max {limit:.3g}" if support.bound == "max" else f"training p99 {limit:.3g}"
            if support.bound == "max" and np.isfinite(p99):
                detail += f", p99 {p99:.3g}"
            above.append(f"{name} up to {largest[j]:.3g} ({detail})")
    never = [name for j, name in enumerate(au_names) if name in support.unsupported and largest[j] > UNSUPPORTED_GIVEN]
    parts = []
    if above:
        parts.append(
            f"aus: {', '.join(above)} beyond the training data ({rows} row(s)): the mesh there is an extrapolation"
        )
    if never:
        parts.append(
            f"{', '.join(never)} {'was' if len(never) == 1 else 'were'} never expressed in the training data "
            f"(p99 < {UNSUPPORTED_P99:g}; given above {UNSUPPORTED_GIVEN:g}): {'its field is' if len(never) == 1 else 'their fields are'} "
            f"not supported by data"
        )
    return "; ".join(parts) or None


def table_detector(columns: Sequence[str], where: str = "table") -> str | None:
    """The py-feat detector a table's columns come from (:func:`aumesh.data.pyfeat.layout`: Detectorv2's
    ``mesh_x_*`` or MPDetector's ``x_i/y_i/z_i``), None when the columns are not a detector's export (input columns
    only, the split layout, or a table the layout does not recognise)."""
    from aumesh.core.errors import TableError
    from aumesh.data import pyfeat

    try:
        found = pyfeat.layout(list(columns), where).detector
    except TableError:
        return None
    return found if found in DETECTORS else None


def detector_mismatch(table_detector: str | None, support: Support | None, what: str) -> str | None:
    """One line when a table's detector (``table_detector``, from its columns) is a py-feat detector other than the
    one the release was trained on, or None (either unknown, or the same)."""
    trained = None if support is None else support.detector
    if table_detector not in DETECTORS or trained not in DETECTORS or table_detector == trained:
        return None
    return (
        f"{what}: its columns are {table_detector}'s but the release was trained on {trained}'s AUs; the two AU "
        f"spaces differ ({table_detector}: {AU_MEANING[table_detector].split(' (')[0]}; {trained}: "
        f"{AU_MEANING[trained].split(' (')[0]}), so the meshes map one detector's numbers through the other's fields. "
        f"Fix: use a release trained on {table_detector} tables"
    )


__all__ = [
    "ACTIVE_AU",
    "AU_MEANING",
    "RANGE_QUANTILES",
    "UNSUPPORTED_GIVEN",
    "UNSUPPORTED_P99",
    "Support",
    "au_extent",
    "beyond_phrase",
    "beyond_training",
    "data_support",
    "detector_counts",
    "detector_mismatch",
    "detector_summary",
    "feature_p99",
    "people_summary",
    "range_record",
    "release_support",
    "table_detector",
    "training_metadata",
    "unsupported_inputs",
]
