"""Column names and shapes of the frame tables and of the released model.

One place for every name the card fixes, so no module spells them again.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

# Card, "File format": input_columns = AU01..AU43, Pitch, Yaw, Roll.
AU_COLUMNS: tuple[str, ...] = (
    "AU01",
    "AU02",
    "AU04",
    "AU05",
    "AU06",
    "AU07",
    "AU09",
    "AU10",
    "AU11",
    "AU12",
    "AU14",
    "AU15",
    "AU17",
    "AU20",
    "AU23",
    "AU24",
    "AU25",
    "AU26",
    "AU28",
    "AU43",
)
# FACS names of the 20 AUs (Ekman & Friesen; py-feat's labels), for people who think "Lip corner puller", not "AU12".
AU_NAMES: dict[str, str] = {
    "AU01": "Inner brow raiser",
    "AU02": "Outer brow raiser",
    "AU04": "Brow lowerer",
    "AU05": "Upper lid raiser",
    "AU06": "Cheek raiser",
    "AU07": "Lid tightener",
    "AU09": "Nose wrinkler",
    "AU10": "Upper lip raiser",
    "AU11": "Nasolabial deepener",
    "AU12": "Lip corner puller",
    "AU14": "Dimpler",
    "AU15": "Lip corner depressor",
    "AU17": "Chin raiser",
    "AU20": "Lip stretcher",
    "AU23": "Lip tightener",
    "AU24": "Lip pressor",
    "AU25": "Lips part",
    "AU26": "Jaw drop",
    "AU28": "Lip suck",
    "AU43": "Eyes closed",
}
# The model's pose order (py-feat's Fex tables store Pitch, Roll, Yaw: always select by name).
POSE_COLUMNS: tuple[str, ...] = ("Pitch", "Yaw", "Roll")
INPUT_COLUMNS: tuple[str, ...] = AU_COLUMNS + POSE_COLUMNS

N_VERTICES = 478
N_TARGETS = 3 * N_VERTICES  # 1434

# Card, "Training data": 12 stable upper-face anchors.
ANCHOR_INDICES: tuple[int, ...] = (10, 9, 8, 151, 6, 168, 197, 195, 33, 263, 133, 362)

VIDEO_COLUMN = "video_id"
FRAME_COLUMN = "frame"
INPUT_PATH_COLUMN = "input"  # py-feat's source-file column, used to derive video_id


def mesh_columns_axis_major(n_vertices: int = N_VERTICES) -> list[str]:
    """Mesh column names in the model's output layout ``[x_0..x_477 | y_0.. | z_0..]``."""
    return [f"{axis}_{i}" for axis in "xyz" for i in range(n_vertices)]


def interaction_columns(
    au_columns: Sequence[str] = AU_COLUMNS, pose_columns: Sequence[str] = POSE_COLUMNS
) -> list[str]:
    """Names of the pose x input interaction features, pose-major: ``Pitch*AU01 .. Roll*AU43`` for the AUs."""
    return [f"{p}*{a}" for p in pose_columns for a in au_columns]


def feature_columns(pose: bool, interactions: bool, inputs: Sequence[str] = AU_COLUMNS) -> list[str]:
    """Design-matrix column names: ``[inputs | 3 pose | 3 x len(inputs) pose x input]`` (pose-major interactions).

    For the AUs (the default) 20, 23 or 83 columns; the other input families (``aumesh.core.families``) use the same
    layout, which is the one py-feat's ``PLSFeatMeshModel`` reads (its first ``len(inputs)`` coefficient rows).
    """
    if interactions and not pose:
        raise ValueError("features.interactions=true needs features.pose=true (interactions are pose x input)")
    cols = list(inputs)
    if pose:
        cols += list(POSE_COLUMNS)
    if interactions:
        cols += interaction_columns(inputs)
    return cols


def instrument_columns(pattern: str | None) -> tuple[str, ...]:
    """A second detector's AU columns named by ``model.eiv.instrument_aus`` (``{au}`` replaced by each AU name, in
    ``AU_COLUMNS`` order, e.g. ``"{au}_2"`` -> ``AU01_2 .. AU28_2``); ``()`` when none are configured."""
    return tuple(pattern.format(au=au) for au in AU_COLUMNS) if pattern else ()


def flatten_axis_major(mesh: np.ndarray) -> np.ndarray:
    """(..., 478, 3) -> (..., 1434) in the model's layout ``[x_0..x_477 | y_.. | z_..]``."""
    m = np.asarray(mesh)
    return np.swapaxes(m, -1, -2).reshape(*m.shape[:-2], 3 * m.shape[-2])


def unflatten_axis_major(flat: np.ndarray, n_vertices: int = N_VERTICES) -> np.ndarray:
    """(..., 1434) axis-major -> (..., 478, 3); inverse of :func:`flatten_axis_major`."""
    f = np.asarray(flat)
    if f.shape[-1] != 3 * n_vertices:
        raise ValueError(f"expected last axis of length {3 * n_vertices}, got {f.shape}")
    return np.swapaxes(f.reshape(*f.shape[:-1], 3, n_vertices), -1, -2)


#: ``preprocess.target`` values: what each video's rows have subtracted before the fit (design, mesh).
TARGETS = {
    "absolute": (None, None),  # the card's default: pooled absolute coordinates
    "neutral": (None, "neutral"),  # the card's neutral subtraction: the video's neutral mesh, from the mesh only
    "within": ("video_mean", "video_mean"),  # fixed effects: design and mesh demeaned per video
    "within_neutral": ("neutral", "neutral"),  # the video's neutral frames' mean design and mesh, from both sides
}

#: The card's pose filter (``preprocess.pose_filter``): frames beyond these |Pitch| and |Yaw| (degrees) are not
#: trained on; predictions beyond them warn (``aumesh.model.input_checks``).
MAX_ABS_PITCH_DEG = 30.0
MAX_ABS_YAW_DEG = 40.0
