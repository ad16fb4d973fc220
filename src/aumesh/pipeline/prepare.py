"""Stage ``prepare``: frame tables -> pose-filtered, Procrustes-aligned meshes on disk.

Card, "Training data": pose filter |yaw| <= 40 deg, |pitch| <= 30 deg; per-frame Umeyama
similarity Procrustes onto a reference built on the 12 anchors; top 1 % of frames by max
anchor residual dropped.

Two streaming passes, bounded memory at any number of frames:

1. anchors only (36 of the 1434 mesh columns) + AU/pose: validation, pose filter, GPA
   reference (on a seeded subsample), residuals, the outlier cut, low-AU frames;
2. full meshes, chunk by chunk: align the kept frames and write them (float32, axis-major)
   into a memory-mapped ``meshes.npy``; accumulate the population and per-video means.

Outputs (in ``paths.prepared_dir``, swapped in atomically as a whole folder):
``meshes.npy`` (n_kept, 1434) float32; ``frames.parquet`` (video_id, frame, AUs, pose,
video_index, low_au per kept frame, same order); ``neutrals.npz`` (per-video neutral meshes);
``reference.npz`` (reference anchors, mean meshes); ``summary.json`` (counts per filter).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from aumesh.geometry.align import align_to_reference, generalized_procrustes, umeyama_batch
from aumesh.config import Config, PreprocessConfig
from aumesh.utils.io import atomic_directory, atomic_write_json
from aumesh.data.schema import AU_COLUMNS, N_TARGETS, N_VERTICES, VIDEO_COLUMN
from aumesh.model.statistics import video_indicator
from aumesh.data import contract
from aumesh.data.tables import FrameTable, TableError, check_unique_frames, iter_mesh_columns, iter_vertices, read_metadata

log = logging.getLogger(__name__)


@dataclass
class Selection:
    """Which rows survive each filter, and what pass 2 needs to align them."""

    meta: pd.DataFrame  # all rows, with `file_index`, `row`
    keep: np.ndarray  # (n_rows,) bool, final
    reference: np.ndarray  # (n_anchors, 3)
    counts: dict
    dropped_videos: list[str]


def pose_mask(pitch: np.ndarray, yaw: np.ndarray, cfg: PreprocessConfig) -> np.ndarray:
    """Card: |yaw| <= 40 deg and |pitch| <= 30 deg (inputs in radians)."""
    f = cfg.pose_filter
    return (np.abs(yaw) <= np.deg2rad(f.max_abs_yaw_deg)) & (np.abs(pitch) <= np.deg2rad(f.max_abs_pitch_deg))


def low_au_masks(au_sum: np.ndarray, video_index: np.ndarray, quantile: float) -> tuple[np.ndarray, np.ndarray]:
    """Low-AU frames: AU sum at or below the ``quantile`` of its video (per-subject) and of all frames (population).

    Returns
    -------
    per_video, population : ndarray of bool, shape (n_frames,)
    """
    order = np.lexsort((au_sum, video_index))
    sorted_video = video_index[order]
    starts = np.flatnonzero(np.r_[True, sorted_video[1:] != sorted_video[:-1]])
    sizes = np.diff(np.r_[starts, len(order)])
    # the rank of the per-video quantile, at least the video's lowest frame
    cut_rank = np.floor(quantile * (sizes - 1)).astype(int)
    thresholds = au_sum[order][starts + cut_rank]
    per_video = au_sum <= thresholds[np.searchsorted(np.unique(video_index), video_index)]
    population = au_sum <= np.quantile(au_sum, quantile)
    return per_video, population


def select_frames(tables: list[FrameTable], cfg: Config) -> tuple[Selection, np.ndarray]:
    """Pass 1: metadata + anchors of every row; the pose filter, GPA reference and outlier cut."""
    pre = cfg.preprocess
    anchor_idx = list(pre.alignment.anchor_indices)
    metas = []
    # (n_rows, n_anchors, 3) float32: the only per-frame mesh data kept (144 bytes a frame), filled in place
    anchors_all = np.empty((sum(t.n_rows for t in tables), len(anchor_idx), 3), np.float32)
    offset = 0
    for i, table in enumerate(tables):
        meta = read_metadata(table, cfg.data.coerce_numeric)
        meta["file_index"] = i
        meta["row"] = np.arange(len(meta))
        metas.append(meta)
        for start, block in iter_vertices(table, cfg.data.chunk_rows, anchor_idx):
            anchors_all[offset + start : offset + start + len(block)] = block
        offset += table.n_rows
    meta = pd.concat(metas, ignore_index=True)
    check_unique_frames(meta, [t.path for t in tables], meta["file_index"].to_numpy())
    n_rows = len(meta)

    keep_pose = pose_mask(meta["Pitch"].to_numpy(), meta["Yaw"].to_numpy(), pre)
    if not keep_pose.any():
        raise TableError(
            f"{cfg.paths.data_dir}: no frame passes the pose filter (|yaw| <= {pre.pose_filter.max_abs_yaw_deg} deg, "
            f"|pitch| <= {pre.pose_filter.max_abs_pitch_deg} deg) of {n_rows}. Likely cause: Pitch/Yaw in degrees "
            f"(convert with np.deg2rad), or preprocess.pose_filter narrower than the data."
        )
    partial = {"frames_in": n_rows, "dropped_pose": int(n_rows - keep_pose.sum())}
    contract.check_filter_shares(contract.filter_shares(partial), pre.max_drop_fraction, cfg.paths.data_dir)
    contract.check_pose_units(meta[["Pitch", "Yaw", "Roll"]].to_numpy(), cfg.paths.data_dir)
    pose_rows = np.flatnonzero(keep_pose)
    rng = np.random.default_rng(cfg.seed)
    sample = pose_rows if len(pose_rows) <= pre.alignment.gpa_max_frames else np.sort(
        rng.choice(pose_rows, pre.alignment.gpa_max_frames, replace=False))
    reference = generalized_procrustes(anchors_all[sample], pre.alignment.gpa_max_iter, pre.alignment.gpa_tol)

    residual = np.full(n_rows, np.inf)
    for start in range(0, len(pose_rows), 65536):
        rows = pose_rows[start : start + 65536]
        residual[rows], _ = align_to_reference(anchors_all[rows], reference)
    if pre.alignment.outlier_quantile < 1.0:
        threshold = float(np.quantile(residual[pose_rows], pre.alignment.outlier_quantile))
        keep_align = keep_pose & (residual <= threshold)
    else:
        threshold = float(residual[pose_rows].max())
        keep_align = keep_pose

    videos_before = meta[VIDEO_COLUMN].unique()
    kept_videos = set(meta.loc[keep_align, VIDEO_COLUMN].unique())
    dropped_videos = sorted(set(videos_before) - kept_videos)
    if dropped_videos and pre.empty_video == "error":
        v = dropped_videos[0]
        f = tables[int(meta.loc[meta[VIDEO_COLUMN] == v, "file_index"].iloc[0])].path
        raise TableError(
            f"{f}: video {v!r} (column {VIDEO_COLUMN!r}) has no frames left after the pose filter and the alignment "
            f"outlier cut ({len(dropped_videos)} such videos). Fix: remove it from the tables, widen "
            f"preprocess.pose_filter, or set preprocess.empty_video=drop to skip such videos."
        )
    counts = {
        "frames_in": int(n_rows),
        "videos_in": int(len(videos_before)),
        "dropped_pose": int(n_rows - keep_pose.sum()),
        "dropped_alignment_outliers": int(keep_pose.sum() - keep_align.sum()),
        "alignment_residual_threshold": threshold,
        "videos_dropped_no_frames_left": int(len(dropped_videos)),
        "frames_kept": int(keep_align.sum()),
        "videos_kept": int(len(kept_videos)),
    }
    shares = contract.filter_shares(counts)
    for name, share in shares.items():
        log.info("%s: dropped %d of %d %s (%.1f%%)", name, share["dropped"], share["of"], share["unit"], 100 * share["fraction"])
        counts[f"{contract.FILTER_KEYS[name]}_fraction"] = share["fraction"]
    if dropped_videos:
        log.warning("%d video(s) have no frames left after filtering and are dropped (first: %s)",
                    len(dropped_videos), ", ".join(dropped_videos[:5]))
    contract.check_filter_shares(shares, pre.max_drop_fraction, cfg.paths.data_dir)
    return Selection(meta=meta, keep=keep_align, reference=reference, counts=counts, dropped_videos=dropped_videos), anchors_all


class _VideoMeans:
    """Per-video means of mesh rows, summed in float64 only while a video still has frames to come.

    Memory is the float32 result (n_videos, 1434) plus the videos open in the current chunks, instead of
    float64 sums for every video (tables usually hold a video's frames together, so few are open at once).
    """

    def __init__(self, frames_per_video: np.ndarray):
        self.count = frames_per_video.astype(np.float64)
        self.remaining = frames_per_video.astype(np.int64).copy()
        self.means = np.zeros((len(frames_per_video), N_TARGETS), dtype=np.float32)
        self._open: dict[int, np.ndarray] = {}

    def add(self, video: np.ndarray, rows: np.ndarray) -> None:
        """Add ``rows`` (m, 1434) of videos ``video`` (m,)."""
        if len(video) == 0:
            return
        videos, indicator = video_indicator(video)
        sums = indicator @ rows
        n_rows = np.asarray(indicator.sum(axis=1)).ravel().astype(np.int64)
        for j, v in enumerate(videos.tolist()):
            acc = self._open.get(v)
            if acc is None:
                acc = self._open[v] = np.zeros(N_TARGETS)
            acc += sums[j]
            self.remaining[v] -= n_rows[j]
            if self.remaining[v] == 0:
                self.means[v] = acc / self.count[v]
                del self._open[v]


def _align_rows(rows: np.ndarray, rotation: np.ndarray, scale: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """``apply_similarity`` on axis-major mesh rows (m, 1434) -> (m, 1434) float64, same arithmetic per element
    (``scale * (R[a,0] x + R[a,1] y + R[a,2] z) + t[a]``) without the (m, 478, 3) einsum."""
    pts = rows.reshape(len(rows), 3, N_VERTICES)
    out = np.empty((len(rows), 3, N_VERTICES))
    tmp = np.empty((len(rows), N_VERTICES))
    for a in range(3):
        o = out[:, a]
        np.multiply(pts[:, 0], rotation[:, a, 0, None], out=o)
        np.multiply(pts[:, 1], rotation[:, a, 1, None], out=tmp)
        o += tmp
        np.multiply(pts[:, 2], rotation[:, a, 2, None], out=tmp)
        o += tmp
        o *= scale[:, None]
        o += translation[:, a, None]
    return out.reshape(len(rows), N_TARGETS)


def run(tables: list[FrameTable], cfg: Config, out_dir: str | Path) -> dict:
    """Prepare the frame tables into ``out_dir`` (replaced atomically). Returns the summary."""
    pre = cfg.preprocess
    selection, anchors_all = select_frames(tables, cfg)
    meta, keep = selection.meta, selection.keep
    kept = meta.loc[keep].reset_index(drop=True)
    video_ids, video_index = np.unique(kept[VIDEO_COLUMN].to_numpy(), return_inverse=True)
    kept["video_index"] = video_index.astype(np.int32)
    au_sum = kept[list(AU_COLUMNS)].to_numpy().sum(axis=1)
    low_video, low_population = low_au_masks(au_sum, video_index, pre.neutral.low_au_quantile)
    kept["low_au"] = low_video
    n_kept, n_videos = len(kept), len(video_ids)

    # output position of each input row (-1: dropped)
    position = np.full(len(keep), -1, dtype=np.int64)
    position[np.flatnonzero(keep)] = np.arange(n_kept)
    file_offsets = np.r_[0, np.cumsum([t.n_rows for t in tables])]

    del meta, selection.meta  # per-row metadata of dropped rows is not needed any more
    sums = np.zeros((2, N_TARGETS))  # all kept frames, population low-AU frames
    video_means = _VideoMeans(np.bincount(video_index, minlength=n_videos))
    video_low_means = _VideoMeans(np.bincount(video_index[low_video], minlength=n_videos))
    with atomic_directory(out_dir) as tmp:
        # the header via numpy; rows written with plain file I/O (kept rows arrive in output order), so the
        # meshes never sit in this process's memory (a memmap would count every written page in its RSS)
        header = np.lib.format.open_memmap(tmp / "meshes.npy", mode="w+", dtype=np.float32, shape=(n_kept, N_TARGETS))
        data_offset = header.offset
        del header
        written = 0
        with open(tmp / "meshes.npy", "r+b") as fh:
            fh.seek(data_offset)
            for i, table in enumerate(tables):
                for start, coords in iter_mesh_columns(table, cfg.data.chunk_rows):
                    m = coords.shape[1]
                    pos = position[file_offsets[i] + start : file_offsets[i] + start + m]
                    sel = pos >= 0
                    if not sel.any():
                        continue
                    pos = pos[sel]
                    if pos[0] != written or pos[-1] != written + len(pos) - 1:  # pragma: no cover - by construction
                        raise AssertionError("prepare: kept rows out of order")
                    anchors = anchors_all[file_offsets[i] + start : file_offsets[i] + start + m][sel]
                    transform = umeyama_batch(anchors.astype(np.float64), selection.reference)
                    flat = _align_rows(coords.T[sel], *transform)  # (m, 1434) float64, axis-major [x | y | z]
                    flat.astype(np.float32).tofile(fh)
                    written += len(pos)
                    sums[0] += flat.sum(axis=0)
                    sums[1] += flat[low_population[pos]].sum(axis=0)
                    video_means.add(video_index[pos], flat)
                    low = low_video[pos]
                    video_low_means.add(video_index[pos][low], flat[low])
        if written != n_kept:  # pragma: no cover - by construction
            raise AssertionError(f"prepare: wrote {written} of {n_kept} meshes")
        kept.drop(columns=["file_index", "row"]).to_parquet(tmp / "frames.parquet", index=False)
        np.savez(
            tmp / "neutrals.npz",
            video_ids=video_ids.astype(str),
            neutral_mean=video_means.means,
            neutral_low_au=video_low_means.means,
        )
        mean_aligned = sums[0] / n_kept
        mean_low = sums[1] / max(int(low_population.sum()), 1)
        np.savez(
            tmp / "reference.npz",
            reference_anchors=selection.reference.astype(np.float32),
            anchor_indices=np.asarray(pre.alignment.anchor_indices, dtype=np.int32),
            mean_aligned_mesh=mean_aligned.reshape(3, N_VERTICES).T.astype(np.float32),
            mean_low_au_mesh=mean_low.reshape(3, N_VERTICES).T.astype(np.float32),
        )
        summary = {
            "counts": selection.counts,
            "n_frames": n_kept,
            "n_videos": int(n_videos),
            "n_low_au_population": int(low_population.sum()),
            "dropped_videos": selection.dropped_videos[:1000],
            "tables": [str(t.path) for t in tables],
        }
        atomic_write_json(tmp / "summary.json", summary)
    return summary


def load_summary(prepared_dir: str | Path) -> dict:
    with open(Path(prepared_dir) / "summary.json") as fh:
        return json.load(fh)
