"""How long the evaluate stage runs on after its ``dvc repro`` is SIGKILLed (issue 44: 10-37 s on 4c2936e; the README
promises about a second).

A git + DVC workspace of one source tree (``--src``: its ``dvc.yaml``, ``conf/``, ``params.yaml``; default this
checkout) on synthetic tables, ``dvc repro prepare`` once; then ``--runs`` times: ``dvc repro -f -s evaluate`` (the stage alone), wait
``--delay`` seconds after the evaluate stage's process started (the middle of its CV passes and fits), SIGKILL the DVC process alone (as ``kill -9 <dvc>`` or the OOM killer of DVC) and time until the stage
process is gone. Prints each time and the median.

    python benchmarks/bench_stage_kill.py                          # this checkout
    git worktree add /tmp/old 4c2936e && python benchmarks/bench_stage_kill.py --src /tmp/old/src   # before
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import AUMESH, REPO, ensure_data, source_env, videos_for

BIN = Path(sys.executable).parent


def _run(args: list, cwd: Path, env: dict) -> None:
    proc = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"{' '.join(map(str, args))} failed:\n{proc.stdout}\n{proc.stderr}")


def workspace(root: Path, checkout: Path, data: Path, env: dict) -> Path:
    ws = root / "ws"
    ws.mkdir()
    for name in ("dvc.yaml", "params.yaml", "promotion.json", ".gitignore"):
        shutil.copy(checkout / name, ws / name)
    for name in ("conf", "validation", "src"):  # src/: the stages' code is their DVC deps
        if (checkout / name).is_dir():
            shutil.copytree(checkout / name, ws / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    shutil.copytree(data, ws / "data")
    for args in (["git", "init", "-q"], [BIN / "dvc", "init", "-q"], [BIN / "dvc", "add", "-q", "data"]):
        _run(args, ws, env)
    _run([BIN / "dvc", "repro", "prepare"], ws, env)
    return ws


def _stage_process(dvc_pid: int):
    import psutil

    for child in psutil.Process(dvc_pid).children(recursive=True):
        try:
            if child.cmdline()[1:4] == ["-m", "aumesh", "evaluate"]:
                return child
        except psutil.Error:
            continue
    return None


def one_kill(ws: Path, env: dict, delay: float) -> tuple[float, int | None]:
    """Seconds from the SIGKILL of ``dvc repro -f evaluate`` to the end of its evaluate stage, and the stage's exit."""
    import psutil

    log = open(ws.parent / "dvc-repro.log", "w")  # noqa: SIM115  (closed below)
    proc = subprocess.Popen(
        [BIN / "dvc", "repro", "-f", "-s", "evaluate"],
        cwd=ws,
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    stage, deadline = None, time.monotonic() + 600
    while proc.poll() is None and time.monotonic() < deadline and stage is None:
        stage = _stage_process(proc.pid)
        time.sleep(0.02)
    if stage is None or proc.poll() is not None:
        raise SystemExit("the evaluate stage never started")
    # the same moment of the stage's work for every source tree: seconds since its process started (the trees open
    # their MLflow run at different points)
    time.sleep(max(0.0, stage.create_time() + delay - time.time()))
    if proc.poll() is not None:
        log.close()
        raise SystemExit(
            f"dvc repro ended within {delay} s of the stage's start: use more --frames or less --delay\n"
            + (ws.parent / "dvc-repro.log").read_text()
        )
    proc.send_signal(signal.SIGKILL)  # the DVC process only; the shell and the stage are left to notice
    t0 = time.monotonic()
    proc.wait()  # reaped at once, as an interactive shell does
    gone, alive = psutil.wait_procs([stage], timeout=300)
    seconds = time.monotonic() - t0
    for p in alive:
        p.kill()
    log.close()
    return seconds, (gone[0].returncode if gone else None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--src", type=Path, default=None, help="source tree to run (default: this checkout's src/)")
    parser.add_argument("--frames", type=int, default=60_000)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--delay", type=float, default=6.0, help="seconds after the stage's start before the kill")
    parser.add_argument("--workdir", type=Path, default=REPO / "benchmarks" / "out" / "stage_kill")
    args = parser.parse_args()
    src = (args.src or REPO / "src").resolve()
    env = {**source_env(src), "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}"}
    args.workdir.mkdir(parents=True, exist_ok=True)
    data, _ = ensure_data(args.workdir, args.frames, videos_for(args.frames))
    with tempfile.TemporaryDirectory(prefix="bench-stage-kill-", dir=args.workdir) as tmp:
        ws = workspace(Path(tmp), src.parent, data, env)
        env["MLFLOW_TRACKING_URI"] = f"sqlite:///{ws / 'mlflow.db'}"
        times = []
        for i in range(args.runs):
            seconds, code = one_kill(ws, env, args.delay)
            times.append(seconds)
            print(f"run {i + 1}: evaluate gone {seconds:.2f} s after the SIGKILL of dvc (exit {code})", flush=True)
    print(
        f"{src}: {args.frames:,} frames, kill {args.delay:g} s into evaluate: median {statistics.median(times):.2f} s "
        f"(min {min(times):.2f}, max {max(times):.2f}, {args.runs} runs); via {' '.join(AUMESH[1:])}"
    )


if __name__ == "__main__":
    main()
