"""Which columns of a table the model takes: picked by name from the header, and the errors that name them.

py-feat's detector tables (Fex output, CSV or parquet, MPDetector or Detectorv2) have 2,000 columns besides the
20 AUs and the pose; a table of input columns only may leave AUs out (0). :func:`select_columns` tells the two apart
from the header alone (a reader then reads only those columns), and a missing or unknown name is one line with the
closest name (:func:`closest_name`: ``did you mean 'AU12'?``), never every column. The values are checked by
:mod:`aumesh.model.input_checks`.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from aumesh.core.errors import UserError
from aumesh.core.schema import AU_COLUMNS, POSE_COLUMNS

# py-feat's face-detection confidence: 0 (MPDetector) or NaN (Detectorv2) on the one row of a frame without a face.
FACE_SCORE_COLUMN = "FaceScore"


class PredictionInputError(UserError, ValueError):
    """AU or pose input that the model cannot take as it is; the message names the column and the fix."""


@dataclass(frozen=True)
class ColumnSelection:
    """The columns of a table that :func:`aumesh.model.input_checks.input_rows` uses, chosen from its header by
    :func:`select_columns`.

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


__all__ = [
    "FACE_SCORE_COLUMN",
    "ColumnSelection",
    "PredictionInputError",
    "closest_name",
    "select_columns",
    "short_list",
]
