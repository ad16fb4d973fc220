"""Seconds to the first line, and the exit code, of the experiment guards of issue 45 (median of ``--runs``).

Starts what the cases need for real, in a temporary folder: a git + DVC workspace of this checkout (its ``dvc.yaml``,
``conf/``, ``src/``) on synthetic tables, built once with ``dvc repro``; a ``dask scheduler`` (started in a folder that
is not the workspace); an ``aumesh server`` (MLflow, SQLite backend) the workspace logs to. Then, per case, ``--runs``
times, from the start of the command to the first line it prints (stdout or stderr), and its exit code:

* ``dvc exp run -S compute=distributed -S compute.address=<the scheduler>``: refused by the check_params stage;
* ``aumesh exp apply <exp>`` of an experiment whose outputs left the cache (a real ``dvc exp run``, its objects removed);
* ``make promote`` where a newer evaluate run of this clone evaluated another configuration: the overrule refusal.

    python benchmarks/bench_experiment_guards.py [--runs 3] [--frames 900]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from _common import REPO

BIN = Path(sys.executable).parent


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run(args: list, cwd: Path, env: dict) -> str:
    proc = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"{' '.join(map(str, args))} failed:\n{proc.stdout}\n{proc.stderr}")
    return proc.stdout


def first_line(args: list, cwd: Path, env: dict) -> tuple[float, float, int, str]:
    """Seconds from the start of ``args`` to its first non-empty output line (either stream) and to its first
    ``error:`` line (DVC says "Running stage ..." first), its exit code, the error line."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [str(a) for a in args], cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    first: list[tuple[float, str]] = []
    error: list[tuple[float, str]] = []
    lock = threading.Lock()

    def read(stream) -> None:
        for line in stream:
            if line.strip():
                with lock:
                    now = time.perf_counter() - t0
                    if not first:
                        first.append((now, line.rstrip()))
                    if not error and "error:" in line:
                        error.append((now, line.rstrip()))

    threads = [threading.Thread(target=read, args=(s,)) for s in (proc.stdout, proc.stderr)]
    for t in threads:
        t.start()
    code = proc.wait()
    for t in threads:
        t.join()
    end = time.perf_counter() - t0
    seconds = first[0][0] if first else end
    to_error, line = error[0] if error else (end, first[0][1] if first else "")
    return seconds, to_error, code, line


def wait_healthy(url: str, proc: subprocess.Popen, timeout: float = 120) -> None:
    import urllib.request

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"server exited {proc.returncode}")
        try:
            with urllib.request.urlopen(f"{url}/health", timeout=2) as r:
                if r.status == 200:
                    return
        except OSError:
            time.sleep(0.3)
    raise SystemExit(f"{url} not healthy after {timeout} s")


def build_workspace(root: Path, frames: int, env: dict) -> Path:
    from aumesh.config import compose, write_params
    from aumesh.synthetic.tables import SynthSpec, write_tables

    ws = root / "ws"
    ws.mkdir()
    for name in ("dvc.yaml", ".gitignore"):
        shutil.copy(REPO / name, ws / name)
    for name in ("conf", "validation", "src"):
        shutil.copytree(
            REPO / name, ws / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info", "promoted.yaml")
        )
    write_params(compose(config_dir=ws / "conf"), ws / "params.yaml")
    (ws / "promotion.json").write_text('{"promoted": null}\n')
    write_tables(ws / "data", SynthSpec(n_frames=frames, n_videos=60, seed=3))
    for args in (
        ["git", "init", "-q"],
        ["git", "config", "user.email", "bench@example.com"],
        ["git", "config", "user.name", "bench"],
        [BIN / "dvc", "init", "-q"],
    ):
        _run(args, ws, env)
    shutil.copy(REPO / ".dvc" / "config", ws / ".dvc" / "config")
    _run([BIN / "dvc", "remote", "remove", "demo"], ws, env)
    _run([BIN / "dvc", "add", "-q", "data"], ws, env)
    _run([BIN / "dvc", "repro", "-q"], ws, env)
    _run(["git", "add", "-A"], ws, env)
    _run(["git", "commit", "-qm", "built"], ws, env)
    return ws


def _objects(ws: Path, lock_text: str) -> set[Path]:
    import yaml

    def obj(md5: str) -> Path:
        return ws / ".dvc" / "cache" / "files" / "md5" / md5[:2] / md5[2:]

    found: set[Path] = set()
    for stage in yaml.safe_load(lock_text)["stages"].values():
        for out in stage.get("outs", []):
            if obj(out["md5"]).exists():
                found.add(obj(out["md5"]))
                if out["md5"].endswith(".dir"):
                    found |= {obj(e["md5"]) for e in json.loads(obj(out["md5"]).read_text())}
    return found


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=900)
    args = ap.parse_args(argv)

    root = Path(tempfile.mkdtemp(prefix="aumesh-bench-guards-"))
    procs: list[subprocess.Popen] = []
    try:
        env = {k: v for k, v in os.environ.items() if not k.startswith(("AUMESH_", "DVC_", "MLFLOW_"))}
        env |= {"PATH": f"{BIN}{os.pathsep}{env['PATH']}", "PYTHONPATH": str(REPO / "src")}
        # the servers, started outside the workspace
        elsewhere = root / "elsewhere"
        elsewhere.mkdir()
        dask_port, mlflow_port = _free_port(), _free_port()
        log = open(elsewhere / "servers.log", "w")
        procs.append(
            subprocess.Popen(
                [BIN / "dask", "scheduler", "--host", "127.0.0.1", "--port", str(dask_port), "--no-dashboard"],
                cwd=elsewhere,
                env=env,
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        )
        url = f"http://127.0.0.1:{mlflow_port}"
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "aumesh", "server", "--backend-store-uri", f"sqlite:///{elsewhere}/mlflow.db"]
                + ["--artifacts-destination", str(elsewhere / "artifacts"), "--port", str(mlflow_port)],
                cwd=elsewhere,
                env=env,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        )
        wait_healthy(url, procs[-1])
        env["MLFLOW_TRACKING_URI"] = url
        print(f"servers: dask tcp://127.0.0.1:{dask_port}, mlflow {url}; building the workspace ...", flush=True)
        ws = build_workspace(root, args.frames, env)

        # case 3's state: a sweep, then an evaluate run of this clone on another configuration
        aumesh = [sys.executable, "-m", "aumesh"]
        _run([*aumesh, "sweep", "-m", "model.n_components=2,3"], ws, env)
        _run([*aumesh, "evaluate"], ws, env)  # params.yaml's 83 components, after the sweep
        # case 2's state: an experiment whose objects are gone from the cache
        lock = (ws / "dvc.lock").read_text()
        _run([BIN / "dvc", "exp", "run", "-q", "-n", "unpushed", "-S", "model.n_components=4"], ws, env)
        exp_lock = (ws / "dvc.lock").read_text()
        _run(["bash", "-c", "git checkout dvc.lock params.yaml metrics && dvc checkout -q"], ws, env)
        for path in _objects(ws, exp_lock) - _objects(ws, lock):
            path.unlink()
        for name in ("requirements.lock", "pyproject.toml"):
            (ws / name).touch()
        stamp = ws / "installed.stamp"
        stamp.touch()
        os.utime(stamp, (time.time() + 10, time.time() + 10))

        cases = {
            "dvc exp run -S compute.address=tcp://...": (
                [
                    BIN / "dvc",
                    "exp",
                    "run",
                    "-S",
                    "compute=distributed",
                    "-S",
                    f"compute.address=tcp://127.0.0.1:{dask_port}",
                ],
                lambda: _run([*aumesh, "compose-params"], ws, env),
            ),
            "aumesh exp apply (outputs not cached)": ([*aumesh, "exp", "apply", "unpushed"], None),
            "make promote (newer evaluate run)": (
                ["make", "-s", "-f", REPO / "Makefile", "promote", f"VENV={BIN.parent}", f"STAMP={stamp}"],
                None,
            ),
        }
        rows = []
        for name, (cmd, reset) in cases.items():
            seconds, errors, codes, line = [], [], [], ""
            for _ in range(args.runs):
                s, e, code, line = first_line(cmd, ws, env)
                seconds.append(s)
                errors.append(e)
                codes.append(code)
                if reset:
                    reset()
            rows.append((name, statistics.median(seconds), statistics.median(errors), sorted(set(codes)), line))
        print(f"\nmedian of {args.runs} runs, seconds from the start of the command")
        print(f"{'case':45} {'first line':>10} {'error line':>10} {'exit':>6}")
        for name, med, med_error, codes, line in rows:
            print(f"{name:45} {med:10.2f} {med_error:10.2f} {','.join(map(str, codes)):>6}")
            print(f"    {line[:220]}")
        return 0
    finally:
        for proc in procs:
            if proc.poll() is None:
                os.killpg(proc.pid, 15) if proc is procs[-1] else proc.terminate()  # the server's workers too
                try:
                    proc.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    proc.kill()
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
