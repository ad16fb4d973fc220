"""Which frames the prepare stage keeps, and for what: rules on arrays, the same on every partition.

The pose filter (card, "Training data": |yaw| <= 40 deg, |pitch| <= 30 deg), the alignment's outlier cut on the max
anchor residual, the GPA subsample (the ``gpa_max_frames`` pose-passing frames of smallest seeded hash of
``(video_id, frame)``: :class:`Candidates`, merged partition by partition) and the per-video low-AU thresholds that
pick each video's neutral frames (``preprocess.neutral.low_au_quantile``). The passes of :mod:`aumesh.pipeline.prepare`
apply them; none of them depends on the partitioning.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import pandas as pd

from aumesh.config import PreprocessConfig
from aumesh.core.schema import FRAME_COLUMN, VIDEO_COLUMN


def pose_mask(pitch: np.ndarray, yaw: np.ndarray, cfg: PreprocessConfig) -> np.ndarray:
    """Card: |yaw| <= 40 deg and |pitch| <= 30 deg (inputs in radians)."""
    f = cfg.pose_filter
    return (np.abs(yaw) <= np.deg2rad(f.max_abs_yaw_deg)) & (np.abs(pitch) <= np.deg2rad(f.max_abs_pitch_deg))


def keep_mask(residual: np.ndarray, threshold: float | None) -> np.ndarray:
    """Frames under the outlier threshold (``None``: no outlier cut)."""
    return np.ones(len(residual), bool) if threshold is None else residual <= threshold


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
    anchors (:func:`aumesh.pipeline.prepare.staging.anchors_in_table_order` reads the chosen ones back), so the
    results a reduction holds at a time cost ~80 bytes a candidate, not ~450 (anchors and table paths: +100 MiB at
    the peak of pass 1 over 48 partitions, 3.1M frames).
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
