"""Predicting meshes from AUs (+ head pose) with a release: the card's inference snippet.

``load_release`` (:mod:`aumesh.model.release_check`, which loads and checks a release) and ``predict_mesh`` are
exported at the top (``aumesh.load_release``, ``aumesh.predict_mesh``); they are the one way the project itself
predicts (figures, CLI).

The computation is the card's inference snippet, ``flat = x @ coef + intercept`` with
``x = [20 AUs | Pitch, Yaw, Roll]`` and the axis-major layout ``[x_0..x_477 | y_.. | z_..]``
(see ``docs/conventions.md``). When the release has ``coef_full`` (trained with pose x AU
interactions), ``x_full = [AUs | pose | pose x AU]`` (pose-major products) and
``flat = x_full @ coef_full + intercept``: pose-conditioned prediction is exact, and at pose 0
it equals the 23-row ``coef``.

Inputs are checked before any arithmetic (:mod:`aumesh.model.input_checks`): unknown AU names (with the closest
input name), wrong lengths, partly NaN rows, AUs above py-feat's 0..1 in a detector's table and pose that looks like
degrees are errors (:class:`aumesh.model.input_columns.PredictionInputError`) that say what was expected; pose beyond
the training range is a warning (:class:`aumesh.model.input_checks.InputRangeWarning`). A whole detector table
(py-feat's Fex output, CSV or parquet, MPDetector or Detectorv2) is taken as it is: the AU and pose columns are picked
by name (:mod:`aumesh.model.input_columns`), and a frame without a face gets a NaN mesh.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from aumesh.core.schema import POSE_COLUMNS, unflatten_axis_major
from aumesh.model.input_checks import input_rows
from aumesh.model.release_check import Release, ReleaseError, ReleaseSource, _names


def predict_mesh(release: ReleaseSource, aus: Any = None, pose: Any = None, *, strict: bool = False) -> np.ndarray:
    """Predict face meshes from AU intensities (and head pose) with a release.

    Parameters
    ----------
    release : str, path-like or mapping
        A release NPZ path or its loaded arrays (:func:`load_release`; load once when predicting
        many times). A family release (issue 46: ``releases/blendshapes/bs_to_mesh_pls.npz``,
        ``releases/emotions/emotion_to_mesh_pls.npz``, or py-feat's own NPZs of that format) takes its family's
        inputs instead of the AUs, by the same rules: an array in its ``feature_columns`` order ((k,), (N, k), or
        (k + 3,) / (N, k + 3) with pose), a mapping or a DataFrame by name (Detectorv2's ``Happy`` is
        ``happiness``; a whole py-feat table must hold every input of the family), its pose x input terms used,
        and the warnings beyond its ``feature_p99`` and for its ``unsupported_features`` said in the family's
        names (:mod:`aumesh.model.family_inference`).
    aus : array-like, mapping, DataFrame or None
        AU intensities on py-feat's 0..1 scale (the training tables'):

        - array of shape (20,) or (N, 20) in the release's ``au_columns`` order
          (``AU01, AU02, AU04, ..., AU43``), or (23,) / (N, 23) with ``Pitch, Yaw, Roll`` appended
          (the card's ``input_columns``);
        - mapping ``{"AU12": 1.0}``: one row, AUs not named are 0;
        - pandas DataFrame (or a subclass, such as py-feat's ``Fex``), one mesh per row, columns
          taken by name:

          * only input columns (AUs, optionally ``Pitch``, ``Yaw``, ``Roll``): AUs not named are 0;
          * a whole table, with other columns too (py-feat's detector output, MPDetector or
            Detectorv2: face boxes, landmarks, mesh, emotions, identity, ``input``, ``frame``, ...):
            the other columns are ignored; all 20 AUs must be there, and ``Pitch``, ``Yaw``,
            ``Roll`` all or none (none: pose 0); an AU above 1 is an error (0..5 is OpenFace's
            scale: divide by 5);
        - None: all AUs 0 (the model's neutral face).

        Unknown names (``strict``) and missing ones (whole table) are errors naming the column and
        the closest name (``did you mean 'AU12'?``). Given as numbers (array, mapping, input columns),
        an AU above 1 is a warning.
    pose : array-like of shape (3,) or (N, 3), mapping, or None
        Head pose in **radians**, in the order **Pitch, Yaw, Roll** (py-feat's tables store
        Pitch, Roll, Yaw: select by name). Default 0 (frontal, the usual use: rotate the
        predicted mesh afterwards to show another view). One row applies to every AU row.
        Values above pi/2 in magnitude are refused as degrees; Pitch or Yaw beyond the training
        range (:func:`aumesh.model.input_checks.training_pose_limits`) is a warning.
    strict : bool, keyword-only
        True: every DataFrame column must be an input name (the behaviour before whole tables were
        taken). Default False.

    Returns
    -------
    np.ndarray, float64
        Shape (478, 3) for one row (1-D array, mapping, None), (N, 478, 3) for a batch
        (2-D array or DataFrame), in the release's frame and units (the card's canonical
        frame; see ``docs/conventions.md``). A row without a face (``FaceScore`` 0, or every AU
        and pose value NaN: py-feat's row for a frame where it found none) gets a mesh of NaN;
        ``np.isnan(meshes).all(axis=(1, 2))`` flags them. A row only partly NaN is an error.

    Raises
    ------
    FileNotFoundError, ReleaseError
        From :func:`load_release`.
    PredictionInputError
        Unknown or missing names, wrong lengths (the message lists the expected columns), a partly
        NaN row (the message names the row and the column), pose that looks like degrees, an AU
        above 1 in a whole table.

    Warns
    -----
    InputRangeWarning
        One line a call: Pitch or Yaw beyond the training range; an AU above 1 given as numbers; an AU above
        the largest value the training data had (named with the largest value given, the training max and p99);
        an AU the training data never expressed (training p99 below 0.05, the release's
        ``unsupported_features``) given above 0.02, py-feat's rule (:mod:`aumesh.model.support`). Releases that
        record no ranges are checked for pose and the 0..1 scale only.
    NoFaceWarning
        One line a call when rows without a face were given: their number (``aus: 3 of 40 row(s) without a face``);
        their meshes are NaN.

    Notes
    -----
    ``flat = x @ coef + intercept`` with ``x = [AUs | Pitch, Yaw, Roll]``, unflattened from the
    axis-major layout; with ``coef_full`` (pose x AU interactions) the full design
    ``[AUs | pose | pose x AU]`` is used, so non-zero pose is exact (pose-conditioned prediction).

    Examples
    --------
    >>> import aumesh
    >>> m = aumesh.load_release("release/au_to_mesh_pls.npz")  # doctest: +SKIP
    >>> smile = aumesh.predict_mesh(m, {"AU12": 1.0})             # doctest: +SKIP
    >>> smile.shape                                               # doctest: +SKIP
    (478, 3)
    >>> fex = pd.read_csv("video.csv")   # py-feat's detector output  # doctest: +SKIP
    >>> meshes = aumesh.predict_mesh(m, fex)  # (len(fex), 478, 3)     # doctest: +SKIP
    """
    from aumesh.model import family_inference

    arrays = family_inference.load_any_release(release)
    if family_inference.release_family(arrays) != "au":  # a blendshape or emotion release (issue 46)
        x, pose_rows, single = family_inference.family_input_rows(arrays, aus, pose, strict=strict)
        meshes = predict_rows(family_inference.au_view(arrays), x, pose_rows)
        return meshes[0] if single else meshes
    au, pose_rows, single = input_rows(arrays, aus, pose, strict=strict)
    meshes = predict_rows(arrays, au, pose_rows)
    return meshes[0] if single else meshes


def predict_rows(release: Release, au: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Meshes of rows already checked by :func:`aumesh.model.input_checks.input_rows` (no check here).

    Parameters
    ----------
    release : mapping
        Release arrays (:func:`load_release`).
    au : np.ndarray, shape (N, 20)
        AUs in ``au_columns`` order; a row of NaN (no face) gives a mesh of NaN.
    pose : np.ndarray, shape (N, 3)
        Pitch, Yaw, Roll in radians.

    Returns
    -------
    np.ndarray, shape (N, 478, 3), float64
    """
    return unflatten_axis_major(_linear(release, au, pose))


def _linear(arrays: Release, au: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(N, 1434) = design @ coef + intercept, rows by name (AU order of ``au_columns``)."""
    values = {name: au[:, j] for j, name in enumerate(_names(arrays["au_columns"]))}
    values.update({name: pose[:, j] for j, name in enumerate(POSE_COLUMNS)})
    if "coef_full" in arrays:
        names, coef = _names(arrays["input_columns_full"]), arrays["coef_full"]
    else:
        names, coef = _names(arrays["input_columns"]), arrays["coef"]
    x = np.stack([_column(values, name) for name in names], axis=1)
    return x @ np.asarray(coef, dtype=np.float64) + np.asarray(arrays["intercept"], dtype=np.float64)


def _column(values: Mapping[str, np.ndarray], name: str) -> np.ndarray:
    """A design column: an input, or a pose x AU product named ``Pitch*AU01``."""
    if name in values:
        return values[name]
    left, _, right = name.partition("*")
    if left in values and right in values:
        return values[left] * values[right]
    raise ReleaseError(f"release column {name!r} is neither an input ({', '.join(values)}) nor a product 'Pose*AU'")


__all__ = ["predict_mesh", "predict_rows"]
