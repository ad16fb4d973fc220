"""Using a release from Python: load it, check it, predict meshes from AUs (+ head pose).

``load_release`` and ``predict_mesh`` are exported at the top (``aumesh.load_release``,
``aumesh.predict_mesh``); they are the one way the project itself predicts (figures, CLI).

The computation is the card's inference snippet, ``flat = x @ coef + intercept`` with
``x = [20 AUs | Pitch, Yaw, Roll]`` and the axis-major layout ``[x_0..x_477 | y_.. | z_..]``
(see ``docs/conventions.md``). When the release has ``coef_full`` (trained with pose x AU
interactions), ``x_full = [AUs | pose | pose x AU]`` (pose-major products) and
``flat = x_full @ coef_full + intercept``: pose-conditioned prediction is exact, and at pose 0
it equals the 23-row ``coef``.

Inputs are checked before any arithmetic: unknown AU names (with the closest input name),
wrong lengths, partly NaN rows, AUs above py-feat's 0..1 in a detector's table and pose that
looks like degrees are errors (:class:`PredictionInputError`) that say what was expected; pose
beyond the training range is a warning (:class:`InputRangeWarning`). A whole detector table
(py-feat's Fex output, CSV or parquet, MPDetector or Detectorv2) is taken as it is: the AU and
pose columns are picked by name, and a frame without a face gets a NaN mesh.
"""

from __future__ import annotations

import difflib
import logging
import os
import re
import sys
import warnings
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.core.errors import MissingFileError, UserError
from aumesh.core.schema import (
    AU_COLUMNS,
    MAX_ABS_PITCH_DEG,
    MAX_ABS_YAW_DEG,
    N_TARGETS,
    N_VERTICES,
    POSE_COLUMNS,
    unflatten_axis_major,
)
from aumesh.model import support
from aumesh.model.release import load_npz

# A head turned more than 90 degrees is no longer a face seen from the front: any pose value above
# this (in radians) means the caller passed degrees. Training keeps |yaw| <= 40 deg, |pitch| <= 30 deg
# (the release's preprocess.pose_filter): beyond that, a warning (training_pose_limits).
MAX_ABS_POSE_RAD = np.pi / 2

# py-feat's AU intensities (both detectors) are 0..1, and so are the training tables'; OpenFace's are 0..5.
AU_SCALE_MAX = 1.0
_AU_SCALE_SLACK = 1e-6  # float32 rounding of a 1.0

# py-feat's face-detection confidence: 0 (MPDetector) or NaN (Detectorv2) on the one row of a frame without a face.
FACE_SCORE_COLUMN = "FaceScore"

REQUIRED_KEYS: tuple[str, ...] = ("coef", "intercept", "input_columns", "au_columns", "mean_aligned_mesh")

Release = Mapping[str, Any]
ReleaseSource = str | os.PathLike | Release


class ReleaseError(UserError, ValueError):
    """A file or mapping that is not a usable release; the message names the key and what it should be."""


class PredictionInputError(UserError, ValueError):
    """AU or pose input that the model cannot take as it is; the message names the column and the fix."""


class InputRangeWarning(UserWarning):
    """Input the model takes but was not trained on (pose beyond the training range, an AU above 1 given as
    numbers, an AU above its training max, an AU the training data never expressed given, a table from another
    detector than the release's); one line a call, naming the columns, the values and the training range. The mesh
    there is an extrapolation."""


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


# --------------------------------------------------------------------------- which columns of a table
@dataclass(frozen=True)
class ColumnSelection:
    """The columns of a table that :func:`input_rows` uses, chosen from its header by :func:`select_columns`.

    Attributes
    ----------
    whole : bool
        True for a whole table: one with columns besides the model's inputs (py-feat's Fex output,
        a detector's CSV or parquet). Its other columns are ignored, every AU must be present,
        and an AU above 1 is an error. False for a table of input columns only (missing AUs are 0).
    inputs : tuple of str
        The AU and pose columns present, as the table names them.
    face_score : str or None
        ``FaceScore`` when a whole table has it (0 marks a frame without a face).
    """

    whole: bool
    inputs: tuple[str, ...]
    face_score: str | None = None

    @property
    def columns(self) -> list[str]:
        """Every column to read: ``inputs`` and ``face_score``."""
        return [*self.inputs, *([self.face_score] if self.face_score else [])]


def select_columns(
    columns: Iterable[Any],
    au_columns: Sequence[str] = AU_COLUMNS,
    *,
    strict: bool = False,
    pose_given: bool = False,
    what: str = "table",
) -> ColumnSelection:
    """Pick the model's input columns of a table by name, from its header alone.

    Parameters
    ----------
    columns : iterable of str
        The table's column names (e.g. the header of a 2,045-column py-feat CSV).
    au_columns : sequence of str, length 20
        The release's AU names (``au_columns``).
    strict : bool
        True: every column must be an input name (AU01 .. AU43, Pitch, Yaw, Roll), as before py-feat's
        whole tables were taken. False (default): a table with other columns is a whole table.
    pose_given : bool
        Pose comes from elsewhere (``pose=``): a whole table need not have pose columns.
    what : str
        How messages name the table (its path).

    Returns
    -------
    ColumnSelection

    Raises
    ------
    PredictionInputError
        ``strict`` and a column that is not an input (the first few named, with the closest input name);
        a whole table without an AU, or with some pose columns and not others (the missing column named
        with the table's closest column: ``did you mean 'AU_12'?``); one line, never every column.
    """
    names = [str(c) for c in columns]
    au_columns = [str(a) for a in au_columns]
    known = set(au_columns) | set(POSE_COLUMNS)
    others = [c for c in names if c not in known]
    present = [c for c in names if c in known]
    if strict or not others:
        if others:
            raise _unknown_error(
                what,
                others,
                au_columns,
                present,
                fix="rename or drop them (missing AUs count as 0); "
                "without strict (--strict), other columns are ignored",
            )
        _check_pose_complete(present, what)
        return ColumnSelection(False, tuple(present))
    missing = [a for a in au_columns if a not in present]
    if missing:
        raise _missing_error(
            what,
            missing,
            others,
            f"all {len(au_columns)} AUs ({au_columns[0]} .. {au_columns[-1]})",
            "rename the column, or give only input columns (then missing AUs count as 0)",
        )
    pose_missing = [p for p in POSE_COLUMNS if p not in present]
    if pose_missing:
        partial = len(pose_missing) < len(POSE_COLUMNS)
        if partial or (not pose_given and any(closest_name(p, others) for p in pose_missing)):
            raise _missing_error(
                what,
                pose_missing,
                others,
                f"all of {', '.join(POSE_COLUMNS)} (radians) or none",
                "rename the column, or drop every pose column (pose 0)",
            )
    face_score = FACE_SCORE_COLUMN if FACE_SCORE_COLUMN in names else None
    return ColumnSelection(True, tuple(present), face_score)


def _check_pose_complete(present: Sequence[str], what: str) -> None:
    named = [p for p in POSE_COLUMNS if p in present]
    if named and len(named) != len(POSE_COLUMNS):
        missing = [p for p in POSE_COLUMNS if p not in present]
        raise PredictionInputError(
            f"{what}: has {named} but not {missing}; give all of {', '.join(POSE_COLUMNS)} (radians) or none (pose 0)"
        )


def _key(name: Any) -> str:
    """A name as compared for "did you mean": case, blanks, ``_`` and ``-`` ignored; ``AU1``, ``AU01``,
    ``AU12_r`` (OpenFace's intensity) and ``AU12_c`` read as ``au1`` / ``au12``."""
    key = re.sub(r"[\s_\-]+", "", str(name).lower())
    au = re.fullmatch(r"au0*(\d+)[rc]?", key)
    return f"au{au.group(1)}" if au else key


def closest_name(name: str, candidates: Iterable[Any]) -> str | None:
    """The candidate that ``name`` most likely means, for a "did you mean" (``AU_12``, ``au12``, ``AU12_r``, ``Yaw ``).

    Parameters
    ----------
    name : str
        The name looked for (a missing column, or an unknown one).
    candidates : iterable of str
        The names it may mean (a table's other columns, or the model's inputs).

    Returns
    -------
    str or None
        The first candidate with the same :func:`_key` (case, blanks, ``_``, ``-``, leading zeros of an
        AU number and OpenFace's ``_r`` / ``_c`` ignored); else, for a name that is not an AU (AU13 is
        not a misspelt AU12), the closest by ``difflib`` with a ratio >= 0.8; else None.
    """
    keyed: dict[str, str] = {}
    for c in candidates:
        keyed.setdefault(_key(c), str(c))
    key = _key(name)
    if key in keyed:
        return keyed[key]
    if re.fullmatch(r"au\d+", key):
        return None
    match = difflib.get_close_matches(key, list(keyed), n=1, cutoff=0.8)
    return keyed[match[0]] if match else None


def short_list(names: Sequence[str], n: int = 5) -> str:
    """``['a', 'b']``, or the first ``n`` and how many in all (a message never lists 2,000 columns)."""
    if len(names) <= n:
        return repr(list(names))
    return f"[{', '.join(repr(x) for x in names[:n])}, ... ({len(names)} in all)]"


def _unknown_error(
    what: str, unknown: Sequence[str], au_names: Sequence[str], present: Sequence[str], fix: str
) -> PredictionInputError:
    wanted = [c for c in (*au_names, *POSE_COLUMNS) if c not in present]
    hint = next(((u, m) for u in unknown if (m := closest_name(u, wanted))), None)
    meant = f" (did you mean {hint[1]!r} for {hint[0]!r}?)" if hint else ""
    return PredictionInputError(
        f"{what}: unknown name(s) {short_list(unknown)}; the model takes {', '.join(au_names)} "
        f"and {', '.join(POSE_COLUMNS)} (radians){meant}. Fix: {fix}."
    )


def _missing_error(
    what: str, missing: Sequence[str], others: Sequence[str], needs: str, fix: str
) -> PredictionInputError:
    """One line: the first missing column that has a near miss in the table (else the first), and that near miss."""
    hint = next(((m, c) for m in missing if (c := closest_name(m, others))), None)
    name, meant = hint if hint else (missing[0], None)
    more = f"; {len(missing) - 1} more missing" if len(missing) > 1 else ""
    near = f"did you mean {meant!r}?" if meant else "no column has a name close to it"
    return PredictionInputError(
        f"{what}: no column {name!r} ({near}){more}. A table with columns besides the model's inputs needs {needs}, "
        f"by name. Fix: {fix}"
    )


# --------------------------------------------------------------------------- inputs
def input_rows(
    release: Release,
    aus: Any = None,
    pose: Any = None,
    *,
    strict: bool = False,
    selection: ColumnSelection | None = None,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """AU and pose rows in the release's column order, checked (the inputs of :func:`predict_mesh`).

    Parameters
    ----------
    release : mapping
        Release arrays (:func:`load_release`); ``au_columns`` gives the AU order, ``training_metadata``
        the training pose range.
    aus, pose, strict
        As in :func:`predict_mesh`.
    selection : ColumnSelection, optional
        For a DataFrame ``aus``: the columns already chosen from the whole table's header
        (:func:`select_columns`), e.g. by a reader that read only those columns.

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
        Unknown or missing names, wrong lengths, partly NaN rows, pose in degrees, pose given twice,
        mismatched row counts, an AU above 1 in a whole table.

    Warns
    -----
    InputRangeWarning
        One line: pose beyond the training range; an AU above 1 given as numbers (array, mapping, a DataFrame of
        input columns); AUs beyond the training data (:func:`predict_mesh`).

    Notes
    -----
    A row without a face (``FaceScore`` 0, or every AU and every given pose value NaN; see
    :func:`predict_mesh`) is all NaN in both ``au`` and ``pose``; every other row is finite, so
    ``np.isnan(au).all(axis=1)`` flags them.
    """
    au_names = _names(release["au_columns"])
    pose_from_aus, face_score, whole = None, None, False
    if aus is None:
        au, single = np.zeros((1, len(au_names))), True
    elif isinstance(aus, Mapping):
        several = [str(k) for k, v in aus.items() if np.ndim(v) != 0]
        if several:
            raise PredictionInputError(
                f"aus: the mapping's values must be single numbers (one row), not {several}; "
                f"for many rows pass a DataFrame or an (N, {len(au_names)}) array"
            )
        au, pose_from_aus = _from_names({k: [v] for k, v in aus.items()}, 1, au_names, "aus")
        single = True
    elif _is_dataframe(aus):
        what = "aus (DataFrame)"
        if selection is None:
            selection = select_columns(aus.columns, au_names, strict=strict, pose_given=pose is not None, what=what)
        au, pose_from_aus, face_score = _table_values(aus, selection, au_names, what)
        whole, single = selection.whole, False
    else:
        au, pose_from_aus, single = _from_array(aus, au_names)
    pose_in_input = pose_from_aus is not None or pose is not None
    if pose_from_aus is not None:
        if pose is not None:
            raise PredictionInputError(
                f"pose given twice: aus has {', '.join(POSE_COLUMNS)} and pose= is set too. Fix: pass one of them."
            )
        pose_rows = pose_from_aus
    elif pose is None:
        pose_rows = np.zeros((len(au), 3))
    else:
        pose_rows, pose_single = _pose_array(pose)
        single = single and pose_single
    if len(au) == len(pose_rows) or len(pose_rows) == 1:
        n = len(au)
    elif len(au) == 1:
        n = len(pose_rows)
    else:
        raise PredictionInputError(
            f"aus has {len(au)} rows but pose has {len(pose_rows)}; give pose one row per AU row, or one row for all"
        )
    no_face = _no_face(au, pose_rows if pose_in_input else None, face_score, n)
    _check_finite(au, au_names, "aus", no_face)
    _check_finite(pose_rows, list(POSE_COLUMNS), "pose", no_face)
    if len(au) != n:
        au = np.repeat(au, n, axis=0)
    if len(pose_rows) != n:
        pose_rows = np.repeat(pose_rows, n, axis=0)
    if no_face.any():
        au, pose_rows = au.copy(), pose_rows.copy()
        au[no_face], pose_rows[no_face] = np.nan, np.nan
    face = ~no_face
    _check_radians(pose_rows[face])
    scale = _check_au_scale(au, au_names, face, refuse=whole)
    _warn_beyond_training(au, pose_rows, au_names, face, release, scale)
    return au, pose_rows, single


def _is_dataframe(obj: Any) -> bool:
    """A pandas DataFrame or a subclass (py-feat's ``Fex``), without importing pandas."""
    pandas = sys.modules.get("pandas")
    if pandas is not None and isinstance(obj, pandas.DataFrame):
        return True
    return type(obj).__name__ == "DataFrame" and hasattr(obj, "columns") and hasattr(obj, "to_numpy")


def _table_values(
    df: Any, selection: ColumnSelection, au_names: list[str], what: str
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The selected columns of a DataFrame -> (N, 20) AUs (missing AUs 0), (N, 3) pose or None, FaceScore or None."""
    labels = {str(c): c for c in df.columns}
    absent = [c for c in selection.columns if c not in labels]
    if absent:
        raise PredictionInputError(f"{what}: the selected column(s) {absent} are not in the DataFrame")
    values = {c: _numeric(df[labels[c]].to_numpy(), f"{what}[{c!r}]") for c in selection.inputs}
    au = np.zeros((len(df), len(au_names)))
    for j, name in enumerate(au_names):
        if name in values:
            au[:, j] = values[name]
    pose = np.stack([values[p] for p in POSE_COLUMNS], axis=1) if all(p in values for p in POSE_COLUMNS) else None
    score = None
    if selection.face_score:
        score = _numeric(df[labels[selection.face_score]].to_numpy(), f"{what}[{selection.face_score!r}]")
    return au, pose, score


def _from_names(
    columns: Mapping[Any, Any], n: int, au_names: list[str], what: str
) -> tuple[np.ndarray, np.ndarray | None]:
    """Named columns -> (N, 20) AUs (missing AUs are 0) and (N, 3) pose if any pose column is named."""
    known = set(au_names) | set(POSE_COLUMNS)
    names = [str(k) for k in columns]
    unknown = [k for k in names if k not in known]
    if unknown:
        raise _unknown_error(
            what,
            unknown,
            au_names,
            [k for k in names if k in known],
            fix="rename or drop them (missing AUs count as 0)",
        )
    values = {str(k): _numeric(v, f"{what}[{str(k)!r}]") for k, v in columns.items()}
    _check_pose_complete(list(values), what)
    au = np.zeros((n, len(au_names)))
    for j, name in enumerate(au_names):
        if name in values:
            au[:, j] = values[name]
    if not any(p in values for p in POSE_COLUMNS):
        return au, None
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
        raise PredictionInputError(
            f"aus: not numeric ({exc}); pass an array, a mapping {{'AU12': 1.0}} or a DataFrame with named columns"
        ) from exc
    n_au, n_in = len(au_names), len(au_names) + len(POSE_COLUMNS)
    if a.ndim not in (1, 2) or a.shape[-1] not in (n_au, n_in):
        raise PredictionInputError(
            f"aus has shape {a.shape}; expected ({n_au},) or (N, {n_au}) in the release's AU order "
            f"[{', '.join(au_names)}], or ({n_in},) / (N, {n_in}) with {', '.join(POSE_COLUMNS)} (radians) appended"
        )
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
            raise PredictionInputError(
                f"pose: keys must be {list(POSE_COLUMNS)} (radians); unknown {unknown}, missing {missing}"
            )
        pose = [pose[p] for p in POSE_COLUMNS]
    try:
        p = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PredictionInputError(f"pose: not numeric ({exc}); pass {', '.join(POSE_COLUMNS)} in radians") from exc
    if p.ndim not in (1, 2) or p.shape[-1] != len(POSE_COLUMNS):
        raise PredictionInputError(
            f"pose has shape {p.shape}; expected (3,) or (N, 3): {', '.join(POSE_COLUMNS)} in radians, in that order"
        )
    return p.reshape(-1, 3), p.ndim == 1


def _no_face(au: np.ndarray, pose: np.ndarray | None, face_score: np.ndarray | None, n: int) -> np.ndarray:
    """(n,) bool: rows of a frame without a face: FaceScore 0, or every AU and every given pose value NaN."""
    blank = np.broadcast_to(np.isnan(au).all(axis=1), (n,)) if len(au) else np.zeros(n, dtype=bool)
    if pose is not None:
        blank = blank & np.broadcast_to(np.isnan(pose).all(axis=1), (n,))
    if face_score is not None:
        blank = blank | (face_score == 0)
    return np.array(blank, dtype=bool)


def _check_finite(values: np.ndarray, names: list[str], what: str, no_face: np.ndarray) -> None:
    """Refuse NaN/inf outside the no-face rows; ``values`` has len(no_face) rows or one row (for all)."""
    skip = no_face if len(values) == len(no_face) else np.array([no_face.all()])
    bad = ~np.isfinite(values) & ~skip[:, None]
    if bad.any():
        row, col = (int(i) for i in np.argwhere(bad)[0])
        raise PredictionInputError(
            f"{what}: {int(bad.sum())} NaN/inf value(s), first in {names[col]!r} at row {row}. A frame without a face "
            f"has every AU and pose value NaN (or FaceScore 0) and gets a NaN mesh; this row is only partly NaN. "
            f"Fix: fill or drop it"
        )


def _check_radians(pose: np.ndarray) -> None:
    if not pose.size:
        return
    biggest = np.abs(pose).max(axis=0)
    j = int(np.argmax(biggest))
    if biggest[j] > MAX_ABS_POSE_RAD:
        raise PredictionInputError(
            f"pose: {POSE_COLUMNS[j]} reaches {biggest[j]:g}, more than pi/2: pose looks like degrees. "
            f"Pose is in radians, in the order {', '.join(POSE_COLUMNS)}. Fix: np.deg2rad(pose)"
        )


def _check_au_scale(au: np.ndarray, au_names: list[str], face: np.ndarray, refuse: bool) -> str | None:
    """An AU above 1: an error in a whole (detector's) table; for numbers given directly, the warning's phrase."""
    bad = (au > AU_SCALE_MAX + _AU_SCALE_SLACK) & face[:, None]
    if not bad.any():
        return None
    row, col = (int(i) for i in np.argwhere(bad)[0])
    where = f"aus: {au_names[col]} = {au[row, col]:g} at row {row} is above {AU_SCALE_MAX:g}"
    if refuse:
        raise PredictionInputError(
            f"{where}: py-feat's AU intensities, and the model's, are 0..1 (0..5 is OpenFace's scale). "
            f"Fix: divide the AU columns by 5"
        )
    return (
        f"{where}, beyond the 0..1 scale the model was trained on (py-feat's); the mesh is an extrapolation "
        f"(OpenFace's 0..5 AUs: divide by 5)"
    )


def training_pose_limits(release: Release) -> tuple[dict[str, float], str]:
    """|angle| limits (radians) of the training frames, and where they come from.

    Returns
    -------
    limits : dict of str -> float
        ``{"Pitch": ..., "Yaw": ...}``: the release's ``preprocess.pose_filter`` (recorded in its
        ``training_metadata``); when the release records none, the card's (|pitch| <= 30 deg, |yaw| <= 40 deg).
        Roll is not filtered in training.
    source : str
        ``"the release's pose filter"`` or ``"the card's pose filter"``.
    """
    meta = support.training_metadata(release)
    pose_filter: dict[str, Any] = ((meta.get("config") or {}).get("preprocess") or {}).get("pose_filter") or {}
    if pose_filter.get("max_abs_pitch_deg") is not None and pose_filter.get("max_abs_yaw_deg") is not None:
        pitch, yaw, source = (
            pose_filter["max_abs_pitch_deg"],
            pose_filter["max_abs_yaw_deg"],
            "the release's pose filter",
        )
    else:
        pitch, yaw = MAX_ABS_PITCH_DEG, MAX_ABS_YAW_DEG  # the card's defaults (core.schema, one place)
        source = "the card's pose filter (the release records none)"
    return {"Pitch": float(np.deg2rad(float(pitch))), "Yaw": float(np.deg2rad(float(yaw)))}, source


def _pose_beyond(pose: np.ndarray, face: np.ndarray, release: Release) -> str | None:
    """The warning's phrase when a face row's Pitch or Yaw is beyond the training range, else None."""
    if not face.any() or not (np.abs(pose[face]).max(initial=0.0) > 0):
        return None
    limits, source = training_pose_limits(release)
    beyond = np.zeros(pose.shape, dtype=bool)
    for name, limit in limits.items():
        j = POSE_COLUMNS.index(name)
        beyond[:, j] = face & (np.abs(pose[:, j]) > limit)
    if not beyond.any():
        return None
    row, j = (int(i) for i in np.argwhere(beyond)[0])
    name, value = POSE_COLUMNS[j], pose[row, j]
    rows = int(beyond.any(axis=1).sum())
    return (
        f"pose: {name} = {value:.3g} rad ({np.rad2deg(value):.1f} deg) at row {row} is beyond the training range "
        f"|{name}| <= {np.rad2deg(limits[name]):g} deg ({source}; {rows} row(s) beyond): "
        f"the mesh there is an extrapolation"
    )


def _warn_beyond_training(
    au: np.ndarray, pose: np.ndarray, au_names: list[str], face: np.ndarray, release: Release, scale: str | None
) -> None:
    """One :class:`InputRangeWarning` (one line) for everything in a call's input beyond what the model was trained
    on: AUs above 1 given as numbers (``scale``, :func:`_check_au_scale`'s phrase), AUs above the training max or
    unsupported AUs given (:func:`aumesh.model.support.beyond_training`, from the release's recorded support), pose
    beyond the training range."""
    found = support.release_support(release)
    parts = [
        scale,
        None if found is None or not face.any() else support.beyond_training(au, au_names, face, found),
        _pose_beyond(pose, face, release),
    ]
    message = "; ".join(p for p in parts if p)
    if message:
        _warn(message)


@contextmanager
def logged_range_warnings(logger: logging.Logger, where: str) -> Iterator[None]:
    """Inside: :class:`InputRangeWarning` is caught and logged by ``logger``, one line each as ``"<where>: <line>"``
    (``aumesh predict``, ``aumesh animate``, the served model: a command's output, not Python's warning format);
    other warnings pass on as they are."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", InputRangeWarning)
        yield
    for w in caught:
        if issubclass(w.category, InputRangeWarning):
            logger.warning("%s: %s", where, w.message)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def _warn(message: str) -> None:
    """``warnings.warn`` an :class:`InputRangeWarning` at the first caller outside this module."""
    level, frame = 1, sys._getframe(0)
    while frame.f_code.co_filename == __file__ and frame.f_back is not None:
        frame, level = frame.f_back, level + 1
    warnings.warn(message, InputRangeWarning, stacklevel=level)


# --------------------------------------------------------------------------- prediction
def predict_mesh(release: ReleaseSource, aus: Any = None, pose: Any = None, *, strict: bool = False) -> np.ndarray:
    """Predict face meshes from AU intensities (and head pose) with a release.

    Parameters
    ----------
    release : str, path-like or mapping
        A release NPZ path or its loaded arrays (:func:`load_release`; load once when predicting
        many times).
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
        range (:func:`training_pose_limits`) is a warning.
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
    arrays = load_release(release)
    au, pose_rows, single = input_rows(arrays, aus, pose, strict=strict)
    meshes = predict_rows(arrays, au, pose_rows)
    return meshes[0] if single else meshes


def predict_rows(release: Release, au: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Meshes of rows already checked by :func:`input_rows` (no check here).

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


__all__ = [
    "AU_SCALE_MAX",
    "FACE_SCORE_COLUMN",
    "MAX_ABS_POSE_RAD",
    "ColumnSelection",
    "InputRangeWarning",
    "PredictionInputError",
    "ReleaseError",
    "check_release",
    "input_rows",
    "load_release",
    "logged_range_warnings",
    "predict_mesh",
    "closest_name",
    "predict_rows",
    "select_columns",
    "short_list",
    "training_pose_limits",
]
