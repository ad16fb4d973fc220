"""One streaming pass, every configuration: per-fold statistics of the full design, and exact algebra
that turns them into the statistics of any feature subset, target and neutral.

Pass A reads the prepared meshes once and accumulates, for each cross-validation fold, the shifted
cross-products of the full 83-column design ``[20 AU | 3 pose | 60 pose x AU]`` with the absolute
aligned coordinates (``aumesh.pls.CrossProducts``), plus per-video sums of the design and of the
coordinates. Then, with no further pass:

* a feature subset (20 or 23 columns) is a sub-block of ``X'X`` and rows of ``X'Y``;
* the neutral-subtracted target ``y - n_v`` (``n_v`` the video's neutral mesh) follows from
  ``sum (x - a)(y - n_v)^T = S_xy - sum_v u_v d_v^T`` with ``u_v`` the video's shifted design sum
  and ``d_v = n_v - b`` its shifted neutral, and likewise for ``sum (y - n_v)`` and the squares;
* the displacement statistics ``(x - xbar_v, y - n_v)`` behind ``r2_displacement`` add the
  symmetric terms in ``e_v = xbar_v - a``.

So a sweep over targets, neutral methods and feature sets costs one pass over the meshes for R²
(and one prediction pass per configuration for MAE). Results equal explicit accumulation up to
float64 rounding (tests/test_statistics.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from aumesh.features import design_matrix
from aumesh.pls import CrossProducts
from aumesh.schema import N_TARGETS, feature_columns

FULL_DESIGN = feature_columns(True, True)


@dataclass
class DesignStatistics:
    """Per-fold statistics of (full design, absolute coordinates) and per-video sums, all shifted by (a, b)."""

    folds: list[CrossProducts]  # shifts x_shift = a (83,), y_shift = b (1434,)
    video_fold: np.ndarray  # (n_videos,) fold of each video
    video_count: np.ndarray  # (n_videos,) frames per video
    video_sum_x: np.ndarray  # (n_videos, 83)  sum over the video's frames of (x - a)
    video_sum_y: np.ndarray  # (n_videos, 1434) sum over the video's frames of (y - b)
    fold: np.ndarray  # (n_frames,) fold of each frame

    @property
    def x_shift(self) -> np.ndarray:
        return self.folds[0].x_shift

    @property
    def y_shift(self) -> np.ndarray:
        return self.folds[0].y_shift


def sort_chunk(fold: np.ndarray, video: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Order of a chunk's rows by (fold, video): fold slices become views and videos contiguous runs.

    Returns
    -------
    order : ndarray (m,)
        Row permutation.
    fold_bounds : ndarray (n_folds + 1,) int
        ``order[fold_bounds[f]:fold_bounds[f + 1]]`` are the rows of fold ``f``.
    video_starts : ndarray (k,) int
        Start of each video run in sorted order (for ``np.add.reduceat``).
    """
    order = np.lexsort((video, fold))
    f_sorted, v_sorted = fold[order], video[order]
    fold_bounds = np.searchsorted(f_sorted, np.arange(int(fold.max(initial=0)) + 2))
    video_starts = np.flatnonzero(np.r_[True, (v_sorted[1:] != v_sorted[:-1]) | (f_sorted[1:] != f_sorted[:-1])])
    return order, fold_bounds, video_starts


def accumulate_design(au: np.ndarray, pose: np.ndarray, video_index: np.ndarray, n_videos: int, fold: np.ndarray,
                      n_splits: int, mesh_chunks) -> DesignStatistics:
    """Pass A over ``mesh_chunks`` (iterable of ``(rows, Y)``, ``Y`` float64 (m, 1434), may be overwritten).

    Parameters
    ----------
    au : ndarray (n, 20), pose : ndarray (n, 3)
        Design inputs of every prepared frame (model order).
    video_index : ndarray (n,) int
        Video of each frame, 0..n_videos-1.
    fold : ndarray (n,) int
        Cross-validation fold of each frame.
    """
    p, q = len(FULL_DESIGN), N_TARGETS
    folds: list[CrossProducts] = []
    video_sum_x = np.zeros((n_videos, p))
    video_sum_y = np.zeros((n_videos, q))
    a = b = None
    buffer = None
    for rows, Y in mesh_chunks:
        X = design_matrix(au[rows], pose[rows], True, True)
        if a is None:  # one provisional shift for every fold, so fold statistics add and subtract
            a, b = X.mean(axis=0), Y.mean(axis=0)
            folds = [CrossProducts(p, q, x_shift=a, y_shift=b) for _ in range(n_splits)]
        X -= a
        Y -= b
        order, bounds, starts = sort_chunk(fold[rows], video_index[rows])
        if buffer is None or buffer.shape[0] < len(order):
            buffer = np.empty((len(order), q))
        Ys = np.take(Y, order, axis=0, out=buffer[: len(order)])
        Xs = X[order]
        for f in range(n_splits):
            lo, hi = bounds[f], bounds[f + 1]
            if hi == lo:
                continue
            xf, yf, s = Xs[lo:hi], Ys[lo:hi], folds[f]
            s.n += hi - lo
            s.sum_x += xf.sum(axis=0)
            s.sum_y += yf.sum(axis=0)
            s.xtx += xf.T @ xf
            s.xty += xf.T @ yf
            s.yty_diag += np.einsum("ij,ij->j", yf, yf)
        runs = video_index[rows][order][starts]
        video_sum_x[runs] += np.add.reduceat(Xs, starts, axis=0)
        video_sum_y[runs] += np.add.reduceat(Ys, starts, axis=0)
    video_fold = np.full(n_videos, -1, dtype=np.int64)
    video_fold[video_index] = fold
    return DesignStatistics(folds=folds, video_fold=video_fold, video_count=np.bincount(video_index, minlength=n_videos),
                            video_sum_x=video_sum_x, video_sum_y=video_sum_y, fold=fold)


def subset(stats: CrossProducts, columns: np.ndarray) -> CrossProducts:
    """Statistics of a subset of the design's columns (exact: sub-blocks)."""
    out = CrossProducts(len(columns), stats.n_targets, x_shift=stats.x_shift[columns], y_shift=stats.y_shift)
    out.n = stats.n
    out.sum_x = stats.sum_x[columns].copy()
    out.sum_y = stats.sum_y.copy()
    out.xtx = stats.xtx[np.ix_(columns, columns)].copy()
    out.xty = stats.xty[columns].copy()
    out.yty_diag = stats.yty_diag.copy()
    return out


def neutral_subtracted(stats: CrossProducts, count: np.ndarray, sum_x: np.ndarray, sum_y: np.ndarray,
                       shifted_neutral: np.ndarray) -> CrossProducts:
    """Statistics of ``(x, y - n_v)`` from those of ``(x, y)`` and per-video sums (videos of these rows only).

    Parameters
    ----------
    count : (k,) frames per video; sum_x : (k, p) sum of (x - a); sum_y : (k, q) sum of (y - b)
    shifted_neutral : (k, q) ``d_v = n_v - b``.
        The result is unshifted in y (``y - n_v`` is already a small displacement).
    """
    d = shifted_neutral
    out = CrossProducts(stats.n_features, stats.n_targets, x_shift=stats.x_shift, y_shift=np.zeros(stats.n_targets))
    out.n = stats.n
    out.sum_x = stats.sum_x.copy()
    out.xtx = stats.xtx.copy()
    out.sum_y = stats.sum_y - count @ d  # sum (y - b) - sum_v c_v d_v
    out.xty = stats.xty - sum_x.T @ d  # sum (x - a)(y - b - d_v)^T
    out.yty_diag = stats.yty_diag - 2.0 * np.einsum("vj,vj->j", sum_y, d) + np.einsum("v,vj,vj->j", count, d, d)
    return out


def displacement(stats: CrossProducts, count: np.ndarray, sum_x: np.ndarray, sum_y: np.ndarray,
                 shifted_neutral: np.ndarray, shifted_neutral_design: np.ndarray) -> CrossProducts:
    """Statistics of ``(x - xbar_v, y - n_v)``: the AU-driven displacement from each video's neutral.

    ``shifted_neutral_design`` (k, p) is ``e_v = xbar_v - a``; both results are unshifted.
    """
    d, e = shifted_neutral, shifted_neutral_design
    y_part = neutral_subtracted(stats, count, sum_x, sum_y, d)
    out = CrossProducts(stats.n_features, stats.n_targets, x_shift=np.zeros(stats.n_features), y_shift=np.zeros(stats.n_targets))
    out.n = stats.n
    out.sum_x = stats.sum_x - count @ e
    cross = sum_x.T @ e
    out.xtx = stats.xtx - cross - cross.T + e.T @ (count[:, None] * e)
    out.xty = y_part.xty - e.T @ sum_y + e.T @ (count[:, None] * d)
    out.sum_y = y_part.sum_y
    out.yty_diag = y_part.yty_diag
    return out


def configuration_statistics(design: DesignStatistics, columns: list[str], target: str, neutral: np.ndarray,
                             neutral_design_full: np.ndarray) -> tuple[list[CrossProducts], list[CrossProducts]]:
    """Per-fold (target, displacement) statistics of one configuration, from the design statistics.

    Parameters
    ----------
    columns : the configuration's design columns (a subset of the full design, in its order)
    target : ``"absolute"`` or ``"neutral"``
    neutral : (n_videos, 1434) the videos' neutral meshes (absolute coordinates)
    neutral_design_full : (n_videos, 83) mean full-design row of each video's neutral frames
    """
    idx = np.array([FULL_DESIGN.index(c) for c in columns])
    d_all = np.asarray(neutral, dtype=np.float64) - design.y_shift
    e_all = (neutral_design_full - design.x_shift)[:, idx]
    targets, displacements = [], []
    for f, stats in enumerate(design.folds):
        v = np.flatnonzero(design.video_fold == f)
        c, sx, sy, d = design.video_count[v].astype(np.float64), design.video_sum_x[v][:, idx], design.video_sum_y[v], d_all[v]
        sub = subset(stats, idx)
        targets.append(sub if target == "absolute" else neutral_subtracted(sub, c, sx, sy, d))
        displacements.append(displacement(sub, c, sx, sy, d, e_all[v]))
    return targets, displacements
