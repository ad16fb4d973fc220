"""A shared Dask cluster that must not serve the run: workers with another clone's aumesh (at connect, or joining
mid-run), an address where something else listens.

The slow cases start real ``dask scheduler`` / ``dask worker`` processes from a folder that is neither workspace
(:class:`test_cluster.Cluster`), some of whose workers import a copy of the aumesh under test with one file changed
(another clone's edit), or whose probe module is an older one with none of the probe's functions; and real listeners
that are no scheduler (a TCP server that accepts and says nothing, an HTTP server) and a closed port. Each ends in one
line and exit 2, and no output is written. The fast cases: the code digest against the files on disk, the probe
pickled by value (it runs where its module cannot be imported), and the line for another code.
"""

from __future__ import annotations

import hashlib
import http.server
import os
import pickle
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from aumesh.config import compose, write_params
from aumesh.pipeline.compute import probe as compute_probe
from aumesh.synthetic.tables import SynthSpec, write_tables
from test_cluster import (
    BIN,
    MID_RUN,
    SRC,
    Cluster,
    _env,
    _free_port,
    _one_line,
    _run,
    assert_same_outputs,
    make_workspace,
    other_aumesh,
    outputs,
)

#: Another clone's edit: a change to prepare (the issue's wild values, here a comment: the code differs all the same).
PREPARE = "pipeline/prepare/__init__.py"
#: An older aumesh: its probe module has none of the probe's functions (the driver's used to be called by name).
OLD_PROBE = "pipeline/compute/probe.py"
OLD_PROBE_TEXT = '"""An older aumesh\'s probe."""\n\n\ndef first_line(err):\n    return str(err)\n\n\ndef check_workers(*args):\n    return None\n'


def _changed(rel: str) -> dict[str, str]:
    if rel == OLD_PROBE:
        return {rel: OLD_PROBE_TEXT}
    return {rel: (SRC / "aumesh" / rel).read_text() + "\n# another clone's change\n"}


def _workers(address: str) -> dict[str, int]:
    """The cluster's workers: address -> the worker process's pid."""
    from distributed import Client

    with Client(address, timeout=30, set_as_default=False) as client:
        return client.run(os.getpid)


@pytest.mark.slow
@pytest.mark.parametrize("changed", [PREPARE, OLD_PROBE])
def test_a_worker_running_another_clones_aumesh_is_refused_in_one_line(changed, tmp_path, fixed_conf):
    """Two workers, one of them with the other clone's aumesh: the stage stops before any work, naming that worker,
    both codes' folders and the file that differs (the one the test changed)."""
    other = other_aumesh(tmp_path / "other-clone", _changed(changed))
    ws = make_workspace(tmp_path / "ws", fixed_conf, seed=3, n_frames=300)
    (tmp_path / "elsewhere").mkdir()
    c = Cluster(tmp_path / "elsewhere", n_workers=1)
    try:
        c.add_worker(other)
        from distributed import Client

        with Client(c.address, timeout=30, set_as_default=False) as client:
            client.wait_for_workers(2, timeout=120)
            paths = client.run(lambda: __import__("importlib").util.find_spec("aumesh").origin)
        (theirs,) = [w for w, origin in paths.items() if origin.startswith(str(other))]
        proc = _run([BIN / "aumesh", "ingest"], ws, _env(AUMESH_COMPUTE_ADDRESS=c.address), check=False)
    finally:
        c.stop()
    line = _one_line(proc.stderr)
    assert proc.returncode == 2, proc.stderr
    assert line.startswith(
        f"aumesh ingest: error: worker {theirs} runs other aumesh code: {other / 'aumesh'} (code "
    ), line
    assert f"not this stage's {SRC / 'aumesh'} (code " in line and f"; they differ in {changed}. " in line, line
    assert f"PYTHONPATH={SRC}" in line and "unset AUMESH_COMPUTE_ADDRESS to run here" in line, line
    assert not (ws / "build" / "ingested").exists()


@pytest.mark.slow
@pytest.mark.parametrize("newcomer", ["other code", "no view of the data"])
def test_a_worker_that_joins_mid_run_and_fails_the_probe_stops_the_run_and_none_of_its_results_land(
    newcomer, tmp_path, fixed_conf
):
    """A cluster of one worker that serves the stage; once prepare's first pass is under way that worker is paused
    (SIGSTOP: the run cannot end without the newcomer) and another joins: one of another clone's aumesh, or one that
    does not see the data (``paths.data_dir=/proc/self/cwd/data``, each process's own directory: the workspace's for
    the stage and the first worker, started there, another folder for the newcomer). The stage stops with the one
    line naming the newcomer, and the previous output is what it was (nothing of the newcomer's landed)."""
    ws = make_workspace(tmp_path / "ws", fixed_conf, seed=5, n_frames=6000)
    blind = newcomer == "no view of the data"
    overrides = ["compute.partition_rows=100"] + (["paths.data_dir=/proc/self/cwd/data"] if blind else [])
    write_params(compose(overrides, config_dir=ws / "conf"), ws / "params.yaml")
    for s in ("ingest", "prepare"):  # the previous output, built here
        _run([BIN / "aumesh", s], ws, _env())
    before = outputs(ws)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    src = SRC if blind else other_aumesh(tmp_path / "other-clone", _changed(PREPARE))
    c = Cluster(ws if blind else elsewhere, n_workers=1)
    paused = None
    try:
        ((ours, paused),) = _workers(c.address).items()
        proc = subprocess.Popen(
            [str(BIN / "aumesh"), "prepare"],
            cwd=ws,
            text=True,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env=_env(AUMESH_COMPUTE_ADDRESS=c.address),
        )
        deadline = time.monotonic() + 120
        while not list((ws / "build").glob(MID_RUN["prepare"])) and proc.poll() is None:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        os.kill(paused, signal.SIGSTOP)
        c.add_worker(src, cwd=elsewhere)
        out, err = proc.communicate(timeout=300)  # a cap for a stage that hangs, not a time it must keep
    finally:
        if paused is not None:
            os.kill(paused, signal.SIGCONT)
        c.stop()
    line = _one_line(err)
    assert proc.returncode == 2, err
    assert line.startswith("aumesh prepare: error: worker tcp://127.0.0.1:"), line
    assert not line.startswith(f"aumesh prepare: error: worker {ours} "), line  # the newcomer, not ours
    if blind:
        assert " cannot read /proc/self/cwd/data/frames_0000.parquet (FileNotFoundError" in line, line
    else:
        assert f"runs other aumesh code: {src / 'aumesh'} (code " in line and f"they differ in {PREPARE}. " in line
    assert_same_outputs(outputs(ws), before)
    assert not list((ws / "build").glob(".*"))  # the run's temporary folders are gone


class _Silent(threading.Thread):
    """A TCP server that accepts connections and never says a word (a port of some other service)."""

    def __init__(self):
        super().__init__(daemon=True)
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.accepted: list[socket.socket] = []

    def run(self) -> None:
        try:
            while True:
                self.accepted.append(self.sock.accept()[0])
        except OSError:  # closed
            pass

    def close(self) -> None:
        self.sock.close()
        for conn in self.accepted:
            conn.close()


class _Http(threading.Thread):
    """An HTTP server (Python's), which answers a scheduler's handshake with an HTTP error."""

    def __init__(self):
        super().__init__(daemon=True)
        self.requests: list[str] = []
        seen = self.requests

        class Handler(http.server.BaseHTTPRequestHandler):
            def log_message(self, *args):  # the test's output stays quiet
                seen.append(args[0] % args[1:])

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.server.server_address[1]

    def run(self) -> None:
        self.server.serve_forever(poll_interval=0.05)

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


@pytest.mark.slow
@pytest.mark.parametrize("listener", ["silent TCP", "HTTP", "closed port"])
def test_an_address_where_no_scheduler_answers_is_one_line_and_exit_2(listener, tmp_path):
    """The stage exits 2 with one line naming the address and where it was set, the environment (silent TCP, closed
    port) or params.yaml (HTTP), where it hung forever before (a peer that accepts and then says nothing or HTTP)."""
    from conftest import default_config

    server = {"silent TCP": _Silent, "HTTP": _Http}.get(listener)
    srv = server() if server else None
    port = srv.port if srv else _free_port()
    address = f"tcp://127.0.0.1:{port}"
    write_tables(tmp_path / "data", SynthSpec(n_frames=200, n_videos=20, seed=1))
    if listener == "HTTP":  # through params.yaml: the line names compute.address and compute.connect_timeout
        params = default_config(
            **{"compute": "distributed", "compute.address": address, "compute.connect_timeout": 1}
        ).to_dict()
        env = _env()
        where, wait = f"compute.address={address}", "compute.connect_timeout sets the wait."
    else:
        params = default_config().to_dict()
        env = _env(AUMESH_COMPUTE_ADDRESS=address, AUMESH_COMPUTE_CONNECT_TIMEOUT="1")
        where, wait = f"AUMESH_COMPUTE_ADDRESS={address}", "AUMESH_COMPUTE_CONNECT_TIMEOUT sets the wait."
    write_params(params, tmp_path / "params.yaml")
    if srv:
        srv.start()
    try:
        # a cap for a stage that hangs (what it did), not a time it must keep
        proc = subprocess.run(
            [str(BIN / "aumesh"), "ingest"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120
        )
    finally:
        if srv:
            srv.close()
    line = _one_line(proc.stderr)
    assert proc.returncode == 2, proc.stderr
    if listener == "closed port":
        assert line.startswith(
            f"aumesh ingest: error: {where}: nothing listens there (every connection refused) within 1 s"
        ), line
    else:
        assert line.startswith(f"aumesh ingest: error: {where}: no Dask scheduler answered there within 1 s "), line
        assert srv is not None and (srv.accepted if listener == "silent TCP" else srv.requests)  # it was reached
    assert line.endswith(wait), line
    assert not (tmp_path / "build" / "ingested").exists() and not list((tmp_path / "build").glob(".*"))


# ------------------------------------------------------------------------------------------------------- fast cases
def test_the_code_digest_is_of_every_py_file_of_the_imported_package():
    """Against the files as this test reads them: the package's folder, each .py file's sha256 by its path."""
    import aumesh

    code = compute_probe._aumesh_code()
    root = Path(aumesh.__file__).parent
    assert code["path"] == str(root)
    files = {
        p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in root.rglob("*.py")
        if "__pycache__" not in p.parts
    }
    assert code["files"] == files and len(files) > 100
    whole = hashlib.sha256("".join(f"{k}\0{v}\n" for k, v in sorted(files.items())).encode()).hexdigest()
    assert code["digest"] == whole


def test_the_probe_travels_by_value_so_a_worker_without_its_module_runs_it(monkeypatch, tmp_path):
    """Pickled as ``distributed`` pickles it for ``Client.run``, the probe loads and runs where its module cannot be
    imported (an older aumesh without it); pickled by name, as before, it could not (``AttributeError`` there)."""
    from distributed.protocol import pickle as dask_pickle

    compute_probe._by_value()
    blob = dask_pickle.dumps(compute_probe._probe)
    table = tmp_path / "t.bin"
    table.write_bytes(b"x" * 100)
    monkeypatch.setitem(sys.modules, "aumesh.pipeline.compute.probe", None)  # importing it now fails
    with pytest.raises(ImportError):
        __import__("aumesh.pipeline.compute.probe")
    result = pickle.loads(blob)(str(table), str(tmp_path), "tok")
    assert result["code"]["digest"] == compute_probe._driver_code()["digest"]
    assert tuple(result["read"]) == (100, hashlib.sha256(b"x" * 100).hexdigest())
    assert (tmp_path / result["wrote"]).read_text() == "tok"


def test_the_line_for_another_code_names_both_folders_and_the_files_that_differ(monkeypatch):
    monkeypatch.delenv("AUMESH_COMPUTE_ADDRESS", raising=False)
    ours = compute_probe._driver_code()
    files = dict(ours["files"])
    files["pipeline/prepare/__init__.py"] = "0" * 64
    del files["cli/__init__.py"]
    theirs = {"path": "/elsewhere/src/aumesh", "digest": "f" * 64, "files": files}
    line = compute_probe._probe_problem("tcp://w:1", {"code": theirs}, None, None, None, "t")
    assert line == (
        f"worker tcp://w:1 runs other aumesh code: /elsewhere/src/aumesh (code ffffffffffff), not this stage's "
        f"{ours['path']} (code {ours['digest'][:12]}); they differ in cli/__init__.py, pipeline/prepare/__init__.py. "
        f"Its results would be another code's. Fix: start the workers with this workspace's aumesh (its "
        f"environment's `dask worker`, or PYTHONPATH={os.path.dirname(ours['path'])}), or compute=local runs here."
    )
    none = compute_probe._probe_problem("tcp://w:1", {"code": {"path": None}}, None, None, None, "t")
    assert none is not None and none.startswith("worker tcp://w:1 imports no aumesh, where this stage's ")
    same = {"code": dict(ours), "read": [1, "x"]}
    assert compute_probe._probe_problem("tcp://w:1", same, "/d/t", None, (1, "x"), "t") is None


def test_no_line_claims_outputs_stand_that_dvc_removed(monkeypatch):
    """Under ``dvc repro`` (``DVC_STAGE``) DVC removed a stage's outputs before running it (``release/`` excepted: a
    ``persist`` output): the stopped stage's and the cluster's lines do not say they stand; outside DVC they do."""
    from aumesh import cli
    from aumesh.pipeline import compute

    monkeypatch.delenv("DVC_STAGE", raising=False)
    assert cli._kept("prepare") == "nothing was swapped in, the previous outputs are intact"
    assert compute._kept() == " The previous outputs stand."
    monkeypatch.setenv("DVC_STAGE", "prepare")
    assert cli._kept("prepare") == "nothing was swapped in"
    assert cli._kept("release") == "nothing was swapped in, the previous outputs are intact"
    assert compute._kept() == ""
