"""Offline tests of aumesh.tracking.runs / .beside / .handle / aumesh.core.provenance against a temporary SQLite store."""

from __future__ import annotations

import shutil
import subprocess
import uuid
from pathlib import Path

import pytest

from aumesh.core import provenance
from aumesh.tracking import beside, experiment, mlflow_store, queries, values
from aumesh.tracking import runs as tracking
from conftest import new_store

MD5 = "0123456789abcdef0123456789abcdef.dir"
DVC_FILE = f"""outs:
- md5: {MD5}
  size: 12345
  nfiles: 7
  hash: md5
  path: data
"""


def _git(ws: Path, *args: str) -> str:
    out = subprocess.run(
        ["git", "-c", "user.email=t@example.com", "-c", "user.name=t", "-c", "commit.gpgsign=false", *args],
        cwd=ws,
        capture_output=True,
        text=True,
        check=True,
    )
    return out.stdout.strip()


@pytest.fixture(scope="module")
def store_uri(tmp_path_factory) -> str:
    """One SQLite store per module (schema creation costs ~1 s); tests use distinct experiments."""
    return f"sqlite:///{new_store(tmp_path_factory.mktemp('store') / 'mlflow.db')}"


@pytest.fixture
def workspace(tmp_path, monkeypatch) -> Path:
    """A throwaway aumesh-like workspace: git repo with dvc.yaml and data.dvc, as cwd."""
    ws = tmp_path / "ws"
    ws.mkdir()
    (ws / "dvc.yaml").write_text("stages: {}\n")
    (ws / "data.dvc").write_text(DVC_FILE)
    for var in ("MLFLOW_TRACKING_URI", "DVC_ROOT", "DVC_EXP_BASELINE_REV", "DVC_EXP_NAME", "DVC_STAGE"):
        monkeypatch.delenv(var, raising=False)
    if shutil.which("git"):
        _git(ws, "init", "-q")
        _git(ws, "add", "dvc.yaml", "data.dvc")
        _git(ws, "commit", "-q", "-m", "init")
    monkeypatch.chdir(ws)
    return ws


@pytest.fixture
def cfg(store_uri, workspace, monkeypatch) -> dict:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", store_uri)
    return {"enabled": True, "experiment": f"test-{uuid.uuid4().hex[:8]}"}


def _client(uri: str):
    from mlflow import MlflowClient

    return MlflowClient(tracking_uri=uri)


# ----------------------------------------------------------------------------- the experiment
def test_experiment_is_model_training_with_a_description(cfg, store_uri, workspace):
    """MLflow 3 opens a model-training experiment on its runs (not GenAI traces); the description says what aumesh
    is, which data (the DVC hash of data.dvc) and where to read more."""
    import mlflow.utils.mlflow_tags

    with tracking.tracked_run(cfg, "fit", {"a": 1}):
        pass
    client = _client(store_uri)
    exp = client.get_experiment_by_name(cfg["experiment"])
    tags = exp.tags
    # MLflow's own names: the experiment-kind tag its UI reads, and the note tag it shows as the description
    assert experiment.NOTE_TAG == mlflow.utils.mlflow_tags.MLFLOW_RUN_NOTE  # "mlflow.note.content"
    assert tags["mlflow.experimentKind"] == "custom_model_development"
    note = tags["mlflow.note.content"]
    assert note.startswith("**aumesh**") and MD5 in note and "README" in note and "Tracking" in note
    assert "http" not in note  # a pointer, not a link
    assert tags["aumesh.data.md5"] == MD5 and tags["aumesh.project"] == "aumesh"
    # an experiment made before (no tags) gets them with the next run; a description edited in the UI is kept
    other = client.create_experiment(f"{cfg['experiment']}-old")
    client.set_experiment_tag(other, "mlflow.note.content", "my notes")
    with tracking.tracked_run(cfg | {"experiment": f"{cfg['experiment']}-old"}, "fit", None):
        pass
    tags = client.get_experiment(other).tags
    assert tags["mlflow.experimentKind"] == "custom_model_development" and tags["mlflow.note.content"] == "my notes"


def test_a_dataset_another_run_created_at_the_same_moment_is_linked_on_the_next_attempt():
    """Two sweeps starting together on a PostgreSQL server both insert the data's dataset; the second insert fails on
    the dataset's key (seen in the team test). The dataset exists then: one more attempt links it; other errors and a
    key that never stops clashing are raised."""
    from mlflow.exceptions import MlflowException

    from aumesh.tracking.handle import DATASET_RACE_ATTEMPTS, log_inputs_once_created

    clash = 'BAD_REQUEST: (psycopg2.errors.UniqueViolation) duplicate key value violates unique constraint "dataset_pk"'

    class Client:
        def __init__(self, errors):
            self.errors, self.calls = list(errors), []

        def log_inputs(self, run_id, datasets):
            self.calls.append((run_id, datasets))
            if self.errors:
                raise MlflowException(self.errors.pop(0))

    raced = Client([clash])
    log_inputs_once_created(raced, "run-b", ["frame_tables"], pause_s=0)
    assert raced.calls == [("run-b", ["frame_tables"])] * 2

    sqlite = Client(["UNIQUE constraint failed: datasets.experiment_id, datasets.name, datasets.digest"])
    log_inputs_once_created(sqlite, "run-b", ["frame_tables"], pause_s=0)
    assert len(sqlite.calls) == 2

    other = Client(["RESOURCE_DOES_NOT_EXIST: run 'run-b' not found"])
    with pytest.raises(MlflowException, match="not found"):
        log_inputs_once_created(other, "run-b", ["frame_tables"], pause_s=0)
    assert len(other.calls) == 1

    stuck = Client([clash] * (DATASET_RACE_ATTEMPTS + 1))
    with pytest.raises(MlflowException, match="dataset_pk"):
        log_inputs_once_created(stuck, "run-b", ["frame_tables"], pause_s=0)
    assert len(stuck.calls) == DATASET_RACE_ATTEMPTS


# ----------------------------------------------------------------------------- runs
def test_run_logs_params_metrics_config_dataset_tags(cfg, store_uri, workspace):
    params = {"model": {"n_components": 8, "scale": True}, "anchors": [10, 9, 8], "long": "x" * 7000}
    with tracking.tracked_run(cfg, "fit", params, tags={"stage": "train"}) as run:
        run.log_fold_metrics({"r2": [0.5, 0.6, 0.7], "mae": [0.3, 0.2, 0.1]})
        run.log_metrics({"r2_mean": 0.6})
        run.log_config({"model": {"n_components": 8}, "anchors": [10, 9, 8]})
        run.log_dict({"a": 1}, "extra/a.json")
        digest = provenance.data_digest(workspace)
        run.log_dataset(digest, source=str(workspace / "data"))

    client = _client(store_uri)
    got = client.get_run(run.run_id)
    assert got.info.status == "FINISHED"
    assert got.info.run_name == "fit"
    p = got.data.params
    assert p["model.n_components"] == "8" and p["model.scale"] == "True"
    assert p["anchors"] == "[10, 9, 8]"
    assert len(p["long"]) == values.MAX_PARAM_VALUE_LENGTH and p["long"].endswith(values.TRUNCATION_MARK)

    hist = client.get_metric_history(run.run_id, "r2")
    assert sorted((m.step, m.value) for m in hist) == [(0, 0.5), (1, 0.6), (2, 0.7)]
    assert [m.step for m in sorted(client.get_metric_history(run.run_id, "mae"), key=lambda m: m.step)] == [0, 1, 2]
    assert got.data.metrics["r2_mean"] == pytest.approx(0.6)

    arts = {a.path for a in client.list_artifacts(run.run_id)}
    assert {"config.yaml", "extra"} <= arts
    cfg_text = Path(client.download_artifacts(run.run_id, "config.yaml")).read_text()
    assert "n_components: 8" in cfg_text
    # artifacts land in the workspace (absolute), not ./mlruns of whatever cwd
    assert Path(got.info.artifact_uri.removeprefix("file://")).is_relative_to(workspace / "mlartifacts")

    (ds_in,) = got.inputs.dataset_inputs
    assert ds_in.dataset.digest == MD5 and ds_in.dataset.name == "frame_tables"
    assert str(workspace / "data") in ds_in.dataset.source
    itags = {t.key: t.value for t in ds_in.tags}
    assert itags["dvc.md5"] == MD5 and itags["dvc.nfiles"] == "7" and itags["mlflow.data.context"] == "training"

    tags = got.data.tags
    assert tags["stage"] == "train"
    assert tags["aumesh.data.md5"] == MD5 and tags["aumesh.data.nfiles"] == "7"
    assert tags["aumesh.version"] and tags["aumesh.lib.mlflow"]
    assert tags["aumesh.workspace"] == str(workspace)
    if shutil.which("git"):
        head = _git(workspace, "rev-parse", "HEAD")
        assert tags["aumesh.git.commit"] == head == tags["mlflow.source.git.commit"]
        assert tags["aumesh.git.dirty"] == "false"


def test_exception_marks_run_failed_and_reraises(cfg, store_uri):
    with pytest.raises(RuntimeError, match="boom"):
        with tracking.tracked_run(cfg, "broken", {"a": 1}) as run:
            run.log_metrics({"partial": 1.0})
            raise RuntimeError("boom")
    got = _client(store_uri).get_run(run.run_id)
    assert got.info.status == "FAILED"
    assert got.data.tags[tracking.ERROR_TAG] == "RuntimeError: boom"
    assert got.data.metrics["partial"] == 1.0


def test_parent_and_children_are_linked(cfg, store_uri):
    parent = tracking.start_parent_run(cfg, "sweep", params={"sweep": {"grid": [2, 4]}})
    for k in (2, 4):
        with tracking.tracked_run(cfg, f"k={k}", {"model": {"n_components": k}}, parent_run_id=parent) as child:
            child.log_fold_metrics({"r2": [k / 10, k / 10 + 0.01]})
    tracking.mark_failed(parent, "one config crashed", cfg)

    client = _client(store_uri)
    assert client.get_run(parent).info.status == "FAILED"
    assert client.get_run(parent).data.tags[tracking.ROLE_TAG] == "sweep-parent"
    df = queries.list_child_runs(parent, cfg)
    assert list(df["run_name"]) == ["k=2", "k=4"]
    assert list(df["params.model.n_components"]) == ["2", "4"]
    assert df["metrics.r2"].tolist() == pytest.approx([0.21, 0.41])
    assert (df["status"] == "FINISHED").all()
    for rid in df["run_id"]:
        assert client.get_run(rid).data.tags["mlflow.parentRunId"] == parent


def test_nested_uses_enclosing_run(cfg, store_uri):
    with tracking.tracked_run(cfg, "outer", {}) as outer:
        with tracking.tracked_run(cfg, "inner", {}, nested=True) as inner:
            pass
        with tracking.tracked_run(cfg, "independent", {}) as independent:
            pass
    client = _client(store_uri)
    assert client.get_run(inner.run_id).data.tags["mlflow.parentRunId"] == outer.run_id
    assert "mlflow.parentRunId" not in client.get_run(independent.run_id).data.tags
    assert list(queries.list_child_runs(outer.run_id, cfg)["run_id"]) == [inner.run_id]


def test_disabled_tracking_is_a_noop(workspace):
    with tracking.tracked_run({"enabled": False}, "x", {"a": 1}) as run:
        run.log_metrics({"m": 1.0})
        run.log_fold_metrics({"r2": [1.0]})
    assert run.run_id is None and not run.enabled
    assert tracking.start_parent_run({"enabled": False}, "sweep") is None
    assert not (workspace / "mlflow.db").exists()


# ----------------------------------------------------------- a run held by a helper process
def _pid(handle) -> int:  # what the helper runs, with its TrackedRun
    import os

    return os.getpid()


def _broken(handle) -> None:
    raise ValueError("the store refused it")


def test_a_run_beside_is_the_same_run_logged_from_a_helper_process_in_order(cfg, store_uri, workspace):
    import os

    with beside.tracked_run_beside(cfg, "beside", {"model": {"n_components": 8}}, tags={"stage": "evaluate"}) as run:
        helper = run.call(_pid)
        for step in range(5):  # queued in order: the history is the order of the calls
            run.log_metrics({"m": float(step)}, step=step)
        run.log_fold_metrics({"r2": [0.5, 0.6, 0.7]})
        run.log_config({"model": {"n_components": 8}})
        run.log_dataset(provenance.data_digest(workspace), source=str(workspace / "data"))
    assert helper.result() != os.getpid()  # logged by another process
    got = _client(store_uri).get_run(run.run_id)
    assert got.info.status == "FINISHED" and got.info.run_name == "beside"
    assert got.data.params["model.n_components"] == "8" and got.data.tags["stage"] == "evaluate"
    assert got.data.tags[tracking.PID_TAG] == str(os.getpid())  # the process whose end ends the run: this one
    assert got.data.tags["aumesh.data.md5"] == MD5 and got.inputs.dataset_inputs[0].dataset.digest == MD5
    history = sorted(_client(store_uri).get_metric_history(run.run_id, "m"), key=lambda m: m.step)
    assert [(m.step, m.value) for m in history] == [(s, float(s)) for s in range(5)]
    assert {"config.yaml"} <= {a.path for a in _client(store_uri).list_artifacts(run.run_id)}


@pytest.mark.parametrize("error, status", [(RuntimeError("boom"), "FAILED"), (KeyboardInterrupt(), "KILLED")])
def test_a_run_beside_ends_failed_or_killed_with_the_callers_error(cfg, store_uri, error, status):
    with pytest.raises(type(error)):
        with beside.tracked_run_beside(cfg, "broken", {"a": 1}) as run:
            run.log_metrics({"partial": 1.0})
            raise error
    got = _client(store_uri).get_run(run.run_id)
    assert got.info.status == status and got.data.metrics["partial"] == 1.0
    assert got.data.tags[tracking.ERROR_TAG].startswith(type(error).__name__)
    assert "error.txt" in {a.path for a in _client(store_uri).list_artifacts(run.run_id)}


def test_a_failed_queued_call_fails_the_run_and_is_raised_here(cfg, store_uri):
    with pytest.raises(ValueError, match="the store refused it"):
        with beside.tracked_run_beside(cfg, "refused", None) as run:
            run.call(_broken)
            run.log_metrics({"after": 1.0})  # queued behind the failure: still logged
    got = _client(store_uri).get_run(run.run_id)
    assert got.info.status == "FAILED" and "the store refused it" in got.data.tags[tracking.ERROR_TAG]


@pytest.mark.slow
def test_the_helper_ends_with_its_caller_and_the_next_run_marks_the_run_killed(cfg, store_uri, tmp_path):
    """The stage process killed alone (the OOM killer picks the largest process): its helper does not outlive it,
    and the run it left RUNNING is marked KILLED by the next run, as a run of the stage's own process would be."""
    import os
    import subprocess
    import sys
    import time

    from aumesh.core.signals import process_gone

    code = (
        "import os, signal, sys\n"
        "from aumesh.tracking import beside\n"
        "from test_tracking import _pid\n"
        "with beside.tracked_run_beside({'experiment': sys.argv[1]}, 'victim', {'a': 1}) as run:\n"
        "    print(run.run_id, run.call(_pid).result(), flush=True)\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")])}
    with open(tmp_path / "out.txt", "w+") as out:  # a file, not a pipe: an orphaned helper would hold a pipe open
        assert subprocess.run([sys.executable, "-c", code, cfg["experiment"]], stdout=out, env=env).returncode == -9
        out.seek(0)
        victim, helper = out.read().split()
    # a process started after now is not the helper (pid reuse); the deadline is a cap for a helper that stays, not a
    # time it must keep (a loaded machine is slower to get there)
    now, deadline = time.time(), time.monotonic() + 120
    while not process_gone(int(helper), now) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert process_gone(int(helper), now), f"the helper {helper} outlived its caller"
    client = _client(store_uri)
    assert client.get_run(victim).info.status == "RUNNING"
    with tracking.tracked_run(cfg, "next", None):
        pass
    after = client.get_run(victim)
    assert after.info.status == "KILLED" and "ended without closing" in after.data.tags[tracking.ERROR_TAG]


def test_a_disabled_run_beside_is_a_noop(workspace):
    with beside.tracked_run_beside({"enabled": False}, "x", {"a": 1}) as run:
        run.log_metrics({"m": 1.0})
        assert run.call(_broken) is None
    assert run.run_id is None and not run.enabled
    assert not (workspace / "mlflow.db").exists()


# ------------------------------------------------------------------- URI resolution
def test_resolve_tracking_uri_from_subdirectory(workspace, monkeypatch):
    sub = workspace / "src" / "deep"
    sub.mkdir(parents=True)
    monkeypatch.chdir(sub)
    assert mlflow_store.resolve_tracking_uri(None) == f"sqlite:///{workspace}/mlflow.db"
    assert mlflow_store.resolve_tracking_uri({"tracking_uri": None}) == f"sqlite:///{workspace}/mlflow.db"
    assert (
        mlflow_store.resolve_tracking_uri({"tracking_uri": "sqlite:///runs/t.db"}) == f"sqlite:///{workspace}/runs/t.db"
    )
    assert mlflow_store.resolve_tracking_uri({"tracking_uri": "sqlite:////abs/t.db"}) == "sqlite:////abs/t.db"
    assert mlflow_store.resolve_tracking_uri({"tracking_uri": "http://127.0.0.1:5000"}) == "http://127.0.0.1:5000"


@pytest.mark.parametrize("copy", [".dvc/tmp/exps/tmpabc", ".dvc/tmp/exps/standalone/tmpxyz"])
def test_resolve_tracking_uri_from_dvc_temp_copy(workspace, monkeypatch, copy):
    tmp_copy = workspace / copy
    (tmp_copy / "src").mkdir(parents=True)
    (tmp_copy / "dvc.yaml").write_text("stages: {}\n")  # the copy looks like a repo of its own
    (tmp_copy / ".git").mkdir()
    monkeypatch.chdir(tmp_copy / "src")
    assert provenance.repo_root() == workspace
    assert mlflow_store.resolve_tracking_uri({"tracking_uri": None}) == f"sqlite:///{workspace}/mlflow.db"
    assert (
        mlflow_store.resolve_tracking_uri({"tracking_uri": "sqlite:///mlflow.db"}) == f"sqlite:///{workspace}/mlflow.db"
    )
    assert provenance.in_dvc_temp_copy()


def test_env_var_wins(workspace, monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:9")
    assert mlflow_store.resolve_tracking_uri({"tracking_uri": "sqlite:///other.db"}) == "http://127.0.0.1:9"


def test_repo_root_errors_clearly_outside_a_workspace(tmp_path, monkeypatch):
    monkeypatch.delenv("DVC_ROOT", raising=False)
    lonely = tmp_path / "lonely"
    lonely.mkdir()
    if any((d / ".git").exists() or (d / "dvc.yaml").exists() for d in (lonely, *lonely.parents)):
        pytest.skip("tmp dir is inside a repository")
    with pytest.raises(FileNotFoundError, match="dvc.yaml"):
        provenance.repo_root(lonely)


# ------------------------------------------------------------------------ provenance
def test_data_digest_reads_dvc_file(workspace):
    d = provenance.data_digest(workspace)
    assert d["md5"] == MD5 and d["size"] == 12345 and d["nfiles"] == 7 and d["path"] == "data"
    assert d["dvc_file"] == "data.dvc"  # relative: records that hold it are shared


def test_data_digest_errors_clearly(workspace):
    with pytest.raises(FileNotFoundError) as err:
        provenance.data_digest(workspace, "missing.dvc")
    assert "missing.dvc" in str(err.value) and "dvc add data" in str(err.value)
    (workspace / "bad.dvc").write_text("outs:\n- path: data\n")
    with pytest.raises(ValueError, match=r"outs\[0\]\.md5"):
        provenance.data_digest(workspace, "bad.dvc")


@pytest.mark.skipif(shutil.which("git") is None, reason="git not installed")
def test_git_commit_reports_dvc_baseline_and_dirty(workspace, monkeypatch):
    info = provenance.git_commit(workspace)
    assert info["commit"] == _git(workspace, "rev-parse", "HEAD") and info["dirty"] is False
    # what DVC itself rewrites (the lock file, the git-tracked metrics it lists) is not a dirty tree
    (workspace / "metrics").mkdir()
    (workspace / "metrics" / "m.json").write_text("{}")
    (workspace / "dvc.lock").write_text(
        "schema: '2.0'\nstages:\n  a:\n    cmd: echo\n    outs:\n"
        "    - path: metrics/m.json\n      hash: md5\n      md5: 0\n"
    )
    _git(workspace, "add", "dvc.lock", "metrics/m.json")
    _git(workspace, "commit", "-q", "-m", "lock")
    (workspace / "metrics" / "m.json").write_text('{"r2": 0.5}')
    (workspace / "dvc.lock").write_text((workspace / "dvc.lock").read_text().replace("md5: 0", "md5: 1"))
    _git(workspace, "add", "dvc.lock")  # autostage
    assert provenance.git_commit(workspace)["dirty"] is False
    (workspace / "dvc.yaml").write_text("stages: {a: {cmd: echo}}\n")
    assert provenance.git_commit(workspace)["dirty"] is True
    monkeypatch.setenv("DVC_EXP_BASELINE_REV", "f" * 40)
    monkeypatch.setenv("DVC_EXP_NAME", "brisk-lynx")
    info = provenance.git_commit(workspace)
    assert info["commit"] == "f" * 40 and info["dvc_exp_name"] == "brisk-lynx" and info["source"] == "dvc-experiment"


def test_git_commit_never_raises_without_git(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))  # no git executable on PATH
    monkeypatch.delenv("DVC_EXP_BASELINE_REV", raising=False)
    info = provenance.git_commit(tmp_path)
    assert info["commit"] is None and info["dirty"] is False and info["source"] == "unavailable"


def test_flatten_and_library_versions():
    flat = provenance.flatten({"a": {"b": {"c": 1}, "l": [1, 2]}, "e": {}, "n": None})
    assert flat == {"a.b.c": 1, "a.l": "[1, 2]", "e": "{}", "n": None}
    assert provenance.flatten({"a": {"b": 1}}, sep="/") == {"a/b": 1}
    versions = provenance.library_versions()
    assert set(versions) >= {
        "numpy",
        "scipy",
        "scikit-learn",
        "pandas",
        "pyarrow",
        "mlflow",
        "dvc",
        "hydra-core",
        "python",
        "aumesh",
    }
    assert versions["mlflow"].startswith("3.")


@pytest.mark.slow
def test_concurrent_first_use_of_a_fresh_sqlite_store(tmp_path, workspace):
    """Parallel jobs creating the same new store must not race on MLflow's schema migrations."""
    import os
    import sys

    uri = f"sqlite:///{tmp_path / 'fresh.db'}"
    script = (
        "import sys\nfrom aumesh.tracking import runs as tracking\n"
        "with tracking.tracked_run({'experiment': 'conc'}, 'w' + sys.argv[1], {'i': sys.argv[1]}) as r:\n"
        "    r.log_fold_metrics({'r2': [0.1, 0.2]})\n"
    )
    env = dict(os.environ, MLFLOW_TRACKING_URI=uri)
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", script, str(i)],
            env=env,
            cwd=workspace,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i in range(4)
    ]
    outs = [p.communicate(timeout=120)[0] for p in procs]
    assert all(p.returncode == 0 for p in procs), "\n".join(outs)
    client = _client(uri)
    runs = client.search_runs([client.get_experiment_by_name("conc").experiment_id])
    assert len(runs) == 4 and {r.info.status for r in runs} == {"FINISHED"}
