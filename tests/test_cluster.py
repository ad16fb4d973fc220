"""One Dask cluster, many workspaces: the ``dask scheduler`` / ``dask worker`` commands started outside the workspaces.

The slow cases start a real scheduler and two worker processes with the venv's ``dask`` CLI, from a folder that is
neither workspace (so a relative path on a worker names nothing), on loopback free ports. Two workspaces run
``dvc repro -f evaluate`` on it at the same time, the cluster chosen by ``AUMESH_COMPUTE_ADDRESS`` alone, and each
equals its own local run bit for bit (the arrays of the NPZ files, every other output byte for byte); the scheduler
killed mid-run stops the stage with one line and exit 2 and leaves the previous output; a data folder the workers do
not see (``/proc/self/cwd/...``: each process's own directory) is named by the probe. The fast cases: an address
nobody answers within a 1 s connect timeout, the probe's message on a real (in-process) ``distributed`` worker, and
the environment's settings over ``params.yaml``.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import aumesh
from aumesh import cli
from aumesh.config import ComputeConfig, compose, write_params
from aumesh.core.errors import ClusterError, ConfigError
from aumesh.pipeline import compute
from aumesh.pipeline.compute import probe as compute_probe
from aumesh.pipeline.compute import settings as compute_settings
from aumesh.synthetic.tables import SynthSpec, write_tables
from conftest import REPO

BIN = Path(sys.executable).parent
#: The aumesh under test, for the workers (they import the partition functions from it).
SRC = Path(aumesh.__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(compute_settings.ENV_PREFIX)}
    env["PATH"] = f"{BIN}{os.pathsep}{env['PATH']}"
    env["PYTHONPATH"] = os.pathsep.join([str(SRC), *filter(None, [os.environ.get("PYTHONPATH")])])
    return {**env, **extra}


class Cluster:
    """``dask scheduler`` + ``dask worker`` processes started in ``cwd`` (not a workspace), on loopback; the workers
    import the aumesh under ``src`` (default: the one under test)."""

    def __init__(self, cwd: Path, n_workers: int = 2, src: Path = SRC):
        self.cwd, self.port = cwd, _free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.log = open(cwd / "cluster.log", "ab")
        # --idle-timeout / --death-timeout: they stop by themselves if the test process dies before it stops them
        self.scheduler = subprocess.Popen(
            [
                BIN / "dask",
                "scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                str(self.port),
                "--no-dashboard",
                "--idle-timeout",
                "600",
            ],
            **self._common(SRC),
        )
        self.workers: list[subprocess.Popen] = []
        for _ in range(n_workers):
            self.add_worker(src)
        from distributed import Client

        with Client(self.address, timeout=60, set_as_default=False) as client:
            client.wait_for_workers(n_workers, timeout=120)
            self.worker_dirs = set(client.run(os.getcwd).values())

    def _common(self, src: Path, cwd: Path | None = None) -> dict:
        path = os.pathsep.join([str(src), *filter(None, [os.environ.get("PYTHONPATH")])])
        env = _env(ARROW_DEFAULT_MEMORY_POOL="system", PYTHONPATH=path)
        return dict(cwd=cwd or self.cwd, env=env, stdout=self.log, stderr=subprocess.STDOUT)

    def add_worker(self, src: Path = SRC, cwd: Path | None = None) -> subprocess.Popen:
        """Start one more worker (it joins when it has started, ~2 s), importing the aumesh under ``src``, in ``cwd``
        (default: the cluster's folder)."""
        proc = subprocess.Popen(
            [
                BIN / "dask",
                "worker",
                self.address,
                "--host",
                "127.0.0.1",
                "--nthreads",
                "1",
                "--no-dashboard",
                "--death-timeout",
                "30",
                "--local-directory",
                str(self.cwd / f"worker-{len(self.workers)}"),
            ],
            **self._common(src, cwd),
        )
        self.workers.append(proc)
        return proc

    def stop(self) -> None:
        for proc in [*self.workers, self.scheduler]:
            if proc.poll() is None:
                proc.terminate()
        for proc in [*self.workers, self.scheduler]:
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self.log.close()


def other_aumesh(root: Path, changed: dict[str, str]) -> Path:
    """Another clone's aumesh: a copy of the one under test in ``root/src`` (a folder that is neither workspace), with
    the files ``changed`` (path in the package -> its new text). Returns the folder to put on a worker's PYTHONPATH."""
    src = root / "src"
    shutil.copytree(SRC / "aumesh", src / "aumesh", ignore=shutil.ignore_patterns("__pycache__"))
    for rel, text in changed.items():
        (src / "aumesh" / rel).write_text(text)
    return src


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    elsewhere = tmp_path_factory.mktemp("cluster-cwd")
    c = Cluster(elsewhere)
    try:
        yield c
    finally:
        c.stop()


def _run(args, cwd, env, check=True):
    proc = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True)
    if check:
        assert proc.returncode == 0, f"{' '.join(map(str, args))} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc


def make_workspace(root: Path, fixed_conf: Path, seed: int, n_frames: int = 1500) -> Path:
    """A git + DVC workspace with the repo's pipeline, the fixed conf/ composed into params.yaml, synthetic tables
    (partitions of 300 rows: several tasks a pass, videos split across them)."""
    ws = root
    ws.mkdir(parents=True)
    for name in ("dvc.yaml", ".gitignore"):
        shutil.copy(REPO / name, ws / name)
    shutil.copytree(fixed_conf, ws / "conf")
    shutil.copytree(REPO / "validation", ws / "validation")  # evaluate's dep (paths.validation_dir), as in a clone
    write_params(compose(["compute.partition_rows=300"], config_dir=ws / "conf"), ws / "params.yaml")
    (ws / "promotion.json").write_text('{"promoted": null}\n')
    shutil.copytree(REPO / "src", ws / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    env = _env()
    for args in (
        ["git", "init", "-q"],
        ["git", "config", "user.email", "t@example.com"],
        ["git", "config", "user.name", "test"],
        [BIN / "dvc", "init", "-q"],
    ):
        _run(args, ws, env)
    shutil.copy(REPO / ".dvc" / "config", ws / ".dvc" / "config")
    _run([BIN / "dvc", "remote", "remove", "demo"], ws, env)
    write_tables(ws / "data", SynthSpec(n_frames=n_frames, n_videos=60, seed=seed, frames_per_file=700))
    _run([BIN / "dvc", "add", "-q", "data"], ws, env)
    _run(["git", "add", "-A"], ws, env)
    _run(["git", "commit", "-qm", "init"], ws, env)
    return ws


#: The outputs of the stages with passes; the MLflow run's id (tracking.json) differs from run to run.
COMPARED = ("build/ingested", "build/prepared", "build/model", "metrics")


def outputs(ws: Path) -> dict[str, object]:
    """Every output file of ``COMPARED``: NPZ files as their arrays (the zip's member timestamps differ), the rest as
    their bytes' digest."""
    out: dict[str, object] = {}
    for folder in COMPARED:
        for p in sorted((ws / folder).rglob("*")):
            if not p.is_file() or p.name == "tracking.json":
                continue
            key = str(p.relative_to(ws))
            if p.suffix == ".npz":
                with np.load(p) as z:
                    out[key] = {k: z[k] for k in z.files}
            else:
                out[key] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def assert_same_outputs(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key, value in a.items():
        if isinstance(value, dict):
            assert value.keys() == b[key].keys(), key
            for name, array in value.items():
                np.testing.assert_array_equal(array, b[key][name], err_msg=f"{key}:{name}")
        else:
            assert value == b[key], key


def _records_hold_no_local_path(ws: Path, cluster: Cluster) -> None:
    for folder in ("build/ingested", "build/prepared", "build/model", "metrics"):
        for p in (ws / folder).rglob("*.json"):
            text = p.read_text()
            assert str(ws) not in text and str(cluster.cwd) not in text, p
    assert _run(["git", "status", "--porcelain", "params.yaml", "conf"], ws, _env()).stdout == ""


@pytest.mark.slow
def test_two_workspaces_share_one_cluster_started_elsewhere_and_equal_their_local_runs(cluster, tmp_path, fixed_conf):
    assert all(Path(d).resolve() == cluster.cwd.resolve() for d in cluster.worker_dirs)  # not a workspace
    spaces = [make_workspace(tmp_path / f"ws{i}", fixed_conf, seed=20 + i) for i in range(2)]
    local = {}
    for ws in spaces:
        _run([BIN / "dvc", "repro", "-f", "evaluate"], ws, _env())
        local[ws] = outputs(ws)
    # the two workspaces at once on the one cluster, chosen by the environment alone: params.yaml stays as it is
    env = _env(AUMESH_COMPUTE_ADDRESS=cluster.address)
    procs = [
        subprocess.Popen(
            [str(BIN / "dvc"), "repro", "-f", "evaluate"],
            cwd=ws,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for ws in spaces
    ]
    for proc in procs:
        log = proc.communicate(timeout=900)[0]
        assert proc.returncode == 0, log
        assert "Running stage 'prepare'" in log and "Running stage 'evaluate'" in log
    from distributed import Client

    with Client(cluster.address, set_as_default=False) as client:  # the passes did run on the workers
        done = client.run(lambda dask_worker: len(dask_worker.state.log), on_error="raise")
        assert all(n > 0 for n in done.values())
        # each stage's probe of the workers that join later (a worker plugin) went with the stage
        plugins = client.run_on_scheduler(lambda dask_scheduler: sorted(dask_scheduler.worker_plugins))
        assert not [name for name in plugins if name.startswith("aumesh-probe-")], plugins
    for ws in spaces:
        assert_same_outputs(outputs(ws), local[ws])
        _records_hold_no_local_path(ws, cluster)
    assert local[spaces[0]]["build/prepared/meshes.npy"] != local[spaces[1]]["build/prepared/meshes.npy"]
    # nothing left behind in the workspaces (scratch folders are per run and removed) or where the workers run
    for ws in spaces:
        assert not list((ws / "build").glob(".*")), list((ws / "build").glob(".*"))
    assert not list(cluster.cwd.glob("build")) and not list(cluster.cwd.glob("data"))


def _one_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1, stderr
    return lines[0]


@pytest.mark.slow
def test_data_the_workers_do_not_see_is_named_by_the_probe(cluster, tmp_path, fixed_conf):
    """``/proc/self/cwd/data``: this workspace's tables for the stage, the workers' own (empty) folder for them."""
    ws = make_workspace(tmp_path / "ws", fixed_conf, seed=3, n_frames=300)
    params = compose(["compute.partition_rows=300", "paths.data_dir=/proc/self/cwd/data"], config_dir=ws / "conf")
    write_params(params, ws / "params.yaml")
    proc = _run([BIN / "aumesh", "ingest"], ws, _env(AUMESH_COMPUTE_ADDRESS=cluster.address), check=False)
    line = _one_line(proc.stderr)
    assert proc.returncode == 2, proc.stderr
    assert line.startswith("aumesh ingest: error: worker tcp://127.0.0.1:"), line
    assert "cannot read /proc/self/cwd/data/frames_0000.parquet (FileNotFoundError" in line
    assert "must be on a filesystem every worker sees at the same path" in line
    assert not (ws / "build" / "ingested").exists()


#: What shows a stage's passes are under way on the cluster: pass 1's staged partitions (prepare), the scratch
#: folder of pass A's per-video sums (evaluate).
MID_RUN = {"prepare": ".prepared.tmp-*/scratch/*.arrow", "evaluate": ".evaluate-scratch.tmp-*/*.npy"}


@pytest.mark.slow
@pytest.mark.parametrize(("stage", "runner"), [("prepare", "aumesh"), ("evaluate", "aumesh"), ("prepare", "dvc")])
def test_a_scheduler_lost_mid_run_is_one_line_that_says_what_is_left(stage, runner, tmp_path, fixed_conf):
    """Run by ``aumesh``: the previous output stands, and the line says so. Run by ``dvc repro``: DVC removed the
    stage's output before it ran the stage, so the line claims nothing of it and the next one names what is gone and
    the command that brings it back, which does (the same bytes as before)."""
    import mlflow

    ws = make_workspace(tmp_path / "ws", fixed_conf, seed=5, n_frames=6000)
    write_params(compose(["compute.partition_rows=100"], config_dir=ws / "conf"), ws / "params.yaml")
    stages = ["ingest", "prepare"] + (["evaluate"] if stage == "evaluate" else [])
    if runner == "dvc":  # the previous output, built here, in dvc.lock and DVC's cache
        _run([BIN / "dvc", "repro", "-q", stage], ws, _env())
        command = [str(BIN / "dvc"), "repro", "-f", "-s", stage]
    else:
        for s in stages:  # the previous output, built here
            _run([BIN / "aumesh", s], ws, _env())
        command = [str(BIN / "aumesh"), stage]
    before = outputs(ws)
    (tmp_path / "elsewhere").mkdir()
    c = Cluster(tmp_path / "elsewhere", n_workers=1)
    try:
        proc = subprocess.Popen(
            command,
            cwd=ws,
            text=True,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=_env(AUMESH_COMPUTE_ADDRESS=c.address),
        )
        deadline = time.monotonic() + 120
        while not list((ws / "build").glob(MID_RUN[stage])) and proc.poll() is None:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        c.scheduler.send_signal(signal.SIGKILL)
        # the stage notices the lost scheduler and stops: a cap for a stage that hangs, not a time it must keep
        out, err = proc.communicate(timeout=300)
    finally:
        c.stop()
    lost = f"aumesh {stage}: error: AUMESH_COMPUTE_ADDRESS={c.address}: lost the Dask scheduler"
    if runner == "dvc":
        assert proc.returncode != 0, err
        lines = (out + err).splitlines()
        at = next(i for i, text in enumerate(lines) if text.startswith(lost))
        assert "stand" not in lines[at], lines[at]
        assert lines[at + 1] == (
            f"DVC removed build/prepared before running {stage}: `dvc checkout {stage}` brings back the last good one."
        ), err
        assert not (ws / "build" / "prepared").exists()  # what the line says is gone is gone
        _run([BIN / "dvc", "checkout", stage], ws, _env())  # and its command brings it back
    else:
        line = _one_line(err)
        assert proc.returncode == 2, err
        assert line.startswith(lost), line
        assert line.endswith("The previous outputs stand."), line
    after = outputs(ws)
    if stage == "evaluate":  # and the run that failed is FAILED in MLflow, the one before FINISHED
        runs = mlflow.MlflowClient().search_runs(
            mlflow.get_experiment_by_name("aumesh").experiment_id, order_by=["attributes.start_time DESC"]
        )
        assert [r.info.status for r in runs] == ["FAILED", "FINISHED"]
    assert_same_outputs(after, before)
    assert not list((ws / "build").glob(".*"))  # the run's temporary folders are gone


# ------------------------------------------------------------------------------------------------------- fast cases
@pytest.mark.slow
def test_an_address_nobody_answers_is_one_line_and_exit_2_within_the_connect_timeout(tmp_path, monkeypatch, capsys):
    """The connection is refused until AUMESH_COMPUTE_CONNECT_TIMEOUT's 1 s (compute.connect_timeout's default is
    10 s) have passed, and the line says so: nothing listens there (where ``distributed`` said it timed out, as it
    says of a peer that is no scheduler). tests/test_cluster_failures.py: silent and HTTP listeners."""
    address = f"tcp://127.0.0.1:{_free_port()}"  # nothing listens there
    monkeypatch.setenv("AUMESH_COMPUTE_ADDRESS", address)
    monkeypatch.setenv("AUMESH_COMPUTE_CONNECT_TIMEOUT", "1")
    with pytest.raises(ClusterError) as err, compute.engine(ComputeConfig()):
        pytest.fail("the engine must not start")
    assert str(err.value) == (
        f"AUMESH_COMPUTE_ADDRESS={address}: nothing listens there (every connection refused) within 1 s (the "
        "scheduler is not running there). Fix: start one (`make cluster`, or `dask scheduler` and `dask worker "
        "ADDRESS`) or correct the address, or unset AUMESH_COMPUTE_ADDRESS to run here; AUMESH_COMPUTE_CONNECT_TIMEOUT "
        "sets the wait."
    )

    # through the command: a stage that reaches its passes stops with the one line, exit 2
    write_tables(tmp_path / "data", SynthSpec(n_frames=200, n_videos=20, seed=1))
    from conftest import default_config

    write_params(default_config().to_dict(), tmp_path / "params.yaml")
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    assert cli.main(["ingest"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert line.startswith(f"aumesh ingest: error: AUMESH_COMPUTE_ADDRESS={address}: nothing listens there"), line
    assert not (tmp_path / "build" / "ingested").exists() and not list((tmp_path / "build").glob(".*"))


def test_the_probe_names_the_worker_and_the_path_it_cannot_read_or_write(tmp_path):
    """A real ``distributed`` worker (in-process, loopback): a table it cannot read, a folder it cannot write into;
    what it reads and writes where the stage does passes, and leaves nothing behind."""
    from distributed import Client, LocalCluster

    table = tmp_path / "data" / "frames_0000.parquet"
    table.parent.mkdir()
    table.write_bytes(os.urandom(200_000))
    out = tmp_path / "build"
    out.mkdir()
    with (
        LocalCluster(
            n_workers=1,
            threads_per_worker=1,
            processes=False,
            protocol="tcp://",
            host="127.0.0.1",
            dashboard_address=None,
        ) as lc,
        Client(lc, set_as_default=False) as client,
    ):
        (worker,) = client.scheduler_info()["workers"]
        compute_probe.check_workers(client, table, out)  # passes, and leaves no probe file
        assert list(out.iterdir()) == []
        with pytest.raises(ClusterError) as err:
            compute_probe.check_workers(client, tmp_path / "elsewhere" / "frames_0000.parquet", out)
        assert str(err.value).startswith(
            f"worker {worker} cannot read {tmp_path}/elsewhere/frames_0000.parquet (FileNotFoundError: "
        )
        assert f"the folder {tmp_path}/elsewhere must be on a filesystem every worker sees at the same path" in str(
            err.value
        )
        with pytest.raises(
            ClusterError,
            match=rf"^worker {worker} cannot write into {tmp_path}/missing "
            r"\(FileNotFoundError: .*\): the folder .* must be on a filesystem",
        ):
            compute_probe.check_workers(client, table, tmp_path / "missing")
        assert list(out.iterdir()) == []


def test_the_environment_chooses_where_the_passes_run_over_params(monkeypatch):
    cfg = ComputeConfig(scheduler="threads", partition_rows=500)
    assert compute_settings.effective(cfg, {}) is cfg
    remote = compute_settings.effective(
        cfg, {"AUMESH_COMPUTE_ADDRESS": "tcp://10.0.0.5:8786", "AUMESH_COMPUTE_CONNECT_TIMEOUT": "2.5"}
    )
    assert remote == ComputeConfig(
        scheduler="distributed", address="tcp://10.0.0.5:8786", partition_rows=500, connect_timeout=2.5
    )
    assert compute_settings.effective(cfg, {"AUMESH_COMPUTE_SCHEDULER": "synchronous"}).scheduler == "synchronous"
    with pytest.raises(
        ConfigError,
        match=r"^AUMESH_COMPUTE_CONNECT_TIMEOUT=soon \(environment\): "
        r"compute.connect_timeout='soon': must be a number",
    ):
        compute_settings.effective(cfg, {"AUMESH_COMPUTE_CONNECT_TIMEOUT": "soon"})
    with pytest.raises(ConfigError, match="compute.connect_timeout=0.0: must be > 0"):
        compute_settings.effective(cfg, {"AUMESH_COMPUTE_CONNECT_TIMEOUT": "0"})
    assert compute_settings.source_of("address", {"AUMESH_COMPUTE_ADDRESS": "tcp://h:1"}) == "AUMESH_COMPUTE_ADDRESS"
    assert compute_settings.source_of("address", {}) == "compute.address"


@pytest.mark.slow
def test_tasks_get_absolute_paths_and_the_records_keep_the_workspace_relative_ones(tmp_path, monkeypatch):
    """Ingest and prepare in a workspace with relative paths (params.yaml's): the partition tasks are handed absolute
    paths (what a worker elsewhere needs), the manifest and the summary record ``data/...`` as before."""
    from aumesh.core.io import recorded
    from aumesh.pipeline.prepare import tasks as prepare_tasks
    from conftest import default_config

    write_tables(tmp_path / "data", SynthSpec(n_frames=300, n_videos=30, seed=2, frames_per_file=150))
    write_params(
        default_config(**{"compute": "synchronous", "compute.partition_rows": 100}).to_dict(), tmp_path / "params.yaml"
    )
    seen = []
    scan = prepare_tasks.scan_partition

    def spy(item, cfg, scratch, exclude=None):
        seen.append((scratch, [p.table.path for p in item[1]]))
        return scan(item, cfg, scratch, exclude)

    monkeypatch.setattr(prepare_tasks, "scan_partition", spy)
    monkeypatch.chdir(tmp_path)
    assert cli.main(["ingest"]) == 0 and cli.main(["prepare"]) == 0
    assert len(seen) > 1 and all(s.is_absolute() and all(p.is_absolute() for p in paths) for s, paths in seen)
    assert {str(p) for _, paths in seen for p in paths} == {str(p) for p in (tmp_path / "data").glob("*.parquet")}
    assert seen[0][0].parent.name.startswith(".prepared.tmp-") and seen[0][0].parent.parent == tmp_path / "build"
    manifest = (tmp_path / "build" / "ingested" / "manifest.json").read_text()
    summary = (tmp_path / "build" / "prepared" / "summary.json").read_text()
    for text in (manifest, summary):
        assert '"data/frames_0000.parquet"' in text and str(tmp_path) not in text
    # recorded(): relative inside the workspace, as given outside it
    assert recorded(tmp_path / "data" / "x.parquet") == "data/x.parquet" and recorded("data/x") == "data/x"
    assert recorded("/elsewhere/x.parquet") == "/elsewhere/x.parquet"
    assert recorded(tmp_path.parent / "x") == str(tmp_path.parent / "x")
