"""Derived per-fold statistics (feature subsets, neutral target, displacement) equal explicit accumulation."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from aumesh.core.schema import N_TARGETS, feature_columns
from aumesh.model.cross_products import CrossProducts
from aumesh.model.features import design_matrix
from aumesh.model.statistics import (
    DesignSums,
    VideoSumStream,
    accumulate_design,
    configuration_statistics,
    video_indicator,
    video_row_sums,
)


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
    Y = (
        400.0 + rng.normal(size=(n, N_TARGETS)) + rng.normal(size=(n_videos, N_TARGETS))[video] * 3
    )  # far from 0, per-video offsets
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


@pytest.mark.parametrize(
    "pose_on,interactions,target", [(True, True, "absolute"), (True, False, "neutral"), (False, False, "neutral")]
)
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
        _assert_same(
            displacements[f], CrossProducts.from_arrays(X[m] - xbar[video[m]][:, idx], Y[m] - neutral[video[m]])
        )


def test_chunking_does_not_change_the_statistics(frames):
    au, pose, video, n_videos, fold, Y, _, _ = frames
    one = accumulate_design(au, pose, video, n_videos, fold, 3, _chunks(Y, len(Y)))
    many = accumulate_design(au, pose, video, n_videos, fold, 3, _chunks(Y, 77))
    for a, b in zip(one.folds, many.folds, strict=True):
        _assert_same(a.reshifted(b.x_shift, b.y_shift) if hasattr(a, "reshifted") else a, b)
    np.testing.assert_allclose(
        one.video_sum_y + one.y_shift * one.video_count[:, None],
        many.video_sum_y + many.y_shift * many.video_count[:, None],
        rtol=1e-12,
    )


def test_design_sums_give_each_folds_cross_products_and_add():
    rng = np.random.default_rng(1)
    X, Y = rng.normal(size=(50, 4)), rng.normal(size=(50, 6))
    fold = rng.integers(0, 3, 50)
    sums = DesignSums(4, 6, 3)
    sums.add(X[:20], Y[:20].copy(), fold[:20])
    rest = DesignSums(4, 6, 3)
    rest.add(X[20:], Y[20:].copy(), fold[20:])
    total = sums + rest
    for f, s in enumerate(total.folds(np.zeros(4), np.zeros(6))):
        m = fold == f
        assert s.n == m.sum()
        np.testing.assert_allclose(s.xty, X[m].T @ Y[m], atol=1e-12)
        np.testing.assert_allclose(s.xtx, X[m].T @ X[m], atol=1e-12)
        np.testing.assert_allclose(s.sum_y, Y[m].sum(axis=0), atol=1e-12)
        np.testing.assert_allclose(s.sum_x, X[m].sum(axis=0), atol=1e-12)
        np.testing.assert_allclose(s.yty_diag, (Y[m] ** 2).sum(axis=0), atol=1e-12)


def test_video_indicator_sums_rows_per_video():
    video = np.array([7, 3, 7, 9, 3])
    Y = np.arange(10.0).reshape(5, 2)
    videos, indicator = video_indicator(video)
    assert videos.tolist() == [3, 7, 9]
    np.testing.assert_array_equal(indicator @ Y, [[2 + 8, 3 + 9], [0 + 4, 1 + 5], [6, 7]])


@pytest.mark.parametrize("layout", ["sorted", "consecutive", "scattered"])
def test_video_row_sums_equal_the_indicator_product_bit_for_bit(layout):
    """Rows grouped by video, sorted or in any video order (summed in place), or scattered (sorted first): the CSR
    product's sums exactly, bincount's counts; the videos in their rows' order when grouped, else sorted."""
    rng = np.random.default_rng(5)
    video = rng.integers(0, 12, 300)
    if layout == "sorted":
        video = np.sort(video)
    elif layout == "consecutive":  # a fold-grouped block: each video's rows together, the videos not in order
        video = rng.permutation(12)[np.sort(video)]
    rows = rng.standard_normal((300, 50)) * 10.0 ** rng.uniform(-4, 4, 50)
    videos, sums, counts = video_row_sums(video, rows)
    expected_videos, indicator = video_indicator(video)
    order = np.searchsorted(expected_videos, videos)  # the indicator's rows are the sorted videos
    np.testing.assert_array_equal(np.sort(videos), expected_videos)
    np.testing.assert_array_equal(videos, pd.unique(video) if layout != "scattered" else expected_videos)
    np.testing.assert_array_equal(sums, (indicator @ rows)[order])
    np.testing.assert_array_equal(counts, np.bincount(video)[videos])
    empty = video_row_sums(video[:0], rows[:0])
    assert [a.shape for a in empty] == [(0,), (0, 50), (0,)]


def test_video_sum_stream_hands_each_video_once_when_its_last_row_is_added():
    """Blocks that cut videos anywhere: each video's sum goes out once, right after the block with its last row, equal
    bit for bit to a dense (n_videos, n) array every block's per-video sums are added into; nothing stays open."""
    rng = np.random.default_rng(6)
    video = np.repeat(rng.permutation(40), rng.integers(1, 30, 40))  # consecutive rows per video, videos unsorted
    rows = rng.standard_normal((len(video), 7)) * 10.0 ** rng.uniform(-4, 4, 7)
    dense = np.zeros((40, 7))
    out: dict[int, tuple[np.ndarray, int]] = {}

    def done(v: int, total: np.ndarray, n: int) -> None:
        assert v not in out, f"video {v} handed out twice"
        out[v] = (total, n)

    stream = VideoSumStream(video, done)
    cuts = np.r_[0, np.sort(rng.choice(np.arange(1, len(video)), 25, replace=False)), len(video)]
    for lo, hi in zip(cuts[:-1], cuts[1:], strict=True):
        v, sums, _ = video_row_sums(video[lo:hi], rows[lo:hi])
        dense[v] += sums
        stream.add(video[lo:hi], rows[lo:hi])
        finished = set(video[:hi].tolist()) - set(video[hi:].tolist())
        assert set(out) == finished  # out as soon as its last row is in, not before
    assert not stream.open
    for v in range(40):
        np.testing.assert_array_equal(out[v][0], dense[v])
        assert out[v][1] == (video == v).sum()


def _demeaned(A, video):
    """Explicit per-video demeaning: each row minus its video's mean row."""
    sums = np.zeros((video.max() + 1, A.shape[1]))
    np.add.at(sums, video, A)
    return A - (sums / np.bincount(video)[:, None])[video]


def _close(a, b, rtol=1e-10):
    np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol * np.abs(b).max())


@pytest.mark.parametrize("pose_on,interactions", [(True, True), (True, False), (False, False)])
@pytest.mark.parametrize("video_block", [2048, 4])
def test_within_statistics_equal_explicit_per_video_demeaned_accumulation(frames, pose_on, interactions, video_block):
    au, pose, video, n_videos, fold, Y, neutral, xbar = frames
    design = accumulate_design(au, pose, video, n_videos, fold, 3, _chunks(Y, 128))
    columns = feature_columns(pose_on, interactions)
    targets, _ = configuration_statistics(design, columns, "within", neutral, xbar, video_block=video_block)
    X = design_matrix(au, pose, pose_on, interactions)
    for f in range(3):
        m = fold == f
        # each held-out video demeaned by its own means (the fold's videos are whole videos)
        Xd, Yd = (
            _demeaned(X[m], np.unique(video[m], return_inverse=True)[1]),
            _demeaned(Y[m], np.unique(video[m], return_inverse=True)[1]),
        )
        got, want = (
            targets[f],
            CrossProducts.from_arrays(Xd, Yd, x_shift=np.zeros(X.shape[1]), y_shift=np.zeros(N_TARGETS)),
        )
        assert got.n == want.n
        _close(got.xtx, want.xtx)  # X'X_w = X'X - sum_v n_v xbar_v xbar_v^T
        _close(got.xty, want.xty)
        _close(got.yty_diag, want.yty_diag)
        _close(got.cxx, want.cxx)
        _close(got.cxy, want.cxy)
        _close(got.cyy_diag, want.cyy_diag)
        assert np.abs(got.sum_x).max() < 1e-9 * np.abs(X).sum() and np.abs(got.sum_y).max() < 1e-9 * np.abs(Y).sum()


def test_within_neutral_is_both_sides_minus_the_neutral_frames_means(frames):
    au, pose, video, n_videos, fold, Y, neutral, xbar = frames
    design = accumulate_design(au, pose, video, n_videos, fold, 3, _chunks(Y, 128))
    columns = feature_columns(True, True)
    targets, _ = configuration_statistics(design, columns, "within_neutral", neutral, xbar)
    X = design_matrix(au, pose, True, True)
    for f in range(3):
        m = fold == f
        _assert_same(targets[f], CrossProducts.from_arrays(X[m] - xbar[video[m]], Y[m] - neutral[video[m]]))


@pytest.mark.parametrize("target", ["absolute", "neutral", "within", "within_neutral"])
def test_target_offsets_are_what_each_row_subtracts(frames, target):
    from aumesh.model.statistics import target_offsets

    au, pose, video, n_videos, fold, Y, neutral, xbar = frames
    design = accumulate_design(au, pose, video, n_videos, fold, 3, _chunks(Y, 128))
    columns = feature_columns(True, False)
    x_off, y_off = target_offsets(design, columns, target, neutral, xbar)
    X = design_matrix(au, pose, True, False)
    if target == "within":
        _close(X - x_off[video], _demeaned(X, video))
        _close(Y - y_off[video], _demeaned(Y, video), rtol=1e-9)
    else:
        assert (x_off is None) == (target in ("absolute", "neutral"))
        assert (y_off is None) == (target == "absolute")
        if target == "within_neutral":
            np.testing.assert_array_equal(x_off, xbar[:, :23])
        if y_off is not None:
            assert y_off is neutral


def test_unknown_target_is_refused(frames):
    au, pose, video, n_videos, fold, Y, neutral, xbar = frames
    design = accumulate_design(au, pose, video, n_videos, fold, 3, _chunks(Y, 128))
    with pytest.raises(ValueError, match="preprocess.target='fixed'.*within"):
        configuration_statistics(design, feature_columns(True, True), "fixed", neutral, xbar)


@pytest.mark.parametrize("video_block", [256, 3])
def test_the_screens_within_au_statistics_equal_explicit_demeaning_over_every_video(frames, video_block):
    from aumesh.core.schema import AU_COLUMNS
    from aumesh.model.statistics import pose_moments, within_statistics

    au, pose, video, n_videos, fold, Y, neutral, xbar = frames
    design = accumulate_design(au, pose, video, n_videos, fold, 3, _chunks(Y, 128))
    got = within_statistics(design, list(AU_COLUMNS), video_block=video_block)
    Xd, Yd = _demeaned(au, video), _demeaned(Y, video)
    assert got.n == len(au)
    _close(got.cxx, Xd.T @ Xd, rtol=1e-9)
    _close(got.cxy, Xd.T @ Yd, rtol=1e-9)
    _close(got.cyy_diag, (Yd**2).sum(0), rtol=1e-8)
    mean, second = pose_moments(design)
    _close(mean, pose.mean(0))
    _close(second, pose.T @ pose / len(pose))
