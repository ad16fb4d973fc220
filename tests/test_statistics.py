"""Derived per-fold statistics (feature subsets, neutral target, displacement) equal explicit accumulation."""

from __future__ import annotations

import numpy as np
import pytest

from aumesh.model.features import design_matrix
from aumesh.model.cross_products import CrossProducts
from aumesh.data.schema import N_TARGETS, feature_columns
from aumesh.model.statistics import accumulate_design, configuration_statistics, fold_stacked, video_indicator


@pytest.fixture(scope="module")
def frames():
    rng = np.random.default_rng(5)
    n, n_videos = 900, 30
    video = np.sort(rng.integers(0, n_videos, n))
    video = np.unique(video, return_inverse=True)[1]
    n_videos = video.max() + 1
    fold = (video % 3).astype(np.int8)
    au = rng.random((n, 20))
    pose = rng.normal(0, 0.2, (n, 3))
    Y = 400.0 + rng.normal(size=(n, N_TARGETS)) + rng.normal(size=(n_videos, N_TARGETS))[video] * 3  # far from 0, per-video offsets
    neutral = 400.0 + rng.normal(size=(n_videos, N_TARGETS))
    xbar = rng.random((n_videos, 83))
    return au, pose, video, n_videos, fold, Y, neutral, xbar


def _chunks(Y, size):
    for start in range(0, len(Y), size):
        rows = slice(start, min(start + size, len(Y)))
        yield rows, Y[rows].copy()  # the pass may overwrite its chunk


def _assert_same(derived: CrossProducts, explicit: CrossProducts):
    assert derived.n == explicit.n
    np.testing.assert_allclose(derived.x_mean, explicit.x_mean, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(derived.y_mean, explicit.y_mean, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(derived.cxx, explicit.cxx, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(derived.cxy, explicit.cxy, rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(derived.cyy_diag, explicit.cyy_diag, rtol=1e-9)


@pytest.mark.parametrize("pose_on,interactions,target", [(True, True, "absolute"), (True, False, "neutral"), (False, False, "neutral")])
def test_derived_statistics_equal_explicit_accumulation(frames, pose_on, interactions, target):
    au, pose, video, n_videos, fold, Y, neutral, xbar = frames
    design = accumulate_design(au, pose, video, n_videos, fold, 3, _chunks(Y, 128))
    columns = feature_columns(pose_on, interactions)
    targets, displacements = configuration_statistics(design, columns, target, neutral, xbar)
    idx = [feature_columns(True, True).index(c) for c in columns]
    X = design_matrix(au, pose, pose_on, interactions)
    Yt = Y - neutral[video] if target == "neutral" else Y
    for f in range(3):
        m = fold == f
        _assert_same(targets[f], CrossProducts.from_arrays(X[m], Yt[m]))
        _assert_same(displacements[f], CrossProducts.from_arrays(X[m] - xbar[video[m]][:, idx], Y[m] - neutral[video[m]]))


def test_chunking_does_not_change_the_statistics(frames):
    au, pose, video, n_videos, fold, Y, _, _ = frames
    one = accumulate_design(au, pose, video, n_videos, fold, 3, _chunks(Y, len(Y)))
    many = accumulate_design(au, pose, video, n_videos, fold, 3, _chunks(Y, 77))
    for a, b in zip(one.folds, many.folds):
        _assert_same(a.reshifted(b.x_shift, b.y_shift) if hasattr(a, "reshifted") else a, b)
    np.testing.assert_allclose(one.video_sum_y + one.y_shift * one.video_count[:, None],
                               many.video_sum_y + many.y_shift * many.video_count[:, None], rtol=1e-12)


def test_fold_stacked_product_gives_each_folds_cross_products():
    rng = np.random.default_rng(1)
    X, Y = rng.normal(size=(50, 4)), rng.normal(size=(50, 6))
    fold = rng.integers(0, 3, 50)
    cross = Y.T @ fold_stacked(X, fold, 3)
    for f in range(3):
        m = fold == f
        np.testing.assert_allclose(cross[:, 4 * f : 4 * f + 4].T, X[m].T @ Y[m], atol=1e-12)
        np.testing.assert_allclose(cross[:, 12 + f], Y[m].sum(axis=0), atol=1e-12)


def test_video_indicator_sums_rows_per_video():
    video = np.array([7, 3, 7, 9, 3])
    Y = np.arange(10.0).reshape(5, 2)
    videos, indicator = video_indicator(video)
    assert videos.tolist() == [3, 7, 9]
    np.testing.assert_array_equal(indicator @ Y, [[2 + 8, 3 + 9], [0 + 4, 1 + 5], [6, 7]])
