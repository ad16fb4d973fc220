"""Using a release from Python: load it, check it, predict meshes from AUs (+ head pose).

``load_release`` and ``predict_mesh`` are exported at the top (``aumesh.load_release``,
``aumesh.predict_mesh``); they are the one way the project itself predicts (figures, CLI).

The computation is the card's inference snippet, ``flat = x @ coef + intercept`` with
``x = [20 AUs | Pitch, Yaw, Roll]`` and the axis-major layout ``[x_0..x_477 | y_.. | z_..]``
(see ``docs/conventions.md``). When the release has ``coef_full`` (trained with pose x AU
interactions), ``x_full = [AUs | pose | pose x AU]`` (pose-major products) and
``flat = x_full @ coef_full + intercept``: pose-conditioned prediction is exact, and at pose 0
it equals the 23-row ``coef``.

Inputs are checked before any arithmetic: unknown AU names, wrong lengths, NaN/inf and pose
that looks like degrees are errors (:class:`PredictionInputError`) that say what was expected.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Union

import numpy as np

from aumesh.data.schema import N_TARGETS, N_VERTICES, POSE_COLUMNS, unflatten_axis_major
from aumesh.model.release import load_npz
from aumesh.utils.errors import MissingFileError, UserError

# A head turned more than 90 degrees is no longer a face seen from the front: any pose value above
# this (in radians) means the caller passed degrees. Training keeps |yaw| <= 40 deg, |pitch| <= 30 deg.
MAX_ABS_POSE_RAD = np.pi / 2

REQUIRED_KEYS: tuple[str, ...] = ("coef", "intercept", "input_columns", "au_columns", "mean_aligned_mesh")

Release = Mapping[str, Any]
ReleaseSource = Union[str, os.PathLike, Release]


class ReleaseError(UserError, ValueError):
    """A file or mapping that is not a usable release; the message names the key and what it should be."""


class PredictionInputError(UserError, ValueError):
    """AU or pose input that the model cannot take as it is; the message names the column and the fix."""


# --------------------------------------------------------------------------- the release
def load_release(source: ReleaseSource) -> dict[str, np.ndarray]:
    """Load and check a release in the card's NPZ format.

    Parameters
    ----------
    source : str, path-like or mapping
        The release NPZ (e.g. ``release/au_to_mesh_pls.npz``), an open ``np.load`` result or a
        mapping of its arrays (then checked and returned as a dict, nothing is read).

    Returns
    -------
    dict of str -> np.ndarray
        Every array of the file: ``coef`` (23, 1434) with rows ``input_columns``
        (``AU01 .. AU43, Pitch, Yaw, Roll``), ``intercept`` (1434,), ``au_columns`` (20,),
        ``mean_aligned_mesh`` (478, 3), and ``coef_full`` (83, 1434) with ``input_columns_full``
        when the model was trained with pose x AU interactions. Coordinates are in the release's
        units (the reference's pixels) and axis-major order.

    Raises
    ------
    MissingFileError
        ``source`` is a path that does not exist (a ``FileNotFoundError``).
    ReleaseError
        The file is not an NPZ, or a key is missing or has the wrong shape.
    """
    if isinstance(source, Mapping):
        arrays, where = {k: np.asarray(source[k]) for k in source}, "<release arrays>"
    else:
        path = Path(source)
        where = str(path)
        if not path.is_file():
            raise MissingFileError(
                f"release NPZ not found: {path}. Fix: pass the path of a release NPZ "
                f"(`dvc repro` writes release/au_to_mesh_pls.npz in the project)."
            )
        try:
            arrays = load_npz(path)
        except (OSError, ValueError) as exc:
            raise ReleaseError(f"{path}: not a release NPZ ({exc})") from exc
    check_release(arrays, where)
    return arrays


def check_release(arrays: Mapping[str, Any], where: str = "<release arrays>") -> None:
    """Raise :class:`ReleaseError` if release arrays lack a key or have a wrong shape.

    ``coef`` must be (len(input_columns), 1434) and name every AU of ``au_columns``; ``intercept``
    (1434,); ``mean_aligned_mesh`` (478, 3); ``coef_full``, when present, (len(input_columns_full), 1434).
    """
    for key in REQUIRED_KEYS:
        if key not in arrays:
            raise ReleaseError(f"{where}: missing key {key!r}; a release NPZ has {list(REQUIRED_KEYS)} "
                               f"(see docs/conventions.md); this one has {sorted(arrays)}")
    cols = _names(arrays["input_columns"])
    coef, intercept = np.asarray(arrays["coef"]), np.asarray(arrays["intercept"])
    if coef.shape != (len(cols), N_TARGETS):
        raise ReleaseError(f"{where}: 'coef' must be ({len(cols)}, {N_TARGETS}) (rows = input_columns), got {coef.shape}")
    if intercept.shape != (N_TARGETS,):
        raise ReleaseError(f"{where}: 'intercept' must be ({N_TARGETS},), got {intercept.shape}")
    if np.asarray(arrays["mean_aligned_mesh"]).shape != (N_VERTICES, 3):
        raise ReleaseError(f"{where}: 'mean_aligned_mesh' must be ({N_VERTICES}, 3), "
                           f"got {np.asarray(arrays['mean_aligned_mesh']).shape}")
    missing = [a for a in _names(arrays["au_columns"]) if a not in cols]
    if missing:
        raise ReleaseError(f"{where}: 'input_columns' lacks the AUs {missing} of 'au_columns'")
    if "coef_full" in arrays:
        if "input_columns_full" not in arrays:
            raise ReleaseError(f"{where}: 'coef_full' needs 'input_columns_full' (its row names)")
        full = _names(arrays["input_columns_full"])
        if np.asarray(arrays["coef_full"]).shape != (len(full), N_TARGETS):
            raise ReleaseError(f"{where}: 'coef_full' must be ({len(full)}, {N_TARGETS}) (rows = input_columns_full), "
                               f"got {np.asarray(arrays['coef_full']).shape}")


def _names(values: Any) -> list[str]:
    return [str(v) for v in np.asarray(values).tolist()]


# --------------------------------------------------------------------------- inputs
def input_rows(release: Release, aus: Any = None, pose: Any = None) -> tuple[np.ndarray, np.ndarray, bool]:
    """AU and pose rows in the release's column order, checked (the inputs of :func:`predict_mesh`).

    Parameters
    ----------
    release : mapping
        Release arrays (:func:`load_release`); ``au_columns`` gives the AU order.
    aus, pose
        As in :func:`predict_mesh`.

    Returns
    -------
    au : np.ndarray, shape (N, 20), float64
        AU intensities in ``au_columns`` order.
    pose : np.ndarray, shape (N, 3), float64
        Pitch, Yaw, Roll in radians.
    single : bool
        True when the input was one row (a 1-D array, a mapping or None): predict one (478, 3) mesh.

    Raises
    ------
    PredictionInputError
        Unknown names, wrong lengths, NaN/inf, pose in degrees, pose given twice, mismatched row counts.
    """
    au_names = _names(release["au_columns"])
    pose_from_aus = None
    if aus is None:
        au, single = np.zeros((1, len(au_names))), True
    elif isinstance(aus, Mapping):
        several = [str(k) for k, v in aus.items() if np.ndim(v) != 0]
        if several:
            raise PredictionInputError(f"aus: the mapping's values must be single numbers (one row), not {several}; "
                                       f"for many rows pass a DataFrame or an (N, {len(au_names)}) array")
        au, pose_from_aus = _from_names({k: [v] for k, v in aus.items()}, 1, au_names, "aus")
        single = True
    elif _is_dataframe(aus):
        au, pose_from_aus = _from_names({c: aus[c].to_numpy() for c in aus.columns}, len(aus), au_names,
                                        "aus (DataFrame)")
        single = False
    else:
        au, pose_from_aus, single = _from_array(aus, au_names)
    if pose_from_aus is not None:
        if pose is not None:
            raise PredictionInputError(
                f"pose given twice: aus has {', '.join(POSE_COLUMNS)} and pose= is set too. Fix: pass one of them.")
        pose_rows = pose_from_aus
    elif pose is None:
        pose_rows = np.zeros((len(au), 3))
    else:
        pose_rows, pose_single = _pose_array(pose)
        single = single and pose_single
    _check_finite(au, au_names, "aus")
    _check_finite(pose_rows, list(POSE_COLUMNS), "pose")
    _check_radians(pose_rows)
    if len(au) != len(pose_rows):
        if len(au) == 1:
            au = np.repeat(au, len(pose_rows), axis=0)
        elif len(pose_rows) == 1:
            pose_rows = np.repeat(pose_rows, len(au), axis=0)
        else:
            raise PredictionInputError(f"aus has {len(au)} rows but pose has {len(pose_rows)}; "
                                       f"give pose one row per AU row, or one row for all")
    return au, pose_rows, single


def _is_dataframe(obj: Any) -> bool:
    return type(obj).__name__ == "DataFrame" and hasattr(obj, "columns") and hasattr(obj, "to_numpy")


def _from_names(columns: Mapping[Any, Any], n: int, au_names: list[str], what: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Named columns -> (N, 20) AUs (missing AUs are 0) and (N, 3) pose if any pose column is named."""
    known = set(au_names) | set(POSE_COLUMNS)
    unknown = [str(k) for k in columns if str(k) not in known]
    if unknown:
        raise PredictionInputError(
            f"{what}: unknown name(s) {unknown}; the model takes {', '.join(au_names)} "
            f"and {', '.join(POSE_COLUMNS)} (radians). Fix: rename or drop them (missing AUs count as 0).")
    values = {str(k): _numeric(v, f"{what}[{str(k)!r}]") for k, v in columns.items()}
    au = np.zeros((n, len(au_names)))
    for j, name in enumerate(au_names):
        if name in values:
            au[:, j] = values[name]
    named_pose = [p for p in POSE_COLUMNS if p in values]
    if not named_pose:
        return au, None
    if len(named_pose) != len(POSE_COLUMNS):
        missing = [p for p in POSE_COLUMNS if p not in values]
        raise PredictionInputError(f"{what}: has {named_pose} but not {missing}; give all of "
                                   f"{', '.join(POSE_COLUMNS)} (radians) or none (pose 0)")
    return au, np.stack([values[p] for p in POSE_COLUMNS], axis=1)


def _numeric(values: Any, what: str) -> np.ndarray:
    try:
        return np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise PredictionInputError(f"{what}: not numeric ({exc})") from exc


def _from_array(aus: Any, au_names: list[str]) -> tuple[np.ndarray, np.ndarray | None, bool]:
    """A (20,) / (N, 20) AU array, or (23,) / (N, 23) AU + pose in input-column order."""
    try:
        a = np.asarray(aus, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PredictionInputError(f"aus: not numeric ({exc}); pass an array, a mapping {{'AU12': 1.0}} "
                                   f"or a DataFrame with named columns") from exc
    n_au, n_in = len(au_names), len(au_names) + len(POSE_COLUMNS)
    if a.ndim not in (1, 2) or a.shape[-1] not in (n_au, n_in):
        raise PredictionInputError(
            f"aus has shape {a.shape}; expected ({n_au},) or (N, {n_au}) in the release's AU order "
            f"[{', '.join(au_names)}], or ({n_in},) / (N, {n_in}) with {', '.join(POSE_COLUMNS)} (radians) appended")
    single = a.ndim == 1
    a = a.reshape(-1, a.shape[-1])
    if a.shape[1] == n_in:
        return a[:, :n_au], a[:, n_au:], single
    return a, None, single


def _pose_array(pose: Any) -> tuple[np.ndarray, bool]:
    if isinstance(pose, Mapping):
        unknown = [str(k) for k in pose if str(k) not in POSE_COLUMNS]
        missing = [p for p in POSE_COLUMNS if p not in pose]
        if unknown or missing:
            raise PredictionInputError(f"pose: keys must be {list(POSE_COLUMNS)} (radians); "
                                       f"unknown {unknown}, missing {missing}")
        pose = [pose[p] for p in POSE_COLUMNS]
    try:
        p = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PredictionInputError(f"pose: not numeric ({exc}); pass {', '.join(POSE_COLUMNS)} in radians") from exc
    if p.ndim not in (1, 2) or p.shape[-1] != len(POSE_COLUMNS):
        raise PredictionInputError(f"pose has shape {p.shape}; expected (3,) or (N, 3): "
                                   f"{', '.join(POSE_COLUMNS)} in radians, in that order")
    return p.reshape(-1, 3), p.ndim == 1


def _check_finite(values: np.ndarray, names: list[str], what: str) -> None:
    bad = ~np.isfinite(values)
    if bad.any():
        row, col = (int(i) for i in np.argwhere(bad)[0])
        raise PredictionInputError(f"{what}: {int(bad.sum())} NaN/inf value(s), first in {names[col]!r} at row {row}. "
                                   f"Fix: drop or fill those rows (e.g. frames where no face was found)")


def _check_radians(pose: np.ndarray) -> None:
    if not pose.size:
        return
    biggest = np.abs(pose).max(axis=0)
    j = int(np.argmax(biggest))
    if biggest[j] > MAX_ABS_POSE_RAD:
        raise PredictionInputError(
            f"pose: {POSE_COLUMNS[j]} reaches {biggest[j]:g}, more than pi/2: pose looks like degrees. "
            f"Pose is in radians, in the order {', '.join(POSE_COLUMNS)}. Fix: np.deg2rad(pose)")


# --------------------------------------------------------------------------- prediction
def predict_mesh(release: ReleaseSource, aus: Any = None, pose: Any = None) -> np.ndarray:
    """Predict face meshes from AU intensities (and head pose) with a release.

    Parameters
    ----------
    release : str, path-like or mapping
        A release NPZ path or its loaded arrays (:func:`load_release`; load once when predicting
        many times).
    aus : array-like, mapping, DataFrame or None
        AU intensities (the tables' scale, e.g. py-feat's 0..1):

        - array of shape (20,) or (N, 20) in the release's ``au_columns`` order
          (``AU01, AU02, AU04, ..., AU43``), or (23,) / (N, 23) with ``Pitch, Yaw, Roll`` appended
          (the card's ``input_columns``);
        - mapping ``{"AU12": 1.0}``: one row, AUs not named are 0;
        - pandas DataFrame with named columns (AUs, optionally ``Pitch``, ``Yaw``, ``Roll``):
          one mesh per row, AUs not named are 0;
        - None: all AUs 0 (the model's neutral face).

        Unknown names are an error naming them.
    pose : array-like of shape (3,) or (N, 3), mapping, or None
        Head pose in **radians**, in the order **Pitch, Yaw, Roll** (py-feat's tables store
        Pitch, Roll, Yaw: select by name). Default 0 (frontal, the usual use: rotate the
        predicted mesh afterwards to show another view). One row applies to every AU row.
        Values above pi/2 in magnitude are refused as degrees.

    Returns
    -------
    np.ndarray, float64
        Shape (478, 3) for one row (1-D array, mapping, None), (N, 478, 3) for a batch
        (2-D array or DataFrame), in the release's frame and units (the card's canonical
        frame; see ``docs/conventions.md``).

    Raises
    ------
    FileNotFoundError, ReleaseError
        From :func:`load_release`.
    PredictionInputError
        Unknown names, wrong lengths (the message lists the expected columns), NaN/inf, pose
        that looks like degrees.

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
    """
    arrays = load_release(release)
    au, pose_rows, single = input_rows(arrays, aus, pose)
    flat = _linear(arrays, au, pose_rows)
    meshes = unflatten_axis_major(flat)
    return meshes[0] if single else meshes


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


__all__ = ["MAX_ABS_POSE_RAD", "PredictionInputError", "ReleaseError", "check_release", "input_rows",
           "load_release", "predict_mesh"]
