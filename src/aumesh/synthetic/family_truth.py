"""Synthetic ground truth for the blendshape and emotion families (issue 46): a known linear field per input.

Each blendshape and each emotion moves the canonical face by a fixed displacement field at value 1, built from the
AU fields :func:`aumesh.synthetic.tables.true_coefficients` plants (so the fields are FACS-plausible and share the AU
truth's frame, pixels and rigid anchors):

* a blendshape follows one AU (:data:`BLENDSHAPE_AU`, by the shape's meaning: ``mouthSmileLeft`` is AU12,
  ``jawOpen`` AU26, ``eyeBlinkLeft`` AU43, ...); a ``...Left`` shape moves only the subject's left half of the face
  (the AU field times a smooth weight across the midline), ``...Right`` the right half, so a Left/Right pair sums to
  the AU's field. The shapes not in the table (gaze, ``cheekPuff``, ``jawLeft``, ``_neutral``, ...) move nothing:
  their truth is the zero field (what a fit should leave near zero and py-feat calls ``unsupported_features``);
* an emotion is its prototypical AUs' fields summed (:data:`EMOTION_AUS`, after Ekman & Friesen's EMFACS
  prototypes: happiness AU06 + AU12, surprise AU01 + AU02 + AU05 + AU26, ...); ``neutral`` is the zero field. The
  probabilities sum to 1, so only differences from neutral are identifiable: with neutral's field zero, each
  emotion's field is its difference from neutral.

With ``write_pyfeat_tables(..., family_truth=True)`` each main face's blendshapes and emotions are drawn from their
own random stream, independently of the AUs, and its mesh moves by ``blendshapes @ fields + emotions @ fields`` on
top of the AU expression: a fit of the mesh on one family's columns then has that family's fields as its
expectation (the AU expression is independent noise to it). Off (the default), nothing is drawn or moved.
"""

from __future__ import annotations

import numpy as np

from aumesh.core.families import BLENDSHAPE_COLUMNS, EMOTION_COLUMNS
from aumesh.core.schema import AU_COLUMNS, N_VERTICES

#: Blendshape -> the AU it follows (its meaning, MediaPipe/ARKit's description of the shape). The synthetic tables'
#: default blendshapes follow the same AUs loosely (:func:`aumesh.synthetic.pyfeat_faces._blendshapes`).
BLENDSHAPE_AU: dict[str, str] = {
    "browInnerUp": "AU01",
    "browOuterUpLeft": "AU02",
    "browOuterUpRight": "AU02",
    "browDownLeft": "AU04",
    "browDownRight": "AU04",
    "eyeWideLeft": "AU05",
    "eyeWideRight": "AU05",
    "cheekSquintLeft": "AU06",
    "cheekSquintRight": "AU06",
    "eyeSquintLeft": "AU07",
    "eyeSquintRight": "AU07",
    "noseSneerLeft": "AU09",
    "noseSneerRight": "AU09",
    "mouthUpperUpLeft": "AU10",
    "mouthUpperUpRight": "AU10",
    "mouthSmileLeft": "AU12",
    "mouthSmileRight": "AU12",
    "mouthDimpleLeft": "AU14",
    "mouthDimpleRight": "AU14",
    "mouthFrownLeft": "AU15",
    "mouthFrownRight": "AU15",
    "mouthShrugLower": "AU17",
    "mouthStretchLeft": "AU20",
    "mouthStretchRight": "AU20",
    "mouthPressLeft": "AU24",
    "mouthPressRight": "AU24",
    "jawOpen": "AU26",
    "mouthRollLower": "AU28",
    "eyeBlinkLeft": "AU43",
    "eyeBlinkRight": "AU43",
}

#: Emotion -> its prototypical AUs (EMFACS prototypes, restricted to the 20 AUs py-feat detects).
EMOTION_AUS: dict[str, tuple[str, ...]] = {
    "anger": ("AU04", "AU05", "AU07", "AU23"),
    "disgust": ("AU09", "AU15"),
    "fear": ("AU01", "AU02", "AU04", "AU05", "AU20", "AU26"),
    "happiness": ("AU06", "AU12"),
    "sadness": ("AU01", "AU04", "AU15"),
    "surprise": ("AU01", "AU02", "AU05", "AU26"),
    "neutral": (),
}

_MIDLINE_WIDTH = 0.03  # IOD: how sharply a one-sided shape's weight falls across the face's midline


def side_weight(template: np.ndarray) -> np.ndarray:
    """(478,) weight of the subject's left half of ``template`` (any orientation): 1 on the left, 0 on the right,
    a logistic of the face-frame x (x points to the subject's left, ``aumesh.geometry.face.to_face_frame``)."""
    from aumesh.geometry.face import to_face_frame

    x = to_face_frame(np.asarray(template, dtype=np.float64))[:, 0]
    return 1.0 / (1.0 + np.exp(-np.clip(x / _MIDLINE_WIDTH, -50, 50)))


def family_fields(au_fields: np.ndarray, template: np.ndarray) -> dict[str, np.ndarray]:
    """Each blendshape's and each emotion's displacement field at value 1.

    Parameters
    ----------
    au_fields : ndarray, shape (20, 1434)
        The AU fields, axis-major ``[x | y | z]``, in ``AU_COLUMNS`` order (``true_coefficients(spec)[0][:20]``).
    template : ndarray, shape (478, 3)
        The face the fields live on (for the midline), same frame as ``au_fields``.

    Returns
    -------
    dict
        ``"blendshapes"``: (52, 1434) in ``BLENDSHAPE_COLUMNS`` order; ``"emotions"``: (7, 1434) in
        ``EMOTION_COLUMNS`` order; axis-major, the units of ``au_fields``.
    """
    au = np.asarray(au_fields, dtype=np.float64)
    if au.shape != (len(AU_COLUMNS), 3 * N_VERTICES):
        raise ValueError(f"au_fields must be ({len(AU_COLUMNS)}, {3 * N_VERTICES}), got {au.shape}")
    left = np.tile(side_weight(template), 3)  # axis-major: the same weight for x, y and z of a vertex
    bs = np.zeros((len(BLENDSHAPE_COLUMNS), 3 * N_VERTICES))
    for k, name in enumerate(BLENDSHAPE_COLUMNS):
        if name in BLENDSHAPE_AU:
            field = au[AU_COLUMNS.index(BLENDSHAPE_AU[name])]
            weight = left if name.endswith("Left") else 1.0 - left if name.endswith("Right") else 1.0
            bs[k] = weight * field
    emo = np.zeros((len(EMOTION_COLUMNS), 3 * N_VERTICES))
    for k, name in enumerate(EMOTION_COLUMNS):
        for a in EMOTION_AUS[name]:
            emo[k] += au[AU_COLUMNS.index(a)]
    return {"blendshapes": bs, "emotions": emo}


def draw_family_values(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` frames' blendshapes (n, 52) in [0, 1] (mostly small, as MediaPipe's are) and emotions (n, 7), a softmax
    in ``EMOTION_COLUMNS`` order with neutral the likeliest, as both of py-feat's detectors write them; independent of
    each other and of everything else."""
    blend = rng.beta(0.6, 3.0, size=(n, len(BLENDSHAPE_COLUMNS)))
    logits = rng.normal(0.0, 1.0, size=(n, len(EMOTION_COLUMNS)))
    logits[:, EMOTION_COLUMNS.index("neutral")] += 1.0
    p = np.exp(logits - logits.max(axis=1, keepdims=True))
    return blend, p / p.sum(axis=1, keepdims=True)


def family_truth_fields(au_coef: np.ndarray, intercept: np.ndarray) -> dict[str, np.ndarray]:
    """:func:`family_fields` on a synthetic spec's AU truth, in pixels of the canonical template.

    Parameters
    ----------
    au_coef : ndarray, shape (>= 20, 1434)
        The truth's rows (:func:`aumesh.synthetic.tables.true_coefficients`: ``spec.reversed_aus`` reverse the shapes
        built on them); the first 20 are the AU fields.
    intercept : ndarray, shape (1434,)
        The template mesh, axis-major pixels.
    """
    from aumesh.core.schema import unflatten_axis_major

    return family_fields(np.asarray(au_coef)[: len(AU_COLUMNS)], unflatten_axis_major(intercept))


def family_truth_arrays(au_coef: np.ndarray, intercept: np.ndarray) -> dict[str, np.ndarray]:
    """The family truth of tables written with ``family_truth=True`` (AU truth ``au_coef``, ``intercept``: as
    :func:`family_truth_fields`), for ``np.savez``: ``blendshape_fields`` (52, 1434) and ``emotion_fields`` (7, 1434)
    axis-major pixels, ``blendshape_columns``, ``emotion_columns``, and, as in the AU truth NPZ (``aumesh synth
    --truth``), ``template_px`` (478, 3) and ``anchor_indices`` (12,), for mapping the fields into a fitted model's
    aligned frame (:func:`aumesh.synthetic.truth.au_field_cosines`' way)."""
    from aumesh.core.schema import ANCHOR_INDICES, unflatten_axis_major

    fields = family_truth_fields(au_coef, intercept)
    return {
        "blendshape_fields": fields["blendshapes"],
        "emotion_fields": fields["emotions"],
        "blendshape_columns": np.array(BLENDSHAPE_COLUMNS),
        "emotion_columns": np.array(EMOTION_COLUMNS),
        "template_px": unflatten_axis_major(intercept),
        "anchor_indices": np.asarray(ANCHOR_INDICES, dtype=np.int32),
    }


def family_source(spec):
    """What ``aumesh synth --families`` writes (:class:`aumesh.synthetic.tables.FamilySource`): the fields of
    :func:`family_truth_fields`, :func:`draw_family_values` for each video's values, and the truth NPZ's family keys
    (:func:`family_truth_arrays` without ``template_px`` and ``anchor_indices``, which the AU truth already holds: the
    same arrays)."""
    from aumesh.synthetic import tables as synth

    coef, intercept, _ = synth.true_coefficients(spec)
    truth = {
        k: v for k, v in family_truth_arrays(coef, intercept).items() if k not in ("template_px", "anchor_indices")
    }
    return synth.FamilySource(family_truth_fields(coef, intercept), draw_family_values, truth)
