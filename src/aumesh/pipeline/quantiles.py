"""Exact quantiles of a vector held in partitions (on disk), never whole in one process.

``np.quantile`` needs the whole vector; a stage at tens of millions of frames must not gather it.
The quantile of ``n`` values only depends on the values at one or two ranks (order statistics), so:

1. a pass of counts and ranges gives ``n`` and ``[min, max]``; the ranks each quantile needs follow
   from ``n`` exactly as NumPy computes them;
2. a histogram pass (``BINS`` equal-width bins, counts summed over partitions) locates the bin of
   every needed rank; a bin still holding more than ``max_gather`` values is split again the same
   way, restricted to its interval;
3. the values of the needed bins are gathered (a few per bin on average) and sorted: the order
   statistics are read off at their rank minus the count below the bin.

The result equals ``np.quantile(np.concatenate(parts), q, method=method)`` bit for bit (tested),
whatever the partitioning: counts, bins and the gathered values do not depend on it. Memory is
``BINS`` counts plus the gathered bins, not ``n``. The passes run on the current Dask scheduler
(:mod:`aumesh.pipeline.compute`); ``values`` must be picklable (a module-level function or a
``functools.partial`` of one) for the process and distributed schedulers.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any, overload

import numpy as np

from aumesh.pipeline import compute

#: Bins of one histogram pass.
BINS = 4096
#: Histogram passes before a bin is gathered whatever its size (a bin narrows 4096-fold a pass: float64
#: resolution is reached in ~5).
MAX_ROUNDS = 8
METHODS = ("linear", "inverted_cdf")


@dataclass(frozen=True)
class Interval:
    """Values ``lo <= v < hi`` (``lo <= v <= hi`` when ``closed``)."""

    lo: float
    hi: float
    closed: bool

    def edges(self) -> np.ndarray:
        return np.linspace(self.lo, self.hi, BINS + 1)

    def bin(self, j: int, edges: np.ndarray) -> Interval:
        last = j == BINS - 1
        return Interval(float(edges[j]), float(self.hi if last else edges[j + 1]), self.closed if last else False)


def _columns(values: Callable[[Any], np.ndarray], part: Any) -> np.ndarray:
    """``values(part)`` as (m, k) float64 columns (a vector is one column)."""
    v = np.asarray(values(part), dtype=np.float64)
    return v[:, None] if v.ndim == 1 else v


def _range(
    values: Callable[[Any], np.ndarray], part: Any
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(n, min, max, count at min, count at max)`` of the partition's columns (each (k,))."""
    v = _columns(values, part)
    if not np.isfinite(v).all():
        raise ValueError("exact_quantiles: the values hold NaN or inf (pass finite values only)")
    if not len(v):
        none = np.zeros(v.shape[1], np.int64)
        return 0, np.full(v.shape[1], np.inf), np.full(v.shape[1], -np.inf), none, none
    lo, hi = v.min(axis=0), v.max(axis=0)
    return len(v), lo, hi, (v == lo).sum(axis=0), (v == hi).sum(axis=0)


def _merge_range(a, b):
    """Two partitions' :func:`_range`: the counts at the extremes follow the extreme that wins (summed on a tie)."""
    lo, hi = np.minimum(a[1], b[1]), np.maximum(a[2], b[2])
    at_lo = np.where(a[1] == lo, a[3], 0) + np.where(b[1] == lo, b[3], 0)
    at_hi = np.where(a[2] == hi, a[4], 0) + np.where(b[2] == hi, b[4], 0)
    return a[0] + b[0], lo, hi, at_lo, at_hi


def _locate(v: np.ndarray, intervals: tuple[Interval, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The values of ``v`` inside the disjoint ``intervals``, grouped by interval: ``(values, bounds)``, interval ``i``'s
    values being ``values[bounds[i]:bounds[i + 1]]`` (in no particular order).

    One search of each value among the intervals' lower ends, not a mask of the whole vector per interval: the
    error curve asks for 1,001 quantiles, whose gather pass cost ~1,000 passes over every partition's values.
    """
    if len(intervals) == 1:  # one interval (a column's first round): a mask, no search
        iv = intervals[0]
        inside = (v >= iv.lo) & ((v < iv.hi) | (iv.closed & (v == iv.hi)))
        return v[inside], np.array([0, int(inside.sum())])
    order = np.argsort([iv.lo for iv in intervals], kind="stable")
    lo = np.array([intervals[i].lo for i in order])
    hi = np.array([intervals[i].hi for i in order])
    closed = np.array([intervals[i].closed for i in order], dtype=bool)
    k = np.searchsorted(lo, v, side="right") - 1  # the interval of largest lower end <= v, if any
    candidate = k >= 0
    k, v = k[candidate], v[candidate]
    inside = (v < hi[k]) | (closed[k] & (v == hi[k]))
    which = order[k[inside]]  # back to the caller's numbering
    grouped = np.argsort(which, kind="stable")
    return v[inside][grouped], np.searchsorted(which[grouped], np.arange(len(intervals) + 1))


def _per_column(
    v: np.ndarray, intervals: tuple[tuple[int, Interval], ...]
) -> list[tuple[list[int], np.ndarray, np.ndarray]]:
    """For each column with intervals: (the intervals' positions in ``intervals``, :func:`_locate` of the column)."""
    out = []
    for column in sorted({c for c, _ in intervals}):
        mine = [i for i, (c, _) in enumerate(intervals) if c == column]
        out.append((mine, *_locate(v[:, column], tuple(intervals[i][1] for i in mine))))
    return out


def _bin_of(x: np.ndarray, iv: Interval) -> np.ndarray:
    """Each value's bin among ``iv.edges()``: ``clip(searchsorted(edges, x, side="right") - 1, 0, BINS - 1)``, the
    largest edge at or below it, exactly. Estimated by arithmetic, then corrected against the edges themselves (the
    estimate is off by at most one bin in float64), instead of a binary search of 4,097 edges for every value (most of
    the passes' time on 23 columns)."""
    edges = iv.edges()
    width = iv.hi - iv.lo
    scale = BINS / width if iv.hi > iv.lo else np.inf
    if not (np.isfinite(scale) and np.isfinite(width) and scale > 0):  # a point, or a width beyond float64
        return np.clip(np.searchsorted(edges, x, side="right") - 1, 0, BINS - 1)
    j = np.clip(((x - iv.lo) * scale).astype(np.int64), 0, BINS - 1)
    for _ in range(2):  # two corrections either way: bit for bit the search's answer even at a rounding tie
        j = np.clip(j - (x < edges[j]), 0, BINS - 1)
        j = j + ((j < BINS - 1) & (x >= edges[np.minimum(j + 1, BINS)]))
    return j


def _histogram(
    values: Callable[[Any], np.ndarray], intervals: tuple[tuple[int, Interval], ...], part: Any
) -> np.ndarray:
    """(len(intervals), BINS) counts of the partition's values of each ``(column, interval)`` in its bins."""
    out = np.zeros((len(intervals), BINS), dtype=np.int64)
    for mine, inside, bounds in _per_column(_columns(values, part), intervals):
        for j, i in enumerate(mine):
            iv = intervals[i][1]
            out[i] = np.bincount(_bin_of(inside[bounds[j] : bounds[j + 1]], iv), minlength=BINS)
    return out


def _gather(
    values: Callable[[Any], np.ndarray], intervals: tuple[tuple[int, Interval], ...], part: Any
) -> list[np.ndarray]:
    out: list[np.ndarray] = [np.empty(0)] * len(intervals)
    for mine, inside, bounds in _per_column(_columns(values, part), intervals):
        for j, i in enumerate(mine):
            out[i] = inside[bounds[j] : bounds[j + 1]]
    return out


def needed_ranks(n: int, q: np.ndarray, method: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ranks (0-based, in sorted order) each quantile reads, as NumPy's ``np.quantile`` computes them.

    Returns ``previous`` and ``next`` ranks (n_q,) and the interpolation weight ``gamma`` (n_q,)
    (``inverted_cdf``: ``previous == next``, ``gamma`` 0).
    """
    if method == "linear":  # NumPy: virtual index (n - 1) q, Hyndman & Fan's method 7
        virtual = (n - 1) * q
        previous = np.floor(virtual)
        nxt = previous + 1
        above = virtual >= n - 1
        previous[above], nxt[above] = n - 1, n - 1
        below = virtual < 0
        previous[below], nxt[below] = 0, 0
        gamma = virtual - np.floor(virtual)
        return previous.astype(np.int64), nxt.astype(np.int64), gamma
    if method == "inverted_cdf":  # NumPy: n q - 1, rounded up unless it is whole; clipped at 0
        index = n * q - 1
        previous = np.floor(index)
        rank = np.where(index - previous == 0, previous, previous + 1).astype(np.int64)
        rank = np.clip(rank, 0, n - 1)
        return rank, rank, np.zeros(len(q))
    raise ValueError(f"exact_quantiles: method {method!r} is not one of {METHODS}")


def _lerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    """NumPy's quantile interpolation, operation for operation (``numpy/lib/_function_base_impl.py: _lerp``)."""
    diff = b - a
    out = a + diff * t
    return np.where(t >= 0.5, b - diff * (1 - t), out)


class NoValuesError(ValueError):
    """The partitions hold no value, so no quantile exists."""


@overload
def exact_quantiles(
    values: Callable[[Any], np.ndarray], partitions: Sequence[Any], q: float, method: str = ..., max_gather: int = ...
) -> float: ...
@overload
def exact_quantiles(
    values: Callable[[Any], np.ndarray],
    partitions: Sequence[Any],
    q: np.ndarray,
    method: str = ...,
    max_gather: int = ...,
) -> np.ndarray: ...
def exact_quantiles(
    values: Callable[[Any], np.ndarray], partitions: Sequence[Any], q, method: str = "linear", max_gather: int = 1 << 18
) -> float | np.ndarray:
    """``np.quantile`` of the concatenated ``values(p)`` for ``p`` in ``partitions``, without concatenating them.

    Parameters
    ----------
    values : callable
        ``values(partition) -> ndarray (m,)`` of finite floats (read from disk, typically).
    partitions : sequence
        The partitions; their order and sizes do not change the result.
    q : float or array-like of shape (n_q,)
        Probabilities in [0, 1].
    method : {"linear", "inverted_cdf"}
        NumPy's method of the same name.
    max_gather : int
        Largest number of values gathered from one bin before it is split again.

    Returns
    -------
    float or ndarray of shape (n_q,)
        As ``np.quantile(np.concatenate([values(p) for p in partitions]), q, method=method)``.
    """
    result = exact_column_quantiles(
        values, partitions, np.atleast_1d(np.asarray(q, dtype=np.float64)), method, max_gather
    )
    return float(result[0, 0]) if np.ndim(q) == 0 else result[0]


def exact_column_quantiles(
    values: Callable[[Any], np.ndarray],
    partitions: Sequence[Any],
    q: Any,
    method: str = "linear",
    max_gather: int = 1 << 18,
) -> np.ndarray:
    """:func:`exact_quantiles` of each column of a partitioned table, in the same passes for every column.

    Parameters
    ----------
    values : callable
        ``values(partition) -> ndarray (m, k)`` of finite floats: the partition's rows of the ``k`` columns (a
        vector ``(m,)`` is one column).
    partitions, method, max_gather
        As :func:`exact_quantiles`.
    q : array-like of shape (n_q,)
        Probabilities in [0, 1].

    Returns
    -------
    ndarray of shape (k, n_q)
        Row ``c``: ``np.quantile(np.concatenate([values(p)[:, c] for p in partitions]), q, method=method)``, bit for
        bit. The passes (counts and ranges, histograms, gathers) serve every column at once: the cost of one column's
        quantiles, not ``k`` times it, in passes over the partitions.
    """
    qs = np.atleast_1d(np.asarray(q, dtype=np.float64))
    if ((qs < 0) | (qs > 1)).any():
        raise ValueError("exact_quantiles: probabilities must lie in [0, 1]")
    n, lo, hi, at_lo, at_hi = compute.map_reduce(partial(_range, values), _merge_range, partitions)
    if n == 0:
        raise NoValuesError("exact_quantiles: no values")
    previous, nxt, gamma = needed_ranks(n, qs, method)
    ranks = np.unique(np.r_[previous, nxt])
    k = len(lo)
    found: list[dict[int, float]] = [{} for _ in range(k)]
    # the ranks among the ties at a column's minimum or maximum are known from the counts (detectors' AUs clipped to
    # [0, 1] hold most of their frames at exactly 0: without this, the bin of the zeros was split round after round)
    pending = []  # (column, interval, values of the whole column below it, ranks inside it), refined until small
    for c in range(k):
        low, high = ranks < at_lo[c], ranks >= n - at_hi[c]
        found[c].update({int(r): float(lo[c]) for r in ranks[low]})
        found[c].update({int(r): float(hi[c]) for r in ranks[high & ~low]})
        if (~low & ~high).any():
            pending.append((c, Interval(float(lo[c]), float(hi[c]), True), 0, ranks[~low & ~high]))
    for depth in range(MAX_ROUNDS):
        if not pending:
            break
        intervals = tuple((c, iv) for c, iv, _, _ in pending)
        counts = compute.map_reduce(partial(_histogram, values, intervals), np.add, partitions)
        small, refine = [], []
        for (c, iv, below, inside), cnt in zip(pending, counts, strict=True):
            edges, cum = iv.edges(), np.cumsum(cnt)
            bins = np.searchsorted(cum, inside - below, side="right")  # the bin of each rank
            for j in np.unique(bins):
                sub = iv.bin(int(j), edges)
                sub_below = below + (int(cum[j - 1]) if j else 0)
                sub_ranks = inside[bins == j]
                if sub.lo == sub.hi or (not sub.closed and np.nextafter(sub.lo, np.inf) >= sub.hi):
                    found[c].update({int(r): sub.lo for r in sub_ranks})  # the bin holds one representable value
                elif cnt[j] <= max_gather or depth == MAX_ROUNDS - 1:
                    small.append((c, sub, sub_below, sub_ranks))
                else:
                    refine.append((c, sub, sub_below, sub_ranks))
        if small:
            gathered = compute.map_gather(partial(_gather, values, tuple((c, iv) for c, iv, _, _ in small)), partitions)
            for i, (c, _, below, inside) in enumerate(small):
                v = np.sort(np.concatenate([g[i] for g in gathered]))
                found[c].update({int(r): float(v[r - below]) for r in inside})
        pending = refine
        if not pending:
            break
    out = np.empty((k, len(qs)))
    for c in range(k):
        a = np.array([found[c][int(r)] for r in previous])
        b = np.array([found[c][int(r)] for r in nxt])
        out[c] = a if method == "inverted_cdf" else _lerp(a, b, gamma)
    return out
