"""``aumesh predict``: a release applied to a table of AU (+ pose) rows, meshes written to a file.

Reads a CSV or parquet table, one row per mesh, and picks the model's inputs by name:

- a whole detector table (py-feat's output, MPDetector or Detectorv2, 2,000+ columns): only the
  20 AUs ``AU01 .. AU43``, ``Pitch``, ``Yaw``, ``Roll`` (radians) and ``FaceScore`` are read as inputs, and
  ``input`` and ``frame`` as the rows' keys (the header decides, the rest of the file is never materialised); every
  other column is ignored;
- a table of input columns only: missing AUs are 0, no pose columns means pose 0;
- ``strict``: every column must be an input column (after ``ignore``).

A row without a face (``FaceScore`` 0, or every AU and pose value NaN: py-feat's row for a frame
where it found none) gets a mesh of NaN and ``no_face`` True; a row only partly NaN is an error
naming the row and the column. Meshes are predicted with :func:`aumesh.predict_mesh`'s checks and
written, by the output's suffix:

- ``.npz``: ``meshes`` (N, 478, 3) float32 in table row order, ``no_face`` (N,) bool, the inputs
  ``au`` (N, 20) and ``pose`` (N, 3) as the model used them (NaN on no-face rows), ``au_columns``
  and ``pose_columns``; and, when the table has them, the keys that join each mesh back to its py-feat row
  (:func:`row_keys`): ``input`` (N,) str (py-feat's video path, or ``video_id``), ``frame`` (N,) and ``face`` (N,)
  (the face's index within its frame: 0, 1, ... in file order);
- ``.obj`` / ``.ply``: one row only (with a face), the mesh with the project's triangulation
  (:func:`aumesh.geometry.face.triangulate`), triangles facing out of the face.

Files are written atomically. Input-range warnings (inputs beyond the training data, a table from another
detector than the release's: :mod:`aumesh.model.support`) are logged, one line each.
"""

from __future__ import annotations

import csv
import logging
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from aumesh.core.errors import MissingFileError
from aumesh.core.io import atomic_savez, atomic_write_text
from aumesh.core.schema import AU_COLUMNS, FRAME_COLUMN, INPUT_PATH_COLUMN, POSE_COLUMNS, VIDEO_COLUMN
from aumesh.data import pyfeat
from aumesh.export import meshfiles
from aumesh.geometry import face
from aumesh.model import support
from aumesh.model.inference import predict_rows
from aumesh.model.input_checks import InputRangeWarning, input_rows, logged_range_warnings
from aumesh.model.input_columns import ColumnSelection, PredictionInputError, closest_name, select_columns, short_list
from aumesh.model.release_check import load_release

log = logging.getLogger(__name__)

TABLE_SUFFIXES = (".csv", ".parquet")
MESH_SUFFIXES = (".obj", ".ply")
OUT_SUFFIXES = (".npz", *MESH_SUFFIXES)


def table_header(path: str | os.PathLike) -> list[str]:
    """The column names of a CSV or parquet table, read without its rows.

    Raises
    ------
    FileNotFoundError
        No such file (:class:`MissingFileError`).
    PredictionInputError
        Unsupported suffix, or a file that is not a readable table.
    """
    path = Path(path)
    if path.suffix.lower() not in TABLE_SUFFIXES:
        raise PredictionInputError(f"{path}: unsupported table type {path.suffix!r}; use {' or '.join(TABLE_SUFFIXES)}")
    if not path.is_file():
        raise MissingFileError(f"input table not found: {path}")
    try:
        if path.suffix.lower() == ".csv":
            names = [str(c) for c in pd.read_csv(path, nrows=0).columns]
            with open(path, newline="", encoding="utf-8", errors="replace") as fh:
                raw = next(csv.reader(fh), [])  # as written: pandas renames a second 'AU12' to 'AU12.1'
        else:
            import pyarrow.parquet as pq

            names = raw = [str(c) for c in pq.read_schema(path).names]
    except (OSError, ValueError) as exc:  # pandas' EmptyDataError, ParserError and pyarrow's ArrowInvalid: ValueErrors
        raise PredictionInputError(f"{path}: not a readable {path.suffix[1:]} table ({exc})") from exc
    pyfeat.check_unique_names(raw, str(path))  # a column read twice: which one to use is unknown
    return names


def read_table(
    path: str | os.PathLike,
    au_columns: Sequence[str] = AU_COLUMNS,
    ignore: Sequence[str] = (),
    *,
    strict: bool = False,
    keys: Sequence[str] = (),
) -> tuple[pd.DataFrame, ColumnSelection]:
    """The model-input columns of a CSV or parquet table (and ``FaceScore``), chosen from its header.

    Parameters
    ----------
    path : str or path-like
        ``.csv`` or ``.parquet``.
    au_columns : sequence of str
        The release's AU names.
    ignore : sequence of str
        Columns to leave out before choosing (each must exist), e.g. the pose columns of a detector
        table to predict frontal meshes.
    strict : bool
        Every remaining column must be an input column.
    keys : sequence of str
        Columns read besides (those the table has), never inputs: py-feat's ``input``, ``frame``
        (:func:`row_keys`).

    Returns
    -------
    df : pd.DataFrame, shape (N, k)
        Only the ``selection.columns`` (k <= 24) and ``keys``, in the file's row order; a 2,045-column py-feat CSV
        is parsed for those columns only (``usecols``; parquet: ``columns=``).
    selection : ColumnSelection
        Whether the table is a whole table, and its input columns (:func:`aumesh.model.input_columns.select_columns`).

    Raises
    ------
    FileNotFoundError
        No such file.
    PredictionInputError
        Unsupported suffix, an ``ignore`` column the table lacks, a missing or (``strict``) unknown
        column (named with the closest one), or no rows.
    """
    path = Path(path)
    header = table_header(path)
    absent = [c for c in ignore if c not in header]
    if absent:
        near = closest_name(absent[0], header)
        hint = f" (did you mean {near!r} for {absent[0]!r}?)" if near else ""
        raise PredictionInputError(
            f"{path}: --ignore names column(s) {short_list(absent)} that the table does not have{hint}"
        )
    dropped = set(ignore)
    selection = select_columns([c for c in header if c not in dropped], au_columns, strict=strict, what=str(path))
    wanted = selection.columns + [k for k in keys if k in header and k not in dropped and k not in selection.columns]
    try:
        if path.suffix.lower() == ".csv":
            df = pd.read_csv(path, usecols=wanted) if wanted else pd.read_csv(path).drop(columns=list(ignore))
        else:
            df = pd.read_parquet(path, columns=wanted)
    except (OSError, ValueError) as exc:
        raise PredictionInputError(f"{path}: cannot read the columns {short_list(wanted)} ({exc})") from exc
    if df.empty:
        raise PredictionInputError(f"{path}: no rows to predict")
    return df, selection


#: The columns that name a py-feat row: the video (py-feat's ``input`` path, else ``video_id``) and the frame.
KEY_COLUMNS = (INPUT_PATH_COLUMN, VIDEO_COLUMN, FRAME_COLUMN)


def row_keys(df: pd.DataFrame) -> dict[str, np.ndarray]:
    """What joins each mesh back to its py-feat row: ``input`` (N,) str (py-feat's video path, else ``video_id``),
    ``frame`` (N,) and ``face`` (N,) int64, the row's face index within its frame (0, 1, ... in file order, as py-feat
    writes a frame's faces one row each). Keys the table lacks are left out (a table of input columns has none); with
    a frame but no video column, faces are counted within each frame."""
    out: dict[str, np.ndarray] = {}
    video = next((c for c in (INPUT_PATH_COLUMN, VIDEO_COLUMN) if c in df.columns), None)
    if video is not None:
        out["input"] = df[video].astype(str).to_numpy().astype(str)
    if FRAME_COLUMN in df.columns:
        frame = df[FRAME_COLUMN].to_numpy()
        if np.issubdtype(frame.dtype, np.number) and np.isfinite(frame).all() and (frame == np.round(frame)).all():
            frame = frame.astype(np.int64)
        out["frame"] = frame
        by = [video, FRAME_COLUMN] if video is not None else [FRAME_COLUMN]
        out["face"] = df.groupby(by, sort=False, dropna=False).cumcount().to_numpy(np.int64)
    return out


def read_input_table(path: str | os.PathLike, ignore: Sequence[str] = (), *, strict: bool = False) -> pd.DataFrame:
    """The model-input columns of a CSV or parquet table, ``ignore`` columns dropped (:func:`read_table`'s table)."""
    return read_table(path, AU_COLUMNS, ignore, strict=strict)[0]


def predict_table(
    release: str | os.PathLike,
    table: str | os.PathLike,
    out: str | os.PathLike,
    ignore: Sequence[str] = (),
    *,
    strict: bool = False,
) -> tuple[Path, int]:
    """Predict one mesh per table row and write them to ``out`` (``.npz``, or ``.obj`` / ``.ply`` for one row).

    Parameters
    ----------
    release, table, out : str or path-like
        The release NPZ, the input table (CSV or parquet; a whole py-feat table or input columns
        only, see the module's docstring) and the file to write.
    ignore : sequence of str
        Table columns to leave out.
    strict : bool
        Every column (after ``ignore``) must be an input column, as before whole tables were taken.

    Returns
    -------
    (Path, int)
        The file written and the number of meshes (rows, no-face rows included: NaN, ``no_face`` True).

    Raises
    ------
    FileNotFoundError, ReleaseError, PredictionInputError
        A missing file, an unusable release, or table values the model cannot take (the message
        names the file, the column and the row).
    """
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in OUT_SUFFIXES:
        raise PredictionInputError(f"--out {out}: unsupported suffix {out.suffix!r}; use {', '.join(OUT_SUFFIXES)}")
    arrays = load_release(release)
    df, selection = read_table(
        table, [str(a) for a in np.asarray(arrays["au_columns"]).tolist()], ignore, strict=strict, keys=KEY_COLUMNS
    )
    with logged_range_warnings(log, str(table)):
        mismatch = support.detector_mismatch(
            support.table_detector(table_header(table), str(table)), support.release_support(arrays), "table"
        )
        if mismatch:
            warnings.warn(mismatch, InputRangeWarning, stacklevel=1)
        try:
            au, pose, _ = input_rows(arrays, df, selection=selection)
        except PredictionInputError as exc:
            raise PredictionInputError(f"{table}: {exc}") from exc
    no_face = np.isnan(au).all(axis=1)
    if suffix in MESH_SUFFIXES and len(df) != 1:
        raise PredictionInputError(
            f"{table} has {len(df)} rows; {suffix} holds one mesh. Fix: write .npz, or give a one-row table"
        )
    if suffix in MESH_SUFFIXES and no_face[0]:
        raise PredictionInputError(
            f"{table}: row 0 has no face (FaceScore 0, or every AU and pose value NaN); "
            f"{suffix} needs a mesh. Fix: give a row with a face, or write .npz"
        )
    meshes = predict_rows(arrays, au, pose)
    if no_face.any():
        log.warning(
            "%s: %d of %d row(s) without a face (FaceScore 0, or every AU and pose value NaN): NaN meshes, "
            "no_face True in %s",
            table,
            int(no_face.sum()),
            len(no_face),
            out.name,
        )
    if suffix == ".npz":
        atomic_savez(
            out,
            meshes=meshes.astype(np.float32),
            no_face=no_face,
            au=au,
            pose=pose,
            au_columns=np.asarray(arrays["au_columns"]),
            pose_columns=np.array(POSE_COLUMNS),
            **row_keys(df),
        )
    else:
        mesh = meshes[0]
        tri = face.outward_triangles(mesh, face.triangulate(mesh))
        comment = f"aumesh predict: {Path(release).name}, row 0 of {Path(table).name}"
        text = meshfiles.obj_text(mesh, tri, comment) if suffix == ".obj" else meshfiles.ply_text(mesh, tri, comment)
        atomic_write_text(out, text)
    log.info("predicted %d mesh(es) from %s with %s -> %s", len(meshes), table, release, out)
    return out, len(meshes)
