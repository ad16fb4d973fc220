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

The table is streamed, a chunk of rows at a time (:mod:`aumesh.pipeline.predict_stream`): memory is flat in its
rows. Files are written atomically. Input-range warnings (inputs beyond the training data, a table from another
detector than the release's: :mod:`aumesh.model.support`) are logged, one line each for the whole table.
"""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from aumesh.core.io import atomic_write_text
from aumesh.core.schema import AU_COLUMNS, FRAME_COLUMN, INPUT_PATH_COLUMN, VIDEO_COLUMN
from aumesh.export import meshfiles
from aumesh.geometry import face
from aumesh.model import support
from aumesh.model.inference import predict_rows
from aumesh.model.input_checks import InputRangeWarning, InputTally, logged_range_warnings
from aumesh.model.input_columns import ColumnSelection, PredictionInputError, short_list
from aumesh.pipeline import predict_stream
from aumesh.pipeline.predict_stream import choose_columns, table_header

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".ply")
OUT_SUFFIXES = (".npz", *MESH_SUFFIXES)


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
    wanted, selection = choose_columns(path, header, au_columns, ignore, strict, keys)
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
    chunk_rows: int | None = None,
) -> tuple[Path, int]:
    """Predict one mesh per table row and write them to ``out`` (``.npz``, or ``.obj`` / ``.ply`` for one row).

    The table is streamed (:mod:`aumesh.pipeline.predict_stream`): ``chunk_rows`` rows are read, checked, predicted
    and written at a time, so memory does not grow with the table's rows (a 1M-row py-feat CSV needed ~23 GB when
    the table and its meshes were held whole). The input checks are summed over the chunks
    (:class:`aumesh.model.input_checks.InputTally`): one range warning a run, rows numbered from the table's start.

    Parameters
    ----------
    release, table, out : str or path-like
        The release NPZ, the input table (CSV or parquet; a whole py-feat table or input columns
        only, see the module's docstring) and the file to write.
    ignore : sequence of str
        Table columns to leave out.
    strict : bool
        Every column (after ``ignore``) must be an input column, as before whole tables were taken.
    chunk_rows : int, optional
        Rows predicted at a time (default :data:`aumesh.pipeline.predict_stream.CHUNK_ROWS`); the output does not
        depend on it.

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
    arrays, family, rename = _release_and_names(release, table, ignore, strict)
    source = predict_stream.open_table(
        table,
        [str(a) for a in np.asarray(arrays["au_columns"]).tolist()],
        ignore,
        strict=strict,
        keys=KEY_COLUMNS,
        rename=rename,
    )
    if suffix in MESH_SUFFIXES and source.n_rows != 1:
        raise PredictionInputError(
            f"{table} has {source.n_rows} rows; {suffix} holds one mesh. Fix: write .npz, or give a one-row table"
        )
    tally = InputTally()
    with logged_range_warnings(log, str(table)):
        # the detector check's words are the AUs' (their two spaces); a family's inputs are checked by their ranges
        mismatch = (
            support.detector_mismatch(
                support.table_detector(source.header, str(table)), support.release_support(arrays), "table"
            )
            if family == "au"
            else None
        )
        if mismatch:
            warnings.warn(mismatch, InputRangeWarning, stacklevel=1)
        if suffix == ".npz":
            predict_stream.write_npz(arrays, source, out, tally, chunk_rows or predict_stream.CHUNK_ROWS)
        else:
            _write_mesh_file(arrays, source, out, release, tally)
        message = tally.range_message(arrays)
        if message and family != "au":
            message = message.replace("aus: ", f"{family}: ")
        if message:
            warnings.warn(message, InputRangeWarning, stacklevel=1)
    if tally.no_face:
        log.warning(
            "%s: %d of %d row(s) without a face (FaceScore 0, or every AU and pose value NaN): NaN meshes, "
            "no_face True in %s",
            table,
            tally.no_face,
            tally.rows,
            out.name,
        )
    log.info("predicted %d mesh(es) from %s with %s -> %s", tally.rows, table, release, out)
    return out, tally.rows


def _release_and_names(
    release: str | os.PathLike, table: str | os.PathLike, ignore: Sequence[str], strict: bool
) -> tuple[dict, str, dict[str, str]]:
    """The release's arrays as the predictor reads them (a family release through
    :func:`aumesh.model.family_inference.au_view`), its family, and the table's columns to rename to the family's
    names (Detectorv2's ``Happy`` -> ``happiness``; ``{}`` for the AUs). A whole table (columns besides the inputs)
    without one of the family's columns is one line naming the file, the column and the fix."""
    from aumesh.core.families import NAME_MAPS, family_columns
    from aumesh.core.schema import POSE_COLUMNS
    from aumesh.model import family_inference as fi
    from aumesh.model.input_columns import FACE_SCORE_COLUMN

    arrays = fi.load_any_release(release)
    family = fi.release_family(arrays)
    if family == "au":
        return arrays, family, {}
    header = [c for c in predict_stream.table_header(table) if c not in set(ignore)]
    known = set(NAME_MAPS[family]) | set(POSE_COLUMNS) | {FACE_SCORE_COLUMN, *KEY_COLUMNS}
    if not strict and any(c not in known for c in header):
        family_columns(header, family, str(table))
    return fi.au_view(arrays), family, fi.renamed(family, header)


def _write_mesh_file(arrays, source, out: Path, release, tally: InputTally) -> None:
    """The one row of ``source`` as an ``.obj`` / ``.ply`` mesh (triangles facing out of the face)."""
    (df,) = list(predict_stream.iter_chunks(source, 1))
    au, pose = predict_stream.checked_rows(arrays, df, source, tally)
    if np.isnan(au[0]).all():
        raise PredictionInputError(
            f"{source.path}: row 0 has no face (FaceScore 0, or every AU and pose value NaN); "
            f"{out.suffix.lower()} needs a mesh. Fix: give a row with a face, or write .npz"
        )
    mesh = predict_rows(arrays, au, pose)[0]
    tri = face.outward_triangles(mesh, face.triangulate(mesh))
    comment = f"aumesh predict: {Path(release).name}, row 0 of {source.path.name}"
    text = (
        meshfiles.obj_text(mesh, tri, comment)
        if out.suffix.lower() == ".obj"
        else meshfiles.ply_text(mesh, tri, comment)
    )
    atomic_write_text(out, text)
