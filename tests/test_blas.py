"""aumesh.core.blas.one_blas_thread: nested blocks share one threadpoolctl limit, restored by the outermost."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from aumesh.core import blas


def _blas_threads() -> set[int]:
    return {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}


@pytest.fixture
def two_blas_threads():
    """numpy's BLAS at 2 threads around the test (whatever the worker's environment set), as threadpoolctl sees it."""
    np.ones(1) @ np.ones(1)  # numpy's BLAS is loaded
    if not _blas_threads():
        pytest.skip("threadpoolctl finds no BLAS library")
    with threadpool_limits(limits=2, user_api="blas"):
        yield


def test_nested_blocks_hold_one_thread_until_the_outermost_ends(two_blas_threads, monkeypatch):
    import threadpoolctl

    calls = []
    monkeypatch.setattr(
        threadpoolctl, "threadpool_limits", lambda *a, **k: calls.append(k) or threadpool_limits(*a, **k)
    )
    assert _blas_threads() == {2}
    with blas.one_blas_thread():
        assert _blas_threads() == {1}
        with blas.one_blas_thread():
            assert _blas_threads() == {1}
        assert _blas_threads() == {1}, "an inner block's end lifted the outer block's limit"
    assert _blas_threads() == {2}, "the outermost block did not restore the previous limit"
    assert calls == [{"limits": 1, "user_api": "blas"}], "threadpoolctl asked again inside a block"


def test_blocks_on_worker_threads_inside_a_block_leave_its_limit(two_blas_threads):
    """As the fits run: the engine's block on the main thread, each fit's own block on a worker thread."""
    seen = []

    def fit():
        with blas.one_blas_thread():
            seen.append(_blas_threads())
        seen.append(_blas_threads())

    with blas.one_blas_thread():
        threads = [threading.Thread(target=fit) for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(10)
        assert seen == [{1}] * 8, "a worker's block ending lifted the limit of the block around it"
        assert _blas_threads() == {1}
    assert _blas_threads() == {2}
