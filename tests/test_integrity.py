"""Checksums of the prepared data (``aumesh.pipeline.integrity``): ``meshes.npy``'s blocks verified as evaluate's first
pass reads them, the rest up front.

References: ``xxhash``/``hashlib`` digests of the bytes read back with plain Python, and the byte ranges of each row
group computed from ``frames.parquet``'s footer and the ``.npy`` header here, not by the code under test.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from itertools import pairwise
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import xxhash

from aumesh import cli
from aumesh.config import write_params
from aumesh.core.errors import CorruptFileError
from aumesh.core.io import create_npy
from aumesh.pipeline import evaluate as ev
from aumesh.pipeline import integrity
from aumesh.pipeline.evaluate import statistics_pass
from aumesh.pipeline.evaluate.prepared_data import load_prepared
from aumesh.synthetic.tables import SynthSpec, write_tables
from conftest import default_config, new_store

PREPARED = "build/prepared"
FIX = "dvc repro -f prepare"


# ------------------------------------------------------------------------------------------------- units
def test_range_digests_of_pieces_in_file_order_equal_the_ranges_hashed_whole(tmp_path):
    """Bytes fed in pieces of any size (cutting ranges anywhere, gaps between ranges skipped) give each range the digest
    of its bytes hashed at once, for both algorithms."""
    rng = np.random.default_rng(0)
    data = rng.integers(0, 256, 10_000, dtype=np.uint8).tobytes()
    ranges = [(100, 1_000), (1_000, 1_001), (2_500, 7_777), (9_000, 10_000)]
    for algorithm, ref in (("xxh3_128", lambda b: xxhash.xxh3_128(b).hexdigest()), ("sha256", None)):
        ref = ref or (lambda b: hashlib.sha256(b).hexdigest())
        for step in (1, 7, 999, 4_096, 10_000):
            digests = integrity.RangeDigests(ranges, algorithm)
            for pos in range(50, len(data), step):  # the first 50 bytes never fed: no range starts there
                digests.update(pos, data[pos : pos + step])
            assert digests.digests == {(a, b): ref(data[a:b]) for a, b in ranges}, (algorithm, step)
    path = tmp_path / "f"
    path.write_bytes(data)
    assert integrity.hash_range(path, 2_500, 7_777) == xxhash.xxh3_128(data[2_500:7_777]).hexdigest()


def test_range_digests_refuse_pieces_out_of_order():
    digests = integrity.RangeDigests([(0, 10)])
    digests.update(0, b"abcd")
    with pytest.raises(RuntimeError, match="out of order"):
        digests.update(5, b"ef")


def _record(path: Path, bounds: list[int]) -> dict:
    data = path.read_bytes()
    blocks = [(a, b, xxhash.xxh3_128(data[a:b]).hexdigest()) for a, b in pairwise(bounds)]
    return integrity.file_record(path, blocks)


def test_streamed_blocks_are_deferred_and_the_rest_verified_up_front(tmp_path):
    """Blocks inside a partition's range are returned for the pass; the header and a block no range holds whole are
    read here: a flipped byte there is refused at once, one in a deferred block only by the check of its digests."""
    path = tmp_path / "m.bin"
    path.write_bytes(os.urandom(1_000))
    records = {"m.bin": _record(path, [0, 100, 400, 700, 1_000])}
    ranges = {"m.bin": {0: (100, 400), 1: (400, 650), 2: (650, 1_000)}}  # 400-700 straddles two ranges
    checks = integrity.verify(tmp_path, records, streamed=ranges)
    check = checks["m.bin"]
    assert check.ranges(0) == [(100, 400)] and check.ranges(1) == [] and check.ranges(2) == [(700, 1_000)]

    def flip(at: int) -> None:
        raw = bytearray(path.read_bytes())
        raw[at] ^= 0x01
        path.write_bytes(bytes(raw))

    for at, block in ((5, "0-100"), (500, "400-700")):  # header, straddling block: up front
        flip(at)
        with pytest.raises(CorruptFileError, match=f"m.bin: bytes {block} do not match the xxh3_128 checksum"):
            integrity.verify(tmp_path, records, streamed=ranges)
        flip(at)
    flip(800)  # in a deferred block: passes up front, refused by the pass's digests
    checks = integrity.verify(tmp_path, records, streamed=ranges)
    data = path.read_bytes()
    got = {(a, b): xxhash.xxh3_128(data[a:b]).hexdigest() for a, b in ((100, 400), (700, 1_000))}
    with pytest.raises(CorruptFileError, match="bytes 700-1,000 do not match"):
        checks["m.bin"].check(got)
    with pytest.raises(RuntimeError, match="not hashed"):  # a pass that skipped a block is a bug, never a pass
        checks["m.bin"].check({(100, 400): got[(100, 400)]})


def test_sha256_records_of_an_older_prepare_still_verify(tmp_path):
    path = tmp_path / "m.bin"
    path.write_bytes(os.urandom(300))
    data = path.read_bytes()
    record = {"algorithm": "sha256", "size": 300, "blocks": [[0, 300, hashlib.sha256(data).hexdigest()]]}
    integrity.verify(tmp_path, {"m.bin": record})
    record["blocks"][0][2] = hashlib.sha256(b"other").hexdigest()
    with pytest.raises(CorruptFileError, match="sha256 checksum"):
        integrity.verify(tmp_path, {"m.bin": record})


# ------------------------------------------------------------------------------------- evaluate, end to end
@pytest.fixture(scope="module")
def good_workspace(tmp_path_factory):
    """A workspace whose prepared meshes are 4 row groups (4 partitions), prepared and evaluated once."""
    ws = tmp_path_factory.mktemp("integrity") / "ws"
    ws.mkdir()
    write_tables(ws / "data", SynthSpec(n_frames=400, n_videos=40, seed=3))
    for f in (ws / "data").glob("*.parquet"):  # 50-row row groups: prepare's partitions are whole row groups
        pq.write_table(pq.read_table(f), f, row_group_size=50)
    write_params(default_config(**{"compute.partition_rows": 100}).to_dict(), ws / "params.yaml")
    old = Path.cwd()
    os.chdir(ws)
    try:
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{new_store(ws / 'mlflow.db')}")
            for stage in ("ingest", "prepare", "evaluate"):
                assert cli.main([stage]) == 0
    finally:
        os.chdir(old)
    return ws


def _runs(ws: Path) -> pd.DataFrame:
    import mlflow

    client = mlflow.MlflowClient(tracking_uri=f"sqlite:///{ws / 'mlflow.db'}")
    runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
    return pd.DataFrame({"run_id": [r.info.run_id for r in runs], "status": [r.info.status for r in runs]})


def _tree(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() for p in root.rglob("*") if p.is_file()
    }


def _row_group_bytes(prepared: Path) -> list[tuple[int, int]]:
    """Each row group's byte range in meshes.npy, from the parquet footer and numpy's header reader."""
    with open(prepared / "meshes.npy", "rb") as fh:
        np.lib.format.read_magic(fh)
        shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
        offset = fh.tell()
    row = shape[1] * dtype.itemsize
    md = pq.ParquetFile(prepared / "frames.parquet").metadata
    bounds = np.cumsum([0] + [md.row_group(g).num_rows for g in range(md.num_row_groups)])
    assert bounds[-1] == shape[0]
    return [(offset + int(a) * row, offset + int(b) * row) for a, b in pairwise(bounds)]


def _flip(path: Path, at: int, mask: int = 0x01) -> None:
    with open(path, "r+b") as fh:  # in place: as a byte flipped in DVC's hard-linked cache
        fh.seek(at)
        byte = fh.read(1)[0]
        fh.seek(at)
        fh.write(bytes([byte ^ mask]))


def _evaluate_refused(ws: Path, capsys) -> str:
    old = Path.cwd()
    os.chdir(ws)
    try:
        code = cli.main(["evaluate"])
    finally:
        os.chdir(old)
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.startswith("aumesh evaluate: error: ") and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err and FIX in err, err
    return err


@pytest.mark.parametrize("where", ["first", "middle", "last"])
def test_byte_flipped_in_a_partition_of_meshes_is_refused_before_any_fit(workspace, where, capsys):
    """A byte flipped in the first, a middle or the last row group's rows: evaluate's first pass hashes what it reads
    and stops before any fit: one line naming the file, that row group's bytes and the fix; nothing written, no run
    FINISHED (the run opened beside the pass is FAILED, with the reason)."""
    ranges = _row_group_bytes(workspace / PREPARED)
    assert len(ranges) == 4
    a, b = ranges[{"first": 0, "middle": 2, "last": 3}[where]]
    kept = {d: _tree(workspace / d) for d in ("build/model", PREPARED)}
    runs = _runs(workspace)
    _flip(workspace / PREPARED / "meshes.npy", (a + b) // 2)
    kept[PREPARED] = _tree(workspace / PREPARED)
    err = _evaluate_refused(workspace, capsys)
    assert f"{PREPARED}/meshes.npy: bytes {a:,}-{b:,} do not match the xxh3_128 checksum" in err, err
    assert {d: _tree(workspace / d) for d in kept} == kept
    after = _runs(workspace)
    new = after[~after.run_id.isin(runs.run_id)]
    assert list(new.status) == ["FAILED"], after
    pd.testing.assert_frame_equal(after[after.run_id.isin(runs.run_id)].reset_index(drop=True), runs)


@pytest.mark.parametrize(
    "name, where",
    [("meshes.npy", "header"), ("frames.parquet", 0.5), ("neutral_mean.npy", 0.7), ("video_ids.npy", 0.9)],
)
def test_byte_flipped_in_a_header_or_metadata_is_refused_before_a_run_opens(workspace, name, where, capsys):
    path = workspace / PREPARED / name
    runs = _runs(workspace)
    if where == "header":  # a space of the header's padding made a tab: numpy still parses it, the checksum does not
        at = path.read_bytes()[:128].rindex(b" ")
        _flip(path, at, 0x20 ^ 0x09)
        np.load(path, mmap_mode="r")
    else:
        _flip(path, int(path.stat().st_size * where))
    err = _evaluate_refused(workspace, capsys)
    assert f"{PREPARED}/{name}: bytes " in err and "checksum" in err, err
    if where == "header":
        assert f"meshes.npy: bytes 0-{_row_group_bytes(workspace / PREPARED)[0][0]:,} " in err, err
    pd.testing.assert_frame_equal(_runs(workspace), runs)


def test_the_first_pass_hashes_every_byte_of_meshes_it_reads(good_workspace, tmp_path):
    """The row groups' blocks are all deferred to pass A, and its digests are those of the file's bytes (blocks of 37
    rows, reordered by fold: fed back in the file's order)."""
    d = good_workspace / PREPARED
    prepared = load_prepared(d)
    check = prepared.mesh_check
    ranges = _row_group_bytes(d)
    assert [r for g in range(4) for r in check.ranges(g)] == ranges
    for name, width in statistics_pass.VIDEO_SUMS.items():
        create_npy(tmp_path / f"{name}.npy", np.float64, (len(prepared.video_ids), width))
    fold = ev.video_folds(prepared.videos.count, 3)
    digests: dict = {}
    for group in prepared.row_groups():
        part = statistics_pass.design_partition(
            group, d, fold, np.zeros(83), np.zeros(1434), 3, 37, tmp_path, prepared.videos.split, check
        )
        digests |= part.digests
    data = (d / "meshes.npy").read_bytes()
    assert digests == {(a, b): xxhash.xxh3_128(data[a:b]).hexdigest() for a, b in ranges}


@pytest.mark.parametrize("scheduler", ["synchronous", "local", "processes"])
def test_every_scheduler_refuses_a_flipped_partition(good_workspace, tmp_path, scheduler):
    """The digests come back from the tasks wherever they ran (threads, worker processes) and are compared in the
    driver: the same refusal on every local scheduler (a LocalCluster: tests/test_compute.py)."""
    d = tmp_path / "prepared"
    shutil.copytree(good_workspace / PREPARED, d)
    a, b = _row_group_bytes(d)[1]
    _flip(d / "meshes.npy", a + 3)
    cfg = default_config(**{"compute": scheduler, "compute.n_workers": 2} if scheduler != "synchronous" else {})
    with pytest.raises(CorruptFileError, match=f"meshes.npy: bytes {a:,}-{b:,} do not match"):
        ev.cross_validate_and_fit(load_prepared(d), cfg)
