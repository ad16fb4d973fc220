"""A team on one tracking store: whose and where every run is, `aumesh runs --sweeps --mine/--user`, a bare
`aumesh promote` taking the caller's own sweep (not a teammate's newer one), `--across` ranking everyone's runs on
the same data, the overrule check limited to the caller's clone; where a run executes (tracking, compute) neither
stales the pipeline nor is promoted nor lands in a shared record; which store wins (environment, aumesh.local.yaml,
conf/, default) and the PostgreSQL driver spelling.

Two clones (git repositories with their own user.email) share one SQLite store, as two teammates share a server.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
import yaml

from aumesh import cli, config
from aumesh.core import provenance
from aumesh.experiments import promote, sweep_cache, sweep_child
from aumesh.tracking import mlflow_store, queries
from aumesh.tracking import runs as tracking
from conftest import new_store
from test_sweep import make_workspace

REPO = Path(__file__).resolve().parents[1]
USERS = {"alice": "alice@lab.example", "bob": "bob@lab.example"}


def _git(ws: Path, *args: str) -> None:
    subprocess.run(["git", *args], cwd=ws, check=True, capture_output=True)


def _sweep(
    ws: Path, grid: list[list[str]], cache: sweep_cache.SweepCache, mp: pytest.MonkeyPatch
) -> tuple[str, list[str]]:
    """A sweep from clone *ws* (its cwd, so its identity): a parent and one child per configuration."""
    mp.chdir(ws)
    parent = tracking.start_parent_run({}, f"sweep of {ws.name}", tags={"aumesh.sweep.overrides": str(grid)})
    ids = []
    for ov in grid:
        result = sweep_child.run_configuration(
            config.compose(ov, config_dir=ws / "conf"), ov, parent, cache=cache, root=ws
        )
        assert result["status"] == "FINISHED", result
        ids.append(result["run_id"])
    tracking.finish_sweep(parent, {})
    return parent, ids


@pytest.fixture(scope="module")
def team(tmp_path_factory):
    """Alice's and Bob's clones on one store; Alice sweeps first, Bob 1 s later (the team's latest sweep is his)."""
    store = new_store(tmp_path_factory.mktemp("aumesh-test-team-store") / "mlflow.db")
    clones = {}
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{store}")  # "aumesh-test" in the path: conftest keeps it
        for var in ("DVC_ROOT", "DVC_EXP_NAME", "AUMESH_SWEEP_PARENT_RUN_ID", "AUMESH_USER", "AUMESH_LOCAL_SETTINGS"):
            mp.delenv(var, raising=False)
        for name, email in USERS.items():
            ws = make_workspace(tmp_path_factory.mktemp(name) / "aumesh")
            _git(ws, "init", "-q")
            _git(ws, "config", "user.email", email)
            _git(ws, "remote", "add", "origin", "https://git.lab.example/aumesh.git")  # one remote, two clones
            clones[name] = ws
        cache = sweep_cache.SweepCache()
        sweeps = {
            "alice": _sweep(clones["alice"], [["model.n_components=1"]], cache, mp),
            "bob": _sweep(clones["bob"], [["model.n_components=2"], ["model.n_components=6"]], cache, mp),
        }
        yield {"clones": clones, "sweeps": sweeps, "mp": mp}


def _as(team, name: str) -> Path:
    team["mp"].chdir(team["clones"][name])
    return team["clones"][name]


def test_every_run_names_its_user_and_clone(team):
    client = mlflow_store.get_client({})
    ids = {provenance.workspace_id(ws) for ws in team["clones"].values()}
    assert len(ids) == 2 and all(len(i) == 16 for i in ids)  # same remote, other path: other clone
    for name, (parent, children) in team["sweeps"].items():
        expected = {
            "aumesh.user": USERS[name],
            "mlflow.user": USERS[name],
            "aumesh.workspace.id": provenance.workspace_id(team["clones"][name]),
        }
        for run_id in [parent, *children]:
            tags = client.get_run(run_id).data.tags
            assert {k: tags.get(k) for k in expected} == expected
    # stable: the same clone gets the same id again, from a subfolder too
    ws = _as(team, "alice")
    assert queries.current_owner()["workspace"] == provenance.workspace_id(ws)
    team["mp"].chdir(ws / "conf")
    owner = queries.current_owner()
    assert {k: owner[k] for k in ("user", "workspace")} == {
        "user": USERS["alice"],
        "workspace": provenance.workspace_id(ws),
    }
    assert owner["workspaces"][0] == owner["workspace"]  # then the ids of before (tests/test_workspace_identity.py)


def test_runs_sweeps_shows_owners_and_filters_mine_and_user(team, capsys):
    _as(team, "alice")
    (alice, _), (bob, _) = team["sweeps"]["alice"], team["sweeps"]["bob"]
    capsys.readouterr()
    assert cli.main(["runs", "--sweeps", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [(r["sweep"], r["user"]) for r in rows] == [(bob, USERS["bob"]), (alice, USERS["alice"])]  # newest first
    assert cli.main(["runs", "--sweeps"]) == 0
    text = capsys.readouterr().out
    assert "user" in text.splitlines()[0] and USERS["bob"] in next(ln for ln in text.splitlines() if ln.startswith(bob))
    assert cli.main(["runs", "--sweeps", "--mine", "--json"]) == 0
    assert [r["sweep"] for r in json.loads(capsys.readouterr().out)] == [alice]
    assert cli.main(["runs", "--sweeps", "--user", USERS["bob"], "--json"]) == 0
    assert [r["sweep"] for r in json.loads(capsys.readouterr().out)] == [bob]
    assert cli.main(["runs", "--sweeps", "--user", "nobody@lab.example"]) == 0
    assert "(no sweeps" in capsys.readouterr().out
    # a bare `aumesh runs` shows the caller's own latest sweep, not the team's latest
    assert cli.main(["runs"]) == 0
    assert capsys.readouterr().out.startswith(f"sweep {alice} ")


def test_bare_promote_takes_your_own_sweep_and_only_your_evaluate_runs_overrule(team, capsys):
    ws = _as(team, "alice")
    alice_parent, alice_children = team["sweeps"]["alice"]
    # Bob's pipeline run (a `dvc exp run` of his), after both sweeps, of another configuration
    team["mp"].chdir(team["clones"]["bob"])
    with tracking.tracked_run(
        {},
        "bob: absolute au_pose_interactions k=20",
        config.compose(["model.n_components=20"], config_dir=team["clones"]["bob"] / "conf"),
        tags={"aumesh.stage": "evaluate"},
    ):
        pass
    _as(team, "alice")
    capsys.readouterr()
    assert cli.main(["promote", "--no-register"]) == 0  # Bob's run is his: it does not stop Alice
    out = capsys.readouterr().out
    assert f"your latest sweep: {alice_parent}" in out
    record = json.loads((ws / "promotion.json").read_text())["promoted"]
    assert (record["parent_run_id"], record["run_id"]) == (alice_parent, alice_children[0])
    assert (record["user"], record["workspace"]) == (USERS["alice"], provenance.workspace_id(ws))
    # Alice's own newer pipeline run of another configuration does stop her
    with tracking.tracked_run(
        {},
        "alice: k=20",
        config.compose(["model.n_components=20"], config_dir=ws / "conf"),
        tags={"aumesh.stage": "evaluate"},
    ) as newer:
        pass
    assert cli.main(["promote", "--no-register"]) == 2
    assert f"older than evaluate run {newer.run_id}" in capsys.readouterr().err
    # a sweep named with --sweep, anyone's, is taken as it is
    bob_parent, _ = team["sweeps"]["bob"]
    assert cli.main(["promote", "--sweep", bob_parent, "--no-register"]) == 0
    record = json.loads((ws / "promotion.json").read_text())["promoted"]
    assert record["parent_run_id"] == bob_parent and record["user"] == USERS["bob"]


def test_promote_across_ranks_everyones_runs_on_the_data_and_says_whose_won(team, capsys):
    ws = _as(team, "alice")
    # the reference: every FINISHED sweep child of both clones, best r2_mean (same target: comparable)
    import pandas as pd

    children = pd.concat([queries.list_child_runs(p, {}) for p, _ in team["sweeps"].values()])
    best = children[children["status"] == "FINISHED"].sort_values("metrics.r2_mean", ascending=False).iloc[0]
    assert best["user"] == USERS["bob"]  # 6 components beat 1 on these tables: the teammate's run should win
    capsys.readouterr()
    assert cli.main(["promote", "--across", "--no-register"]) == 0
    out = capsys.readouterr().out
    record = json.loads((ws / "promotion.json").read_text())["promoted"]
    assert record["run_id"] == best["run_id"] and record["across"] is True
    assert record["user"] == USERS["bob"] and record["parent_run_id"] == team["sweeps"]["bob"][0]
    assert f"{USERS['bob']}'s run {best['run_id']} won" in out
    assert "whoever ran them" in record["criterion"]
    # the evaluate runs logged above (params only, no metrics) are candidates without the metric: not ranked
    assert record["n_candidates"] == 3
    assert yaml.safe_load((ws / "conf" / "experiment" / "promoted.yaml").read_text())["model"]["n_components"] == 6


def test_a_cluster_run_on_a_server_promotes_what_it_is_not_where_it_ran(team, tmp_path):
    """A sweep child run with compute=distributed on a scheduler and a tracking server address in its params:
    promotion writes neither into conf/, params.yaml or promotion.json."""
    ws = _as(team, "alice")
    before = yaml.safe_load((ws / "params.yaml").read_text())
    where = [
        "compute=distributed",
        "compute.address=tcp://10.0.0.5:8786",
        "compute.partition_rows=1000",
        "tracking.tracking_uri=http://10.0.0.9:5000",
        "tracking.experiment=aumesh",
    ]
    raw = config.compose(["model.n_components=3", *where], config_dir=ws / "conf")
    parent = tracking.start_parent_run({}, "cluster sweep")
    with tracking.tracked_run(
        {}, "k=3 on the cluster", raw, tags={"aumesh.role": "sweep-child"}, parent_run_id=parent
    ) as run:
        run.log_metrics({"r2_mean": 0.5, "n_components": 3.0})
    tracking.end_run(parent)
    params = queries.run_record(run.run_id, {})["params"]
    assert params["model.n_components"] == "3"
    assert not [k for k in params if k.startswith(("compute.", "tracking."))]  # where it ran is no part of the run
    record = promote.promote(parent, ws, {}, register=False)
    exp = yaml.safe_load((ws / "conf" / "experiment" / "promoted.yaml").read_text())
    assert exp == {
        "preprocess": {"target": "absolute", "neutral": {"method": "low_au"}},
        "features": {"name": "au_pose_interactions"},
        "model": {"n_components": 3, "scale": True, "clip_n_components": True},
    }
    after = yaml.safe_load((ws / "params.yaml").read_text())
    assert after["compute"] == before["compute"] and after["tracking"] == before["tracking"]
    shared = (ws / "promotion.json").read_text() + (ws / "params.yaml").read_text()
    assert "10.0.0." not in shared and str(ws) not in shared
    assert record["tracking_uri"] == mlflow_store.EXTERNAL_STORE  # the test's store is outside the clone


def test_no_stage_has_where_parameters():
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    for name, stage in stages.items():
        for param in stage.get("params", []):
            key = param if isinstance(param, str) else next(iter(param))
            assert not key.startswith(("tracking", "compute", "paths")), f"{name}: {key}"


# ------------------------------------------------------------------ which store wins
def test_store_order_environment_then_local_settings_then_conf_then_default(tmp_path, monkeypatch):
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "dvc.yaml").write_text("stages: {}\n")
    monkeypatch.chdir(ws)
    for var in ("MLFLOW_TRACKING_URI", "AUMESH_LOCAL_SETTINGS", "DVC_ROOT"):
        monkeypatch.delenv(var, raising=False)
    resolve = mlflow_store.resolve_tracking_uri
    assert resolve({}) == f"sqlite:///{ws.resolve()}/mlflow.db"
    assert resolve({"tracking_uri": "sqlite:///team.db"}) == f"sqlite:///{ws.resolve()}/team.db"
    (ws / "aumesh.local.yaml").write_text("tracking:\n  tracking_uri: http://10.0.0.9:5000\n")
    assert resolve({"tracking_uri": "sqlite:///team.db"}) == "http://10.0.0.9:5000"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:5999")
    assert resolve({"tracking_uri": "sqlite:///team.db"}) == "http://127.0.0.1:5999"
    # the file is git-ignored (the repo's .gitignore): a teammate's server never gets committed
    assert "/aumesh.local.yaml" in (REPO / ".gitignore").read_text().splitlines()
    # a broken settings file is one line naming it
    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    (ws / "aumesh.local.yaml").write_text("trackng:\n  tracking_uri: x\n")
    from aumesh.core.errors import ConfigError

    with pytest.raises(ConfigError, match="aumesh.local.yaml: unknown group.*trackng"):
        resolve({})


def test_shared_records_name_no_server(tmp_path, monkeypatch):
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "dvc.yaml").write_text("stages: {}\n")
    monkeypatch.chdir(ws)
    label = mlflow_store.store_label
    assert label(f"sqlite:///{ws}/mlflow.db", ws) == "sqlite:///mlflow.db"
    for uri in (
        "http://10.0.0.9:5000",
        "https://user:pw@mlflow.lab.example",
        "sqlite:////elsewhere/mlflow.db",
        "postgresql+psycopg2://mlflow:pw@db:5432/mlflow",
        f"file://{tmp_path}/other",
    ):
        assert label(uri, ws) == mlflow_store.EXTERNAL_STORE


def test_postgresql_uri_gets_the_installed_driver():
    """SQLAlchemy 2 reads a driverless postgresql:// as psycopg 3; with psycopg2 installed that fails to load. The
    rewritten URI loads a dialect whose driver imports (SQLAlchemy itself is the reference; no connection)."""
    import importlib.util

    import sqlalchemy

    uri = "postgresql://mlflow:pw@127.0.0.1:5432/mlflow"
    if importlib.util.find_spec("psycopg") is None and importlib.util.find_spec("psycopg2") is None:
        from aumesh.core.errors import ConfigError

        with pytest.raises(ConfigError, match=r"aumesh\[postgres\]"):
            mlflow_store.database_uri(uri)
        return
    fixed = mlflow_store.database_uri(uri)
    assert fixed.startswith(("postgresql+psycopg2://", "postgresql+psycopg://")) and fixed.endswith(
        "@127.0.0.1:5432/mlflow"
    )
    assert sqlalchemy.create_engine(fixed).dialect.driver in ("psycopg2", "psycopg")
    if importlib.util.find_spec("psycopg") is None:  # the defect this fixes
        with pytest.raises(ModuleNotFoundError, match="psycopg"):
            sqlalchemy.create_engine(uri)
    assert mlflow_store.database_uri("postgresql+psycopg2://a@b/c") == "postgresql+psycopg2://a@b/c"
    assert mlflow_store.database_uri("sqlite:///x.db") == "sqlite:///x.db"
