"""A stage stops as Ctrl-C stops it when it is told to (SIGTERM) or when the DVC process that started it dies.

``kill -TERM`` (what CI cancellation, ``timeout`` and systemd send) of ``dvc repro`` makes DVC exit at once; it does not
pass the signal on, and the stage, a grandchild (DVC runs ``$SHELL -c 'cmd'``), went on as an orphan that swapped in a
release DVC never recorded, or finished its MLflow run FINISHED. Here:

* SIGTERM (and SIGHUP) raise :class:`Terminated` in the main thread, a :class:`KeyboardInterrupt`: everything that
  cleans up after Ctrl-C does so (atomic writers remove their temporaries, the MLflow run is marked KILLED);
* under DVC (``DVC_STAGE`` in the environment) a daemon thread watches the DVC process (the nearest ancestor whose
  command is ``dvc``; else the nearest that is not a shell) and the stage's own parent; when either is gone it sends
  the stage SIGTERM, so the orphan stops at once. Linux's ``PR_SET_PDEATHSIG`` is not enough: the stage's parent is
  the shell, which outlives DVC. On Linux >= 5.3 the thread waits on a ``pidfd`` of each process (readable the moment
  it exits, reaped or not), else it polls every :data:`POLL_SECONDS`;
* the main thread may be inside a long C call (a LAPACK fit) when the SIGTERM comes, and Python runs the handler only
  when that call returns: if the stage is still there :data:`GRACE_SECONDS` after the SIGTERM, the watcher ends it
  (``os._exit``; the next run removes its temporaries and marks its MLflow run KILLED);
* a stopped command leaves at once (:func:`aumesh.cli.run`): not waiting for the compute threads' tasks in flight
  (Dask's thread pool is joined at exit, and a pass's running tasks took 10-37 s to finish after DVC was killed,
  issue 44), whose outputs the stage had already thrown away.

Outside DVC no ancestor is watched: ``nohup aumesh evaluate &`` must survive its shell.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from pathlib import Path

log = logging.getLogger(__name__)

POLL_SECONDS = 0.5
#: how long after its SIGTERM a stage whose DVC is gone may take to stop before the watcher ends it
GRACE_SECONDS = 3.0
SHELLS = frozenset({"sh", "bash", "dash", "zsh", "ksh", "mksh", "fish", "busybox", "env", "timeout", "nice"})
_INSTALLED = False


class Terminated(KeyboardInterrupt):
    """The stage was told to stop (SIGTERM, SIGHUP) or its DVC process died; handled everywhere as Ctrl-C is."""


class Interrupted(KeyboardInterrupt):
    """An interruption already cleaned up and described (e.g. a sweep's "interrupted after 2 of 5 runs ...");
    ``aumesh`` prints the message as it is and exits ``128 + signum``."""

    def __init__(self, message: str, signum: int = signal.SIGINT) -> None:
        super().__init__(message)
        self.signum = int(signum)


def _raise(signum: int, _frame) -> None:
    reason = _REASON.pop(0) if _REASON else f"{signal.Signals(signum).name} received"
    raise Terminated(reason)


_REASON: list[str] = []  # why the watcher sent SIGTERM (read by the handler, in the main thread)


def _is_dvc(cmdline: list[str]) -> bool:
    words = [Path(w).name for w in cmdline[:2]]
    return "dvc" in words or (len(cmdline) > 2 and cmdline[1:3] == ["-m", "dvc"])


def dvc_process():
    """The DVC process this stage runs under (a :class:`psutil.Process`), or None outside DVC.

    The nearest ancestor whose command is ``dvc`` (``.venv/bin/dvc``, ``python -m dvc``); failing that (DVC embedded in
    another program), the nearest ancestor that is not a shell.
    """
    if not os.environ.get("DVC_STAGE"):
        return None
    import psutil

    fallback = None
    for parent in psutil.Process().parents():
        if parent.pid <= 1:
            break
        try:
            cmdline, name = parent.cmdline(), parent.name()
        except psutil.Error:
            continue
        if _is_dvc(cmdline):
            return parent
        if fallback is None and name not in SHELLS and Path(cmdline[0] if cmdline else name).name not in SHELLS:
            fallback = parent
    return fallback


def process_gone(pid: int, started_s: float) -> bool:
    """No process ``pid`` on this host, a zombie (a killed child that nobody reaped, common in containers) or a
    process created after ``started_s`` (epoch seconds; the pid was reused)."""
    import psutil

    try:
        proc = psutil.Process(pid)
        return proc.status() == psutil.STATUS_ZOMBIE or proc.create_time() > started_s + 1.0
    except psutil.NoSuchProcess:
        return True


_WATCHED: list[tuple[int, float, str]] = []  # (pid, start time, what) of the processes this stage runs under


def _gone(watched: list[tuple[int, float, str]]) -> str | None:
    for pid, started, what in watched:
        if process_gone(pid, started):
            return f"{what} (pid {pid}) is gone"
    return None


def _pidfds(watched: list[tuple[int, float, str]]) -> list[int]:
    """A ``pidfd`` of each watched process (Linux >= 5.3), or [] where the system has none."""
    fds: list[int] = []
    for pid, _, _ in watched:
        try:
            fds.append(os.pidfd_open(pid))
        except (AttributeError, OSError):  # no pidfd here, or the process is gone already: poll
            for fd in fds:
                os.close(fd)
            return []
    return fds


def wait_gone(watched: list[tuple[int, float, str]]) -> str:
    """Block until one of the ``watched`` processes is gone; return why (which one)."""
    import select

    fds = _pidfds(watched)
    poller = select.poll() if fds else None
    for fd in fds:
        poller.register(fd, select.POLLIN)  # type: ignore[union-attr]
    try:
        while True:
            reason = _gone(watched)
            if reason:
                return reason
            if poller is not None:
                poller.poll(POLL_SECONDS * 1000)  # readable when a process exits; the timeout re-checks anyway
            else:
                time.sleep(POLL_SECONDS)
    finally:
        for fd in fds:
            os.close(fd)


def _watch(watched: list[tuple[int, float, str]]) -> None:
    reason = wait_gone(watched)
    _REASON.append(reason)
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(GRACE_SECONDS)  # the main thread stops as after Ctrl-C; a daemon thread: gone with the process
    log.warning("%s and this stage did not stop within %g s of its SIGTERM: ending it now", reason, GRACE_SECONDS)
    os._exit(128 + signal.SIGTERM)


def supervisor_gone() -> bool:
    """Whether this stage runs under DVC and that DVC process (or the stage's parent) is gone."""
    return bool(_WATCHED) and _gone(_WATCHED) is not None


def check_supervisor() -> None:
    """Raise :class:`Terminated` now if the DVC process this stage runs under is gone: called where a stage commits
    (an output swapped in, a run marked FINISHED), so a stage quicker than the watcher's poll never commits as an
    orphan. Nothing outside DVC."""
    reason = _gone(_WATCHED) if _WATCHED else None
    if reason:
        raise Terminated(reason)


def install_stage_signals() -> None:
    """SIGTERM/SIGHUP raise :class:`Terminated`; under DVC, watch the DVC process and the parent (idempotent).

    Call from the main thread before the stage's work. Child processes that must outlive a SIGTERM of the stage
    itself (the MLflow helper, which ends the run KILLED) reset SIGTERM to ignored.
    """
    global _INSTALLED
    if _INSTALLED or threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if sig is not None and signal.getsignal(sig) is not signal.SIG_IGN:  # `nohup` (SIGHUP ignored) stays ignored
            signal.signal(sig, _raise)
    _INSTALLED = True
    dvc = dvc_process()
    if dvc is None:
        return
    import psutil

    watched = [(dvc.pid, dvc.create_time(), "the DVC process that started this stage")]
    parent = psutil.Process().parent()
    if parent is not None and parent.pid != dvc.pid:
        watched.append((parent.pid, parent.create_time(), f"this stage's parent process ({parent.name()})"))
    _WATCHED[:] = watched
    threading.Thread(target=_watch, args=(watched,), name="aumesh-dvc-watch", daemon=True).start()
