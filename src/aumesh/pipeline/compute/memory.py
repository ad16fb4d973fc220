"""The stage process's memory: which allocator Arrow uses, glibc's malloc arenas, and freed memory handed back.

The passes allocate and free a partition's buffers on worker threads, task after task; what keeps a stage's resident
memory flat in the partitions it streams is here: Arrow on the C library's allocator
(:func:`prefer_system_arrow_pool`), at most one glibc arena per worker (:func:`limit_malloc_arenas`) and freed pages
returned to the system (:func:`release_freed_memory`), which :mod:`aumesh.pipeline.compute` calls when a pass starts and
ends and every few tasks of a long pass. No-ops where the C library is not glibc.
"""

from __future__ import annotations

import functools
import os
import sys

#: Arrow's allocator, read once, when pyarrow first allocates (so it is set before pyarrow is imported).
ARROW_POOL_ENV = "ARROW_DEFAULT_MEMORY_POOL"


def prefer_system_arrow_pool() -> None:
    """Arrow's buffers from the C library's allocator rather than Arrow's bundled mimalloc, unless
    ``ARROW_DEFAULT_MEMORY_POOL`` is already set. The stage processes' entry point calls it (:func:`aumesh.cli.run`);
    a local process pool inherits it, a ``dask.distributed`` worker takes its own environment's (README, "Scale out").

    The passes allocate and free a partition's Arrow buffers on worker threads, task after task. mimalloc kept their
    pages resident with nothing allocated (its arena at the start of prepare's pass 3: 13 MiB at 100k frames, 35 MiB at
    3.1M, from /proc/self/smaps), so the stage's memory grew with the partitions; glibc's free pages go back to the
    system at each pass's end (:func:`release_freed_memory`). Prepare's peak at 3.1M frames: 475 -> 420 MiB.
    """
    os.environ.setdefault(ARROW_POOL_ENV, "system")


#: glibc's ``mallopt`` parameter of the most malloc arenas (``M_ARENA_MAX`` in malloc.h).
_M_ARENA_MAX = -8


def limit_malloc_arenas(n: int) -> bool:
    """At most ``n`` glibc malloc arenas for the threads that allocate from now on (process-wide, not undone: glibc
    fixes its limit the first time it needs one); False where the C library is not glibc.

    Every thread that allocates gets an arena of its own up to glibc's limit (8 per core), and each arena keeps the
    holes its freed partition arrays leave: with the threads scheduler (its workers, Arrow's and BLAS's pools)
    a stage's resident memory grew with the partitions it streamed, e.g. evaluate at 2.95M frames retained
    ~90 MiB after its statistics pass (~25 MiB at 1M) and peaked at 621 MiB; with one arena per worker 574 MiB.
    """
    libc = _libc()
    if libc is None or not hasattr(libc, "mallopt"):
        return False
    return bool(libc.mallopt(_M_ARENA_MAX, max(1, int(n))))


def release_freed_memory() -> None:
    """Return freed heap memory to the operating system (glibc's ``malloc_trim``, Arrow's pool); no-op elsewhere.

    Arrow's system pool's ``release_unused`` is ``malloc_trim(0)`` itself; another pool (mimalloc, jemalloc) has its
    own to release."""
    if "pyarrow" in sys.modules:
        pool = sys.modules["pyarrow"].default_memory_pool()
        if pool.backend_name != "system":
            pool.release_unused()
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)


@functools.lru_cache(maxsize=1)
def _libc():
    """glibc, for ``malloc_trim`` (as ``dask.distributed``'s ``trim_memory``), or None on another C library."""
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return None
    return libc if hasattr(libc, "malloc_trim") else None
