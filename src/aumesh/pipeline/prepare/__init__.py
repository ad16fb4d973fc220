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
   staged per partition with |pose| (:func:`~aumesh.pipeline.prepare.tasks.residual_partition`). The outlier threshold, the
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
   metadata of pass 3 (:func:`~aumesh.pipeline.prepare.summary.input_ranges`: exact quantiles of the 23 columns in shared passes, ~0.9 s at 344k
   frames), for the release's record of what its data supports (:mod:`aumesh.model.support`).

Outputs (in ``paths.prepared_dir``, swapped in atomically as a whole folder):
``meshes.npy`` (n_kept, 1434) float32; ``frames.parquet`` (video_id, frame, AUs, pose, the instrument AUs when
configured, the carried families' columns under the family's names (float64: 52 blendshapes, 7 emotions, issue 46),
video_index, low_au per kept frame, same order; a row group per partition); ``video_ids.npy``
(n_videos,) and ``neutral_mean.npy`` / ``neutral_low_au.npy`` (n_videos, 1434) float32 (per-video
neutral meshes); ``reference.npz`` (reference anchors, mean meshes); ``summary.json`` (counts, ``input_ranges``,
the tables' ``detector``).
The tasks get absolute paths (the tables, the output's temporary folder, its scratch folder: per run, unique names),
so workers that run elsewhere, for several workspaces, read and write this run's files; on a cluster the tables and the
output folder must be on a filesystem every worker sees at the same path (a probe checks it when the stage connects).

This module is the driver: the order of the passes and what the stage process does between them (the reference, the
thresholds, the counts and the drop checks, the outputs). What a worker runs on one partition is in
:mod:`aumesh.pipeline.prepare.tasks` (passes 1, 2 and the cut) and :mod:`aumesh.pipeline.prepare.write` (pass 3);
the selection rules (pose filter, outlier cut, GPA subsample, low-AU thresholds) in
:mod:`aumesh.pipeline.prepare.selection`; the scratch files in :mod:`aumesh.pipeline.prepare.staging`; the summary's
ranges and checksums in :mod:`aumesh.pipeline.prepare.summary`.
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from aumesh.config import Config
from aumesh.core.io import absolute, atomic_directory, atomic_write_json, create_npy, recorded, write_rows
from aumesh.core.schema import N_TARGETS, N_VERTICES, VIDEO_COLUMN
from aumesh.data import contract
from aumesh.data.tables import FrameTable, TableError, check_unique_frames, partitions
from aumesh.geometry.align import generalized_procrustes, reference_scale
from aumesh.geometry.frame import canonical_frame
from aumesh.model import support
from aumesh.pipeline import compute
from aumesh.pipeline.prepare import tasks as prepare_tasks
from aumesh.pipeline.prepare import write as prepare_write
from aumesh.pipeline.prepare.staging import (
    anchors_in_table_order,
    kept_au_sums,
    read_staged,
    staged_abs_pose,
    staged_residuals,
    staged_table,
)
from aumesh.pipeline.prepare.summary import checksums, input_ranges
from aumesh.pipeline.prepare.tasks import Partition
from aumesh.pipeline.prepared_files import (
    FRAMES_FILE,
    MESHES_FILE,
    NEUTRAL_FILES,
    REFERENCE_FILE,
    SUMMARY_FILE,
    VIDEO_IDS_FILE,
)
from aumesh.pipeline.quantiles import exact_quantiles

log = logging.getLogger(__name__)


def _table_of_video(scratch: Path, parts: list[Partition], video: str) -> Path:
    """The first table with rows of ``video`` (for an error message), from pass 1's staged metadata."""
    for i, part in enumerate(parts):
        meta = staged_table(scratch, i)
        rows = np.flatnonzero(meta[VIDEO_COLUMN].to_numpy(zero_copy_only=False).astype(str) == video)
        if len(rows):
            return part[int(meta["piece"].to_numpy()[rows[0]])].table.path
    raise KeyError(video)


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
    families: dict | None = None,
) -> dict:
    """Prepare the frame tables into ``out_dir`` (replaced atomically). Returns the summary.

    ``ingested``: the ingest stage's counts (rows read, no-face rows and other faces dropped), added to the summary's.
    ``detectors``: ``{detector: n_sources}`` of the ingest manifest (:func:`aumesh.model.support.detector_counts`),
    recorded as the summary's ``detector`` (:func:`aumesh.model.support.detector_summary`; ``unknown`` when None).
    ``families``: the ingest manifest's ``families`` (``{"carried": [...], "not_carried": {family: why}}``), recorded
    as the summary's: ``frames.parquet`` holds the carried families' columns (read from the tables,
    :attr:`aumesh.data.tables.FrameTable.family_columns`), and a fit of another family names why it is not there.
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
                if families is not None:  # only when given: other callers' summaries are unchanged
                    summary["families"] = families
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


def check_handedness(scan: prepare_tasks.Scan, cfg: Config) -> None:
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
        partial(prepare_tasks.scan_partition, cfg=cfg, scratch=scratch, exclude=exclude),
        prepare_tasks.Scan.__add__,
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
        partial(
            prepare_tasks.residual_partition, cfg=cfg, reference=reference, split_videos=split_names, scratch=scratch
        ),
        list(enumerate(parts)),
        desc="prepare: residuals",
    )
    # every frame (float32: compared with 1 rad); np.median is np.quantile(.., 0.5) here: the midpoint of two
    # float32 values is exact in float64 either way. The exact medians (nine small passes) only when the counts
    # above the limit leave a median in doubt: pose in radians has almost none there
    if contract.pose_medians_may_exceed(np.sum([r.pose_above for r in res], axis=0), sum(scan.n_rows)):
        contract.check_pose_medians(
            [exact_quantiles(partial(staged_abs_pose, j), staged, 0.5) for j in range(3)], cfg.paths.data_dir
        )
    split_rows = pd.concat([r.split_rows for r in res], ignore_index=True)
    if len(split_rows):  # (video, frame) pairs across partitions (within one: checked in pass 1)
        files = sorted(set(split_rows["file"]))
        check_unique_frames(split_rows, [Path(f) for f in files], np.searchsorted(files, split_rows["file"]))
    quantile_cut = pre.alignment.outlier_quantile < 1.0
    # exact and independent of the partitioning: the quantile of the whole vector, which is never gathered
    threshold = (
        exact_quantiles(staged_residuals, staged, pre.alignment.outlier_quantile)
        if quantile_cut
        else max(r.residual_max for r in res)
    )
    outlier = threshold if quantile_cut else None  # what the partitions apply (None: no outlier cut)
    del res, split_rows
    kept = compute.map_gather(
        partial(prepare_tasks.keep_partition, threshold=outlier, split_videos=split_names),
        staged,
        desc="prepare: outlier cut",
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
    cuts = prepare_write.Cuts(outlier, q, exact_quantiles(partial(kept_au_sums, outlier), staged, q))
    plans = prepare_write.plans(kept, video_ids, split_names, q)
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
            prepare_write.write_item,
            cfg=cfg,
            reference=reference,
            cuts=cuts,
            out_dir=tmp,
            scratch=scratch,
            chunk_rows=compute.task_rows(cfg.data.chunk_rows),
            wild_radius=(reference.mean(axis=0), radius),
        ),
        prepare_write.Written.__add__,
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
        "checksums": checksums(tmp, written.digests, mesh_offset),
        "n_frames": n_kept,
        "n_videos": int(n_videos),
        "n_low_au_population": n_low_population,
        "dropped_videos": dropped_videos[:1000],
        "input_ranges": ranges,
    }
    return summary


def _concatenate_parts(parts_dir: Path, out: Path) -> None:
    """One parquet of the partitions' kept metadata, in partition order (a row group per partition)."""
    files = sorted(parts_dir.glob("*.arrow"))
    writer = None
    for f in files:
        table = read_staged(f)
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
