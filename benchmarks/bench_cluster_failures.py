"""Seconds to the first line, and the exit code, of a stage whose Dask cluster cannot serve it (issue 45).

Real servers and workers on loopback, started from a temporary folder that is no workspace: a TCP server that accepts
and says nothing, an HTTP server (Python's), a closed port, a ``dask scheduler`` without workers, a worker importing
another clone's aumesh (a copy of this one with ``pipeline/prepare/__init__.py`` changed) when the stage connects and
when it joins mid-run, and the scheduler SIGKILLed mid-run. Each case runs ``--runs`` times (``python -m aumesh
ingest``, or ``prepare`` for the mid-run cases, in a workspace of synthetic tables, ``AUMESH_COMPUTE_ADDRESS`` set and
``AUMESH_COMPUTE_CONNECT_TIMEOUT`` at ``--timeout``); printed: the median seconds from the stage's start (the late
worker: from the worker's start; the lost scheduler: from the kill) to the stage's first line on stderr, the exit
codes, and the line.

    .venv/bin/python benchmarks/bench_cluster_failures.py                 # 3 runs each, connect timeout 5 s
    .venv/bin/python benchmarks/bench_cluster_failures.py --src /tmp/old/src --cases silent http   # another tree
"""

from __future__ import annotations

import argparse
import http.server
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
CASES = ("silent", "http", "closed", "no-worker", "other-code", "late-other-code", "scheduler-killed")
CHANGED = "pipeline/prepare/__init__.py"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Silent(threading.Thread):
    def __init__(self):
        super().__init__(daemon=True)
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port, self.conns = self.sock.getsockname()[1], []

    def run(self):
        try:
            while True:
                self.conns.append(self.sock.accept()[0])
        except OSError:
            pass

    def close(self):
        self.sock.close()
        for c in self.conns:
            c.close()


class Http(threading.Thread):
    def __init__(self):
        super().__init__(daemon=True)

        class Quiet(http.server.BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Quiet)
        self.port = self.server.server_address[1]

    def run(self):
        self.server.serve_forever(poll_interval=0.05)

    def close(self):
        self.server.shutdown()
        self.server.server_close()


class Cluster:
    """``dask scheduler`` and workers (each importing the aumesh of its ``src``) started in ``cwd``."""

    def __init__(self, cwd: Path, src: Path, workers: list[Path]):
        self.cwd, self.port = cwd, _free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.log = open(cwd / "cluster.log", "ab")
        self.procs: list[subprocess.Popen] = []
        self._start(["scheduler", "--host", "127.0.0.1", "--port", str(self.port)], src)
        self.workers = [self.add_worker(w) for w in workers]
        if workers:
            from distributed import Client

            with Client(self.address, timeout=60, set_as_default=False) as client:
                client.wait_for_workers(len(workers), timeout=120)
                self.pids = client.run(os.getpid)

    def _start(self, args: list[str], src: Path) -> subprocess.Popen:
        env = {**os.environ, "PYTHONPATH": str(src), "ARROW_DEFAULT_MEMORY_POOL": "system"}
        env = {k: v for k, v in env.items() if not k.startswith("AUMESH_COMPUTE_")}
        proc = subprocess.Popen(
            [BIN / "dask", *args, "--no-dashboard"], cwd=self.cwd, env=env, stdout=self.log, stderr=subprocess.STDOUT
        )
        self.procs.append(proc)
        return proc

    def add_worker(self, src: Path) -> subprocess.Popen:
        return self._start(["worker", self.address, "--host", "127.0.0.1", "--nthreads", "1"], src)

    def stop(self):
        for p in self.procs:
            if p.poll() is None:
                p.kill()
            p.wait()
        self.log.close()


def workspace(root: Path, n_frames: int, env: dict) -> Path:
    from aumesh.config import compose, write_params
    from aumesh.synthetic.tables import SynthSpec, write_tables

    ws = root / "ws"
    write_tables(ws / "data", SynthSpec(n_frames=n_frames, n_videos=60, seed=5, frames_per_file=700))
    write_params(compose(["compute.partition_rows=100"], config_dir=REPO / "conf"), ws / "params.yaml")
    (ws / "promotion.json").write_text('{"promoted": null}\n')
    if n_frames > 1000:  # the mid-run cases: prepare's input, built here
        subprocess.run([sys.executable, "-m", "aumesh", "ingest"], cwd=ws, env=env, check=True, capture_output=True)
    return ws


def first_line(proc: subprocess.Popen, t0: list[float], cap: float = 600) -> tuple[float, int, str]:
    """Seconds from ``t0[0]`` (set by the caller, possibly later) to ``proc``'s first stderr line; its exit code."""
    assert proc.stderr is not None
    line = proc.stderr.readline()
    at = time.monotonic()
    rest = proc.communicate(timeout=cap)[1]
    return at - t0[0], proc.returncode, (line or rest).strip()


def one(case: str, tmp: Path, src: Path, other: Path, timeout: float) -> tuple[float, int, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("AUMESH_COMPUTE_")}
    env.update(PYTHONPATH=str(src), AUMESH_COMPUTE_CONNECT_TIMEOUT=f"{timeout:g}")
    mid_run = case in ("late-other-code", "scheduler-killed")
    ws = workspace(tmp, 6000 if mid_run else 300, env)
    (tmp / "elsewhere").mkdir()
    server = {"silent": Silent, "http": Http}.get(case)
    srv = server() if server else None
    cluster = None
    if srv:
        srv.start()
        address = f"tcp://127.0.0.1:{srv.port}"
    elif case == "closed":
        address = f"tcp://127.0.0.1:{_free_port()}"
    else:
        workers = {"no-worker": [], "other-code": [other]}.get(case, [src])
        cluster = Cluster(tmp / "elsewhere", src, workers)
        address = cluster.address
    stage = "prepare" if mid_run else "ingest"
    try:
        t0 = [time.monotonic()]
        proc = subprocess.Popen(
            [sys.executable, "-m", "aumesh", stage],
            cwd=ws,
            env={**env, "AUMESH_COMPUTE_ADDRESS": address},
            stderr=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
            text=True,
        )
        if mid_run:
            assert cluster is not None
            while not list((ws / "build").glob(".prepared.tmp-*/scratch/*.arrow")) and proc.poll() is None:
                time.sleep(0.02)
            if case == "scheduler-killed":
                t0[0] = time.monotonic()
                cluster.procs[0].send_signal(signal.SIGKILL)
            else:  # the one worker paused (the run cannot end without the newcomer), another clone's joins
                (pid,) = cluster.pids.values()
                os.kill(pid, signal.SIGSTOP)
                t0[0] = time.monotonic()
                cluster.add_worker(other)
        return first_line(proc, t0)
    finally:
        if case == "late-other-code" and cluster is not None:
            for pid in cluster.pids.values():
                os.kill(pid, signal.SIGCONT)
        if cluster:
            cluster.stop()
        if srv:
            srv.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--timeout", type=float, default=5.0, help="AUMESH_COMPUTE_CONNECT_TIMEOUT, seconds")
    parser.add_argument("--src", type=Path, default=REPO / "src", help="the source tree the stage and workers run")
    parser.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-cluster-") as tmp_root:
        other = Path(tmp_root) / "other-clone" / "src"
        shutil.copytree(args.src / "aumesh", other / "aumesh", ignore=shutil.ignore_patterns("__pycache__"))
        changed = other / "aumesh" / CHANGED
        changed.write_text(changed.read_text() + "\n# another clone's change\n")
        print(f"connect timeout {args.timeout:g} s, {args.runs} runs each, source {args.src}")
        print(f"{'case':<18} {'first line s (median)':>22} {'runs':>22}  exit  line")
        for case in args.cases:
            results = []
            for i in range(args.runs):
                tmp = Path(tmp_root) / f"{case}-{i}"
                tmp.mkdir()
                results.append(one(case, tmp, args.src.resolve(), other, args.timeout))
            times = [r[0] for r in results]
            codes = sorted({r[1] for r in results})
            shown = " ".join(f"{t:.2f}" for t in times)
            print(f"{case:<18} {statistics.median(times):>22.2f} {shown:>22}  {codes}  {results[-1][2][:150]}")


if __name__ == "__main__":
    main()
