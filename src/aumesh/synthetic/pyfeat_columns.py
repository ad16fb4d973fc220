"""py-feat 2.1.5's column layouts, for the synthetic tables of :mod:`aumesh.synthetic.pyfeat`: the names and order
of every column of a ``detect(..., save=)`` export, for ``MPDetector`` (``detector="mp"``: the 478-vertex mesh
interleaved ``x_0, y_0, z_0, ...``, 52 blendshapes, lower-case emotions, ``Identity_*``) or ``Detectorv2``
(``detector="v2"``: a 68-point block ``x_0..x_67, y_0..y_67``, the mesh axis-major ``mesh_x_*, mesh_y_*, mesh_z_*``,
capitalised emotions, valence/arousal, identity embeddings), and the hand-cleaned table's.

Only column names are taken from py-feat; nothing of its code or data.
"""

from __future__ import annotations

import numpy as np

from aumesh.core import families
from aumesh.core.schema import AU_COLUMNS, N_VERTICES

DETECTORS = ("mp", "v2")

FACE_RECT_COLUMNS = ("FaceRectX", "FaceRectY", "FaceRectWidth", "FaceRectHeight")
FEX_POSE_COLUMNS = ("Pitch", "Roll", "Yaw")  # py-feat's Fex order (the model's is Pitch, Yaw, Roll)
HEAD_POSITION_COLUMNS = ("X", "Y", "Z")
# The blendshape and emotion names and orders each detector writes: aumesh.core.families (py-feat's own lists, cited
# there). MPDetector writes the emotions in the family's order under its names; Detectorv2 capitalised, its own order.
BLENDSHAPE_COLUMNS = families.BLENDSHAPE_COLUMNS
EMOTION_COLUMNS_MP = families.EMOTION_COLUMNS
EMOTION_COLUMNS_V2 = families.EMOTION_COLUMNS_V2
IDENTITY_COLUMNS = tuple(f"Identity_{i}" for i in range(1, 513))
GAZE_COLUMNS = ("gaze_pitch", "gaze_yaw", "gaze_angle")
FRAME_SIZE_COLUMNS = ("FrameHeight", "FrameWidth")
TRAILING_COLUMNS = ("input", "frame", "approx_time", "Identity")
# v2's 68-point block: a fixed subset of the mesh's vertices (any fixed subset serves the ingest tests).
LANDMARK68_VERTICES: tuple[int, ...] = tuple(int(i) for i in np.round(np.linspace(0, N_VERTICES - 1, 68)))


def mesh_columns(detector: str) -> list[str]:
    """The 478-vertex mesh's columns as the detector writes them (mp interleaved, v2 axis-major ``mesh_*``)."""
    if detector == "mp":
        return [f"{a}_{i}" for i in range(N_VERTICES) for a in "xyz"]
    return [f"mesh_{a}_{i}" for a in "xyz" for i in range(N_VERTICES)]


def landmark68_columns() -> list[str]:
    """v2's 68-point block ``x_0..x_67, y_0..y_67``."""
    return [f"{a}_{i}" for a in "xy" for i in range(68)]


def pyfeat_columns(detector: str = "mp", frame_size: bool = True, mesh: bool = True) -> list[str]:
    """Columns of a py-feat 2.1.5 table in order (``mesh=False``: without the 478-vertex mesh, the split layout)."""
    check_detector(detector)
    size = list(FRAME_SIZE_COLUMNS) if frame_size else []
    head = list(FACE_RECT_COLUMNS) + ["FaceScore"]
    pose = list(FEX_POSE_COLUMNS) + list(HEAD_POSITION_COLUMNS)
    mesh_cols = mesh_columns(detector) if mesh else []
    if detector == "mp":
        cols = (
            head
            + mesh_cols
            + pose
            + list(BLENDSHAPE_COLUMNS)
            + list(AU_COLUMNS)
            + list(EMOTION_COLUMNS_MP)
            + list(IDENTITY_COLUMNS)
            + list(GAZE_COLUMNS)
        )
    else:
        cols = (
            head
            + landmark68_columns()
            + pose
            + list(AU_COLUMNS)
            + list(EMOTION_COLUMNS_V2)
            + ["valence", "arousal"]
            + list(GAZE_COLUMNS)
            + list(IDENTITY_COLUMNS)
            + mesh_cols
            + list(BLENDSHAPE_COLUMNS)
        )
    return cols + size + list(TRAILING_COLUMNS)


def clean_columns() -> list[str]:
    """The hand-cleaned table's columns (synth's ``columns`` layout): video_id, frame, AUs, Pitch, Roll, Yaw, mesh."""
    return (
        ["video_id", "frame"]
        + list(AU_COLUMNS)
        + list(FEX_POSE_COLUMNS)
        + [f"{a}_{i}" for i in range(N_VERTICES) for a in "xyz"]
    )


def check_detector(detector: str) -> None:
    if detector not in DETECTORS:
        raise ValueError(f"detector={detector!r}: use 'mp' (MPDetector) or 'v2' (Detectorv2)")
