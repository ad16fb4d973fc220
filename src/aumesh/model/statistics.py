"""One streaming pass, every configuration: per-fold statistics of the full design, and exact algebra
that turns them into the statistics of any feature subset, target and neutral.

Pass A reads the prepared meshes once and accumulates, for each cross-validation fold, the shifted
cross-products of the full 83-column design ``[20 AU | 3 pose | 60 pose x AU]`` with the absolute
aligned coordinates (``aumesh.model.cross_products.CrossProducts``), plus per-video sums of the design and of the
coordinates. Then, with no further pass:

* a feature subset (20 or 23 columns) is a sub-block of ``X'X`` and rows of ``X'Y``;
* the neutral-subtracted target ``y - n_v`` (``n_v`` the video's neutral mesh) follows from
  ``sum (x - a)(y - n_v)^T = S_xy - sum_v u_v d_v^T`` with ``u_v`` the video's shifted design sum
  and ``d_v = n_v - b`` its shifted neutral, and likewise for ``sum (y - n_v)`` and the squares;
* the displacement statistics ``(x - xbar_v, y - n_v)`` behind ``r2_displacement`` add the
  symmetric terms in ``e_v = xbar_v - a`` (``xbar_v`` the mean design row of the neutral frames);
  they are also the statistics of the ``within_neutral`` target;
* the ``within`` target (fixed effects: design and mesh demeaned per video) is the same algebra with
  each video's own means, ``d_v = w_v / c_v`` and ``e_v = u_v / c_v``; it reduces to
  ``X'X_w = X'X - sum_v c_v xbar_v xbar_v^T`` and likewise for ``X'Y`` and ``diag(Y'Y)``.
* with a second detector's AUs (``model/eiv=instruments``) the pass accumulates the augmented design ``[X | Z]``
  (:func:`augmented_design`, 166 columns), so each fold's within-video ``Z'X``, ``Z'Z``, ``Z'Y`` are the same algebra
  on :func:`augmented_index`'s columns (:func:`fold_within_statistics`; docs/method.md eq. 7).

So a sweep over targets, neutral methods and feature sets costs one pass over the meshes for R²
(and one prediction pass per configuration for MAE). Results equal explicit accumulation up to
float64 rounding (tests/test_statistics.py).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # annotations only: scipy.sparse is imported where it is used, not at import time
    import scipy.sparse

from aumesh.core.io import RowArray
from aumesh.core.schema import N_TARGETS, POSE_COLUMNS, TARGETS, feature_columns
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


@dataclass
class DesignStatistics:
    """Per-fold statistics of (the pass's design, absolute coordinates) and per-video sums, all shifted by (a, b).

    The pass's design is :attr:`columns` (:func:`design_union`: :data:`FULL_DESIGN` and the other designs a run needs,
    pose shared); with instruments the statistics' columns are :attr:`stat_columns` (``[FULL_DESIGN | its instrument
    copy | the rest of the union]``). A configuration's columns are selected by name (:meth:`index`).
    """

    folds: list[CrossProducts]  # shifts x_shift = a (p,), y_shift = b (1434,)
    video_fold: np.ndarray  # (n_videos,) fold of each video
    video_count: np.ndarray  # (n_videos,) frames per video
    video_sum_x: RowArray  # (n_videos, p)  sum over the video's frames of (x - a)
    video_sum_y: RowArray  # (n_videos, 1434) sum over the video's frames of (y - b)
    neutral_design: dict = field(default_factory=dict)  # neutral method -> (n_videos, p) mean design row of its frames
    # model/eiv=instruments: the second detector's AU columns; the statistics are then of the augmented design
    # [X | Z | rest] (FULL_DESIGN, the same design of the instrument AUs, then the union's other columns: augmented_index)
    instruments: tuple[str, ...] = ()
    columns: tuple[str, ...] = tuple(FULL_DESIGN)  # the union of the designs accumulated (design_union)

    @property
    def stat_columns(self) -> list[str]:
        """The statistics' columns in order: :attr:`columns`, with instruments their :data:`FULL_DESIGN` part
        followed by its instrument copy (named ``Z:<column>``) before the rest."""
        return stat_columns(self.columns, bool(self.instruments))

    def index(self, columns: Sequence[str]) -> np.ndarray:
        """Indices of the design columns ``columns`` in the statistics (by name)."""
        return column_index(self.stat_columns, columns)

    def augmented_index(self, columns: Sequence[str]) -> np.ndarray:
        """:func:`augmented_index` of ``columns`` in these statistics."""
        return augmented_index(columns, self.columns)

    @property
    def x_shift(self) -> np.ndarray:
        return self.folds[0].x_shift

    @property
    def y_shift(self) -> np.ndarray:
        return self.folds[0].y_shift


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


def fold_order(fold: np.ndarray, n_splits: int) -> tuple[np.ndarray | None, np.ndarray]:
    """A stable order grouping rows by fold (None when they already are) and each fold's ``[lo, hi)`` in it."""
    fold = np.asarray(fold)
    grouped = bool(np.all(fold[1:] >= fold[:-1])) if len(fold) else True
    order = None if grouped else np.argsort(fold, kind="stable")
    bounds = np.searchsorted(fold if grouped else fold[order], np.arange(n_splits + 1))
    return order, bounds


def video_indicator(video: np.ndarray) -> tuple[np.ndarray, scipy.sparse.csr_matrix]:
    """The chunk's distinct videos and a sparse (n_distinct, m) 0/1 matrix: per-video row sums as one product."""
    import scipy.sparse as sp  # here, not at import: scipy.sparse is slow to import

    videos, inverse = np.unique(video, return_inverse=True)
    m = len(video)
    return videos, sp.csr_matrix((np.ones(m), (inverse, np.arange(m))), shape=(len(videos), m))


def video_row_sums(video: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sums of ``rows`` per video, each video's rows added one after another in their order.

    The same float64 sums, bit for bit, as ``video_indicator(video)[1] @ rows`` (whose CSR product adds a
    row's entries in order), without building a sparse matrix: when each video's rows are consecutive (frames of a
    video are consecutive in the tables, and a fold-grouped block keeps them so) they are summed where they are,
    whatever the videos' order; others after a stable sort. ``np.add.reduceat`` is not used: it adds a segment
    pairwise, which rounds differently.

    Parameters
    ----------
    video : ndarray, shape (m,)
        The video of each row (any sortable labels).
    rows : ndarray, shape (m, n)

    Returns
    -------
    videos : ndarray, shape (n_distinct,)
        The distinct videos: in the order of their rows when each video's rows are consecutive, else sorted.
    sums : ndarray of float64, shape (n_distinct, n)
    counts : ndarray of int64, shape (n_distinct,)
    """
    if len(video) == 0:
        return video[:0], np.zeros((0, rows.shape[1])), np.zeros(0, np.int64)
    starts = np.flatnonzero(np.r_[True, video[1:] != video[:-1]])
    if len(np.unique(video[starts])) < len(starts):  # a video in several runs
        order = np.argsort(video, kind="stable")
        video, rows = video[order], rows[order]
        starts = np.flatnonzero(np.r_[True, video[1:] != video[:-1]])
    stops = np.r_[starts[1:], len(video)]
    sums = np.empty((len(starts), rows.shape[1]))
    for j, (lo, hi) in enumerate(zip(starts.tolist(), stops.tolist(), strict=True)):
        np.sum(rows[lo:hi], axis=0, out=sums[j])  # along the rows: one row after another from 0
    return video[starts], sums, (stops - starts).astype(np.int64)


class VideoSumStream:
    """Per-video sums of rows streamed in any number of blocks, in float64, held only while a video still has rows to
    come: a finished video's sum goes to ``done(video, sum, n_rows)`` (memory: the videos open in the current block,
    not one row per video of the partition).

    Each video's rows are added one after another in their order (:func:`video_row_sums` within a block, blocks in
    the order they are added): the same float64 sums, bit for bit, as a dense ``(n_videos, n)`` array that every
    block's per-video sums are added into.

    Parameters
    ----------
    video : ndarray, shape (m,)
        The video of every row that will be added (any sortable labels), to know when a video is finished.
    done : callable ``(video, sum, n_rows)``
        Called once per video, with ``sum`` of shape (n,), float64.
    """

    def __init__(self, video: np.ndarray, done):
        videos, counts = np.unique(video, return_counts=True)
        self.count = dict(zip(videos.tolist(), counts.tolist(), strict=True))
        self.remaining = dict(self.count)
        self.open: dict = {}
        self.done = done

    def add(self, video: np.ndarray, rows: np.ndarray) -> None:
        """Add ``rows`` (k, n) of videos ``video`` (k,)."""
        if len(video) == 0:
            return
        videos, sums, n_rows = video_row_sums(video, rows)
        for j, v in enumerate(videos.tolist()):
            acc = self.open.get(v)
            if acc is None:
                acc = self.open[v] = np.zeros(rows.shape[1])
            acc += sums[j]
            self.remaining[v] -= int(n_rows[j])
            if self.remaining[v] == 0:
                self.done(v, self.open.pop(v), self.count[v])


class DesignSums:
    """Per-fold sums of a pass over shifted rows: ``Y'[X_f | 1_f]``, ``X_f'X_f``, ``sum X_f`` and ``diag(Y_f'Y_f)``.

    Sums of disjoint row sets add (``+``), so partitions of the rows are summed in any grouping.
    """

    def __init__(self, p: int, q: int, n_splits: int, head: int | None = None):
        self.p, self.q, self.K = p, q, n_splits
        # the first ``head`` columns (the AU design, with instruments [X | Z]) are multiplied in GEMMs of their own, the
        # same as a pass of those columns alone: the AU model's statistics are the same bits whatever else the pass
        # accumulates (a GEMM's rounding may depend on its shape); the rest of the union in GEMMs after them
        self.head = p if head is None else head
        self.cross = np.zeros((n_splits, p + 1, q))  # per fold: [X_f | 1]'Y_f, X'Y and the column sums of Y
        self.squares = np.zeros((q, n_splits))  # per fold: diag(Y'Y)
        self.xtx = np.zeros((n_splits, p, p))
        self.sum_x = np.zeros((n_splits, p))
        self.n = np.zeros(n_splits, dtype=np.int64)

    def add(self, X: np.ndarray, Y: np.ndarray, fold: np.ndarray) -> None:
        """Add shifted rows ``X`` (m, p), ``Y`` (m, q) of folds ``fold`` (m,).

        Rows are grouped by fold (one stable reordering copy), so each fold costs one GEMM of its own
        rows, ``Y_f' [X_f | 1]``, instead of a GEMM of every row against every fold's zero-padded block.
        """
        K = self.K
        order, bounds = fold_order(fold, K)
        if order is not None:
            X, Y = X[order], Y[order]
        ones = np.ones((len(X), 1))
        for f in range(K):
            lo, hi = bounds[f], bounds[f + 1]
            if lo == hi:
                continue
            Xf, Yf = X[lo:hi], Y[lo:hi]
            h = self.head
            if h == self.p:
                # (p + 1, q): X_f'Y_f and the column sums of Y_f, a contiguous block per fold (adding into strided
                # column slices cost 30 % of the GEMM); [X|1]'Y runs ~15 % faster in OpenBLAS than Y'[X|1] on fold
                # blocks of ~170 rows x 84 (52 vs 45 GFLOP/s, one thread)
                self.cross[f] += np.hstack([Xf, ones[lo:hi]]).T @ Yf
                self.xtx[f] += Xf.T @ Xf
                self.sum_x[f] += Xf.sum(axis=0)
            else:  # the head's products exactly as above, then the rest's (rows of the same arrays)
                Xh, Xr = np.ascontiguousarray(Xf[:, :h]), np.ascontiguousarray(Xf[:, h:])
                head_cross = np.hstack([Xh, ones[lo:hi]]).T @ Yf
                self.cross[f, :h] += head_cross[:h]
                self.cross[f, self.p] += head_cross[h]
                self.cross[f, h : self.p] += Xr.T @ Yf
                self.xtx[f, :h, :h] += Xh.T @ Xh
                rest = Xr.T @ Xf  # (p - h, p): the rest against every column
                self.xtx[f, h:, :] += rest
                self.xtx[f, :h, h:] += rest[:, :h].T
                self.sum_x[f, :h] += Xh.sum(axis=0)
                self.sum_x[f, h:] += Xr.sum(axis=0)
            self.squares[:, f] += np.einsum("ij,ij->j", Yf, Yf)
            self.n[f] += hi - lo

    def __add__(self, other: DesignSums) -> DesignSums:
        out = DesignSums(self.p, self.q, self.K, self.head)
        for name in ("cross", "squares", "xtx", "sum_x", "n"):
            setattr(out, name, getattr(self, name) + getattr(other, name))
        return out

    def folds(self, a: np.ndarray, b: np.ndarray) -> list[CrossProducts]:
        """Each fold's :class:`CrossProducts`, shifted by ``(a, b)``."""
        K, p = self.K, self.p
        out = []
        for f in range(K):
            s = CrossProducts(p, self.q, x_shift=a, y_shift=b)
            s.n = int(self.n[f])
            s.sum_x = self.sum_x[f].copy()
            s.xtx = self.xtx[f].copy()
            s.xty = self.cross[f, :p].copy()
            s.sum_y = self.cross[f, p].copy()
            s.yty_diag = self.squares[:, f].copy()
            out.append(s)
        return out


def accumulate_design(
    au: np.ndarray,
    pose: np.ndarray,
    video_index: np.ndarray,
    n_videos: int,
    fold: np.ndarray,
    n_splits: int,
    mesh_chunks,
    instrument_au: np.ndarray | None = None,
    instruments: tuple[str, ...] = (),
    columns: Sequence[str] | None = None,
    inputs: np.ndarray | None = None,
) -> DesignStatistics:
    """Pass A over ``mesh_chunks`` (iterable of ``(rows, Y)``, ``Y`` float64 (m, 1434), may be overwritten).

    Parameters
    ----------
    au : ndarray (n, 20), pose : ndarray (n, 3)
        Design inputs of every prepared frame (model order).
    video_index : ndarray (n,) int
        Video of each frame, 0..n_videos-1.
    fold : ndarray (n,) int
        Cross-validation fold of each frame (all frames of a video in one fold).
    instrument_au : ndarray (n, 20), optional
        The second detector's AUs (``model/eiv=instruments``): the statistics are then of the augmented design
        ``[X | Z]`` (:func:`augmented_design`, 166 columns).
    instruments : tuple of str
        The names of ``instrument_au``'s columns (:func:`aumesh.core.schema.instrument_columns`), recorded.
    columns : sequence of str, optional
        The union of the designs to accumulate (:func:`design_union`; default :data:`FULL_DESIGN`).
    inputs : ndarray (n, k), optional
        The other families' inputs the union's columns beyond :data:`FULL_DESIGN` need, in :func:`extra_inputs`'
        order.
    """
    columns = list(FULL_DESIGN if columns is None else columns)
    names = extra_inputs(columns)
    head = head_width(columns, instrument_au is not None)
    p, q, K = len(columns) + (len(FULL_DESIGN) if instrument_au is not None else 0), N_TARGETS, n_splits
    video_sum_x = np.zeros((n_videos, p))
    video_sum_y = np.zeros((n_videos, q))
    sums = DesignSums(p, q, K, head)
    a = b = None
    for rows, Y in mesh_chunks:
        X = pass_design(
            au[rows],
            pose[rows],
            None if instrument_au is None else instrument_au[rows],
            columns,
            None if inputs is None else inputs[rows],
            names,
        )
        if a is None:  # one provisional shift for every fold, so fold statistics add and subtract
            a, b = X.mean(axis=0), Y.mean(axis=0)
        X -= a
        Y -= b
        videos, indicator = video_indicator(video_index[rows])
        video_sum_x[videos] += indicator @ X
        video_sum_y[videos] += indicator @ Y
        sums.add(X, Y, fold[rows])
    if a is None or b is None:
        raise ValueError("design_statistics: mesh_chunks yielded no rows")
    video_fold = np.full(n_videos, -1, dtype=np.int64)
    video_fold[video_index] = fold
    return DesignStatistics(
        folds=sums.folds(a, b),
        video_fold=video_fold,
        video_count=np.bincount(video_index, minlength=n_videos),
        video_sum_x=video_sum_x,
        video_sum_y=video_sum_y,
        instruments=() if instrument_au is None else tuple(instruments),
        columns=tuple(columns),
    )


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


@dataclass
class VideoMoments:
    """Sums over a set of videos of the terms that turn (x, y) statistics into neutral-relative ones.

    With ``c_v`` frames, ``u_v = sum (x - a)``, ``w_v = sum (y - b)`` per video, the shifted neutral
    ``d_v = n_v - b`` and the shifted neutral design row ``e_v = xbar_v - a``.
    """

    cd: np.ndarray  # (q,)   sum c_v d_v
    ud: np.ndarray  # (p, q) sum u_v d_v^T
    wd: np.ndarray  # (q,)   sum w_v * d_v
    cdd: np.ndarray  # (q,)  sum c_v d_v^2
    ce: np.ndarray  # (p,)   sum c_v e_v
    ue: np.ndarray  # (p, p) sum u_v e_v^T
    cee: np.ndarray  # (p, p) sum c_v e_v e_v^T
    ew: np.ndarray  # (p, q) sum e_v w_v^T
    ced: np.ndarray  # (p, q) sum c_v e_v d_v^T

    @classmethod
    def of(cls, count, sum_x, sum_y, d, e) -> VideoMoments:
        """Moments of a block of videos: count (k,), sum_x (k, p), sum_y (k, q), d (k, q), e (k, p)."""
        ce_rows = count[:, None] * e
        return cls(
            cd=count @ d,
            ud=sum_x.T @ d,
            wd=np.einsum("vj,vj->j", sum_y, d),
            cdd=np.einsum("v,vj,vj->j", count, d, d),
            ce=count @ e,
            ue=sum_x.T @ e,
            cee=e.T @ ce_rows,
            ew=e.T @ sum_y,
            ced=ce_rows.T @ d,
        )

    def __add__(self, other: VideoMoments) -> VideoMoments:
        return VideoMoments(**{k: getattr(self, k) + getattr(other, k) for k in self.__dataclass_fields__})


def neutral_subtracted(stats: CrossProducts, m: VideoMoments) -> CrossProducts:
    """Statistics of ``(x, y - n_v)`` from those of ``(x, y)``; unshifted in y (a small displacement already)."""
    out = CrossProducts(stats.n_features, stats.n_targets, x_shift=stats.x_shift, y_shift=np.zeros(stats.n_targets))
    out.n = stats.n
    out.sum_x = stats.sum_x.copy()
    out.xtx = stats.xtx.copy()
    out.sum_y = stats.sum_y - m.cd  # sum (y - b) - sum_v c_v d_v
    out.xty = stats.xty - m.ud  # sum (x - a)(y - b - d_v)^T
    out.yty_diag = stats.yty_diag - 2.0 * m.wd + m.cdd  # sum (y - b - d_v)^2
    return out


def displacement(stats: CrossProducts, m: VideoMoments) -> CrossProducts:
    """Statistics of ``(x - xbar_v, y - n_v)``: the AU-driven displacement from each video's neutral (unshifted)."""
    y_part = neutral_subtracted(stats, m)
    out = CrossProducts(
        stats.n_features, stats.n_targets, x_shift=np.zeros(stats.n_features), y_shift=np.zeros(stats.n_targets)
    )
    out.n = stats.n
    out.sum_x = stats.sum_x - m.ce
    out.xtx = stats.xtx - m.ue - m.ue.T + m.cee  # sum (x - a - e_v)(x - a - e_v)^T
    out.xty = y_part.xty - m.ew + m.ced  # sum (x - a - e_v)(y - b - d_v)^T
    out.sum_y = y_part.sum_y
    out.yty_diag = y_part.yty_diag
    return out


def _moments(
    design: DesignStatistics, idx: np.ndarray, videos: np.ndarray, d_of, e_of, video_block: int
) -> VideoMoments:
    """:class:`VideoMoments` of ``videos`` in blocks; ``d_of(v)`` (k, q) and ``e_of(v)`` (k, p) give the shifted centres."""
    moments = None
    for lo in range(0, len(videos), video_block):
        v = videos[lo : lo + video_block]
        block = VideoMoments.of(
            design.video_count[v].astype(np.float64),
            design.video_sum_x[v][:, idx],
            design.video_sum_y[v],
            d_of(v),
            e_of(v),
        )
        moments = block if moments is None else moments + block
    if moments is None:
        raise ValueError("video_moments: no videos")
    return moments


def configuration_statistics(
    design: DesignStatistics,
    columns: list[str],
    target: str,
    neutral: RowArray,
    neutral_design_full: np.ndarray,
    video_block: int = 256,
) -> tuple[list[CrossProducts], list[CrossProducts]]:
    """Per-fold (target, displacement) statistics of one configuration, from the design statistics
    (:func:`fold_configuration_statistics` of every fold, in order).

    Every target's fold statistics use only that fold's videos (a held-out video is demeaned by its
    own means), so training statistics are still the total minus the fold's.

    Parameters
    ----------
    columns : the configuration's design columns (a subset of the pass's union, selected by name)
    target : one of :data:`TARGETS`
    neutral : (n_videos, 1434) the videos' neutral meshes (absolute coordinates; float32 is fine)
    neutral_design_full : (n_videos, p) mean design row (the pass's columns) of each video's neutral frames
    video_block : videos per block of the correction sums (bounds the float64 temporaries: ~3 MiB an array
        at 256; a block of 2,048 cost the evaluate stage ~110 MiB at 30k videos but ~50 at 2.9k, so its memory grew
        with the frames until a fold held 2,048 videos)
    """
    per_fold = [
        fold_configuration_statistics(design, f, columns, target, neutral, neutral_design_full, video_block)
        for f in range(len(design.folds))
    ]
    return [t for t, _ in per_fold], [d for _, d in per_fold]


def fold_configuration_statistics(
    design: DesignStatistics,
    fold: int,
    columns: list[str],
    target: str,
    neutral: RowArray,
    neutral_design_full: np.ndarray,
    video_block: int = 256,
) -> tuple[CrossProducts, CrossProducts]:
    """Fold ``fold``'s (target, displacement) statistics (:func:`configuration_statistics`); the folds are independent,
    so a caller may compute them at once."""
    if target not in TARGETS:
        raise ValueError(f"preprocess.target={target!r}: use one of {', '.join(TARGETS)}")
    idx = design.index(columns)
    videos = np.flatnonzero(design.video_fold == fold)
    moments = _moments(
        design,
        idx,
        videos,
        lambda v: np.asarray(neutral[v], dtype=np.float64) - design.y_shift,
        lambda v: neutral_design_full[v][:, idx] - design.x_shift[idx],
        video_block,
    )
    sub = subset(design.folds[fold], idx)
    disp = displacement(sub, moments)
    if target == "absolute":
        return sub, disp
    if target == "neutral":
        return neutral_subtracted(sub, moments), disp
    if target == "within_neutral":
        return disp, disp
    return fold_within_statistics(design, fold, idx, video_block, videos, sub), disp


def fold_within_statistics(
    design: DesignStatistics,
    fold: int,
    idx: np.ndarray,
    video_block: int = 256,
    videos: np.ndarray | None = None,
    sub: CrossProducts | None = None,
) -> CrossProducts:
    """Fold ``fold``'s within-video statistics (design and mesh demeaned by each video's own means) of the design
    columns ``idx`` (indices into the statistics' columns: :data:`FULL_DESIGN`'s, or :func:`augmented_index`'s of the
    augmented design ``[X | Z]``); the ``within`` target's statistics (:func:`fold_configuration_statistics`).

    The fold's videos are demeaned by their own means, so the folds' statistics add: training is total - fold.
    ``videos`` (the fold's) and ``sub`` (``subset(design.folds[fold], idx)``) are reused when given.
    """
    if videos is None:
        videos = np.flatnonzero(design.video_fold == fold)
    if sub is None:
        sub = subset(design.folds[fold], idx)
    # each video's own means, d_v = w_v / c_v, e_v = u_v / c_v
    own = _moments(
        design,
        idx,
        videos,
        lambda v: design.video_sum_y[v] / _count(design, v),
        lambda v: design.video_sum_x[v][:, idx] / _count(design, v),
        video_block,
    )
    return displacement(sub, own)


def target_offsets(
    design: DesignStatistics, columns: list[str], target: str, neutral: RowArray, neutral_design_full: np.ndarray
) -> tuple[np.ndarray | None, RowArray | None]:
    """What each video's rows subtract in ``target``'s space: ``(x_offset, y_offset)``.

    Returns
    -------
    x_offset : ndarray (n_videos, p) or None
        Per-video design centre (``None``: the design is used as it is).
    y_offset : ndarray (n_videos, 1434) or None
        Per-video mesh centre (``neutral`` itself for the neutral targets, so their rows stay bit-identical).
    """
    x_kind, y_kind = TARGETS[target]
    idx = design.index(columns)
    every = np.arange(len(design.video_count))
    x_offset = y_offset = None
    if x_kind == "neutral":
        x_offset = neutral_design_full[:, idx]
    elif x_kind == "video_mean":
        x_offset = design.x_shift[idx] + design.video_sum_x[:, idx] / _count(design, every)
    if y_kind == "neutral":
        y_offset = neutral
    elif y_kind == "video_mean":
        y_offset = design.y_shift + design.video_sum_y / _count(design, every)
    return x_offset, y_offset


def within_statistics(design: DesignStatistics, columns: list[str], video_block: int = 256) -> CrossProducts:
    """Within-video statistics of ``columns`` with the mesh over every video (all folds): design and mesh demeaned per
    video (docs/method.md eq. 2), whatever the configuration's target.

    ``sum (x - xbar_v)(y - ybar_v)^T = S_xy - sum_v u_v w_v^T / c_v`` with the shifted per-video sums ``u_v``, ``w_v``
    (likewise ``X'X`` and ``diag(Y'Y)``); one ``(p, n_videos) @ (n_videos, 1434)`` product, in blocks of videos.
    The result is unshifted and centred (its sums are 0).
    """
    idx = design.index(columns)
    total = design.folds[0].copy()
    for fold in design.folds[1:]:
        total = total + fold
    sub = subset(total, idx)
    xtx, xty, yty = sub.xtx.copy(), sub.xty.copy(), sub.yty_diag.copy()
    videos = np.flatnonzero(design.video_count > 0)
    for lo in range(0, len(videos), video_block):
        v = videos[lo : lo + video_block]
        c = design.video_count[v].astype(np.float64)[:, None]
        u = design.video_sum_x[v][:, idx]
        w = np.asarray(design.video_sum_y[v], dtype=np.float64)
        xtx -= u.T @ (u / c)
        xty -= u.T @ (w / c)
        yty -= np.einsum("vj,vj->j", w, w / c)
    out = CrossProducts(len(idx), sub.n_targets, x_shift=np.zeros(len(idx)), y_shift=np.zeros(sub.n_targets))
    out.n = sub.n
    out.sum_x, out.sum_y = np.zeros(len(idx)), np.zeros(sub.n_targets)
    out.xtx, out.xty, out.yty_diag = 0.5 * (xtx + xtx.T), xty, np.maximum(yty, 0.0)
    return out


def pose_moments(design: DesignStatistics) -> tuple[np.ndarray, np.ndarray]:
    """``E[p]`` (3,) and ``E[p p^T]`` (3, 3) of the raw pose over every frame (radians, POSE_COLUMNS order): what the
    pose x AU columns' share of the detector's error depends on (``aumesh.model.eiv.design_error_covariance``)."""
    idx = design.index(POSE_COLUMNS)
    n = sum(f.n for f in design.folds)
    s = sum(f.sum_x[idx] for f in design.folds)
    ss = sum(f.xtx[np.ix_(idx, idx)] for f in design.folds)
    a = design.x_shift[idx]
    mean = a + s / n
    second = (ss + np.outer(a, s) + np.outer(s, a)) / n + np.outer(a, a)
    return mean, 0.5 * (second + second.T)


def _count(design: DesignStatistics, videos: np.ndarray) -> np.ndarray:
    """Frames of each of ``videos`` as a float64 column (k, 1), at least 1."""
    return np.maximum(design.video_count[videos], 1).astype(np.float64)[:, None]
