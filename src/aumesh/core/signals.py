"""A stage stops as Ctrl-C stops it when it is told to (SIGTERM) or when the DVC process that started it dies.

``kill -TERM`` (what CI cancellation, ``timeout`` and systemd send) of ``dvc repro`` makes DVC exit at once; it does not
pass the signal on, and the stage, a grandchild (DVC runs ``$SHELL -c 'cmd'``), went on as an orphan that swapped in a
release DVC never recorded, or finished its MLflow run FINISHED. Here:

* SIGTERM (and SIGHUP) raise :class:`Terminated` in the main thread, a :class:`KeyboardInterrupt`: everything that
  cleans up after Ctrl-C does so (atomic writers remove their temporaries, the MLflow run is marked KILLED);
* under DVC (``DVC_STAGE`` in the environment) a daemon thread watches the DVC process (the nearest ancestor whose
  command is ``dvc``; else the nearest that is not a shell) and the stage's own parent; when either is gone it sends
  the stage SIGTERM, so the orphan stops within :data:`POLL_SECONDS`. Linux's ``PR_SET_PDEATHSIG`` is not enough:
  the stage's parent is the shell, which outlives DVC.

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


def _watch(watched: list[tuple[int, float, str]]) -> None:
    while True:
        time.sleep(POLL_SECONDS)
        reason = _gone(watched)
        if reason:
            _REASON.append(reason)
            os.kill(os.getpid(), signal.SIGTERM)
            return


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
