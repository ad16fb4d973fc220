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


def _range(values: Callable[[Any], np.ndarray], part: Any) -> tuple[int, float, float]:
    v = np.asarray(values(part), dtype=np.float64)
    if not np.isfinite(v).all():
        raise ValueError("exact_quantiles: the values hold NaN or inf (pass finite values only)")
    return (len(v), float(v.min()), float(v.max())) if len(v) else (0, np.inf, -np.inf)


def _merge_range(a, b):
    return a[0] + b[0], min(a[1], b[1]), max(a[2], b[2])


def _locate(v: np.ndarray, intervals: tuple[Interval, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The values of ``v`` inside the disjoint ``intervals``, grouped by interval: ``(values, bounds)``, interval ``i``'s
    values being ``values[bounds[i]:bounds[i + 1]]`` (in no particular order).

    One search of each value among the intervals' lower ends, not a mask of the whole vector per interval: the
    error curve asks for 1,001 quantiles, whose gather pass cost ~1,000 passes over every partition's values.
    """
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


def _histogram(values: Callable[[Any], np.ndarray], intervals: tuple[Interval, ...], part: Any) -> np.ndarray:
    """(len(intervals), BINS) counts of the partition's values in each interval's bins."""
    inside, bounds = _locate(np.asarray(values(part), dtype=np.float64), intervals)
    out = np.zeros((len(intervals), BINS), dtype=np.int64)
    for i, iv in enumerate(intervals):
        j = np.clip(np.searchsorted(iv.edges(), inside[bounds[i] : bounds[i + 1]], side="right") - 1, 0, BINS - 1)
        out[i] = np.bincount(j, minlength=BINS)
    return out


def _gather(values: Callable[[Any], np.ndarray], intervals: tuple[Interval, ...], part: Any) -> list[np.ndarray]:
    inside, bounds = _locate(np.asarray(values(part), dtype=np.float64), intervals)
    return [inside[bounds[i] : bounds[i + 1]] for i in range(len(intervals))]


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
    scalar = np.ndim(q) == 0
    qs = np.atleast_1d(np.asarray(q, dtype=np.float64))
    if ((qs < 0) | (qs > 1)).any():
        raise ValueError("exact_quantiles: probabilities must lie in [0, 1]")
    n, lo, hi = compute.map_reduce(partial(_range, values), _merge_range, partitions)
    if n == 0:
        raise NoValuesError("exact_quantiles: no values")
    previous, nxt, gamma = needed_ranks(n, qs, method)
    ranks = np.unique(np.r_[previous, nxt])
    found: dict[int, float] = {}
    # (interval, values of the whole vector below it, ranks inside it), refined until each is small enough
    pending = [(Interval(lo, hi, True), 0, ranks)]
    for depth in range(MAX_ROUNDS):
        intervals = tuple(iv for iv, _, _ in pending)
        counts = compute.map_reduce(partial(_histogram, values, intervals), np.add, partitions)
        small, refine = [], []
        for (iv, below, inside), c in zip(pending, counts, strict=True):
            edges, cum = iv.edges(), np.cumsum(c)
            bins = np.searchsorted(cum, inside - below, side="right")  # the bin of each rank
            for j in np.unique(bins):
                sub = iv.bin(int(j), edges)
                sub_below = below + (int(cum[j - 1]) if j else 0)
                sub_ranks = inside[bins == j]
                if sub.lo == sub.hi or (not sub.closed and np.nextafter(sub.lo, np.inf) >= sub.hi):
                    found.update({int(r): sub.lo for r in sub_ranks})  # the bin holds one representable value
                elif c[j] <= max_gather or depth == MAX_ROUNDS - 1:
                    small.append((sub, sub_below, sub_ranks))
                else:
                    refine.append((sub, sub_below, sub_ranks))
        if small:
            gathered = compute.map_gather(partial(_gather, values, tuple(iv for iv, _, _ in small)), partitions)
            for i, (_, below, inside) in enumerate(small):
                v = np.sort(np.concatenate([g[i] for g in gathered]))
                found.update({int(r): float(v[r - below]) for r in inside})
        pending = refine
        if not pending:
            break
    a = np.array([found[int(r)] for r in previous])
    b = np.array([found[int(r)] for r in nxt])
    result = a if method == "inverted_cdf" else _lerp(a, b, gamma)
    return float(result[0]) if scalar else result
