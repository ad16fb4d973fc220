"""Bad frame tables fail with an error naming the file, the column and the fix; good ones in any layout pass."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from aumesh.core.schema import AU_COLUMNS, N_VERTICES, POSE_COLUMNS
from aumesh.data import tables
from aumesh.geometry.align import apply_similarity_vertices
from aumesh.pipeline import prepare
from aumesh.synthetic.tables import SynthSpec, write_tables
from conftest import default_config

PATTERN, NPY = "**/*.parquet", "{stem}.npy"


def _frame(small_tables):
    path = sorted(small_tables.glob("*.parquet"))[0]
    return path, pd.read_parquet(path)


def _discover_and_read(data_dir):
    found = tables.discover(data_dir, PATTERN, NPY)
    for t in found:
        tables.read_metadata(t)
        for _ in tables.iter_vertices(t, 128):
            pass
    return found


def test_valid_columns_layout_is_read_by_name_in_any_column_order(small_tables):
    path, df = _frame(small_tables)
    shuffled = df[list(np.random.default_rng(0).permutation(df.columns))]
    shuffled.to_parquet(path)
    (found,) = tables.discover(small_tables, PATTERN, NPY)
    meta = tables.read_metadata(found)
    np.testing.assert_array_equal(meta["Yaw"].to_numpy(), df["Yaw"].to_numpy())
    np.testing.assert_array_equal(meta.columns[-3:], list(POSE_COLUMNS))  # model order Pitch, Yaw, Roll
    _, block = next(tables.iter_vertices(found, 1000, [10, 263]))
    np.testing.assert_allclose(block[:, 1, 0], df["x_263"].to_numpy())
    np.testing.assert_allclose(block[:, 0, 2], df["z_10"].to_numpy())


def test_pyfeat_split_layout_with_float16_npy_and_input_column(tmp_path):
    write_tables(tmp_path / "data", SynthSpec(n_frames=200, n_videos=20, seed=2, layout="pyfeat"))
    npy = sorted((tmp_path / "data").glob("*.npy"))[0]
    mesh = np.load(npy)
    np.save(npy, mesh.astype(np.float16))
    (found,) = tables.discover(tmp_path / "data", PATTERN, NPY)
    assert found.mesh_npy == npy and found.video_from_input
    meta = tables.read_metadata(found)
    assert meta["video_id"].iloc[0] == "videos/vid000000.mp4"  # py-feat's `input` path as written
    _, block = next(tables.iter_vertices(found, 64))
    np.testing.assert_allclose(block, mesh[:64].astype(np.float16).astype(np.float64))


def test_npy_mesh_chunks_are_the_stored_rows_read_without_a_memory_map(tmp_path, monkeypatch):
    write_tables(tmp_path / "data", SynthSpec(n_frames=300, n_videos=20, seed=3, layout="pyfeat"))
    npy = sorted((tmp_path / "data").glob("*.npy"))[0]
    mesh = np.load(npy).astype(np.float16)
    np.save(npy, mesh)
    (found,) = tables.discover(tmp_path / "data", PATTERN, NPY)
    real_load = np.load
    monkeypatch.setattr(
        np,
        "load",
        lambda *a, **k: (
            pytest.fail("mesh rows read through np.load (a memory map)") if k.get("mmap_mode") else real_load(*a, **k)
        ),
    )
    starts, rows, columns, previous = [], [], [], None
    for start, chunk in tables.iter_mesh_chunks(found, 64, row_groups=None):
        assert chunk.vertices.dtype == np.float16  # as stored: converted a block at a time later
        # every chunk is read into the same buffer (one chunk resident a task, no page faults per chunk)
        assert previous is None or np.shares_memory(chunk.vertices, previous)
        previous = chunk.vertices
        n = len(chunk)  # moved by the identity, as pass 3 moves them: the rows' coordinates, axis-major
        moved = apply_similarity_vertices(chunk.vertices, np.tile(np.eye(3), (n, 1, 1)), np.ones(n), np.zeros((n, 3)))
        starts.append(start), rows.append(chunk.vertices.copy()), columns.append(moved.T)
    assert starts == list(range(0, len(mesh), 64))
    np.testing.assert_array_equal(np.concatenate(rows), mesh)
    coords = np.concatenate(columns, axis=1)
    # axis-major rows [x_0..x_477 | y_.. | z_..], one column per frame, float16 widened exactly
    np.testing.assert_array_equal(coords, mesh.astype(np.float64).transpose(2, 1, 0).reshape(3 * N_VERTICES, -1))


def test_a_partitions_npy_chunks_are_its_pieces_rows_read_into_one_buffer(tmp_path):
    """A partition's pieces (here 3-4 tables) are read into one buffer: the last chunk of one piece, still held by the
    consumer, would otherwise live beside the next piece's fresh buffer (2 chunks a task at 3.1M frames)."""
    write_tables(tmp_path / "data", SynthSpec(n_frames=600, n_videos=30, seed=4, layout="pyfeat", frames_per_file=200))
    found = tables.discover(tmp_path / "data", PATTERN, NPY)
    (part,) = tables.partitions(found, 10_000)
    assert len({p.table.path for p in part}) == len(found) >= 3
    expected = np.concatenate([np.load(t.mesh_npy) for t in found])
    starts, rows, buffer = [], [], None
    for start, chunk in tables.iter_pieces_mesh_chunks(part, 64):
        assert buffer is None or np.shares_memory(chunk.vertices, buffer)
        buffer = chunk.vertices
        starts.append(start), rows.append(chunk.vertices.copy())
    np.testing.assert_array_equal(np.concatenate(rows), expected)
    assert starts == [
        s + sum(len(np.load(t.mesh_npy)) for t in found[:i])
        for i, t in enumerate(found)
        for s in range(0, len(np.load(t.mesh_npy)), 64)
    ]


@pytest.mark.slow
@pytest.mark.parametrize("layout", ["pyfeat", "columns"])
def test_a_nan_mesh_coordinate_past_the_first_block_of_a_chunk_is_found(tmp_path, layout):
    """The finiteness check walks a chunk a block at a time (no chunk-sized bool temporary); a NaN in a later
    block still fails, naming the row."""
    write_tables(tmp_path / "data", SynthSpec(n_frames=900, n_videos=20, seed=5, layout=layout, frames_per_file=900))
    (found,) = tables.discover(tmp_path / "data", PATTERN, NPY)
    row = tables._FINITE_BLOCK * 3 + 7
    if layout == "pyfeat":
        mesh = np.load(found.mesh_npy)
        mesh[row, 33, 1] = np.nan
        np.save(found.mesh_npy, mesh)
    else:
        df = pd.read_parquet(found.path)
        df.loc[row, "y_33"] = np.nan
        df.to_parquet(found.path)
    with pytest.raises(tables.TableError, match=rf"y_33 is NaN/inf at row {row}\b"):
        for _ in tables.iter_mesh_chunks(found, 900):
            pass


@pytest.mark.slow
def test_parquet_mesh_columns_are_read_a_row_group_at_a_time_not_pre_buffered(tmp_path):
    """Reading a partition of 8 row groups holds one row group's column chunks at a time, not all 8 (pyarrow's
    default ``pre_buffer`` read every requested row group's mesh columns before the first batch: for 1,434 columns
    that is the whole partition, compressed, resident at once). Arrow's own count of its peak allocation, in a fresh
    interpreter, against the compressed size of the 8 row groups' mesh columns (what pre-buffering holds)."""
    import pyarrow.parquet as pq

    from aumesh.core.schema import mesh_columns_axis_major
    from aumesh.pipeline.compute.memory import ARROW_POOL_ENV

    write_tables(tmp_path / "raw", SynthSpec(n_frames=8000, n_videos=40, seed=3, frames_per_file=8000))
    (tmp_path / "data").mkdir()
    (raw,) = sorted((tmp_path / "raw").glob("*.parquet"))
    pq.write_table(pq.read_table(raw), tmp_path / "data" / raw.name, row_group_size=1000)
    md = pq.read_metadata(tmp_path / "data" / raw.name)
    names = md.schema.names
    mesh = [names.index(name) for name in mesh_columns_axis_major()]
    assert md.num_row_groups == 8 and len(mesh) == 3 * N_VERTICES
    compressed = sum(md.row_group(g).column(i).total_compressed_size for g in range(8) for i in mesh)
    code = (
        "import sys, pyarrow as pa\nfrom aumesh.data import tables\n"
        f"(t,) = tables.discover({str(tmp_path / 'data')!r}, '*.parquet', '{{stem}}.npy')\n"
        "n = sum(c.columns.shape[1] for _, c in tables.iter_mesh_chunks(t, 1000, range(8)))\n"
        "print(n, pa.default_memory_pool().max_memory())"
    )
    env = {**os.environ, ARROW_POOL_ENV: "system"}
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    assert int(out[0]) == 8000
    assert int(out[1]) < 0.8 * compressed  # pre-buffered: 1.5x (89 vs 58 MiB); a row group at a time: 0.65x


def test_fortran_ordered_npy_is_rejected_with_the_fix(tmp_path):
    write_tables(tmp_path / "data", SynthSpec(n_frames=100, n_videos=10, seed=2, layout="pyfeat"))
    npy = sorted((tmp_path / "data").glob("*.npy"))[0]
    np.save(npy, np.asfortranarray(np.load(npy)))
    with pytest.raises(tables.TableError, match=r"frames_0000.npy: saved in Fortran order.*np.ascontiguousarray"):
        _discover_and_read(tmp_path / "data")


def test_missing_au_column_names_file_column_and_suggests_rename(small_tables):
    path, df = _frame(small_tables)
    df.rename(columns={"AU12": "au12"}).to_parquet(path)
    with pytest.raises(tables.TableError, match=r"frames_0000.parquet: column 'AU12' is missing \(found 'au12'"):
        _discover_and_read(small_tables)


def test_missing_video_id_and_input_is_an_error(small_tables):
    path, df = _frame(small_tables)
    df.drop(columns=["video_id", "input"]).to_parquet(path)
    with pytest.raises(tables.TableError, match="column 'video_id' is missing"):
        _discover_and_read(small_tables)


def test_468_vertex_mesh_is_a_wrong_vertex_count(small_tables):
    path, df = _frame(small_tables)
    drop = [f"{a}_{i}" for a in "xyz" for i in range(468, N_VERTICES)]
    df.drop(columns=drop).to_parquet(path)
    with pytest.raises(tables.TableError, match=r"wrong vertex count in column x_i: found 468 vertices, need 478"):
        _discover_and_read(small_tables)


def test_npy_with_wrong_vertex_count_is_rejected(tmp_path):
    write_tables(tmp_path / "data", SynthSpec(n_frames=100, n_videos=10, seed=2, layout="pyfeat"))
    npy = sorted((tmp_path / "data").glob("*.npy"))[0]
    np.save(npy, np.load(npy)[:, :468])
    with pytest.raises(tables.TableError, match=r"frames_0000.npy: wrong vertex count.*\(100, 468, 3\)"):
        _discover_and_read(tmp_path / "data")


@pytest.mark.parametrize("column,value", [("AU04", np.nan), ("Yaw", np.inf), ("y_33", np.nan)])
def test_nan_or_inf_names_the_column_and_row(small_tables, column, value):
    path, df = _frame(small_tables)
    df.loc[5, column] = value
    df.to_parquet(path)
    with pytest.raises(tables.TableError, match=rf"{column}.*NaN/inf.*row 5"):
        _discover_and_read(small_tables)


def test_pose_in_degrees_is_detected(small_tables):
    path, df = _frame(small_tables)
    df["Yaw"] = np.rad2deg(df["Yaw"])
    df.to_parquet(path)
    with pytest.raises(tables.TableError, match=r"column 'Yaw'.*looks like degrees.*np.deg2rad"):
        _discover_and_read(small_tables)


def test_duplicate_video_frame_rows_across_files(small_tables, tmp_path):
    path, df = _frame(small_tables)
    df.iloc[:10].to_parquet(small_tables / "copy.parquet")
    cfg = default_config(**{"paths.data_dir": str(small_tables)})
    with pytest.raises(tables.TableError, match=r"rows share a \(video_id, frame\) pair"):
        prepare.run(tables.discover(small_tables, PATTERN, NPY), cfg, tmp_path / "prepared")


@pytest.mark.slow
def test_video_with_no_frames_left_after_filtering(small_tables, tmp_path):
    path, df = _frame(small_tables)
    df.loc[df["video_id"] == "vid000001", "Yaw"] = np.deg2rad(60.0)
    df.to_parquet(path)
    found = tables.discover(small_tables, PATTERN, NPY)
    strict = default_config(**{"preprocess.empty_video": "error"})
    with pytest.raises(
        tables.TableError, match=r"video 'vid000001' \(column 'video_id'\) has no frames left.*empty_video=drop"
    ) as err:
        prepare.run(found, strict, tmp_path / "strict")
    assert str(err.value).startswith(f"{path}: ")  # the table that holds the video
    summary = prepare.run(found, default_config(), tmp_path / "lenient")
    assert "vid000001" in summary["dropped_videos"]
    assert summary["counts"]["videos_dropped_no_frames_left"] >= 1


def test_empty_input_folder_and_zero_row_tables(tmp_path):
    (tmp_path / "data").mkdir()
    with pytest.raises(tables.TableError, match=r"no frame tables found \(empty input\).*dvc add"):
        tables.discover(tmp_path / "data", PATTERN, NPY)
    cols = {c: pd.Series([], dtype=float) for c in ["frame", *AU_COLUMNS, *POSE_COLUMNS]}
    cols["video_id"] = pd.Series([], dtype=str)
    cols.update({f"{a}_{i}": pd.Series([], dtype=float) for i in range(N_VERTICES) for a in "xyz"})
    pd.DataFrame(cols).to_parquet(tmp_path / "data" / "empty.parquet")
    with pytest.raises(tables.TableError, match="every table has 0 rows"):
        tables.discover(tmp_path / "data", PATTERN, NPY)


def test_no_frame_passes_pose_filter(small_tables, tmp_path):
    path, df = _frame(small_tables)
    df["Pitch"] = np.deg2rad(45.0)
    df.to_parquet(path)
    with pytest.raises(tables.TableError, match="no frame passes the pose filter"):
        prepare.run(tables.discover(small_tables, PATTERN, NPY), default_config(), tmp_path / "p")


@pytest.mark.slow
def test_a_partition_of_several_tables_is_checked_at_once_and_a_broken_one_named(tmp_path):
    """A partition's pieces (row groups of several tables) are read and checked together: the same rows as each table
    read alone; an AU out of range in the third table is reported with that table and its own row number."""
    write_tables(tmp_path / "data", SynthSpec(n_frames=600, n_videos=30, seed=4, frames_per_file=200))
    found = tables.discover(tmp_path / "data", PATTERN, NPY)
    assert len(found) >= 3
    pieces = [piece for t in found for piece in tables.pieces(t)]
    together = tables.read_pieces_metadata(pieces)
    alone = pd.concat([tables.read_metadata(t) for t in found], ignore_index=True)
    pd.testing.assert_frame_equal(together, alone)

    broken = pd.read_parquet(found[2].path)
    broken.loc[17, "AU12"] = 3.0
    broken.to_parquet(found[2].path)
    found = tables.discover(tmp_path / "data", PATTERN, NPY)
    with pytest.raises(tables.TableError, match=rf"{found[2].path.name}.*'AU12'.*row 17\b"):
        tables.read_pieces_metadata([piece for t in found for piece in tables.pieces(t)])


@pytest.mark.parametrize(
    "path",
    [
        "clips/a/vid1.mp4",
        "vid1.mp4",
        "a/b.tar.gz",
        "a/.hidden",
        "a/b.",
        "a/b/",
        "/x/y/z",
        "..",
        "a/..b",
        "noext",
        "dir.v/file",
        "C:\\clips\\v.mp4",
    ],
)
def test_video_from_input_path_is_pathlibs_stem(path):
    """py-feat's ``input`` column names the video by its path's stem, computed without pathlib (which interns every
    component, for the life of the process), exactly as ``PurePosixPath.stem``."""
    from pathlib import PurePosixPath

    from aumesh.data.pyfeat import video_stem

    assert video_stem(path) == PurePosixPath(path).stem


def test_npy_reads_are_capped_at_npy_read_rows_whatever_the_chunk_rows(tmp_path, monkeypatch):
    """The .npy read buffer is transit only (whole rows, the consumer takes what it needs), so its size is capped
    (``NPY_READ_ROWS``) below any ``chunk_rows``; the rows and their starts are still the stored ones."""
    write_tables(tmp_path / "data", SynthSpec(n_frames=300, n_videos=20, seed=6, layout="pyfeat"))
    (found,) = tables.discover(tmp_path / "data", PATTERN, NPY)
    mesh = np.load(found.mesh_npy)
    monkeypatch.setattr(tables, "NPY_READ_ROWS", 48)
    for chunk_rows in (32, 1000):
        step = min(chunk_rows, 48)
        chunks = list(tables.iter_mesh_chunks(found, chunk_rows, row_groups=None))
        assert [start for start, _ in chunks] == list(range(0, len(mesh), step))
        assert max(len(chunk) for _, chunk in chunks) == step
        anchors = list(tables.iter_vertices(found, chunk_rows, [10, 263]))
        assert [start for start, _ in anchors] == list(range(0, len(mesh), step))
        np.testing.assert_array_equal(np.concatenate([block for _, block in anchors]), mesh[:, [10, 263]])
