"""Tables on object storage: ``paths.data_dir=s3://bucket/prefix`` read where they are (:mod:`aumesh.core.storage`).

The slow cases start moto's S3-compatible server (``moto_server``, a process of its own on a free loopback port),
upload the synthetic py-feat tables there and check the S3 route against the same tables read from disk, the
independent reference: the ingested tables byte for byte, and through ``dvc repro`` the prepared data, the model and
the metrics, on this machine's threads and on a real ``dask scheduler`` + ``dask worker`` started in another folder
(the workers read S3 with their own environment's credentials: workers started without them are named by the
cluster probe). DVC tracks the S3 folder as an external dependency
(its ETags in ``dvc.lock``: an object changed there reruns ingest), ``dvc push``/``dvc pull`` work with an S3 remote
(dvc-s3 from the lock) and skip ``build/prepared`` (``push: false``). Each failure (no bucket, no such prefix, no
credentials, the endpoint down) is one line and exit 2. The fast cases: :class:`~aumesh.core.storage.ObjectPath`
against ``pathlib`` and the local fast path.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path, PurePosixPath

import pytest

from aumesh.config import compose, write_params
from aumesh.core import storage
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from aumesh.synthetic.tables import SynthSpec
from conftest import REPO

BIN = Path(sys.executable).parent
BUCKET = "lab-tables"
#: py-feat CSVs (MPDetector): no-face rows, background faces, z in crop units; one file per 4 videos, one gzipped
SPEC = SynthSpec(n_frames=1500, n_videos=16, seed=7)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


#: No profile: an empty AWS config and credentials file (dvc-s3 reads the file AWS_CONFIG_FILE names, which must exist)
_EMPTY = Path(tempfile.gettempdir()) / "aumesh-test-empty-aws-config"


def aws_env(endpoint: str, credentials: bool = True) -> dict[str, str]:
    """The environment a lab sets for its object store (never the config); without ``credentials``: none anywhere
    (no keys, no profile files, no instance metadata)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("AWS_") and not k.startswith("AUMESH_COMPUTE_")}
    env |= {
        "AWS_ENDPOINT_URL": endpoint,
        "AWS_DEFAULT_REGION": "us-east-1",
        "AWS_EC2_METADATA_DISABLED": "true",
        "AWS_SHARED_CREDENTIALS_FILE": str(_EMPTY),
        "AWS_CONFIG_FILE": str(_EMPTY),
    }
    _EMPTY.touch()
    if credentials:
        env |= {"AWS_ACCESS_KEY_ID": "lab", "AWS_SECRET_ACCESS_KEY": "lab-secret"}
    env["PATH"] = f"{BIN}{os.pathsep}{env['PATH']}"
    return env


class MotoServer:
    """``moto_server`` on 127.0.0.1: an S3-compatible server in a process of its own."""

    def __init__(self, folder: Path):
        self.port = _free_port()
        self.endpoint = f"http://127.0.0.1:{self.port}"
        self.log = open(folder / "moto.log", "ab")
        self.proc = subprocess.Popen(
            [str(BIN / "moto_server"), "-H", "127.0.0.1", "-p", str(self.port)], stdout=self.log, stderr=self.log
        )
        deadline = time.monotonic() + 60
        while True:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1).close()
                break
            except OSError:
                assert self.proc.poll() is None and time.monotonic() < deadline, "moto_server did not start"
                time.sleep(0.1)

    def fs(self):
        import s3fs

        return s3fs.S3FileSystem(
            key="lab",
            secret="lab-secret",
            endpoint_url=self.endpoint,
            skip_instance_cache=True,
            use_listings_cache=False,
        )

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.log.close()


@pytest.fixture(scope="module")
def moto(tmp_path_factory):
    server = MotoServer(tmp_path_factory.mktemp("moto"))
    try:
        yield server
    finally:
        server.stop()


def pyfeat_tables(folder: Path) -> Path:
    """The synthetic py-feat CSVs (and one gzipped) in ``folder``."""
    write_pyfeat_tables(folder, SPEC, detector="mp", fmt="csv", videos_per_file=4)
    first = sorted(folder.glob("*.csv"))[0]
    with open(first, "rb") as src, gzip.open(first.with_name(first.name + ".gz"), "wb") as dst:
        shutil.copyfileobj(src, dst)
    first.unlink()
    return folder


def upload(moto: MotoServer, folder: Path, prefix: str) -> str:
    fs = moto.fs()
    if not fs.exists(BUCKET):
        fs.mkdir(BUCKET)
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            fs.put_file(str(p), f"{BUCKET}/{prefix}/{p.relative_to(folder).as_posix()}")
    return f"s3://{BUCKET}/{prefix}"


def _run(args, cwd, env, check=True, timeout=900):
    proc = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    if check:
        assert proc.returncode == 0, f"{' '.join(map(str, args))} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc


def _one_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1, stderr
    return lines[0]


def _digests(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


# ------------------------------------------------------------------------------------------------------------ fast


def test_object_paths_name_and_sort_as_pathlib_does():
    keys = ["a/b-c/x.csv", "a/b/z.csv.gz", "a/b/y.parquet", "a/.hidden", "a/b/noext"]
    paths = [storage.input_path(f"s3://bkt/{k}") for k in keys]
    assert all(isinstance(p, storage.ObjectPath) for p in paths)
    for k, p in zip(keys, paths, strict=True):
        ref = PurePosixPath("/bkt") / k
        assert (p.name, p.stem, p.suffix) == (ref.name, ref.stem, ref.suffix)
        assert str(p.with_name("m.npy")) == "s3://bkt" + str(ref.with_name("m.npy"))[4:]
    # the order the tables are ingested in: the order pathlib gives the same names on disk
    assert [str(p)[len("s3://bkt/") :] for p in sorted(paths)] == [
        str(p)[5:] for p in sorted(PurePosixPath("/bkt") / k for k in keys)
    ]
    assert storage.absolute(paths[0]) is paths[0] and not storage.is_url("data") and not storage.is_url(Path("s3:/x"))


def test_a_local_folder_keeps_its_own_files_and_order(tmp_path):
    for name in ("b/2.csv", "a/1.csv", "a-b/3.csv", "c.parquet"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_bytes(name.encode() * 3)
    found = storage.list_inputs(tmp_path, "**/*")
    assert found == sorted(p for p in tmp_path.glob("**/*") if p.is_file())
    assert storage.list_inputs(tmp_path / "missing", "**/*") is None
    p = tmp_path / "a-b/3.csv"
    with storage.open_input(p) as fh:
        assert type(fh).__module__ == "_io"  # the builtin file, not fsspec's
    assert storage.read_range(p, 2, 5) == p.read_bytes()[2:7] and storage.size(p) == p.stat().st_size


def test_a_failed_request_is_one_line_naming_the_url_and_the_fix():
    class NoCredentialsError(Exception):
        __module__ = "botocore.exceptions"

    url = "s3://bkt/data"
    line = str(storage.storage_error(url, NoCredentialsError("Unable to locate credentials")))
    assert line.startswith(url + ": no credentials") and "AWS_ACCESS_KEY_ID" in line and "\n" not in line
    line = str(storage.storage_error(url, FileNotFoundError("The specified bucket does not exist")))
    assert "no bucket 'bkt'" in line and "Fix:" in line
    assert isinstance(storage.storage_error(url, FileNotFoundError("x")), OSError)  # the cluster probe catches it


# ------------------------------------------------------------------------------------------------------------ slow


@pytest.mark.slow
def test_ingest_reads_the_s3_tables_as_it_reads_them_from_disk(moto, tmp_path, monkeypatch):
    import dataclasses

    from aumesh.pipeline import ingest
    from conftest import default_config

    data = pyfeat_tables(tmp_path / "data")
    url = upload(moto, data, "ingest-csv")
    for k, v in aws_env(moto.endpoint).items():
        if k.startswith("AWS_"):
            monkeypatch.setenv(k, v)
    cfg = default_config()
    manifests = {}
    for name, where in (("disk", str(data)), ("s3", url)):
        c = dataclasses.replace(cfg, paths=dataclasses.replace(cfg.paths, data_dir=where))
        manifests[name] = ingest.run(c, tmp_path / name)
    assert manifests["s3"]["counts"] == manifests["disk"]["counts"] and manifests["s3"]["counts"]["tables_in"] == 4
    assert [e["source"] for e in manifests["s3"]["sources"]] == [
        url + "/" + Path(e["source"]).name for e in manifests["disk"]["sources"]
    ]
    assert _digests(tmp_path / "s3" / "tables") == _digests(tmp_path / "disk" / "tables")


@pytest.mark.slow
def test_a_parquet_table_on_s3_is_copied_once_and_prepares_as_on_disk(moto, tmp_path, monkeypatch):
    """A clean parquet table is read in place from disk, copied into build/ingested from S3: the same prepared data."""
    import dataclasses

    import numpy as np
    import pandas as pd

    from aumesh.data import tables
    from aumesh.pipeline import ingest, prepare
    from conftest import default_config

    spec = SynthSpec(n_frames=900, n_videos=12, seed=4)
    write_pyfeat_tables(tmp_path / "raw", spec, detector="mp", fmt="parquet", clean_dir=tmp_path / "data")
    url = upload(moto, tmp_path / "data", "clean-parquet")
    for k, v in aws_env(moto.endpoint).items():
        if k.startswith("AWS_"):
            monkeypatch.setenv(k, v)
    cfg = default_config()
    for name, where in (("disk", str(tmp_path / "data")), ("s3", url)):
        c = dataclasses.replace(cfg, paths=dataclasses.replace(cfg.paths, data_dir=where))
        manifest = ingest.run(c, tmp_path / name / "ingested")
        reads = {e["read"] for e in manifest["sources"]}
        assert reads == (
            {"in place"} if name == "disk" else {"cleaned (on object storage: copied once, not read in place)"}
        )
        found = tables.check_tables(manifest["tables"], c.data.mesh_npy, c.data.coerce_numeric)
        prepare.run(found, c, tmp_path / name / "prepared", ingested=manifest["counts"])
    a, b = tmp_path / "disk" / "prepared", tmp_path / "s3" / "prepared"
    np.testing.assert_array_equal(np.load(a / "meshes.npy"), np.load(b / "meshes.npy"))
    pd.testing.assert_frame_equal(pd.read_parquet(a / "frames.parquet"), pd.read_parquet(b / "frames.parquet"))


#: Each failure: (paths.data_dir, whether the stage has credentials, whether the endpoint answers, what the line says)
FAILURES = {
    "no bucket": ("s3://no-such-bucket/tables", True, True, "no bucket 'no-such-bucket'"),
    "no such prefix": (f"s3://{BUCKET}/no-such-prefix", True, True, "no object under this prefix"),
    "no credentials": (f"s3://{BUCKET}/ingest-cli", False, True, "no credentials for the object store"),
    "endpoint down": (f"s3://{BUCKET}/ingest-cli", True, False, "cannot reach the object store at http://127.0.0.1:"),
}


@pytest.fixture(scope="module")
def cli_folder(moto, tmp_path_factory, fixed_conf):
    """A folder with tables under s3://BUCKET/ingest-cli, where the failure cases run ``aumesh ingest``."""
    root = tmp_path_factory.mktemp("s3-cli")
    write_pyfeat_tables(root / "data", SynthSpec(n_frames=120, n_videos=3, seed=1), detector="mp", fmt="csv")
    upload(moto, root / "data", "ingest-cli")
    return root


@pytest.mark.slow
@pytest.mark.parametrize("case", sorted(FAILURES))
def test_each_object_store_failure_is_one_line_naming_the_url_and_exit_2(case, moto, cli_folder, fixed_conf, tmp_path):
    url, credentials, up, says = FAILURES[case]
    endpoint = moto.endpoint if up else f"http://127.0.0.1:{_free_port()}"  # a port nobody listens on
    write_params(compose([f"paths.data_dir={url}"], config_dir=fixed_conf), tmp_path / "params.yaml")
    proc = _run(["aumesh", "ingest"], tmp_path, aws_env(endpoint, credentials), check=False, timeout=120)
    line = _one_line(proc.stderr)
    assert proc.returncode == 2, proc.stderr
    assert line.startswith(f"aumesh ingest: error: {url}: ") and says in line and "Fix: " in line, line
    assert not (tmp_path / "build" / "ingested").exists()


def s3_workspace(root: Path, fixed_conf: Path, url: str | None, data: Path) -> Path:
    """The repo's pipeline in a git + DVC workspace (tests/test_cluster.py's), the py-feat tables in ``data/``
    (``dvc add``) or, with ``url``, only on S3 (``paths.data_dir=url`` in params.yaml, no data/)."""
    from test_cluster import make_workspace

    ws = make_workspace(root, fixed_conf, seed=1, n_frames=300)
    env = aws_env("http://unused")
    _run(["git", "rm", "-q", "--cached", "data.dvc"], ws, env)
    shutil.rmtree(ws / "data")
    (ws / "data.dvc").unlink()
    if url is None:
        shutil.copytree(data, ws / "data")
        _run([BIN / "dvc", "add", "-q", "data"], ws, env)
    else:
        write_params(
            compose(["compute.partition_rows=300", f"paths.data_dir={url}"], config_dir=ws / "conf"), ws / "params.yaml"
        )
    _run(["git", "add", "-A"], ws, env)
    _run(["git", "commit", "-qm", "tables"], ws, env)
    return ws


def compared(ws: Path) -> dict[str, object]:
    """tests/test_cluster.py's outputs, but the ingest manifest (it names the sources where they are: data/... or
    s3://...): its counts instead."""
    from test_cluster import outputs

    out = outputs(ws)
    manifest = json.loads((ws / "build" / "ingested" / "manifest.json").read_text())
    out["build/ingested/manifest.json"] = hashlib.sha256(json.dumps(manifest["counts"]).encode()).hexdigest()
    return out


@pytest.fixture(scope="module")
def repro_pair(moto, tmp_path_factory, fixed_conf):
    """Two workspaces of the same py-feat tables, one reading them from disk, one from S3, each `dvc repro evaluate`
    run on this machine: (disk workspace, s3 workspace, url, env)."""
    root = tmp_path_factory.mktemp("s3-repro")
    data = pyfeat_tables(root / "tables")
    url = upload(moto, data, "repro")
    env = aws_env(moto.endpoint)
    disk = s3_workspace(root / "disk", fixed_conf, None, data)
    s3 = s3_workspace(root / "s3", fixed_conf, url, data)
    for ws in (disk, s3):
        _run([BIN / "dvc", "repro", "evaluate"], ws, env)
    return disk, s3, url, env


@pytest.mark.slow
def test_dvc_repro_reads_the_tables_on_s3_tracks_their_etags_and_equals_disk(repro_pair, moto):
    from test_cluster import assert_same_outputs

    disk, s3, url, env = repro_pair
    assert_same_outputs(compared(s3), compared(disk))
    lock = (s3 / "dvc.lock").read_text()
    import yaml

    deps = {d["path"]: d for d in yaml.safe_load(lock)["stages"]["ingest"]["deps"]}
    # DVC's external dependency: a hash of the objects' ETags (a listing, no download), 4 objects
    assert deps[url]["md5"].endswith(".dir") and deps[url]["nfiles"] == 4, deps
    assert "up to date" in _run([BIN / "dvc", "status", "--with-deps", "evaluate"], s3, env).stdout
    # an object changed on S3 (a frame less) is a changed dependency: ingest reruns
    fs = moto.fs()
    key = sorted(fs.find(url))[-1]
    original = fs.cat_file(key)
    fs.pipe_file(key, original[: original.rstrip(b"\n").rfind(b"\n") + 1])
    try:
        status = _run([BIN / "dvc", "status", "ingest"], s3, env).stdout
        assert "changed deps" in status and url in status, status
    finally:
        fs.pipe_file(key, original)
    assert "up to date" in _run([BIN / "dvc", "status", "--with-deps", "evaluate"], s3, env).stdout


@pytest.mark.slow
def test_workers_started_elsewhere_read_the_tables_on_s3_and_equal_disk(repro_pair, tmp_path, monkeypatch):
    """A real ``dask scheduler`` + 2 ``dask worker`` in another folder, with the lab's AWS_* environment."""
    from test_cluster import Cluster, assert_same_outputs

    disk, s3, url, env = repro_pair
    for k, v in env.items():
        if k.startswith("AWS_"):
            monkeypatch.setenv(k, v)
    (tmp_path / "elsewhere").mkdir()
    cluster = Cluster(tmp_path / "elsewhere")
    try:
        proc = _run([BIN / "dvc", "repro", "-f", "evaluate"], s3, env | {"AUMESH_COMPUTE_ADDRESS": cluster.address})
        assert "Running stage 'ingest'" in proc.stdout
        from distributed import Client

        with Client(cluster.address, set_as_default=False) as client:  # the passes did run on the workers
            assert all(n > 0 for n in client.run(lambda dask_worker: len(dask_worker.state.log)).values())
    finally:
        cluster.stop()
    assert_same_outputs(compared(s3), compared(disk))


@pytest.mark.slow
def test_dvc_push_to_an_s3_remote_skips_build_prepared_and_pull_restores_the_rest(repro_pair, moto):
    import yaml

    disk, _, _, env = repro_pair
    remote = f"s3://{BUCKET}/dvc-remote"
    _run([BIN / "dvc", "remote", "add", "--local", "lab", remote], disk, env)
    _run([BIN / "dvc", "push", "-r", "lab"], disk, env)
    pushed = {k.rsplit("/", 2)[-2] + k.rsplit("/", 1)[-1] for k in moto.fs().find(f"{BUCKET}/dvc-remote")}
    outs = {
        o["path"]: o["md5"]
        for s in yaml.safe_load((disk / "dvc.lock").read_text())["stages"].values()
        for o in s.get("outs", [])
    }
    assert outs["build/ingested"] in pushed and outs["build/model"] in pushed
    assert outs["build/prepared"] not in pushed  # push: false
    before = _digests(disk / "build")
    shutil.rmtree(disk / "build")
    shutil.rmtree(disk / ".dvc" / "cache")
    _run([BIN / "dvc", "pull", "-r", "lab", "--allow-missing"], disk, env)
    after = _digests(disk / "build")
    assert after == {k: v for k, v in before.items() if not k.startswith("prepared/")}
    assert "Running stage 'prepare'" in _run([BIN / "dvc", "repro", "evaluate"], disk, env).stdout  # rebuilt here
    assert _digests(disk / "build") == before
    # the demo's way (make refresh-demo): build/prepared copied into a folder remote all the same, pulled whole
    folder = disk.parent / "folder-remote"
    _run([BIN / "dvc", "remote", "add", "--local", "folder", folder], disk, env)
    _run([BIN / "dvc", "push", "-r", "folder"], disk, env)
    _run([sys.executable, REPO / "scripts" / "push_unpushed.py", folder, "build/prepared"], disk, env)
    shutil.rmtree(disk / "build")
    shutil.rmtree(disk / ".dvc" / "cache")
    # no --allow-missing: every object of the four is there (release/ was never built here)
    _run(
        [BIN / "dvc", "pull", "-r", "folder", "build/ingested", "build/prepared", "build/model", "build/families"],
        disk,
        env,
    )
    assert _digests(disk / "build") == before


@pytest.mark.slow
def test_workers_without_credentials_are_named_by_the_probe(repro_pair, tmp_path, monkeypatch):
    """The workers read S3 with their own environment: started without the keys, the probe names the first one."""
    from test_cluster import Cluster

    _, s3, url, env = repro_pair
    for k in [k for k in os.environ if k.startswith("AWS_")]:
        monkeypatch.delenv(k)
    for k, v in aws_env(env["AWS_ENDPOINT_URL"], credentials=False).items():
        if k.startswith("AWS_"):
            monkeypatch.setenv(k, v)
    (tmp_path / "elsewhere").mkdir()
    cluster = Cluster(tmp_path / "elsewhere", n_workers=1)
    try:
        proc = _run(["aumesh", "ingest"], s3, env | {"AUMESH_COMPUTE_ADDRESS": cluster.address}, check=False)
    finally:
        cluster.stop()
    line = _one_line(proc.stderr)
    assert proc.returncode == 2, proc.stderr
    assert line.startswith("aumesh ingest: error: worker tcp://127.0.0.1:") and f"cannot read {url}/" in line, line
    assert "no credentials for the object store" in line and "AWS_ACCESS_KEY_ID" in line, line
