"""A family release's record (issue 46, contract item 3): ``model_card.json`` of a family fit, what its training data
supports (each input's range over the prepared frames) and the promotion that chose it.

The AU release's card (:func:`aumesh.pipeline.release.build_card`) is built from the same files (the family's fit
folder ``build/families/<family>/`` holds exactly the files of ``build/model/``) and then told what differs: the
family's inputs, their ranges (prepare records the 23 AU/pose inputs' ranges in ``summary.json``; the family's are
read here from ``frames.parquet``'s family columns, exactly as prepare reads the AUs': the same quantiles,
:func:`aumesh.pipeline.quantiles.exact_column_quantiles`, a row group at a time, never the frames gathered), its
design, and its own promotion (``promotion.json``'s ``"families": {<family>: {...}}``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.config import Config
from aumesh.core.errors import MissingFileError, TableError
from aumesh.core.families import FAMILIES, FEATURE_SETS, PYFEAT_FEATURE
from aumesh.model import family_release, support
from aumesh.pipeline.prepared_files import FRAMES_FILE

#: the one-line fix when the prepared frames lack a family's columns
NO_FAMILY_FIX = (
    "export the tables with py-feat's Detectorv2 or MPDetector (both write the 52 blendshapes and the emotions) and "
    "`dvc repro -f prepare`, or drop the family from conf/families"
)


def family_fit_dir(cfg: Config, family: str) -> Path:
    """``paths.families_model_dir/<family>``: the evaluate stage's fit of ``family`` (the files of ``build/model/``)."""
    return Path(cfg.paths.families_model_dir) / family


def family_release_dir(cfg: Config, family: str) -> Path:
    """``paths.families_release_dir/<family>``: the family's release (``releases/<family>/``)."""
    return Path(cfg.paths.families_release_dir) / family


def family_promotion(promotion_file: str | Path, family: str) -> dict | None:
    """``promotion.json``'s ``families.<family>`` record (what ``aumesh promote --family`` writes), None when the file,
    its ``families`` or the family's entry is absent (the family's configuration is then conf/'s own)."""
    path = Path(promotion_file)
    if not path.exists():
        return None
    try:
        record = json.loads(path.read_text())
    except ValueError as err:
        raise TableError(f"{path}: not readable JSON ({err}). Fix: `git checkout {path}` or `aumesh promote`") from None
    families = record.get("families") if isinstance(record, dict) else None
    entry = families.get(family) if isinstance(families, dict) else None
    return entry or None


def _row_group_values(part: tuple[str, int, tuple[str, ...]]) -> np.ndarray:
    """(m, k) float64 of one row group's family columns (``part`` = (frames.parquet, row group, columns)); a
    non-finite value is a one-line error naming the file and column."""
    import pyarrow.parquet as pq

    path, group, columns = part
    table = pq.ParquetFile(path).read_row_group(group, columns=list(columns))
    values = np.column_stack([table.column(c).to_numpy(zero_copy_only=False) for c in columns]).astype(np.float64)
    bad = ~np.isfinite(values).all(axis=0)
    if bad.any():
        raise TableError(
            f"{path}: column {columns[int(np.argmax(bad))]!r} holds NaN or inf in row group {group}. "
            f"Fix: `dvc repro -f prepare` (prepare keeps finite family inputs only)"
        )
    return values.reshape(table.num_rows, len(columns))


def _active(part: tuple[str, int, tuple[str, ...]]) -> np.ndarray:
    """(k + 1,) int64: the row group's frames with each input above :data:`aumesh.model.support.ACTIVE_AU`, then its
    frames."""
    v = _row_group_values(part)
    return np.array([*(v > support.ACTIVE_AU).sum(axis=0), len(v)], np.int64)


def _sum_range(part: tuple[str, int, tuple[str, ...]]) -> np.ndarray:
    """(2,) float64: the smallest and largest sum of the family's inputs over one row group's frames."""
    total = _row_group_values(part).sum(axis=1)
    return np.array([total.min(), total.max()]) if len(total) else np.array([np.inf, -np.inf])


def input_sum_range(prepared_dir: str | Path, family: str) -> dict[str, float]:
    """The smallest and largest per-frame sum of ``family``'s inputs over the training frames.

    A family whose inputs sum to the same value in every frame (py-feat's emotions: a softmax, so 1) has a design of
    lower rank than its width: the intercept is the sum of the inputs' columns (and each pose column the sum of its
    pose x input columns), so only differences between the inputs' fields are identified
    (:func:`aumesh.card.limits.release_warnings`' ``inputs_sum_constant``).

    Returns
    -------
    dict
        ``{"min": float, "max": float}``.
    """
    from aumesh.pipeline import compute

    path = Path(prepared_dir) / FRAMES_FILE
    parts = [(str(path), g, tuple(FAMILIES[family])) for g in range(pq_row_groups(path))]
    lo_hi = compute.map_reduce(_sum_range, lambda a, b: np.array([min(a[0], b[0]), max(a[1], b[1])]), parts)
    return {"min": float(lo_hi[0]), "max": float(lo_hi[1])}


#: Correlation over the training frames from which a Left/Right pair's two inputs count as moving together: the fit
#: then cannot tell their sides apart (tables writing one value on both sides), so the direction check's side verdict
#: of the pair is doubtful, not failed
TOGETHER_CORRELATION = 0.95


def _pair_sums(part: tuple[str, int, tuple[str, ...]]) -> np.ndarray:
    """(2 + 2k + k,) float64 per row group of the (Left, Right) columns: n, sums, sums of squares, cross sums."""
    v = _row_group_values(part)
    left, right = v[:, 0::2], v[:, 1::2]
    return np.concatenate([[len(v)], v.sum(axis=0), (v**2).sum(axis=0), (left * right).sum(axis=0)])


def sides_together(prepared_dir: str | Path, family: str) -> list[str]:
    """The blendshape Left/Right pairs (``"<stem>Left/Right"``) whose two inputs' correlation over the training
    frames is at least :data:`TOGETHER_CORRELATION` (or that never vary): the fit
    cannot tell their sides apart (the direction check then leaves their side doubtful). ``[]`` for the emotions."""
    from aumesh.pipeline import compute

    names = FAMILIES[family]
    stems = [n[: -len("Left")] for n in names if n.endswith("Left") and n[: -len("Left")] + "Right" in names]
    if not stems:
        return []
    columns = tuple(c for stem in stems for c in (stem + "Left", stem + "Right"))
    path = Path(prepared_dir) / FRAMES_FILE
    parts = [(str(path), g, columns) for g in range(pq_row_groups(path))]
    total = compute.map_reduce(_pair_sums, np.add, parts)
    k = len(columns)
    n, sums, squares, cross = total[0], total[1 : 1 + k], total[1 + k : 1 + 2 * k], total[1 + 2 * k :]
    mean = sums / max(n, 1.0)
    var = np.maximum(squares / max(n, 1.0) - mean**2, 0.0)
    cov = cross / max(n, 1.0) - mean[0::2] * mean[1::2]
    sd = np.sqrt(var[0::2] * var[1::2])
    corr = np.where(sd > 0, cov / np.where(sd > 0, sd, 1.0), 1.0)
    return [f"{stem}Left/Right" for stem, r in zip(stems, corr, strict=True) if r >= TOGETHER_CORRELATION]


def pq_row_groups(path: Path) -> int:
    """Row groups of the parquet file ``path``."""
    import pyarrow.parquet as pq

    return pq.ParquetFile(path).num_row_groups


def training_ranges(prepared_dir: str | Path, family: str) -> dict[str, dict[str, float | None]]:
    """Each of ``family``'s inputs' range record over the training frames (``frames.parquet``: the frames every fit
    uses), as prepare records the AUs' (:func:`aumesh.pipeline.prepare.summary.input_ranges`).

    Returns
    -------
    dict
        ``{name: {"min", "p1", "p50", "p99", "max", "active_fraction"}}`` in the family's order.

    Raises
    ------
    MissingFileError
        No ``frames.parquet``.
    TableError
        One line naming ``frames.parquet`` and the first family column it lacks (contract item 1: a family absent from
        the tables is absent from ``frames.parquet``) or that holds a non-finite value.
    """
    import pyarrow.parquet as pq

    from aumesh.pipeline import compute
    from aumesh.pipeline.quantiles import exact_column_quantiles

    path = Path(prepared_dir) / FRAMES_FILE
    if not path.exists():
        raise MissingFileError(f"{path}: not found. Fix: run the prepare stage first (`dvc repro prepare`).")
    columns = FAMILIES[family]
    names = set(pq.read_schema(path).names)
    missing = [c for c in columns if c not in names]
    if missing:
        raise TableError(
            f"{path}: no column {missing[0]!r} ({len(missing)} of the {len(columns)} {family} inputs missing): the "
            f"tables have no {family}. Fix: {NO_FAMILY_FIX}"
        )
    groups = pq.ParquetFile(path).num_row_groups
    parts = [(str(path), g, tuple(columns)) for g in range(groups)]
    if not parts:
        raise TableError(f"{path}: no frames. Fix: `dvc repro -f prepare`")
    q = np.array(list(support.RANGE_QUANTILES.values()))
    counts = compute.map_reduce(_active, np.add, parts)
    quantiles = exact_column_quantiles(_row_group_values, parts, q)
    return family_release.input_ranges(quantiles, counts[:-1], int(counts[-1]), columns)


def build_family_card(
    cfg: Config,
    family: str,
    fit_dir: Path,
    prepared_dir: Path,
    promotion: dict | None,
    ranges: dict[str, dict[str, Any]],
    n_components: int,
    design: list[str],
) -> dict:
    """``model_card.json`` of a family release: the AU card's record (:func:`aumesh.pipeline.release.build_card`: CV,
    data counts, digest, config, provenance, MLflow runs, libraries) of the family's fit folder, with the family's own
    inputs, ranges, unsupported inputs, design and promotion.

    Parameters
    ----------
    fit_dir : Path
        ``build/families/<family>/`` (``metrics.json``, ``tracking.json``).
    ranges : dict
        :func:`training_ranges`.
    n_components, design
        The fit's PLS components and design columns (``model.npz``).
    """
    from aumesh.pipeline.release import build_card

    card = build_card(cfg, fit_dir, prepared_dir, promotion)
    spec = dict(cfg.families.items())[family] if family in dict(cfg.families.items()) else None
    features = spec.features if spec is not None else None
    inputs = list(FAMILIES[family])
    _, pose, interactions = FEATURE_SETS[features] if features in FEATURE_SETS else (family, False, False)
    card["name"] = f"{family} -> MediaPipe mesh PLS (aumesh; py-feat's {PYFEAT_FEATURE[family][0]} model format)"
    card["family"] = {
        "name": family,
        "pyfeat_feature": PYFEAT_FEATURE[family][0],
        "npz": family_release.npz_name(family),
        "features": features,
        "n_components_config": None if spec is None else spec.n_components,
        "inputs": inputs,
        "pose": pose,
        "interactions": interactions,
        "design": design,
    }
    card["model"]["n_components"] = int(n_components)
    card["model"]["n_features"] = len(design)
    data = card["data"]
    # the family's inputs replace the AUs' in what the data supports (the AU/pose ranges stay in prepare's summary)
    data["input_ranges"] = ranges
    data["unsupported_inputs"] = support.unsupported_inputs(ranges, inputs)
    p99 = {n: r["p99"] for n, r in ranges.items()}
    expressed = {n: v for n, v in p99.items() if n not in data["unsupported_inputs"]}
    data["p99_range"] = {
        "min": min(p99.values()),
        "max": max(p99.values()),
        "min_expressed": min(expressed.values()) if expressed else None,
        "rule": f"unsupported: training p99 < {support.UNSUPPORTED_P99:g} (py-feat's unsupported_features)",
    }
    # the AU identification screen is about AUs: no family has one
    card.pop("au_identification", None)
    card["cv"].pop("au_identification", None)
    return card
