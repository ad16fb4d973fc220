"""Stage ``prepare``: frame tables -> pose-filtered, Procrustes-aligned meshes on disk.

Card, "Training data": pose filter |yaw| <= 40 deg, |pitch| <= 30 deg; per-frame Umeyama
similarity Procrustes onto a reference built on the 12 anchors; top 1 % of frames by max
anchor residual dropped.

Passes over the tables, each a pure function mapped over partitions (whole parquet row groups,
``aumesh.data.tables.partitions``) on the Dask scheduler of the ``compute`` group
(``aumesh.pipeline.compute``). Per-frame results stay in the partitions' scratch files; the stage
process holds per-partition and per-video summaries only (memory flat in frames):

1. ``scan``: metadata + the 12 anchors (36 of the 1434 mesh columns): validation, pose filter and
   the GPA candidates: the ``gpa_max_frames`` pose-passing frames of smallest seeded hash of
   ``(video_id, frame)``, merged in a tree and averaged in the tables' order (so the subsample,
   and the reference, do not depend on the partitioning). The validated metadata and anchors are
   staged per partition in a scratch folder, so the tables are parsed once;
2. ``residuals``: each pose-passing frame's max anchor residual to the reference and its AU sum,
   staged per partition with |pose| (:func:`residual_partition`). The outlier threshold, the
   population low-AU threshold and the pose-units check's medians (when the counts above its limit
   leave them in doubt) are exact quantiles of these files
   (:func:`aumesh.pipeline.quantiles.exact_quantiles`: ``np.quantile`` of the whole vector,
   bit for bit, without gathering it);
   ``keep``: each partition's kept count (the output offsets) and kept videos; the kept AU sums of
   videos split across partitions are gathered for their per-video low-AU thresholds (a video held
   whole by a partition gets its threshold there, in pass 3). Tables grouped by video split one or
   two videos per partition boundary; tables whose videos are scattered over many partitions
   gather those videos' AU sums (and their ``(video, frame)`` keys for the duplicate check);
3. ``write``: full meshes, chunk by chunk: each partition derives its kept rows, video index and
   low-AU flags from its scratch files and the thresholds, aligns the kept frames and writes them
   (float32, axis-major) into its rows of ``meshes.npy`` (``pwrite``: partitions write disjoint
   rows), its kept metadata, and the neutral meshes of the videos it holds whole; sums of the
   population means and of videos split across partitions are reduced in a tree;
4. ``ranges``: each input's range over the kept frames (the ones the model is fitted on), from the partitions' kept
   metadata of pass 3 (:func:`input_ranges`: exact quantiles of the 23 columns in shared passes, ~0.9 s at 344k
   frames), for the release's record of what its data supports (:mod:`aumesh.model.support`).

Outputs (in ``paths.prepared_dir``, swapped in atomically as a whole folder):
``meshes.npy`` (n_kept, 1434) float32; ``frames.parquet`` (video_id, frame, AUs, pose,
video_index, low_au per kept frame, same order; a row group per partition); ``video_ids.npy``
(n_videos,) and ``neutral_mean.npy`` / ``neutral_low_au.npy`` (n_videos, 1434) float32 (per-video
neutral meshes); ``reference.npz`` (reference anchors, mean meshes); ``summary.json`` (counts, ``input_ranges``,
the tables' ``detector``).
The tasks get absolute paths (the tables, the output's temporary folder, its scratch folder: per run, unique names),
so workers that run elsewhere, for several workspaces, read and write this run's files; on a cluster the tables and the
output folder must be on a filesystem every worker sees at the same path (a probe checks it when the stage connects).
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.feather as feather
import pyarrow.parquet as pq

from aumesh.config import Config, PreprocessConfig
from aumesh.core.io import (
    NpyRowFile,
    absolute,
    atomic_directory,
    atomic_write_json,
    create_npy,
    load_npz,
    read_row_set,
    recorded,
    write_rows,
)
from aumesh.core.schema import (
    AU_COLUMNS,
    FRAME_COLUMN,
    INPUT_COLUMNS,
    N_TARGETS,
    N_VERTICES,
    POSE_COLUMNS,
    VIDEO_COLUMN,
)
from aumesh.data import contract
from aumesh.data.tables import (
    FrameTable,
    MeshChunk,
    Piece,
    TableError,
    check_unique_frames,
    iter_pieces_mesh_chunks,
    iter_vertices,
    partitions,
    read_pieces_metadata,
)
from aumesh.geometry.align import (
    align_to_reference,
    apply_similarity_columns,
    apply_similarity_vertices,
    beyond_radius,
    generalized_procrustes,
    not_a_face,
    reference_scale,
)
from aumesh.geometry.frame import HANDEDNESS_LANDMARKS, canonical_frame, mirrored
from aumesh.model import support
from aumesh.model.statistics import VideoSumStream
from aumesh.pipeline import compute, integrity
from aumesh.pipeline.prepared_files import (
    FRAMES_FILE,
    MESHES_FILE,
    NEUTRAL_FILES,
    REFERENCE_FILE,
    SUMMARY_FILE,
    VIDEO_IDS_FILE,
)
from aumesh.pipeline.quantiles import exact_column_quantiles, exact_quantiles

log = logging.getLogger(__name__)

Partition = tuple[Piece, ...]
#: Frames whose anchors pass 2 aligns at a time: the alignment's float64 temporaries (~7 arrays of 288 bytes a frame)
#: are ~4 MiB at 2,048 frames, the same for any partition size (~15 MiB at 8,192; a whole 65,536-row partition at once:
#: ~120 MiB a task). Each frame is solved on its own, so the block size does not change a bit of the results (the
#: prepared data at 100k frames: identical at 8,192 and 2,048).
RESIDUAL_BLOCK = 2048
#: Rows aligned, summed and written at a time in pass 3 (a (256, 1434) float64 block is 2.9 MB: in cache).
ALIGN_BLOCK = 256


def pose_mask(pitch: np.ndarray, yaw: np.ndarray, cfg: PreprocessConfig) -> np.ndarray:
    """Card: |yaw| <= 40 deg and |pitch| <= 30 deg (inputs in radians)."""
    f = cfg.pose_filter
    return (np.abs(yaw) <= np.deg2rad(f.max_abs_yaw_deg)) & (np.abs(pitch) <= np.deg2rad(f.max_abs_pitch_deg))


def low_au_thresholds(au_sum: np.ndarray, video: np.ndarray, quantile: float) -> tuple[np.ndarray, np.ndarray]:
    """Per-video low-AU thresholds: the AU sum at rank ``floor(quantile (size - 1))`` of the video's sorted AU sums
    (at least the video's lowest frame). A frame is low-AU within its video when its AU sum is at or below it.

    Parameters
    ----------
    au_sum : ndarray, shape (n_frames,)
    video : ndarray, shape (n_frames,)
        The video of each frame (any sortable labels).

    Returns
    -------
    videos : ndarray, shape (n_videos,)
        The distinct videos, sorted.
    thresholds : ndarray, shape (n_videos,)
    """
    if len(au_sum) == 0:
        return video[:0], au_sum[:0]
    order = np.lexsort((au_sum, video))
    sorted_video = video[order]
    starts = np.flatnonzero(np.r_[True, sorted_video[1:] != sorted_video[:-1]])
    sizes = np.diff(np.r_[starts, len(order)])
    cut_rank = np.floor(quantile * (sizes - 1)).astype(int)
    return sorted_video[starts], au_sum[order][starts + cut_rank]


def gpa_hash(video: np.ndarray, frame: np.ndarray, seed: int) -> np.ndarray:
    """Seeded 64-bit hash of each ``(video_id, frame)`` (pandas' SipHash: the same on every machine and run).

    The GPA subsample is the frames of smallest hash, so it depends on the data and the seed only.
    """
    key = hashlib.sha256(f"aumesh-gpa-{seed}".encode()).hexdigest()[:16]
    keys = pd.DataFrame(
        {VIDEO_COLUMN: np.asarray(video, dtype=object), FRAME_COLUMN: np.asarray(frame, dtype=np.int64)}
    )
    return pd.util.hash_pandas_object(keys, index=False, hash_key=key).to_numpy(np.uint64)


@dataclass
class Candidates:
    """GPA candidates: the frames of smallest ``(hash, video, frame)`` seen so far, at most ``k``.

    A frame is named by its partition and row there, not carried with its anchors: pass 1 stages every partition's
    anchors (:func:`anchors_in_table_order` reads the chosen ones back), so the results a reduction holds at a time
    cost ~80 bytes a candidate, not ~450 (anchors and table paths: +100 MiB at the peak of pass 1 over
    48 partitions, 3.1M frames).
    """

    hash: np.ndarray  # (m,) uint64
    video: np.ndarray  # (m,) str (fixed width)
    frame: np.ndarray  # (m,) int64
    part: np.ndarray  # (m,) int32: the partition
    row: np.ndarray  # (m,) int64: the row within its partition

    def take(self, order: np.ndarray) -> Candidates:
        return Candidates(*(getattr(self, f)[order] for f in self.__dataclass_fields__))

    def smallest(self, k: int) -> Candidates:
        return self.take(np.lexsort((self.frame, self.video.astype(str), self.hash))[:k])

    def merge(self, other: Candidates, k: int) -> Candidates:
        return Candidates(
            *(np.concatenate([getattr(self, f), getattr(other, f)]) for f in self.__dataclass_fields__)
        ).smallest(k)

    def in_table_order(self) -> Candidates:
        """The same frames in the tables' order (what the GPA mean sums in: the order of the input). Partitions are
        consecutive row groups of the tables in order, so (partition, row) is that order on any partitioning."""
        return self.take(np.lexsort((self.row, self.part)))


def anchors_in_table_order(scratch: Path, candidates: Candidates) -> np.ndarray:
    """(m, n_anchors, 3) float32 anchors of ``candidates`` in the tables' order (:meth:`Candidates.in_table_order`:
    partition by partition), read from the partitions' staged anchors."""
    ordered = candidates.in_table_order()
    return np.concatenate(
        [
            read_row_set(_staged_anchors_file(scratch, i), ordered.row[ordered.part == i])
            for i in np.unique(ordered.part)
        ]
    )


@dataclass
class Scan:
    """Pass 1 of consecutive partitions: rows and distinct videos of each, merged GPA candidates."""

    n_rows: list[int]
    videos: list[np.ndarray]  # per partition: sorted distinct video ids
    n_pose: int  # frames that pass the pose filter
    n_wild: int  # of those, frames with wild values (anchors that are no face, or frames ``exclude`` names)
    candidates: Candidates
    k: int
    n_mirrored: int = 0  # frames (not wild) whose mesh is mirrored (aumesh.geometry.frame.mirrored)
    n_checked: int = 0  # frames (not wild) checked for it
    mirrored_table: str | None = None  # the first table (in order) with a mirrored frame

    def __add__(self, other: Scan) -> Scan:
        return Scan(
            self.n_rows + other.n_rows,
            self.videos + other.videos,
            self.n_pose + other.n_pose,
            self.n_wild + other.n_wild,
            self.candidates.merge(other.candidates, self.k),
            self.k,
            self.n_mirrored + other.n_mirrored,
            self.n_checked + other.n_checked,
            self.mirrored_table or other.mirrored_table,
        )


def _read_meta(part: Partition, cfg: Config) -> tuple[pd.DataFrame, np.ndarray]:
    """The partition's validated metadata (every row, table order) and the table index of each row."""
    meta = read_pieces_metadata(part, cfg.data.coerce_numeric)
    return meta, np.repeat(np.arange(len(part)), [p.n_rows for p in part])


def _read_anchors(part: Partition, cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """(n_rows, n_anchors, 3) anchors of every row, float32 (the precision the alignment is defined at), and (n_rows,)
    bool: the rows whose mesh is mirrored (:func:`aumesh.geometry.frame.mirrored`; its landmarks are read with the
    anchors, most of them are anchors)."""
    anchors = list(cfg.preprocess.alignment.anchor_indices)
    idx = list(dict.fromkeys(anchors + list(HANDEDNESS_LANDMARKS)))
    out = np.empty((sum(p.n_rows for p in part), len(anchors), 3), np.float32)
    flipped = np.zeros(len(out), bool)
    offset = 0
    for p in part:
        for start, block in iter_vertices(p.table, compute.task_rows(cfg.data.chunk_rows), idx, p.row_groups):
            rows = slice(offset + start - p.start, offset + start - p.start + len(block))
            out[rows] = block[:, : len(anchors)]
            flipped[rows] = mirrored(block[:, [idx.index(v) for v in HANDEDNESS_LANDMARKS]])
        offset += p.n_rows
    return out, flipped


def _write_staged(table: pa.Table, path: Path) -> None:
    """A table the stage reads back itself (scratch, the partitions' kept metadata): Arrow IPC, uncompressed
    (written and read at memory speed; parquet's encoding and compression cost seconds a pass at 344k frames)."""
    feather.write_feather(table, path, compression="uncompressed")


def _read_staged(path: Path, columns: list[str] | None = None) -> pa.Table:
    """A table :func:`_write_staged` wrote (``columns``: only those). Memory-mapped: the uncompressed columns are read
    in place, not copied onto the task's heap. On the calling thread only, as every read of the passes (the partitions
    already run on every core; Arrow's own thread pool would only oversubscribe them, and a process interrupted while
    it works can hang in the pool's teardown at exit, as in apache/arrow#50482)."""
    return feather.read_table(path, columns=columns, memory_map=True, use_threads=False)


def _staged_metadata_file(scratch: Path, i: int) -> Path:
    """Partition ``i``'s validated metadata (with the ``piece`` of each row), as pass 1 stages it."""
    return scratch / f"{i:06d}.arrow"


def _staged_anchors_file(scratch: Path, i: int) -> Path:
    """Partition ``i``'s float32 anchors of every row, (n_rows, n_anchors, 3), as pass 1 stages them."""
    return scratch / f"{i:06d}.npy"


def _staged_table(scratch: Path, i: int, columns: list[str] | None = None) -> pa.Table:
    """Partition ``i``'s validated metadata (with the ``piece`` of each row), as pass 1 staged it (``columns``: only
    those)."""
    return _read_staged(_staged_metadata_file(scratch, i), columns)


def _video_codes(video: pa.ChunkedArray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(video, return_inverse=True)`` of a string column, from its Arrow dictionary encoding: the distinct
    videos, sorted (fixed-width ``str``), and each row's index into them, without a Python string per row."""
    encoded = video.combine_chunks().dictionary_encode()
    names = encoded.dictionary.to_numpy(zero_copy_only=False).astype(str)
    order = np.argsort(names)
    rank = np.empty(len(order), np.intp)
    rank[order] = np.arange(len(order))
    return names[order], rank[encoded.indices.to_numpy()]


def scan_partition(
    item: tuple[int, Partition], cfg: Config, scratch: Path, exclude: dict[int, np.ndarray] | None = None
) -> Scan:
    """Pass 1 on one partition: validation, the pose filter, the wild-value screen of the anchors and the partition's
    GPA candidates.

    The validated metadata (with each row's ``wild`` flag: anchors that are no face, or a row of partition ``i`` that
    ``exclude[i]`` names, found by pass 3 of an earlier round) and the anchors (the only columns passes 2 and 3 need
    besides the meshes) are staged in ``scratch`` (~350 bytes a frame), so the tables are parsed and validated once.
    """
    i, part = item
    meta, file_index = _read_meta(part, cfg)
    check_unique_frames(meta, [p.table.path for p in part], file_index)
    anchors_all, flipped = _read_anchors(part, cfg)
    wild = not_a_face(anchors_all)
    if exclude and i in exclude:
        wild[exclude[i]] = True
    staged = pa.Table.from_pandas(meta, preserve_index=False)  # the piece appended in Arrow (``assign`` copied meta)
    staged = staged.append_column("piece", pa.array(file_index.astype(np.int32))).append_column("wild", pa.array(wild))
    _write_staged(staged, _staged_metadata_file(scratch, i))
    np.save(_staged_anchors_file(scratch, i), anchors_all)
    passing = pose_mask(meta["Pitch"].to_numpy(), meta["Yaw"].to_numpy(), cfg.preprocess)
    pose = np.flatnonzero(passing & ~wild)
    k = cfg.preprocess.alignment.gpa_max_frames
    video = meta[VIDEO_COLUMN].to_numpy(dtype=object)[pose]
    frame = meta[FRAME_COLUMN].to_numpy(dtype=np.int64)[pose]
    h = gpa_hash(video, frame, cfg.seed)
    order = np.lexsort((frame, video.astype(str), h))[:k]  # the k smallest hashes (as Candidates.smallest)
    # fixed-width strings, not the rows' str objects: candidates outlive their partition, and a few surviving
    # objects from each partition's millions kept Python's small-object arenas, and the stage's memory, growing
    # with the partitions (+90 MiB retained after this pass at 1M frames)
    candidates = Candidates(
        h[order], video[order].astype(str), frame[order], np.full(len(order), i, np.int32), pose[order].astype(np.int64)
    )
    flipped &= ~wild
    first_flipped = part[int(file_index[np.argmax(flipped)])].table.path if flipped.any() else None
    return Scan(
        [len(meta)],
        [np.unique(meta[VIDEO_COLUMN].to_numpy(dtype=str))],
        int(passing.sum()),
        int((passing & wild).sum()),
        candidates,
        k,
        int(flipped.sum()),
        int((~wild).sum()),
        None if first_flipped is None else str(first_flipped),
    )


@dataclass
class Residuals:
    """Pass 2 of one partition, as the stage process sees it (the per-frame results are in the scratch folder)."""

    residual_max: float  # largest residual of the partition's pose-passing frames (-inf if none)
    split_rows: pd.DataFrame  # (video_id, frame, file) of rows of videos also in other partitions
    pose_above: np.ndarray  # (3,) rows whose |Pitch|, |Yaw|, |Roll| exceed the pose-units limit (all rows)


def _pass2_file(scratch: Path, i: int) -> Path:
    return scratch / f"{i:06d}.pass2.npz"


def _pass2(item: tuple[Path, int], *keys: str) -> list[np.ndarray]:
    """Arrays ``keys`` of partition ``item = (scratch, i)`` as pass 2 staged them (:func:`residual_partition`)."""
    return load_npz(_pass2_file(*item), keys)


def au_sums(meta: pa.Table, rows: np.ndarray) -> np.ndarray:
    """(len(rows),) float64: the AU sum of rows ``rows`` of ``meta``, added AU by AU, left to right: the additions
    (and bits) of pandas' row sums of the AU columns (``frame[AU_COLUMNS].to_numpy().sum(axis=1)`` on its column-major
    block), which the stage computed before, so the low-AU flags do not change."""
    total = np.zeros(len(rows))
    for name in AU_COLUMNS:
        total += meta.column(name).to_numpy()[rows]
    return total


def residual_partition(
    item: tuple[int, Partition], cfg: Config, reference: np.ndarray, split_videos: np.ndarray, scratch: Path
) -> Residuals:
    """Pass 2 on one partition: residuals of the pose-passing frames to the reference, and their AU sums.

    Staged in ``scratch`` (``<i>.pass2.npz``): ``rows`` (n_pose,) the pose-passing rows, ``residual`` and
    ``au_sum`` (n_pose,) float64, ``videos`` the partition's sorted distinct videos and ``code`` (n_pose,) int32
    each frame's index into them, ``abs_pose`` (n_rows, 3) float32 |Pitch|, |Yaw|, |Roll| of every row
    (the pose-units check), and each pose-passing frame's similarity transform onto the reference
    (``rotation`` (n_pose, 3, 3), ``scale``, ``translation`` (n_pose, 3): pass 3 applies them instead of
    solving the Procrustes problem again): ~150 bytes a frame.

    The staged columns are read as Arrow arrays and the anchors a block at a time: pandas' frame of the metadata (a
    Python string per row), the whole partition's anchors twice (all rows, then the pose-passing ones) and alignment
    blocks of 8,192 frames took 32 MiB a task at 33.6k rows (synchronous, above the trimmed heap), the peak pass of
    the stage at 3.1M frames; now 17-21 MiB.
    """
    i, part = item
    meta = _staged_table(scratch, i, [VIDEO_COLUMN, FRAME_COLUMN, "piece", "wild", *POSE_COLUMNS, *AU_COLUMNS])
    pitch, yaw, roll = (meta.column(c).to_numpy() for c in POSE_COLUMNS)
    rows = np.flatnonzero(pose_mask(pitch, yaw, cfg.preprocess) & ~meta.column("wild").to_numpy(zero_copy_only=False))
    au_sum = au_sums(meta, rows)
    residual, rotation, scale, translation = (np.empty((len(rows), *shape)) for shape in ((), (3, 3), (), (3,)))
    with NpyRowFile(_staged_anchors_file(scratch, i)) as anchors:
        block_anchors = np.empty((min(RESIDUAL_BLOCK, len(rows)), *anchors.shape[1:]), anchors.dtype)
        for lo in range(0, len(rows), RESIDUAL_BLOCK):
            block = slice(lo, lo + RESIDUAL_BLOCK)
            residual[block], (rotation[block], scale[block], translation[block]) = align_to_reference(
                anchors.take(rows[block], block_anchors), reference
            )
    videos, code = _video_codes(meta.column(VIDEO_COLUMN))
    split = np.isin(videos, split_videos)[code]
    file_index = meta.column("piece").to_numpy()[split]
    split_rows = pd.DataFrame(
        {
            VIDEO_COLUMN: meta.column(VIDEO_COLUMN).filter(split).to_numpy(zero_copy_only=False),
            FRAME_COLUMN: meta.column(FRAME_COLUMN).to_numpy()[split],
            "file": [str(part[k].table.path) for k in file_index],
        }
    )
    abs_pose = np.abs(np.column_stack([pitch, yaw, roll])).astype(np.float32)
    np.savez(
        _pass2_file(scratch, i),
        rows=rows.astype(np.int32),
        residual=residual,
        au_sum=au_sum,
        videos=videos,
        code=code[rows].astype(np.int32),
        abs_pose=abs_pose,
        rotation=rotation,
        scale=scale,
        translation=translation,
    )
    return Residuals(
        float(residual.max()) if len(residual) else -np.inf,
        split_rows,
        (abs_pose > contract.MAX_MEDIAN_ABS_POSE_RAD).sum(axis=0),
    )


def _staged_residuals(item: tuple[Path, int]) -> np.ndarray:
    return _pass2(item, "residual")[0]


def _staged_abs_pose(column: int, item: tuple[Path, int]) -> np.ndarray:
    return _pass2(item, "abs_pose")[0][:, column].astype(np.float64)


def _keep(residual: np.ndarray, threshold: float | None) -> np.ndarray:
    """Frames under the outlier threshold (``None``: no outlier cut)."""
    return np.ones(len(residual), bool) if threshold is None else residual <= threshold


def _kept_au_sums(threshold: float | None, item: tuple[Path, int]) -> np.ndarray:
    residual, au_sum = _pass2(item, "residual", "au_sum")
    return au_sum[_keep(residual, threshold)]


@dataclass
class Kept:
    """The outlier cut on one partition: its kept frames' count and videos, and the kept AU sums of split videos."""

    n_kept: int
    videos: np.ndarray  # sorted distinct videos with kept frames
    split_au: dict[str, np.ndarray]  # video -> AU sums of its kept frames here, for videos split across partitions


def keep_partition(item: tuple[Path, int], threshold: float | None, split_videos: np.ndarray) -> Kept:
    """The partition's frames kept by the outlier cut (``threshold``, ``None``: no cut), from pass 2's staged files."""
    residual, au_sum, videos, code = _pass2(item, "residual", "au_sum", "videos", "code")
    keep = _keep(residual, threshold)
    kept_code = code[keep]
    split = np.flatnonzero(np.isin(videos, split_videos))
    return Kept(
        int(keep.sum()),
        videos[np.unique(kept_code)],
        {str(videos[j]): au_sum[keep][kept_code == j] for j in split if (kept_code == j).any()},
    )


@dataclass(frozen=True)
class Cuts:
    """The thresholds every partition applies in pass 3."""

    outlier: float | None  # max anchor residual kept (None: no outlier cut)
    low_au_quantile: float  # per-video low-AU quantile (preprocess.neutral.low_au_quantile)
    low_au_population: float  # AU sum at or below which a frame is low-AU in the population


@dataclass
class Plan:
    """What pass 3 needs of the stage for one partition (per partition and per video, nothing per frame)."""

    part_index: int
    offset: int  # output row of the partition's first kept frame
    video_index: np.ndarray  # (n_local,) int32 output index of each of the partition's kept videos (sorted)
    split: np.ndarray  # (n_local,) bool: the video has rows in other partitions too (split)
    split_threshold: np.ndarray  # (n_local,) its low-AU threshold over all partitions (NaN for videos held whole)


@dataclass
class Written:
    """Pass 3 of consecutive partitions: population sums and the per-video sums of videos split across partitions."""

    sums: np.ndarray  # (2, 1434): all kept frames, population low-AU frames
    n_low_population: int = 0
    split: dict[int, np.ndarray] = field(default_factory=dict)  # video -> (2, 1434) sums (all, low-AU)
    split_counts: dict[int, np.ndarray] = field(default_factory=dict)  # video -> (2,) frames
    wild: dict[int, list[int]] = field(default_factory=dict)  # partition -> its rows with a vertex beyond the radius
    # partition -> (first row, stop row, digest of those rows of meshes.npy as written: aumesh.pipeline.integrity)
    digests: dict[int, tuple[int, int, str]] = field(default_factory=dict)

    def __add__(self, other: Written) -> Written:
        out = Written(
            self.sums + other.sums,
            self.n_low_population + other.n_low_population,
            dict(self.split),
            dict(self.split_counts),
            {**self.wild, **other.wild},
            {**self.digests, **other.digests},
        )
        for v, s in other.split.items():
            if v in out.split:
                out.split[v] = out.split[v] + s
                out.split_counts[v] = out.split_counts[v] + other.split_counts[v]
            else:
                out.split[v], out.split_counts[v] = s, other.split_counts[v]
        return out


def kept_frames(scratch: Path, plan: Plan, cuts: Cuts) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The partition's kept rows (in order), their video index and low-AU flags (within the video, in the
    population), from pass 2's staged files; per-video thresholds of the videos the partition holds whole are
    computed here, those of split videos come with the plan.

    Returns
    -------
    rows : ndarray of int32, shape (n_kept,)
    video_index : ndarray of int32, shape (n_kept,)
    low_video, low_population : ndarray of bool, shape (n_kept,)
    """
    rows, residual, au_sum, code = _pass2((scratch, plan.part_index), "rows", "residual", "au_sum", "code")
    keep = _keep(residual, cuts.outlier)
    au_sum = au_sum[keep]
    _, local = np.unique(code[keep], return_inverse=True)  # index into the partition's kept videos
    _, whole = low_au_thresholds(au_sum, local, cuts.low_au_quantile)
    thresholds = np.where(plan.split, plan.split_threshold, whole)
    return rows[keep], plan.video_index[local], au_sum <= thresholds[local], au_sum <= cuts.low_au_population


def write_partition(
    part: Partition,
    cfg: Config,
    reference: np.ndarray,
    plan: Plan,
    cuts: Cuts,
    out_dir: Path,
    scratch: Path,
    chunk_rows: int,
    wild_radius: tuple[np.ndarray, float],
) -> Written:
    """Pass 3 on one partition: align and write its kept meshes, metadata and whole videos' neutrals.

    Videos with rows in other partitions too (``plan.split``): their sums are returned instead of written. Rows whose
    aligned mesh has a vertex beyond ``wild_radius`` (centre (3,), radius) are returned in ``Written.wild``: the stage
    then runs again without them (their sums are in this round's, which is discarded).
    """
    rows, video_index, low_video, low_population = kept_frames(scratch, plan, cuts)
    pose_rows, rotation, scale, translation = _pass2(
        (scratch, plan.part_index), "rows", "rotation", "scale", "translation"
    )
    transform = np.searchsorted(pose_rows, rows)  # each kept row's transform, as pass 2 solved it (read per block)
    # the kept rows of the staged metadata, in Arrow (pandas' Python strings cost ~300 bytes a row of the task's memory)
    kept = _staged_table(scratch, plan.part_index).drop_columns(["piece", "wild"]).take(rows)
    kept = kept.append_column("video_index", pa.array(video_index)).append_column("low_au", pa.array(low_video))
    _write_staged(kept.replace_schema_metadata(None), out_dir / "parts" / f"{plan.part_index:06d}.arrow")
    del kept
    result = Written(np.zeros((2, N_TARGETS)), int(low_population.sum()))
    split_video = set(plan.video_index[plan.split].tolist())
    neutrals: dict[str, dict[int, np.ndarray]] = {name: {} for name in NEUTRAL_FILES.values()}

    def finished(name: str, slot: int):
        def done(v: int, total: np.ndarray, count: int) -> None:
            if v in split_video:
                result.split.setdefault(v, np.zeros((2, N_TARGETS)))[slot] += total
                result.split_counts.setdefault(v, np.zeros(2, np.int64))[slot] += count
            else:
                neutrals[NEUTRAL_FILES[name]][v] = (total / count).astype(np.float32)

        return done

    def write_neutrals(files: dict[str, NpyRowFile]) -> None:
        """The neutral rows of the videos finished so far (a partition's videos are mostly consecutive)."""
        for name, finished_rows in neutrals.items():
            files[name].write_row_map(finished_rows)
            finished_rows.clear()

    all_frames = VideoSumStream(video_index, finished("mean", 0))
    low_frames = VideoSumStream(video_index[low_video], finished("low_au", 1))
    position = np.full(sum(p.n_rows for p in part), -1, dtype=np.int64)
    position[rows] = np.arange(len(rows))
    aligned = np.empty((ALIGN_BLOCK, N_TARGETS))  # a block's aligned rows, float64, allocated once a task
    # the partition's rows of meshes.npy are one contiguous range, written in order: hashed as they are written
    digest, next_row = integrity.new_hash(), 0
    with ExitStack() as stack:  # the output files opened once for the partition's writes
        files = {
            name: stack.enter_context(NpyRowFile(out_dir / name, writable=True))
            for name in (MESHES_FILE, *NEUTRAL_FILES.values())
        }
        for local, chunk in iter_pieces_mesh_chunks(part, chunk_rows):
            m = len(chunk)
            pos = position[local : local + m]
            sel = pos >= 0
            if not sel.any():
                continue
            pos, columns = pos[sel], np.flatnonzero(sel)
            # a block of rows at a time: the gather, the alignment's temporaries and the sums stay in the CPU's
            # cache instead of streaming a chunk-sized float64 array through memory for every step
            for lo in range(0, len(pos), ALIGN_BLOCK):
                rows_out = pos[lo : lo + ALIGN_BLOCK]
                solved = transform[rows_out]
                flat = _aligned_rows(
                    chunk,
                    columns[lo : lo + ALIGN_BLOCK],
                    rotation[solved],
                    scale[solved],
                    translation[solved],
                    aligned[: len(rows_out)],
                )
                block = flat.astype(np.float32)
                far = beyond_radius(block, *wild_radius)  # on the float32 rows written: half the bytes to reduce
                if far.any():  # preprocess.alignment.max_vertex_iod: the round is rerun without these rows
                    result.wild.setdefault(plan.part_index, []).extend(rows[rows_out[far]].tolist())
                if int(rows_out[0]) != next_row or int(rows_out[-1]) != next_row + len(rows_out) - 1:
                    raise RuntimeError(
                        f"partition {plan.part_index}: rows written out of order, the checksum would not be the file's"
                    )
                files[MESHES_FILE].write(plan.offset + next_row, block)
                digest.update(memoryview(block.data).cast("B"))
                next_row += len(rows_out)
                result.sums[0] += flat.sum(axis=0)
                result.sums[1] += flat[low_population[rows_out]].sum(axis=0)
                all_frames.add(video_index[rows_out], flat)
                low = low_video[rows_out]
                low_frames.add(video_index[rows_out][low], flat[low])
            write_neutrals(files)
    result.digests[plan.part_index] = (plan.offset, plan.offset + next_row, digest.hexdigest())
    return result


def _table_of_video(scratch: Path, parts: list[Partition], video: str) -> Path:
    """The first table with rows of ``video`` (for an error message), from pass 1's staged metadata."""
    for i, part in enumerate(parts):
        meta = _staged_table(scratch, i)
        rows = np.flatnonzero(meta[VIDEO_COLUMN].to_numpy(zero_copy_only=False).astype(str) == video)
        if len(rows):
            return part[int(meta["piece"].to_numpy()[rows[0]])].table.path
    raise KeyError(video)


def _aligned_rows(
    chunk: MeshChunk,
    frames: np.ndarray,
    rotation: np.ndarray,
    scale: np.ndarray,
    translation: np.ndarray,
    out: np.ndarray,
) -> np.ndarray:
    """(k, 1434) float64 aligned meshes of the chunk's rows ``frames`` (k,), from the layout they were read in, into
    ``out``."""
    if chunk.vertices is not None:
        return apply_similarity_vertices(chunk.vertices, rotation, scale, translation, frames, out)
    assert chunk.columns is not None  # a chunk holds its rows in one of the two layouts
    return apply_similarity_columns(chunk.columns, rotation, scale, translation, frames, out)


def _write_item(item: tuple[Partition, Plan], **kwargs) -> Written:
    return write_partition(item[0], plan=item[1], **kwargs)


def _plans(kept: list[Kept], video_ids: np.ndarray, split_names: np.ndarray, quantile: float) -> list[Plan]:
    """Each partition's output offset (cumulative kept counts), its kept videos' output index, and the low-AU
    thresholds of videos split across partitions (exact over their kept frames in every partition)."""
    gathered: dict[str, list[np.ndarray]] = {}
    for k in kept:
        for v, video_au in k.split_au.items():
            gathered.setdefault(v, []).append(video_au)
    names = np.array(sorted(gathered), dtype=str)
    au = [np.concatenate(gathered[v]) for v in names]
    _, split_thresholds = low_au_thresholds(
        np.concatenate(au) if au else np.empty(0), np.repeat(np.arange(len(au)), [len(a) for a in au]), quantile
    )
    offsets = np.r_[0, np.cumsum([k.n_kept for k in kept])]
    plans = []
    for i, k in enumerate(kept):
        split = np.isin(k.videos, split_names)
        threshold = np.full(len(k.videos), np.nan)
        threshold[split] = split_thresholds[np.searchsorted(names, k.videos[split])]
        plans.append(Plan(i, int(offsets[i]), np.searchsorted(video_ids, k.videos).astype(np.int32), split, threshold))
    return plans


class _WildRows(Exception):
    """Pass 3 found aligned meshes beyond the wild-value radius: the passes run again without them."""

    def __init__(self, rows: dict[int, np.ndarray]):
        super().__init__(f"{sum(len(r) for r in rows.values())} frames with wild values")
        self.rows = rows


def run(
    tables: list[FrameTable],
    cfg: Config,
    out_dir: str | Path,
    ingested: dict | None = None,
    detectors: dict[str, int] | None = None,
) -> dict:
    """Prepare the frame tables into ``out_dir`` (replaced atomically). Returns the summary.

    ``ingested``: the ingest stage's counts (rows read, no-face rows and other faces dropped), added to the summary's.
    ``detectors``: ``{detector: n_sources}`` of the ingest manifest (:func:`aumesh.model.support.detector_counts`),
    recorded as the summary's ``detector`` (:func:`aumesh.model.support.detector_summary`; ``unknown`` when None).
    Frames whose aligned mesh has a vertex beyond ``preprocess.alignment.max_vertex_iod`` are found while pass 3 writes
    them; the passes then run once more without them, so the result is what tables without those frames give (the
    GPA subsample, the thresholds and the means included). Clean data never takes the second round.
    """
    given = [t.path for t in tables]  # what the summary records (as the ingest manifest lists them)
    # the tasks get absolute paths: a cluster's workers run in directories of their own (README, "Scale out")
    tables = [
        replace(t, path=absolute(t.path), mesh_npy=None if t.mesh_npy is None else absolute(t.mesh_npy)) for t in tables
    ]
    parts = partitions(tables, cfg.compute.partition_rows)
    exclude: dict[int, np.ndarray] = {}
    with (
        atomic_directory(absolute(out_dir)) as tmp,
        compute.engine(cfg.compute, read=tables[0].path if tables else None, write=tmp),
    ):
        while True:
            try:
                summary = _passes(tables, parts, cfg, tmp, exclude, ingested or {})
                summary["tables"] = [recorded(p) for p in given]
                summary["detector"] = support.detector_summary(detectors or {})
                atomic_write_json(tmp / SUMMARY_FILE, summary)
                return summary
            except _WildRows as found:
                log.warning(
                    "prepare: %d frame(s) have a vertex beyond %g inter-ocular distances after alignment "
                    "(preprocess.alignment.max_vertex_iod): dropped, the passes run again without them",
                    sum(len(r) for r in found.rows.values()),
                    cfg.preprocess.alignment.max_vertex_iod,
                )
                for i, rows in found.rows.items():
                    exclude[i] = np.union1d(exclude.get(i, np.empty(0, np.int64)), rows).astype(np.int64)
                for child in tmp.iterdir():
                    shutil.rmtree(child) if child.is_dir() else child.unlink()


MIRROR_FIX = (
    "Fix: the tables' x, y, z must form a right-handed system (py-feat's and MediaPipe's image pixels: x right, "
    "y down, z into the image): negate one axis (e.g. z) of every mesh, or swap x and y back, and run again."
)


def check_handedness(scan: Scan, cfg: Config) -> None:
    """Refuse mirrored meshes (a left-handed export, x and y swapped) after pass 1, before the alignment and any fit.

    The release's frame is a proper rotation found from the anatomy (:func:`aumesh.geometry.frame.canonical_frame`),
    which has none for a mirrored face: without this check the stage's mean mesh, and the release, failed only after the
    whole cross-validation. Most frames mirrored: the tables' convention is; a few: a detector's odd frames, which the
    alignment's outlier cut drops like any other bad fit (said in the log).
    """
    if scan.n_checked and scan.n_mirrored * 2 > scan.n_checked:
        raise TableError(
            f"{scan.mirrored_table}: the meshes are mirrored ({scan.n_mirrored:,} of {scan.n_checked:,} "
            f"frames in {cfg.paths.data_dir}): with x = 33 -> 263 (subject's left) and y = chin 152 -> "
            f"forehead 10, the nose tip 1 lies behind the eyes in a right-handed frame. {MIRROR_FIX}"
        )
    if scan.n_mirrored:
        log.warning(
            "prepare: %d of %d frames have a mirrored mesh (first in %s): the alignment's outlier cut is "
            "expected to drop them",
            scan.n_mirrored,
            scan.n_checked,
            scan.mirrored_table,
        )


def _passes(
    tables: list[FrameTable],
    parts: list[Partition],
    cfg: Config,
    tmp: Path,
    exclude: dict[int, np.ndarray],
    ingested: dict,
) -> dict:
    """One round of the passes into ``tmp`` (module docstring); :class:`_WildRows` when pass 3 finds wild values."""
    pre = cfg.preprocess
    scratch = tmp / "scratch"  # per-partition validated metadata and anchors (pass 1), residuals (pass 2)
    scratch.mkdir()
    staged = [(scratch, i) for i in range(len(parts))]
    # pass 1: validation, pose filter, wild anchors, GPA candidates
    scan = compute.map_reduce(
        partial(scan_partition, cfg=cfg, scratch=scratch, exclude=exclude),
        Scan.__add__,
        list(enumerate(parts)),
        desc="prepare: read + validate",
    )
    if scan.n_pose - scan.n_wild == 0:
        raise TableError(
            f"{cfg.paths.data_dir}: no frame passes the pose filter (|yaw| <= {pre.pose_filter.max_abs_yaw_deg} deg, "
            f"|pitch| <= {pre.pose_filter.max_abs_pitch_deg} deg) of {sum(scan.n_rows)}. Likely cause: Pitch/Yaw in degrees "
            f"(convert with np.deg2rad), or preprocess.pose_filter narrower than the data."
        )
    check_handedness(scan, cfg)
    partial_counts = {
        **ingested,
        "frames_in": int(sum(scan.n_rows)),
        "dropped_pose": int(sum(scan.n_rows) - scan.n_pose),
        "dropped_wild_values": scan.n_wild,
    }
    contract.check_filter_shares(contract.filter_shares(partial_counts), pre.max_drop_fraction, cfg.paths.data_dir)
    # one array of the videos in the stage, not one per partition besides (memory flat in frames)
    every_video, in_parts = np.unique(np.concatenate(scan.videos), return_counts=True)
    split_names = every_video[in_parts > 1]
    scan = replace(scan, videos=[])
    del in_parts
    sample = anchors_in_table_order(scratch, scan.candidates)
    reference = generalized_procrustes(sample, pre.alignment.gpa_max_iter, pre.alignment.gpa_tol, map=compute.local_map)
    del sample

    # pass 2: residuals and AU sums of the pose-passing frames, staged per partition
    res = compute.map_gather(
        partial(residual_partition, cfg=cfg, reference=reference, split_videos=split_names, scratch=scratch),
        list(enumerate(parts)),
        desc="prepare: residuals",
    )
    # every frame (float32: compared with 1 rad); np.median is np.quantile(.., 0.5) here: the midpoint of two
    # float32 values is exact in float64 either way. The exact medians (nine small passes) only when the counts
    # above the limit leave a median in doubt: pose in radians has almost none there
    if contract.pose_medians_may_exceed(np.sum([r.pose_above for r in res], axis=0), sum(scan.n_rows)):
        contract.check_pose_medians(
            [exact_quantiles(partial(_staged_abs_pose, j), staged, 0.5) for j in range(3)], cfg.paths.data_dir
        )
    split_rows = pd.concat([r.split_rows for r in res], ignore_index=True)
    if len(split_rows):  # (video, frame) pairs across partitions (within one: checked in pass 1)
        files = sorted(set(split_rows["file"]))
        check_unique_frames(split_rows, [Path(f) for f in files], np.searchsorted(files, split_rows["file"]))
    quantile_cut = pre.alignment.outlier_quantile < 1.0
    # exact and independent of the partitioning: the quantile of the whole vector, which is never gathered
    threshold = (
        exact_quantiles(_staged_residuals, staged, pre.alignment.outlier_quantile)
        if quantile_cut
        else max(r.residual_max for r in res)
    )
    outlier = threshold if quantile_cut else None  # what the partitions apply (None: no outlier cut)
    del res, split_rows
    kept = compute.map_gather(
        partial(keep_partition, threshold=outlier, split_videos=split_names), staged, desc="prepare: outlier cut"
    )
    n_kept_pose = sum(k.n_kept for k in kept)
    n_aligned = scan.n_pose - scan.n_wild
    video_ids = np.unique(np.concatenate([k.videos for k in kept]))
    # sorted, as NumPy strings: a Python string per video (and a set of them) left the freed strings' memory
    # scattered over Python's small-object arenas (~6 MiB at 90k videos)
    dropped_videos = np.setdiff1d(every_video, video_ids, assume_unique=True).tolist()
    n_videos_in = len(every_video)
    del every_video
    n_rows = int(sum(scan.n_rows))
    if dropped_videos and pre.empty_video == "error":
        v = dropped_videos[0]
        f = _table_of_video(scratch, parts, v)
        raise TableError(
            f"{f}: video {v!r} (column {VIDEO_COLUMN!r}) has no frames left after the pose filter and the alignment "
            f"outlier cut ({len(dropped_videos)} such videos). Fix: remove it from the tables, widen "
            f"preprocess.pose_filter, or set preprocess.empty_video=drop to skip such videos."
        )
    counts = {
        **ingested,
        "frames_in": n_rows,
        "videos_in": int(n_videos_in),
        "dropped_pose": int(n_rows - scan.n_pose),
        "dropped_wild_values": int(scan.n_wild),
        "dropped_alignment_outliers": int(n_aligned - n_kept_pose),
        "alignment_residual_threshold": threshold,
        "videos_dropped_no_frames_left": int(len(dropped_videos)),
        "frames_kept": n_kept_pose,
        "videos_kept": int(len(video_ids)),
    }
    shares = contract.filter_shares(counts)
    for name, share in shares.items():
        log.info(
            "%s: dropped %d of %d %s (%.1f%%)",
            name,
            share["dropped"],
            share["of"],
            share["unit"],
            100 * share["fraction"],
        )
        counts[f"{contract.FILTER_KEYS[name]}_fraction"] = share["fraction"]
    if dropped_videos:
        log.warning(
            "%d video(s) have no frames left after filtering and are dropped (first: %s)",
            len(dropped_videos),
            ", ".join(dropped_videos[:5]),
        )
    contract.check_filter_shares(shares, pre.max_drop_fraction, cfg.paths.data_dir)
    q = pre.neutral.low_au_quantile
    cuts = Cuts(outlier, q, exact_quantiles(partial(_kept_au_sums, outlier), staged, q))
    plans = _plans(kept, video_ids, split_names, q)
    del kept
    n_kept, n_videos = n_kept_pose, len(video_ids)
    np.save(tmp / VIDEO_IDS_FILE, video_ids.astype(str))
    del video_ids  # ~4 MiB at 88k videos, not needed by pass 3

    (tmp / "parts").mkdir()
    mesh_offset = create_npy(tmp / MESHES_FILE, np.float32, (n_kept, N_TARGETS))
    for name in NEUTRAL_FILES.values():
        create_npy(tmp / name, np.float32, (n_videos, N_TARGETS))
    # pass 3: align and write; population sums and split videos' sums reduced in a tree
    radius = pre.alignment.max_vertex_iod * reference_scale(reference, pre.alignment.anchor_indices)
    written = compute.map_reduce(
        partial(
            _write_item,
            cfg=cfg,
            reference=reference,
            cuts=cuts,
            out_dir=tmp,
            scratch=scratch,
            chunk_rows=compute.task_rows(cfg.data.chunk_rows),
            wild_radius=(reference.mean(axis=0), radius),
        ),
        Written.__add__,
        list(zip(parts, plans, strict=True)),
        desc="prepare: align + write",
    )
    del plans
    if written.wild:
        raise _WildRows({i: np.asarray(rows, np.int64) for i, rows in written.wild.items()})
    # each input's range over exactly the frames written (the ones the model is fitted on), from the partitions' kept
    # metadata before it is concatenated: a few small passes over 23 columns, never the frames gathered
    ranges = input_ranges(sorted((tmp / "parts").glob("*.arrow")))
    for v, total in written.split.items():  # videos with frames in several partitions
        for slot, name in enumerate(("mean", "low_au")):
            write_rows(
                tmp / NEUTRAL_FILES[name], v, (total[slot] / written.split_counts[v][slot]).astype(np.float32)[None]
            )
    _concatenate_parts(tmp / "parts", tmp / FRAMES_FILE)
    shutil.rmtree(scratch)
    n_low_population = written.n_low_population
    mean_aligned = written.sums[0] / n_kept
    mean_low = written.sums[1] / max(n_low_population, 1)
    try:  # what the release's frame is found from (aumesh.model.release.release_arrays): the same check, here
        canonical_frame(mean_aligned.reshape(3, N_VERTICES).T)
    except ValueError as err:
        raise TableError(
            f"{cfg.paths.data_dir}: the mean aligned mesh of the kept frames is mirrored, so no release "
            f"can be built from these tables ({str(err).split('. Fix')[0]}). {MIRROR_FIX}"
        ) from None
    np.savez(
        tmp / REFERENCE_FILE,
        reference_anchors=reference.astype(np.float32),
        anchor_indices=np.asarray(pre.alignment.anchor_indices, dtype=np.int32),
        mean_aligned_mesh=mean_aligned.reshape(3, N_VERTICES).T.astype(np.float32),
        mean_low_au_mesh=mean_low.reshape(3, N_VERTICES).T.astype(np.float32),
    )
    summary = {
        "counts": counts,
        "checksums": _checksums(tmp, written.digests, mesh_offset),
        "n_frames": n_kept,
        "n_videos": int(n_videos),
        "n_low_au_population": n_low_population,
        "dropped_videos": dropped_videos[:1000],
        "input_ranges": ranges,
    }
    return summary


def _kept_inputs(path: Path) -> np.ndarray:
    """(n_kept, 23) float64 input columns of a partition's kept metadata (pass 3's ``parts/<i>.arrow``)."""
    table = _read_staged(path, list(INPUT_COLUMNS))
    return np.column_stack([table.column(c).to_numpy().astype(np.float64) for c in INPUT_COLUMNS]).reshape(
        table.num_rows, len(INPUT_COLUMNS)
    )


def _active_counts(path: Path) -> np.ndarray:
    """(21,) int64: the partition's kept frames with each AU above :data:`aumesh.model.support.ACTIVE_AU`, then its
    kept frames."""
    table = _read_staged(path, list(AU_COLUMNS))
    counts = [int((table.column(a).to_numpy() > support.ACTIVE_AU).sum()) for a in AU_COLUMNS]
    return np.array([*counts, table.num_rows], np.int64)


def input_ranges(parts: list[Path]) -> dict[str, dict[str, float | None]]:
    """Each input's range record (:func:`aumesh.model.support.range_record`) over the kept frames of ``parts``
    (pass 3's per-partition metadata files, in order).

    The quantiles are :func:`aumesh.pipeline.quantiles.exact_column_quantiles` of the 23 columns: ``np.quantile`` of
    each column over every kept frame, bit for bit, never gathered, the 23 columns in the same three passes (counts
    and ranges, a histogram, a gather of the needed bins); ``min`` and ``max`` are the 0 and 1 quantiles. The active
    fractions are one more pass of counts.

    Returns
    -------
    dict
        ``{name: {"min", "p1", "p50", "p99", "max", "active_fraction"}}`` for the 23
        :data:`~aumesh.core.schema.INPUT_COLUMNS` (``active_fraction`` None for pose).
    """
    q = np.array(list(support.RANGE_QUANTILES.values()))
    counts = compute.map_reduce(_active_counts, np.add, parts)
    quantiles = exact_column_quantiles(_kept_inputs, parts, q)
    n = max(int(counts[-1]), 1)
    return {
        name: support.range_record(quantiles[j], float(counts[j] / n) if name in AU_COLUMNS else None)
        for j, name in enumerate(INPUT_COLUMNS)
    }


def _checksums(directory: Path, mesh_digests: dict[int, tuple[int, int, str]], mesh_offset: int) -> dict[str, dict]:
    """The files' checksums for ``summary.json`` (:mod:`aumesh.pipeline.integrity`): ``meshes.npy`` from the digests
    pass 3 computed while writing its rows (plus its header), the others read back once (small: per video, or the
    frames' metadata)."""
    row_bytes = N_TARGETS * np.dtype(np.float32).itemsize
    blocks = [(0, mesh_offset, integrity.hash_range(directory / MESHES_FILE, 0, mesh_offset))]
    blocks += [
        (mesh_offset + a * row_bytes, mesh_offset + b * row_bytes, h) for a, b, h in mesh_digests.values() if b > a
    ]
    records = {MESHES_FILE: integrity.file_record(directory / MESHES_FILE, blocks)}
    for name in (FRAMES_FILE, VIDEO_IDS_FILE, *NEUTRAL_FILES.values(), REFERENCE_FILE):
        records[name] = integrity.file_record(directory / name)
    return records


def _concatenate_parts(parts_dir: Path, out: Path) -> None:
    """One parquet of the partitions' kept metadata, in partition order (a row group per partition)."""
    files = sorted(parts_dir.glob("*.arrow"))
    writer = None
    for f in files:
        table = _read_staged(f)
        if table.num_rows:  # a partition with no frame kept is skipped (its columns may even lack a type)
            if writer is None:
                # dictionary pages for the video ids only: on continuous values (AUs, pose) Arrow builds a dictionary
                # until it overflows and falls back to plain pages, 0.45 s of the stage at 344k frames, 20 % more bytes
                writer = pq.ParquetWriter(out, table.schema, use_dictionary=[VIDEO_COLUMN])
            writer.write_table(table.cast(writer.schema))
        del table  # its memory map, before the file goes
        f.unlink()
    if writer is not None:
        writer.close()
    parts_dir.rmdir()


def load_summary(prepared_dir: str | Path) -> dict:
    with open(Path(prepared_dir) / SUMMARY_FILE) as fh:
        return json.load(fh)
