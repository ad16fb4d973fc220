"""A stage whose ``dvc repro`` is killed stops at once, not after the compute tasks in flight (issue 44: the evaluate
stage ran on 10-37 s after a SIGKILL of DVC).

Each case runs ``aumesh evaluate`` in a child process whose work is replaced by compute jobs of 60 s each (a Dask
pass's tasks, the fits of ``local_map``), and whose "DVC process" is a ``sleep`` the watcher watches and that is
killed (not reaped: a zombie, as after ``kill -9`` of DVC under a parent that does not wait). The child must end with
the stage's stop status (143) and its line long before one job could finish: ``timeout`` is that bound, not a timing
measurement (``benchmarks/bench_stage_kill.py`` measures)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

CHILD = textwrap.dedent(
    """
    import os, signal, subprocess, sys, threading, time
    import psutil
    from aumesh import cli
    from aumesh.cli import stages
    from aumesh.core import signals

    work, stuck = sys.argv[1], sys.argv[2] == "stuck"
    dvc = subprocess.Popen(["sleep", "120"])  # stands for the DVC process: killed, never reaped

    def job(_):
        time.sleep(60)

    def evaluate(args):
        from aumesh.pipeline import compute

        watched = [(dvc.pid, psutil.Process(dvc.pid).create_time(), "the DVC process that started this stage")]
        signals._WATCHED[:] = watched
        if stuck:  # a main thread that never gets to run the SIGTERM handler (inside a long C call)
            signals.GRACE_SECONDS = 0.5
            signal.signal(signal.SIGTERM, lambda *a: None)
        threading.Thread(target=signals._watch, args=(watched,), daemon=True).start()
        threading.Timer(0.5, dvc.kill).start()
        if work == "dask pass":
            compute.map_gather(job, list(range(8)))
        else:
            compute.local_map(job, list(range(8)))
        return 0

    stages._cmd_evaluate = evaluate
    sys.argv = ["aumesh", "evaluate"]
    cli.run()
    """
)


@pytest.mark.slow
@pytest.mark.parametrize("work", ["dask pass", "local fits"])
def test_a_stage_whose_dvc_is_killed_stops_without_waiting_for_its_compute_tasks(work):
    proc = subprocess.run([sys.executable, "-c", CHILD, work, "responsive"], capture_output=True, text=True, timeout=20)
    assert proc.returncode == 143, proc.stderr
    assert "aumesh evaluate: stopped: the DVC process that started this stage (pid" in proc.stderr, proc.stderr
    assert "is gone; nothing was swapped in" in proc.stderr


@pytest.mark.slow
def test_a_stage_that_cannot_run_its_handler_is_ended_by_the_watcher():
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, "local fits", "stuck"], capture_output=True, text=True, timeout=20
    )
    assert proc.returncode == 143, proc.stderr
    assert "did not stop within 0.5 s of its SIGTERM: ending it now" in proc.stderr, proc.stderr
