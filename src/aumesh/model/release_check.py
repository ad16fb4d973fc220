"""A release loaded and checked: the card's NPZ read without pickle, every key and shape checked, finite.

:func:`load_release` (``aumesh.load_release``) is how the project itself opens a release (figures, CLI, the served
model): a missing key, a wrong shape, a product column that names nothing or a NaN coefficient is a
:class:`ReleaseError` naming the key and what it should be, before any prediction. The arrays are built by
:mod:`aumesh.model.release`; the key list is the card's "File format" (``docs/conventions.md``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.core.errors import CorruptFileError, MissingFileError, UserError
from aumesh.core.schema import N_TARGETS, N_VERTICES
from aumesh.model.release import RELEASE_FIX, load_npz

REQUIRED_KEYS: tuple[str, ...] = ("coef", "intercept", "input_columns", "au_columns", "mean_aligned_mesh")

Release = Mapping[str, Any]
ReleaseSource = str | os.PathLike | Release


class ReleaseError(UserError, ValueError):
    """A file or mapping that is not a usable release; the message names the key and what it should be."""


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
        units (the reference's pixels) and axis-major order. Releases that record their data's support
        also have ``feature_p99`` (23,) and ``unsupported_features`` (k,) (:mod:`aumesh.model.support`);
        releases without them load as before (nothing is checked against the data then).

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
        except CorruptFileError as exc:  # one line naming the file and the fix (RELEASE_FIX)
            raise ReleaseError(str(exc)) from None
        except (OSError, ValueError) as exc:
            raise ReleaseError(f"{path}: not a release NPZ ({exc}). Fix: {RELEASE_FIX}") from exc
        try:
            check_release(arrays, where)
        except ReleaseError as exc:  # a key missing or misshapen in a file: damaged, or not a release
            if "Fix:" in str(exc):
                raise
            raise ReleaseError(f"{exc}. Fix: {RELEASE_FIX}") from None
        return arrays
    check_release(arrays, where)
    return arrays


def check_release(arrays: Mapping[str, Any], where: str = "<release arrays>") -> None:
    """Raise :class:`ReleaseError` if release arrays lack a key or have a wrong shape.

    ``coef`` must be (len(input_columns), 1434) and name every AU of ``au_columns``; ``intercept``
    (1434,); ``mean_aligned_mesh`` (478, 3); ``coef_full``, when present, (len(input_columns_full), 1434).
    """
    for key in REQUIRED_KEYS:
        if key not in arrays:
            raise ReleaseError(
                f"{where}: missing key {key!r}; a release NPZ has {list(REQUIRED_KEYS)} "
                f"(see docs/conventions.md); this one has {sorted(arrays)}"
            )
    cols = _names(arrays["input_columns"])
    coef, intercept = np.asarray(arrays["coef"]), np.asarray(arrays["intercept"])
    if coef.shape != (len(cols), N_TARGETS):
        raise ReleaseError(
            f"{where}: 'coef' must be ({len(cols)}, {N_TARGETS}) (rows = input_columns), got {coef.shape}"
        )
    if intercept.shape != (N_TARGETS,):
        raise ReleaseError(f"{where}: 'intercept' must be ({N_TARGETS},), got {intercept.shape}")
    if np.asarray(arrays["mean_aligned_mesh"]).shape != (N_VERTICES, 3):
        raise ReleaseError(
            f"{where}: 'mean_aligned_mesh' must be ({N_VERTICES}, 3), "
            f"got {np.asarray(arrays['mean_aligned_mesh']).shape}"
        )
    missing = [a for a in _names(arrays["au_columns"]) if a not in cols]
    if missing:
        raise ReleaseError(f"{where}: 'input_columns' lacks the AUs {missing} of 'au_columns'")
    if "coef_full" in arrays:
        if "input_columns_full" not in arrays:
            raise ReleaseError(f"{where}: 'coef_full' needs 'input_columns_full' (its row names)")
        full = _names(arrays["input_columns_full"])
        if np.asarray(arrays["coef_full"]).shape != (len(full), N_TARGETS):
            raise ReleaseError(
                f"{where}: 'coef_full' must be ({len(full)}, {N_TARGETS}) (rows = input_columns_full), "
                f"got {np.asarray(arrays['coef_full']).shape}"
            )
    if "feature_p99" in arrays and np.asarray(arrays["feature_p99"]).shape != (len(cols),):
        raise ReleaseError(
            f"{where}: 'feature_p99' must be ({len(cols)},) (each input's training p99, rows = input_columns), "
            f"got {np.asarray(arrays['feature_p99']).shape}"
        )
    if "unsupported_features" in arrays:
        unknown = [u for u in _names(np.asarray(arrays["unsupported_features"]).reshape(-1)) if u not in cols]
        if unknown or np.asarray(arrays["unsupported_features"]).ndim != 1:
            raise ReleaseError(
                f"{where}: 'unsupported_features' must be a 1-D list of input_columns names, got "
                f"{np.asarray(arrays['unsupported_features']).tolist()!r}"
            )
    nonfinite = nonfinite_arrays(arrays)
    if nonfinite:
        raise ReleaseError(
            f"{where}: {nonfinite}: a release must be finite (every mesh it predicts would be NaN/inf). "
            f"Fix: rebuild the release (`dvc repro -f evaluate release`), or use another release NPZ."
        )


#: The arrays a prediction is computed from: a release is refused unless every value of them is finite.
FINITE_KEYS = ("coef", "coef_full", "intercept")


def nonfinite_arrays(arrays: Mapping[str, Any], keys: tuple[str, ...] = FINITE_KEYS) -> str | None:
    """``None`` when ``arrays[k]`` is finite for each of ``keys`` present; else a phrase naming the first that is not,
    e.g. ``"'intercept' has 1 NaN/inf value(s) of 1434 (first at index 5)"``."""
    for key in keys:
        if key in arrays:
            a = np.asarray(arrays[key])
            bad = ~np.isfinite(a) if a.dtype.kind in "fc" else np.zeros(a.shape, bool)
            if bad.any():
                first = np.unravel_index(int(np.argmax(bad)), a.shape)
                return (
                    f"{key!r} has {int(bad.sum()):,} NaN/inf value(s) of {a.size:,} "
                    f"(first at index {first[0] if len(first) == 1 else tuple(int(i) for i in first)})"
                )
    return None


def _names(values: Any) -> list[str]:
    return [str(v) for v in np.asarray(values).tolist()]


__all__ = ["FINITE_KEYS", "REQUIRED_KEYS", "ReleaseError", "check_release", "load_release", "nonfinite_arrays"]
