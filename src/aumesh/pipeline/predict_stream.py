"""``aumesh predict``'s table streamed: chunks of rows in, checked and predicted, chunks of meshes out.

Holding a table and its meshes whole cost ~23 KB a row (a 1M-row py-feat CSV, 162 MB, needed ~23 GB). Here:

- the table is read ``chunk_rows`` rows at a time, its needed columns only: a CSV a byte range of
  :data:`CSV_BLOCK_BYTES` at a time (whole lines, parsed by pyarrow's CSV reader), a parquet file by record batches
  (``ParquetFile.iter_batches``). The rows are counted first (the parquet footer; a CSV by one pass of the same
  reader over one column), since an ``.npy`` header states its shape before its rows;
- each chunk goes through :func:`aumesh.model.input_checks.input_rows` with one :class:`InputTally` for the table:
  errors name the table's row, and the warnings are said once for the whole table by the caller;
- the meshes are written into the output NPZ's ``meshes`` entry as they come (:class:`aumesh.core.npz_stream
  .NpzStream`); the other per-row arrays (``no_face``, ``au``, ``pose``, the join keys) go to ``.npy`` files in a
  scratch folder beside the output and are copied into the NPZ after it (~200 bytes a row, on disk);
- py-feat's ``face`` index (the face's number within its frame) needs the whole table's (video, frame) keys: it is
  computed at the end from the scratch files (~30 bytes a row in memory, the one part that grows with the rows).

The NPZ equals what the one-shot reader (:func:`aumesh.pipeline.predict.read_table` + ``np.savez``) wrote: the same
keys, dtypes and values for any ``chunk_rows`` (tests/test_predict_stream.py).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from aumesh.core.errors import MissingFileError, UserError
from aumesh.core.io import NpyRowFile, atomic_path, create_npy, scratch_directory
from aumesh.core.npz_stream import NpzStream
from aumesh.core.schema import FRAME_COLUMN, INPUT_PATH_COLUMN, POSE_COLUMNS, VIDEO_COLUMN
from aumesh.data import pyfeat, readers
from aumesh.model.inference import predict_rows
from aumesh.model.input_checks import InputTally, input_rows
from aumesh.model.input_columns import ColumnSelection, PredictionInputError, closest_name, select_columns, short_list

TABLE_SUFFIXES = (".csv", ".parquet")
#: Rows checked and predicted at a time: ~17 KB a row in flight (the float64 mesh, its float32 copy), ~70 MB.
CHUNK_ROWS = 4096
#: CSV bytes pyarrow parses at a time (a py-feat row is ~20-40 KB: a few hundred rows; input columns only: ~25,000).
CSV_BLOCK_BYTES = 8 << 20
#: Rows copied at a time from the scratch files into the NPZ.
COPY_ROWS = 1 << 16
#: The CSV cells read as missing: pandas' ``read_csv`` defaults (the one-shot reader's), so both read alike.
CSV_NA = [
    *("", "#N/A", "#N/A N/A", "#NA", "-1.#IND", "-1.#QNAN", "-NaN", "-nan", "1.#IND", "1.#QNAN", "<NA>", "N/A"),
    *("NA", "NULL", "NaN", "None", "n/a", "nan", "null"),
]


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
        if path.suffix.lower() == ".csv":  # the ingest's header reader: a BOM accepted, ';' or NUL bytes named
            names = readers.csv_header(path)
        else:
            import pyarrow.parquet as pq

            names = [str(c) for c in pq.read_schema(path).names]
        pyfeat.check_unique_names(names, str(path))  # a column read twice: which one to use is unknown
    except UserError:  # the header reader's one line (file, line, fix) as it is
        raise
    except (OSError, ValueError) as exc:  # pandas' EmptyDataError, ParserError and pyarrow's ArrowInvalid: ValueErrors
        raise PredictionInputError(f"{path}: not a readable {path.suffix[1:]} table ({exc})") from exc
    return names


def choose_columns(
    path: Path,
    header: Sequence[str],
    au_columns: Sequence[str],
    ignore: Sequence[str],
    strict: bool,
    keys: Sequence[str],
) -> tuple[list[str], ColumnSelection]:
    """The columns to read of a table with ``header``: the model's inputs (and ``FaceScore``) chosen by
    :func:`aumesh.model.input_columns.select_columns` after ``ignore``, then the ``keys`` the table has.

    Raises
    ------
    PredictionInputError
        An ``ignore`` column the table lacks (with the closest name), or a missing or (``strict``) unknown column.
    """
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
    return wanted, selection


@dataclass(frozen=True)
class TableSource:
    """A table opened for streaming: its header, the columns read, the model's selection and its row count."""

    path: Path
    header: list[str]
    columns: list[str]
    selection: ColumnSelection
    n_rows: int
    #: header column -> the name the model reads it by (a family release: Detectorv2's ``Happy`` -> ``happiness``)
    rename: tuple[tuple[str, str], ...] = ()

    @property
    def video(self) -> str | None:
        """The column naming each row's video: py-feat's ``input`` path, else ``video_id`` (None: neither read)."""
        return next((c for c in (INPUT_PATH_COLUMN, VIDEO_COLUMN) if c in self.columns), None)

    @property
    def csv(self) -> bool:
        return self.path.suffix.lower() == ".csv"


def open_table(
    path: str | os.PathLike,
    au_columns: Sequence[str],
    ignore: Sequence[str] = (),
    *,
    strict: bool = False,
    keys: Sequence[str] = (),
    rename: Mapping[str, str] | None = None,
) -> TableSource:
    """A table's header, the columns to read (:func:`choose_columns`) and its rows counted. ``rename``: header
    columns the model knows by another name (a family release's inputs under Detectorv2's names), chosen by that name
    and read under it (:func:`iter_chunks`).

    Raises
    ------
    FileNotFoundError, PredictionInputError
        As :func:`table_header` and :func:`choose_columns`; a table without rows.
    """
    path = Path(path)
    header = table_header(path)
    rename = dict(rename or {})
    back = {v: k for k, v in rename.items()}
    named = [rename.get(c, c) for c in header]
    columns, selection = choose_columns(path, named, au_columns, [rename.get(c, c) for c in ignore], strict, keys)
    columns = [back.get(c, c) for c in columns]  # read by the header's names
    # nothing to read (a table of other columns only, not strict): one column still carries the row count
    source = TableSource(path, header, columns or [c for c in header if c not in set(ignore)][:1], selection, 0)
    n_rows = _count_rows(source)
    if not n_rows:
        raise PredictionInputError(f"{path}: no rows to predict")
    return TableSource(path, header, source.columns, selection, n_rows, tuple(rename.items()))


def _count_rows(source: TableSource) -> int:
    """Rows of the table: the parquet footer's count; a CSV read through by the streaming reader, one column."""
    if not source.csv:
        import pyarrow.parquet as pq

        return int(pq.read_metadata(source.path).num_rows)
    import pyarrow.csv as pacsv

    one = source.columns[:1]
    convert = pacsv.ConvertOptions(include_columns=one, column_types=dict.fromkeys(one, _string()))
    return sum(batch.num_rows for batch in _csv_batches(source, convert))


def _string():
    import pyarrow as pa

    return pa.string()


def _csv_batches(source: TableSource, convert) -> Iterator:
    """The CSV's rows as Arrow tables, one byte range of about :data:`CSV_BLOCK_BYTES` (cut at a line end) at a time,
    each parsed by pyarrow's multi-threaded reader as :func:`aumesh.data.readers._read_csv_span` parses a range.

    Not ``pyarrow.csv.open_csv``: its streaming reader reads blocks ahead of the consumer without a bound the caller
    sets (measured: +246 MiB of RSS for a 181 MB CSV whose rows were only counted, +62 MiB with 1 MB blocks), so
    memory grew with the file; one range in flight keeps it flat. py-feat's CSVs (pandas' ``to_csv``) have no line
    breaks inside quoted fields, as :func:`aumesh.data.readers.csv_spans` assumes.
    """
    import io

    import pyarrow as pa
    import pyarrow.csv as pacsv

    read = pacsv.ReadOptions(column_names=source.header, use_threads=True, block_size=CSV_BLOCK_BYTES + (1 << 20))
    try:
        with open(source.path, "rb") as fh:
            fh.readline()  # the header (its names: source.header)
            while True:
                data = fh.read(CSV_BLOCK_BYTES)
                if not data:
                    break
                if not data.endswith(b"\n"):
                    data += fh.readline()  # the rest of the range's last line
                yield pacsv.read_csv(io.BytesIO(data), read_options=read, convert_options=convert)
    except (pa.ArrowException, OSError) as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise PredictionInputError(
            f"{source.path}: cannot read the columns {short_list(source.columns)} ({message}). Fix: numbers as "
            f"numbers, missing values empty or NaN (--ignore a key column that is not)"
        ) from None


def iter_chunks(source: TableSource, chunk_rows: int) -> Iterator[pd.DataFrame]:
    """The table's columns (``source.columns``) ``chunk_rows`` rows at a time (fewer where a CSV block ends), in file
    order, typed as the one-shot reader (pandas) read them: inputs float64 (text cells an error naming the file),
    the video key as text (a CSV's empty cell ``"nan"``, as pandas), ``frame`` float64 (the NPZ's int64 when
    integral, :func:`write_npz`)."""
    if source.csv:
        import pyarrow as pa
        import pyarrow.csv as pacsv

        types = {c: pa.float64() for c in source.columns} | {
            k: pa.string() for k in (INPUT_PATH_COLUMN, VIDEO_COLUMN) if k in source.columns
        }
        convert = pacsv.ConvertOptions(
            include_columns=source.columns,
            column_types=types,
            null_values=CSV_NA,
            strings_can_be_null=True,
            quoted_strings_can_be_null=True,
        )
        batches = _csv_batches(source, convert)
    else:
        batches = _parquet_batches(source, chunk_rows)
    for batch in batches:
        for start in range(0, batch.num_rows, chunk_rows):
            df = batch.slice(start, chunk_rows).to_pandas()
            if source.csv and source.video is not None:
                df[source.video] = df[source.video].fillna("nan")  # pandas' read_csv: NaN, then astype(str)
            yield df.rename(columns=dict(source.rename)) if source.rename else df


def _parquet_batches(source: TableSource, chunk_rows: int) -> Iterator:
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        yield from pq.ParquetFile(source.path).iter_batches(batch_size=chunk_rows, columns=source.columns)
    except (pa.ArrowException, OSError) as exc:
        raise PredictionInputError(
            f"{source.path}: cannot read the columns {short_list(source.columns)} ({exc})"
        ) from None


def checked_rows(
    arrays: Mapping[str, np.ndarray], df: pd.DataFrame, source: TableSource, tally: InputTally
) -> tuple[np.ndarray, np.ndarray]:
    """A chunk's (n, 20) AUs and (n, 3) pose, checked and counted into ``tally``; errors name the table's row."""
    try:
        au, pose, _ = input_rows(arrays, df, selection=source.selection, tally=tally)
    except PredictionInputError as exc:
        raise PredictionInputError(f"{source.path}: {exc}") from exc
    return au, pose


def write_npz(
    arrays: Mapping[str, np.ndarray], source: TableSource, out: str | os.PathLike, tally: InputTally, chunk_rows: int
) -> Path:
    """Predict every row of ``source`` and write the NPZ of :mod:`aumesh.pipeline.predict` (atomically), a chunk at a
    time: ``meshes`` (N, 478, 3) float32, ``no_face``, ``au``, ``pose``, ``au_columns``, ``pose_columns`` and the
    join keys ``input``, ``frame``, ``face`` when the table has them."""
    out = Path(out)
    n = source.n_rows
    out.parent.mkdir(parents=True, exist_ok=True)
    scratch = scratch_directory(out)
    try:
        files = {
            "no_face": (np.bool_, (n,)),
            "au": (np.float64, (n, len(arrays["au_columns"]))),
            "pose": (np.float64, (n, len(POSE_COLUMNS))),
        }
        if source.video is not None:
            files["video_code"] = (np.int64, (n,))
        if FRAME_COLUMN in source.columns:
            files["frame"] = (np.float64, (n,))
        for name, (dtype, shape) in files.items():
            create_npy(scratch / f"{name}.npy", dtype, shape)
        names: dict[str, int] = {}
        integral = True
        with atomic_path(out, suffix=".npz") as tmp, NpzStream(tmp) as npz:
            with npz.array("meshes", np.float32, (n, *predict_rows(arrays, *_neutral(arrays)).shape[1:])) as meshes:
                handles = {name: NpyRowFile(scratch / f"{name}.npy", writable=True) for name in files}
                try:
                    for df in iter_chunks(source, chunk_rows):
                        first = tally.rows
                        au, pose = checked_rows(arrays, df, source, tally)
                        if tally.rows > n:
                            raise PredictionInputError(f"{source.path}: more rows than counted; it changed while read")
                        meshes.write(predict_rows(arrays, au, pose).astype(np.float32))
                        handles["no_face"].write(first, np.isnan(au).all(axis=1))
                        handles["au"].write(first, au)
                        handles["pose"].write(first, pose)
                        if "video_code" in handles:
                            handles["video_code"].write(first, _codes(df[source.video], names))
                        if "frame" in handles:
                            frame = _frames(df[FRAME_COLUMN], source.path)
                            integral &= bool(np.isfinite(frame).all() and (frame == np.round(frame)).all())
                            handles["frame"].write(first, frame)
                finally:
                    for h in handles.values():
                        h.close()
                if tally.rows != n:  # fewer rows than counted: the file changed while read
                    raise PredictionInputError(f"{source.path}: {tally.rows} rows read of {n} counted; it changed")
            for name in ("no_face", "au", "pose"):
                _copy(npz, name, scratch / f"{name}.npy")
            npz.add("au_columns", np.asarray(arrays["au_columns"]))  # a family release: its inputs (``au`` too)
            if "family" in arrays:
                npz.add("family", np.asarray(arrays["family"]))
            npz.add("pose_columns", np.array(POSE_COLUMNS))
            _write_keys(npz, scratch, names, integral)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return out


def _neutral(arrays: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """One row of zeros: predicted once for the meshes' row shape."""
    return np.zeros((1, len(arrays["au_columns"]))), np.zeros((1, len(POSE_COLUMNS)))


def _codes(video: pd.Series, names: dict[str, int]) -> np.ndarray:
    """Each row's video as a number (the table's videos in order of first appearance, ``names``: kept across chunks),
    from its text as the one-shot reader wrote it (``astype(str)``)."""
    codes, uniques = pd.factorize(video.astype(str).to_numpy(), use_na_sentinel=False)
    table = np.array([names.setdefault(str(u), len(names)) for u in uniques], dtype=np.int64)
    return table[codes]


def _frames(values: pd.Series, path: Path) -> np.ndarray:
    try:
        return np.asarray(values.to_numpy(), dtype=np.float64)
    except (TypeError, ValueError):
        raise PredictionInputError(
            f"{path}: column {FRAME_COLUMN!r} is not numeric (py-feat writes frame numbers). "
            f"Fix: --ignore {FRAME_COLUMN} to write the meshes without it"
        ) from None


def _copy(npz: NpzStream, name: str, path: Path, convert=None, dtype=None) -> None:
    """A scratch ``.npy`` into the NPZ as entry ``name``, :data:`COPY_ROWS` rows at a time (``convert``: applied to
    each block, giving ``dtype``)."""
    with NpyRowFile(path) as src, npz.array(name, dtype or src.dtype, src.shape) as rows:
        for start in range(0, src.shape[0], COPY_ROWS):
            block = src.read(start, start + COPY_ROWS)
            rows.write(block if convert is None else convert(block))


def _write_keys(npz: NpzStream, scratch: Path, names: dict[str, int], integral: bool) -> None:
    """``input`` (N,) str, ``frame`` (N,) int64 when every frame is a whole number (else float64) and ``face`` (N,)
    int64, as :func:`aumesh.pipeline.predict.row_keys` makes them from a whole table."""
    video, frame = scratch / "video_code.npy", scratch / "frame.npy"
    if video.exists():
        text = np.array(list(names), dtype=str) if names else np.array([], dtype=str)
        _copy(npz, "input", video, convert=lambda codes: text[codes], dtype=text.dtype)
    if not frame.exists():
        return
    _copy(
        npz,
        "frame",
        frame,
        convert=(lambda f: f.astype(np.int64)) if integral else None,
        dtype=np.int64 if integral else None,
    )
    # py-feat's face index needs every (video, frame) key of the table at once: pandas' cumcount, as row_keys
    keys = {"frame": np.load(frame, mmap_mode="r")[:]}
    if video.exists():
        keys = {"video": np.load(video, mmap_mode="r")[:]} | keys
    face = pd.DataFrame(keys).groupby(list(keys), sort=False, dropna=False).cumcount().to_numpy(np.int64)
    npz.add("face", face)


__all__ = [
    "CHUNK_ROWS",
    "CSV_BLOCK_BYTES",
    "TableSource",
    "checked_rows",
    "choose_columns",
    "iter_chunks",
    "open_table",
    "table_header",
    "write_npz",
]
