"""The engine of the data passes: Dask, on the scheduler the ``compute`` config group names.

A pass maps a pure partition function over the partitions (``dask.bag``, one partition per bag
partition) and either gathers the small per-partition results in order or sums them in partition
order, a left fold (:func:`map_reduce`). The task graph depends only on the partitions, never on the
scheduler, so every scheduler sums in the same order.

``compute=local`` (default) runs the tasks on a thread per core of this machine (the partition
functions spend their time in NumPy, BLAS and Arrow, which release the GIL); ``synchronous`` runs
them one by one in the caller (debugging); ``processes`` on a local process pool; ``distributed``
on a running ``dask.distributed`` scheduler (``compute.address``), e.g. a SLURM cluster started
with ``dask-jobqueue`` (README, "Scale out").

Where a run executes is not what it computes: the environment's ``AUMESH_COMPUTE_<KEY>`` (``AUMESH_COMPUTE_ADDRESS=
tcp://host:8786`` alone selects the cluster) overrides the ``compute`` group of ``params.yaml``
(:func:`aumesh.pipeline.compute.settings.effective`), so ``dvc repro -f`` runs on a cluster without a change to a
tracked file. One cluster serves many workspaces: the stages hand their tasks absolute paths and per-run scratch
folders, and a probe on every worker checks, when the stage connects, that it reads the data and writes the output
folder at those paths and runs this stage's aumesh code (:func:`aumesh.pipeline.compute.probe.check_workers`; a worker
that joins later likewise, :class:`aumesh.pipeline.compute.probe.LateWorkers`). A scheduler that does not answer
within ``compute.connect_timeout`` (wall clock), or is lost mid-run, is one line
(:class:`aumesh.core.errors.ClusterError`, exit 2).

This module is the engine (the scheduler a run uses, the cluster's client) and the map helpers the passes call
(:func:`map_gather`, :func:`map_reduce`, :func:`local_map`, :func:`task_rows`): every import of ``dask`` and
``dask.distributed`` is here. The environment's settings are :mod:`aumesh.pipeline.compute.settings`, the workers'
probe :mod:`aumesh.pipeline.compute.probe`, the process's allocators and freed memory
:mod:`aumesh.pipeline.compute.memory`.
"""

from __future__ import annotations

import contextvars
import itertools
import logging
import os
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Any

from aumesh.config import ComputeConfig
from aumesh.core.blas import one_blas_thread
from aumesh.core.errors import ClusterError, UserError
from aumesh.pipeline.compute import memory as compute_memory
from aumesh.pipeline.compute.probe import check_workers, first_line
from aumesh.pipeline.compute.settings import effective, local_fix, source_of

log = logging.getLogger(__name__)

_BLAS_THREADS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
_ACTIVE: contextvars.ContextVar[ComputeConfig | None] = contextvars.ContextVar("aumesh_compute_engine", default=None)


def n_workers(cfg: ComputeConfig) -> int:
    """Worker threads/processes of a local scheduler (``compute.n_workers``, default every core)."""
    return int(cfg.n_workers or os.cpu_count() or 1)


@contextmanager
def engine(cfg: ComputeConfig, read: str | Path | None = None, write: str | Path | None = None) -> Iterator[None]:
    """Run the enclosed passes on ``cfg``'s scheduler (:func:`~aumesh.pipeline.compute.settings.effective`: the
    environment's settings over ``cfg``), with single-threaded BLAS in every worker.

    The partitions already use every core; a BLAS thread pool per task would only oversubscribe
    them (``dask.distributed`` workers set ``OPENBLAS_NUM_THREADS=1`` themselves).

    Parameters
    ----------
    cfg : ComputeConfig
    read, write : path, optional
        On a ``dask.distributed`` cluster, a file every worker must read (the data) and a folder every worker must
        write (the output's temporary folder), checked on each worker when the client connects
        (:func:`~aumesh.pipeline.compute.probe.check_workers`); absolute paths, as the tasks get them.

    Raises
    ------
    ClusterError
        No scheduler at the address, no worker or no probe's answer within ``compute.connect_timeout`` seconds (wall
        clock), a worker that runs other aumesh code or cannot read ``read`` or write ``write`` (when the stage
        connects, or when it joins later), the scheduler lost or a worker killed mid-run. One line; the outputs were being
        built in temporary folders, so outside DVC the previous ones stand (under ``dvc repro`` DVC removed them
        before the stage ran: the line after says how to get them back).
    """
    import dask

    cfg = effective(cfg)
    token = _ACTIVE.set(cfg)
    try:
        if cfg.scheduler == "threads":  # before the scheduler starts its threads
            compute_memory.limit_malloc_arenas(n_workers(cfg))
        with one_blas_thread():
            if cfg.scheduler == "distributed":
                yield from _distributed(cfg, dask, read, write)
            else:
                yield from _scheduler(cfg, dask)
    finally:
        _ACTIVE.reset(token)


def _connect(cfg: ComputeConfig, read: str | Path | None, write: str | Path | None):
    """A client of the scheduler at ``cfg.address`` with at least one worker, every worker probed
    (:func:`~aumesh.pipeline.compute.probe.check_workers`) and the later ones watched
    (:class:`~aumesh.pipeline.compute.probe.LateWorkers`), within ``compute.connect_timeout`` seconds of wall clock;
    or a :class:`ClusterError` naming the address, where it was set and the step that did not finish.

    The wall clock is a guard around all of it: ``distributed``'s own timeouts do not bound a peer that accepts the
    connection and then says nothing or something else (a silent TCP server, an HTTP server: the client waited for
    the scheduler's handshake forever, 11 min before it was stopped). So the steps run in a daemon thread that is
    abandoned when the time is up (whatever it made later is closed by it); an error of its own raised at that moment
    is waited for a moment, as it says the same or more. A closed port is told from a peer that is no scheduler
    (:func:`_listening`): ``distributed`` said "timed out" for both.
    """
    import threading

    from aumesh.pipeline.compute.probe import LateWorkers

    where = f"{source_of('address')}={cfg.address}"
    timeout = source_of("connect_timeout")
    deadline = time.monotonic() + cfg.connect_timeout
    lock = threading.Lock()
    box: dict[str, Any] = {"step": "connect"}
    done = threading.Event()

    def steps() -> None:
        made = None
        try:
            box["step"] = _listening(str(cfg.address), deadline)
            if box["step"] == "refused":
                raise ClusterError(_guard_line(cfg, "refused"))
            client = made = _client(cfg, where, timeout)
            box["step"] = "workers"
            _wait_for_a_worker(client, cfg, deadline)
            box["step"] = "probe"
            check_workers(client, read, write)
            late = LateWorkers(client, read, write)
            late.start()
            made = (client, late)
        except BaseException as err:
            with lock:
                box.setdefault("error", err)
        finally:
            with lock:
                abandoned = box.get("abandoned", False)
                if not abandoned and "error" not in box:
                    box["result"] = made
            if made is not None and (abandoned or "error" in box):
                _close(made[0] if isinstance(made, tuple) else made, quiet=True)
            done.set()

    threading.Thread(target=steps, name="aumesh-connect", daemon=True).start()
    try:
        done.wait(cfg.connect_timeout) or done.wait(_LATE_ERROR_WAIT)
    finally:  # decided under the lock: the thread either handed its result over or closes it itself
        with lock:
            if "result" not in box and "error" not in box:
                box["abandoned"] = True
    if "error" in box:
        raise box["error"]
    if "result" in box:
        return box["result"]
    raise ClusterError(_guard_line(cfg, box["step"]))


def _guard_line(cfg: ComputeConfig, step: str) -> str:
    """The line of a connection that did not get past ``step`` within ``compute.connect_timeout`` seconds: its
    address and timeout named where they were set (:func:`~aumesh.pipeline.compute.settings.source_of`)."""
    where, timeout = f"{source_of('address')}={cfg.address}", source_of("connect_timeout")
    start = "start one (`make cluster`, or `dask scheduler` and `dask worker ADDRESS`) or correct the address"
    what, hint, fix = {
        "refused": ("nothing listens there (every connection refused)", "the scheduler is not running there", start),
        "connect": (
            "no Dask scheduler answered there",
            "something else listens at that port, a Dask scheduler's is 8786 by default; or the scheduler is stuck",
            "correct the address (the scheduler prints it: `Scheduler at: tcp://...`)",
        ),
        "workers": (
            "the scheduler has no worker",
            "none joined",
            f"start workers (`dask worker {cfg.address}`, or `make cluster`)",
        ),
        "probe": ("the workers did not answer the probe", "see the workers' logs", "restart the workers"),
    }[step]
    return (
        f"{where}: {what} within {cfg.connect_timeout:g} s ({hint}). Fix: {fix}, or {local_fix()}; "
        f"{timeout} sets the wait."
    )


#: Seconds :func:`_connect` waits, after ``compute.connect_timeout``, for the connection's own error raised at that
#: moment (the steps end at the same deadline), which says the same or more than the guard.
_LATE_ERROR_WAIT = 0.25


def _listening(address: str, deadline: float) -> str:
    """Wait until something accepts TCP connections at ``address`` (``tcp://host:port``), as ``distributed`` would
    before it says it timed out, but knowing why: "connect" once it does, else (every connection refused until the
    deadline) "refused", which :func:`_connect`'s guard turns into its line. Other schemes, or an address this cannot
    parse, are left to ``distributed``."""
    import socket

    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        host, port = parse_host_port(location, default_port=8786)
    except Exception:
        return "connect"
    if scheme != "tcp":
        return "connect"
    while True:
        try:
            socket.create_connection((host, port), timeout=max(deadline - time.monotonic(), 0.01)).close()
            return "connect"
        except ConnectionRefusedError:
            if time.monotonic() >= deadline:
                return "refused"
            time.sleep(0.05)  # a scheduler still starting: as distributed, try again until the deadline
        except OSError:  # no such host, unreachable, timed out: distributed says which
            return "connect"


def _client(cfg: ComputeConfig, where: str, timeout: str):
    from distributed import Client

    try:
        return Client(cfg.address, timeout=cfg.connect_timeout, set_as_default=False)
    except Exception as err:  # OSError (timed out, refused), ValueError (no port), or a peer that is no scheduler
        raise ClusterError(
            f"{where}: cannot connect to a Dask scheduler there ({first_line(err)}). "
            f"Fix: start one (`make cluster`, or `dask scheduler` and `dask worker ADDRESS`) or correct "
            f"the address, or {local_fix()}; {timeout} sets the wait."
        ) from None


def _wait_for_a_worker(client, cfg: ComputeConfig, deadline: float) -> None:
    try:
        client.wait_for_workers(1, timeout=max(deadline - time.monotonic(), 0.001))
    except Exception:
        raise ClusterError(_guard_line(cfg, "workers")) from None


def _close(client, quiet: bool) -> None:
    """Close ``client``; ``quiet`` (the scheduler is gone): without ``distributed``'s traceback of its cancelled
    reconnection, which it logs as an error while it closes."""
    if quiet:  # every logger: distributed.client has a level of its own (distributed's logging config)
        logging.disable(logging.CRITICAL)
    try:
        client.close(timeout=5)
    except Exception:
        if not quiet:
            raise
    finally:
        if quiet:
            logging.disable(logging.NOTSET)


def _lost(err: BaseException, client) -> bool:
    """``err`` means the cluster, not the task, failed: the scheduler's connection lost (futures cancelled, a closed
    comm), or a worker killed by a task (:class:`distributed.scheduler.KilledWorker`)."""
    from concurrent.futures import CancelledError

    from distributed.comm import CommClosedError
    from distributed.scheduler import KilledWorker

    return isinstance(err, (CancelledError, CommClosedError, KilledWorker)) or client.status != "running"


def _distributed(cfg: ComputeConfig, dask, read: str | Path | None, write: str | Path | None) -> Iterator[None]:
    client, late = _connect(cfg, read, write)
    where = f"{source_of('address')}={cfg.address}"
    failed = False

    def get(*args, **kwargs):
        """The client's ``get``, then the late workers' check: no result of a worker that failed its probe lands."""
        result = client.get(*args, **kwargs)
        late.check()
        return result

    try:
        n = len(client.scheduler_info().get("workers", {}))
        log.info("compute: dask.distributed scheduler at %s (%d workers)", cfg.address, n)
        with dask.config.set(scheduler=get):
            yield
        late.check()  # a worker that joined with other code after the last computation: the run is refused alike
    except UserError:
        failed = client.status != "running"
        raise
    except Exception as err:
        late.check()  # the computation was cancelled because a late worker failed its probe: that line
        if not _lost(err, client):
            raise
        failed = True
        from distributed.scheduler import KilledWorker

        if isinstance(err, KilledWorker):
            raise ClusterError(
                f"{where}: a task ended its worker's process {dask.config.get('distributed.scheduler.allowed-failures', 3) + 1} "
                f"times ({first_line(err)}), likely its memory limit. Fix: see the workers' logs; give "
                "them more memory (`dask worker --memory-limit`) or lower data.chunk_rows and "
                f"compute.partition_rows.{_kept()}"
            ) from None
        raise ClusterError(
            f"{where}: lost the Dask scheduler during the run ({first_line(err)}). Fix: restart the "
            f"scheduler and its workers and run again, or {local_fix()}.{_kept()}"
        ) from None
    finally:
        if not failed:
            late.stop()
        _close(client, quiet=failed)


def _kept() -> str:
    """What a failed run leaves of the stage's previous outputs, as the end of its line: outside DVC they stand (the
    stages build their outputs in temporary folders and swap them in only when complete); under ``dvc repro``
    (``DVC_STAGE``) DVC removed them before it ran the stage, and ``aumesh``'s next line names them and the command
    that brings them back (:func:`aumesh.stages.common.removed_by_dvc`), so nothing is claimed here."""
    return "" if os.environ.get("DVC_STAGE") else " The previous outputs stand."


def _scheduler(cfg: ComputeConfig, dask) -> Iterator[None]:
    # the scheduler's function, not its name: given a name, dask first imports dask.distributed to look for a
    # client (0.2 s of every stage that runs a pass)
    settings: dict[str, Any] = {"scheduler": _local_get(cfg.scheduler)}
    if cfg.scheduler != "synchronous":
        settings["num_workers"] = n_workers(cfg)
    # a process pool's workers start fresh: single-threaded BLAS through their environment
    blas_env = {k: "1" for k in _BLAS_THREADS} if cfg.scheduler == "processes" else {}
    saved = {k: os.environ.get(k) for k in blas_env}
    os.environ.update(blas_env)
    pool = None
    try:
        if cfg.scheduler == "processes":
            pool = settings["pool"] = _process_pool(settings["num_workers"])
        with dask.config.set(settings):
            log.info(
                "compute: dask %s scheduler%s",
                cfg.scheduler,
                f", {settings['num_workers']} workers" if "num_workers" in settings else "",
            )
            yield
    except BaseException:
        if pool is not None:  # interrupted or failed: the queued tasks are not started, the running ones not awaited
            pool.shutdown(wait=False, cancel_futures=True)
            pool = None
        raise
    finally:
        if pool is not None:
            pool.shutdown()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _process_pool(workers: int):
    """One process pool for every pass of an :func:`engine`, as ``dask.multiprocessing`` would start it.

    Given no pool, ``dask.multiprocessing.get`` starts a fresh one for every pass, and each of its workers (spawned,
    Dask's default) imports NumPy, pyarrow and aumesh again: prepare's ~20 passes over 100k frames took 44 s on the
    process pool against 6 s on threads. Started here, after the single-threaded BLAS environment is set, which its
    workers inherit when they start on the first pass.
    """
    from concurrent.futures import ProcessPoolExecutor

    from dask.multiprocessing import get_context, initialize_worker_process

    return ProcessPoolExecutor(workers, mp_context=get_context(), initializer=initialize_worker_process)


def _local_get(scheduler: str) -> Callable:
    """Dask's ``get`` of a local scheduler (``synchronous``, ``threads``, ``processes``)."""
    if scheduler == "synchronous":
        from dask.local import get_sync

        return get_sync
    if scheduler == "threads":
        from dask.threaded import get

        return get
    if scheduler == "processes":
        from dask.multiprocessing import get as get_processes

        return get_processes
    raise ValueError(f"compute.scheduler={scheduler!r}: use synchronous, threads, processes or distributed")


def _current():
    """The active engine, or the default one (``compute=local``) for a caller outside :func:`engine`."""
    return nullcontext() if _ACTIVE.get() is not None else engine(ComputeConfig())


def task_rows(chunk_rows: int) -> int:
    """Rows a task streams at a time: ``data.chunk_rows`` shared by the tasks that run at once in one process
    (the local threads: every worker; a process pool or a cluster: one per process), so a stage's rows in
    flight, and its memory, are those of one ``chunk_rows`` chunk on any local scheduler."""
    cfg = _ACTIVE.get() or ComputeConfig()
    return max(1, chunk_rows // (n_workers(cfg) if cfg.scheduler == "threads" else 1))


@contextmanager
def _releasing_freed_memory() -> Iterator[None]:
    """Hand freed memory back to the operating system when a pass starts and ends
    (:func:`aumesh.pipeline.compute.memory.release_freed_memory`).

    At the end of a pass (and every :data:`TRIM_EVERY_TASKS` tasks of a long pass, :class:`_Task`), not after each
    task of a short pass: the tasks of a pass allocate alike, and a task that finds the previous task's freed pages in
    its arena reuses them, where pages returned after every task were faulted in again by the next (prepare's pass 3
    on 344k frames of parquet mesh columns: 1.3M page faults and 6.7 s of system time; at the pass's end: 0.4M and
    3.6 s, wall 0.87x, peak +30 MiB). With glibc's arenas capped at the workers
    (:func:`aumesh.pipeline.compute.memory.limit_malloc_arenas`) and Arrow on the same allocator
    (:func:`aumesh.pipeline.compute.memory.prefer_system_arrow_pool`), the reuse does
    not grow with the partitions: the peaks at 100k and 3.1M frames were 390 / 409 and 390 / 417 MiB in two runs.

    It trims the stage process, whose threads run the local passes. A local process pool's workers keep their freed
    pages for their next task; ``dask.distributed``'s nanny starts its workers with glibc's ``MALLOC_TRIM_THRESHOLD_``
    at 64 KiB (its ``distributed.nanny.pre-spawn-environ``), so they trim as they free.

    And when the pass starts: the stage's own work between two passes (prepare's GPA reference, cut and plans) frees
    memory the next pass's tasks would otherwise add to (prepare at 3.1M frames started its pass 2 with 42 MiB of it
    resident; with the return, the stage's peak fell 289 -> 274 MiB). Short passes too: it costs no measurable time
    (100k and 344k frames, side by side, 2 runs: 8.4 / 14.5 s either way) and lowers their peaks (243 -> 228 and
    256 -> 248 MiB).
    """
    compute_memory.release_freed_memory()
    try:
        yield
    finally:
        compute_memory.release_freed_memory()


def _bag(partitions: Sequence[Any]):
    """A bag of one partition per item, as ``dask.bag.from_sequence(items, npartitions=len(items))`` builds it but
    named by a fresh token: ``from_sequence`` tokenizes every item, which walked every field of every partition (the
    ingest's tasks of thousands of per-video CSV spans, each with its source's ~2,045 column names: ~2 ms a span)."""
    import uuid

    import dask.bag as db

    name = f"from_sequence-{uuid.uuid4().hex}"
    return db.Bag({(name, i): [item] for i, item in enumerate(partitions)}, name, len(partitions))


def _progress(desc: str):
    """A bar over the pass's finished tasks (tqdm's Dask callback), on a terminal only; local schedulers report
    their tasks to it, a ``dask.distributed`` cluster shows its own dashboard instead."""
    if not desc or not sys.stderr.isatty() or (_ACTIVE.get() or ComputeConfig()).scheduler == "distributed":
        return nullcontext()
    from tqdm.dask import TqdmCallback

    return TqdmCallback(desc=desc, unit="task", leave=False, dynamic_ncols=True)


def local_map(fn: Callable, items: Sequence[Any]) -> list:
    """``[fn(x) for x in items]`` on threads of this process, one per core (one by one under the ``synchronous``
    scheduler), results in order.

    For a few independent jobs on data already in memory (the model fits from statistics), whose inputs and results
    (fitted models) belong in the stage process whichever scheduler runs the data passes; NumPy and LAPACK run
    them outside the GIL.
    """
    cfg = _ACTIVE.get() or ComputeConfig()
    workers = 1 if cfg.scheduler == "synchronous" else min(len(items), n_workers(cfg))
    if workers <= 1:
        return [fn(x) for x in items]
    from concurrent.futures import ThreadPoolExecutor

    pool = ThreadPoolExecutor(workers, thread_name_prefix="aumesh-local")
    try:
        results = list(pool.map(fn, items))
    except BaseException:  # Ctrl-C, SIGTERM, DVC gone, an error: the queued jobs are not started, nor waited for
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()
    return results


#: Tasks a process runs between two returns of its freed memory to the system
#: (:func:`aumesh.pipeline.compute.memory.release_freed_memory`), in a pass of more than :data:`TRIM_AFTER_TASKS`
#: partitions, besides the return at each pass's end. Each task's freed buffers stay in glibc's arenas for the next
#: tasks to reuse, but the holes they leave are rarely the next task's sizes, so the resident pages crept up with the
#: tasks a pass ran: a pass of 96 partitions (3.1M frames) peaked 20-25 MiB higher than one of 4, all else equal.
#: Every 4 tasks: prepare's peak at 3.1M frames 305 -> 287 MiB, evaluate's 321 -> 298 and 326 -> 305 MiB, the same
#: wall time (single runs). After every task (the count is process-wide, so with 2 threads every 4 was every 2 tasks of
#: a thread): prepare at 3.1M 275-295 -> 261-271 MiB (4 runs each, alternating), the same wall time; the tasks of a
#: long pass are ~0.5-1 s, so faulting their working set in again costs them little.
TRIM_EVERY_TASKS = 1
#: Passes of at most this many partitions return freed memory at their end only: they creep little, and each return
#: costs the next tasks the page faults of their working set again (prepare at 344k frames in the columns layout,
#: 12 partitions whose tasks read ~400 MiB of Arrow buffers each: 1.043x wall with returns every 4 tasks, 4 pairs).
TRIM_AFTER_TASKS = 16
_TASKS_RUN = itertools.count(1)  # tasks this process has run (``next`` is atomic under the GIL)


class _Task:
    """A pass's partition function; in a pass of more than :data:`TRIM_AFTER_TASKS` partitions it returns freed
    memory every :data:`TRIM_EVERY_TASKS` tasks of this process (picklable: a process pool or a cluster worker counts
    its own tasks)."""

    def __init__(self, fn: Callable, n_partitions: int):
        self.fn, self.trims = fn, n_partitions > TRIM_AFTER_TASKS

    def __call__(self, item: Any) -> Any:
        try:
            return self.fn(item)
        finally:
            if self.trims and next(_TASKS_RUN) % TRIM_EVERY_TASKS == 0:
                compute_memory.release_freed_memory()


def map_gather(fn: Callable, partitions: Sequence[Any], desc: str = "") -> list:
    """``[fn(p) for p in partitions]`` on the current scheduler, results in partition order; ``desc`` names the
    progress bar."""
    if not partitions:
        return []
    with _current(), _progress(desc), _releasing_freed_memory():
        return _bag(partitions).map(_Task(fn, len(partitions))).compute()


def map_reduce(fn: Callable, combine: Callable[[Any, Any], Any], partitions: Sequence[Any], desc: str = "") -> Any:
    """``combine(...combine(combine(fn(p0), fn(p1)), fn(p2))..., fn(pn))``: the results summed in partition order, the
    same additions on every scheduler; ``desc`` names the progress bar.

    A left fold, one task per addition, rather than a tree: a result waits only for the running sum of the results
    before it, so the results held at once stay a few (4 with 2 workers, at 4 or 400 partitions) where a tree of pairs
    holds one per level (4 at 4 partitions, 9 at 96, 11 at 400): evaluate's are ~5 MB, so its statistics pass grew with
    the frames. The additions are cheap beside the partition functions, and the tasks still run as they are ready.
    """
    if not partitions:
        raise ValueError("map_reduce: no partitions")
    from dask import delayed

    parts = _bag(partitions).map(_Task(fn, len(partitions))).to_delayed()  # one list of one result per partition
    fold = delayed(_FoldInto(combine), pure=True)
    total = fold(None, parts[0])
    for part in parts[1:]:
        total = fold(total, part)
    with _current(), _progress(desc), _releasing_freed_memory():
        return total.compute()


class _FoldInto:
    """``combine`` the items of a partition's result list into a running total (None: none yet), as a picklable
    callable (a task of :func:`map_reduce`'s fold)."""

    def __init__(self, combine: Callable[[Any, Any], Any]):
        self.combine = combine

    def __call__(self, total: Any, items) -> Any:
        for item in items:
            total = item if total is None else self.combine(total, item)
        return total
