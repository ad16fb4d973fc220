"""Single-threaded BLAS for a block of code: the statistics passes, the PLS fits and the engine that runs them.

The per-component PLS work is small (p x q) matrices, and on 2 cores shared with other work threaded OpenBLAS spends
its time waking and spinning threads (5-60x slower measured under load), so aumesh runs its BLAS on one thread and
uses the cores through its own workers instead.

The limit nests: the engine holds it around a pass, a configuration's fits hold it across their threads and each fit
holds it again, because :func:`aumesh.model.kernel_pls.fit_statistics` is also called on its own. Only the outermost
block calls threadpoolctl: a ``threadpool_limits`` inspects every shared library the process has loaded (about 3 ms
with pyarrow, pandas and MLflow imported), and a sweep's fits called it thousands of times. The limit is
process-wide (BLAS has one thread setting), so the blocks inside share it; numpy's BLAS, the one the fits use, is
loaded with numpy, before any block starts. Open the outermost block on the thread that starts the workers and keep
it open until they are joined: OpenBLAS (pthreads) ignored a thread count set from another thread here.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator

_lock = threading.Lock()
_depth = 0  # blocks open in this process, on any thread
_limits = None  # the outermost block's threadpoolctl limiter, restored when the last block closes


@contextlib.contextmanager
def one_blas_thread() -> Iterator[None]:
    """BLAS/LAPACK on one thread until the block ends (the outermost block's exit restores the previous limits)."""
    global _depth, _limits
    with _lock:
        if _depth == 0:
            from threadpoolctl import threadpool_limits

            _limits = threadpool_limits(limits=1, user_api="blas")
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0 and _limits is not None:
                _limits.restore_original_limits()
                _limits = None
