"""End-to-end: a real ``mlflow server`` on 127.0.0.1 with a SQLite backend, runs logged over HTTP."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from aumesh.experiments import mlflow_store, queries, tracking

pytestmark = pytest.mark.server

STARTUP_TIMEOUT_S = 90.0  # ~20 s on a loaded 2-core box; bounded so a broken server fails the test


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _healthy(url: str) -> bool:
    try:
        with urllib.request.urlopen(f"{url}/health", timeout=2) as resp:
            return resp.status == 200
    except (urllib.error.URLError, ConnectionError, OSError):
        return False


def _stop(proc: subprocess.Popen) -> None:
    """Terminate the server's whole process group (uvicorn workers included), then reap."""
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(timeout=10)


@pytest.fixture(scope="module")
def mlflow_server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mlflow_server")
    port = _free_port()
    url = f"http://127.0.0.1:{port}"
    # No job runner (huey consumers for GenAI jobs): halves start-up time and CPU.
    env = dict(os.environ, MLFLOW_DISABLE_TELEMETRY="true", DO_NOT_TRACK="true",
               MLFLOW_SERVER_ENABLE_JOB_EXECUTION="false")
    env.pop("MLFLOW_TRACKING_URI", None)
    log = open(tmp / "server.log", "w")
    cmd = [
        sys.executable, "-m", "mlflow", "server",
        "--backend-store-uri", f"sqlite:///{tmp / 'mlflow.db'}",
        "--artifacts-destination", str(tmp / "mlartifacts"),
        "--host", "127.0.0.1", "--port", str(port), "--workers", "1",
    ]
    proc = subprocess.Popen(cmd, cwd=tmp, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not _healthy(url):
            if proc.poll() is not None:
                pytest.fail(f"mlflow server exited with {proc.returncode}:\n{(tmp / 'server.log').read_text()[-3000:]}")
            if time.monotonic() > deadline:
                pytest.fail(f"mlflow server not healthy after {STARTUP_TIMEOUT_S}s:\n"
                            f"{(tmp / 'server.log').read_text()[-3000:]}")
            time.sleep(0.25)
        yield url
    finally:
        _stop(proc)
        log.close()


def test_parent_and_children_over_http(mlflow_server, tmp_path, monkeypatch):
    from mlflow import MlflowClient

    monkeypatch.setenv("MLFLOW_TRACKING_URI", mlflow_server)
    monkeypatch.chdir(Path(__file__).resolve().parents[1])  # provenance tags from the project checkout
    cfg = {"enabled": True, "experiment": "server-test"}
    assert mlflow_store.resolve_tracking_uri(cfg) == mlflow_server

    parent = tracking.start_parent_run(cfg, "sweep", params={"sweep": {"k": [2, 4]}})
    children = []
    for k in (2, 4):
        with tracking.tracked_run(cfg, f"k={k}", {"model": {"n_components": k}}, parent_run_id=parent) as run:
            run.log_fold_metrics({"r2": [0.1 * k, 0.1 * k + 0.01, 0.1 * k + 0.02]})
            run.log_config({"model": {"n_components": k}})
            children.append(run.run_id)
    tracking.end_run(parent, cfg)

    client = MlflowClient(tracking_uri=mlflow_server)
    assert client.get_run(parent).info.status == "FINISHED"
    for rid, k in zip(children, (2, 4)):
        got = client.get_run(rid)
        assert got.info.status == "FINISHED"
        assert got.data.tags["mlflow.parentRunId"] == parent
        assert got.data.params["model.n_components"] == str(k)
        assert [m.step for m in sorted(client.get_metric_history(rid, "r2"), key=lambda m: m.step)] == [0, 1, 2]
        assert "config.yaml" in {a.path for a in client.list_artifacts(rid)}  # proxied upload via the server
    df = queries.list_child_runs(parent, cfg)
    assert sorted(df["run_id"]) == sorted(children)
