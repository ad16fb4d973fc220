"""The frame tables' data contract, checked with pandera: pure functions on one chunk of rows.

Every pass over the tables (pandas today, Dask partitions tomorrow) calls the same functions:

* :func:`validate_metadata` — the AU/pose/id columns of a chunk: numeric (text is an error unless
  ``data.coerce_numeric``), finite, AUs in py-feat's 0–1 range, pose within ±π, ids present;
* :func:`numeric_values` — one column of text converted to float, or an error naming the first bad
  row and value;
* :func:`check_pose_units` — pose judged from its distribution (a still subject in degrees has every
  value below π but a median far beyond any plausible head pose in radians); :func:`check_pose_medians`
  the same check on medians computed elsewhere (the prepare stage's exact quantiles over partitions);
* :func:`check_filter_shares` — a filter that drops more than ``preprocess.max_drop_fraction``
  of what it sees points at wrong units or scale, not at the data.

Errors are :class:`~aumesh.core.errors.TableError` naming the file, the column, the first bad row
(0-based within the file) and value, and the fix.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import pandera.pandas as pa

from aumesh.core.errors import TableError
from aumesh.core.schema import AU_COLUMNS, FRAME_COLUMN, POSE_COLUMNS, VIDEO_COLUMN

AU_RANGE = (0.0, 1.0)  # py-feat's AU intensities (OpenFace's are 0-5)
OPENFACE_MAX = 5.0
# Radians, judged from the distribution: a median |angle| beyond 1 rad (57 degrees) is no set of faces the
# card's pose limits (30/40 degrees) could use, while a near-still subject recorded in degrees (values of a
# few units, every one below pi) lands there. Smaller degree values make the pose filter drop most frames,
# which check_filter_shares reports as units.
MAX_MEDIAN_ABS_POSE_RAD = 1.0
COERCE_HINT = "set data.coerce_numeric=true to convert numbers stored as text"


def _finite(series: pd.Series) -> pd.Series:
    return pd.Series(np.isfinite(series.to_numpy(dtype=np.float64, na_value=np.nan)), index=series.index)


def _schema() -> pa.DataFrameSchema:
    """The metadata columns' contract (dtype, NaN, inf, range); the column order is the report order."""
    au = [pa.Check(_finite, name="finite"), pa.Check.in_range(*AU_RANGE)]
    pose = [pa.Check(_finite, name="finite"), pa.Check.in_range(-np.pi, np.pi)]
    columns = {VIDEO_COLUMN: pa.Column(str, nullable=False), FRAME_COLUMN: pa.Column(nullable=False)}
    columns |= {c: pa.Column("float64", au, nullable=False) for c in AU_COLUMNS}
    columns |= {c: pa.Column("float64", pose, nullable=False) for c in POSE_COLUMNS}
    return pa.DataFrameSchema(columns, strict=False, coerce=False)


METADATA_SCHEMA = _schema()


def numeric_values(values, path: Path | str, column: str, row_offset: int = 0) -> np.ndarray:
    """Text holding numbers -> float64; an error naming the first value that is not a number.

    Parameters
    ----------
    values : array-like, shape (n,)
        One column of one chunk (strings, or numbers stored as objects).
    row_offset : int
        Row of ``values[0]`` within the file, for the message.
    """
    series = pd.Series(np.asarray(values, dtype=object))
    parsed = pd.to_numeric(series, errors="coerce")
    bad = parsed.isna().to_numpy() & ~series.isna().to_numpy()
    bad |= series.map(lambda v: isinstance(v, str) and not v.strip()).to_numpy(dtype=bool)  # "" is not a number
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise TableError(
            f"{path}: column {column!r} holds a value that is not a number at row {row_offset + row}: "
            f"{series.iloc[row]!r} ({int(bad.sum())} such in this chunk). Fix: write missing values as NaN (and drop "
            f"those frames) or remove the text before `dvc add data`."
        )
    return parsed.to_numpy(dtype=np.float64)


def text_error(path: Path | str, column: str, first_value, row: int = 0) -> TableError:
    """A numeric column stored as text, refused (``data.coerce_numeric`` is off)."""
    return TableError(
        f"{path}: column {column!r} is stored as text, not numbers (row {row}: {first_value!r}; e.g. after a CSV "
        f"round trip). Fix: write float columns (df[cols].astype(float)) before `dvc add data`, or {COERCE_HINT}."
    )


def _numeric_frame(df: pd.DataFrame, path: Path | str, row_offset: int, coerce: bool) -> pd.DataFrame:
    """Widen integer/float32 AU and pose columns to float64 (exact); text only when ``coerce``. Columns are replaced,
    never written into, so ``df`` is left as it was without a deep copy of every column (a partition's ~14 MiB)."""
    out = df.copy(deep=False)
    for col in (*AU_COLUMNS, *POSE_COLUMNS):
        if col not in out:
            continue
        kind = out[col].dtype.kind
        if kind in "fiub":
            out[col] = out[col].to_numpy(dtype=np.float64)
        elif coerce:
            out[col] = numeric_values(out[col].to_numpy(), path, col, row_offset)
        else:
            values = out[col].to_numpy(dtype=object)
            numeric_values(values, path, col, row_offset)  # a non-number: name it first
            raise text_error(path, col, values[0], row_offset)
    return out


def validate_metadata(
    df: pd.DataFrame,
    path: Path | str,
    row_offset: int = 0,
    coerce: bool = False,
    row_name: Callable[[int], str] | None = None,
) -> pd.DataFrame:
    """Check one chunk of metadata rows against :data:`METADATA_SCHEMA`; return it with float64 AU/pose columns.

    Parameters
    ----------
    df : DataFrame, shape (n, 2 + 20 + 3)
        ``video_id``, ``frame``, the 20 AUs, Pitch, Yaw, Roll of consecutive rows of one file.
    path : path of the file, for the message.
    row_offset : row of ``df``'s first row in the file.
    coerce : convert AU/pose columns stored as text (``data.coerce_numeric``).
    row_name : names row ``i`` of ``df`` in the user's file (the ingest stage: "line 7" of a CSV); default
        ``"row {row_offset + i}"``.

    Raises
    ------
    TableError
        Text in a numeric column, NaN/inf, an all-NaN column, AUs outside 0-1, pose beyond ±π.
    """
    out = _numeric_frame(df.reset_index(drop=True), path, row_offset, coerce)
    try:
        # in place: the schema only checks (no coercion), and pandera would otherwise check a deep copy of ``out``
        METADATA_SCHEMA.validate(out, lazy=True, inplace=True)
    except pa.errors.SchemaErrors as err:
        raise _first_failure(err.failure_cases, out, path, row_name or (lambda i: f"row {row_offset + i}")) from None
    return out


def _first_failure(cases: pd.DataFrame, df: pd.DataFrame, path, row_name: Callable[[int], str]) -> TableError:
    order = {c: i for i, c in enumerate(METADATA_SCHEMA.columns)}
    cases = cases.assign(_order=cases["column"].map(order).fillna(len(order))).sort_values("_order", kind="stable")
    column = str(cases["column"].iloc[0])
    mine = cases[cases["column"] == column]
    checks = [str(c) for c in mine["check"]]
    values = df[column] if column in df else pd.Series(dtype=float)
    n = len(values)
    missing = values.isna().to_numpy() if n else np.zeros(0, bool)

    def first(mask: np.ndarray) -> tuple[str, object]:
        i = int(np.flatnonzero(mask)[0])
        return row_name(i), values.iloc[i]

    if any(c.startswith("dtype") for c in checks):
        return TableError(
            f"{path}: column {column!r} has dtype {values.dtype}, need {METADATA_SCHEMA.columns[column].dtype}. "
            f"Fix: write it as py-feat does (video_id text, frame and the AU/pose columns numbers)."
        )
    if missing.all() and n:
        return TableError(
            f"{path}: column {column!r} is empty (all {n} values are NaN): the detector did not produce it, and "
            f"dropping frames would drop every frame. Fix: re-export the table with a model that outputs "
            f"{column!r} (py-feat's Detector gives all 20 AUs and pose)."
        )
    x = values.to_numpy(dtype=np.float64, na_value=np.nan) if values.dtype.kind in "fiub" else np.zeros(n)
    bad = ~np.isfinite(x) | missing
    if bad.any():
        row, value = first(bad)
        return TableError(
            f"{path}: column {column!r} has {int(bad.sum())} NaN/inf value(s) (first at {row}: {value}) in rows with a "
            f"face (py-feat's no-face rows, every measurement NaN, are dropped by the ingest stage itself): a corrupt or "
            f"partial export. Fix: re-export those videos with py-feat, or drop those rows before `dvc add data`."
        )
    if column in AU_COLUMNS:
        bad = (x < AU_RANGE[0]) | (x > AU_RANGE[1])
        row, value = first(bad)
        top = float(np.max(x))
        if AU_RANGE[1] < top <= OPENFACE_MAX and float(np.min(x)) >= 0.0:
            hint = (
                f"values reach {top:g}: this looks like OpenFace's 0-5 intensity scale. Fix: divide every AU "
                f"column by 5 (py-feat's scale is 0-1) before `dvc add data`."
            )
        else:
            hint = f"Fix: AU intensities are py-feat's probabilities in [{AU_RANGE[0]:g}, {AU_RANGE[1]:g}]."
        return TableError(f"{path}: column {column!r} is outside 0-1 at {row} ({value:g}); {hint}")
    if column in POSE_COLUMNS:
        top = float(np.max(np.abs(x)))
        return TableError(
            f"{path}: column {column!r} reaches {top:.1f}, more than pi: pose looks like degrees. Fix: convert "
            f"{', '.join(POSE_COLUMNS)} to radians (np.deg2rad) before `dvc add data`."
        )
    row = row_name(int(mine["index"].dropna().iloc[0])) if mine["index"].notna().any() else row_name(0)
    return TableError(f"{path}: column {column!r} fails check {checks[0]} at {row}.")


def check_pose_units(pose: np.ndarray, where: str | Path) -> None:
    """Pose in radians, judged from the distribution, not only the maximum.

    Parameters
    ----------
    pose : ndarray, shape (n, 3)
        Pitch, Yaw, Roll of the frames (all tables, before any filter).
    where : what to name in the message (the data folder or a file).

    Raises
    ------
    TableError
        The median |angle| of a pose column exceeds :data:`MAX_MEDIAN_ABS_POSE_RAD` (1 rad, 57 deg):
        degrees from a (near-)still subject, whose values all stay below pi.
    """
    if len(pose) == 0:
        return
    check_pose_medians(np.median(np.abs(np.asarray(pose, dtype=np.float64)), axis=0), where)


def pose_medians_may_exceed(n_above, n: int) -> bool:
    """Whether a median |angle| can exceed :data:`MAX_MEDIAN_ABS_POSE_RAD`, from the counts alone: ``n_above`` (3,)
    values of |Pitch|, |Yaw|, |Roll| above it among ``n``. A median reads the sorted values at ranks ``(n - 1) // 2``
    and ``n // 2``; it cannot exceed the limit while the upper one is at or below it, that is while at most
    ``n - n // 2 - 1`` values are above. So the exact medians (passes over every frame) are needed only then."""
    return bool(np.any(np.asarray(n_above) > n - n // 2 - 1))


def check_pose_medians(median, where: str | Path) -> None:
    """:func:`check_pose_units` on the medians of |Pitch|, |Yaw|, |Roll| (3,) over the frames (computed elsewhere,
    e.g. by exact quantiles of a vector held in partitions)."""
    for name, m in zip(POSE_COLUMNS, median, strict=True):
        if m > MAX_MEDIAN_ABS_POSE_RAD:
            raise TableError(
                f"{where}: column {name!r} has median |{name}| = {m:.2f}: as radians that is {np.rad2deg(m):.0f} degrees, "
                f"beyond any head pose the card's pose limits keep: the pose looks like degrees. Fix: convert {', '.join(POSE_COLUMNS)} to "
                f"radians (np.deg2rad) before `dvc add data`."
            )


# filter name -> (counted in, what it drops, the likely cause, the option that allows it)
FILTERS = {
    "no-face rows": (
        "rows",
        "videos where py-feat rarely found a face (occlusion, a face_detection_threshold too high)",
    ),
    "pose filter": ("frames", "pose in degrees, or pose limits narrower than the data (preprocess.pose_filter)"),
    "wild values": (
        "frames",
        "a corrupt export (coordinates far outside the face), or a mesh in another layout "
        "(preprocess.alignment.max_vertex_iod)",
    ),
    "alignment outlier cut": (
        "frames",
        "landmarks in different units or layouts across tables (preprocess.alignment.outlier_quantile)",
    ),
    "empty videos": ("videos", "pose in degrees or filters too narrow for whole videos (preprocess.empty_video)"),
}


# filter name -> its count key in the prepared summary (``<key>_fraction`` is the share)
FILTER_KEYS = {
    "no-face rows": "dropped_no_face",
    "pose filter": "dropped_pose",
    "wild values": "dropped_wild_values",
    "alignment outlier cut": "dropped_alignment_outliers",
    "empty videos": "videos_dropped_no_frames_left",
}


def filter_shares(counts: Mapping[str, int]) -> dict[str, dict]:
    """Counts and fractions dropped by each filter (no-face rows, pose filter, wild values, alignment outlier cut, empty
    videos) in ``counts``
    (the prepared summary's counts, or the part known so far)."""
    after_pose = counts["frames_in"] - counts["dropped_pose"]
    seen = {
        "no-face rows": counts.get("rows_in", 0),
        "pose filter": counts["frames_in"],
        "wild values": after_pose,
        "alignment outlier cut": after_pose - counts.get("dropped_wild_values", 0),
        "empty videos": counts.get("videos_in", 0),
    }
    out = {name: (counts[key], seen[name]) for name, key in FILTER_KEYS.items() if key in counts}
    return {
        name: {"dropped": int(d), "of": int(n), "fraction": (d / n if n else 0.0), "unit": FILTERS[name][0]}
        for name, (d, n) in out.items()
    }


def check_filter_shares(shares: Mapping[str, Mapping], max_fraction: float, where: str | Path) -> None:
    """Fail when a filter drops more than ``max_fraction`` of what it sees (``preprocess.max_drop_fraction``).

    Raises
    ------
    TableError
        Naming the filter, the count and fraction, the likely cause and the option that allows it.
    """
    for name, s in shares.items():
        if s["fraction"] > max_fraction:
            raise TableError(
                f"{where}: the {name} drops {s['dropped']} of {s['of']} {s['unit']} ({s['fraction']:.1%}), more than "
                f"preprocess.max_drop_fraction={max_fraction:g}. Likely cause: {FILTERS[name][1]}. Fix the data, or "
                f"allow it with preprocess.max_drop_fraction={min(1.0, round(s['fraction'] + 0.05, 2)):g}."
            )


def check_instrument_values(
    df: pd.DataFrame,
    instruments: Sequence[str],
    path: Path | str,
    first_row: int = 0,
    row_name: Callable[[int], str] | None = None,
) -> None:
    """Every instrument value (``model.eiv.instrument_aus``) a finite number.

    A frame the second detector has no value for is refused, not dropped: the instruments are the same frames'
    second measurement, so a missing one is an export to repair (dropping it silently would fit the model on other
    frames than ``model/eiv=none`` does), as a face row with only some values missing is the contract's error.

    Raises
    ------
    TableError
        One line naming the file, the column, the row (within the file; ``row_name(i)`` names row ``i`` of ``df``
        instead, e.g. its CSV line) and the fix.
    """
    for name in instruments:
        values = pd.to_numeric(df[name], errors="coerce").to_numpy(np.float64)
        bad = ~np.isfinite(values)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            at = row_name(row) if row_name is not None else f"row {first_row + row}"
            raise TableError(
                f"{path}: column {name!r} is {df[name].iloc[row]!r} at {at} ({int(bad.sum())} "
                f"such rows): model/eiv=instruments needs the second detector's AUs on every frame. Fix: drop "
                f"the frames the second detector missed from the tables, or use model/eiv=none."
            )
        df[name] = values


def check_family_values(
    df: pd.DataFrame, columns: Sequence[str], path: Path | str, first_row: int = 0, family: str = "family"
) -> None:
    """Every value of a carried family's ``columns`` (issue 46: the blendshapes or emotions the ingest stage carries)
    a finite number, as the AUs must be: a kept frame without them is an export to repair, never filled in.

    Raises
    ------
    TableError
        One line naming the file, the column, the row (within the file) and the fix.
    """
    for name in columns:
        values = pd.to_numeric(df[name], errors="coerce").to_numpy(np.float64)
        bad = ~np.isfinite(values)
        if bad.any():
            row = int(np.flatnonzero(bad)[0])
            raise TableError(
                f"{path}: {family} column {name!r} is {df[name].iloc[row]!r} at row {first_row + row} "
                f"({int(bad.sum())} such rows), a frame the other tables' {family} cover. Fix: drop those frames "
                f"from the table, or drop every {family} column of every table to train without them."
            )
        df[name] = values
