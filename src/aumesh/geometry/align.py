"""Similarity Procrustes alignment, batched over frames.

Umeyama (1991), "Least-squares estimation of transformation parameters between two point
patterns", eqs. (34)-(43): the rotation, uniform scale and translation (no reflection) that
map source points onto target points in the least-squares sense. Card, "Training data":
per-frame Umeyama similarity Procrustes onto a reference built on the 12 anchors.
"""

from __future__ import annotations

from functools import partial

import numpy as np


def umeyama_batch(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Similarity transforms mapping each frame's ``source`` points onto ``target``.

    Parameters
    ----------
    source : ndarray, shape (n_frames, n_points, 3)
        Points to move (e.g. one frame's anchors).
    target : ndarray, shape (n_points, 3) or (n_frames, n_points, 3)
        Points to move them onto.

    Returns
    -------
    rotation : ndarray, shape (n_frames, 3, 3)
        Proper rotations (det = +1).
    scale : ndarray, shape (n_frames,)
    translation : ndarray, shape (n_frames, 3)
        Such that ``scale * source @ rotation.T + translation`` best fits ``target``.
    """
    src = np.asarray(source, dtype=np.float64)
    tgt = np.asarray(target, dtype=np.float64)
    if tgt.ndim == 2:
        tgt = np.broadcast_to(tgt, src.shape)
    n_points = src.shape[1]
    mu_src = src.mean(axis=1)
    mu_tgt = tgt.mean(axis=1)
    src_c = src - mu_src[:, None, :]
    tgt_c = tgt - mu_tgt[:, None, :]
    var_src = np.einsum("fpk,fpk->f", src_c, src_c) / n_points  # eq. (36)
    cov = np.einsum("fpi,fpj->fij", tgt_c, src_c) / n_points  # eq. (38), Sigma_xy
    u, d, vt = np.linalg.svd(cov)
    # eq. (39)/(43): flip the smallest singular direction when the best orthogonal map is a reflection
    sign = np.ones_like(d)
    sign[:, -1] = np.where(np.linalg.det(u) * np.linalg.det(vt) < 0, -1.0, 1.0)
    rotation = np.einsum("fij,fj,fjk->fik", u, sign, vt)  # eq. (40)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(var_src > 0, np.einsum("fj,fj->f", d, sign) / var_src, 1.0)  # eq. (42)
    translation = mu_tgt - scale[:, None] * np.einsum("fij,fj->fi", rotation, mu_src)  # eq. (41)
    return rotation, scale, translation


def apply_similarity(
    points: np.ndarray, rotation: np.ndarray, scale: np.ndarray, translation: np.ndarray
) -> np.ndarray:
    """``scale * points @ rotation.T + translation`` per frame; points shape (n_frames, n_points, 3)."""
    return scale[:, None, None] * np.einsum("fpj,fij->fpi", points, rotation) + translation[:, None, :]


#: Frames moved at a time by :func:`apply_similarity_columns`: a (64, 1434) float64 block and its float32 source stay
#: in a core's L2 cache (512 KiB here); 256 frames at a time took twice as long (measured on 2 AMD EPYC cores).
SIMILARITY_FRAMES = 64


def apply_similarity_columns(
    columns: np.ndarray,
    rotation: np.ndarray,
    scale: np.ndarray,
    translation: np.ndarray,
    frames: np.ndarray | None = None,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """:func:`apply_similarity` on point sets stored one per column, axis-major, returned as rows.

    ``(scale R) p + t`` per point in float64: each frame's ``scale * R`` (3, 3) times its (3, n_points) coordinates
    (a batched matmul), plus ``t`` (the einsum of :func:`apply_similarity` multiplies in another order: they agree
    to rounding). The columns (how the streaming passes read mesh tables, one column per coordinate) are
    transposed into rows while still float32, half the bytes of transposing the float64 result, a few frames at a
    time (:data:`SIMILARITY_FRAMES`) so every step stays in the CPU's cache.

    Parameters
    ----------
    columns : ndarray, shape (3 n_points, n_columns)
        Axis-major points ``[x_0..x_{n-1} | y_.. | z_..]``, one frame per column (float32 or float64).
    rotation : ndarray, shape (n_frames, 3, 3)
    scale : ndarray, shape (n_frames,)
    translation : ndarray, shape (n_frames, 3)
    frames : ndarray of int, shape (n_frames,), optional
        The columns to move, in this order (default: every column). Each few are gathered as they are transposed:
        a chunk's selected frames are never copied out first (prepare's pass 3 moves the kept frames of a parquet
        chunk: gathering 256 of them, then transposing, took 44.7 ms a 4,096-row chunk against 40.1, one thread).
    out : ndarray of float64, shape (n_frames, 3 n_points), optional
        Where to write the result (a pass moving block after block reuses one).

    Returns
    -------
    ndarray of float64, shape (n_frames, 3 n_points)
        The moved points, a frame per row, axis-major.
    """
    n_coords = columns.shape[0]
    if frames is None:
        return _moved_rows(
            lambda lo, hi: np.ascontiguousarray(columns[:, lo:hi].T).reshape(hi - lo, 3, -1),
            columns.shape[1],
            n_coords,
            rotation,
            scale,
            translation,
            out,
        )
    # np.take's (n_coords, k) block is dense (rows of k values), so its transpose stays in cache
    return _moved_rows(
        lambda lo, hi: np.take(columns, frames[lo:hi], axis=1).T.copy().reshape(hi - lo, 3, -1),
        len(frames),
        n_coords,
        rotation,
        scale,
        translation,
        out,
    )


def apply_similarity_vertices(
    vertices: np.ndarray,
    rotation: np.ndarray,
    scale: np.ndarray,
    translation: np.ndarray,
    frames: np.ndarray | None = None,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """:func:`apply_similarity_columns` on point sets stored a frame per row, as a mesh ``.npy`` stores them.

    Each frame's points are transposed to (3, n_points) a few frames at a time, widened to at least float32 (exact),
    so the product, and every bit of the result, is that of :func:`apply_similarity_columns` on the same points.

    Parameters
    ----------
    vertices : ndarray, shape (n_rows, n_points, 3)
        Any float dtype (float16 as py-feat may save them).
    rotation, scale, translation, out
        As in :func:`apply_similarity_columns`.
    frames : ndarray of int, shape (n_frames,), optional
        The rows to move, in this order (default: every row), gathered a few at a time.

    Returns
    -------
    ndarray of float64, shape (n_frames, 3 n_points)
        As :func:`apply_similarity_columns` returns.
    """
    n_points = vertices.shape[1]
    dtype = np.promote_types(vertices.dtype, np.float32)
    if frames is None:
        return _moved_rows(
            lambda lo, hi: np.ascontiguousarray(vertices[lo:hi].transpose(0, 2, 1), dtype=dtype),
            len(vertices),
            3 * n_points,
            rotation,
            scale,
            translation,
            out,
        )
    return _moved_rows(
        lambda lo, hi: np.ascontiguousarray(vertices[frames[lo:hi]].transpose(0, 2, 1), dtype=dtype),
        len(frames),
        3 * n_points,
        rotation,
        scale,
        translation,
        out,
    )


def _moved_rows(
    points_of,
    n_frames: int,
    n_coords: int,
    rotation: np.ndarray,
    scale: np.ndarray,
    translation: np.ndarray,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """``(scale R) p + t`` of frames ``lo:hi`` at a time, ``points_of(lo, hi)`` their (hi - lo, 3, n_points)
    points; returns (n_frames, n_coords) float64 axis-major rows (``out``, when given)."""
    if out is None:
        rows = np.empty((n_frames, n_coords))
    elif out.shape != (n_frames, n_coords) or out.dtype != np.float64 or not out.flags.c_contiguous:
        raise ValueError(
            f"out must be C-contiguous float64 of shape {(n_frames, n_coords)}, got {out.dtype} {out.shape}"
        )
    else:
        rows = out
    for lo in range(0, n_frames, SIMILARITY_FRAMES):
        hi = min(lo + SIMILARITY_FRAMES, n_frames)
        moved = rows[lo:hi].reshape(hi - lo, 3, -1)
        np.matmul(rotation[lo:hi] * scale[lo:hi, None, None], points_of(lo, hi), out=moved)
        moved += translation[lo:hi, :, None]
    return rows


def align_to_reference(anchors: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, tuple]:
    """Align each frame's anchors onto ``reference``; returns the per-frame max anchor residual and the transform.

    Parameters
    ----------
    anchors : ndarray, shape (n_frames, n_anchors, 3)
    reference : ndarray, shape (n_anchors, 3)

    Returns
    -------
    max_residual : ndarray, shape (n_frames,)
        Largest Euclidean distance between an aligned anchor and its reference point.
    transform : tuple (rotation (n,3,3), scale (n,), translation (n,3))
    """
    transform = umeyama_batch(anchors, reference)
    aligned = apply_similarity(np.asarray(anchors, dtype=np.float64), *transform)
    residual = np.linalg.norm(aligned - reference[None], axis=2).max(axis=1)
    return residual, transform


#: Frames aligned per block by :func:`generalized_procrustes` (a fixed size: the blocks, and the bits, do not depend on
#: how many run at once).
GPA_BLOCK = 4096


def _aligned_onto(reference: np.ndarray, frames: np.ndarray) -> np.ndarray:
    return apply_similarity(frames, *umeyama_batch(frames, reference))


def generalized_procrustes(anchors: np.ndarray, max_iter: int = 50, tol: float = 1e-10, map=map) -> np.ndarray:
    """Reference shape by generalised Procrustes analysis (Gower 1975) on anchor sets.

    Starts from the plain mean of the frames (near-frontal after the pose filter, so the
    reference keeps the tables' orientation and pixel scale), then alternates: align every
    frame onto the reference, re-average, and re-fix the average's pose and size to the
    starting mean (GPA leaves those free; without the re-fix the reference would drift).

    Parameters
    ----------
    anchors : ndarray, shape (n_frames, n_anchors, 3)
    max_iter : int
    tol : float
        Stop when the reference moves less than ``tol`` relative to its largest coordinate.
    map : callable, default the builtin
        ``map(fn, blocks)``, run over blocks of :data:`GPA_BLOCK` frames each iteration; e.g. a thread pool's
        (the stage's cores: NumPy's batched SVD and products release the GIL). Each frame is aligned on its own,
        so the reference is the same to the bit whatever runs the blocks.

    Returns
    -------
    reference : ndarray, shape (n_anchors, 3)
    """
    anchors = np.asarray(anchors, dtype=np.float64)
    if anchors.ndim != 3 or anchors.shape[0] == 0:
        raise ValueError(
            f"generalized_procrustes needs (n_frames, n_anchors, 3) with n_frames > 0, got {anchors.shape}"
        )
    blocks = [anchors[lo : lo + GPA_BLOCK] for lo in range(0, len(anchors), GPA_BLOCK)]
    start = anchors.mean(axis=0)
    reference = start.copy()
    for _ in range(max_iter):
        aligned = np.concatenate(list(map(partial(_aligned_onto, reference), blocks)))
        mean = aligned.mean(axis=0)
        rot, scale, trans = umeyama_batch(mean[None], start)
        new_reference = apply_similarity(mean[None], rot, scale, trans)[0]
        change = np.abs(new_reference - reference).max() / max(np.abs(reference).max(), 1e-12)
        reference = new_reference
        if change < tol:
            break
    return reference


#: Pass 1's screen, before a reference exists: a frame whose farthest anchor lies more than this many times the
#: anchors' median distance from their median point is no face at all (a corrupt export). Real faces stay near 3.5-4.3
#: (the demo tables: median 3.5, max 4.3), so only gross corruption is caught here; the stated rule
#: (:func:`beyond_radius`, ``preprocess.alignment.max_vertex_iod``) follows after alignment on every vertex.
ANCHOR_SPREAD_LIMIT = 10.0


def not_a_face(anchors: np.ndarray, limit: float = ANCHOR_SPREAD_LIMIT) -> np.ndarray:
    """(n,) bool: frames whose anchors are not a face (non-finite, collapsed, or one far beyond the others).

    Robust to any one anchor (medians), and invariant to rotation, scale and translation.

    Parameters
    ----------
    anchors : ndarray, shape (n, k, 3)
    """
    a = np.asarray(anchors, dtype=np.float64)
    centre = np.median(a, axis=1, keepdims=True)
    distance = np.sqrt(((a - centre) ** 2).sum(axis=2))  # (n, k)
    spread = np.median(distance, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        bad = ~(distance.max(axis=1) <= limit * spread)  # NaN/inf compare False
    return bad | ~(spread > 0)


def reference_scale(reference: np.ndarray, anchor_indices, iod_vertices=(33, 263)) -> float:
    """The reference's inter-ocular distance (outer canthi 33-263) when both are anchors; else the anchors' RMS
    distance from their centroid times 1.6 (the ratio of the two on MediaPipe's face)."""
    idx = list(anchor_indices)
    ref = np.asarray(reference, dtype=np.float64)
    if all(v in idx for v in iod_vertices):
        return float(np.linalg.norm(ref[idx.index(iod_vertices[0])] - ref[idx.index(iod_vertices[1])]))
    return 1.6 * float(np.sqrt(((ref - ref.mean(axis=0)) ** 2).sum(axis=1).mean()))


def beyond_radius(flat: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """(m,) bool: aligned meshes with any vertex farther than ``radius`` from ``centre`` (or not finite).

    The largest coordinate deviation ``d`` of a row bounds its farthest vertex: between ``d`` and ``sqrt(3) d``. So
    the rows' per-axis maxima and minima settle every row but those with ``radius / sqrt(3) < d <= radius``, whose
    Euclidean distances are computed (a face spans about 2 inter-ocular distances, the radius is 4: none, on real
    data). Reductions only, no temporary of the block: this runs on every aligned frame.

    Parameters
    ----------
    flat : ndarray, shape (m, 1434)
        Aligned meshes, axis-major ``[x_0..x_477 | y_.. | z_..]``.
    centre : ndarray, shape (3,)
    """
    m, n = len(flat), flat.shape[1] // 3
    if not n:
        return np.zeros(m, bool)
    deviation = np.zeros(m)
    for axis in range(3):  # reductions only: no temporary of the block (NaN propagates through max and min)
        segment = flat[:, axis * n : (axis + 1) * n]
        deviation = np.maximum(
            deviation, np.maximum(segment.max(axis=1) - centre[axis], centre[axis] - segment.min(axis=1))
        )
    far = ~(deviation <= radius)
    unsure = np.flatnonzero(~far & (deviation > radius / np.sqrt(3.0)))
    if len(unsure):
        rows = flat[unsure].reshape(len(unsure), 3, n) - np.asarray(centre)[None, :, None]
        far[unsure] = ~(np.sqrt((rows**2).sum(axis=1)).max(axis=1) <= radius)
    return far
