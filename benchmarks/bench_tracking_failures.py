"""How fast ``aumesh evaluate`` says that its tracking store failed (issue 45, item 3: a wrong port took 4.5 min then a
traceback; a server stopped mid-evaluate 25 min of retry warnings then a ~100-line traceback).

A workspace on synthetic tables (400 frames; ingest, prepare and evaluate run once on a SQLite store), then per case
``--runs`` times ``aumesh evaluate`` as a subprocess, timing the first line it writes on stderr that says ``error:``
and recording its exit status and how many lines stderr held:

* closed port: ``MLFLOW_TRACKING_URI`` at a port nothing listens on;
* silent port: a TCP server that accepts and never answers (``tracking.check_timeout_s``, 5 s, bounds the check);
* wrong host name: ``http://mlflow.invalid:5000`` (``.invalid`` never resolves, RFC 2606);
* server stopped mid-evaluate: a real ``mlflow server`` (SQLite backend) SIGKILLed once the stage's run exists (the
  stage paused meanwhile); timed from the kill;
* server hung mid-evaluate: the same server SIGSTOPped instead (accepts, never answers), with
  ``MLFLOW_HTTP_REQUEST_TIMEOUT=5`` so that the bound ((max_retries + 1) x 5 s + backoff, then one try to mark the
  run FAILED) is seen in seconds; timed from the stop;
* database URI, PostgreSQL stopped: initdb / pg_ctl (as tests/test_team_postgres.py), started then stopped.

Prints one row per case: the median seconds to the line, the exit statuses, stderr's line count and the line itself.

    .venv/bin/python benchmarks/bench_tracking_failures.py [--runs 3] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import json
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
import urllib.request
from collections.abc import Callable
from pathlib import Path

from _common import AUMESH, REPO, source_env

PG_BIN = Path(os.environ.get("AUMESH_PG_BIN", "/usr/lib/postgresql/15/bin"))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def workspace(root: Path, env: dict) -> Path:
    """400 synthetic frames through ingest, prepare and evaluate (a SQLite store): the previous outputs the failures
    must keep."""
    ws = root / "ws"
    ws.mkdir()
    shutil.copy(REPO / "params.yaml", ws / "params.yaml")
    subprocess.run(["git", "init", "-q"], cwd=ws, check=True)
    run_env = dict(env, MLFLOW_TRACKING_URI=f"sqlite:///{ws / 'mlflow.db'}")
    for args in (
        ["synth", "--out", "data", "--frames", "400", "--videos", "40", "--seed", "3"],
        ["ingest"],
        ["prepare"],
    ):
        subprocess.run([*AUMESH, *args], cwd=ws, env=run_env, check=True, capture_output=True)
    subprocess.run([*AUMESH, "evaluate"], cwd=ws, env=run_env, check=True, capture_output=True)
    return ws


def timed_evaluate(ws: Path, env: dict, during: Callable[[subprocess.Popen], float] | None = None) -> dict:
    """``aumesh evaluate``: seconds from its start (or from what ``during`` returns, a ``time.monotonic()`` stamp)
    to its first ``error:`` line on stderr, its exit status and stderr."""
    t0 = time.monotonic()
    proc = subprocess.Popen(
        [*AUMESH, "evaluate"],
        cwd=ws,
        env=env,
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
        start_new_session=True,
    )
    lines: list[tuple[float, str]] = []

    def read() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.append((time.monotonic(), line.rstrip("\n")))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    if during is not None:
        t0 = during(proc)
    proc.wait(timeout=1800)
    reader.join(10)
    first = next(((t, line) for t, line in lines if "error:" in line), (float("nan"), "(no error line)"))
    return {"seconds": first[0] - t0, "code": proc.returncode, "n_lines": len(lines), "line": first[1]}


def silent_server() -> tuple[int, Callable[[], None]]:
    server = socket.create_server(("127.0.0.1", 0))
    held, stop = [], threading.Event()

    def accept() -> None:
        server.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(server.accept()[0])
            except TimeoutError:
                continue
            except OSError:
                return

    threading.Thread(target=accept, daemon=True).start()

    def close() -> None:
        stop.set()
        for conn in held:
            conn.close()
        server.close()

    return server.getsockname()[1], close


def mlflow_server(home: Path) -> tuple[str, subprocess.Popen]:
    from aumesh.tracking.server import server_command, server_environment

    home.mkdir(parents=True)
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = server_environment()
    env.pop("MLFLOW_TRACKING_URI", None)
    cmd = server_command(f"sqlite:///{home / 'mlflow.db'}", str(home / "artifacts"), port=port, workers=1)
    proc = subprocess.Popen(
        cmd, cwd=home, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    deadline = time.monotonic() + 120
    while True:
        try:
            with urllib.request.urlopen(f"{url}/health", timeout=2):
                return url, proc
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f"mlflow server did not start ({home})") from None
            time.sleep(0.25)


def runs_on(url: str) -> list:
    body = json.dumps({"experiment_ids": ["0", "1"], "max_results": 10}).encode()
    req = urllib.request.Request(
        f"{url}/api/2.0/mlflow/runs/search", data=body, headers={"Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(req, timeout=2) as resp:
            return json.loads(resp.read()).get("runs", [])
    except OSError:
        return []


def mid_evaluate(ws: Path, env: dict, home: Path, how: str) -> dict:
    """The server SIGKILLed (``kill``) or SIGSTOPped (``hang``) once the stage's run exists."""
    url, server = mlflow_server(home)

    def provoke(stage: subprocess.Popen) -> float:
        while not runs_on(url):
            if stage.poll() is not None:
                raise SystemExit("evaluate ended before its run appeared")
            time.sleep(0.05)
        os.killpg(stage.pid, signal.SIGSTOP)
        os.killpg(server.pid, signal.SIGKILL if how == "kill" else signal.SIGSTOP)
        if how == "kill":
            server.wait()
        stamp = time.monotonic()
        os.killpg(stage.pid, signal.SIGCONT)
        return stamp

    try:
        return timed_evaluate(ws, dict(env, MLFLOW_TRACKING_URI=url), provoke)
    finally:
        for sig in (signal.SIGKILL, signal.SIGCONT):
            try:
                os.killpg(server.pid, sig)
            except ProcessLookupError:
                pass
        server.wait()


def stopped_postgres(home: Path) -> str:
    """A PostgreSQL cluster initialised in ``home`` (a new folder directly under /tmp: as root, PostgreSQL runs as
    `postgres`, who must reach it), started and stopped: its URI."""
    sudo = ["runuser", "-u", "postgres", "--"] if os.geteuid() == 0 else []
    if sudo:
        shutil.chown(home, user="postgres")
    port = free_port()
    pg_ctl = [*sudo, str(PG_BIN / "pg_ctl"), "-D", str(home / "data")]
    subprocess.run(
        [*sudo, str(PG_BIN / "initdb"), "-D", str(home / "data"), "-U", "mlflow", "--auth=trust", "--no-instructions"],
        check=True,
        capture_output=True,
    )
    start = ["-l", str(home / "log"), "-w", "start", "-o", f"-p {port} -c listen_addresses=127.0.0.1 -k {home}"]
    subprocess.run([*pg_ctl, *start], check=True, capture_output=True)
    subprocess.run([*pg_ctl, "-m", "fast", "-w", "stop"], check=True, capture_output=True)
    return f"postgresql://mlflow@127.0.0.1:{port}/postgres"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=None, help="(default: a temporary folder, removed)")
    args = parser.parse_args()
    root = Path(args.workdir or tempfile.mkdtemp(prefix="aumesh-bench-tracking-"))
    root.mkdir(parents=True, exist_ok=True)
    env = source_env(REPO / "src")
    for variable in (
        "MLFLOW_HTTP_REQUEST_TIMEOUT",
        "MLFLOW_HTTP_REQUEST_MAX_RETRIES",
        "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR",
    ):
        env.pop(variable, None)  # the configured bounds (conf/tracking/mlflow.yaml), not a caller's
    try:
        ws = workspace(root, env)
        port, close_silent = silent_server()
        pg_home = Path(tempfile.mkdtemp(prefix="aumesh-bench-pg-"))
        pg_uri = stopped_postgres(pg_home) if (PG_BIN / "initdb").exists() else None
        cases: dict[str, Callable[[int], dict]] = {
            "closed port": lambda i: timed_evaluate(
                ws, dict(env, MLFLOW_TRACKING_URI=f"http://127.0.0.1:{free_port()}")
            ),
            "silent port (check_timeout_s=5)": lambda i: timed_evaluate(
                ws, dict(env, MLFLOW_TRACKING_URI=f"http://127.0.0.1:{port}")
            ),
            "wrong host name": lambda i: timed_evaluate(
                ws, dict(env, MLFLOW_TRACKING_URI="http://mlflow.invalid:5000")
            ),
            "server stopped mid-evaluate (from the kill)": lambda i: mid_evaluate(ws, env, root / f"kill{i}", "kill"),
            "server hung mid-evaluate, request_timeout 5 s (from the stop)": lambda i: mid_evaluate(
                ws, dict(env, MLFLOW_HTTP_REQUEST_TIMEOUT="5"), root / f"hang{i}", "hang"
            ),
        }
        if pg_uri:
            cases["database URI, PostgreSQL stopped"] = lambda i: timed_evaluate(
                ws, dict(env, MLFLOW_TRACKING_URI=pg_uri)
            )
        print(f"{'case':62} {'s to line':>9}  exit  lines  the line")
        for name, case in cases.items():
            results = [case(i) for i in range(args.runs)]
            median = statistics.median(r["seconds"] for r in results)
            codes = ",".join(str(r["code"]) for r in results)
            lines = ",".join(str(r["n_lines"]) for r in results)
            print(f"{name:62} {median:9.2f}  {codes:5} {lines:6} {results[-1]['line'][:240]}", flush=True)
        close_silent()
    finally:
        if args.workdir is None:
            shutil.rmtree(root, ignore_errors=True)
        if "pg_home" in locals():
            shutil.rmtree(pg_home, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
