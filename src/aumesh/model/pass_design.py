"""The design one statistics pass accumulates: which columns (the union of the designs a run needs, by name) and how
their rows are built (issue 46: the AU design ``[20 AU | 3 pose | 60 pose x AU]`` first when any AU design is in the
run, bit for bit as a pass of it alone, then each other family's ``[inputs | pose | pose x input]`` columns not yet
listed, pose shared; with a second detector's AUs the instrument copy of the AU design: docs/method.md eq. 7).
:mod:`aumesh.model.statistics` accumulates and derives every configuration's statistics from these columns.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from aumesh.core.schema import POSE_COLUMNS, feature_columns
from aumesh.model.cross_products import CrossProducts
from aumesh.model.features import design_matrix

FULL_DESIGN = feature_columns(True, True)


#: Prefix of the instrument copy's column names in :attr:`DesignStatistics.stat_columns` (``model/eiv=instruments``)
INSTRUMENT_PREFIX = "Z:"


def design_union(feature_sets: Iterable[str]) -> list[str]:
    """The columns one statistics pass accumulates for the feature sets ``feature_sets`` (names of
    :data:`aumesh.core.families.FEATURE_SETS`): :data:`FULL_DESIGN` (the AU family's 83 columns) when any of them is an
    AU design (the AU model, its identification screen and instruments read the whole AU design), else the pose
    columns (the pose moments read them); then every other design's columns not yet listed, in the order of
    ``feature_sets``. The pose columns are shared (one copy); each configuration's columns are taken from the union by
    name (:meth:`DesignStatistics.index`).

    E.g. ``["au_pose_interactions", "blendshapes_pose_interactions", "emotions_pose_interactions"]`` -> 83 + 208 + 28
    = 319 columns; ``["blendshapes_pose_interactions"]`` -> 3 + 208.
    """
    from aumesh.core.families import FEATURE_SETS, feature_set_columns

    feature_sets = list(feature_sets)
    au = any(FEATURE_SETS[name][0] == "au" for name in feature_sets if name in FEATURE_SETS)
    out = list(FULL_DESIGN) if au else list(POSE_COLUMNS)
    seen = set(out)
    for name in feature_sets:
        for c in feature_set_columns(name):
            if c not in seen:
                seen.add(c)
                out.append(c)
    return out


def has_au_head(columns: Sequence[str]) -> bool:
    """The union starts with :data:`FULL_DESIGN` (:func:`design_union` of a run with an AU design)."""
    return list(columns[: len(FULL_DESIGN)]) == FULL_DESIGN


def head_width(columns: Sequence[str], instruments: bool) -> int:
    """Columns of a pass's statistics multiplied in GEMMs of their own (:class:`DesignSums`' head): the AU design (with
    ``instruments`` its instrument copy too) when the union starts with it, else the whole union."""
    if has_au_head(columns):
        return len(FULL_DESIGN) * (2 if instruments else 1)
    return len(columns)


def extra_inputs(columns: Sequence[str]) -> list[str]:
    """The raw input columns (of ``frames.parquet``) the union's columns beyond its AU head (:func:`has_au_head`) are
    made of: each plain column, and the input of each ``pose*input`` product, in order of appearance (pose excluded:
    always read)."""
    base = set(FULL_DESIGN) if has_au_head(columns) else set()
    out: list[str] = []
    for c in columns:
        if c in base:
            continue
        name = c.split("*", 1)[1] if "*" in c else c
        if name not in out and name not in POSE_COLUMNS:
            out.append(name)
    return out


def named_design(pose: np.ndarray, inputs: np.ndarray, names: Sequence[str], columns: Sequence[str]) -> np.ndarray:
    """Design columns by name: a plain column is an input (or a pose angle), ``"P*I"`` the product of pose angle ``P``
    and input ``I`` (pose-major interactions, :func:`aumesh.core.schema.interaction_columns`); the products are the
    same float64 multiplications as :func:`aumesh.model.features.design_matrix`'s.

    Parameters
    ----------
    pose : ndarray, shape (m, 3)
        Pitch, Yaw, Roll (radians).
    inputs : ndarray, shape (m, k)
        The inputs named ``names``.
    names : sequence of str, length k
    columns : sequence of str, length p

    Returns
    -------
    X : ndarray of float64, shape (m, p)
    """
    values = np.hstack([np.asarray(pose, dtype=np.float64), np.asarray(inputs, dtype=np.float64)])
    where = {name: j for j, name in enumerate([*POSE_COLUMNS, *names])}
    X = np.empty((len(values), len(columns)))
    plain = [j for j, c in enumerate(columns) if "*" not in c]
    products = [j for j, c in enumerate(columns) if "*" in c]
    if plain:
        X[:, plain] = values[:, [where[columns[j]] for j in plain]]
    if products:
        left = [where[columns[j].split("*", 1)[0]] for j in products]
        right = [where[columns[j].split("*", 1)[1]] for j in products]
        X[:, products] = values[:, left] * values[:, right]
    return X


def stat_columns(columns: Sequence[str], instruments: bool) -> list[str]:
    """The columns of a pass's statistics: ``columns`` (the union, :data:`FULL_DESIGN` first), and with
    ``instruments`` the instrument copy of :data:`FULL_DESIGN` (``Z:<column>``) right after it (docs/method.md eq. 7)."""
    columns = list(columns)
    if not instruments:
        return columns
    head = len(FULL_DESIGN)
    if columns[:head] != FULL_DESIGN:
        raise ValueError("stat_columns: the union must start with FULL_DESIGN (design_union)")
    return [*columns[:head], *(INSTRUMENT_PREFIX + c for c in FULL_DESIGN), *columns[head:]]


def column_index(available: Sequence[str], columns: Sequence[str]) -> np.ndarray:
    """Positions of ``columns`` in ``available`` (by name); a design column the pass did not accumulate is refused."""
    where = {c: j for j, c in enumerate(available)}
    missing = [c for c in columns if c not in where]
    if missing:
        raise ValueError(
            f"the design statistics hold no column {', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''}: "
            "the pass was accumulated for other feature sets (design_union of every configuration it serves)"
        )
    return np.array([where[c] for c in columns], dtype=np.int64)


def augmented_design(au: np.ndarray, pose: np.ndarray, instrument_au: np.ndarray | None) -> np.ndarray:
    """The full design of ``au`` (m, 20) and ``pose`` (m, 3), and with instruments (``instrument_au`` (m, 20), the
    second detector's AUs: ``model/eiv=instruments``) the augmented design ``[X | Z]`` (m, 166): ``Z`` the same design
    of the instrument AUs with the same pose (pose instruments itself, pose x AU is instrumented by pose x instrument
    AU; docs/method.md eq. 7)."""
    X = design_matrix(au, pose, True, True)
    if instrument_au is None:
        return X
    return np.hstack([X, design_matrix(instrument_au, pose, True, True)])


def pass_design(
    au: np.ndarray,
    pose: np.ndarray,
    instrument_au: np.ndarray | None,
    columns: Sequence[str],
    inputs: np.ndarray | None = None,
    names: Sequence[str] = (),
) -> np.ndarray:
    """The rows of a pass's design: :func:`augmented_design` (the AU family's, the same bits as a pass of it alone),
    then the union ``columns``' other columns (:func:`named_design` of the other families' ``inputs`` (m, k), named
    ``names``: :func:`extra_inputs`)."""
    if not has_au_head(columns):  # no AU design in the run: the other families' designs alone
        if instrument_au is not None:
            raise ValueError("pass_design: instruments are the AU design's; the union has no AU design")
        return named_design(pose, np.empty((len(pose), 0)) if inputs is None else inputs, names, columns)
    X = augmented_design(au, pose, instrument_au)
    rest = list(columns)[len(FULL_DESIGN) :]
    if not rest:
        return X
    if inputs is None:
        raise ValueError(f"pass_design: the union's columns {rest[:3]} ... need the inputs {list(names)[:3]} ...")
    return np.hstack([X, named_design(pose, inputs, names, rest)])


def augmented_index(columns: Sequence[str], union: Sequence[str] | None = None) -> np.ndarray:
    """Indices into the augmented design ``[X | Z | rest]`` (``FULL_DESIGN``, its instrument copy, then the union's
    other columns) of a configuration's columns and their instruments: ``[idx, 83 + idx]`` (docs/method.md eq. 7).

    ``Z = design_matrix(instrument AUs, pose, ...)`` of the same feature set, so an AU is instrumented by the second
    detector's reading of it, a pose angle by itself and pose x AU by pose x instrument AU: just identified. Only the
    AU family has instruments: ``columns`` are :data:`FULL_DESIGN`'s.
    """
    available = stat_columns(FULL_DESIGN if union is None else union, True)
    return np.r_[column_index(available, columns), column_index(available, [INSTRUMENT_PREFIX + c for c in columns])]


def subset(stats: CrossProducts, columns: np.ndarray) -> CrossProducts:
    """Statistics of a subset of the design's columns (exact: sub-blocks)."""
    out = CrossProducts(len(columns), stats.n_targets, x_shift=stats.x_shift[columns], y_shift=stats.y_shift)
    out.n = stats.n
    out.sum_x = stats.sum_x[columns].copy()
    out.sum_y = stats.sum_y.copy()
    out.xtx = stats.xtx[np.ix_(columns, columns)].copy()
    out.xty = stats.xty[columns].copy()
    out.yty_diag = stats.yty_diag.copy()
    return out
