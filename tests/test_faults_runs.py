"""Fault injection, the runs side: a damaged or busy MLflow store, promotion of a run whose artifacts are gone, an
interrupted sweep, a copied workspace, and SIGTERM to ``dvc repro`` (slow).

Every case asserts the exit code, the cause named in one line (no traceback), and that ``release/``, ``build/``, the
promotion records and the tracking store are unchanged or consistent.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from aumesh import cli
from aumesh.experiments import sweep_child
from aumesh.tracking import mlflow_store, queries, registry
from aumesh.tracking import runs as tracking
from conftest import new_store
from test_faults import dvc_env, mlflow_runs, run_cli, tree_digest

KEPT = ("release", "build")


def one_line(err: str, command: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"aumesh {command}: "), err
    assert "Traceback" not in err
    return lines[0]


def hold_lock(db: Path, seconds: float) -> subprocess.Popen:
    """Another process holding an exclusive lock on the store (as a long transaction of another program does); after
    ``seconds`` it prints the time (``time.time()``) and only then lets go: what happened after the lock was gone
    happened after that time, however late the process got to it."""
    code = (
        "import sqlite3, sys, time\n"
        "c = sqlite3.connect(sys.argv[1], isolation_level=None); c.execute('BEGIN EXCLUSIVE')\n"
        "print('locked', flush=True); time.sleep(float(sys.argv[2]))\n"
        "print(time.time(), flush=True); c.execute('ROLLBACK')\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code, str(db), str(seconds)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def set_busy_timeout(ws: Path, seconds: float) -> None:
    params = yaml.safe_load((ws / "params.yaml").read_text())
    params["tracking"]["busy_timeout_s"] = seconds
    (ws / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))


@pytest.fixture(autouse=True)
def _fresh_store_checks(monkeypatch):
    """The store checks run once per process and store: each test starts without that memory."""
    monkeypatch.setattr(mlflow_store, "_CHECKED", set())
    monkeypatch.setattr(mlflow_store, "_RELOCATED", set())


# ------------------------------------------------------------------------------------ a damaged or busy store
def damage(db: Path, how: str) -> None:
    raw = bytearray(db.read_bytes())
    if how == "truncated":
        raw = raw[: len(raw) // 2]
    elif how == "bytes overwritten":
        for i in range(len(raw) // 3, len(raw) // 3 + 20 * 4096, 7):
            raw[i] ^= 0xFF
    else:  # header
        raw[:16] = b"not a database!!"
    db.write_bytes(bytes(raw))


@pytest.mark.parametrize("how", ["truncated", "bytes overwritten", "header"])
def test_damaged_store_is_one_line_before_any_work(workspace, how, capsys, monkeypatch):
    from aumesh.pipeline import compute

    damage(workspace / "mlflow.db", how)
    before = {d: tree_digest(workspace / d) for d in KEPT}
    store = (workspace / "mlflow.db").read_bytes()
    engine, entered = compute.engine, []  # the stage's passes (the CV) run in compute.engine: observed, not timed
    monkeypatch.setattr(compute, "engine", lambda *a, **k: entered.append(a) or engine(*a, **k))
    code, err = run_cli(["evaluate"], workspace, capsys)
    assert code == 2, err
    line = one_line(err, "evaluate")
    assert "mlflow.db: the MLflow tracking store is damaged (" in line and "mv mlflow.db mlflow.db.damaged" in line
    assert entered == []  # before the CV, not after it
    assert {d: tree_digest(workspace / d) for d in KEPT} == before
    assert (workspace / "mlflow.db").read_bytes() == store  # not touched
    code, err = run_cli(["runs", "--sweeps"], workspace, capsys)  # a command that reads the store says the same
    assert code == 2 and "is damaged" in one_line(err, "runs")


@pytest.mark.slow
def test_busy_store_is_retried_then_one_line(workspace, capsys, monkeypatch):
    set_busy_timeout(workspace, 1.5)
    before = {d: tree_digest(workspace / d) for d in KEPT}
    runs = mlflow_runs(workspace)
    check, limits = mlflow_store.check_store, []  # the wait the stage asks for, observed
    monkeypatch.setattr(mlflow_store, "check_store", lambda uri, limit: limits.append(limit) or check(uri, limit))
    holder = hold_lock(workspace / "mlflow.db", 60)
    try:
        t0 = time.perf_counter()
        code, err = run_cli(["evaluate"], workspace, capsys)
        waited = time.perf_counter() - t0
    finally:
        holder.kill()
        holder.wait()
    assert code == 2, err
    line = one_line(err, "evaluate")
    assert "mlflow.db: the MLflow tracking store is locked by another process (database is locked)" in line
    assert "tracking.busy_timeout_s=1.5" in line and "fuser mlflow.db" in line
    # retried up to the limit asked for (tracking.busy_timeout_s, not SQLite's 5 s nor aumesh's default 60 s): a
    # lower bound, which load only makes longer; "not forever" is the run returning at all
    assert limits == [1.5] and waited > 1.0, (limits, waited)
    assert {d: tree_digest(workspace / d) for d in KEPT} == before
    assert mlflow_runs(workspace).equals(runs)


@pytest.mark.slow
def test_busy_store_that_frees_up_is_waited_for(workspace, capsys):
    import mlflow

    holder = hold_lock(workspace / "mlflow.db", 1.5)
    try:
        code, err = run_cli(["evaluate"], workspace, capsys)
    finally:
        holder.wait()
    freed = float(holder.stdout.read())  # the holder's time just before it let go
    assert code == 0, err
    run_id = json.loads((workspace / "build/model/tracking.json").read_text())["run_id"]
    statuses = mlflow_runs(workspace).set_index("run_id")["status"]
    assert statuses[run_id] == "FINISHED" and (statuses != "RUNNING").all()
    started = mlflow.MlflowClient(f"sqlite:///{workspace / 'mlflow.db'}").get_run(run_id).info.start_time / 1000
    # the run was opened once the lock was gone: it waited (MLflow's start_time is in whole milliseconds)
    assert started > freed - 0.001, started - freed


def test_store_client_retries_a_write_while_another_writer_holds_the_lock(tmp_path, monkeypatch):
    """Past the first check, a locked store in the middle of a run (MLflow's 20 s busy wait runs out) is retried.
    The waits on a fake clock (the module's ``time``): the backoff is what it sleeps, not what a busy machine took."""
    import types

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    now, slept, calls = [0.0], [], []

    def sleep(seconds):
        slept.append(seconds)
        now[0] += seconds

    monkeypatch.setattr(mlflow_store, "time", types.SimpleNamespace(monotonic=lambda: now[0], sleep=sleep))

    def flaky():
        calls.append(now[0])
        if len(calls) < 3:
            raise sqlite3.OperationalError("database is locked")
        return "ok"

    assert mlflow_store._with_store_retry(flaky, uri, 10) == "ok" and len(calls) == 3
    assert slept == [0.25, 0.5] and calls == [0.0, 0.25, 0.75]  # backoff: 0.25 s, doubling

    def always(exc):
        def call():
            raise exc

        return call

    slept.clear()
    with pytest.raises(mlflow_store.TrackingStoreError, match="locked by another process.*busy_timeout_s=0.3"):
        mlflow_store._with_store_retry(always(sqlite3.OperationalError("database is locked")), uri, 0.3)
    assert slept == [0.25]  # the next wait (0.5 s) would pass the limit: given up before it
    with pytest.raises(mlflow_store.TrackingStoreError, match="damaged \\(database disk image is malformed\\)"):
        mlflow_store._with_store_retry(always(sqlite3.DatabaseError("database disk image is malformed")), uri, 10)
    with pytest.raises(ValueError, match="other"):  # anything else is not the store's fault: raised as it is
        mlflow_store._with_store_retry(always(ValueError("other")), uri, 10)


# ------------------------------------------------------------------------------ promotion, sweeps, copied workspace
@pytest.fixture(scope="module")
def swept_workspace(tmp_path_factory):
    """A workspace with the default store (ws/mlflow.db, ws/mlartifacts) and a finished sweep of 3 configurations."""
    from test_sweep import make_workspace

    ws = make_workspace(tmp_path_factory.mktemp("promote-faults") / "ws")
    new_store(ws / "mlflow.db")  # the workspace's default store (tracking.tracking_uri unset)
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(ws)
        for var in ("MLFLOW_TRACKING_URI", "DVC_ROOT", "DVC_EXP_NAME", "AUMESH_SWEEP_PARENT_RUN_ID"):
            mp.delenv(var, raising=False)
        mp.setattr(mlflow_store, "_RELOCATED", set())
        assert cli.main(["sweep", "-m", "model.n_components=2,4,6"]) == 0
        parent = queries.latest_parent_run({})
    return ws, parent


@pytest.fixture
def swept(swept_workspace, tmp_path, monkeypatch):
    """A copy (``cp -a``) of the swept workspace, as the current directory, with its own default store."""
    ws, parent = swept_workspace
    copy = tmp_path / "copy"
    subprocess.run(["cp", "-a", str(ws), str(copy)], check=True)
    monkeypatch.chdir(copy)
    for var in ("MLFLOW_TRACKING_URI", "DVC_ROOT", "DVC_EXP_NAME", "AUMESH_SWEEP_PARENT_RUN_ID"):
        monkeypatch.delenv(var, raising=False)
    return copy, parent


def promotion_files(ws: Path) -> dict[str, bytes]:
    return {p: (ws / p).read_bytes() for p in ("promotion.json", "params.yaml")} | {
        "conf": json.dumps(tree_digest(ws / "conf")).encode()
    }


def ranked(ws: Path, parent: str) -> list[str]:
    from aumesh.experiments import ranking

    children = queries.list_child_runs(parent, {})
    return [r for r, _ in ranking.choose(ranking.candidates_from_frame(children)).ranking]


def no_absolute_path(record, where: str) -> None:
    for value in record.values() if isinstance(record, dict) else record:
        if isinstance(value, (dict, list)):
            no_absolute_path(value, where)
        elif isinstance(value, str):
            assert not re.search(r"(^/|file:/|sqlite:////)", value), f"{where} holds an absolute path: {value}"


@pytest.mark.slow
def test_copied_workspace_registers_its_own_artifacts(swept_workspace, swept, capsys, caplog):
    original, parent = swept_workspace
    copy, _ = swept
    original_store = (original / "mlflow.db").read_bytes()
    original_artifacts = tree_digest(original / "mlartifacts")
    code, err = run_cli(["promote", "--parent", parent], copy, capsys)
    assert code == 0, err
    assert "a copied or moved workspace" in caplog.text  # said once, when the store was pointed at its own folder
    record = json.loads((copy / "promotion.json").read_text())["promoted"]
    assert record["model_source"].startswith("mlartifacts/") and (copy / record["model_source"] / "MLmodel").is_file()
    assert record["tracking_uri"] == "sqlite:///mlflow.db"
    no_absolute_path(record, "promotion.json")
    version = registry.model_version_by_alias("aumesh-au-to-mesh", "champion", {})
    assert Path(version["source"].removeprefix("file://")).is_relative_to(copy)
    # a new run in the copy logs into the copy
    with tracking.tracked_run({}, "in the copy", None) as run:
        run.log_text("x", "x.txt")
    assert (copy / "mlartifacts").is_dir() and any((copy / "mlartifacts").rglob("x.txt"))
    assert (original / "mlflow.db").read_bytes() == original_store  # the original is not touched
    assert tree_digest(original / "mlartifacts") == original_artifacts


@pytest.mark.slow
def test_promote_names_the_run_whose_artifacts_are_gone(swept, capsys):
    ws, parent = swept
    best = ranked(ws, parent)[0]
    shutil.rmtree(next(p for p in (ws / "mlartifacts").rglob(best) if p.is_dir()))
    before = promotion_files(ws)
    code, err = run_cli(["promote", "--parent", parent], ws, capsys)
    assert code == 2, err
    line = one_line(err, "promote")
    assert f"run {best}" in line and "has lost its model artifacts (mlartifacts/" in line and "--skip-missing" in line
    assert promotion_files(ws) == before
    assert registry.model_version_by_alias("aumesh-au-to-mesh", "champion", {}) is None  # nothing registered


@pytest.mark.slow
def test_promote_skip_missing_takes_the_next_best_and_says_so(swept, capsys):
    ws, parent = swept
    best, second, _ = ranked(ws, parent)
    shutil.rmtree(next(p for p in (ws / "mlartifacts").rglob(best) if p.is_dir()))
    code, err = run_cli(["promote", "--parent", parent, "--skip-missing"], ws, capsys)
    assert code == 0, err
    assert f"skipped run {best}" in err and f"promoting run {second}" in err
    record = json.loads((ws / "promotion.json").read_text())["promoted"]
    assert record["run_id"] == second and record["skipped_missing_artifacts"][0]["run_id"] == best
    assert registry.model_version_by_alias("aumesh-au-to-mesh", "champion", {})["run_id"] == second
    no_absolute_path(record, "promotion.json")


@pytest.mark.slow
def test_interrupted_sweep_is_marked_killed_and_not_promoted_by_accident(swept, capsys, monkeypatch):
    ws, _ = swept
    real = sweep_child._evaluate_in_run
    calls = []

    def ctrl_c_on_the_third(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt  # what SIGINT raises in the middle of a configuration
        return real(*args, **kwargs)

    monkeypatch.setattr(sweep_child, "_evaluate_in_run", ctrl_c_on_the_third)
    code, err = run_cli(["sweep", "-m", "model.n_components=2,3,4,5,7"], ws, capsys)
    assert code == 130, err
    line = one_line(err, "sweep")
    assert "interrupted after 2 of 5 runs (Ctrl-C)" in line and "marked KILLED" in line and "--partial" in line
    parent = queries.latest_parent_run({})
    record = queries.run_record(parent, {})
    children = queries.list_child_runs(parent, {})
    assert record["status"] == "KILLED" and record["tags"]["aumesh.sweep.interrupted"].startswith("interrupted after 2")
    assert sorted(children["status"]) == ["FINISHED", "FINISHED", "KILLED"]
    assert line.split("running configuration ")[1].startswith(
        children[children["status"] == "KILLED"]["run_name"].iloc[0]
    )

    before = promotion_files(ws)
    code, err = run_cli(["promote"], ws, capsys)
    assert code == 2, err
    assert "did not finish (interrupted after 2 of 5 runs (Ctrl-C); 2 of 5 configurations finished)" in err
    assert "--partial" in err and "Traceback" not in err
    assert promotion_files(ws) == before
    code, err = run_cli(["promote", "--partial"], ws, capsys)
    assert code == 0, err
    finished = children[children["status"] == "FINISHED"]
    assert "partial sweep" in err and all(f"{r.run_name} ({r.run_id})" in err for r in finished.itertuples())
    promoted = json.loads((ws / "promotion.json").read_text())["promoted"]
    assert promoted["run_id"] in set(finished["run_id"]) and promoted["partial"].startswith("partial sweep")


# ------------------------------------------------------------------------------------------ SIGTERM, DVC gone
def test_sigterm_stops_a_stage_as_ctrl_c_does(workspace, tmp_path):
    """``aumesh release`` told to stop (SIGTERM) in the middle of its work: exit 143, one line, the temporaries
    removed, the release bit for bit."""
    before = tree_digest(workspace / "release")
    env = {**os.environ, "PYTHONPATH": str(Path(cli.__file__).parents[2])}
    proc = subprocess.Popen(
        [sys.executable, "-m", "aumesh", "release"],
        cwd=workspace,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 120
    while proc.poll() is None and not any(workspace.glob(".release.tmp-*")) and time.monotonic() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 143, err
    assert one_line(err, "release").startswith("aumesh release: stopped: SIGTERM received; nothing was swapped in")
    assert tree_digest(workspace / "release") == before
    assert not list(workspace.glob(".release.*"))


def test_interrupt_between_the_two_renames_puts_the_previous_folder_back(tmp_path, monkeypatch):
    """Ctrl-C or SIGTERM after the old release was moved aside and before the new one moved in: the old one goes
    back (it used to stay under ``.release.old-*`` with no ``release/`` at all)."""
    from aumesh.core import io, swap

    (tmp_path / "release").mkdir()
    (tmp_path / "release" / "card.md").write_text("previous")
    monkeypatch.setattr(swap, "exchange", lambda a, b: False)  # the two renames: a filesystem without RENAME_EXCHANGE
    real = os.replace
    calls = []

    def interrupted_second(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(src, dst)

    monkeypatch.setattr(io.os, "replace", interrupted_second)
    with pytest.raises(KeyboardInterrupt):
        with io.atomic_directory(tmp_path / "release") as tmp:
            (tmp / "card.md").write_text("new")
    monkeypatch.setattr(io.os, "replace", real)
    assert len(calls) >= 2 and (tmp_path / "release" / "card.md").read_text() == "previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["release"]


def _stage_process(dvc_pid: int, stage: str):
    import psutil

    for child in psutil.Process(dvc_pid).children(recursive=True):
        try:
            if ["-m", "aumesh", stage] == child.cmdline()[1:4]:
                return child
        except psutil.Error:
            continue
    return None


@pytest.mark.slow
@pytest.mark.parametrize("stage", ["prepare", "evaluate", "release"])
def test_sigterm_to_dvc_repro_stops_the_stage_and_keeps_the_release(dvc_workspace, tmp_path, stage):
    """``kill -TERM`` of the `dvc repro` process alone (what `timeout` and CI cancellation send): DVC exits at once
    and does not pass it on; the stage notices DVC is gone and stops within seconds, as after Ctrl-C."""
    import mlflow
    import psutil

    from test_dvc_pipeline import BIN
    from test_faults import _in_work, _stale

    ws = tmp_path / "ws"
    shutil.copytree(dvc_workspace, ws, symlinks=True)
    release = tree_digest(ws / "release")
    lock = _stages_locked(ws)
    _stale(ws, stage)
    env = dvc_env(ws)
    proc = subprocess.Popen(
        [BIN / "dvc", "repro"],
        cwd=ws,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline = time.monotonic() + 600
    worker = None
    while proc.poll() is None and time.monotonic() < deadline:
        worker = worker or _stage_process(proc.pid, stage)
        if worker is not None and _in_work(ws, stage):
            break
        time.sleep(0.02)
    assert worker is not None and proc.poll() is None, f"{stage} never got to work"
    proc.send_signal(signal.SIGTERM)  # the DVC process only, not its group
    proc.wait(timeout=30)
    t0 = time.monotonic()
    # the stage follows DVC out: a cap for a stage that stays, not a time it must keep (the time is printed)
    gone, _ = psutil.wait_procs([worker], timeout=120)
    assert gone, f"the {stage} stage is still running {time.monotonic() - t0:.0f} s after DVC exited"
    print(f"{stage}: stage gone {time.monotonic() - t0:.1f} s after DVC exited")
    time.sleep(1)
    assert tree_digest(ws / "release") == release  # nothing swapped in, then or later
    assert _stages_locked(ws) == lock  # check_params, which ran to its end, is recorded
    assert not [p for p in ws.rglob(".*.tmp-*")], "temporaries left behind"
    client = mlflow.MlflowClient(f"sqlite:///{ws / 'mlflow.db'}")
    for _ in range(60):  # the stage leaves at once; its MLflow helper ends the run KILLED on its own, just after
        runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
        if not [r for r in runs if r.info.status == "RUNNING"]:
            break
        time.sleep(0.25)
    assert not [r for r in runs if r.info.status == "RUNNING"]
    if stage == "evaluate":
        newest = max(runs, key=lambda r: r.info.start_time)
        assert newest.info.status == "KILLED", newest.info
        assert "DVC process" in newest.data.tags[tracking.ERROR_TAG]


def test_a_stage_whose_dvc_is_gone_commits_nothing(tmp_path, monkeypatch):
    """Quicker than the watcher's poll: the commit points themselves check that DVC still runs."""
    from aumesh.core import signals
    from aumesh.core.io import atomic_directory, atomic_path

    dead = subprocess.Popen(["true"])
    dead.wait()
    monkeypatch.setattr(signals, "_WATCHED", [(dead.pid, time.time() - 60, "the DVC process")])
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "old.txt").write_text("previous")
    with pytest.raises(signals.Terminated, match="the DVC process"):
        with atomic_directory(tmp_path / "out") as tmp:
            (tmp / "new.txt").write_text("new")
    with pytest.raises(signals.Terminated):
        with atomic_path(tmp_path / "file.txt") as tmp:
            tmp.write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["old.txt"]
    monkeypatch.setattr(signals, "_WATCHED", [])
    signals.check_supervisor()  # outside DVC: nothing to check


def _stages_locked(ws: Path) -> dict:
    """``dvc.lock``'s stages after ``check_params`` (a params.yaml edit reruns it first, to its end, and DVC records
    it): a stopped stage must leave these as they were."""
    import yaml

    stages = yaml.safe_load((ws / "dvc.lock").read_text())["stages"]
    return {name: entry for name, entry in stages.items() if name != "check_params"}
