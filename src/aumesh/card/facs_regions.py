"""The FACS expectation of each AU for the direction check (:mod:`aumesh.card.directions`): its region(s), the
areas nearby where FACS also describes its appearance changes, and the direction its region moves, in face terms.

Data only (no computation), split from :mod:`aumesh.card.directions` to keep that module short. Regions and directions
follow the appearance changes the FACS manual describes for each action unit (Ekman, Friesen & Hager, 2002, *Facial
Action Coding System: The Manual*, Research Nexus); groups are :data:`aumesh.geometry.landmarks.AREA_SEEDS` names
without their side.
"""

from __future__ import annotations

from typing import Any

from aumesh.core.schema import AU_NAMES

# Face-term unit vectors in local coordinates (lateral, up, toward). "lateral" is
# subject's left for midline groups and outward for bilateral groups.
FACE_TERMS: dict[str, tuple[float, float, float]] = {
    "up": (0, 1, 0),
    "down": (0, -1, 0),
    "toward": (0, 0, 1),
    "away": (0, 0, -1),
    "outward": (1, 0, 0),
    "inward": (-1, 0, 0),
    "left": (1, 0, 0),
    "right": (-1, 0, 0),
}

# The FACS expectation table (data). "checks": the direction FACS gives in the AU's FACS region(s),
# (area group, {term: weight}); "regions" (default: the checks' groups): the AU's FACS region(s), where its largest
# motion must be; "nearby": the other area groups where FACS describes appearance changes of the AU.
# Groups are aumesh.geometry.landmarks.AREA_SEEDS names without their side.
FACS_EXPECTATIONS: dict[str, dict[str, Any]] = {
    "AU01": {
        "name": AU_NAMES["AU01"],
        "checks": [("brow_inner", {"up": 1.0})],
        "nearby": ("forehead", "glabella", "brow_outer", "upper_eyelid"),
    },
    "AU02": {
        "name": AU_NAMES["AU02"],
        "checks": [("brow_outer", {"up": 1.0})],
        "nearby": ("forehead", "temple", "brow_inner", "upper_eyelid"),
    },
    "AU04": {
        "name": AU_NAMES["AU04"],
        "checks": [("brow_inner", {"down": 1.0, "inward": 0.6})],
        "nearby": ("glabella", "brow_outer", "upper_eyelid", "forehead"),
    },
    "AU05": {"name": AU_NAMES["AU05"], "checks": [("upper_eyelid", {"up": 1.0})], "nearby": ("brow_outer",)},
    "AU06": {
        "name": AU_NAMES["AU06"],
        "checks": [("cheek", {"up": 1.0})],
        "nearby": ("lower_eyelid", "nasolabial", "temple", "face_side"),
    },
    "AU07": {"name": AU_NAMES["AU07"], "checks": [("lower_eyelid", {"up": 1.0})], "nearby": ("upper_eyelid",)},
    "AU09": {
        "name": AU_NAMES["AU09"],
        "checks": [("nose", {"up": 1.0})],
        "nearby": ("glabella", "brow_inner", "nasolabial", "upper_lip", "cheek"),
    },
    "AU10": {
        "name": AU_NAMES["AU10"],
        "checks": [("upper_lip", {"up": 1.0})],
        "nearby": ("nasolabial", "nose", "lip_corner", "cheek"),
    },
    "AU11": {
        "name": AU_NAMES["AU11"],
        "checks": [("nasolabial", {"up": 1.0, "outward": 0.5})],
        "nearby": ("nose", "upper_lip", "cheek", "lip_corner"),
    },
    "AU12": {
        "name": AU_NAMES["AU12"],
        "checks": [("lip_corner", {"up": 1.0, "outward": 1.0})],
        "nearby": ("nasolabial", "cheek", "upper_lip", "lower_lip"),
    },
    "AU14": {
        "name": AU_NAMES["AU14"],
        "checks": [("lip_corner", {"away": 1.0, "inward": 0.3})],
        "nearby": ("upper_lip", "lower_lip", "cheek"),
    },
    "AU15": {
        "name": AU_NAMES["AU15"],
        "checks": [("lip_corner", {"down": 1.0})],
        "nearby": ("lower_lip", "upper_lip", "chin", "jaw"),
    },
    "AU17": {
        "name": AU_NAMES["AU17"],
        "checks": [("chin", {"up": 1.0})],
        "regions": ("chin", "lower_lip"),
        "nearby": ("jaw", "lip_corner"),
    },
    "AU20": {
        "name": AU_NAMES["AU20"],
        "checks": [("lip_corner", {"outward": 1.0})],
        "nearby": ("upper_lip", "lower_lip", "cheek", "jaw"),
    },
    "AU23": {
        "name": AU_NAMES["AU23"],
        "checks": [("lip_corner", {"inward": 1.0})],
        "nearby": ("upper_lip", "lower_lip"),
    },
    "AU24": {
        "name": AU_NAMES["AU24"],
        "checks": [("upper_lip", {"down": 1.0}), ("lower_lip", {"up": 1.0})],
        "nearby": ("lip_corner", "chin"),
    },
    "AU25": {
        "name": AU_NAMES["AU25"],
        "checks": [("lower_lip", {"down": 1.0})],
        "nearby": ("upper_lip", "lip_corner", "chin"),
    },
    "AU26": {
        "name": AU_NAMES["AU26"],
        "checks": [("jaw", {"down": 1.0}), ("lower_lip", {"down": 1.0})],
        "nearby": ("chin", "lip_corner", "face_side"),
    },
    "AU28": {
        "name": AU_NAMES["AU28"],
        "checks": [("upper_lip", {"away": 1.0}), ("lower_lip", {"away": 1.0})],
        "nearby": ("lip_corner", "chin"),
    },
    "AU43": {"name": AU_NAMES["AU43"], "checks": [("upper_eyelid", {"down": 1.0})], "nearby": ("lower_eyelid",)},
}
