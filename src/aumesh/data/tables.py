"""Reading and validating frame tables (py-feat's Fex convention). All table I/O lives here.

Two layouts are accepted:

* one parquet with the metadata columns and mesh columns ``x_i, y_i, z_i`` (i = 0..477) in any
  order (py-feat stores them interleaved; we always select by name);
* py-feat's own split layout: an AU/pose parquet without mesh columns plus an ``[N, 478, 3]``
  mesh ``.npy`` beside it (float16, float32 or float64), named by ``data.mesh_npy``.

Every error names the file, the column and the fix.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from aumesh.core.errors import TableError, corrupt_parquet
from aumesh.core.families import family_columns
from aumesh.core.io import NpyRowFile, check_npy
from aumesh.core.schema import (
    AU_COLUMNS,
    FRAME_COLUMN,
    INPUT_PATH_COLUMN,
    N_TARGETS,
    N_VERTICES,
    POSE_COLUMNS,
    VIDEO_COLUMN,
)
from aumesh.data import contract, pyfeat

_MESH_COLUMN = pyfeat.POINT_COLUMN
META_COLUMNS = (VIDEO_COLUMN, FRAME_COLUMN, *AU_COLUMNS, *POSE_COLUMNS)


@dataclass(frozen=True)
class FrameTable:
    """One input table: a parquet file and, in py-feat's split layout, its mesh ``.npy``."""

    path: Path
    n_rows: int
    mesh_npy: Path | None  # None: mesh columns are inside the parquet
    video_from_input: bool  # video_id derived from py-feat's `input` column
    text_columns: frozenset[str] = frozenset()  # mesh columns stored as text, converted (data.coerce_numeric)
    # the carried families' columns (issue 46): (family, family name, the table's column), in FAMILIES order
    family_columns: tuple[tuple[str, str, str], ...] = ()


def discover(
    data_dir: str | Path, pattern: str, mesh_npy_pattern: str, coerce_numeric: bool = False
) -> list[FrameTable]:
    """Find and schema-check every frame table under ``data_dir``.

    Raises
    ------
    TableError
        No tables, a missing or misnamed column, a wrong vertex count, or a mesh .npy whose
        shape does not match its table.
    """
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise TableError(
            f"{data_dir}: the data folder does not exist (paths.data_dir). Fix: `dvc pull data.dvc` for the demo "
            f"tables, or put py-feat frame tables (parquet) under {data_dir}/ and run `dvc add {data_dir}`."
        )
    paths = sorted(p for p in data_dir.glob(pattern) if p.is_file() and p.suffix == ".parquet")
    if not paths:
        raise TableError(
            f"{data_dir}/{pattern}: no frame tables found (empty input). Fix: put py-feat frame tables "
            f"(parquet) under {data_dir}/ and run `dvc add {data_dir}`, or `dvc pull` for the demo data."
        )
    tables = [_check_schema(p, mesh_npy_pattern, coerce_numeric) for p in paths]
    if sum(t.n_rows for t in tables) == 0:
        raise TableError(
            f"{data_dir}/{pattern}: every table has 0 rows (empty input). Fix: export frames with py-feat first."
        )
    return tables


def check_tables(
    paths: Sequence[str | Path],
    mesh_npy_pattern: str,
    coerce_numeric: bool = False,
    instruments: Sequence[str] = (),
    families: Sequence[str] = (),
) -> list[FrameTable]:
    """Schema-check the tables the ingest stage lists (its manifest: cleaned tables and clean ones read in place);
    each must hold the ``instruments`` columns (``model.eiv.instrument_aus``: a table ingested without them names the
    fix) and the ``families`` the manifest carries (``manifest["families"]["carried"]``), found by name
    (:func:`aumesh.core.families.family_columns`: a table read in place may name them as its detector does)."""
    tables = [_check_schema(Path(p), mesh_npy_pattern, coerce_numeric, instruments, families) for p in paths]
    if sum(t.n_rows for t in tables) == 0:
        raise TableError(
            f"{', '.join(str(p) for p in paths[:3])}: no frame with a face: every table has 0 rows or only "
            f"py-feat's no-face rows (empty input). Fix: export frames with py-feat first, or check the videos "
            f"and py-feat's face_detection_threshold."
        )
    return tables


def _check_schema(
    path: Path,
    mesh_npy_pattern: str,
    coerce_numeric: bool = False,
    instruments: Sequence[str] = (),
    families: Sequence[str] = (),
) -> FrameTable:
    try:
        # the footer alone, parsed once for the check and the partitioning (:func:`_footer`): a reader
        # (pq.ParquetFile) on it cost each table 7 ms more to check
        footer = _footer(path)
        schema = footer.schema.to_arrow_schema()
    except Exception as err:  # pyarrow raises several types for a bad file
        raise corrupt_parquet(path, err) from None
    names = schema.names
    n_rows = footer.num_rows
    video_from_input = pyfeat.fex_video_column(names, str(path)) == INPUT_PATH_COLUMN
    pyfeat.check_instruments(names, instruments, str(path))
    held = [(f, name, col) for f in families for name, col in family_columns(names, f, str(path)).items()]
    has_mesh = any(_MESH_COLUMN.match(name) for name in names)
    mesh_npy = None
    text_columns: set[str] = set()
    if has_mesh:
        pyfeat.mesh_point_columns(names, str(path))  # 478 vertices on every axis, or the error naming the fix
        for field in schema:
            if _MESH_COLUMN.match(field.name) and not (
                pa.types.is_floating(field.type) or pa.types.is_integer(field.type)
            ):
                values = _read_columns(path, [field.name])[field.name].to_numpy(zero_copy_only=False)
                contract.numeric_values(values, path, field.name)  # a value that is not a number: always an error
                if not coerce_numeric:
                    raise contract.text_error(path, field.name, values[0] if len(values) else None)
                text_columns.add(field.name)
    else:
        mesh_npy = path.with_name(mesh_npy_pattern.format(stem=path.stem))
        if not mesh_npy.exists():
            raise TableError(
                f"{path}: no mesh columns (x_0..z_477) and no mesh file {mesh_npy}. Fix: add the mesh columns, "
                f"or save py-feat's [N, 478, 3] landmarks as {mesh_npy.name} (pattern data.mesh_npy)."
            )
        from aumesh.data.readers import DATA_NPY_FIX

        check_npy(
            mesh_npy, DATA_NPY_FIX
        )  # numpy's own error for a short file is "mmap length is greater than file size"
        arr = np.load(mesh_npy, mmap_mode="r")
        if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[1] != N_VERTICES:
            raise TableError(
                f"{mesh_npy}: wrong vertex count: mesh array has shape {arr.shape}, need (N, {N_VERTICES}, 3). "
                f"Fix: save the 478-vertex MediaPipe FaceMesh (with irises) as float16/float32 [N, 478, 3]."
            )
        if arr.shape[0] != n_rows:
            raise TableError(
                f"{mesh_npy}: {arr.shape[0]} meshes but {path} has {n_rows} rows. Fix: one mesh per table row, same order."
            )
        if arr.dtype.kind != "f":
            raise TableError(f"{mesh_npy}: dtype {arr.dtype}; need float16, float32 or float64.")
        if not arr.flags.c_contiguous:  # the passes read rows with plain file I/O
            raise TableError(
                f"{mesh_npy}: saved in Fortran order (a transposed array). "
                f"Fix: np.save(path, np.ascontiguousarray(landmarks))."
            )
    return FrameTable(
        path=path,
        n_rows=n_rows,
        mesh_npy=mesh_npy,
        video_from_input=video_from_input,
        text_columns=frozenset(text_columns),
        family_columns=tuple(held),
    )


#: Parsed parquet footers a process keeps (the most recently used). Partitions are consecutive row groups of the
#: tables in order, so the tasks running at once read a few neighbouring tables and a pass re-parses each table at most
#: once. Bounded by count, not by the tables: a parsed footer is ~9 times its serialized size in memory (a
#: 1,461-column, 4-row-group footer: 6 MiB; 126 py-feat tables' footers held 18 MiB of the stage at 3.1M frames).
FOOTER_CACHE_TABLES = 16


def _footer(path: str | Path) -> pq.FileMetaData:
    """The parquet footer of ``path``, parsed once per process and file version while it is among the
    ``FOOTER_CACHE_TABLES`` most recently used (a 1,461-column footer takes 10-16 ms to parse; every pass opens each
    table for each of its partitions)."""
    st = os.stat(path)
    # by absolute path: the stage checks the tables by the paths it was given, its tasks read them by absolute ones
    return _parsed_footer(os.path.abspath(path), st.st_mtime_ns, st.st_size, st.st_ino)


@functools.lru_cache(maxsize=FOOTER_CACHE_TABLES)
def _parsed_footer(path: str, mtime_ns: int, size: int, inode: int) -> pq.FileMetaData:
    return pq.read_metadata(path)


def _parquet(path: str | Path) -> pq.ParquetFile:
    """A reader of ``path`` on its cached footer (:func:`_footer`); one per use (readers are not shared across threads).

    Without ``pre_buffer`` (pyarrow's default is on): pre-buffering reads the selected columns of *every* requested
    row group into memory before the first batch, so a partition's whole compressed mesh columns were resident at once
    (Arrow's pool peaked at 363 MB reading one 33k-row partition of 1,434 float32 columns in 4,096-row batches, 249 MB
    without it) and each of those pages was a fresh page fault. Each column chunk is read when its rows are decoded.
    """
    return pq.ParquetFile(path, metadata=_footer(path), pre_buffer=False)


def _read_columns(path: Path, columns: list[str]) -> pa.Table:
    try:
        return pq.read_table(path, columns=columns, use_threads=False)  # as _batches
    except (pa.ArrowException, OSError) as err:
        raise corrupt_parquet(
            path,
            err,
            f" (reading {columns[0]}" + (f" and {len(columns) - 1} more columns)" if len(columns) > 1 else ")"),
        ) from None


def _batches(
    table: FrameTable, chunk_rows: int, columns: list[str], row_groups: Sequence[int] | None = None
) -> Iterator[pa.RecordBatch]:
    """Parquet row batches of ``columns`` (of ``row_groups`` only, if given); a page that cannot be decoded is a
    corrupt-file error."""
    try:
        # one thread: the partitions already run on every core; Arrow's own pool on top of them cost 1 CPU s and
        # 100k context switches in prepare at 344k frames (0.5 s of wall time)
        yield from _parquet(table.path).iter_batches(
            batch_size=chunk_rows,
            columns=columns,
            use_threads=False,
            row_groups=None if row_groups is None else list(row_groups),
        )
    except (pa.ArrowException, OSError) as err:
        raise corrupt_parquet(table.path, err, " (reading the mesh columns)") from None


def _column(batch: pa.RecordBatch, k: int, name: str, table: FrameTable, start: int) -> np.ndarray:
    values = batch.column(k).to_numpy(zero_copy_only=False)
    return contract.numeric_values(values, table.path, name, start) if name in table.text_columns else values


@dataclass(frozen=True)
class Piece:
    """Consecutive parquet row groups of one table (rows ``start .. start + n_rows``): a unit of a partition."""

    table: FrameTable
    row_groups: tuple[int, ...]
    start: int
    n_rows: int


def pieces(table: FrameTable) -> list[Piece]:
    """One piece per parquet row group of ``table``."""
    md = _footer(table.path)
    out, start = [], 0
    for g in range(md.num_row_groups):
        n = md.row_group(g).num_rows
        out.append(Piece(table, (g,), start, n))
        start += n
    return out


#: The number of partitions is a multiple of this (when there is more than one), so 1, 2 or 4 workers each get
#: as many partitions and no core idles through a pass's last round: 344,418 frames made 11 partitions of ~31k rows,
#: and every pass ended with one task on one core of two (prepare and evaluate at 344k: 0.96x the time with 12).
PARTITION_MULTIPLE = 4


def partition_count(n_rows: int, partition_rows: int) -> int:
    """``ceil(n_rows / partition_rows)`` rounded up to a multiple of :data:`PARTITION_MULTIPLE` (1 if that is 1)."""
    n = max(1, -(-n_rows // partition_rows))
    return n if n == 1 else -(-n // PARTITION_MULTIPLE) * PARTITION_MULTIPLE


def partitions(tables: Sequence[FrameTable], partition_rows: int) -> list[tuple[Piece, ...]]:
    """Whole row groups, in table order, packed into :func:`partition_count` partitions of about equal rows, at
    most ~``partition_rows`` each.

    A large table is split at row-group boundaries; small tables (e.g. one per video) are packed together. Each
    partition ends at the row group whose middle is nearest its share of the rows, so partitions differ by at most
    about a row group. Equal partitions keep every worker busy to the end of a pass: packing each to *at least*
    ``partition_rows`` left a small remainder (5 x 66k + 11k rows at 344k frames), and the last round of tasks ran
    on one core of two. The partitioning depends on the tables and ``partition_rows`` only (never the scheduler).
    """
    every = [piece for table in tables for piece in pieces(table)]
    total = sum(p.n_rows for p in every)
    n_parts = partition_count(total, partition_rows)
    out: list[tuple[Piece, ...]] = []
    current: list[Piece] = []
    done, k = 0, 1  # rows packed so far; the next partition ends near k * total / n_parts rows
    for piece in every:
        n_rows = piece.n_rows
        middle = done + n_rows / 2
        if current and k < n_parts and middle >= k * total / n_parts:
            out.append(tuple(current))
            current = []
            while k < n_parts and k * total / n_parts <= middle:
                k += 1
        if current and current[-1].table == piece.table:
            last = current.pop()  # consecutive row groups of one table are read as one piece
            piece = Piece(piece.table, last.row_groups + piece.row_groups, last.start, last.n_rows + piece.n_rows)
        current.append(piece)
        done += n_rows
    if current:
        out.append(tuple(current))
    return out


def read_metadata(
    table: FrameTable, coerce_numeric: bool = False, row_groups: Sequence[int] | None = None
) -> pd.DataFrame:
    """``video_id``, ``frame``, the 20 AUs and pose (model order Pitch, Yaw, Roll) of every row, validated.

    ``row_groups``: only these consecutive parquet row groups (default: the whole table); errors still give
    the row's index within the table.

    Raises
    ------
    TableError
        A broken data contract (:func:`aumesh.data.contract.validate_metadata`): text in a numeric column
        (unless ``coerce_numeric``), NaN/inf, an all-NaN column, AUs outside 0-1, pose beyond ±pi.
    """
    return _validated(_raw_metadata(table, row_groups), table.path, _row_range(table, row_groups)[0], coerce_numeric)


def read_pieces_metadata(
    pieces: Sequence[Piece], coerce_numeric: bool = False, instruments: Sequence[str] = ()
) -> pd.DataFrame:
    """:func:`read_metadata` of consecutive pieces, concatenated, validated at once (one check of the data contract
    for a partition, not one per table: the check has a fixed cost of ~12 ms, and a partition of per-video tables
    holds hundreds). A piece that breaks the contract is named by checking the pieces one by one.

    ``instruments``: a second detector's AU columns (``model.eiv.instrument_aus``), read after the pose and checked
    finite (:func:`aumesh.data.contract.check_instrument_values`); then the pieces' carried families
    (:attr:`FrameTable.family_columns`, alike in every table: :func:`check_tables`) under the family's names, float64,
    checked finite (:func:`aumesh.data.contract.check_family_values`).
    """
    raw = [_raw_metadata(p.table, p.row_groups, instruments) for p in pieces]
    families = pieces[0].table.family_columns if pieces else ()
    if len(raw) == 1:
        return _validated(raw[0], pieces[0].table.path, pieces[0].start, coerce_numeric, instruments, families)
    try:
        return _validated(
            pd.concat(raw, ignore_index=True),
            pieces[0].table.path,
            pieces[0].start,
            coerce_numeric,
            instruments,
            families,
        )
    except TableError as err:
        for df, piece in zip(raw, pieces, strict=True):  # the first broken piece, named with its file and row
            _validated(df, piece.table.path, piece.start, coerce_numeric, instruments, families)
        raise err


def _validated(
    df: pd.DataFrame,
    path: Path,
    first_row: int,
    coerce_numeric: bool,
    instruments: Sequence[str] = (),
    families: Sequence[tuple[str, str, str]] = (),
) -> pd.DataFrame:
    """``df`` (rows from ``first_row`` of ``path`` on) checked against the data contract, in the model's column order
    (the instrument columns, when given, after the pose; then the families' columns, by the family's names)."""
    df = contract.validate_metadata(df, path, row_offset=first_row, coerce=coerce_numeric)
    contract.check_instrument_values(df, instruments, path, first_row)
    for family in dict.fromkeys(f for f, _, _ in families):
        contract.check_family_values(df, [n for f, n, _ in families if f == family], path, first_row, family)
    return df[[VIDEO_COLUMN, FRAME_COLUMN, *AU_COLUMNS, *POSE_COLUMNS, *instruments, *(n for _, n, _ in families)]]


def _raw_metadata(table: FrameTable, row_groups: Sequence[int] | None, instruments: Sequence[str] = ()) -> pd.DataFrame:
    """The metadata columns of ``row_groups`` (None: the whole table) as stored, with ``video_id`` as text (py-feat's
    ``input`` path as written when the table names its videos so); then the ``instruments`` columns, when given, and
    the table's carried families (:attr:`FrameTable.family_columns`) renamed to the family's names, float64."""
    cols = [FRAME_COLUMN, *AU_COLUMNS, *POSE_COLUMNS, *instruments, *(c for _, _, c in table.family_columns)]
    cols.insert(0, INPUT_PATH_COLUMN if table.video_from_input else VIDEO_COLUMN)
    if row_groups is None:
        columns = _read_columns(table.path, cols)
    else:
        try:
            columns = _parquet(table.path).read_row_groups(
                list(row_groups), columns=cols, use_threads=False
            )  # as _batches
        except (pa.ArrowException, OSError) as err:
            raise corrupt_parquet(table.path, err, " (reading the metadata columns)") from None
    df = columns.to_pandas(use_threads=False)  # as the reads: the partitions already run on every core
    if table.video_from_input:  # the path as written is the video's identity (pyfeat.video_names shows its stem)
        df.insert(0, VIDEO_COLUMN, df.pop(INPUT_PATH_COLUMN))
    df[VIDEO_COLUMN] = df[VIDEO_COLUMN].astype(str)
    if table.family_columns:  # by name: a table read in place may hold Detectorv2's ``Happy`` for ``happiness``
        df = df.rename(columns={c: n for _, n, c in table.family_columns if c != n})
    return df


def check_unique_frames(meta: pd.DataFrame, files: Sequence[Path], file_index: np.ndarray) -> None:
    """Every (video_id, frame) pair once across all tables."""
    dup = meta.duplicated(subset=[VIDEO_COLUMN, FRAME_COLUMN], keep=False).to_numpy()
    if dup.any():
        rows = np.flatnonzero(dup)
        first = meta.iloc[rows[0]]
        where = sorted({str(files[i]) for i in file_index[rows]})
        raise TableError(
            f"{', '.join(where[:3])}: {len(rows)} rows share a ({VIDEO_COLUMN}, {FRAME_COLUMN}) pair, e.g. "
            f"({first[VIDEO_COLUMN]!r}, {first[FRAME_COLUMN]}). Fix: drop duplicate frames (or give each video "
            f"a distinct {VIDEO_COLUMN}) before `dvc add data`."
        )


def _row_range(table: FrameTable, row_groups: Sequence[int] | None) -> tuple[int, int]:
    if row_groups is None:
        return 0, table.n_rows
    md = _footer(table.path)
    first = sum(md.row_group(g).num_rows for g in range(min(row_groups)))
    return first, first + sum(md.row_group(g).num_rows for g in row_groups)


#: Most rows of a mesh ``.npy`` read at a time (``chunk_rows`` bounds them too). The file stores a frame per row, read
#: whole with ``pread`` into a buffer that is transit only (the consumers take what they need: pass 1 its 36 anchor
#: values of 1,434, pass 3 256 rows at a time), so a small read costs no copy and no extra pass over the data: 1,024
#: float16 rows are 2.8 MiB, where a ``chunk_rows`` chunk (4,096 rows a thread) held 11 MiB in every task.
NPY_READ_ROWS = 1024


def _npy_blocks(
    table: FrameTable, chunk_rows: int, row_groups: Sequence[int] | None, buffers: dict | None = None
) -> Iterator[tuple[int, np.ndarray]]:
    """``(start, rows)`` of the table's mesh ``.npy``, ``rows`` (m, 478, 3) in the file's dtype, read with ``pread``:
    a memory map would keep every page of the file read so far resident in the process (~70 MiB a py-feat table).

    ``rows`` is a view of one buffer that every chunk is read into: valid until the next chunk is read (a consumer
    that keeps rows copies them). A fresh array per chunk held two chunks at once, the one the consumer still held and
    the one being read (2 x 23 MiB a task at 8,192 float16 rows), and cost a page fault per 4 KiB of every chunk.
    ``buffers`` ((dtype, row shape) -> buffer) carries the buffer on to the next table's reads
    (:func:`iter_pieces_mesh_chunks`)."""
    first, stop = _row_range(table, row_groups)
    chunk_rows = min(chunk_rows, NPY_READ_ROWS)
    assert table.mesh_npy is not None  # called for tables whose mesh is a .npy beside them
    with NpyRowFile(table.mesh_npy) as f:
        n, key = min(chunk_rows, max(stop - first, 0)), (f.dtype.str, f.shape[1:])
        buffer = None if buffers is None else buffers.get(key)
        if buffer is None or len(buffer) < n:
            buffer = np.empty((n, *f.shape[1:]), dtype=f.dtype)
            if buffers is not None:
                buffers[key] = buffer
        for start in range(first, stop, chunk_rows):
            yield start, f.read(start, min(start + chunk_rows, stop), out=buffer)


#: Rows (first-axis entries) :func:`_all_finite` checks at a time.
_FINITE_BLOCK = 256


def _all_finite(values: np.ndarray) -> bool:
    """``np.isfinite(values).all()`` a block of the first axis at a time: the check's bool temporary of a whole chunk
    (11.7 MiB at 8,192 mesh rows) was a task's largest allocation after the chunk itself."""
    return all(np.isfinite(values[lo : lo + _FINITE_BLOCK]).all() for lo in range(0, len(values), _FINITE_BLOCK))


def iter_vertices(
    table: FrameTable,
    chunk_rows: int,
    vertex_indices: Sequence[int] | None = None,
    row_groups: Sequence[int] | None = None,
) -> Iterator[tuple[int, np.ndarray]]:
    """Stream mesh vertices in bounded chunks (parquet row batches or rows of the .npy).

    ``row_groups``: only the rows of these consecutive parquet row groups (default: the whole table).

    Yields
    ------
    start : int
        Row index of the chunk's first row within the table.
    vertices : ndarray, shape (chunk, n_selected, 3), float64
        Selected vertices (all 478 by default), selected by column name, never by position.

    Raises
    ------
    TableError
        NaN/inf in a mesh coordinate.
    """
    idx = list(range(N_VERTICES)) if vertex_indices is None else [int(i) for i in vertex_indices]
    if table.mesh_npy is not None:
        for start, rows in _npy_blocks(table, chunk_rows, row_groups):
            block = np.asarray(rows[:, idx, :], dtype=np.float64)
            _check_finite_mesh(table.mesh_npy, block, start, idx)
            yield start, block
        return
    columns = [f"{axis}_{i}" for axis in "xyz" for i in idx]
    start = _row_range(table, row_groups)[0]
    k = len(idx)
    for batch in _batches(table, chunk_rows, columns, row_groups):
        block = np.empty((batch.num_rows, 3, k), dtype=np.float64)
        for j, name in enumerate(columns):
            block[:, j // k, j % k] = _column(batch, batch.schema.get_field_index(name), name, table, start)
        block = block.transpose(0, 2, 1)
        _check_finite_mesh(table.path, block, start, idx)
        yield start, block
        start += batch.num_rows


@dataclass(frozen=True)
class MeshChunk:
    """Full meshes of ``m`` consecutive table rows, in the layout they were read in: exactly one of

    - ``vertices`` (m, 478, 3): rows of a py-feat mesh ``.npy``, in its dtype (float16, float32 or float64);
    - ``columns`` (1434, m): parquet mesh columns, axis-major ``[x_0..x_477 | y_.. | z_..]``, one row per column.

    Kept as read, not converted: transposing a whole chunk of ``.npy`` rows into columns cost a (1434, m) copy per
    chunk (23 MiB a task at 4,096 float16 rows); a consumer converts the rows it uses, a few at a time
    (:func:`aumesh.geometry.align.apply_similarity_vertices` or ``apply_similarity_columns`` with ``frames=``).
    """

    vertices: np.ndarray | None = None
    columns: np.ndarray | None = None

    def __len__(self) -> int:
        if self.vertices is not None:
            return len(self.vertices)
        assert self.columns is not None  # a chunk holds its rows in one of the two layouts
        return self.columns.shape[1]


def iter_mesh_chunks(
    table: FrameTable, chunk_rows: int, row_groups: Sequence[int] | None = None, buffers: dict | None = None
) -> Iterator[tuple[int, MeshChunk]]:
    """Full meshes chunk by chunk as ``(start, chunk)`` (:class:`MeshChunk`: ``.npy`` rows as stored, or parquet's
    columns ``(1434, m)``, one contiguous row per column: no strided scatter). ``row_groups`` as in
    :func:`iter_vertices`.

    ``.npy`` rows are a view of a buffer the next chunk is read into (:func:`_npy_blocks`): use them, or copy them,
    before the next chunk; ``buffers`` as in :func:`_npy_blocks`. Parquet columns keep their precision: float32 when
    every mesh column is float32 (MediaPipe's own precision; half the bytes to move), else float64; they may be
    read-only. A NaN/inf coordinate is a :class:`TableError`."""
    if table.mesh_npy is not None:
        for start, rows in _npy_blocks(table, chunk_rows, row_groups, buffers):
            if not _all_finite(rows):
                _check_finite_mesh(table.mesh_npy, rows, start, range(N_VERTICES))
            yield start, MeshChunk(vertices=rows)
        return
    columns = [f"{axis}_{i}" for axis in "xyz" for i in range(N_VERTICES)]
    start = _row_range(table, row_groups)[0]
    where = None
    for batch in _batches(table, chunk_rows, columns, row_groups):
        if where is None:
            where = [batch.schema.get_field_index(name) for name in columns]
            native = all(batch.schema.field(k).type == pa.float32() for k in where) and not table.text_columns
            dtype = np.float32 if native else np.float64
        m = batch.num_rows
        if native:  # every column copied at once by Arrow: column-major (m, 1434) is (1434, m) row-major
            coords = np.asarray(batch.select(where).to_tensor(null_to_nan=True, row_major=False)).T
        else:
            coords = np.empty((N_TARGETS, m), dtype=dtype)
            for j, k in enumerate(where):
                coords[j] = _column(batch, k, columns[j], table, start)
        if not _all_finite(coords):
            _check_finite_mesh(
                table.path, coords.reshape(3, N_VERTICES, m).transpose(2, 1, 0), start, range(N_VERTICES)
            )
        yield start, MeshChunk(columns=coords)
        start += m


def iter_pieces_mesh_chunks(pieces: Sequence[Piece], chunk_rows: int) -> Iterator[tuple[int, MeshChunk]]:
    """:func:`iter_mesh_chunks` over consecutive pieces (a partition), ``(row, chunk)`` with ``row`` the chunk's first
    row within the pieces' rows, piece after piece.

    The ``.npy`` rows of every piece are read into one buffer: a consumer's last chunk of one piece stayed alive while
    the next piece's reader allocated its own, and at 3.1M frames a partition spans 2-3 tables (prepare's pass 3,
    a task: 61 MiB traced at 8,192 rows, 39 MiB for a partition of one table)."""
    buffers: dict = {}
    offset = 0
    for piece in pieces:
        for start, chunk in iter_mesh_chunks(piece.table, chunk_rows, piece.row_groups, buffers):
            yield offset + start - piece.start, chunk
        offset += piece.n_rows


def _check_finite_mesh(path: Path, block: np.ndarray, start: int, idx: Sequence[int]) -> None:
    finite = np.isfinite(block)
    if not finite.all():
        f, v, a = (int(i[0]) for i in np.nonzero(~finite))
        raise TableError(
            f"{path}: mesh column {'xyz'[a]}_{idx[v]} is NaN/inf at row {start + f}. "
            f"Fix: drop frames where the face mesh failed (rows with NaN landmarks) before `dvc add data`."
        )
