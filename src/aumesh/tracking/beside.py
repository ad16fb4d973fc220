"""The helper process that holds the evaluate stage's MLflow run beside the passes (:func:`tracked_run_beside`).

The stage process never imports MLflow: one forked worker imports it, opens the run (as
:func:`aumesh.tracking.runs.tracked_run` does) and runs the stage's logging calls, queued in order, while the stage
computes. The helper ignores the signals a terminal sends the whole process group (the stage marks the run KILLED)
and ends when the stage process is gone.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Iterator, Mapping
from typing import TYPE_CHECKING, Any

from aumesh.core.signals import check_supervisor, supervisor_gone
from aumesh.tracking.connection import TrackingServerError, run_fate
from aumesh.tracking.handle import TrackedRun, _NullRun
from aumesh.tracking.runs import _enabled, _end_failed, _failure, _open_run

if TYPE_CHECKING:  # pragma: no cover
    from concurrent.futures import Future, ProcessPoolExecutor


class RunBeside:
    """The handle of :func:`tracked_run_beside`: :class:`TrackedRun`'s ``log_*`` and ``set_tags`` methods, each
    queued to the helper process that holds the run and run there in the order they were called; they return at once
    (a :class:`concurrent.futures.Future`). ``run_id``, ``experiment_id`` and ``tracking_uri`` wait for the run to be
    open."""

    enabled = True

    def __init__(self, helper: ProcessPoolExecutor, opened: Future) -> None:
        self._helper = helper
        self._opened = opened  # of (run_id, experiment_id, tracking_uri)
        self._queued = [opened]
        self.finished = False  # ended FINISHED by :meth:`finish`

    def __repr__(self) -> str:
        return f"RunBeside(opened={self._opened.done()}, queued={len(self._queued)})"

    run_id = property(lambda self: self._opened.result()[0])
    experiment_id = property(lambda self: self._opened.result()[1])
    tracking_uri = property(lambda self: self._opened.result()[2])

    def call(self, fn, *args, **kwargs):
        """Queue ``fn(handle, *args, **kwargs)`` with the helper's :class:`TrackedRun` ``handle`` (``fn`` and its
        arguments are pickled: a module-level function); returns its Future."""
        future = self._helper.submit(_call_beside, fn, args, kwargs)
        self._queued.append(future)
        return future

    def __getattr__(self, name: str):
        if name.startswith("log_") or name == "set_tags":
            method = getattr(TrackedRun, name)
            return lambda *args, **kwargs: self.call(method, *args, **kwargs)
        raise AttributeError(f"{type(self).__name__} has no attribute {name!r}")

    def wait(self) -> None:
        """Wait for everything queued; raise the first error the helper met."""
        for future in self._queued:
            future.result()

    def cancel_queued(self) -> None:
        """Drop the calls not started yet (a stage that stops does not wait for its figures and metrics)."""
        for future in self._queued[1:]:
            future.cancel()

    def finish(self) -> None:
        """Wait for everything queued, then end the run FINISHED, now: what the caller publishes after this names a
        run that is FINISHED (the evaluate stage swaps in ``build/model`` only then). Raises the first error met; the
        caller's error handling (``tracked_run_beside``) then ends the run FAILED instead."""
        self.wait()
        self._helper.submit(_end_beside, "FINISHED").result()
        self.finished = True

    def end(self, error: BaseException | None = None, timeout: float | None = None) -> bool | None:
        """End the run FINISHED, or with ``error`` as :func:`aumesh.tracking.runs.tracked_run` does (nothing to end if
        it never opened). With ``error`` the calls still queued are dropped, and ``timeout`` bounds the wait: a stage
        that was told to stop does not wait for the helper's figures or MLflow's import (the helper ends with the
        stage, and the next run marks the run KILLED).

        Returns
        -------
        bool or None
            With ``error``: whether the run was marked (False: the server did not answer, or no answer in time),
            None when no run was opened.
        """
        if error is None:
            if not self.finished:
                self._helper.submit(_end_beside, "FINISHED").result()
            return True
        if timeout is not None:
            self.cancel_queued()
            if not self._opened.done():  # the helper still imports MLflow (~4 s of CPU): the next run marks the run
                return False
        deadline = None if timeout is None else time.monotonic() + timeout  # one bound for both waits

        def left() -> float | None:
            return None if deadline is None else max(0.0, deadline - time.monotonic())

        try:
            if self._opened.exception(left()) is not None:
                return None
        except Exception:  # TimeoutError: still opening
            return False
        with contextlib.suppress(Exception):  # TimeoutError, the helper's own error
            return bool(self._helper.submit(_end_beside, *_failure(error)).result(left()))
        return False


_BESIDE: TrackedRun | None = None  # the helper process's open run
#: how long a stopped stage waits for its helper to mark the run KILLED (it may be drawing figures or still importing
#: MLflow); after that the run is left to the next run to mark (:func:`aumesh.tracking.runs.close_orphaned_runs`)
STOP_SECONDS = 0.8


def _start_helper(owner_pid: int, stop_fd: int = -1) -> None:
    """In the helper: Ctrl-C (which a terminal sends to the whole process group) is the stage's to handle, so the run
    can still be marked KILLED; and the helper ends when its stage process is gone (e.g. killed alone). ``stop_fd``:
    the read end of a pipe on which a stage whose DVC is gone sends its ``(status, error, traceback)`` and leaves at
    once; the helper then ends the run with them itself (:func:`_end_for_stopped_owner`)."""
    import signal
    import threading

    # SIGTERM/SIGHUP too: a stage stops on them as on Ctrl-C (aumesh.core.signals), and this helper, forked after the
    # stage installed that handler, must stay to mark the run KILLED when a whole process group is told to stop
    for sig in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if sig is not None:
            signal.signal(sig, signal.SIG_IGN)

    def watch() -> None:
        import select

        while os.getppid() == owner_pid:
            if stop_fd < 0:
                time.sleep(0.5)
            elif select.select([stop_fd], [], [], 0.5)[0]:
                # not a daemon: the helper's own exit (its stage gone, its call queue closed) waits for it
                ender = threading.Thread(target=_end_for_stopped_owner, args=(os.read(stop_fd, 4096),), daemon=False)
                ender.start()
                ender.join()
                break
        os._exit(1)  # a run not ended stays RUNNING under the stage's pid: the next run marks it KILLED

    threading.Thread(target=watch, name="aumesh-owner-watch", daemon=True).start()


def _end_for_stopped_owner(message: bytes, open_wait: float = 15.0) -> None:
    """End the run as the stage that left without waiting asked (its JSON ``[status, error, traceback]``); a run still
    opening (MLflow's import) is waited for up to ``open_wait`` seconds."""
    import json

    with contextlib.suppress(Exception):
        status, error, tb = json.loads(message.decode())
        deadline = time.monotonic() + open_wait
        while _BESIDE is None and time.monotonic() < deadline:
            time.sleep(0.05)
        if _BESIDE is not None:
            _end_failed(_BESIDE, status, error, tb)


def _open_beside(tracking_cfg, run_name, params, tags, owner_pid: int) -> tuple[str, str, str]:
    global _BESIDE
    handle = _open_run(tracking_cfg, run_name, tags, None, owner_pid, params=params)
    _BESIDE = handle
    return handle.run_id, handle.experiment_id, handle.tracking_uri


_LOST: BaseException | None = None  # the helper's server stopped answering: the calls queued after fail at once


def _call_beside(fn, args, kwargs):
    global _LOST
    if _BESIDE is None:
        raise RuntimeError("the MLflow run did not open (see the first error)")
    if _LOST is not None:  # not each queued call retried for the whole bound again
        raise _LOST
    try:
        return fn(_BESIDE, *args, **kwargs)
    except TrackingServerError as err:
        _LOST = err
        raise


def _end_beside(status: str, error: str = "", tb: str = "") -> bool:
    if _BESIDE is None:  # the run never opened: the opening error is what the caller reports
        return False
    if status == "FINISHED":
        _BESIDE.client.set_terminated(_BESIDE.run_id, status)
        return True
    return _end_failed(_BESIDE, status, error, tb)


@contextlib.contextmanager
def tracked_run_beside(
    tracking_cfg: Mapping[str, Any] | None,
    run_name: str | None,
    params: Mapping[str, Any] | None,
    tags: Mapping[str, Any] | None = None,
) -> Iterator[RunBeside | _NullRun]:
    """:func:`aumesh.tracking.runs.tracked_run` held by a helper process, so MLflow is never imported here and works
    beside the caller.

    MLflow 3's import (its GenAI, gateway and data modules, pandas, SQLAlchemy: ~4 s of CPU) ran on one core before
    the evaluate stage's first pass, while the other idled; beside it, the stage at 344k frames takes 0.82x the time.
    The helper (one
    worker of a :class:`concurrent.futures.ProcessPoolExecutor`, forked on Linux) imports MLflow and opens
    the run while the caller computes; the caller's logging is queued to it, in order
    (:class:`RunBeside`). The run is the same as ``tracked_run``'s: params, provenance tags (``aumesh.pid`` is the
    caller's), FINISHED on normal exit; if the body raises, or a queued call failed, the run gets the ``aumesh.error``
    tag and ``error.txt``, is FAILED (KILLED for ``KeyboardInterrupt``) and the error is raised here. If the caller is
    killed the helper ends too, and the next run marks the run KILLED
    (:func:`aumesh.tracking.runs.close_orphaned_runs`).

    Yields
    ------
    RunBeside
        Or the no-op handle (``enabled=False``) when ``tracking.enabled`` is false.
    """
    if not _enabled(tracking_cfg):
        yield _NullRun()
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    # fork (Linux): the helper inherits the imports (NumPy, pandas); elsewhere spawn, the platforms' safe default
    context = multiprocessing.get_context("fork" if sys.platform == "linux" else "spawn")
    owner = os.getpid()
    # forked: the helper keeps the read end of this pipe, on which a stopped stage hands it the run's end
    stop_r, stop_w = os.pipe() if context.get_start_method() == "fork" else (-1, -1)
    helper = ProcessPoolExecutor(1, mp_context=context, initializer=_start_helper, initargs=(owner, stop_r))
    stopped = False
    try:
        run = RunBeside(helper, helper.submit(_open_beside, dict(tracking_cfg or {}), run_name, params, tags, owner))
        try:
            yield run
            run.wait()
            check_supervisor()  # under DVC: a run whose DVC was stopped is KILLED, never FINISHED by an orphan
        except BaseException as exc:
            # DVC gone (killed, stopped): nobody waits for this stage, which must not run on as an orphan; leave within
            # STOP_SECONDS. Ctrl-C and SIGTERM of the stage itself end the run with everything logged so far.
            stopped = isinstance(exc, KeyboardInterrupt) and supervisor_gone()
            if stopped and stop_w >= 0:  # the helper ends the run itself (KILLED, the reason): not waited for
                run.cancel_queued()
                _send_end(stop_w, exc)
                raise
            marked = run.end(exc, timeout=STOP_SECONDS if stopped else None)
            if isinstance(exc, TrackingServerError) and not exc.names_run:  # one line: what became of the run
                raise exc.noted(run_fate(run.run_id if marked is not None else None, marked)) from exc
            raise
        run.end()
    finally:
        helper.shutdown(wait=not stopped, cancel_futures=stopped)
        for fd in (stop_r, stop_w):
            if fd >= 0:
                os.close(fd)


def _send_end(fd: int, exc: BaseException) -> None:
    """One write (at most ``PIPE_BUF`` bytes: atomic) of the run's end for the helper (:func:`_start_helper`)."""
    import json

    status, error, tb = _failure(exc)
    with contextlib.suppress(OSError):
        os.write(fd, json.dumps([status, error[:1000], tb[-2000:]]).encode()[:4096])
