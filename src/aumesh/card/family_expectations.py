"""What each input of the blendshape and emotion families should do to the face, for :mod:`aumesh.card.family_directions`.

Data only (issue 46, item 4). Areas are :data:`aumesh.geometry.landmarks.AREA_SEEDS` names: a group name
(``"upper_eyelid"``: both sides, "outward" taken on each side) or a sided name (``"upper_eyelid_left"``: the
**subject's** left, docs/conventions.md "The frame"); terms are :data:`aumesh.card.facs_regions.FACE_TERMS`
(``left``/``right`` = the subject's, for midline areas).

Blendshapes: MediaPipe's 52 ARKit-style names in py-feat 2.1.5's ``MP_BLENDSHAPE_NAMES`` order
(``feat/utils/__init__.py``; names only). Meanings follow Apple's ARKit ``ARFaceAnchor.BlendShapeLocation``
descriptions (e.g. eyeBlinkLeft "closure of the eyelids over the left eye", eyeLookInLeft "consistent with a rightward
gaze", i.e. toward the nose) and their FACS counterparts (browInnerUp ~ AU01, browDown ~ AU04, eyeWide ~ AU05,
cheekSquint ~ AU06, eyeSquint ~ AU07, noseSneer ~ AU09, mouthUpperUp ~ AU10, mouthSmile ~ AU12, mouthDimple ~ AU14,
mouthFrown ~ AU15, mouthShrugLower ~ AU17, mouthStretch ~ AU20, jawOpen ~ AU26). An entry is either a list of checks
``(area, {term: weight})`` or, for a blendshape with no unambiguous motion on a 478-vertex mesh, a string: the
reason it is left unchecked.

Emotions: py-feat's ``FEAT_EMOTION_COLUMNS`` order. Each prototype is the gross motion of the emotion's EMFACS
prototype (Friesen & Ekman, EMFACS-7, 1983; the AU combinations in the comments), checked as (area, direction): the
prototypes only need to tell the seven apart, which is what catches a permuted column labelling
(py-feat's ``emotion_to_mesh_pls_v5``, ``feat/plotting.py``).
"""

from __future__ import annotations

from typing import Any

Checks = list[tuple[str, dict[str, float]]]


def _sided(name: str, checks: Checks) -> dict[str, Checks]:
    """``name + "Left"`` / ``"Right"`` -> the checks with ``{side}`` filled in (subject's left / right)."""
    return {
        f"{name}{side.capitalize()}": [(area.format(side=side), dict(terms)) for area, terms in checks]
        for side in ("left", "right")
    }


BLENDSHAPE_EXPECTATIONS: dict[str, Checks | str] = {
    "_neutral": "the detector's neutral score: no motion of its own",
    **_sided("browDown", [("brow_inner_{side}", {"down": 1.0})]),
    "browInnerUp": [("brow_inner", {"up": 1.0})],
    **_sided("browOuterUp", [("brow_outer_{side}", {"up": 1.0})]),
    "cheekPuff": [("cheek", {"outward": 1.0, "toward": 1.0})],
    **_sided("cheekSquint", [("cheek_{side}", {"up": 1.0})]),
    **_sided("eyeBlink", [("upper_eyelid_{side}", {"down": 1.0})]),
    **_sided("eyeLookDown", [("iris_{side}", {"down": 1.0})]),
    **_sided("eyeLookIn", [("iris_{side}", {"inward": 1.0})]),
    **_sided("eyeLookOut", [("iris_{side}", {"outward": 1.0})]),
    **_sided("eyeLookUp", [("iris_{side}", {"up": 1.0})]),
    **_sided("eyeSquint", [("lower_eyelid_{side}", {"up": 1.0})]),
    **_sided("eyeWide", [("upper_eyelid_{side}", {"up": 1.0})]),
    "jawForward": [("jaw", {"toward": 1.0})],
    "jawLeft": [("jaw", {"left": 1.0})],
    "jawOpen": [("jaw", {"down": 1.0})],
    "jawRight": [("jaw", {"right": 1.0})],
    "mouthClose": "closes the lips against jawOpen (ARKit pairs them): alone its motion depends on the jaw",
    **_sided("mouthDimple", [("lip_corner_{side}", {"away": 1.0, "inward": 0.3})]),
    **_sided("mouthFrown", [("lip_corner_{side}", {"down": 1.0})]),
    "mouthFunnel": [("upper_lip", {"toward": 1.0}), ("lower_lip", {"toward": 1.0})],
    "mouthLeft": [("upper_lip", {"left": 1.0}), ("lower_lip", {"left": 1.0})],
    **_sided("mouthLowerDown", [("lower_lip", {"down": 1.0})]),
    **_sided("mouthPress", [("lower_lip", {"up": 1.0})]),
    "mouthPucker": [("lip_corner", {"inward": 1.0, "toward": 0.5})],
    "mouthRight": [("upper_lip", {"right": 1.0}), ("lower_lip", {"right": 1.0})],
    "mouthRollLower": [("lower_lip", {"away": 1.0})],
    "mouthRollUpper": [("upper_lip", {"away": 1.0})],
    "mouthShrugLower": [("chin", {"up": 1.0})],
    "mouthShrugUpper": "ARKit's 'outward movement of the upper lip': raised or protruded by rig, no one direction",
    **_sided("mouthSmile", [("lip_corner_{side}", {"up": 1.0, "outward": 1.0})]),
    **_sided("mouthStretch", [("lip_corner_{side}", {"outward": 1.0})]),
    **_sided("mouthUpperUp", [("upper_lip", {"up": 1.0})]),
    **_sided("noseSneer", [("nose", {"up": 1.0})]),
}
# eyeLook* are checked on the iris vertices (468-477), which MediaPipe's refined mesh places on the tracked iris.

EMOTION_PROTOTYPES: dict[str, Checks] = {
    # anger: AU4+5+7+23 - brows lowered and drawn together, lids tightened, lips pressed
    "anger": [
        ("brow_inner", {"down": 1.0, "inward": 0.6}),
        ("lower_eyelid", {"up": 1.0}),
        ("lip_corner", {"inward": 1.0}),
    ],
    # disgust: AU9 or AU10 (+15/16/17/26 by variant: EMFACS-7's disgust prototypes 9, 9+16+15+26, 9+17, 10, ...) -
    # the nose wrinkled and the infraorbital triangle / nasolabial furrow raised, which every variant shares; the
    # lips are not checked (AU10 raises the upper lip, AU15/16/26 lower the corners or the lower lip)
    "disgust": [("nose", {"up": 1.0}), ("nasolabial", {"up": 1.0})],
    # fear: AU1+2+4+5+7+20+26 - brows raised, upper lids raised, lips stretched, jaw dropped
    "fear": [
        ("brow_inner", {"up": 1.0}),
        ("brow_outer", {"up": 1.0}),
        ("upper_eyelid", {"up": 1.0}),
        ("lip_corner", {"outward": 1.0}),
        ("jaw", {"down": 0.5}),
    ],
    # happiness: AU6+12 - cheeks raised, lip corners up and back
    "happiness": [("cheek", {"up": 1.0}), ("lip_corner", {"up": 1.0, "outward": 1.0})],
    # sadness: AU1+4+15 - inner brows raised, lip corners lowered
    "sadness": [("brow_inner", {"up": 1.0, "inward": 0.5}), ("lip_corner", {"down": 1.0})],
    # surprise: AU1+2+5+26 - brows raised, upper lids raised, jaw dropped
    "surprise": [
        ("brow_inner", {"up": 1.0}),
        ("brow_outer", {"up": 1.0}),
        ("upper_eyelid", {"up": 1.0}),
        ("jaw", {"down": 1.0}),
    ],
    # neutral: no motion of its own (with probabilities summing to 1 its coef row is minus the others' mean)
    "neutral": [],
}


def blendshape_checks() -> dict[str, Checks]:
    """The checked blendshapes (those with an expected motion), in ``MP_BLENDSHAPE_NAMES`` order."""
    return {k: v for k, v in BLENDSHAPE_EXPECTATIONS.items() if not isinstance(v, str)}


def unchecked_blendshapes() -> dict[str, str]:
    """The blendshapes left unchecked -> the reason."""
    out: dict[str, Any] = {k: v for k, v in BLENDSHAPE_EXPECTATIONS.items() if isinstance(v, str)}
    return out
