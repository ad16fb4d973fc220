"""`dvc exp run --queue -S model.n_components=10,40` + `dvc queue start`: the queued runs (in DVC temp copies
under .dvc/tmp/exps/) compose params.yaml from conf/ and log their `evaluate` runs to the workspace's mlflow.db.

Slow (two full pipeline runs on the demo data): `make test-slow`. Runs in a temporary `git clone` of this
checkout's HEAD (committed code only, via PYTHONPATH), never in the working tree; skipped when git, dvc or
the demo remote are unavailable.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BIN = REPO / ".venv" / "bin"
QUEUE_TIMEOUT_S = 1500.0

pytestmark = pytest.mark.slow


def _run(args: list[str], cwd: Path, env: dict, timeout: float = 600.0) -> subprocess.CompletedProcess:
    proc = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise AssertionError(f"{' '.join(args)} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


@pytest.fixture
def clone(tmp_path) -> tuple[Path, dict]:
    if shutil.which("git") is None or not (BIN / "dvc").exists() or not (REPO / ".git").exists():
        pytest.skip("needs git, .venv/bin/dvc and a git checkout")
    if not (REPO / "demo-remote").is_dir():
        pytest.skip("the committed demo DVC remote (demo-remote/) is missing")
    ws = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", str(REPO), str(ws)], check=True, capture_output=True)
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("MLFLOW_", "DVC_", "AUMESH_")) and k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env.update(PATH=f"{BIN}:{env.get('PATH', '')}", PYTHONPATH=str(ws / "src"),  # the clone's code, not the checkout's
               GIT_AUTHOR_NAME="t", GIT_AUTHOR_EMAIL="t@example.com", GIT_COMMITTER_NAME="t",
               GIT_COMMITTER_EMAIL="t@example.com", MLFLOW_DISABLE_TELEMETRY="true", DO_NOT_TRACK="true")
    _run(["dvc", "pull", "-q", "data.dvc"], ws, env)  # the remote holds the data; build/ and release/ are rebuilt
    return ws, env


def _evaluate_runs(db: Path) -> list[tuple[str, str, str]]:
    """(run_uuid, status, model.n_components) of every `evaluate` run in an MLflow SQLite store."""
    if not db.exists():
        return []
    with sqlite3.connect(db) as con:
        return con.execute(
            "SELECT r.run_uuid, r.status, p.value FROM runs r "
            "JOIN tags t ON t.run_uuid = r.run_uuid AND t.key = 'aumesh.stage' AND t.value = 'evaluate' "
            "JOIN params p ON p.run_uuid = r.run_uuid AND p.key = 'model.n_components'").fetchall()


def test_queued_experiments_log_to_the_workspace_store(clone):
    ws, env = clone
    out = _run(["dvc", "exp", "run", "--queue", "-S", "model.n_components=10,40"], ws, env).stdout
    assert out.count("Queued experiment") == 2, out
    _run(["dvc", "queue", "start", "-j", "1"], ws, env)
    deadline = time.monotonic() + QUEUE_TIMEOUT_S
    while True:
        status = _run(["dvc", "queue", "status"], ws, env).stdout
        if not any(s in status for s in ("Queued", "Running")):
            break
        if time.monotonic() > deadline:
            pytest.fail(f"queue not done after {QUEUE_TIMEOUT_S}s:\n{status}")
        time.sleep(5)
    assert status.count("Success") == 2, status
    runs = _evaluate_runs(ws / "mlflow.db")  # the clone's (= workspace's) store, not the temp copies'
    assert sorted(v for _, s, v in runs if s == "FINISHED") == ["10", "40"], runs
    assert not list((ws / ".dvc" / "tmp" / "exps").glob("tmp*/mlflow.db"))
    shown = _run(["dvc", "exp", "show", "--csv", "--no-pager"], ws, env).stdout
    assert "model.n_components" in shown.splitlines()[0]
    _run(["dvc", "exp", "remove", "--all-commits", "-q"], ws, env)
