"""Synthetic ground truth: FACS-plausible AU displacement fields and a release made of them.

The fields are what ``aumesh synth`` plants in its tables and what the AU-direction check
must recover; ``synthetic_release_arrays`` packs them in the card's NPZ format (a release
whose AU rows are exactly the truth), for tests of the figures and of the direction check.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from aumesh.core.schema import ANCHOR_INDICES, AU_COLUMNS, N_VERTICES, flatten_axis_major, unflatten_axis_major
from aumesh.geometry.face import canonical_template, face_frame, to_face_frame
from aumesh.geometry.landmarks import IRIS_LEFT, IRIS_RIGHT, REGIONS, region_side
from aumesh.model.release import release_arrays

# --------------------------------------------------------------------------- AU fields
# Synthetic FACS ground truth. Each AU is a list of components
#   (region, d_up, d_out, d_away, sigma, gate)
# in inter-ocular units at intensity 1: the region's vertices move by
# (d_out * side, -d_up, d_away) in the face frame (x left, y down, z away), where
# side = +1 for the subject's left region, -1 for right (d_out must be 0 for
# midline regions); every other vertex gets that vector times
# exp(-d^2 / (2 sigma^2)), d = frontal distance to the nearest region vertex.
# gate restricts the falloff to one side of a horizontal line:
#   "above_mouth"/"below_mouth" (mouth line = mean y of 13, 14),
#   "above_eye"/"below_eye" (eye line = mean y of the region's eye corners).
AU_FIELD_SPEC: dict[str, list[tuple[str, float, float, float, float, str | None]]] = {
    "AU01": [(f"brow_inner_{s}", 0.08, 0.0, 0.0, 0.08, "above_eye") for s in ("left", "right")],
    "AU02": [(f"brow_outer_{s}", 0.08, 0.01, 0.0, 0.08, "above_eye") for s in ("left", "right")],
    "AU04": [(f"brow_inner_{s}", -0.06, -0.04, 0.0, 0.08, "above_eye") for s in ("left", "right")],
    "AU05": [(f"upper_eyelid_{s}", 0.04, 0.0, 0.0, 0.05, "above_eye") for s in ("left", "right")],
    "AU06": [
        *[(f"cheek_{s}", 0.06, 0.01, -0.01, 0.10, "below_eye") for s in ("left", "right")],
        *[(f"lower_eyelid_{s}", 0.02, 0.0, 0.0, 0.03, "below_eye") for s in ("left", "right")],
    ],
    "AU07": [
        *[(f"lower_eyelid_{s}", 0.035, 0.0, 0.0, 0.04, "below_eye") for s in ("left", "right")],
        *[(f"upper_eyelid_{s}", -0.01, 0.0, 0.0, 0.03, "above_eye") for s in ("left", "right")],
    ],
    "AU09": [
        *[("nose", 0.05, 0.0, 0.0, 0.06, "above_mouth")],
        *[(f"brow_inner_{s}", -0.02, 0.0, 0.0, 0.06, "above_eye") for s in ("left", "right")],
    ],
    "AU10": [("upper_lip", 0.06, 0.0, -0.01, 0.06, "above_mouth")],
    "AU11": [(f"nasolabial_{s}", 0.035, 0.02, 0.0, 0.06, "above_mouth") for s in ("left", "right")],
    "AU12": [(f"lip_corner_{s}", 0.08, 0.06, 0.0, 0.12, None) for s in ("left", "right")],
    "AU14": [(f"lip_corner_{s}", 0.0, -0.015, 0.05, 0.08, None) for s in ("left", "right")],
    "AU15": [(f"lip_corner_{s}", -0.07, 0.0, 0.0, 0.10, None) for s in ("left", "right")],
    "AU17": [("chin", 0.07, 0.0, -0.02, 0.12, "below_mouth")],
    "AU20": [(f"lip_corner_{s}", -0.01, 0.09, 0.0, 0.10, None) for s in ("left", "right")],
    "AU23": [(f"lip_corner_{s}", 0.0, -0.06, 0.0, 0.08, None) for s in ("left", "right")],
    "AU24": [("upper_lip", -0.03, 0.0, 0.0, 0.05, "above_mouth"), ("lower_lip", 0.03, 0.0, 0.0, 0.05, "below_mouth")],
    "AU25": [("upper_lip", 0.015, 0.0, 0.0, 0.05, "above_mouth"), ("lower_lip", -0.06, 0.0, 0.0, 0.07, "below_mouth")],
    "AU26": [("jaw", -0.15, 0.0, 0.0, 0.30, "below_mouth"), ("lower_lip", -0.05, 0.0, 0.0, 0.08, "below_mouth")],
    "AU28": [("upper_lip", 0.0, 0.0, 0.06, 0.05, "above_mouth"), ("lower_lip", 0.0, 0.0, 0.06, 0.05, "below_mouth")],
    "AU43": [(f"upper_eyelid_{s}", -0.09, 0.0, 0.0, 0.05, "above_eye") for s in ("left", "right")],
}


def _gate(m: np.ndarray, region: str, gate: str | None) -> np.ndarray:
    if gate is None:
        return np.ones(len(m))
    width = 0.003  # steep: the gate line runs through an opening (mouth or eye)
    if gate.endswith("mouth"):
        line = 0.5 * (m[13, 1] + m[14, 1])
    else:
        side = region_side(region)
        corners = (263, 362) if side > 0 else (33, 133) if side < 0 else (33, 263, 133, 362)
        line = m[list(corners), 1].mean()
    s = (m[:, 1] - line) / width  # > 0 below the line (y down)
    s = np.clip(s, -50, 50)
    below = 1.0 / (1.0 + np.exp(-s))
    return below if gate.startswith("below") else 1.0 - below


def facs_displacement_fields(template: np.ndarray | None = None) -> np.ndarray:
    """Synthetic FACS-plausible displacement fields, one per AU, at intensity 1.

    Parameters
    ----------
    template : array-like, shape (478, 3), optional
        Mesh to build the fields on (any orientation/scale; the fields are built
        in its face frame and mapped back). Defaults to :func:`canonical_template`.

    Returns
    -------
    np.ndarray, shape (20, 478, 3), float64
        ``fields[k]`` is the displacement of every vertex for AU
        ``aumesh.core.schema.AU_COLUMNS[k]`` at intensity 1, in the template's own
        orientation and units (inter-ocular units times the template's scale).
        Recipe: :data:`AU_FIELD_SPEC` (smooth Gaussian falloff from each region);
        the iris vertices 468-477 do not move.
    """
    if template is None:
        m = canonical_template()
        axes, scale = np.eye(3), 1.0
    else:
        _, axes, scale = face_frame(template)
        m = to_face_frame(template)
    xy = m[:, :2]
    out = np.zeros((len(AU_COLUMNS), N_VERTICES, 3))
    for k, au in enumerate(AU_COLUMNS):
        for region, d_up, d_out, d_away, sigma, gate in AU_FIELD_SPEC[au]:
            side = region_side(region)
            if side == 0 and d_out != 0.0:
                raise ValueError(f"{au}: midline region {region!r} cannot move outward")
            vec = np.array([d_out * side, -d_up, d_away])
            idx = REGIONS[region]
            d = np.min(np.linalg.norm(xy[:, None, :] - xy[idx][None, :, :], axis=2), axis=1)
            w = np.exp(-(d**2) / (2.0 * sigma**2)) * _gate(m, region, gate)
            w[idx] = 1.0
            out[k] += w[:, None] * vec[None, :]
    out[:, list(IRIS_RIGHT + IRIS_LEFT)] = 0.0  # irises are not moved by facial AUs
    return out @ axes * scale


def synthetic_release_arrays(template: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Release-NPZ-shaped arrays whose AU rows are exactly the synthetic FACS fields.

    Parameters
    ----------
    template : array-like, shape (478, 3), optional
        Neutral mesh (any orientation/units). Defaults to :func:`canonical_template`.

    Returns
    -------
    dict
        The card's keys: ``coef`` (23, 1434) float32 with rows
        ``flatten_axis_major(facs_displacement_fields(template))`` for the AUs and
        zeros for Pitch/Yaw/Roll; ``intercept`` (1434,) = the flattened template;
        ``input_columns``, ``au_columns``, ``pose_columns``, ``mean_aligned_mesh``,
        ``mean_low_au_mesh``, ``reference_anchors`` (12, 3), ``anchor_indices``
        (12,), ``n_components`` (), ``model_card`` (), ``training_metadata`` () JSON.
        Pass to ``np.savez(path, **arrays)`` to get a synthetic-truth release.
    """
    t = canonical_template() if template is None else np.asarray(template, dtype=np.float64)
    fields = facs_displacement_fields(None if template is None else t)
    anchors = np.asarray(ANCHOR_INDICES, dtype=np.int32)
    reference = {
        "mean_aligned_mesh": t,
        "mean_low_au_mesh": t,
        "reference_anchors": t[anchors],
        "anchor_indices": anchors,
    }
    return release_arrays(
        flatten_axis_major(fields).T,
        flatten_axis_major(t),
        list(AU_COLUMNS),
        len(AU_COLUMNS),
        reference,
        "aumesh synthetic-truth release: coef rows = aumesh.geometry.face.facs_displacement_fields",
        {"source": "aumesh.geometry.face.synthetic_release_arrays"},
    )


def au_field_cosines(
    coef: np.ndarray, feature_columns: list[str], truth: Mapping[str, np.ndarray], reference_anchors: np.ndarray
) -> np.ndarray:
    """Cosine between each fitted AU field and the true one (``aumesh synth --truth``), per AU.

    The truth lives in the generator's canonical frame; it is mapped into the fitted model's aligned frame
    by the similarity (Umeyama) that takes the template's anchors onto ``reference_anchors``.

    Parameters
    ----------
    coef : ndarray, shape (1434, p)
        Fitted coefficients (scikit-learn's layout), columns named by ``feature_columns``.
    truth : mapping
        The truth NPZ: ``au_fields`` (20, 1434) axis-major, ``template_px``, ``anchor_indices``.
    reference_anchors : ndarray, shape (12, 3)
        The prepared data's Procrustes reference anchors.

    Returns
    -------
    ndarray, shape (20,)
        ``aumesh.core.schema.AU_COLUMNS`` order.
    """
    from aumesh.geometry.align import umeyama_batch

    anchors = np.asarray(truth["template_px"], dtype=np.float64)[np.asarray(truth["anchor_indices"])]
    R, _, _ = umeyama_batch(anchors[None], np.asarray(reference_anchors, dtype=np.float64))
    true = flatten_axis_major(unflatten_axis_major(np.asarray(truth["au_fields"], dtype=np.float64)) @ R[0].T)
    est = np.asarray(coef, dtype=np.float64)[:, [list(feature_columns).index(a) for a in AU_COLUMNS]].T
    return np.einsum("kj,kj->k", est, true) / (np.linalg.norm(est, axis=1) * np.linalg.norm(true, axis=1))
