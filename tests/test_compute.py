"""The Dask engine: the same prepared data and model from any partitioning and any scheduler.

References are independent of the engine: the outlier threshold is recomputed with numpy from the
released reference and the raw tables, the GPA subsample from the seeded hash over all frames;
schedulers are compared with each other and with a real ``distributed.LocalCluster`` (2 worker
processes over loopback).
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from aumesh.core.errors import CorruptFileError
from aumesh.core.io import create_npy
from aumesh.core.schema import VIDEO_COLUMN
from aumesh.data import contract, tables
from aumesh.geometry.align import align_to_reference, generalized_procrustes
from aumesh.pipeline import evaluate as ev
from aumesh.pipeline import integrity, prepare
from aumesh.pipeline.evaluate import statistics_pass
from aumesh.pipeline.evaluate.prepared_data import load_prepared
from aumesh.pipeline.prepare import tasks as prepare_tasks
from aumesh.pipeline.prepare.selection import gpa_hash, low_au_thresholds, pose_mask
from aumesh.synthetic import tables as synth
from conftest import default_config

ROW_GROUP = 97  # cuts videos across row groups, so across partitions


@pytest.fixture(scope="module")
def split_tables(tmp_path_factory):
    """1,200 frames of 60 videos in two files with 97-row row groups: videos split across partitions."""
    root = tmp_path_factory.mktemp("split")
    synth.write_tables(root / "raw", synth.SynthSpec(n_frames=1200, n_videos=60, seed=11, frames_per_file=700))
    (root / "data").mkdir()
    for f in sorted((root / "raw").glob("*.parquet")):
        pq.write_table(pq.read_table(f), root / "data" / f.name, row_group_size=ROW_GROUP)
    return root


def _prepare(root, name, **overrides):
    cfg = default_config(**{"paths.data_dir": str(root / "data"), **overrides})
    found = tables.discover(root / "data", cfg.data.tables, cfg.data.mesh_npy)
    summary = prepare.run(found, cfg, root / name)
    return root / name, summary


def _assert_same_prepared(a, b, exact_meshes=True):
    meshes_a, meshes_b = np.load(a / "meshes.npy"), np.load(b / "meshes.npy")
    if exact_meshes:
        np.testing.assert_array_equal(meshes_a, meshes_b)
    pd.testing.assert_frame_equal(pd.read_parquet(a / "frames.parquet"), pd.read_parquet(b / "frames.parquet"))
    np.testing.assert_array_equal(np.load(a / "video_ids.npy"), np.load(b / "video_ids.npy"))
    for name in ("neutral_mean.npy", "neutral_low_au.npy"):
        np.testing.assert_allclose(np.load(a / name), np.load(b / name), rtol=1e-6)  # float32, summation order
    ra, rb = np.load(a / "reference.npz"), np.load(b / "reference.npz")
    np.testing.assert_array_equal(ra["reference_anchors"], rb["reference_anchors"])
    for k in ("mean_aligned_mesh", "mean_low_au_mesh"):
        np.testing.assert_allclose(ra[k], rb[k], rtol=1e-6)


def test_partitions_cover_every_row_group_once_in_order(split_tables):
    cfg = default_config(**{"paths.data_dir": str(split_tables / "data")})
    found = tables.discover(split_tables / "data", cfg.data.tables, cfg.data.mesh_npy)
    for rows in (1, 250, 10**9):
        parts = tables.partitions(found, rows)
        pieces = [(p.table.path, g) for part in parts for p in part for g in p.row_groups]
        expected = [(t.path, g) for t in found for g in range(pq.ParquetFile(t.path).metadata.num_row_groups)]
        assert pieces == expected
    assert len(tables.partitions(found, 1)) == len(expected) and len(tables.partitions(found, 10**9)) == 1


def test_partition_count_gives_1_2_or_4_workers_equal_rounds():
    """One partition stays one; more are a multiple of 4, the fewest of at most ``partition_rows`` rows each."""
    assert tables.partition_count(3_750, 32_768) == 1
    for n_rows, partition_rows in [(344_418, 32_768), (99_911, 32_768), (3_099_762, 32_768), (40_000, 32_768), (7, 1)]:
        n = tables.partition_count(n_rows, partition_rows)
        least = -(-n_rows // partition_rows)
        assert n % 4 == 0 and least <= n < least + 4, (n_rows, n)


@pytest.mark.parametrize("rows", [250, 400, 700])
def test_partitions_are_balanced(split_tables, rows):
    """ceil(n / partition_rows) partitions (up to a multiple of 4), each within a row group of n / count rows: no
    small remainder partition left for the last round of tasks (the old packing, 'at least partition_rows', gave one)."""
    cfg = default_config(**{"paths.data_dir": str(split_tables / "data")})
    found = tables.discover(split_tables / "data", cfg.data.tables, cfg.data.mesh_npy)
    sizes = [sum(p.n_rows for p in part) for part in tables.partitions(found, rows)]
    total = sum(t.n_rows for t in found)
    assert len(sizes) == tables.partition_count(total, rows) and sum(sizes) == total
    assert max(abs(s - total / len(sizes)) for s in sizes) <= ROW_GROUP, sizes


@pytest.mark.slow
def test_prepared_data_do_not_depend_on_partitioning_or_scheduler(split_tables):
    """GPA on a hashed subsample (gpa_max_frames < frames), outlier cut: same outputs from 1 to 13 partitions."""
    sub = {"preprocess.alignment.gpa_max_frames": 300}
    one, s1 = _prepare(split_tables, "one", **sub, **{"compute.partition_rows": 10**9, "compute": "synchronous"})
    many, s2 = _prepare(split_tables, "many", **sub, **{"compute.partition_rows": 1})
    some, s3 = _prepare(
        split_tables, "some", **sub, **{"compute.partition_rows": 300, "compute": "processes", "compute.n_workers": 2}
    )
    # the checksums' byte ranges follow the partitions (each hashes its own rows while writing); the bytes do not
    checksums = [s.pop("checksums") for s in (s1, s2, s3)]
    assert s1 == s2 == s3
    assert len({c["meshes.npy"]["size"] for c in checksums}) == 1 and len(checksums[1]["meshes.npy"]["blocks"]) > 2
    for name in ("video_ids.npy", "neutral_mean.npy", "neutral_low_au.npy"):  # written the same, byte for byte
        assert len({c[name]["blocks"][0][2] for c in checksums}) == 1, name
    for d, c in zip((one, many, some), checksums, strict=True):
        integrity.verify(d, c)
    _assert_same_prepared(one, many)
    _assert_same_prepared(one, some)


@pytest.mark.slow
def test_alignment_block_size_changes_no_bit(split_tables, monkeypatch):
    """Pass 2 aligns a partition's frames a block at a time (bounded temporaries): blocks of 7 frames, with a ragged
    last block in every partition, give the prepared data of one block a partition, bit for bit."""
    sync = {"compute": "synchronous", "compute.partition_rows": 300, "preprocess.alignment.gpa_max_frames": 300}
    whole, s1 = _prepare(split_tables, "block-whole", **sync)
    monkeypatch.setattr(prepare_tasks, "RESIDUAL_BLOCK", 7)
    blocks, s2 = _prepare(split_tables, "block-7", **sync)
    assert s1 == s2
    _assert_same_prepared(whole, blocks)
    for name in ("meshes.npy", "neutral_mean.npy", "neutral_low_au.npy"):
        np.testing.assert_array_equal(np.load(whole / name), np.load(blocks / name))


@pytest.mark.slow
def test_outlier_threshold_and_gpa_subsample_follow_their_definitions(split_tables):
    """Threshold = numpy quantile of every pose-passing frame's residual; subsample = smallest seeded hashes."""
    k = 300
    out, summary = _prepare(
        split_tables, "defs", **{"preprocess.alignment.gpa_max_frames": k, "compute.partition_rows": 200}
    )
    cfg = default_config()
    frames = pd.concat(
        [pq.read_table(f).to_pandas() for f in sorted((split_tables / "data").glob("*.parquet"))], ignore_index=True
    )
    pose = pose_mask(frames["Pitch"].to_numpy(), frames["Yaw"].to_numpy(), cfg.preprocess)
    idx = list(cfg.preprocess.alignment.anchor_indices)
    anchors = np.stack([frames[[f"{a}_{i}" for i in idx]].to_numpy() for a in "xyz"], axis=2).astype(np.float32)
    h = gpa_hash(frames.loc[pose, VIDEO_COLUMN].to_numpy(object), frames.loc[pose, "frame"].to_numpy(), cfg.seed)
    chosen = np.sort(np.argsort(h)[:k])  # summed in the tables' order
    reference = generalized_procrustes(
        anchors[pose][chosen], cfg.preprocess.alignment.gpa_max_iter, cfg.preprocess.alignment.gpa_tol
    )
    np.testing.assert_allclose(np.load(out / "reference.npz")["reference_anchors"], reference, rtol=1e-6, atol=1e-4)
    residual, _ = align_to_reference(anchors[pose].astype(np.float64), reference)
    threshold = summary["counts"]["alignment_residual_threshold"]
    assert threshold == pytest.approx(np.quantile(residual, 0.99), rel=1e-9)
    assert summary["counts"]["frames_kept"] == int((residual <= threshold).sum())
    # another seed draws another subsample
    assert not np.array_equal(
        np.argsort(gpa_hash(frames[VIDEO_COLUMN].to_numpy(object), frames["frame"].to_numpy(), 1))[:k],
        np.argsort(gpa_hash(frames[VIDEO_COLUMN].to_numpy(object), frames["frame"].to_numpy(), 0))[:k],
    )


def _evaluate(prepared_dir, **overrides):
    cfg = default_config(**{"model.n_components": 12, **overrides})
    return ev.cross_validate_and_fit(load_prepared(prepared_dir), cfg)


def _assert_same_model(a, b, rtol=1e-12):
    (cv_a, fit_a), (cv_b, fit_b) = a, b
    for x, y in ((fit_a.coef, fit_b.coef), (fit_a.mesh_intercept, fit_b.mesh_intercept)):
        assert np.abs(x - y).max() <= rtol * np.abs(y).max()
    ma, mb = cv_a.scalar_metrics(), cv_b.scalar_metrics()  # every logged metric, per-AU reliability included
    assert ma.keys() == mb.keys()
    for key, value in mb.items():
        np.testing.assert_allclose(ma[key], value, rtol=rtol, err_msg=key)
    for key in ("r2_folds", "r2_displacement_folds", "mae_folds", "vertex_error_folds"):
        np.testing.assert_allclose(cv_a.metrics()[key], cv_b.metrics()[key], rtol=rtol, err_msg=key)
    np.testing.assert_allclose(cv_a.frame_vertex_error, cv_b.frame_vertex_error, rtol=1e-6)  # float32


@pytest.fixture(scope="module")
def split_prepared(split_tables):
    """The split set prepared once with every row group its own partition (13 partitions in evaluate too)."""
    out, _ = _prepare(split_tables, "prepared-many", **{"compute.partition_rows": 1})
    return out


def test_per_video_counts_and_row_groups_equal_those_of_the_whole_columns(split_prepared):
    """Row groups cutting videos: the per-video pass equals bincount / min / max of the whole video_index and low_au
    columns and of each row's row group (from the file's metadata)."""
    prepared = load_prepared(split_prepared)
    frames = pq.read_table(split_prepared / "frames.parquet", columns=["video_index", "low_au"]).to_pandas()
    video, low, n_videos = frames["video_index"].to_numpy(), frames["low_au"].to_numpy(), len(prepared.video_ids)
    md = pq.ParquetFile(split_prepared / "frames.parquet").metadata
    group = np.repeat(np.arange(md.num_row_groups), [md.row_group(g).num_rows for g in range(md.num_row_groups)])
    assert len(prepared.row_groups()) == md.num_row_groups > 10 and prepared.n_frames == len(video)
    videos = prepared.videos
    np.testing.assert_array_equal(videos.count, np.bincount(video, minlength=n_videos))
    np.testing.assert_array_equal(videos.low_count, np.bincount(video[low], minlength=n_videos))
    np.testing.assert_array_equal(videos.first_group, pd.Series(group).groupby(video).min().reindex(range(n_videos)))
    np.testing.assert_array_equal(videos.last_group, pd.Series(group).groupby(video).max().reindex(range(n_videos)))
    assert 0 < videos.split.sum() < n_videos


def test_pass_a_results_own_their_rows(split_prepared, tmp_path):
    """A partition's result holds its split videos' sums as rows of their own, not views of the partition's
    per-video arrays (a view keeps the whole array alive until the reduction adds the result)."""
    prepared = load_prepared(split_prepared)
    videos = prepared.videos
    for name, width in statistics_pass.VIDEO_SUMS.items():
        create_npy(tmp_path / f"{name}.npy", np.float64, (len(prepared.video_ids), width))
    fold = ev.video_folds(videos.count, 3)
    parts = [
        statistics_pass.design_partition(
            group, prepared.directory, fold, np.zeros(83), np.zeros(1434), 3, 64, tmp_path, videos.split
        )
        for group in prepared.row_groups()
    ]
    rows = [row for part in parts for values in part.split.values() for row in values]
    assert rows and all(row.base is None for row in rows)


def test_models_agree_across_schedulers_and_partitionings(split_tables, split_prepared):
    """1 thread, 2 threads, synchronous, 13 vs 1 partitions; neutral target too: coefficients and CV metrics to 1e-12."""
    one_partition, _ = _prepare(split_tables, "prepared-one", **{"compute.partition_rows": 10**9})
    for target in ("absolute", "neutral"):
        ref = _evaluate(split_prepared, **{"compute": "synchronous", "preprocess.target": target})
        _assert_same_model(_evaluate(split_prepared, **{"compute.n_workers": 1, "preprocess.target": target}), ref)
        _assert_same_model(_evaluate(split_prepared, **{"compute.n_workers": 2, "preprocess.target": target}), ref)
        _assert_same_model(_evaluate(one_partition, **{"compute": "synchronous", "preprocess.target": target}), ref)


@pytest.mark.slow  # a real LocalCluster of 2 worker processes (~8 s of CPU); test_cluster.py's slow tests too
def test_local_cluster_of_two_worker_processes(split_tables, split_prepared):
    """A real dask.distributed LocalCluster (2 processes, loopback): the same prepared data and model."""
    from distributed import LocalCluster

    with LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
    ) as cluster:
        remote = {"compute": "distributed", "compute.address": cluster.scheduler_address}
        out, _ = _prepare(split_tables, "prepared-cluster", **remote, **{"compute.partition_rows": 1})
        _assert_same_prepared(out, split_prepared)
        _assert_same_model(_evaluate(out, **remote), _evaluate(split_prepared, **{"compute": "synchronous"}))
        # a byte flipped in a middle row group: the workers hash what they read, the driver refuses it before any fit
        start, stop = integrity.load_summary(out)["checksums"]["meshes.npy"]["blocks"][5][:2]
        with open(out / "meshes.npy", "r+b") as fh:
            fh.seek((start + stop) // 2)
            byte = fh.read(1)[0]
            fh.seek((start + stop) // 2)
            fh.write(bytes([byte ^ 0x10]))
        with pytest.raises(CorruptFileError, match=f"meshes.npy: bytes {start:,}-{stop:,} do not match"):
            _evaluate(out, **remote)


def test_low_au_thresholds_are_the_lower_quantile_of_each_video():
    """Rank floor(q (size - 1)) of each video's sorted AU sums = numpy's ``method="lower"`` quantile, ties included."""
    rng = np.random.default_rng(5)
    video = rng.integers(0, 40, size=900)
    au_sum = np.round(rng.random(900) * 4, 1)  # many ties
    for q in (0.0, 0.1, 0.37, 1.0):
        videos, thresholds = low_au_thresholds(au_sum, video, q)
        np.testing.assert_array_equal(videos, np.unique(video))
        np.testing.assert_array_equal(thresholds, [np.quantile(au_sum[video == v], q, method="lower") for v in videos])


@pytest.mark.slow
def test_low_au_frames_of_videos_split_across_partitions_follow_the_whole_set(split_tables):
    """Per-video and population low-AU frames from 13 partitions (videos cut at row groups) against numpy on the
    whole kept set: the low_au column, the per-video low-AU neutrals, the population count and mesh."""
    q = 0.37
    out, summary = _prepare(
        split_tables, "low-au-split", **{"compute.partition_rows": 1, "preprocess.neutral.low_au_quantile": q}
    )
    frames = pd.read_parquet(out / "frames.parquet")
    meshes = np.load(out / "meshes.npy").astype(np.float64)
    video = frames["video_index"].to_numpy()
    parquet = pq.ParquetFile(out / "frames.parquet")  # a row group per partition
    groups = [
        set(parquet.read_row_group(g, columns=["video_index"]).column(0).to_pylist())
        for g in range(parquet.num_row_groups)
    ]
    split = {v for g, a in enumerate(groups) for b in groups[g + 1 :] for v in a & b}
    assert len(split) >= 5  # kept frames of these videos lie in two partitions
    au_sum = frames[[c for c in frames.columns if c.startswith("AU")]].to_numpy().sum(axis=1)
    low_video = np.zeros(len(frames), bool)
    for v in np.unique(video):
        mine = video == v
        low_video[mine] = au_sum[mine] <= np.quantile(au_sum[mine], q, method="lower")
    np.testing.assert_array_equal(frames["low_au"].to_numpy(), low_video)
    neutral = np.load(out / "neutral_low_au.npy")
    for v in sorted(split):
        np.testing.assert_allclose(neutral[v], meshes[(video == v) & low_video].mean(axis=0), rtol=1e-6, atol=1e-4)
    low_population = au_sum <= np.quantile(au_sum, q)
    assert summary["n_low_au_population"] == int(low_population.sum())
    mean_low = np.load(out / "reference.npz")["mean_low_au_mesh"]
    np.testing.assert_allclose(mean_low.T.ravel(), meshes[low_population].mean(axis=0), rtol=1e-6, atol=1e-4)


def _with_roll(split_tables, tmp_path, roll):
    """The split tables (same row groups) with Roll replaced by ``roll`` (n_frames,) in the tables' order."""
    (tmp_path / "data").mkdir(parents=True)
    start = 0
    for f in sorted((split_tables / "data").glob("*.parquet")):
        df = pq.read_table(f).to_pandas()
        df["Roll"] = roll[start : start + len(df)]
        start += len(df)
        df.to_parquet(tmp_path / "data" / f.name, index=False, row_group_size=ROW_GROUP)
    return tmp_path


@pytest.mark.slow  # three prepare runs over 13 partitions (~8 s of CPU); the median rule itself is checked below
def test_pose_units_check_fires_across_partitions_at_the_median(split_tables, tmp_path):
    """Roll in degrees (every value below pi, not pose-filtered) stops the run over 13 partitions, with numpy's median
    in the message; the check is on the median: half the frames at 0.5 and half at 1.5 rad (median 1.0) pass,
    one frame more at 1.5 fails."""
    n = sum(pq.ParquetFile(f).metadata.num_rows for f in (split_tables / "data").glob("*.parquet"))
    roll = np.clip(np.rad2deg(np.random.default_rng(2).normal(0.0, 0.15, n)), -3.1, 3.1)
    root = _with_roll(split_tables, tmp_path / "degrees", roll)
    with pytest.raises(tables.TableError, match="Roll") as err:
        _prepare(root, "out", **{"compute.partition_rows": 1})
    median = np.median(np.abs(roll.astype(np.float32)).astype(np.float64))
    assert f"median |Roll| = {median:.2f}" in str(err.value) and "degrees" in str(err.value)
    assert median > 1.0

    halves = np.where(np.random.default_rng(3).permutation(n) < n // 2, 0.5, 1.5)
    assert n % 2 == 0 and (halves == 1.5).sum() == n // 2
    _prepare(_with_roll(split_tables, tmp_path / "median-1", halves), "out", **{"compute.partition_rows": 1})
    one_more = halves.copy()
    one_more[np.flatnonzero(halves == 0.5)[0]] = 1.5
    with pytest.raises(tables.TableError, match=r"median \|Roll\| = 1\.50"):
        _prepare(_with_roll(split_tables, tmp_path / "median-1.5", one_more), "out", **{"compute.partition_rows": 1})


@pytest.mark.parametrize("n", [1, 2, 7, 10, 101])
def test_pose_medians_are_computed_whenever_a_median_can_exceed_the_limit(n):
    """The counts above the limit skip the exact medians only when numpy's median is at or below it, for every count
    of values above it (odd and even frame counts, values exactly at the limit among them)."""
    rng = np.random.default_rng(n)
    limit = contract.MAX_MEDIAN_ABS_POSE_RAD
    for n_above in range(n + 1):
        for below in (rng.uniform(0.0, limit, n), np.full(n, limit)):
            values = below.copy()
            values[rng.permutation(n)[:n_above]] = limit + rng.uniform(1e-9, 2.0, n_above)
            counts = np.array([0, n_above, 0])
            if not contract.pose_medians_may_exceed(counts, n):
                assert np.median(values) <= limit
        assert contract.pose_medians_may_exceed(counts, n) == (n_above >= n - n // 2)


def test_prepared_frames_store_only_the_video_ids_as_a_dictionary(split_prepared):
    """frames.parquet: dictionary pages for video_id only; on continuous columns (AUs, pose) a dictionary overflows
    and falls back to plain pages after the work of building it (0.45 s of prepare at 344k frames)."""
    md = pq.ParquetFile(split_prepared / "frames.parquet").metadata
    columns = md.row_group(0)
    dictionary = {
        columns.column(i).path_in_schema
        for i in range(columns.num_columns)
        if "PLAIN_DICTIONARY" in columns.column(i).encodings or "RLE_DICTIONARY" in columns.column(i).encodings
    }
    assert dictionary == {"video_id"}


@pytest.mark.slow
@pytest.mark.parametrize("scheduler", ["synchronous", "threads", "processes"])
def test_local_schedulers_do_not_import_dask_distributed(scheduler):
    """A pass on a local scheduler leaves dask.distributed unimported (given a scheduler's name, dask imports it to
    look for a client: 0.2 s of every stage)."""
    code = (
        "import sys; from aumesh.config import ComputeConfig; from aumesh.pipeline import compute\n"
        f"with compute.engine(ComputeConfig(scheduler={scheduler!r}, n_workers=2)):\n"
        "    assert compute.map_gather(abs, [-1, -2, 3]) == [1, 2, 3]\n"
        "print('distributed' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc arenas")
def test_thread_passes_allocate_from_one_malloc_arena_per_worker(tmp_path):
    """A pass on the local threads (2 workers) leaves at most 2 glibc malloc arenas (glibc's own count, ``malloc_info``),
    not one per allocating thread: every arena keeps the holes of the partitions' freed arrays, so their number is
    what made a stage's resident memory grow with the partitions it streamed."""
    report = tmp_path / "malloc_info.xml"
    code = (
        "import ctypes, numpy as np; from aumesh.config import ComputeConfig; from aumesh.pipeline import compute\n"
        "def task(n):\n"
        "    return sum(float(np.ones(k).sum()) for k in range(1000, 3000, 7))\n"
        "with compute.engine(ComputeConfig(scheduler='threads', n_workers=2)):\n"
        "    compute.map_gather(task, list(range(64)))\n"
        "libc = ctypes.CDLL('libc.so.6'); libc.fopen.restype = ctypes.c_void_p\n"
        f"fh = libc.fopen({str(report).encode()!r}, b'w'); libc.malloc_info(0, ctypes.c_void_p(fh)); libc.fclose(ctypes.c_void_p(fh))\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)
    arenas = report.read_text().count("<heap nr=")
    assert 1 <= arenas <= 2


def test_local_map_runs_on_the_local_threads_in_order_and_one_by_one_when_synchronous():
    """The fits' map: results in the items' order; as many threads as workers at once (a barrier only opens
    when both jobs run together); the caller's thread alone under the synchronous scheduler."""
    import threading

    from aumesh.config import ComputeConfig
    from aumesh.pipeline import compute

    both_running = threading.Barrier(2, timeout=10)

    def job(x):
        both_running.wait()  # BrokenBarrierError (after 10 s) if the two jobs ran one after the other
        return x * x, threading.current_thread().name

    with compute.engine(ComputeConfig(scheduler="threads", n_workers=2)):
        out = compute.local_map(job, [3, 4])
    assert [v for v, _ in out] == [9, 16]
    assert len({name for _, name in out}) == 2
    with compute.engine(ComputeConfig(scheduler="synchronous")):
        out = compute.local_map(lambda x: (x, threading.current_thread().name), [1, 2, 3])
    assert out == [(x, threading.current_thread().name) for x in (1, 2, 3)]


@pytest.mark.parametrize("scheduler", ["synchronous", "threads"])
def test_a_pass_returns_freed_memory_when_it_starts_every_few_tasks_and_when_it_ends(scheduler, monkeypatch):
    """Freed memory goes back to the system before the pass's first task (what the stage freed between passes), after
    its last and, in a pass of more than TRIM_AFTER_TASKS partitions, every TRIM_EVERY_TASKS tasks the process runs;
    not after each task (a task that finds its predecessor's freed pages reuses them; returned pages were faulted in
    again by the next task)."""
    import itertools
    import threading

    from aumesh.config import ComputeConfig
    from aumesh.pipeline import compute
    from aumesh.pipeline.compute import memory as compute_memory

    events, lock = [], threading.Lock()

    def task(x):
        with lock:
            events.append("task")
        return x

    k = compute.TRIM_EVERY_TASKS
    monkeypatch.setattr(compute_memory, "release_freed_memory", lambda: events.append("release"))
    # a long pass (more than TRIM_AFTER_TASKS partitions) also every k tasks; a short one at its end only
    for n, periodic in ((compute.TRIM_AFTER_TASKS + k + 1, True), (compute.TRIM_AFTER_TASKS, False)):
        for run in (
            lambda n=n: compute.map_gather(task, list(range(n))) == list(range(n)),
            lambda n=n: compute.map_reduce(task, lambda a, b: a + b, list(range(n))) == n * (n - 1) // 2,
        ):
            monkeypatch.setattr(compute, "_TASKS_RUN", itertools.count(1))
            events.clear()
            with compute.engine(ComputeConfig(scheduler=scheduler, n_workers=2)):
                assert run()
            assert events.count("task") == n and events.count("release") == (n // k if periodic else 0) + 2
            assert events[0] == events[-1] == "release"  # the pass's start and end
            if scheduler == "synchronous" and periodic:  # one task at a time: after every k-th task
                assert events == (
                    ["release"] + (["task"] * k + ["release"]) * (n // k) + ["task"] * (n % k) + ["release"]
                )


class _Held:
    """A partition's result that counts the results alive at once (in one process)."""

    alive, most, lock = set(), 0, threading.Lock()

    def __init__(self, text: str):
        self.text = text
        with _Held.lock:
            _Held.alive.add(id(self))
            _Held.most = max(_Held.most, len(_Held.alive))

    def __del__(self):
        with _Held.lock:
            _Held.alive.discard(id(self))

    def __add__(self, other: _Held) -> _Held:
        return _Held(f"({self.text}+{other.text})")


def _held(i: int) -> _Held:
    time.sleep(0.002)
    return _Held(str(i))


@pytest.mark.parametrize("scheduler", ["synchronous", "threads"])
def test_map_reduce_sums_in_partition_order_holding_a_few_results_at_any_partition_count(scheduler):
    """A left fold in partition order on every scheduler (the same float additions), and the results alive at once
    do not grow with the partitions (a tree of pairs held one per level: 9 at 96 partitions, 11 at 400)."""
    from aumesh.config import ComputeConfig
    from aumesh.pipeline import compute

    most = {}
    for n in (4, 96, 400):
        _Held.most = 0
        with compute.engine(ComputeConfig(scheduler=scheduler, n_workers=2)):
            total = compute.map_reduce(_held, _Held.__add__, list(range(n)))
        expected = "0"
        for i in range(1, n):
            expected = f"({expected}+{i})"
        assert total.text == expected
        most[n] = _Held.most
    # 2 workers: the total, the results running and those waiting for it (4); the threads scheduler under load
    # sometimes holds one or two more (6 and 7 seen), still fewer than the 11 a tree of pairs holds at 400
    assert most[400] <= 2 * 2 + 4 < 11, most


@pytest.mark.slow
def test_a_process_pool_serves_every_pass_of_an_engine():
    """The ``processes`` scheduler starts its workers once per engine, not once per pass (a fresh pool re-imports
    NumPy, pyarrow and aumesh in every worker: prepare's ~20 passes took 44 s instead of 10 s at 100k frames)."""
    from aumesh.config import ComputeConfig
    from aumesh.pipeline import compute

    with compute.engine(ComputeConfig(scheduler="processes", n_workers=2)):
        first, second = (set(compute.map_gather(_worker_pid, list(range(8)))) for _ in range(2))
    assert os.getpid() not in first | second
    assert first & second  # fresh pools: disjoint sets of worker processes
    assert len(first | second) <= 2


def _worker_pid(_):
    return os.getpid()


@pytest.mark.parametrize("preset, expected", [(None, "system"), ("mimalloc", "mimalloc")])
def test_stage_processes_allocate_arrow_buffers_with_the_system_allocator(preset, expected):
    """The ``aumesh`` entry point selects Arrow's system pool before pyarrow is imported (mimalloc, pyarrow's default,
    kept freed partition buffers resident); a user's ``ARROW_DEFAULT_MEMORY_POOL`` stands."""
    from aumesh.pipeline.compute.memory import ARROW_POOL_ENV

    code = (
        "import aumesh.cli as cli\ncli.main = lambda: 0\ntry:\n    cli.run()\nexcept SystemExit:\n    pass\n"
        "import pyarrow as pa\nprint(pa.default_memory_pool().backend_name)"
    )
    env = {k: v for k, v in os.environ.items() if k != ARROW_POOL_ENV}
    if preset:
        env[ARROW_POOL_ENV] = preset
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.split()[-1] == expected
