"""The release's arrays: the card's NPZ (its text is :mod:`aumesh.card.model_card`).

Card, "File format": ``coef`` (23, 1434) float32 with rows ``AU01..AU43, Pitch, Yaw, Roll``;
``intercept`` (1434,) float32; axis-major layout; loads with ``np.load(path, allow_pickle=False)``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.core.io import read_npz
from aumesh.core.schema import AU_COLUMNS, INPUT_COLUMNS, N_TARGETS, POSE_COLUMNS
from aumesh.geometry.frame import canonical_frame, rotate_axis_major, to_canonical
from aumesh.model import support

NPZ_NAME = "au_to_mesh_pls.npz"
CARD_JSON = "model_card.json"
CARD_MD = "MODEL_CARD.md"


#: the fix for a damaged release NPZ: the tracked copy (DVC's cache or remote), else rebuilt
RELEASE_FIX = "`dvc pull --force release` (the tracked copy) or `dvc repro release` (rebuild it)"


def load_npz(path: str | Path) -> dict[str, np.ndarray]:
    """All arrays of a release NPZ, read without pickle (the card's loader); no validation here. A damaged file
    (truncated, CRC error, not a zip) is an :class:`aumesh.core.errors.CorruptFileError` naming it and
    :data:`RELEASE_FIX`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"release NPZ not found: {path}")
    return read_npz(path, fix=RELEASE_FIX, what="not a release NPZ")


def _input_rows(coef: np.ndarray, feature_columns: list[str]) -> np.ndarray:
    """The 23 ``input_columns`` rows (AU + pose) of ``coef`` (1434, p), by name; a design without pose gets zero pose
    rows (the model ignores pose), so the format never changes."""
    by_name = {c: coef[:, j] for j, c in enumerate(feature_columns)}
    return np.stack([by_name.get(c, np.zeros(N_TARGETS)) for c in INPUT_COLUMNS])


def release_arrays(
    coef: np.ndarray,
    intercept: np.ndarray,
    feature_columns: list[str],
    n_components: int,
    reference: dict[str, np.ndarray],
    card_text: str,
    metadata: dict[str, Any],
    uncorrected_coef: np.ndarray | None = None,
    identification: dict[str, np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """The NPZ's arrays, exactly the card's keys and dtypes (+ ``coef_full`` when trained with interactions).

    Every geometric array is expressed in the card's canonical frame (x subject's left, y up, z out of the
    face; :func:`aumesh.geometry.frame.canonical_frame` of ``reference["mean_aligned_mesh"]``): a proper
    rotation plus a translation of the aligned frame, applied here, at the one place every NPZ is made, so
    training and CV metrics stay in the aligned frame and the released model predicts the rotated meshes
    exactly (``x @ coef' + intercept' == ((x @ coef + intercept) - origin) @ R.T`` per vertex).

    Parameters
    ----------
    coef : ndarray, shape (1434, p)
        Raw-input coefficients (scikit-learn ``coef_`` layout) for ``feature_columns``.
    intercept : ndarray, shape (1434,)
        True intercept for raw inputs, yielding a mesh (aligned frame).
    feature_columns : list of str, length p
        The training design's columns (20, 23 or 83).
    reference : dict
        ``reference_anchors`` (12, 3), ``anchor_indices`` (12,), ``mean_aligned_mesh`` and
        ``mean_low_au_mesh`` (478, 3), from the prepare stage (aligned frame).
    metadata : dict
        ``training_metadata`` (the card JSON). When its ``data.input_ranges`` is recorded, the NPZ also gets
        ``feature_p99`` (23,) float32 (each input's training p99, ``input_columns`` order) and
        ``unsupported_features`` (k,) str (the AUs the data never expressed, :mod:`aumesh.model.support`; shape (0,)
        when none), py-feat's names.
    uncorrected_coef : ndarray, shape (1434, p), optional
        A fit corrected for detector noise (``model/eiv``) writes the card's uncorrected fit on the same rows beside it:
        ``coef_uncorrected`` (23, 1434) (and ``coef_full_uncorrected`` with interactions), the same frame and layout.
    identification : dict, optional
        The AU identification screen's ``au_identification_*`` arrays (:meth:`aumesh.model.eiv.IdentificationScreen.
        release_arrays`), copied as they are.
    """
    coef = np.asarray(coef, dtype=np.float64)
    if coef.shape != (N_TARGETS, len(feature_columns)):
        raise ValueError(f"coef has shape {coef.shape}, expected ({N_TARGETS}, {len(feature_columns)})")
    coef23 = _input_rows(coef, feature_columns)
    rotation, origin = canonical_frame(reference["mean_aligned_mesh"])

    def mesh(key: str) -> np.ndarray:
        return to_canonical(reference[key], rotation, origin).astype(np.float32)

    arrays = {
        "coef": rotate_axis_major(coef23, rotation).astype(np.float32),
        "intercept": rotate_axis_major(intercept, rotation, origin).astype(np.float32),
        "input_columns": np.array(INPUT_COLUMNS),
        "au_columns": np.array(AU_COLUMNS),
        "pose_columns": np.array(POSE_COLUMNS),
        "mean_aligned_mesh": mesh("mean_aligned_mesh"),
        "mean_low_au_mesh": mesh("mean_low_au_mesh"),
        "reference_anchors": mesh("reference_anchors"),
        "anchor_indices": np.asarray(reference["anchor_indices"], dtype=np.int32),
        "n_components": np.array(n_components, dtype=np.int32),
        "model_card": np.array(card_text),
        "training_metadata": np.array(json.dumps(metadata, sort_keys=True, default=str)),
    }
    ranges = (metadata.get("data") or {}).get("input_ranges") if isinstance(metadata.get("data"), dict) else None
    if ranges:
        # py-feat's keys (feat/plotting.py: PLSFeatMeshModel's feature_max is the NPZ's feature_p99, its
        # unsupported_features the inputs the detector never expressed): the data's support, readable without aumesh
        arrays["feature_p99"] = support.feature_p99(ranges)
        arrays["unsupported_features"] = np.array(support.unsupported_inputs(ranges), dtype=str).reshape(-1)
    if len(feature_columns) > len(INPUT_COLUMNS):
        # pose x AU interactions: the full design keeps pose-conditioned prediction exact:
        # flat = x_full @ coef_full + intercept, x_full = [AU | pose | pose x AU] (pose-major products)
        arrays["coef_full"] = rotate_axis_major(coef.T, rotation).astype(np.float32)
        arrays["input_columns_full"] = np.array(feature_columns)
    if uncorrected_coef is not None:
        raw = np.asarray(uncorrected_coef, dtype=np.float64)
        arrays["coef_uncorrected"] = rotate_axis_major(_input_rows(raw, feature_columns), rotation).astype(np.float32)
        if len(feature_columns) > len(INPUT_COLUMNS):
            arrays["coef_full_uncorrected"] = rotate_axis_major(raw.T, rotation).astype(np.float32)
    for key, value in (identification or {}).items():
        arrays[key] = np.asarray(value)
    return arrays
