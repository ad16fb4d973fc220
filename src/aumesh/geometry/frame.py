"""The card's canonical frame, found from a face's anatomy.

The reference card's convention notes: "MP canonical: y-axis UP, x-axis to subject's left,
z-axis out of face. Standard right-handed." The release is expressed in that frame:

* ``x`` toward the **subject's left**: along the outer canthi 33 -> 263 (``mesh[263, 0] > mesh[33, 0]``);
* ``y`` **up**: forehead top 10 minus chin 152, made orthogonal to ``x``;
* ``z`` **out of the face**: ``x × y`` (right-handed), so the nose tip 1 is in front of the eyes.

The frame comes from the anatomy alone (via :func:`aumesh.geometry.face.face_frame`), so the
release is the same whatever convention the frame tables use: image pixels with y down and z into
the image (MediaPipe's and py-feat's pixel exports), a y-up frame, or any other rotation of
them. The map is a *proper* rotation (det +1) plus a translation, never a reflection or a change
of scale: coordinates keep the units of the Procrustes reference (the tables' pixels at the
frames' mean face size). Origin: the centroid of the mesh the frame is found from (the release
uses its ``mean_aligned_mesh``, whose centroid is therefore 0).

A mirrored mesh (a left-handed table convention: nose tip behind the eyes in ``x × y``) cannot be
turned into this frame by a rotation; :func:`canonical_frame` says so instead of reflecting it.
"""

from __future__ import annotations

import numpy as np

from aumesh.core.schema import N_VERTICES
from aumesh.geometry.face import face_frame

# face frame (x subject's left, y down, z away from the camera) -> card frame (x left, y up, z out of face)
CARD_FROM_FACE = np.diag([1.0, -1.0, -1.0])


def canonical_frame(mesh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and origin that put a mesh into the card's canonical frame.

    Parameters
    ----------
    mesh : array-like, shape (478, 3)
        A face with MediaPipe's topology, in any rotation and translation.

    Returns
    -------
    rotation : np.ndarray, shape (3, 3)
        Proper rotation (det +1); its rows are the card's x (subject's left), y (up) and
        z (out of the face) axes expressed in the input coordinates.
    origin : np.ndarray, shape (3,)
        Centroid of ``mesh``.

    Notes
    -----
    ``canonical = (points - origin) @ rotation.T`` (:func:`to_canonical`).

    Raises
    ------
    ValueError
        If the mesh is mirrored (no proper rotation gives x left, y up and the nose in front).
    """
    origin, axes, _ = face_frame(mesh)
    rotation = CARD_FROM_FACE @ axes
    if np.linalg.det(rotation) < 0:
        raise ValueError(
            "the mesh is mirrored: with x = 33 -> 263 (subject's left) and y = chin 152 -> forehead 10 (up), "
            "the nose tip 1 lies behind the eyes in a right-handed frame. Fix: the frame tables' x, y, z must form "
            "a right-handed system (e.g. image pixels x right, y down, z into the image); negate one axis "
            "(e.g. z) of every mesh column before training."
        )
    return rotation, origin


#: The landmarks :func:`mirrored` reads: nose tip 1, forehead 10, chin 152, outer and inner canthi 33, 263, 133, 362.
HANDEDNESS_LANDMARKS = (1, 10, 152, 33, 263, 133, 362)


def mirrored(landmarks: np.ndarray) -> np.ndarray:
    """(n,) bool: the frames that :func:`canonical_frame` would refuse as mirrored, from their
    :data:`HANDEDNESS_LANDMARKS` alone (vectorised; a frame whose landmarks are degenerate or not finite: False).

    :func:`aumesh.geometry.face.face_frame` points z so that the nose tip 1 is in front of the eyes; the frame is a
    reflection (det -1) exactly when, with ``left = 263 - 33`` and ``up = 10 - 152``, the nose tip lies on the negative
    side of ``left × up`` (the parts of ``up`` along ``left`` and the axes' lengths do not change that sign).

    Parameters
    ----------
    landmarks : array-like, shape (n, 7, 3)
        The vertices :data:`HANDEDNESS_LANDMARKS`, in that order.
    """
    m = np.asarray(landmarks, dtype=np.float64)
    nose, top, chin, c33, c263, c133, c362 = (m[:, j] for j in range(len(HANDEDNESS_LANDMARKS)))
    eyes = 0.25 * (c33 + c263 + c133 + c362)
    with np.errstate(invalid="ignore"):
        side = np.einsum("ij,ij->i", nose - eyes, np.cross(c263 - c33, top - chin))
    return side < 0  # NaN compares False


def to_canonical(points: np.ndarray, rotation: np.ndarray, origin: np.ndarray | None = None) -> np.ndarray:
    """``(points - origin) @ rotation.T`` for points (..., 3); no origin = directions (displacements)."""
    p = np.asarray(points, dtype=np.float64)
    if origin is not None:
        p = p - np.asarray(origin, dtype=np.float64)
    return p @ np.asarray(rotation, dtype=np.float64).T


def rotate_axis_major(flat: np.ndarray, rotation: np.ndarray, origin: np.ndarray | None = None) -> np.ndarray:
    """:func:`to_canonical` on axis-major rows (..., 1434) ``[x_0..x_477 | y_.. | z_..]``, same layout out.

    Use ``origin`` for meshes (an intercept) and none for displacement rows (coefficients).
    """
    f = np.asarray(flat, dtype=np.float64)
    if f.shape[-1] != 3 * N_VERTICES:
        raise ValueError(f"expected axis-major rows of length {3 * N_VERTICES}, got shape {f.shape}")
    xyz = f.reshape(*f.shape[:-1], 3, N_VERTICES)
    if origin is not None:
        xyz = xyz - np.asarray(origin, dtype=np.float64)[:, None]
    out = np.einsum("ij,...jv->...iv", np.asarray(rotation, dtype=np.float64), xyz)
    return out.reshape(f.shape)
