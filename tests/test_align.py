"""Umeyama similarity and GPA against known transforms."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aumesh.geometry.align import (
    SIMILARITY_FRAMES,
    align_to_reference,
    apply_similarity,
    apply_similarity_columns,
    apply_similarity_vertices,
    generalized_procrustes,
    umeyama_batch,
)


def _points(rng, n=12):
    return rng.normal(size=(n, 3)) * [30.0, 40.0, 10.0] + [300.0, 250.0, 0.0]


def test_umeyama_recovers_a_known_rotation_scale_translation():
    rng = np.random.default_rng(0)
    target = _points(rng)
    rot = Rotation.from_euler("xyz", [[0.3, -0.5, 0.2], [-0.1, 0.7, 1.2]]).as_matrix()
    scale = np.array([1.7, 0.6])
    shift = np.array([[10.0, -5.0, 3.0], [-200.0, 40.0, 1.0]])
    # source = inverse similarity of the target: aligning it back must give R^T, 1/s
    source = np.einsum("ij,fkj->fki", np.eye(3), (target[None] - shift[:, None]) @ rot / scale[:, None, None])
    R, s, t = umeyama_batch(source, target)
    np.testing.assert_allclose(R, rot, atol=1e-10)
    np.testing.assert_allclose(s, scale, rtol=1e-10)
    np.testing.assert_allclose(apply_similarity(source, R, s, t), np.broadcast_to(target, source.shape), atol=1e-8)


def test_umeyama_never_returns_a_reflection():
    rng = np.random.default_rng(1)
    target = _points(rng)
    mirrored = target * [-1.0, 1.0, 1.0]
    R, _, _ = umeyama_batch(mirrored[None], target)
    assert np.linalg.det(R[0]) > 0.999


def test_residual_is_zero_for_exact_similarity_and_flags_a_displaced_anchor():
    rng = np.random.default_rng(2)
    ref = _points(rng)
    frames = np.stack([ref * 1.3 + 5.0, ref.copy()])
    frames[1, 3] += [0.0, 25.0, 0.0]
    residual, _ = align_to_reference(frames, ref)
    assert residual[0] < 1e-9
    assert residual[1] > 5.0


def test_gpa_reference_keeps_the_frames_mean_pose_and_size():
    rng = np.random.default_rng(3)
    shape = _points(rng)
    rots = Rotation.from_euler("xyz", rng.normal(0, 0.15, size=(200, 3))).as_matrix()
    frames = np.einsum("fij,kj->fki", rots, shape - shape.mean(0)) * rng.uniform(0.8, 1.2, (200, 1, 1)) + shape.mean(0)
    ref = generalized_procrustes(frames)
    residual, _ = align_to_reference(frames, ref)
    assert residual.max() < 1e-6  # one shape under similarity: GPA must find it exactly
    _, s, _ = umeyama_batch(ref[None], frames.mean(0))
    assert abs(s[0] - 1.0) < 0.05


def test_similarity_on_columns_moves_points_as_the_known_transform():
    """Frames stored one per column (axis-major, float32 as the tables hold them) -> rows: scale R p + t per point."""
    rng = np.random.default_rng(3)
    points = (rng.normal(size=(5, 40, 3)) * 100).astype(np.float32)  # (frames, points, xyz)
    rot = Rotation.random(5, random_state=4).as_matrix()
    scale, shift = rng.uniform(0.5, 2.0, 5), rng.normal(size=(5, 3)) * 50
    expected = scale[:, None, None] * (points.astype(np.float64) @ rot.transpose(0, 2, 1)) + shift[:, None]
    columns = points.transpose(2, 1, 0).reshape(3 * 40, 5)  # [x_0..x_39 | y.. | z..] down, a frame per column
    rows = apply_similarity_columns(columns, rot, scale, shift)
    assert rows.shape == (5, 120) and rows.flags.c_contiguous and rows.dtype == np.float64
    np.testing.assert_allclose(rows.reshape(5, 3, 40).transpose(0, 2, 1), expected, rtol=1e-13, atol=1e-11)
    np.testing.assert_allclose(
        rows.reshape(5, 3, 40).transpose(0, 2, 1), apply_similarity(points, rot, scale, shift), rtol=1e-13, atol=1e-11
    )


def test_similarity_of_selected_frames_is_bit_for_bit_that_of_the_gathered_frames():
    """``frames`` (prepare's kept rows of a chunk, any order, more than one block of SIMILARITY_FRAMES) moves exactly
    the frames a gather-then-move would, in either layout; without a copy of the selection."""
    rng = np.random.default_rng(8)
    n_rows = 3 * SIMILARITY_FRAMES
    vertices = (rng.normal(size=(n_rows, 40, 3)) * 100).astype(np.float16)
    columns = vertices.astype(np.float32).transpose(2, 1, 0).reshape(3 * 40, n_rows)
    frames = np.r_[rng.permutation(n_rows)[: 2 * SIMILARITY_FRAMES], [5, 5]]  # unsorted, a repeat
    n = len(frames)
    rot = Rotation.random(n, random_state=9).as_matrix()
    scale, shift = rng.uniform(0.5, 2.0, n), rng.normal(size=(n, 3)) * 50
    expected = apply_similarity_columns(np.ascontiguousarray(columns[:, frames]), rot, scale, shift)
    np.testing.assert_array_equal(apply_similarity_columns(columns, rot, scale, shift, frames), expected)
    np.testing.assert_array_equal(apply_similarity_vertices(vertices, rot, scale, shift, frames), expected)
    np.testing.assert_array_equal(apply_similarity_vertices(vertices[frames], rot, scale, shift), expected)
    moved = expected.reshape(n, 3, 40).transpose(0, 2, 1)  # the known transform, on the selected frames
    known = scale[:, None, None] * (vertices[frames].astype(np.float64) @ rot.transpose(0, 2, 1)) + shift[:, None]
    np.testing.assert_allclose(moved, known, rtol=1e-13, atol=1e-11)


def test_similarity_writes_into_a_given_buffer_and_refuses_a_wrong_one():
    """``out`` (pass 3 reuses one buffer for every block): the same rows written there; a buffer of another shape or
    dtype is an error, not a silently reshaped result."""
    rng = np.random.default_rng(10)
    columns = (rng.normal(size=(120, 9)) * 100).astype(np.float32)
    rot, scale, shift = Rotation.random(9, random_state=2).as_matrix(), rng.uniform(0.5, 2, 9), rng.normal(size=(9, 3))
    out = np.full((9, 120), np.nan)
    assert apply_similarity_columns(columns, rot, scale, shift, out=out) is out
    np.testing.assert_array_equal(out, apply_similarity_columns(columns, rot, scale, shift))
    for bad in (np.empty((8, 120)), np.empty((9, 120), np.float32), np.empty((120, 9)).T):
        with pytest.raises(ValueError, match="out must be"):
            apply_similarity_columns(columns, rot, scale, shift, out=bad)


def test_similarity_on_stored_vertices_is_bit_for_bit_that_on_columns():
    """Frames stored a row each (a py-feat mesh .npy: (frames, points, xyz), float16 here) -> the same rows as the
    columns path, bit for bit (prepare writes either), and the known transform to rounding; more frames than one
    block of SIMILARITY_FRAMES."""
    rng = np.random.default_rng(5)
    n = SIMILARITY_FRAMES + 7
    vertices = (rng.normal(size=(n, 40, 3)) * 100).astype(np.float16)
    rot = Rotation.random(n, random_state=6).as_matrix()
    scale, shift = rng.uniform(0.5, 2.0, n), rng.normal(size=(n, 3)) * 50
    rows = apply_similarity_vertices(vertices, rot, scale, shift)
    columns = vertices.astype(np.float32).transpose(2, 1, 0).reshape(3 * 40, n)
    assert rows.shape == (n, 120) and rows.dtype == np.float64
    np.testing.assert_array_equal(rows, apply_similarity_columns(columns, rot, scale, shift))
    expected = scale[:, None, None] * (vertices.astype(np.float64) @ rot.transpose(0, 2, 1)) + shift[:, None]
    np.testing.assert_allclose(rows.reshape(n, 3, 40).transpose(0, 2, 1), expected, rtol=1e-13, atol=1e-11)


@pytest.mark.parametrize("radius", [2.0, 3.4, 3.6, 4.0, 5.0, 7.0])
def test_beyond_radius_is_the_euclidean_rule(radius):
    """The fast rule (per-axis extremes, Euclidean only where they leave it in doubt) against the plain one."""
    from aumesh.geometry.align import beyond_radius

    rng = np.random.default_rng(1)
    flat = rng.normal(0, 1.0, (300, 1434)) * np.linspace(0.4, 2.0, 300)[:, None]  # farthest vertices ~1.6 to ~8
    centre = np.array([0.1, -0.2, 0.3])
    flat[7, 900] = np.nan
    flat[8, 20] = np.inf
    vertices = flat.reshape(len(flat), 3, 478) - centre[None, :, None]
    with np.errstate(invalid="ignore"):
        expected = ~(np.sqrt((vertices**2).sum(axis=1)).max(axis=1) <= radius)
    got = beyond_radius(flat, centre, radius)
    assert got[7] and got[8]
    np.testing.assert_array_equal(got, expected)
    assert 2 < got.sum() < len(got)  # both kinds of rows, and rows the per-axis bound leaves in doubt
