"""The prepare stage's per-partition tasks of its first passes: what a worker runs on one partition.

:func:`scan_partition` (pass 1: validation, the pose filter, the wild-value screen and the partition's GPA
candidates), :func:`residual_partition` (pass 2: each pose-passing frame's max anchor residual to the reference, its
AU sum and its similarity transform) and :func:`keep_partition` (the outlier cut). Each stages its per-frame results in
the run's scratch folder (:mod:`aumesh.pipeline.prepare.staging`) and returns the small per-partition result the stage
process holds (:class:`Scan`, :class:`Residuals`, :class:`Kept`). Pass 3's task is in
:mod:`aumesh.pipeline.prepare.write`; the order of the passes, and what the stage does between them, in
:mod:`aumesh.pipeline.prepare`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

from aumesh.config import Config
from aumesh.core.io import NpyRowFile
from aumesh.core.schema import AU_COLUMNS, FRAME_COLUMN, POSE_COLUMNS, VIDEO_COLUMN, instrument_columns
from aumesh.data import contract
from aumesh.data.tables import Piece, check_unique_frames, iter_vertices, read_pieces_metadata
from aumesh.geometry.align import align_to_reference, not_a_face
from aumesh.geometry.frame import HANDEDNESS_LANDMARKS, mirrored
from aumesh.pipeline import compute
from aumesh.pipeline.prepare.selection import Candidates, gpa_hash, keep_mask, pose_mask
from aumesh.pipeline.prepare.staging import (
    pass2,
    pass2_file,
    staged_anchors_file,
    staged_metadata_file,
    staged_table,
    write_staged,
)

#: A partition of the passes: whole row groups of the tables, in order (:func:`aumesh.data.tables.partitions`).
Partition = tuple[Piece, ...]
#: Frames whose anchors pass 2 aligns at a time: the alignment's float64 temporaries (~7 arrays of 288 bytes a frame)
#: are ~4 MiB at 2,048 frames, the same for any partition size (~15 MiB at 8,192; a whole 65,536-row partition at once:
#: ~120 MiB a task). Each frame is solved on its own, so the block size does not change a bit of the results (the
#: prepared data at 100k frames: identical at 8,192 and 2,048).
RESIDUAL_BLOCK = 2048


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
    meta = read_pieces_metadata(part, cfg.data.coerce_numeric, instrument_columns(cfg.model.eiv.instrument_aus))
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
    write_staged(staged, staged_metadata_file(scratch, i))
    np.save(staged_anchors_file(scratch, i), anchors_all)
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
    meta = staged_table(scratch, i, [VIDEO_COLUMN, FRAME_COLUMN, "piece", "wild", *POSE_COLUMNS, *AU_COLUMNS])
    pitch, yaw, roll = (meta.column(c).to_numpy() for c in POSE_COLUMNS)
    rows = np.flatnonzero(pose_mask(pitch, yaw, cfg.preprocess) & ~meta.column("wild").to_numpy(zero_copy_only=False))
    au_sum = au_sums(meta, rows)
    residual, rotation, scale, translation = (np.empty((len(rows), *shape)) for shape in ((), (3, 3), (), (3,)))
    with NpyRowFile(staged_anchors_file(scratch, i)) as anchors:
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
        pass2_file(scratch, i),
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


@dataclass
class Kept:
    """The outlier cut on one partition: its kept frames' count and videos, and the kept AU sums of split videos."""

    n_kept: int
    videos: np.ndarray  # sorted distinct videos with kept frames
    split_au: dict[str, np.ndarray]  # video -> AU sums of its kept frames here, for videos split across partitions


def keep_partition(item: tuple[Path, int], threshold: float | None, split_videos: np.ndarray) -> Kept:
    """The partition's frames kept by the outlier cut (``threshold``, ``None``: no cut), from pass 2's staged files."""
    residual, au_sum, videos, code = pass2(item, "residual", "au_sum", "videos", "code")
    keep = keep_mask(residual, threshold)
    kept_code = code[keep]
    split = np.flatnonzero(np.isin(videos, split_videos))
    return Kept(
        int(keep.sum()),
        videos[np.unique(kept_code)],
        {str(videos[j]): au_sum[keep][kept_code == j] for j in split if (kept_code == j).any()},
    )
