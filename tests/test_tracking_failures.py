"""A tracking server that is not there, is something else, or goes away mid-run (issue 45, items 3 and 4).

Every command that tracks checks the store before any work and stops in one line (exit 2) naming the URI and where it
came from; MLflow's retries are bounded (``tracking.request_timeout_s``, ``max_retries``, ``backoff_factor``); a server
lost mid-evaluate ends the stage in one line with nothing of the run published (``build/model``, ``tracking.json``,
``metrics/`` as they were). Real servers: an ``mlflow server`` killed mid-evaluate, PostgreSQL (initdb / pg_ctl) stopped,
a TCP server that accepts and never answers, a port nothing listens on.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import pytest
import yaml

from aumesh import cli
from aumesh.tracking import connection, mlflow_store
from conftest import STARTUP_TIMEOUT_S, free_port, new_store, server_healthy, stop_process_group

REPO = Path(__file__).resolve().parents[1]


def tree_digest(*folders: Path) -> dict[str, str]:
    """Every file under ``folders`` -> its sha256 (what "byte-identical" compares)."""
    return {
        str(p): hashlib.sha256(p.read_bytes()).hexdigest()
        for folder in folders
        for p in sorted(Path(folder).rglob("*"))
        if p.is_file()
    }


def set_tracking(ws: Path, **values) -> None:
    params = yaml.safe_load((ws / "params.yaml").read_text())
    params["tracking"].update(values)
    (ws / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if "error" in line.lower() or "Traceback" in line]


@pytest.fixture
def silent_port():
    """A TCP server on loopback that accepts connections and never answers (another service that speaks first, a
    hung server): its port."""
    server = socket.create_server(("127.0.0.1", 0))
    held: list[socket.socket] = []
    stop = threading.Event()

    def accept() -> None:
        server.settimeout(0.1)
        while not stop.is_set():
            try:
                held.append(server.accept()[0])
            except TimeoutError:
                continue
            except OSError:
                return

    thread = threading.Thread(target=accept, daemon=True)
    thread.start()
    yield server.getsockname()[1]
    stop.set()
    thread.join(5)
    for conn in held:
        conn.close()
    server.close()


# ------------------------------------------------------------------------------ where the URI came from
def test_source_of_the_uri(tmp_path, monkeypatch):
    """Each of the four places a tracking URI comes from is named, first found wins (core.settings' order)."""
    local = tmp_path / "aumesh.local.yaml"
    monkeypatch.setenv("AUMESH_LOCAL_SETTINGS", str(local))
    monkeypatch.setattr("aumesh.core.provenance.repo_root", lambda: tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    conf = {"tracking_uri": "http://conf.example:5000"}
    assert mlflow_store.locate_tracking_uri({}) == (f"sqlite:///{tmp_path}/mlflow.db", connection.DEFAULT_SOURCE)
    assert mlflow_store.locate_tracking_uri(conf) == ("http://conf.example:5000", connection.CONF_SOURCE)
    local.write_text("tracking:\n  tracking_uri: http://local.example:5000\n")
    assert mlflow_store.locate_tracking_uri(conf) == (
        "http://local.example:5000",
        f"tracking.tracking_uri in {local}",
    )
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://env.example:5000")
    assert mlflow_store.locate_tracking_uri(conf) == ("http://env.example:5000", connection.ENV_SOURCE)
    assert mlflow_store.resolve_tracking_uri(conf) == "http://env.example:5000"


def test_password_never_shown():
    assert connection.shown_uri("postgresql://mlflow:s3cret@db:5432/mlflow") == "postgresql://mlflow:***@db:5432/mlflow"
    assert connection.shown_uri("http://host:5000") == "http://host:5000"


# ------------------------------------------------------------------------------ checked before any work
def test_closed_port_stops_evaluate_before_any_work(workspace, monkeypatch, capsys):
    """Nothing listens on the port (a wrong port): one line naming the URI and the environment variable, exit 2, at
    once (MLflow's own retries took 4.5 min, then a traceback), the previous outputs as they were."""
    port = free_port()  # bound and released: nothing listens there now
    monkeypatch.chdir(workspace)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"http://127.0.0.1:{port}")
    before = tree_digest(workspace / "build" / "model", workspace / "metrics")
    assert cli.main(["evaluate"]) == 2
    err = capsys.readouterr().err
    [line] = error_lines(err)
    assert line.startswith("aumesh evaluate: error: tracking server http://127.0.0.1:")
    assert f"http://127.0.0.1:{port} (from the MLFLOW_TRACKING_URI environment variable) refused" in line
    assert "Fix:" in line
    assert tree_digest(workspace / "build" / "model", workspace / "metrics") == before


def test_local_settings_named_as_the_source(workspace, monkeypatch, capsys):
    """The URI from aumesh.local.yaml: the line names that file, for runs and promote too."""
    monkeypatch.chdir(workspace)
    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    local = workspace / "aumesh.local.yaml"
    monkeypatch.setenv("AUMESH_LOCAL_SETTINGS", str(local))
    local.write_text(f"tracking:\n  tracking_uri: http://127.0.0.1:{free_port()}\n")
    for command in (["evaluate"], ["runs"], ["promote"]):
        assert cli.main(command) == 2
        [line] = error_lines(capsys.readouterr().err)
        assert f"aumesh {command[0]}: error: tracking server" in line
        assert (
            f"(from tracking.tracking_uri in {local})" in line and f"correct tracking.tracking_uri in {local}" in line
        )


def test_silent_port_ends_within_the_check_timeout(workspace, monkeypatch, capsys, silent_port):
    """Something accepts the connection and never answers (the case that hung a stage for 11 min): the check gives up
    after tracking.check_timeout_s, in one line."""
    monkeypatch.chdir(workspace)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"http://127.0.0.1:{silent_port}")
    set_tracking(workspace, check_timeout_s=0.3)
    before = tree_digest(workspace / "build" / "model")
    assert cli.main(["evaluate"]) == 2
    [line] = error_lines(capsys.readouterr().err)
    assert "accepted the connection but did not answer GET /health within 0.3 s (tracking.check_timeout_s" in line
    assert tree_digest(workspace / "build" / "model") == before


def test_tracking_off_checks_nothing(monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"http://127.0.0.1:{free_port()}")
    assert mlflow_store.check_tracking({"enabled": False}) is None
    with pytest.raises(connection.TrackingServerError, match="refused the connection"):
        mlflow_store.check_tracking({"enabled": True})


# ------------------------------------------------------------------------------ MLflow's retries, bounded
def test_request_bounds_reach_mlflow_unless_the_user_set_them(monkeypatch):
    """The tracking.* bounds are what MLflow's own readers (mlflow.environment_variables) return; a variable the user
    set stays theirs."""
    from mlflow.environment_variables import (
        MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR,
        MLFLOW_HTTP_REQUEST_MAX_RETRIES,
        MLFLOW_HTTP_REQUEST_TIMEOUT,
    )

    for variable in (
        "MLFLOW_HTTP_REQUEST_TIMEOUT",
        "MLFLOW_HTTP_REQUEST_MAX_RETRIES",
        "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR",
    ):
        monkeypatch.delenv(variable, raising=False)
    connection.bound_requests({"request_timeout_s": 7.5, "max_retries": 1, "backoff_factor": 0})
    assert (MLFLOW_HTTP_REQUEST_TIMEOUT.get(), MLFLOW_HTTP_REQUEST_MAX_RETRIES.get()) == (8, 1)
    assert MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR.get() == 0
    connection.bound_requests({})  # a later configuration of this process: the defaults of conf/tracking/mlflow.yaml
    conf = yaml.safe_load((REPO / "conf" / "tracking" / "mlflow.yaml").read_text())
    assert MLFLOW_HTTP_REQUEST_TIMEOUT.get() == conf["request_timeout_s"]
    assert MLFLOW_HTTP_REQUEST_MAX_RETRIES.get() == conf["max_retries"]
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "3")  # the user's
    connection.bound_requests({"request_timeout_s": 60})
    assert MLFLOW_HTTP_REQUEST_TIMEOUT.get() == 3


@pytest.mark.slow  # a 1 s request timeout, waited for
def test_a_silent_server_mid_command_is_one_line_within_the_request_timeout(monkeypatch, silent_port):
    """A client call on a server that stopped answering (here: never answers) ends after tracking.max_retries + 1
    tries of request_timeout_s, as one TrackingServerError naming the URI and the bound (MLflow's own: 120 s x 8)."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"http://127.0.0.1:{silent_port}")
    for variable in ("MLFLOW_HTTP_REQUEST_TIMEOUT", "MLFLOW_HTTP_REQUEST_MAX_RETRIES"):
        monkeypatch.delenv(variable, raising=False)
    client = mlflow_store.get_client({"request_timeout_s": 1, "max_retries": 0, "backoff_factor": 0})
    with pytest.raises(connection.TrackingServerError) as caught:
        client.search_experiments()
    line = str(caught.value)
    assert "\n" not in line
    assert f"tracking server http://127.0.0.1:{silent_port} (from the MLFLOW_TRACKING_URI environment" in line
    assert "stopped answering (no answer within 1 s) after 1 try of up to 1 s" in line


def test_lost_run_marked_failed_when_the_store_answers(tmp_path, monkeypatch):
    """After a lost server the run is still marked FAILED when its store answers again (a blip), the error recorded."""
    from mlflow import MlflowClient

    from aumesh.tracking import runs

    uri = f"sqlite:///{new_store(tmp_path / 'mlflow.db')}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    with pytest.raises(connection.TrackingServerError):
        with runs.tracked_run({"experiment": "lost"}, "r", {"a": 1}) as run:
            raise connection.TrackingServerError("tracking server http://x stopped answering", "Fix: start it")
    got = MlflowClient(uri).get_run(run.run_id)
    assert got.info.status == "FAILED"
    assert got.data.tags["aumesh.error"].startswith("TrackingServerError: tracking server http://x stopped answering")


def lost_while_logging_the_model(handle, arrays) -> None:
    """Stands in for run_record.log_model in the tracking helper: the server goes away while the model uploads."""
    raise connection.TrackingServerError(
        "tracking server http://lab:5000 stopped answering (connection refused)", "Fix: x"
    )


@pytest.mark.slow  # a whole evaluate stage in-process (its helper imports MLflow)
def test_evaluate_publishes_nothing_after_a_tracking_failure(workspace, monkeypatch, capsys):
    """The server is lost at the last logging call (the model's upload): build/model and metrics/ stay byte-identical
    (before the fix the new folder was swapped in with tracking.json naming the FAILED run, exit 1), and the run, its
    store reachable again, is marked FAILED with the line as its error."""
    from mlflow import MlflowClient

    from aumesh.pipeline import run_record

    monkeypatch.chdir(workspace)
    monkeypatch.setattr(run_record, "log_model", lost_while_logging_the_model)  # the helper is forked after this
    before = tree_digest(workspace / "build" / "model", workspace / "metrics")
    previous_run = json.loads((workspace / "build" / "model" / "tracking.json").read_text())["run_id"]
    assert cli.main(["evaluate"]) == 2
    [line] = error_lines(capsys.readouterr().err)
    assert "tracking server http://lab:5000 stopped answering" in line and line.endswith("Fix: x.")
    assert "nothing of this run was published" in line
    assert tree_digest(workspace / "build" / "model", workspace / "metrics") == before
    client = MlflowClient(os.environ["MLFLOW_TRACKING_URI"])
    experiment = client.get_experiment_by_name("aumesh").experiment_id
    [run] = [r for r in client.search_runs([experiment]) if r.info.run_id != previous_run]
    assert f"MLflow run {run.info.run_id} marked FAILED" in line
    assert run.info.status == "FAILED" and "stopped answering" in run.data.tags["aumesh.error"]


# ------------------------------------------------------------------------------ a real server stopped mid-evaluate
@pytest.fixture
def own_server(tmp_path):
    """A real `mlflow server` (SQLite store, served artifacts: the fast path; the database's own failure is the
    PostgreSQL test below) that the test stops: its URL, its database file and its process."""
    from aumesh.tracking.server import server_command, server_environment

    home = tmp_path / "server"
    home.mkdir()
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = server_environment()
    env.pop("MLFLOW_TRACKING_URI", None)
    log = open(home / "server.log", "w")
    cmd = server_command(f"sqlite:///{home / 'mlflow.db'}", str(home / "artifacts"), port=port, workers=1)
    proc = subprocess.Popen(cmd, cwd=home, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not server_healthy(url):
            assert proc.poll() is None, (home / "server.log").read_text()[-3000:]
            assert time.monotonic() < deadline, (home / "server.log").read_text()[-3000:]
            time.sleep(0.25)
        yield url, home / "mlflow.db", proc
    finally:
        stop_process_group(proc)
        log.close()


def _runs_on(url: str) -> list[dict]:
    """The server's runs (its REST API, as any client sees them)."""
    body = json.dumps({"experiment_ids": ["0", "1"], "max_results": 50}).encode()
    request = urllib.request.Request(
        f"{url}/api/2.0/mlflow/runs/search", data=body, headers={"Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(request, timeout=2) as resp:
            return json.loads(resp.read()).get("runs", [])
    except OSError:
        return []


@pytest.mark.slow
@pytest.mark.server
@pytest.mark.timeout(240)  # the bound: the stage must end by itself within it (MLflow's own retries: 25 min)
def test_server_stopped_mid_evaluate_keeps_the_previous_model(workspace, own_server):
    """The server is killed once the stage's run exists (the stage paused meanwhile, so the kill lands mid-run): the
    stage ends in one line, exit 2, saying the run could not be marked FAILED; build/model (tracking.json included)
    and metrics/ byte-identical to before, and the run in the server's database is not FINISHED."""
    url, database, server = own_server
    before = tree_digest(workspace / "build" / "model", workspace / "metrics")
    env = dict(os.environ, MLFLOW_TRACKING_URI=url, PYTHONPATH=str(REPO / "src"))
    stage = subprocess.Popen(
        [sys.executable, "-m", "aumesh", "evaluate"],
        cwd=workspace,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        while not (runs := _runs_on(url)):
            assert stage.poll() is None, stage.communicate()
            time.sleep(0.05)
        os.killpg(stage.pid, signal.SIGSTOP)  # the stage and its tracking helper wait while the server goes
        run_id = runs[0]["info"]["run_id"]
        stop_process_group(server)
        os.killpg(stage.pid, signal.SIGCONT)
        out, err = stage.communicate(timeout=200)
    finally:
        if stage.poll() is None:
            os.killpg(stage.pid, signal.SIGKILL)
    assert stage.returncode == 2, err
    assert "Traceback" not in err and "Retrying" not in err, err
    [line] = error_lines(err)
    assert line.startswith(f"aumesh evaluate: error: tracking server {url} (from the MLFLOW_TRACKING_URI environment")
    assert "stopped answering (connection refused)" in line
    assert f"MLflow run {run_id} could not be marked FAILED" in line
    assert "nothing of this run was published" in line
    assert tree_digest(workspace / "build" / "model", workspace / "metrics") == before
    with sqlite3.connect(database) as con:  # the server's own record of the run, read without the server
        [(status,)] = con.execute("SELECT status FROM runs WHERE run_uuid = ?", (run_id,)).fetchall()
    assert status == "RUNNING"  # never FINISHED: nothing names it as a finished model


@pytest.mark.slow
@pytest.mark.server
@pytest.mark.timeout(300)  # four configurations, each failing within the bound once the server is gone
def test_server_stopped_mid_sweep_is_one_line(tmp_path, own_server):
    """The server killed once the sweep's parent and first child exist: the sweep ends by itself, and its last word is
    one line (exit 2) naming the server and how many configurations failed, not "see `aumesh runs`" (exit 1) on a
    server that is gone, nor Hydra's warning about the parent it could not end."""
    from test_sweep import make_workspace

    url, _, server = own_server
    ws = make_workspace(tmp_path / "ws")
    subprocess.run(["git", "init", "-q"], cwd=ws, check=True)
    env = dict(os.environ, MLFLOW_TRACKING_URI=url, PYTHONPATH=str(REPO / "src"))
    sweep = subprocess.Popen(
        [sys.executable, "-m", "aumesh", "sweep", "-m", "model.n_components=2,3,4,5"],
        cwd=ws,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        while len(_runs_on(url)) < 2:  # the parent and the first configuration's run
            assert sweep.poll() is None, sweep.communicate()
            time.sleep(0.05)
        os.killpg(sweep.pid, signal.SIGSTOP)
        stop_process_group(server)
        os.killpg(sweep.pid, signal.SIGCONT)
        out, err = sweep.communicate(timeout=250)
    finally:
        if sweep.poll() is None:
            os.killpg(sweep.pid, signal.SIGKILL)
    assert sweep.returncode == 2, err
    assert "Traceback" not in out + err and "UserWarning" not in err, err
    [line] = error_lines(err)
    assert line.startswith(f"aumesh sweep: error: tracking server {url} (from the MLFLOW_TRACKING_URI environment")
    assert "of 4 configurations of the sweep failed" in line and "Fix: start the server" in line


# ------------------------------------------------------------------------------ a database URI, PostgreSQL stopped
@pytest.fixture
def stopped_postgres(tmp_path):
    """PostgreSQL 15 (initdb / pg_ctl, as tests/test_team_postgres.py) on a free loopback port: ``(uri, stop)``."""
    import shutil
    import tempfile

    from test_team_postgres import PG_BIN, _as_unprivileged, _run

    if not (PG_BIN / "initdb").exists():
        pytest.fail(f"{PG_BIN}/initdb not found: install Debian's postgresql (apt-get install -y postgresql)")
    sudo = _as_unprivileged()
    home = Path(tempfile.mkdtemp(prefix="aumesh-pg-"))
    if sudo:
        shutil.chown(home, user=sudo[2])
    port = free_port()
    pg_ctl = [*sudo, str(PG_BIN / "pg_ctl"), "-D", str(home / "data")]
    _run([*sudo, str(PG_BIN / "initdb"), "-D", str(home / "data"), "-U", "mlflow", "--auth=trust", "--no-instructions"])
    _run([*pg_ctl, "-l", str(home / "log"), "-w", "start", "-o", f"-p {port} -c listen_addresses=127.0.0.1 -k {home}"])

    def stop() -> None:
        subprocess.run([*pg_ctl, "-m", "fast", "-w", "stop"], capture_output=True)

    try:
        yield f"postgresql://mlflow@127.0.0.1:{port}/postgres", stop
    finally:
        stop()
        shutil.rmtree(home, ignore_errors=True)


@pytest.mark.slow
@pytest.mark.server
@pytest.mark.timeout(120)
def test_database_stopped_is_one_line(workspace, monkeypatch, capsys, stopped_postgres):
    """A database URI: checked by a real connect (it passes while PostgreSQL runs), one line once it is stopped."""
    uri, stop = stopped_postgres
    monkeypatch.chdir(workspace)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    located = mlflow_store.check_tracking({"enabled": True})
    assert located is not None and located.uri.startswith("postgresql+psycopg")  # the installed driver's URI
    stop()
    before = tree_digest(workspace / "build" / "model")
    assert cli.main(["evaluate"]) == 2
    [line] = error_lines(capsys.readouterr().err)
    assert line.startswith("aumesh evaluate: error: tracking database postgresql+psycopg")
    assert "(from the MLFLOW_TRACKING_URI environment variable) did not accept a connection (" in line
    assert "Connection refused" in line and "Fix: start the database" in line
    assert tree_digest(workspace / "build" / "model") == before
