"""Exact quantiles of a partitioned vector (``aumesh.pipeline.quantiles``) against ``np.quantile`` of the whole.

Equality is bit for bit: the order statistics are the vector's own values and the interpolation is
NumPy's. Partitionings, ties, heavy tails and forced bin refinement (``max_gather=1``) are covered.
"""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest

from aumesh.config import ComputeConfig
from aumesh.pipeline import compute
from aumesh.pipeline.quantiles import exact_quantiles

PROBS = np.r_[np.linspace(0.0, 1.0, 101), 0.99, 0.05, 1e-9, 1 - 1e-9]


def _identity(part: np.ndarray) -> np.ndarray:
    return part


def _vectors(rng):
    n = 20_011
    yield "normal", rng.standard_normal(n)
    yield "ties", rng.integers(0, 5, n).astype(float)
    yield "heavy tail", np.exp(5 * rng.standard_normal(n))
    yield "half zeros", np.r_[np.zeros(n // 2), rng.random(n - n // 2)]
    yield "one value", np.full(17, 0.25)
    yield "one element", np.array([3.5])


@pytest.mark.parametrize("method", ["linear", "inverted_cdf"])
@pytest.mark.parametrize("max_gather", [1, 1 << 18])
def test_equals_numpy_quantile_of_the_whole(method, max_gather):
    rng = np.random.default_rng(0)
    # the default engine, entered once: outside one, each of the ~100 passes enters it (threadpoolctl's scan of the
    # loaded libraries, ~3 ms each); the last call below still runs outside it
    with compute.engine(ComputeConfig()):
        for name, x in _vectors(rng):
            ref = np.quantile(x, PROBS, method=method)
            for n_cuts in (0, 1, 6):
                parts = np.split(x, np.sort(rng.integers(0, len(x) + 1, n_cuts)))
                got = exact_quantiles(_identity, parts, PROBS, method, max_gather=max_gather)
                np.testing.assert_array_equal(got, ref, err_msg=f"{name}, {n_cuts} cuts")
    assert exact_quantiles(_identity, [np.arange(10.0)], 0.5) == np.quantile(np.arange(10.0), 0.5)


@pytest.mark.parametrize("scheduler", ["synchronous", "threads", "processes"])
def test_same_on_every_scheduler(scheduler):
    x = np.random.default_rng(1).standard_normal(5_000)
    parts = np.array_split(x, 7)
    with compute.engine(ComputeConfig(scheduler=scheduler, n_workers=2)):
        got = exact_quantiles(partial(np.multiply, 2.0), parts, [0.01, 0.5, 0.99], max_gather=10)
    np.testing.assert_array_equal(got, np.quantile(2.0 * x, [0.01, 0.5, 0.99]))


def test_refuses_bad_input():
    with pytest.raises(ValueError, match="NaN or inf"):
        exact_quantiles(_identity, [np.array([1.0, np.nan])], 0.5)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        exact_quantiles(_identity, [np.arange(3.0)], 1.5)
    with pytest.raises(ValueError, match="no values"):
        exact_quantiles(_identity, [np.array([])], 0.5)


def test_columns_in_the_same_passes_equal_numpy_quantile_of_each_column():
    """exact_column_quantiles: each column's np.quantile, bit for bit, the columns sharing the passes (ties, a
    constant column, a heavy tail and forced refinement side by side)."""
    from aumesh.pipeline.quantiles import exact_column_quantiles

    rng = np.random.default_rng(3)
    n = 5_003
    x = np.column_stack(
        [
            rng.standard_normal(n),
            rng.integers(0, 3, n).astype(float),
            np.full(n, 0.5),
            np.exp(4 * rng.standard_normal(n)),
        ]
    )
    parts = np.split(x, [0, 17, 2_000, 2_000, 4_500])  # empty partitions too
    for max_gather in (1, 1 << 18):
        got = exact_column_quantiles(_identity, parts, PROBS, max_gather=max_gather)
        np.testing.assert_array_equal(got, np.quantile(x, PROBS, axis=0).T)


def test_bin_of_is_the_binary_search_of_the_edges():
    """The histogram's arithmetic bin index equals searchsorted over the edges, on the edges themselves, their
    neighbours and random values, for wide, narrow and tiny intervals."""
    from aumesh.pipeline.quantiles import BINS, Interval, _bin_of

    rng = np.random.default_rng(5)
    for lo, hi in [(0.0, 1.0), (-3.7, 1e-3), (1.0, 1.0 + 1e-12), (0.0, 5e-324 * 8192), (-1e300, 1e300)]:
        iv = Interval(lo, hi, True)
        e = iv.edges()
        x = np.r_[e, np.nextafter(e, -np.inf), np.nextafter(e, np.inf), rng.uniform(lo, hi, 10_000)]
        x = x[(x >= lo) & (x <= hi)]
        expected = np.clip(np.searchsorted(e, x, side="right") - 1, 0, BINS - 1)
        np.testing.assert_array_equal(_bin_of(x, iv), expected, err_msg=f"[{lo}, {hi}]")
