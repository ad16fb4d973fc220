"""Pass 3 of the prepare stage: each partition's kept frames aligned and written, and the plan it needs.

:func:`plans` gives each partition what pass 3 needs of the stage (nothing per frame): its output offset, its kept
videos' output index and the low-AU thresholds of videos split across partitions. :func:`write_partition`, on a
worker, derives the partition's kept rows and low-AU flags from the scratch files (:func:`kept_frames`), applies the
similarity transforms pass 2 solved, writes its rows of ``meshes.npy`` (hashed as they are written), its kept metadata
and the neutral meshes of the videos it holds whole, and returns the sums the stage reduces (:class:`Written`).
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from aumesh.config import Config
from aumesh.core.io import NpyRowFile
from aumesh.core.schema import N_TARGETS
from aumesh.data.tables import MeshChunk, iter_pieces_mesh_chunks
from aumesh.geometry.align import apply_similarity_columns, apply_similarity_vertices, beyond_radius
from aumesh.model.statistics import VideoSumStream
from aumesh.pipeline import integrity
from aumesh.pipeline.prepare.selection import keep_mask, low_au_thresholds
from aumesh.pipeline.prepare.staging import pass2, staged_table, write_staged
from aumesh.pipeline.prepare.tasks import Kept, Partition
from aumesh.pipeline.prepared_files import MESHES_FILE, NEUTRAL_FILES

#: Rows aligned, summed and written at a time in pass 3 (a (256, 1434) float64 block is 2.9 MB: in cache).
ALIGN_BLOCK = 256


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
    rows, residual, au_sum, code = pass2((scratch, plan.part_index), "rows", "residual", "au_sum", "code")
    keep = keep_mask(residual, cuts.outlier)
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
    pose_rows, rotation, scale, translation = pass2(
        (scratch, plan.part_index), "rows", "rotation", "scale", "translation"
    )
    transform = np.searchsorted(pose_rows, rows)  # each kept row's transform, as pass 2 solved it (read per block)
    # the kept rows of the staged metadata, in Arrow (pandas' Python strings cost ~300 bytes a row of the task's memory)
    kept = staged_table(scratch, plan.part_index).drop_columns(["piece", "wild"]).take(rows)
    kept = kept.append_column("video_index", pa.array(video_index)).append_column("low_au", pa.array(low_video))
    write_staged(kept.replace_schema_metadata(None), out_dir / "parts" / f"{plan.part_index:06d}.arrow")
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


def write_item(item: tuple[Partition, Plan], **kwargs) -> Written:
    """:func:`write_partition` on one item of pass 3's map, ``(partition, plan)``."""
    return write_partition(item[0], plan=item[1], **kwargs)


def plans(kept: list[Kept], video_ids: np.ndarray, split_names: np.ndarray, quantile: float) -> list[Plan]:
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
