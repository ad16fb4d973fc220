"""Two promotions of one run at once register it once.

A workspace's promotion lock serialises promotions of one clone; two clones promoting the same sweep on one server
are not serialised by anything local, and each created a version of the same run. Registration is idempotent per run
(:func:`aumesh.tracking.registry.register_model_version`). Fast: a real SQLite store where a concurrent registration
of the run lands between our look-up and our create (the race the lowest-version rule settles). Slow: two `aumesh
promote --sweep ID` processes at once, in two clones, against `aumesh server` on a real PostgreSQL
(tests/test_team_postgres.py's fixtures).
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from aumesh.tracking import mlflow_store, registry
from aumesh.tracking import runs as tracking


def _run_with_a_model() -> str:
    with tracking.tracked_run({}, run_name="registered-once", params=None) as run:
        pass
    mlflow_store.get_client({}).log_text(run.run_id, "flavors: {}\n", "model/MLmodel")
    return run.run_id


def test_a_run_registered_by_two_promotions_at_once_keeps_one_version(monkeypatch):
    from mlflow import MlflowClient

    run_id = _run_with_a_model()
    real = MlflowClient.create_model_version
    raced: list[str] = []

    def racing(self, name, source, run_id=None, **kwargs):
        if not raced:  # the other clone's promotion creates its version between our look-up and our create
            raced.append(real(self, name, source, run_id=run_id, tags={"who": "other"}).version)
        return real(self, name, source, run_id=run_id, **kwargs)

    monkeypatch.setattr(MlflowClient, "create_model_version", racing)
    got = registry.register_model_version(run_id, "model", "once", {}, tags={"who": "me"})
    client = mlflow_store.get_client({})
    versions = [v for v in client.search_model_versions(f"run_id = '{run_id}'") if v.name == "once"]
    assert raced == [versions[0].version] and [str(v.version) for v in versions] == ["1"]  # ours (2) was deleted
    assert got["version"] == "1" and got["reused"] is True
    assert versions[0].tags["who"] == "me"  # this promotion's tags on the version it names
    assert registry.model_version_by_alias("once", "champion", {})["version"] == "1"
    again = registry.register_model_version(run_id, "model", "once", {})  # promoting it again registers nothing
    assert again["version"] == "1" and again["reused"] is True
    assert len(client.search_model_versions(f"run_id = '{run_id}'")) == 1


def test_another_run_gets_its_own_version():
    first, second = _run_with_a_model(), _run_with_a_model()
    a = registry.register_model_version(first, "model", "two-runs", {})
    b = registry.register_model_version(second, "model", "two-runs", {})
    assert (a["version"], a["reused"], b["version"], b["reused"]) == ("1", False, "2", False)
    assert registry.model_version_by_alias("two-runs", "champion", {})["run_id"] == second


# ------------------------------------------------------------------ slow: a real server on PostgreSQL
@pytest.mark.slow
@pytest.mark.server
def test_two_promotes_at_once_in_two_clones_register_one_version(server, tmp_path):
    from mlflow import MlflowClient

    from test_sweep import make_workspace
    from test_team_postgres import USERS, _env, _run

    clones = {}
    for name, email in USERS.items():
        ws = make_workspace(tmp_path / name / "aumesh")
        _run(["git", "init", "-q"], cwd=ws)
        _run(["git", "config", "user.email", email], cwd=ws)
        (ws / "aumesh.local.yaml").write_text(f"tracking:\n  tracking_uri: {server}\n")
        clones[name] = ws
    alice = clones["alice"]
    _run([sys.executable, "-m", "aumesh", "sweep", "-m", "model.n_components=2,3"], cwd=alice, env=_env(alice))
    (parent_file,) = (alice / "build" / "sweeps").glob("*/mlflow_parent.json")
    sweep = json.loads(parent_file.read_text())["run_id"]
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "aumesh", "promote", "--sweep", sweep, "--model-name", "aumesh-concurrent"],
            cwd=ws,
            env=_env(ws),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for ws in clones.values()
    ]
    outs = [p.communicate(timeout=600)[0] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], outs
    records = [json.loads((ws / "promotion.json").read_text())["promoted"] for ws in clones.values()]
    assert records[0]["run_id"] == records[1]["run_id"]
    client = MlflowClient(tracking_uri=server)
    versions = [
        v for v in client.search_model_versions(f"run_id = '{records[0]['run_id']}'") if v.name == "aumesh-concurrent"
    ]
    assert len(versions) == 1, [(v.version, v.tags) for v in versions]
    assert {r["model_version"] for r in records} == {str(versions[0].version)}
    assert str(client.get_model_version_by_alias("aumesh-concurrent", "champion").version) == str(versions[0].version)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """tests/test_team_postgres.py's PostgreSQL cluster and `aumesh server` on it, for this module."""
    from test_team_postgres import postgres as pg_fixture
    from test_team_postgres import server as server_fixture

    timings: dict[str, float] = {}
    pg = pg_fixture.__wrapped__(timings)
    url = next(pg)
    srv = server_fixture.__wrapped__(url, tmp_path_factory, timings)
    try:
        yield next(srv)
    finally:
        srv.close()
        pg.close()
