"""`dvc exp run --queue -S model.n_components=10,40` + `dvc queue start`: the queued runs (in DVC temp copies
under .dvc/tmp/exps/) compose params.yaml from conf/, log their `evaluate` runs to the workspace's mlflow.db,
and compare with the committed baseline in `dvc exp show`, `dvc metrics diff` and `dvc plots diff`.

Slow (two full pipeline runs on the demo data): `make test-slow`. Runs in a temporary `git clone` of this
checkout's HEAD (committed code only, via PYTHONPATH; the checkout's venv linked in as the clone's .venv/),
never in the working tree; skipped when git, dvc or the demo remote are unavailable.
"""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from conftest import REPO

QUEUE_TIMEOUT_S = 1500.0
PATHS = yaml.safe_load((REPO / "conf" / "paths" / "default.yaml").read_text())
METRICS, ERROR_CURVE, R2_CURVE = PATHS["metrics_file"], PATHS["error_curve_file"], PATHS["r2_curve_file"]

pytestmark = pytest.mark.slow


def _run(args: list[str], cwd: Path, env: dict, timeout: float = 600.0) -> subprocess.CompletedProcess:
    proc = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise AssertionError(
            f"{' '.join(args)} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
        )
    return proc


def _evaluate_runs(db: Path) -> list[tuple[str, str, str]]:
    """(run_uuid, status, model.n_components) of every `evaluate` run of the AU model in an MLflow SQLite store (the
    stage's family fits, tagged aumesh.family blendshapes / emotions, are runs of their own)."""
    if not db.exists():
        return []
    with sqlite3.connect(db) as con:
        return con.execute(
            "SELECT r.run_uuid, r.status, p.value FROM runs r "
            "JOIN tags t ON t.run_uuid = r.run_uuid AND t.key = 'aumesh.stage' AND t.value = 'evaluate' "
            "JOIN params p ON p.run_uuid = r.run_uuid AND p.key = 'model.n_components' "
            "JOIN tags f ON f.run_uuid = r.run_uuid AND f.key = 'aumesh.family' AND f.value = 'au'"
        ).fetchall()


def _rows(shown: list) -> dict[str, dict]:
    """``{rev: {"name", "metrics", "n_components"}}`` of every row (commits and experiments) of `dvc exp show --json`."""
    rows: dict[str, dict] = {}

    def visit(node):
        if isinstance(node, list):
            for item in node:
                visit(item)
        elif isinstance(node, dict):
            data = node.get("data")
            if "rev" in node and isinstance(data, dict) and "metrics" in data:
                metrics = (data.get("metrics") or {}).get(METRICS, {}).get("data") or {}
                params = (data.get("params") or {}).get("params.yaml", {}).get("data") or {}
                rows[node["rev"]] = {
                    "name": node.get("name"),
                    "metrics": metrics,
                    "n_components": (params.get("model") or {}).get("n_components"),
                }
            for value in node.values():
                visit(value)

    visit(shown)
    return rows


def test_queued_experiments_compare_with_the_committed_baseline_and_log_to_the_workspace_store(fresh_clone):
    ws, env = fresh_clone
    # as a user who activated the venv: `dvc queue start` spawns its worker as `dvc` looked up on PATH
    env = env | {"PATH": os.pathsep.join([str(ws / ".venv" / "bin"), env["PATH"]])}
    dvc = str(ws / ".venv" / "bin" / "dvc")
    _run([dvc, "pull", "-q", "--allow-missing"], ws, env)  # what `make demo` pulls: the tables and the outputs
    out = _run([dvc, "exp", "run", "--queue", "-S", "model.n_components=10,40"], ws, env).stdout
    assert out.count("Queued experiment") == 2, out
    _run([dvc, "queue", "start", "-j", "1"], ws, env)
    deadline = time.monotonic() + QUEUE_TIMEOUT_S
    while True:
        status = _run([dvc, "queue", "status"], ws, env).stdout
        if not any(s in status for s in ("Queued", "Running")):
            break
        if time.monotonic() > deadline:
            pytest.fail(f"queue not done after {QUEUE_TIMEOUT_S}s:\n{status}")
        time.sleep(5)
    assert status.count("Success") == 2, status
    runs = _evaluate_runs(ws / "mlflow.db")  # the clone's (= workspace's) store, not the temp copies'
    assert sorted(v for _, s, v in runs if s == "FINISHED") == ["10", "40"], runs
    assert not list((ws / ".dvc" / "tmp" / "exps").glob("tmp*/mlflow.db"))

    # the committed baseline and both experiments have numbers (metrics are committed with git, not cached)
    head = _run(["git", "rev-parse", "HEAD"], ws, env).stdout.strip()
    rows = _rows(json.loads(_run([dvc, "exp", "show", "--json"], ws, env).stdout))
    exps = {r["n_components"]: rev for rev, r in rows.items() if rev not in (head, "workspace")}
    assert set(exps) == {10, 40}, rows
    r2 = {rev: rows[rev]["metrics"].get("r2_mean") for rev in (head, exps[10], exps[40])}
    assert all(isinstance(v, float) and 0.0 < v < 1.0 for v in r2.values()), rows
    # the baseline's committed R²-vs-n_components curve predicts each experiment's CV R² (same folds; kernel PLS
    # gives every smaller n_components exactly): plot data and experiments agree to the committed precision
    curve = dict(line.split(",") for line in (ws / R2_CURVE).read_text().splitlines()[1:])
    for k in (10, 40):
        assert abs(float(curve[str(k)]) - r2[exps[k]]) <= 2e-6 * abs(r2[exps[k]]), (k, curve[str(k)], r2[exps[k]])

    diff = json.loads(_run([dvc, "metrics", "diff", head, exps[10], "--json"], ws, env).stdout)
    assert diff[METRICS]["r2_mean"]["old"] == r2[head] and diff[METRICS]["r2_mean"]["new"] == r2[exps[10]], diff
    plots = json.loads(_run([dvc, "plots", "diff", head, exps[10], "--json"], ws, env).stdout)
    for name, n in ((ERROR_CURVE, 2 * 101), (R2_CURVE, 83 + 10)):
        values = plots["data"][name][0]["content"]["data"]["values"]
        assert len(values) == n and len({v["rev"] for v in values}) == 2, name
    _run([dvc, "exp", "remove", "--all-commits", "-q"], ws, env)
