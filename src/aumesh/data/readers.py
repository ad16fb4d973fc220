"""py-feat's files as users have them, read: a file's layout (:class:`Source`), ranges of whole frames
(:class:`Span`) and their rows as arrays (:class:`Block`). What is done to those rows is :mod:`aumesh.data.ingest`'s
(no-face rows, face selection) and :mod:`aumesh.data.units`'s (the mesh to frame pixels); the column vocabulary is
:mod:`aumesh.data.pyfeat`'s.

Sources: py-feat's CSV (read with pyarrow's multi-threaded CSV reader, only the needed columns, types given, in
byte ranges of whole frames: bounded memory), a Fex saved as parquet (either detector), and the card's split layout
(a table plus an ``[N, 478, 3]`` ``.npy``).
"""

from __future__ import annotations

import csv
import gzip
import io
from collections.abc import Iterator, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, replace

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from aumesh.core import storage
from aumesh.core.errors import TableError, corrupt_parquet
from aumesh.core.io import NpyRowFile, check_npy
from aumesh.core.schema import AU_COLUMNS, FRAME_COLUMN, N_VERTICES
from aumesh.core.storage import InputPath, ObjectPath, StorageError
from aumesh.data import csv_text, pyfeat

CSV_SUFFIXES = (".csv", ".csv.gz")
PARQUET_SUFFIXES = (".parquet",)
#: CSV bytes parsed at a time: py-feat writes ~20 KB a row, so ~3,300 rows (~40 MB of float64 columns) per range.
CSV_RANGE_BYTES = 64 << 20
#: Parquet rows read at a time.
PARQUET_RANGE_ROWS = 16384


@dataclass(frozen=True)
class Source:
    """One input file of ``data/``: a py-feat CSV, a parquet table, or a parquet table with its mesh ``.npy``."""

    path: InputPath  # a local Path, or an object's URL (paths.data_dir=s3://..., aumesh.core.storage)
    kind: str  # csv | parquet
    layout: pyfeat.Layout
    header: tuple[str, ...]  # every column, in file order
    mesh_npy: InputPath | None = None
    n_rows: int | None = None  # parquet: rows (CSV: unknown until read)

    def absolute(self) -> Source:
        """The same source named by absolute paths (:func:`aumesh.core.io.absolute`): what partition tasks get, so a
        cluster worker in another directory reads this workspace's file (a URL stays as it is)."""
        return replace(
            self,
            path=storage.absolute(self.path),
            mesh_npy=None if self.mesh_npy is None else storage.absolute(self.mesh_npy),
        )


def is_table(path: InputPath) -> bool:
    return path.name.endswith(CSV_SUFFIXES + PARQUET_SUFFIXES)


#: What to do about a damaged mesh ``.npy`` of ``data/`` (:func:`aumesh.core.io.check_npy`).
DATA_NPY_FIX = (
    "restore it (`dvc checkout data`, or `dvc pull` from the remote), or save py-feat's whole [N, 478, 3] "
    "landmarks again with np.save."
)


def open_source(
    path: InputPath, mesh_npy_pattern: str, instruments: Sequence[str] = (), layouts: dict | None = None
) -> Source:
    """A source's layout from its header (CSV) or schema (parquet); ``instruments``: the second detector's AU
    columns it must hold (``model.eiv.instrument_aus``). ``layouts``: a cache shared by the sources of one run (one
    header tuple and one :class:`~aumesh.data.pyfeat.Layout` per distinct header: py-feat's one CSV per video repeats
    the same ~2,045 names in every file, ~120 KB a source and ~2 ms of parsing when each held its own)."""
    cache: dict = {} if layouts is None else layouts
    if path.name.endswith(CSV_SUFFIXES):
        line, second = _header_lines(path)
        key = ("csv", line, tuple(instruments))  # the header's text: parsed once
        if key not in cache:
            header = tuple(_parse_header(path, line, second))
            cache[key] = (header, pyfeat.layout(header, str(path), instruments=instruments))
        header, lay = cache[key]
        return Source(path, "csv", lay, header)
    try:
        md = _parquet_metadata(path)
    except StorageError:
        raise
    except Exception as err:  # pyarrow raises several types for a bad file
        raise corrupt_parquet(path, err) from None
    names = md.schema.to_arrow_schema().names
    npy = path.with_name(mesh_npy_pattern.format(stem=path.stem))
    split = (
        storage.exists(npy)
        and not set(pyfeat.MESH_NAMES["Detectorv2"]) <= set(names)
        and not {"z_0", "z_477"} <= set(names)
    )
    shape_key = ("parquet", tuple(names), split, tuple(instruments))
    if shape_key not in cache:
        cache[shape_key] = (tuple(names), pyfeat.layout(names, str(path), split_mesh=split, instruments=instruments))
    header, lay = cache[shape_key]
    if split:
        if isinstance(npy, ObjectPath):  # rows are read with pread (NpyRowFile): a local file
            raise TableError(
                f"{npy}: the split layout (a table and its mesh .npy) is read from a local folder only. Fix: save "
                f"the table with its mesh columns (py-feat's Fex.to_parquet), or `aws s3 sync` the folder to local disk."
            )
        _, _, shape = check_npy(npy, DATA_NPY_FIX)
        if len(shape) != 3 or shape[1:] != (N_VERTICES, 3):
            raise TableError(
                f"{npy}: wrong vertex count: mesh array has shape {shape}, need (N, {N_VERTICES}, 3). Fix: "
                f"save the 478-vertex MediaPipe FaceMesh (with irises) as float16/float32 [N, 478, 3]."
            )
        if shape[0] != md.num_rows:
            raise TableError(
                f"{npy}: {shape[0]} meshes but {path} has {md.num_rows} rows. Fix: one mesh per table row, "
                f"same order; keep py-feat's no-face rows in both (aumesh drops them itself)."
            )
    return Source(path, "parquet", lay, header, npy if split else None, md.num_rows)


def _parquet_metadata(path: InputPath) -> pq.FileMetaData:
    with _arrow_input(path) as src:
        return pq.read_metadata(src)


def csv_header(path: InputPath) -> list[str]:
    """The CSV's column names (a byte-order mark, as Excel writes, accepted); a header that is not py-feat's CSV (NUL
    bytes, ``;`` or tab separators) is refused by :func:`aumesh.data.csv_text.check_header_line`."""
    return _parse_header(path, *_header_lines(path))


def _header_lines(path: InputPath) -> tuple[str, str]:
    """The header line and (the start of) the next, decoded as ``utf-8-sig`` (a byte-order mark dropped)."""
    try:
        if isinstance(path, ObjectPath):
            with storage.open_input(path, block_size=storage.LINE_BLOCK_SIZE) as raw:
                stream = gzip.open(raw, "rt", newline="", encoding="utf-8-sig") if path.name.endswith(".gz") else None
                text = stream or io.TextIOWrapper(raw, encoding="utf-8-sig", newline="")
                return text.readline(), text.readline(1 << 16)
        opener = gzip.open if path.name.endswith(".gz") else open
        with opener(path, "rt", newline="", encoding="utf-8-sig") as fh:
            return fh.readline(), fh.readline(1 << 16)
    except StorageError:
        raise
    except (OSError, UnicodeDecodeError, EOFError) as err:
        raise TableError(
            f"{path}: cannot read the CSV header ({err}). Fix: save it with py-feat's detect(..., save=) "
            f"or DataFrame.to_csv."
        ) from None


def _parse_header(path: InputPath, line: str, second: str) -> list[str]:
    csv_text.check_header_line(path, line, second)
    header = next(csv.reader([line]), None)
    if not header:
        raise TableError(f"{path}: empty CSV (no header). Fix: export frames with py-feat first.")
    return header


# ---------------------------------------------------------------------------------------------------- reading ranges


@dataclass(frozen=True)
class Span:
    """Whole frames of one source: CSV bytes ``[start, stop)`` (the header excluded) or parquet rows ``[start, stop)``.

    ``carried``: the range starts inside a run of frames with several faces (no frame of one face within a range's
    length), so the face kept there continues the track of the range before (:mod:`aumesh.data.face_track`)."""

    source: Source
    start: int
    stop: int
    carried: bool = False


def csv_spans(source: Source, range_bytes: int = CSV_RANGE_BYTES) -> list[Span]:
    """Byte ranges of about ``range_bytes`` that start at a line and never split the rows of one frame (py-feat writes a
    frame's faces consecutively). A compressed CSV is one range.

    A range starts, where it can within ``range_bytes`` more, at a new video or at a frame of one face row: there the
    face kept needs no frame before it (:mod:`aumesh.data.face_track`), so cleaning the ranges apart gives the rows
    of one pass over the file. Only a run of frames with several faces longer than that starts a range mid-track."""
    path = source.path
    with storage.open_input(path, block_size=storage.LINE_BLOCK_SIZE) as fh:
        header_end = len(fh.readline())
    size = storage.size(path)
    if path.name.endswith(".gz") or size - header_end <= range_bytes:
        return [Span(source, header_end, size)]
    key_columns = [source.header.index(source.layout.video), source.header.index(FRAME_COLUMN)]
    face_column = source.header.index(source.layout.face_score or AU_COLUMNS[0])
    bounds, carried = [header_end], [False]
    with storage.open_input(path, block_size=storage.LINE_BLOCK_SIZE) as fh:
        target = header_end + range_bytes
        while target < size:
            cut, anchored = _frame_boundary(fh, target, key_columns, face_column, range_bytes)
            if cut >= size:
                break
            if cut > bounds[-1]:
                bounds.append(cut)
                carried.append(not anchored)
            target = max(cut, bounds[-1]) + range_bytes
    bounds.append(size)
    return [Span(source, a, b, c) for a, b, c in zip(bounds[:-1], bounds[1:], carried, strict=True)]


def _is_face(row: list[str], column: int) -> bool:
    """The row's ``column`` (FaceScore, else AU01) is a positive number: a face row, not py-feat's no-face row."""
    try:
        value = float(row[column])
    except (IndexError, ValueError):
        return False
    return value > 0 if np.isfinite(value) else False


def _frame_boundary(
    fh, offset: int, key_columns: list[int], face_column: int | None = None, limit: int = 0
) -> tuple[int, bool]:
    """``(cut, anchored)``: the first line start at or after ``offset`` whose (video, frame) differs from the line
    before it; with ``face_column``, the first such start up to ``limit`` bytes further that begins a new video or a
    frame of one face row (:func:`_is_face`: ``anchored``), else the first (``anchored`` False)."""
    fh.seek(offset - 1)
    fh.readline()  # the rest of the line ``offset`` falls in (offset - 1: a line starting at ``offset`` is kept)
    previous, first, single = None, None, None  # single: a frame start whose frame has one face row so far
    while True:
        start = fh.tell()
        line = fh.readline()
        if not line:
            return (single, True) if single is not None else (start, True) if first is None else (first, False)
        row = next(csv.reader([line.decode("utf-8", "replace")]), [])
        key = tuple(row[k] if k < len(row) else None for k in key_columns)
        if previous is not None and key != previous:
            if face_column is None or key[0] != previous[0] or single is not None:
                return (single if single is not None and key[0] == previous[0] else start), True
            if first is None:
                first = start
            elif start - first > limit:
                return first, False
            single = start if _is_face(row, face_column) else None
        elif single is not None:  # a second row of the frame: several faces
            single = None
        previous = key


def parquet_batches(
    source: Source, columns: list[str], batch_rows: int | None = None, reader: pq.ParquetFile | None = None
) -> Iterator[pa.Table]:
    """The parquet source's ``columns`` a batch of rows at a time (default :data:`PARQUET_RANGE_ROWS`: memory flat in
    the table's rows), typed. ``reader``: the file already open (parsing a py-feat footer of ~2,000 columns costs
    ~40 ms)."""
    types = _types(source.layout)
    try:
        with _arrow_input(source.path) if reader is None else nullcontext() as src:  # an object's file: closed after
            reader = reader or pq.ParquetFile(src)
            for batch in reader.iter_batches(
                batch_size=batch_rows or PARQUET_RANGE_ROWS, columns=columns, use_threads=False
            ):
                table = pa.Table.from_batches([batch])
                names = table.column_names
                wrong = [name in types and table.schema.field(name).type != types[name] for name in names]
                if any(wrong):  # one new table: a set_column per column costs seconds for py-feat's ~1,400 float64 mesh
                    cast = [
                        _cast(table.column(name), types[name], source.path, name, 0) if bad else table.column(name)
                        for name, bad in zip(names, wrong, strict=True)
                    ]
                    table = pa.Table.from_arrays(cast, names=names)
                yield table
    except StorageError:
        raise
    except (pa.ArrowException, OSError) as err:
        raise corrupt_parquet(source.path, err) from None


def _arrow_input(path: InputPath) -> AbstractContextManager:
    """What Arrow opens, as a context: a local file by its path (Arrow's own reader), an object's file through the
    seam (:mod:`aumesh.core.storage`), closed when the context ends."""
    return storage.open_input(path) if isinstance(path, ObjectPath) else nullcontext(str(path))


def _new_frames(video: np.ndarray, frame: np.ndarray, previous: tuple | None) -> np.ndarray:
    """(n,) bool: the row starts a frame (its (video, frame) differs from the row before; ``previous``: the last key of
    the batch before)."""
    if not len(frame):
        return np.zeros(0, bool)
    first = previous is None or (video[0], frame[0]) != previous
    return np.r_[first, (video[1:] != video[:-1]) | (frame[1:] != frame[:-1])]


def _types(layout: pyfeat.Layout) -> dict[str, pa.DataType]:
    types = {name: pa.float64() for name in layout.numeric}
    types |= {name: pa.float32() for name in layout.mesh or ()}
    types |= {layout.video: pa.string(), FRAME_COLUMN: pa.int64()}
    if layout.identity:
        types[layout.identity] = pa.string()
    return types


def read_span(span: Span, columns: Sequence[str] | None = None) -> pa.Table:
    """A CSV span's rows, ``columns`` only (default: every column the layout needs), with the layout's types; a
    column the layout does not type is text as written (Arrow would read py-feat's ``approx_time`` "MM:SS" as a time
    of day, 60 times too long)."""
    lay = span.source.layout
    columns = list(lay.columns if columns is None else columns)
    types = _types(lay)
    return _read_csv_span(span, columns, {k: types.get(k, pa.string()) for k in columns})


def iter_span_tables(span: Span, columns: Sequence[str] | None = None) -> Iterator[tuple[Span, pa.Table]]:
    """The span's rows as ``(rows, table)``, whole frames in each: a CSV range at once; a parquet table a batch of
    :data:`PARQUET_RANGE_ROWS` rows at a time (memory flat in its rows, whatever its row groups), the rows of the
    batch's last frame carried into the next batch (a frame's faces are never split)."""
    if span.source.kind == "csv":
        yield span, read_span(span, columns)
        return
    lay = span.source.layout
    columns = [c for c in (lay.columns if columns is None else columns) if c in span.source.header]
    carry, start = None, 0
    for batch in parquet_batches(span.source, columns):
        table = batch if carry is None else pa.concat_tables([carry, batch])
        video = table.column(lay.video).to_numpy(zero_copy_only=False)
        frame = table.column(FRAME_COLUMN).to_numpy(zero_copy_only=False)
        last = int(np.flatnonzero(_new_frames(video, frame, None))[-1]) if table.num_rows else 0
        if last:
            yield Span(span.source, start, start + last), table.slice(0, last)
        carry, start = table.slice(last), start + last
    if carry is not None and carry.num_rows:
        yield Span(span.source, start, start + carry.num_rows), carry


def _cast(column, typ: pa.DataType, path: InputPath, name: str, first_row: int):
    """``column`` as ``typ``; a value that is not a number is the data contract's error, naming its row and value."""
    try:
        return column.cast(typ)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        from aumesh.data import contract  # pandera: imported only when a value is not a number

        contract.numeric_values(column.to_numpy(zero_copy_only=False), str(path), name, first_row)
        raise TableError(
            f"{path}: column {name!r} cannot be read as {typ}. Fix: write numbers as numbers (missing "
            f"values as NaN) before `dvc add data`."
        ) from None


def _csv_options(
    source: Source, columns: list[str], types: dict[str, pa.DataType], skip_rows: int = 0
) -> tuple[pacsv.ReadOptions, pacsv.ConvertOptions]:
    read = pacsv.ReadOptions(
        column_names=list(source.header), use_threads=True, block_size=8 << 20, skip_rows=skip_rows
    )
    convert = pacsv.ConvertOptions(
        include_columns=columns, column_types=types, strings_can_be_null=True, quoted_strings_can_be_null=True
    )
    return read, convert


def span_bytes(span: Span) -> bytes:
    """An uncompressed CSV span's bytes, refused when they hold NUL bytes (:func:`aumesh.data.csv_text.check_bytes`)."""
    data = storage.read_range(span.source.path, span.start, span.stop - span.start)
    csv_text.check_bytes(span.source.path, data, None, span.start)
    return data


def row_place(span: Span, row: int) -> str:
    """Where row ``row`` of ``span`` (as read, 0-based) is in its file, as the user finds it: a CSV's line as a text
    editor counts it (the header is line 1; py-feat writes a row a line), a parquet table's row (0-based). Counts the
    lines before a CSV range: for error messages only."""
    src = span.source
    if src.kind == "csv":
        return f"line {csv_text.first_line(src.path, span.start, src.path.name.endswith('.gz')) + row}"
    return f"row {span.start + row}"


def _read_csv_span(span: Span, columns: list[str], types: dict[str, pa.DataType]) -> pa.Table:
    path = span.source.path
    if path.name.endswith(".gz"):
        # one range (csv_spans): the whole decompressed stream, its header row skipped (Arrow's compressed
        # streams have no readline)
        read, convert = _csv_options(span.source, columns, types, skip_rows=1)
        try:
            with _arrow_input(path) as raw:
                return pacsv.read_csv(
                    pa.input_stream(raw, compression="gzip"), read_options=read, convert_options=convert
                )
        except pa.ArrowInvalid as err:
            with storage.open_input(path) as raw, gzip.open(raw, "rb") as fh:
                fh.readline()
                data = fh.read()
            raise _csv_error(span, data, err, columns, 2) from None
    data = span_bytes(span)
    read, convert = _csv_options(span.source, columns, types)
    try:
        return pacsv.read_csv(io.BytesIO(data), read_options=read, convert_options=convert)
    except pa.ArrowInvalid as err:
        raise _csv_error(span, data, err, columns) from None


def _csv_error(span: Span, data: bytes, err: Exception, columns: list[str], line: int | None = None) -> TableError:
    """Arrow's refusal of a span, named by :func:`aumesh.data.csv_text.parse_error` (the file, the line, what it is)."""
    path = span.source.path
    if line is not None:  # a gzipped file's NULs (its bytes decompressed, after the header)
        csv_text.check_bytes(path, data, line)
    start = line or csv_text.first_line(path, span.start)
    return csv_text.parse_error(path, data, start, span.source.header, str(err).splitlines()[0], columns)


#: CSV ranges smaller than this are parsed together with the next ranges of the same header (up to
#: :data:`CSV_RANGE_BYTES` in all): py-feat's one CSV per video is thousands of one-range files, and each parse of
#: ~2,045 columns costs ~15 ms of setup whatever its rows.
SMALL_RANGE_BYTES = 4 << 20


def iter_span_groups(
    spans: Sequence[Span], columns: Sequence[str] | None = None
) -> Iterator[tuple[pa.Table, list[tuple[Span, Span, int, int]]]]:
    """The spans' rows as :func:`iter_span_tables` reads them, as ``(table, [(span, rows, first, stop), ...])``: each
    table's rows ``[first, stop)`` are those of ``rows``, whole frames of ``span`` (``rows`` is ``span``, or the part
    of a parquet span a batch holds). Consecutive small CSV ranges (below :data:`SMALL_RANGE_BYTES`) of one header are parsed at once, their bytes joined, when each is one line per row
    (no quotes, no blank lines: its line ends count its rows); otherwise, and when Arrow refuses the joined bytes,
    range by range (the refusal is then named for its own file)."""
    pending: list[tuple[Span, bytes]] = []
    size = 0
    for span in spans:
        src = span.source
        if src.kind == "csv" and not src.path.name.endswith(".gz") and span.stop - span.start < SMALL_RANGE_BYTES:
            if pending and (
                pending[0][0].source.header != src.header or size + span.stop - span.start > CSV_RANGE_BYTES
            ):
                yield from _joined(pending, columns)
                pending, size = [], 0
            pending.append((span, span_bytes(span)))
            size += span.stop - span.start
            continue
        if pending:
            yield from _joined(pending, columns)
            pending, size = [], 0
        for rows, table in iter_span_tables(span, columns):
            yield table, [(span, rows, 0, table.num_rows)]
    if pending:
        yield from _joined(pending, columns)


def _one_line_rows(data: bytes) -> bool:
    return b'"' not in data and b"\n\n" not in data and b"\n\r\n" not in data and not data.startswith((b"\n", b"\r"))


def _joined(
    pending: list[tuple[Span, bytes]], columns: Sequence[str] | None
) -> Iterator[tuple[pa.Table, list[tuple[Span, Span, int, int]]]]:
    if len(pending) > 1 and all(_one_line_rows(data) for _, data in pending):
        source = pending[0][0].source
        cols = list(source.layout.columns if columns is None else columns)
        types = _types(source.layout)
        parts = [data if not data or data.endswith(b"\n") else data + b"\n" for _, data in pending]
        rows = [part.count(b"\n") for part in parts]
        read, convert = _csv_options(source, cols, {k: types.get(k, pa.string()) for k in cols})
        try:
            table = pacsv.read_csv(io.BytesIO(b"".join(parts)), read_options=read, convert_options=convert)
        except pa.ArrowInvalid:
            table = None  # read range by range below: the error names its file
        if table is not None and table.num_rows == sum(rows):
            bounds = np.r_[0, np.cumsum(rows)]
            yield (
                table,
                [
                    (span, span, int(a), int(b))
                    for (span, _), a, b in zip(pending, bounds[:-1], bounds[1:], strict=True)
                ],
            )
            return
    for span, _ in pending:
        table = read_span(span, columns)
        yield table, [(span, span, 0, table.num_rows)]


@dataclass
class Block:
    """Rows of one span as arrays: video ids, frames, the numeric columns by name, identities and the mesh.

    ``mesh`` is (n, 1434) axis-major ``[x_0..x_477 | y_.. | z_..]`` (float32 from parquet/CSV, the ``.npy``'s dtype
    widened to float32 for the split layout).
    """

    video: np.ndarray  # (n,) str
    frame: np.ndarray  # (n,) int64
    values: dict[str, np.ndarray]  # column -> (n,) float64
    identity: np.ndarray | None  # (n,) object, None where absent
    mesh: np.ndarray  # (n, 1434) float32

    def __len__(self) -> int:
        return len(self.frame)

    def take(self, rows: np.ndarray) -> Block:
        return Block(
            self.video[rows],
            self.frame[rows],
            {k: v[rows] for k, v in self.values.items()},
            None if self.identity is None else self.identity[rows],
            self.mesh[rows],
        )


def to_block(table: pa.Table, span: Span) -> Block:
    """A read span as a :class:`Block` (the split layout's mesh read from its ``.npy``)."""
    lay = span.source.layout
    # the video's identity is py-feat's ``input`` path as written (or ``video_id``), never its stem: a/clip01.mp4
    # and b/clip01.mp4 are two people's videos (pyfeat.video_names shows them by their stems where unique)
    video = table.column(lay.video).to_numpy(zero_copy_only=False)
    frame_col = table.column(FRAME_COLUMN)
    if frame_col.null_count:
        row = int(np.flatnonzero(frame_col.is_null().to_numpy(zero_copy_only=False))[0])
        raise TableError(
            f"{span.source.path}: column {FRAME_COLUMN!r} is empty at row {row} of this range. Fix: keep "
            f"py-feat's frame numbers on every row."
        )
    values = {
        name: table.column(name).to_numpy(zero_copy_only=False).astype(np.float64, copy=False) for name in lay.numeric
    }
    identity = table.column(lay.identity).to_numpy(zero_copy_only=False) if lay.identity else None
    if lay.mesh is not None:
        mesh = np.asarray(table.select(list(lay.mesh)).to_tensor(null_to_nan=True, row_major=True), dtype=np.float32)
    else:
        assert span.source.mesh_npy is not None, (
            span.source
        )  # open_source pairs a table without mesh columns with its .npy
        with NpyRowFile(str(span.source.mesh_npy)) as f:  # a local file: open_source refuses a remote .npy
            rows = f.read(span.start, span.stop)
        mesh = np.ascontiguousarray(rows.astype(np.float32).transpose(0, 2, 1)).reshape(len(rows), -1)
    return Block(video.astype(str), frame_col.to_numpy().astype(np.int64), values, identity, mesh)
