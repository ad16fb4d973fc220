"""A team's tracking server, for real: Debian's PostgreSQL 15 (initdb / pg_ctl in a temporary folder, as an
unprivileged user, on a free loopback port), `aumesh server` (mlflow server with the PostgreSQL backend and served
artifacts) on it, two clones pointed at it by their git-ignored aumesh.local.yaml running `aumesh sweep` at the same
time, a bare `aumesh promote` in one (its own sweep, registered: the alias lands in PostgreSQL), `--across` in the
other, and the champion loaded through `mlflow.pyfunc` from the other clone.

Each step's seconds are printed (`pytest -s`): what a team's setup costs on this machine.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from conftest import STARTUP_TIMEOUT_S, free_port, server_healthy, stop_process_group
from test_sweep import make_workspace

pytestmark = [pytest.mark.slow, pytest.mark.server]

REPO = Path(__file__).resolve().parents[1]
PG_BIN = Path(os.environ.get("AUMESH_PG_BIN", "/usr/lib/postgresql/15/bin"))
USERS = {"alice": "alice@lab.example", "bob": "bob@lab.example"}
PASSWORD = "team-secret"
GRIDS = {"alice": "model.n_components=2,6", "bob": "model.n_components=3,10"}


def _as_unprivileged() -> list[str]:
    """PostgreSQL refuses to run as root: as root, run its commands as the `postgres` system user (Debian's package
    creates it), else `nobody`."""
    if os.geteuid() != 0:
        return []
    import pwd

    for user in ("postgres", "nobody"):
        try:
            pwd.getpwnam(user)
            return ["runuser", "-u", user, "--"]
        except KeyError:
            continue
    pytest.fail("running as root and neither a `postgres` nor a `nobody` user exists to run PostgreSQL as")


def _run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    proc = subprocess.run(cmd, capture_output=True, text=True, **kw)
    assert proc.returncode == 0, f"{' '.join(map(str, cmd))} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    return proc


@pytest.fixture(scope="module")
def timings():
    steps: dict[str, float] = {}
    yield steps
    print("\nteam setup, seconds per step:\n" + "\n".join(f"  {k:58} {v:7.1f}" for k, v in steps.items()))


@pytest.fixture(scope="module")
def postgres(timings):
    """A PostgreSQL 15 cluster in a temporary folder on 127.0.0.1:<free port>, user `mlflow` with a password,
    database `mlflow`; stopped (and the folder removed) at the end."""
    if not (PG_BIN / "initdb").exists():
        pytest.fail(
            f"{PG_BIN}/initdb not found: install Debian's postgresql (apt-get install -y postgresql; .ci/run does)"
        )
    sudo = _as_unprivileged()
    home = Path(tempfile.mkdtemp(prefix="aumesh-pg-"))  # /tmp/..., not root's private pytest folder
    data, log = home / "data", home / "server.log"
    (home / "pwfile").write_text(PASSWORD + "\n")
    if sudo:
        shutil.chown(home, user=sudo[2])
        shutil.chown(home / "pwfile", user=sudo[2])
    port = free_port()
    t0 = time.perf_counter()
    _run(
        [
            *sudo,
            str(PG_BIN / "initdb"),
            "-D",
            str(data),
            "-U",
            "mlflow",
            "--pwfile",
            str(home / "pwfile"),
            "--auth=scram-sha-256",
            "-E",
            "UTF8",
            "--no-instructions",
        ]
    )
    timings["initdb (a new PostgreSQL cluster)"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    _run(
        [
            *sudo,
            str(PG_BIN / "pg_ctl"),
            "-D",
            str(data),
            "-l",
            str(log),
            "-w",
            "-t",
            "60",
            "start",
            "-o",
            f"-p {port} -c listen_addresses=127.0.0.1 -k {home}",
        ]
    )
    try:
        env = dict(os.environ, PGPASSWORD=PASSWORD)
        _run([str(PG_BIN / "createdb"), "-h", "127.0.0.1", "-p", str(port), "-U", "mlflow", "mlflow"], env=env)
        timings["pg_ctl start + createdb"] = time.perf_counter() - t0
        yield f"postgresql://mlflow@127.0.0.1:{port}/mlflow"
    finally:
        subprocess.run(
            [*sudo, str(PG_BIN / "pg_ctl"), "-D", str(data), "-m", "fast", "-w", "stop"], capture_output=True
        )
        shutil.rmtree(home, ignore_errors=True)


@pytest.fixture(scope="module")
def server(postgres, tmp_path_factory, timings):
    """`aumesh server` on the database (the URI without a driver: aumesh adds psycopg2's), artifacts served."""
    tmp = tmp_path_factory.mktemp("team-server")
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = dict(os.environ, PGPASSWORD=PASSWORD, PYTHONPATH=str(REPO / "src"))
    env.pop("MLFLOW_TRACKING_URI", None)
    log = open(tmp / "server.log", "w")
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "aumesh",
            "server",
            "--backend-store-uri",
            postgres,
            "--artifacts-destination",
            str(tmp / "artifacts"),
            "--port",
            str(port),
            "--workers",
            "2",
        ],
        cwd=tmp,
        env=env,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not server_healthy(url):
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(
                    f"aumesh server not healthy (exit {proc.poll()}):\n{(tmp / 'server.log').read_text()[-3000:]}"
                )
            time.sleep(0.25)
        timings["aumesh server up (schema created in PostgreSQL)"] = time.perf_counter() - t0
        yield url
    finally:
        stop_process_group(proc)
        log.close()


@pytest.fixture(scope="module")
def clones(server, tmp_path_factory, timings):
    """Alice's and Bob's clones: their own git user.email, the server named only in their aumesh.local.yaml."""
    out = {}
    t0 = time.perf_counter()
    for name, email in USERS.items():
        ws = make_workspace(tmp_path_factory.mktemp(name) / "aumesh")
        _run(["git", "init", "-q"], cwd=ws)
        _run(["git", "config", "user.email", email], cwd=ws)
        (ws / "aumesh.local.yaml").write_text(f"tracking:\n  tracking_uri: {server}\n")
        out[name] = ws
    timings["two clones with data, prepared, aumesh.local.yaml"] = time.perf_counter() - t0
    return out


def _env(ws: Path) -> dict:
    """A teammate's shell: no MLFLOW_TRACKING_URI (the settings file names the server), this checkout's code."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MLFLOW_TRACKING_URI", "DVC_", "AUMESH_"))}
    env.update(PYTHONPATH=str(REPO / "src"), MLFLOW_DISABLE_TELEMETRY="true", DO_NOT_TRACK="true")
    return env


def _aumesh(ws: Path, *args: str) -> subprocess.CompletedProcess:
    return _run([sys.executable, "-m", "aumesh", *args], cwd=ws, env=_env(ws), timeout=900)


@pytest.fixture(scope="module")
def swept(clones, server, timings):
    """Both clones' `aumesh sweep -m ...` at the same time; their parent run ids (from each sweep's folder)."""
    t0 = time.perf_counter()
    procs = {
        name: subprocess.Popen(
            [sys.executable, "-m", "aumesh", "sweep", "-m", GRIDS[name]],
            cwd=ws,
            env=_env(ws),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for name, ws in clones.items()
    }
    outs = {name: p.communicate(timeout=900)[0] for name, p in procs.items()}
    timings["two sweeps at once (2 configurations each)"] = time.perf_counter() - t0
    for name, p in procs.items():
        assert p.returncode == 0, f"{name}'s sweep failed:\n{outs[name][-3000:]}"
    parents = {}
    for name, ws in clones.items():
        (parent_file,) = (ws / "build" / "sweeps").glob("*/mlflow_parent.json")
        parents[name] = json.loads(parent_file.read_text())["run_id"]
    return parents


def test_two_sweeps_at_once_land_whole_under_their_parents_with_owners(swept, clones, server):
    from mlflow import MlflowClient

    from aumesh.core import provenance

    client = MlflowClient(tracking_uri=server)
    for name, parent in swept.items():
        p = client.get_run(parent)
        assert p.info.status == "FINISHED" and p.data.tags["aumesh.user"] == USERS[name]
        children = client.search_runs([p.info.experiment_id], f"tags.`mlflow.parentRunId` = '{parent}'")
        assert sorted(c.data.params["model.n_components"] for c in children) == sorted(
            GRIDS[name].split("=")[1].split(",")
        )
        for c in children:
            assert c.info.status == "FINISHED"
            assert c.data.tags["aumesh.user"] == USERS[name]
            assert c.data.tags["aumesh.workspace.id"] == provenance.workspace_id(clones[name])
            assert c.info.artifact_uri.startswith("mlflow-artifacts:")  # served by the server, not a local path


def test_promote_registers_in_postgres_and_the_other_clone_loads_the_champion(swept, clones, server, postgres, timings):
    import psycopg2

    alice, bob = clones["alice"], clones["bob"]
    t0 = time.perf_counter()
    out = _aumesh(alice, "promote").stdout  # bare: Alice's own sweep, although Bob's may be newer
    timings["aumesh promote (register, alias)"] = time.perf_counter() - t0
    assert f"your latest sweep: {swept['alice']}" in out
    record = json.loads((alice / "promotion.json").read_text())["promoted"]
    assert record["parent_run_id"] == swept["alice"] and record["user"] == USERS["alice"]
    assert record["alias"] == "champion" and record["model_version"] == "1"
    # shared records hold no server address and no local path
    for text in (
        (alice / "promotion.json").read_text(),
        (alice / "params.yaml").read_text(),
        (alice / "conf" / "experiment" / "promoted.yaml").read_text(),
    ):
        assert "127.0.0.1" not in text and str(alice) not in text and "postgresql" not in text

    # the alias is a row of PostgreSQL's registry tables (the database itself, read with psycopg2)
    with psycopg2.connect(postgres.replace("postgresql://mlflow@", f"postgresql://mlflow:{PASSWORD}@")) as conn:
        with conn.cursor() as cur:
            cur.execute("select name, alias, version from registered_model_aliases")
            assert cur.fetchall() == [("aumesh-au-to-mesh", "champion", 1)]
            cur.execute("select count(*) from runs where status = 'FINISHED'")
            assert cur.fetchone()[0] == 6  # two parents, four children

    # Bob, in his clone (his aumesh.local.yaml names the server), loads the champion through MLflow's pyfunc
    t0 = time.perf_counter()
    code = (
        "import json, sys, numpy as np, pandas as pd, mlflow\n"
        "from aumesh.tracking import mlflow_store, registry\n"
        "from aumesh.core.schema import INPUT_COLUMNS\n"
        "mlflow.set_tracking_uri(mlflow_store.resolve_tracking_uri())\n"
        "model = mlflow.pyfunc.load_model('models:/aumesh-au-to-mesh@champion')\n"
        "df = pd.DataFrame(np.random.default_rng(0).uniform(0, 1, (4, 23)), columns=list(INPUT_COLUMNS))\n"
        "df[['Pitch', 'Yaw', 'Roll']] = 0.0\n"
        "run = registry.model_version_by_alias('aumesh-au-to-mesh', 'champion', {})['run_id']\n"
        "npz = np.load(registry.download_run_artifacts(run, 'model/artifacts/au_to_mesh_pls.npz', sys.argv[1]))\n"
        "expected = df.to_numpy() @ npz['coef'].astype(np.float64) + npz['intercept'].astype(np.float64)\n"
        "print(json.dumps({'run': run, 'max_abs_diff': float(np.abs(model.predict(df) - expected).max()),\n"
        "                  'scale': float(np.abs(expected).max())}))\n"
    )
    result = json.loads(
        _run([sys.executable, "-c", code, str(bob / "download")], cwd=bob, env=_env(bob), timeout=600)
        .stdout.strip()
        .splitlines()[-1]
    )
    timings["pyfunc load + predict from the other clone"] = time.perf_counter() - t0
    assert result["run"] == record["run_id"]
    assert result["max_abs_diff"] <= 1e-9 * result["scale"]

    # Bob ranks the whole team's runs on this data: the best of all four children, whoever ran it
    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri=server)
    exp = client.get_experiment_by_name("aumesh")
    children = [
        r
        for r in client.search_runs([exp.experiment_id], "attributes.status = 'FINISHED'")
        if r.data.tags.get("aumesh.role") == "sweep-child"
    ]
    best = max(children, key=lambda r: (r.data.metrics["r2_mean"], -r.data.metrics["n_components"]))
    t0 = time.perf_counter()
    out = _aumesh(bob, "promote", "--across").stdout
    timings["aumesh promote --across"] = time.perf_counter() - t0
    across = json.loads((bob / "promotion.json").read_text())["promoted"]
    assert across["run_id"] == best.info.run_id and across["user"] == best.data.tags["aumesh.user"]
    # one registry version a run: the best child is version 1 again when it is the run alice promoted
    assert across["model_version"] == ("1" if best.info.run_id == record["run_id"] else "2")
    assert across["n_candidates"] == 4
    assert f"run {best.info.run_id} won" in out
