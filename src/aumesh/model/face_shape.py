"""The shape guard: a release's AU=0 face must have a face's proportions.

A face measured in mixed units still fits, cross-validates and renders: a mesh whose z stayed in a detector's crop
units (py-feat's Detectorv2 maps x and y back to the frame and passes the mesh head's [0, 1] z through,
``feat/detector_v2.py`` ``_mesh_to_original_frame``; MPDetector leaves z in its 256 px crop, ``feat/MPDetector.py``
``forward``) gives a flat face, depth/width ~0.001, that nothing else notices. The release stage measures its AU=0
face (:func:`aumesh.geometry.measures.face_proportions`) and refuses one outside :data:`DEPTH_WIDTH_RANGE`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from aumesh.core.schema import unflatten_axis_major
from aumesh.geometry.measures import face_proportions

#: Depth/width of faces measured the same way (:func:`aumesh.geometry.measures.face_proportions`): the numbers the
#: card and the refusal quote.
REFERENCE_DEPTH_WIDTH = {
    "MediaPipe canonical face": 0.65,  # py-feat 2.1.5 resources/canonical_face_model.pt
    "py-feat v4 release": 0.81,  # py-feat 2.1.5 resources/au_to_mesh_pls_v4.npz, intercept and mean_aligned_mesh
}
#: Accepted depth/width of an AU=0 face. Faces measured: aumesh's template 0.47, MediaPipe's canonical 0.65, real
#: Detectorv2 clips with z converted 0.73 (median, issue 41), py-feat's v4 release 0.81: the range leaves a factor
#: of ~2 on either side of all of them (people and detectors differ; a release is not refused for a deep or shallow
#: face), while unit mistakes move the ratio by the crop's size in pixels (Detectorv2's chip: x1/400, 0.0011 on the
#: real clips) or by the frame's (normalized z: ~x1/1000).
DEPTH_WIDTH_RANGE = (0.25, 1.6)


def _sig(value: float) -> float:
    """``value`` to 4 significant digits (a flat face's 0.0011 stays 0.0011, not 0.0)."""
    return float(f"{value:.4g}")


def au0_face(intercept: np.ndarray) -> np.ndarray:
    """The AU=0, pose=0 face ``(478, 3)`` of an axis-major ``(1434,)`` intercept (the card's layout)."""
    return unflatten_axis_major(np.asarray(intercept, dtype=np.float64))


def face_shape_record(au0: np.ndarray, mean_aligned_mesh: np.ndarray) -> dict[str, Any]:
    """``data.face_shape`` of the card: the proportions of the AU=0 face and of ``mean_aligned_mesh``.

    Parameters
    ----------
    au0 : ndarray, shape (478, 3)
        The model's prediction at AU = 0, pose = 0 (:func:`au0_face` of the intercept).
    mean_aligned_mesh : ndarray, shape (478, 3)
        The prepared reference's mean aligned face.
    """
    au0_shape, mean_shape = face_proportions(au0), face_proportions(mean_aligned_mesh)
    return {
        "depth_width": _sig(au0_shape["depth_width"]),
        "width_height": _sig(au0_shape["width_height"]),
        "mean_aligned_mesh": {k: _sig(v) for k, v in mean_shape.items()},
        "accepted_depth_width": list(DEPTH_WIDTH_RANGE),
        "reference_depth_width": REFERENCE_DEPTH_WIDTH,
        "how": "extents of the 468 surface vertices in the face's own frame (x = 33 -> 263, y = chin -> forehead, "
        "z = out of the face); the AU=0 face is the release's intercept",
    }


def face_shape_error(depth_width: float, what: str, source: str) -> str | None:
    """The refusal for a face whose depth/width is outside :data:`DEPTH_WIDTH_RANGE`, or None when it is a face.

    Parameters
    ----------
    depth_width : float
        :func:`aumesh.geometry.measures.face_proportions`'s ``depth_width`` of the face.
    what : str
        Which face it is ("the AU=0 face (intercept)", "mean_aligned_mesh").
    source : str
        The file it was read from (``build/model/model.npz``, ``build/prepared/reference.npz``).

    Returns
    -------
    str or None
        One line: the file, the measured ratio, the accepted range, the likely cause and the fix.
    """
    low, high = DEPTH_WIDTH_RANGE
    if np.isfinite(depth_width) and low <= depth_width <= high:
        return None
    refs = ", ".join(f"{name} {value:.2f}" for name, value in REFERENCE_DEPTH_WIDTH.items())
    if np.isfinite(depth_width) and depth_width > high:
        cause = (
            "z in larger units than x and y (e.g. x, y normalized to [0, 1] and z in pixels, or z in a small crop's "
            "pixels)"
        )
    else:
        cause = (
            "a flat face: z left in the detector's crop units (Detectorv2's [0, 1] chip, MPDetector's 256 px crop) "
            "or normalized units while x and y are pixels"
        )
    return (
        f"{source}: {what} has depth/width {depth_width:.4g}, outside a face's [{low:g}, {high:g}] ({refs}): likely "
        f"{cause}: see data.mesh_units / the ingest manifest's mesh_units; nothing "
        f"written, the previous release is kept. Fix: re-ingest with z in the frame's pixels (`dvc repro -f ingest`)."
    )
