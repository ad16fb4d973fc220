"""The landmark vocabulary of the MediaPipe FaceMesh topology: which of the 478 vertex indices sits at which
anatomical point, the contours and regions they form, and the facial areas the AU-direction report names.

Only *index numbers* of MediaPipe's topology are used (no vertex position of any MediaPipe file); the template that
places them is :mod:`aumesh.geometry.face`, which also defines the face frame (x = subject's left, y = down,
z = away from the camera) that left and right here refer to.

Data in this module
-------------------
``LANDMARKS``   name -> MediaPipe index of the named anatomical points.
``REGIONS``     name -> int array of MediaPipe indices (only named landmarks),
                used by the AU-direction report. ``*_left`` / ``*_right`` are the
                **subject's** left / right.
``AREA_SEEDS``  name -> seed landmarks of a partition of all 478 vertices into facial areas
                (:func:`aumesh.geometry.measures.face_areas`: each vertex in its nearest seed's area), used by the
                AU-direction report to say where an AU field moves the face.
``EYE_CONTOUR_RIGHT/LEFT``, ``LIPS_OUTER``, ``LIPS_INNER``, ``FACE_OVAL``:
                closed contours (ordered) of the MediaPipe topology.
(the synthetic FACS displacement fields live in ``aumesh.synthetic.truth``)
"""

from __future__ import annotations

import numpy as np

# --------------------------------------------------------------------------- contours
FOREHEAD_MIDLINE: tuple[int, ...] = (10, 151, 9, 8)  # top -> down
NOSE_MIDLINE: tuple[int, ...] = (168, 6, 197, 195, 5, 4, 1)  # bridge -> tip
# Right eye (subject's right): lower lid outer->inner, then upper lid inner->outer.
EYE_CONTOUR_RIGHT: tuple[int, ...] = (33, 7, 163, 144, 145, 153, 154, 155, 133, 173, 157, 158, 159, 160, 161, 246)
EYE_CONTOUR_LEFT: tuple[int, ...] = (263, 249, 390, 373, 374, 380, 381, 382, 362, 398, 384, 385, 386, 387, 388, 466)
BROW_UPPER_RIGHT: tuple[int, ...] = (70, 63, 105, 66, 107)  # outer -> inner
BROW_LOWER_RIGHT: tuple[int, ...] = (46, 53, 52, 65, 55)
BROW_UPPER_LEFT: tuple[int, ...] = (300, 293, 334, 296, 336)
BROW_LOWER_LEFT: tuple[int, ...] = (276, 283, 282, 295, 285)
# Lips: upper lip from right corner to left corner, then lower lip back.
LIPS_OUTER: tuple[int, ...] = (
    61,
    185,
    40,
    39,
    37,
    0,
    267,
    269,
    270,
    409,
    291,
    375,
    321,
    405,
    314,
    17,
    84,
    181,
    91,
    146,
)
LIPS_INNER: tuple[int, ...] = (
    78,
    191,
    80,
    81,
    82,
    13,
    312,
    311,
    310,
    415,
    308,
    324,
    318,
    402,
    317,
    14,
    87,
    178,
    88,
    95,
)
CHIN_MIDLINE: tuple[int, ...] = (18, 200, 199, 175, 152)  # below lower lip -> bottom
# Face oval, clockwise in the image starting at the forehead top (10) toward the
# subject's left; 152 (chin bottom) is exactly half-way.
FACE_OVAL: tuple[int, ...] = (
    10,
    338,
    297,
    332,
    284,
    251,
    389,
    356,
    454,
    323,
    361,
    288,
    397,
    365,
    379,
    378,
    400,
    377,
    152,
    148,
    176,
    149,
    150,
    136,
    172,
    58,
    132,
    93,
    234,
    127,
    162,
    21,
    54,
    103,
    67,
    109,
)
IRIS_RIGHT: tuple[int, ...] = (468, 469, 470, 471, 472)  # centre first
IRIS_LEFT: tuple[int, ...] = (473, 474, 475, 476, 477)

LANDMARKS: dict[str, int] = {
    "forehead_top": 10,
    "forehead": 151,
    "glabella_upper": 9,
    "glabella": 8,
    "nose_bridge": 168,
    "nose_bridge_mid": 6,
    "nose_dorsum": 197,
    "nose_dorsum_low": 195,
    "nose_above_tip": 5,
    "nose_tip_upper": 4,
    "nose_tip": 1,
    "subnasale": 2,
    "eye_outer_right": 33,
    "eye_outer_left": 263,
    "eye_inner_right": 133,
    "eye_inner_left": 362,
    "upper_lid_right": 159,
    "lower_lid_right": 145,
    "upper_lid_left": 386,
    "lower_lid_left": 374,
    "iris_right": 468,
    "iris_left": 473,
    "brow_inner_right": 107,
    "brow_outer_right": 70,
    "brow_inner_left": 336,
    "brow_outer_left": 300,
    "lip_corner_right": 61,
    "lip_corner_left": 291,
    "upper_lip_top": 0,
    "lower_lip_bottom": 17,
    "upper_lip_inner": 13,
    "lower_lip_inner": 14,
    "chin": 152,
    "chin_upper": 18,
    "cheek_right": 50,
    "cheek_left": 280,
    "face_right": 234,
    "face_left": 454,
}

REGIONS: dict[str, np.ndarray] = {
    name: np.asarray(idx, dtype=np.int64)
    for name, idx in {
        "brow_inner_right": (107, 66, 55, 65),
        "brow_inner_left": (336, 296, 285, 295),
        "brow_outer_right": (70, 63, 46, 53),
        "brow_outer_left": (300, 293, 276, 283),
        "upper_eyelid_right": (157, 158, 159, 160, 161),
        "upper_eyelid_left": (384, 385, 386, 387, 388),
        "lower_eyelid_right": (163, 144, 145, 153, 154),
        "lower_eyelid_left": (390, 373, 374, 380, 381),
        "nose": (195, 5, 4, 1, 48, 278, 98, 327, 64, 294, 2),
        "cheek_right": (50, 205, 187, 123, 117, 116),
        "cheek_left": (280, 425, 411, 352, 346, 345),
        "nasolabial_right": (64, 205),
        "nasolabial_left": (294, 425),
        "lip_corner_right": (61, 146, 185, 78),
        "lip_corner_left": (291, 375, 409, 308),
        "upper_lip": (0, 37, 267, 39, 269, 13, 82, 312),
        "lower_lip": (17, 84, 314, 181, 405, 14, 87, 317),
        "chin": (18, 200, 199, 175, 152),
        "jaw": (152, 148, 377, 176, 400, 149, 378, 175, 199),
    }.items()
}

BILATERAL_SUFFIXES = ("_left", "_right")

# Areas: a partition of all 478 vertices into facial areas, for "where does an AU field move the face" (the AU-direction
# check, aumesh.card.directions). Each vertex belongs to the area of its nearest seed (3-D distance on the mesh at hand,
# :func:`aumesh.geometry.measures.face_areas`). Seeds are named landmarks and contour vertices only (their anatomy is
# fixed by MediaPipe's topology, and aumesh.geometry.face places them explicitly), disjoint, and include every REGIONS
# vertex except the few REGIONS share (64/294 and 205/425 seed the nasolabial areas, 152/175 the jaw, 199 the chin).
# Areas named like a REGIONS entry are that region's neighbourhood; the others cover the rest of the face (forehead,
# temples, glabella, irises, the face's sides) so that motion there is not credited to a FACS area.
AREA_SEEDS: dict[str, tuple[int, ...]] = {
    "forehead": (10, 151, 9, 338, 109, 297, 67),
    "temple_left": (332, 284, 251, 389),
    "temple_right": (103, 54, 21, 162),
    "glabella": (8, 168),
    "brow_inner_left": (336, 296, 285, 295),
    "brow_inner_right": (107, 66, 55, 65),
    "brow_outer_left": (300, 293, 276, 283, 334, 282),
    "brow_outer_right": (70, 63, 46, 53, 105, 52),
    "upper_eyelid_left": (384, 385, 386, 387, 388, 398, 466),
    "upper_eyelid_right": (157, 158, 159, 160, 161, 173, 246),
    "lower_eyelid_left": (390, 373, 374, 380, 381, 382, 249),
    "lower_eyelid_right": (163, 144, 145, 153, 154, 155, 7),
    "iris_left": IRIS_LEFT,
    "iris_right": IRIS_RIGHT,
    "nose": (6, 197, 195, 5, 4, 1, 2, 48, 278, 98, 327),
    "nasolabial_left": (294, 425),
    "nasolabial_right": (64, 205),
    "cheek_left": (280, 411, 352, 346, 345),
    "cheek_right": (50, 187, 123, 117, 116),
    "face_side_left": (454, 356, 323, 361),
    "face_side_right": (234, 127, 93, 132),
    "lip_corner_left": (291, 375, 409, 308),
    "lip_corner_right": (61, 146, 185, 78),
    "upper_lip": (0, 37, 267, 39, 269, 13, 82, 312, 40, 270, 80, 310, 81, 311),
    "lower_lip": (17, 84, 314, 181, 405, 14, 87, 317, 91, 321, 178, 402, 88, 318),
    "chin": (18, 200, 199),
    "jaw": (152, 175, 148, 377, 176, 400, 149, 378, 150, 379, 136, 365, 172, 397, 58, 288),
}


def region_side(name: str) -> int:
    """Side of a region: +1 for the subject's left, -1 for right, 0 for midline."""
    if name.endswith("_left"):
        return 1
    if name.endswith("_right"):
        return -1
    return 0


def region_group(name: str) -> str:
    """A region's or area's name without its side: ``"brow_inner_left"`` -> ``"brow_inner"``."""
    for suffix in BILATERAL_SUFFIXES:
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name
