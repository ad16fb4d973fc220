"""The inputs of a prediction checked: AU and pose rows in the release's order, errors, and warnings beyond training.

Inputs are checked before any arithmetic (:func:`input_rows`): wrong lengths, partly NaN rows, AUs above py-feat's
0..1 in a detector's table and pose that looks like degrees are errors
(:class:`aumesh.model.input_columns.PredictionInputError`) that say what was expected; a frame without a face
(``FaceScore`` 0, or every value NaN) is a row of NaN. Input the model takes but was not trained on (pose beyond the
training range, :func:`training_pose_limits`; AUs above 1 given as numbers; AUs beyond the data's support,
:mod:`aumesh.model.support`) is one :class:`InputRangeWarning` a call, pointing at the caller's line; rows without a
face, one :class:`NoFaceWarning` with their number. A caller that checks one input in blocks (``aumesh predict``'s
chunks) sums the findings in one :class:`InputTally` and says them once.
"""

from __future__ import annotations

import logging
import sys
import warnings
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from aumesh.core.schema import MAX_ABS_PITCH_DEG, MAX_ABS_YAW_DEG, POSE_COLUMNS
from aumesh.model import support
from aumesh.model.input_columns import (
    ColumnSelection,
    PredictionInputError,
    _check_pose_complete,
    _unknown_error,
    select_columns,
)
from aumesh.model.release_check import Release, _names

# A head turned more than 90 degrees is no longer a face seen from the front: any pose value above
# this (in radians) means the caller passed degrees. Training keeps |yaw| <= 40 deg, |pitch| <= 30 deg
# (the release's preprocess.pose_filter): beyond that, a warning (training_pose_limits).
MAX_ABS_POSE_RAD = np.pi / 2

# py-feat's AU intensities (both detectors) are 0..1, and so are the training tables'; OpenFace's are 0..5.
AU_SCALE_MAX = 1.0
_AU_SCALE_SLACK = 1e-6  # float32 rounding of a 1.0


class InputRangeWarning(UserWarning):
    """Input the model takes but was not trained on (pose beyond the training range, an AU above 1 given as
    numbers, an AU above its training max, an AU the training data never expressed given, a table from another
    detector than the release's), or an AU whose field the data does not identify (the release's identification
    screen); one line a call, naming the columns, the values and the training range. The mesh there is an
    extrapolation, or rests on a field that may point the wrong way."""


class NoFaceWarning(UserWarning):
    """Rows without a face (py-feat's row for a frame where it found none: ``FaceScore`` 0, or every AU and pose value
    NaN) were given: their meshes are NaN. One line a call with the number of such rows, as ``aumesh predict`` says
    in its own line and marks them ``no_face``."""


@dataclass
class InputTally:
    """What a prediction's input holds that its caller must be told, summed over the blocks of rows it comes in.

    :func:`input_rows` fills one per call and warns from it; a caller that feeds one input in blocks (``aumesh
    predict`` streaming a table chunk by chunk) passes the same tally to every block (``tally=``) and says it once at
    the end (:meth:`range_message`, :attr:`no_face`): one line a run, over the whole input, with the input's row
    numbers. Every field is a sum, a maximum, an "any" or a first occurrence, so blocks add up to the whole.

    Attributes
    ----------
    rows : int
        Rows checked so far; the next block's first row (its row numbers in messages are offset by it).
    no_face : int
        Rows without a face.
    scale : tuple of (int, str, float) or None
        The first AU above 1 given as numbers: (row, AU, value).
    largest : np.ndarray, shape (20,), or None
        Each AU's largest value over the face rows (:func:`aumesh.model.support.au_extent`); None before a face row.
    rows_above : int
        Face rows with an AU above its training max.
    pose : tuple of (int, int, float) or None
        The first Pitch or Yaw beyond the training range: (row, column in ``POSE_COLUMNS``, value).
    pose_rows : int
        Face rows with Pitch or Yaw beyond it.
    given : np.ndarray of bool, shape (20,), or None
        AUs non-zero in a face row (for the identification screen's warning).
    """

    rows: int = 0
    no_face: int = 0
    scale: tuple[int, str, float] | None = None
    largest: np.ndarray | None = None
    rows_above: int = 0
    pose: tuple[int, int, float] | None = None
    pose_rows: int = 0
    given: np.ndarray | None = None

    def add(self, release: Release, au: np.ndarray, pose: np.ndarray, face: np.ndarray, scale: Any) -> None:
        """Count a block of checked rows (``au`` (n, 20), ``pose`` (n, 3), ``face`` (n,) bool; ``scale`` the block's
        first AU above 1, :func:`_au_scale`, with the input's row number), then move :attr:`rows` past it."""
        au_names = _names(release["au_columns"])
        self.no_face += int((~face).sum())
        if self.scale is None and scale is not None:
            self.scale = scale
        found = support.release_support(release)
        if found is not None and face.any():
            largest, rows = support.au_extent(au, au_names, face, found)
            self.largest = largest if self.largest is None else np.maximum(self.largest, largest)
            self.rows_above += rows
        first, count = _pose_extent(pose, face, release)
        if self.pose is None and first is not None:
            self.pose = (first[0] + self.rows, first[1], first[2])
        self.pose_rows += count
        if face.any():
            given = (np.abs(np.nan_to_num(au[face])) > 0).any(axis=0)
            self.given = given if self.given is None else self.given | given
        self.rows += len(face)

    def range_message(self, release: Release) -> str | None:
        """The one :class:`InputRangeWarning` line for everything counted beyond the training data, or None: AUs
        above 1 given as numbers, AUs above the training max or unsupported AUs given (:mod:`aumesh.model.support`),
        pose beyond the training range, AUs the identification screen flags."""
        au_names = _names(release["au_columns"])
        found = support.release_support(release)
        parts = [
            None if self.scale is None else _scale_phrase(*self.scale),
            None
            if found is None or self.largest is None
            else support.beyond_phrase(self.largest, self.rows_above, au_names, found),
            _pose_phrase(self.pose, self.pose_rows, release),
            None if self.given is None else _unidentified_given(self.given, au_names, release),
        ]
        return "; ".join(p for p in parts if p) or None

    def no_face_message(self) -> str | None:
        """The one :class:`NoFaceWarning` line, or None when every row had a face."""
        if not self.no_face:
            return None
        return (
            f"aus: {self.no_face} of {self.rows} row(s) without a face (FaceScore 0, or every AU and pose value NaN: "
            f"py-feat's row for a frame where it found none): their meshes are NaN "
            f"(np.isnan(meshes).all(axis=(1, 2)) flags them)"
        )


def input_rows(
    release: Release,
    aus: Any = None,
    pose: Any = None,
    *,
    strict: bool = False,
    selection: ColumnSelection | None = None,
    tally: InputTally | None = None,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """AU and pose rows in the release's column order, checked (the inputs of
    :func:`aumesh.model.inference.predict_mesh`).

    Parameters
    ----------
    release : mapping
        Release arrays (:func:`aumesh.model.release_check.load_release`); ``au_columns`` gives the AU order,
        ``training_metadata`` the training pose range.
    aus, pose, strict
        As in :func:`predict_mesh`.
    selection : ColumnSelection, optional
        For a DataFrame ``aus``: the columns already chosen from the whole table's header
        (:func:`aumesh.model.input_columns.select_columns`), e.g. by a reader that read only those columns.
    tally : InputTally, optional
        A tally of the input's earlier blocks (a streamed table's chunks): these rows are added to it, row numbers in
        errors count from ``tally.rows``, and nothing is warned (the caller says :meth:`InputTally.range_message` and
        the no-face count once at the end). Default: this call's own tally, warned at the end of the call.

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
    NoFaceWarning
        One line with the number of rows without a face (their meshes are NaN).

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
    own = tally is None
    tally = InputTally() if tally is None else tally
    no_face = _no_face(au, pose_rows if pose_in_input else None, face_score, n)
    _check_finite(au, au_names, "aus", no_face, tally.rows)
    _check_finite(pose_rows, list(POSE_COLUMNS), "pose", no_face, tally.rows)
    if len(au) != n:
        au = np.repeat(au, n, axis=0)
    if len(pose_rows) != n:
        pose_rows = np.repeat(pose_rows, n, axis=0)
    if no_face.any():
        au, pose_rows = au.copy(), pose_rows.copy()
        au[no_face], pose_rows[no_face] = np.nan, np.nan
    face = ~no_face
    _check_radians(pose_rows[face])
    scale = _au_scale(au, au_names, face, refuse=whole, first_row=tally.rows)
    tally.add(release, au, pose_rows, face, scale)
    if own:
        message = tally.range_message(release)
        if message:
            _warn(message)
        message = tally.no_face_message()
        if message:
            _warn(message, NoFaceWarning)
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


def _check_finite(values: np.ndarray, names: list[str], what: str, no_face: np.ndarray, first_row: int = 0) -> None:
    """Refuse NaN/inf outside the no-face rows; ``values`` has len(no_face) rows or one row (for all); rows are
    named from ``first_row`` (a streamed table's chunk)."""
    skip = no_face if len(values) == len(no_face) else np.array([no_face.all()])
    bad = ~np.isfinite(values) & ~skip[:, None]
    if bad.any():
        row, col = (int(i) for i in np.argwhere(bad)[0])
        row += first_row
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


def _au_scale(
    au: np.ndarray, au_names: list[str], face: np.ndarray, refuse: bool, first_row: int = 0
) -> tuple[int, str, float] | None:
    """The first AU above 1 in a face row, as (row, AU, value) with rows counted from ``first_row``, or None; in a
    whole (detector's) table (``refuse``) an error instead."""
    bad = (au > AU_SCALE_MAX + _AU_SCALE_SLACK) & face[:, None]
    if not bad.any():
        return None
    row, col = (int(i) for i in np.argwhere(bad)[0])
    found = (row + first_row, au_names[col], float(au[row, col]))
    if refuse:
        raise PredictionInputError(
            f"{_scale_where(*found)}: py-feat's AU intensities, and the model's, are 0..1 (0..5 is OpenFace's scale). "
            f"Fix: divide the AU columns by 5"
        )
    return found


def _scale_where(row: int, name: str, value: float) -> str:
    return f"aus: {name} = {value:g} at row {row} is above {AU_SCALE_MAX:g}"


def _scale_phrase(row: int, name: str, value: float) -> str:
    """The warning's phrase for an AU above 1 given as numbers (:func:`_au_scale`'s first)."""
    return (
        f"{_scale_where(row, name, value)}, beyond the 0..1 scale the model was trained on (py-feat's); the mesh is "
        f"an extrapolation (OpenFace's 0..5 AUs: divide by 5)"
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


def _pose_extent(pose: np.ndarray, face: np.ndarray, release: Release) -> tuple[tuple[int, int, float] | None, int]:
    """The first face row's Pitch or Yaw beyond the training range, as (row, column, value), and the number of face
    rows beyond it; (None, 0) when none is."""
    if not face.any() or not (np.abs(pose[face]).max(initial=0.0) > 0):
        return None, 0
    limits, _ = training_pose_limits(release)
    beyond = np.zeros(pose.shape, dtype=bool)
    for name, limit in limits.items():
        j = POSE_COLUMNS.index(name)
        beyond[:, j] = face & (np.abs(pose[:, j]) > limit)
    if not beyond.any():
        return None, 0
    row, j = (int(i) for i in np.argwhere(beyond)[0])
    return (row, j, float(pose[row, j])), int(beyond.any(axis=1).sum())


def _pose_phrase(first: tuple[int, int, float] | None, rows: int, release: Release) -> str | None:
    """The warning's phrase for pose beyond the training range (:func:`_pose_extent`'s first and count), or None."""
    if first is None:
        return None
    limits, source = training_pose_limits(release)
    row, j, value = first
    name = POSE_COLUMNS[j]
    return (
        f"pose: {name} = {value:.3g} rad ({np.rad2deg(value):.1f} deg) at row {row} is beyond the training range "
        f"|{name}| <= {np.rad2deg(limits[name]):g} deg ({source}; {rows} row(s) beyond): "
        f"the mesh there is an extrapolation"
    )


def _unidentified_given(given_aus: np.ndarray, au_names: list[str], release: Release) -> str | None:
    """The phrase for AUs given (``given_aus`` (20,) bool: non-zero in a face row) that the release's identification
    screen flags
    (``au_identification_flagged``, docs/method.md eq. 6): their fields may point the wrong way under detector noise;
    their partner group is what the data identifies. None for a release without the screen, or none given."""
    if "au_identification_flagged" not in release:
        return None
    flagged = np.asarray(release["au_identification_flagged"], dtype=bool)
    partners = [str(p) for p in np.asarray(release["au_identification_partner"]).tolist()]
    sigma = np.asarray(release["au_identification_sigma_star"], dtype=np.float64)
    given = np.flatnonzero(flagged & given_aus)
    if not len(given):
        return None
    threshold = float(np.asarray(release["au_identification_flag_below"]))
    named = ", ".join(
        f"{au_names[k]} (sigma* {sigma[k]:.3f}; drive {'+'.join(sorted((au_names[k], partners[k])))})" for k in given
    )
    return (
        f"{named} given, but not identified under detector noise (the release's identification screen: sigma* < "
        f"{threshold:g}): the field may point the wrong way; its partner group is what the data identifies"
    )


@contextmanager
def logged_range_warnings(logger: logging.Logger, where: str) -> Iterator[None]:
    """Inside: :class:`InputRangeWarning` and :class:`NoFaceWarning` are caught and logged by ``logger``, one line
    each as ``"<where>: <line>"`` (``aumesh predict``, ``aumesh animate``, the served model: a command's output, not
    Python's warning format); other warnings pass on as they are."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", InputRangeWarning)
        warnings.simplefilter("always", NoFaceWarning)
        yield
    for w in caught:
        if issubclass(w.category, (InputRangeWarning, NoFaceWarning)):
            logger.warning("%s: %s", where, w.message)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


# The modules a call passes through before a warning is made (predict_mesh -> input_rows -> _warn): the warning points
# at the first frame outside them, the caller's line (a name, not an import: inference imports this module).
_OWN_MODULES = frozenset({__name__, "aumesh.model.inference", "aumesh.model.family_inference"})


def _warn(message: str, category: type[Warning] = InputRangeWarning) -> None:
    """``warnings.warn`` an :class:`InputRangeWarning` (or ``category``) at the first caller outside
    :data:`_OWN_MODULES`."""
    level, frame = 1, sys._getframe(0)
    while frame.f_globals.get("__name__") in _OWN_MODULES and frame.f_back is not None:
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)


__all__ = [
    "AU_SCALE_MAX",
    "MAX_ABS_POSE_RAD",
    "InputRangeWarning",
    "InputTally",
    "NoFaceWarning",
    "input_rows",
    "logged_range_warnings",
    "training_pose_limits",
]
