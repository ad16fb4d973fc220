"""The ``prepare`` stage's outputs as the evaluate passes read them: :class:`Prepared` and :func:`load_prepared`
(every file verified against prepare's checksums before use), the partitions of the passes (``frames.parquet``'s row
groups), the videos' frame counts, and the readers a pass task uses (a row group's AU and pose columns, a block of
mesh rows grouped by fold, :func:`block_rows`).

The passes themselves are :mod:`aumesh.pipeline.evaluate.statistics_pass` (pass A) and :mod:`aumesh.pipeline.evaluate`
(pass B, the fits and the cross-validation).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property, partial
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from aumesh.core.errors import UserError
from aumesh.core.io import NpyRowFile, NpyRows, absolute, check_npy
from aumesh.core.schema import AU_COLUMNS, POSE_COLUMNS
from aumesh.model.statistics import fold_order
from aumesh.pipeline import compute, integrity
from aumesh.pipeline.prepared_files import (
    FRAMES_FILE,
    MESHES_FILE,
    NEUTRAL_FILES,
    PREPARED_FILES,
    VIDEO_IDS_FILE,
    scratch_path,
)


@dataclass
class Prepared:
    """The ``prepare`` stage's outputs. Nothing per frame or per video is loaded until asked for: the passes
    read their own rows (``frames.parquet`` row group by row group, ``meshes.npy`` with file I/O)."""

    directory: Path
    meshes: np.ndarray  # (n, 1434) float32 memmap, axis-major
    video_ids: np.ndarray
    neutral: Mapping[str, NpyRows]  # method -> (n_videos, 1434) float32 rows, read on demand
    reference: dict[str, np.ndarray]
    summary: dict
    mesh_path: Path | None = None  # meshes.npy: the passes read it with plain file I/O
    # meshes.npy's checksummed blocks that pass A verifies as it reads them (row group -> blocks; None: not recorded)
    mesh_check: integrity.StreamedCheck | None = None

    @cached_property
    def frames(self) -> pd.DataFrame:
        """Every prepared frame's metadata (whole: for tests and small data; the passes read row groups)."""
        return pd.read_parquet(self.directory / FRAMES_FILE)

    @cached_property
    def videos(self) -> VideoFrames:
        """Per-video frame counts and row groups (one pass over two columns of ``frames.parquet``)."""
        return video_frames(self.directory, self.row_groups(), len(self.video_ids))

    @property
    def n_frames(self) -> int:
        groups = self.row_groups()
        return groups[-1][2] if groups else 0

    def row_groups(self) -> list[tuple[int, int, int]]:
        """``(row_group, first_row, stop_row)`` of ``frames.parquet``: the partitions of the evaluate passes."""
        return row_groups(self.directory)

    @cached_property
    def au(self) -> np.ndarray:
        """(n, 20) AU intensities, float64 (whole)."""
        return self.frames[list(AU_COLUMNS)].to_numpy(np.float64)

    @cached_property
    def pose(self) -> np.ndarray:
        """(n, 3) Pitch, Yaw, Roll in radians, float64 (whole)."""
        return self.frames[list(POSE_COLUMNS)].to_numpy(np.float64)


def row_groups(directory: Path) -> list[tuple[int, int, int]]:
    """``(row_group, first_row, stop_row)`` of ``frames.parquet`` in ``directory``: the partitions of the passes."""
    md = pq.ParquetFile(directory / FRAMES_FILE).metadata
    bounds = np.r_[0, np.cumsum([md.row_group(g).num_rows for g in range(md.num_row_groups)])]
    return [(g, int(bounds[g]), int(bounds[g + 1])) for g in range(md.num_row_groups) if bounds[g + 1] > bounds[g]]


def workers_check(prepared: Prepared) -> dict[str, Path]:
    """What a cluster's workers must reach (:func:`aumesh.pipeline.compute.engine`): read the prepared frames, write
    the scratch folders beside the prepared data (:func:`scratch_path`)."""
    return {"read": prepared.directory / FRAMES_FILE, "write": scratch_path(prepared.directory).parent}


def read_group(directory: Path, group: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """AU (m, 20), pose (m, 3), video index (m,) and low-AU flag (m,) of one row group of ``frames.parquet``.

    A column at a time, straight into the stacked arrays: the row group's decoded columns and their compressed pages,
    read at once and then copied twice, were the largest step of a task that grew with the partition (the error pass's
    task at 3.1M frames: 35 -> 21 MiB above the trimmed heap with this and its reused block buffers)."""
    with pq.ParquetFile(directory / FRAMES_FILE) as parquet:

        def column(name: str) -> np.ndarray:
            # one thread: the partitions already run on every core (as aumesh.data.tables reads the tables)
            return (
                parquet.read_row_group(group, columns=[name], use_threads=False)
                .column(0)
                .to_numpy(zero_copy_only=False)
            )

        n_rows = parquet.metadata.row_group(group).num_rows
        au, pose = np.empty((n_rows, len(AU_COLUMNS))), np.empty((n_rows, len(POSE_COLUMNS)))
        for k, name in enumerate(AU_COLUMNS):
            au[:, k] = column(name)
        for k, name in enumerate(POSE_COLUMNS):
            pose[:, k] = column(name)
        return au, pose, column("video_index"), column("low_au")


def read_columns(directory: Path, group: int, names: Sequence[str]) -> np.ndarray:
    """(m, len(names)) float64: columns ``names`` of one row group of ``frames.parquet`` (the instrument AUs of
    ``model/eiv=instruments``, :func:`aumesh.core.schema.instrument_columns`), a column at a time as
    :func:`read_group`."""
    with pq.ParquetFile(directory / FRAMES_FILE) as parquet:
        out = np.empty((parquet.metadata.row_group(group).num_rows, len(names)))
        for k, name in enumerate(names):
            out[:, k] = parquet.read_row_group(group, columns=[name], use_threads=False).column(0).to_numpy()
        return out


@dataclass(frozen=True)
class VideoFrames:
    """Where each video's frames are in ``frames.parquet``: per-video arrays (n_videos,), nothing per frame."""

    count: np.ndarray  # frames of each video
    low_count: np.ndarray  # low-AU frames of each video
    first_group: np.ndarray  # first row group holding the video (the number of row groups: none)
    last_group: np.ndarray  # last row group holding the video (-1: none)

    @property
    def split(self) -> np.ndarray:
        """(n_videos,) bool: the video's frames are not all in one row group (or it has none)."""
        return self.first_group != self.last_group


def _video_frames_partition(
    group: tuple[int, int, int], directory: Path
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """``(row group, videos, frames, low-AU frames)`` of one row group of ``frames.parquet``."""
    g = group[0]
    t = pq.ParquetFile(directory / FRAMES_FILE).read_row_group(g, columns=["video_index", "low_au"], use_threads=False)
    video = t.column("video_index").to_numpy()
    low = t.column("low_au").to_numpy(zero_copy_only=False)
    videos, local, count = np.unique(video, return_inverse=True, return_counts=True)
    return g, videos, count, np.bincount(local[low], minlength=len(videos))


def video_frames(directory: Path, groups: list[tuple[int, int, int]], n_videos: int) -> VideoFrames:
    """Per-video frame and low-AU frame counts and first/last row group, from one pass over the ``video_index``
    and ``low_au`` columns of ``frames.parquet`` (row group by row group, on the current Dask scheduler)."""
    count, low_count = np.zeros(n_videos, dtype=np.int64), np.zeros(n_videos, dtype=np.int64)
    first, last = np.full(n_videos, len(groups), dtype=np.int64), np.full(n_videos, -1, dtype=np.int64)
    for g, videos, c, low in compute.map_gather(partial(_video_frames_partition, directory=directory), groups):
        count[videos] += c
        low_count[videos] += low
        first[videos] = np.minimum(first[videos], g)
        last[videos] = np.maximum(last[videos], g)
    return VideoFrames(count=count, low_count=low_count, first_group=first, last_group=last)


class _LazyArrays(Mapping):
    """Read-only mapping onto per-video ``.npy`` arrays, rows read on demand (:class:`aumesh.core.io.NpyRows`)."""

    def __init__(self, paths: dict[str, Path]):
        self._paths = paths

    def __getitem__(self, key: str) -> NpyRows:
        return NpyRows(self._paths[key])

    def __iter__(self):
        return iter(self._paths)

    def __len__(self) -> int:
        return len(self._paths)


def load_prepared(prepared_dir: str | Path) -> Prepared:
    """The prepared data in ``prepared_dir``, verified: every file present and as prepare wrote it (its checksums
    in ``summary.json``); ``meshes.npy`` memory-mapped, its blocks verified as pass A reads them (``mesh_check``).

    Raises
    ------
    UserError
        A file is missing (run the prepare stage first), truncated, damaged or edited.
    """
    d = Path(prepared_dir)
    missing = [n for n in PREPARED_FILES if not (d / n).exists()]
    if missing:
        raise UserError(f"{d}: missing {', '.join(missing)}. Fix: run the prepare stage first (`dvc repro prepare`).")
    summary = integrity.load_summary(d)
    # before any file is used, truncated, damaged or edited files are refused: the small ones here, whole (their
    # readers pick rows anywhere); meshes.npy here but for the blocks pass A reads whole, one row group each, which
    # are hashed as it reads them (reading the ~2 GB once more here cost the stage 14 % at 344k frames)
    integrity.verify_prepared(d, summary, [n for n in PREPARED_FILES if n != MESHES_FILE])
    offset, _, shape = check_npy(d / MESHES_FILE, integrity.prepared_fix(d / MESHES_FILE) + ".")
    row_bytes = int(np.prod(shape[1:], dtype=np.int64)) * np.dtype(np.float32).itemsize
    partitions = {g: (offset + start * row_bytes, offset + stop * row_bytes) for g, start, stop in row_groups(d)}
    streamed = integrity.verify_prepared(d, summary, [MESHES_FILE], streamed={MESHES_FILE: partitions})
    d = absolute(d)  # what the partition tasks read, and the scratch folders' place: a cluster's workers run elsewhere
    return Prepared(
        directory=d,
        meshes=np.load(d / MESHES_FILE, mmap_mode="r"),
        mesh_path=d / MESHES_FILE,
        video_ids=np.load(d / VIDEO_IDS_FILE, mmap_mode="r"),  # the stage needs their number; 4 MiB at 88k videos
        neutral=_LazyArrays({method: d / name for method, name in NEUTRAL_FILES.items()}),
        reference=integrity.load_reference(d),
        summary=summary,
        mesh_check=streamed.get(MESHES_FILE),
    )


#: Most rows a pass multiplies at a time: a (512, 1434) float64 block and its products stay in the CPU's cache
#: (measured on a 4,096-row chunk of pass A: 511 -> 340 ms single-threaded), and 1 or 2 workers, or the
#: synchronous scheduler, then cut the rows the same way (the same float64 sums).
BLOCK_ROWS = 512


def block_rows(chunk_rows: int) -> int:
    """Rows a task of the evaluate passes reads and multiplies at a time (``data.chunk_rows`` bounds it too)."""
    return min(BLOCK_ROWS, compute.task_rows(chunk_rows))


def fold_grouped_block(
    meshes: NpyRowFile, raw: np.ndarray, lo: int, hi: int, start: int, fold: np.ndarray, n_splits: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mesh rows ``lo:hi`` grouped by fold (a stable order: rows of a fold, and of a video, keep their order), read
    run by run in that order so the block is never copied to reorder it.

    Returns
    -------
    rows : ndarray of int, shape (m,)
        The partition's rows (``lo - start`` ... ) in the grouped order.
    bounds : ndarray, shape (n_splits + 1,)
        Fold ``f``'s rows are ``[bounds[f], bounds[f + 1])`` of the block.
    Y : ndarray of float32, shape (m, 1434)
        The rows as stored (the first rows of ``raw``): the passes widen them to float64 in their first arithmetic step
        instead of in a copy of their own.
    """
    order, bounds = fold_order(fold[lo - start : hi - start], n_splits)
    if order is None:
        return np.arange(lo - start, hi - start), bounds, meshes.read(lo, hi, raw)
    return order + (lo - start), bounds, meshes.take(order + lo, raw)
