"""py-feat's files as users have them -> the pipeline's frame tables: one row per (video, frame), pixels, only the
contract's columns. Pure functions on a block of rows, and the readers and writer at the edges.

What a block goes through (:func:`clean_block`), in order:

1. **no face**: py-feat writes a frame without a face as one row with ``FaceScore`` 0 (MPDetector) or with every
   measurement NaN (Detectorv2: its FaceScore is NaN too). Such rows are dropped and counted. A row with only *some*
   values missing is kept, and the data contract refuses it downstream: that is corruption, not a missing face;
2. **several faces**: py-feat writes one row per face, the rows of one frame consecutive (same ``input`` and
   ``frame``). ``data.face_selection`` keeps one: ``largest`` (the largest face box), ``identity`` (py-feat's
   ``Identity`` seen in most of the video's face rows; frames without that person are dropped) or ``error``;
3. **units** (docs/conventions.md, "py-feat's mesh units"): the mesh leaves in frame pixels, x, y and z.

   * MediaPipe's raw landmarks are normalized image coordinates (x / width, y / height, z on x's scale). Judged from
     the mesh's whole 2-D extent (:func:`normalized_rows`: a face in pixels, even in profile, is tens of pixels tall;
     one in normalized units spans less than :data:`NORMALIZED_MAX_EXTENT`, and a small fraction of its FaceRect),
     converted with ``FrameWidth``/``FrameHeight`` or refused when the table lacks them;
   * py-feat writes x, y in frame pixels but z in its detector's crop units (:data:`Z_CROP`, :func:`z_scale`):
     Detectorv2's z is in 0-1 of its square chip (``z_px = z * FaceRectWidth``), MPDetector's in pixels of its
     256-px crop (``z_px = z * FaceRectWidth / 256``). ``data.mesh_units=pixels`` takes every z as pixels;
   * the face's proportions are measured per source (:func:`depth_height`: face depth over face height, z- over
     y-extent, stable under yaw) for the ingest stage's guard (:data:`DEPTH_HEIGHT_RANGE`).

Sources: py-feat's CSV (read with pyarrow's multi-threaded CSV reader, only the needed columns, types given, in
byte ranges of whole frames: bounded memory), a Fex saved as parquet (either detector), and the card's split layout
(a table plus an ``[N, 478, 3]`` ``.npy``).
"""

from __future__ import annotations

import csv
import gzip
import io
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from aumesh.core.errors import TableError, corrupt_parquet
from aumesh.core.io import NpyRowFile, absolute, check_npy
from aumesh.core.schema import AU_COLUMNS, FRAME_COLUMN, INPUT_PATH_COLUMN, N_VERTICES, POSE_COLUMNS, VIDEO_COLUMN
from aumesh.data import pyfeat
from aumesh.data.pyfeat import video_stem
from aumesh.geometry.face import FACE_OVAL

CSV_SUFFIXES = (".csv", ".csv.gz")
PARQUET_SUFFIXES = (".parquet",)
#: Vertices whose extents judge the units and measure the face's proportions: the face oval (its top 10 and chin 152
#: span the face's height at any yaw, its sides 234/454 lie at the back of the face) and the nose tip 1 (the front).
SHAPE_VERTICES: tuple[int, ...] = (*FACE_OVAL, 1)
#: A mesh whose 2-D extent (the larger of its x and y spans) is below this is in normalized image units: a face in
#: pixels is tens of pixels tall even in profile (py-feat's smallest detected face, a ~20 px box), a face in 0-1
#: units spans at most the frame (1) and a little beyond it.
NORMALIZED_MAX_EXTENT = 1.5
#: ... and below this fraction of its FaceRect's longer side, where py-feat wrote one (FaceRect is in pixels in
#: either detector's export; a mesh in pixels spans ~0.6-0.9 of its crop box, one in 0-1 units ~1/frame size).
NORMALIZED_MAX_RECT_FRACTION = 0.1
#: The detectors' z units: name and divisor, z_px = z * FaceRectWidth / divisor (docs/conventions.md).
#: Detectorv2: ``_mesh_to_original_frame`` (feat/detector_v2.py) maps x, y from 0-1 over the square chip
#: (``extract_face_square_pad_torch``, feat/utils/image_operations.py: the detector box squared to its longer side x
#: EXPAND_BBOX 1.2) to frame pixels and returns z unchanged; ``forward`` writes that square (``_crop_affine_to_box``)
#: divided by the loader's rescale as FaceRect, so FaceRectWidth is the chip's side in frame pixels.
#: MPDetector: ``detect_faces`` crops ``extract_face_from_bbox_torch(face_size=256, expand_bbox=1.25)`` (the box
#: expanded 1.25x, resized to 256 x 256), FaceRect is that expanded box in frame pixels, and ``forward`` rescales
#: only x, y ("leave Z in original scale"): z is in the 256-px crop's pixels, on x's scale (MediaPipe's z).
Z_CROP: dict[str, tuple[str, float]] = {"Detectorv2": ("chip", 1.0), "MPDetector": ("crop256", 256.0)}
#: The median over a source's faces of face depth over face height (z- over y-extent of :data:`SHAPE_VERTICES`)
#: must lie in this range. MediaPipe's canonical face (py-feat's canonical_face_model.pt) has depth/width ~0.65,
#: width/height ~0.85: depth/height ~0.55; py-feat's v4 release ~0.7 (depth/width 0.81); aumesh's template 0.34;
#: a profile face (yaw 90) shows its width as depth, ~1.2. A flat face (z left in Detectorv2's chip units) is
#: ~0.001. The range is a factor of ~3 beyond the faces: it refuses units, not people.
DEPTH_HEIGHT_RANGE = (0.1, 3.0)
#: z's growth with the face (:func:`growth_slope`) is judged on at least this many near-frontal faces whose heights
#: spread at least this much (SD of log face height: ~8 %); with a frontal face's depth varying ~10 % (expression,
#: the pose left) the slope's standard error is then below ~0.2, a fifth of the gap between py-feat's crop units (0)
#: and pixels (1); the verdict is at 0.5. (Synthetic faces: 1.06 in pixels, 0.07-0.10 in either crop's units.)
GROWTH_MIN_ROWS = 50
GROWTH_MIN_SPREAD = 0.08
#: ... among near-frontal faces (|pitch| and |yaw| below this, radians: ~11 deg), whose depth/height is the face's.
GROWTH_MAX_POSE = 0.2
#: log10 bin width of the depth/height histograms (:class:`RatioHist`: ~2.3 %), and their range (beyond: the end bins).
RATIO_BIN = 0.01
RATIO_LOG_RANGE = (-6.0, 4.0)
#: CSV bytes parsed at a time: py-feat writes ~20 KB a row, so ~3,300 rows (~40 MB of float64 columns) per range.
CSV_RANGE_BYTES = 64 << 20
#: Parquet rows read at a time.
PARQUET_RANGE_ROWS = 16384
#: Rows of an output row group (prepare packs whole row groups into its partitions).
ROW_GROUP_ROWS = 8192


@dataclass(frozen=True)
class Source:
    """One input file of ``data/``: a py-feat CSV, a parquet table, or a parquet table with its mesh ``.npy``."""

    path: Path
    kind: str  # csv | parquet
    layout: pyfeat.Layout
    header: tuple[str, ...]  # every column, in file order
    mesh_npy: Path | None = None
    n_rows: int | None = None  # parquet: rows (CSV: unknown until read)

    def absolute(self) -> Source:
        """The same source named by absolute paths (:func:`aumesh.core.io.absolute`): what partition tasks get, so a
        cluster worker in another directory reads this workspace's file."""
        return replace(
            self, path=absolute(self.path), mesh_npy=None if self.mesh_npy is None else absolute(self.mesh_npy)
        )


def is_table(path: Path) -> bool:
    return path.name.endswith(CSV_SUFFIXES + PARQUET_SUFFIXES)


#: What to do about a damaged mesh ``.npy`` of ``data/`` (:func:`aumesh.core.io.check_npy`).
DATA_NPY_FIX = (
    "restore it (`dvc checkout data`, or `dvc pull` from the remote), or save py-feat's whole [N, 478, 3] "
    "landmarks again with np.save."
)


def open_source(path: Path, mesh_npy_pattern: str) -> Source:
    """A source's layout from its header (CSV) or schema (parquet)."""
    if path.name.endswith(CSV_SUFFIXES):
        header = csv_header(path)
        return Source(path, "csv", pyfeat.layout(header, str(path)), tuple(header))
    try:
        md = pq.read_metadata(path)
    except Exception as err:  # pyarrow raises several types for a bad file
        raise corrupt_parquet(path, err) from None
    names = md.schema.to_arrow_schema().names
    npy = path.with_name(mesh_npy_pattern.format(stem=path.stem))
    split = (
        npy.exists() and not set(pyfeat.MESH_NAMES["Detectorv2"]) <= set(names) and not {"z_0", "z_477"} <= set(names)
    )
    lay = pyfeat.layout(names, str(path), split_mesh=split)
    if split:
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
    return Source(path, "parquet", lay, tuple(names), npy if split else None, md.num_rows)


def csv_header(path: Path) -> list[str]:
    opener = gzip.open if path.name.endswith(".gz") else open
    try:
        with opener(path, "rt", newline="") as fh:
            header = next(csv.reader(fh), None)
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise TableError(
            f"{path}: cannot read the CSV header ({err}). Fix: save it with py-feat's detect(..., save=) "
            f"or DataFrame.to_csv."
        ) from None
    if not header:
        raise TableError(f"{path}: empty CSV (no header). Fix: export frames with py-feat first.")
    return header


# ---------------------------------------------------------------------------------------------------- reading ranges


@dataclass(frozen=True)
class Span:
    """Whole frames of one source: CSV bytes ``[start, stop)`` (the header excluded) or parquet rows ``[start, stop)``."""

    source: Source
    start: int
    stop: int


def csv_spans(source: Source, range_bytes: int = CSV_RANGE_BYTES) -> list[Span]:
    """Byte ranges of about ``range_bytes`` that start at a line and never split the rows of one frame (py-feat writes a
    frame's faces consecutively). A compressed CSV is one range."""
    path = source.path
    with open(path, "rb") as fh:
        header_end = len(fh.readline())
    size = path.stat().st_size
    if path.name.endswith(".gz") or size - header_end <= range_bytes:
        return [Span(source, header_end, size)]
    key_columns = [source.header.index(source.layout.video), source.header.index(FRAME_COLUMN)]
    bounds = [header_end]
    with open(path, "rb") as fh:
        target = header_end + range_bytes
        while target < size:
            cut = _frame_boundary(fh, target, key_columns)
            if cut >= size:
                break
            if cut > bounds[-1]:
                bounds.append(cut)
            target = max(cut, bounds[-1]) + range_bytes
    bounds.append(size)
    return [Span(source, a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def _frame_boundary(fh, offset: int, key_columns: list[int]) -> int:
    """The first line start at or after ``offset`` whose (video, frame) differs from the line before it."""
    fh.seek(offset - 1)
    fh.readline()  # the rest of the line ``offset`` falls in (offset - 1: a line starting at ``offset`` is kept)
    previous = None
    while True:
        start = fh.tell()
        line = fh.readline()
        if not line:
            return start
        row = next(csv.reader([line.decode("utf-8", "replace")]), [])
        key = tuple(row[k] if k < len(row) else None for k in key_columns)
        if previous is not None and key != previous:
            return start
        previous = key


def _parquet_batches(
    source: Source, columns: list[str], batch_rows: int | None = None, reader: pq.ParquetFile | None = None
) -> Iterator[pa.Table]:
    """The parquet source's ``columns`` a batch of rows at a time (default :data:`PARQUET_RANGE_ROWS`: memory flat in
    the table's rows), typed. ``reader``: the file already open (parsing a py-feat footer of ~2,000 columns costs
    ~40 ms)."""
    types = _types(source.layout)
    try:
        reader = reader or pq.ParquetFile(source.path)
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
    except (pa.ArrowException, OSError) as err:
        raise corrupt_parquet(source.path, err) from None


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
    for batch in _parquet_batches(span.source, columns):
        table = batch if carry is None else pa.concat_tables([carry, batch])
        video = table.column(lay.video).to_numpy(zero_copy_only=False)
        frame = table.column(FRAME_COLUMN).to_numpy(zero_copy_only=False)
        last = int(np.flatnonzero(_new_frames(video, frame, None))[-1]) if table.num_rows else 0
        if last:
            yield Span(span.source, start, start + last), table.slice(0, last)
        carry, start = table.slice(last), start + last
    if carry is not None and carry.num_rows:
        yield Span(span.source, start, start + carry.num_rows), carry


def _cast(column, typ: pa.DataType, path: Path, name: str, first_row: int):
    """``column`` as ``typ``; a value that is not a number is the data contract's error, naming its row and value."""
    try:
        return column.cast(typ)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError):
        from aumesh.data import contract  # pandera: imported only when a value is not a number

        contract.numeric_values(column.to_numpy(zero_copy_only=False), path, name, first_row)
        raise TableError(
            f"{path}: column {name!r} cannot be read as {typ}. Fix: write numbers as numbers (missing "
            f"values as NaN) before `dvc add data`."
        ) from None


def _read_csv_span(span: Span, columns: list[str], types: dict[str, pa.DataType]) -> pa.Table:
    path = span.source.path
    read = pacsv.ReadOptions(column_names=list(span.source.header), use_threads=True, block_size=8 << 20)
    convert = pacsv.ConvertOptions(
        include_columns=columns, column_types=types, strings_can_be_null=True, quoted_strings_can_be_null=True
    )
    try:
        if path.name.endswith(".gz"):
            # one range (csv_spans): the whole decompressed stream, its header row skipped (Arrow's compressed
            # streams have no readline)
            stream = pa.input_stream(str(path), compression="gzip")
            skip = pacsv.ReadOptions(
                column_names=list(span.source.header), use_threads=True, block_size=8 << 20, skip_rows=1
            )
            return pacsv.read_csv(stream, read_options=skip, convert_options=convert)
        with open(path, "rb") as fh:
            fh.seek(span.start)
            data = fh.read(span.stop - span.start)
        return pacsv.read_csv(io.BytesIO(data), read_options=read, convert_options=convert)
    except pa.ArrowInvalid as err:
        message = str(err).splitlines()[0]
        column = next(
            (c for c in columns if f"'{c}'" in message or f"column #{span.source.header.index(c)}" in message), None
        )
        raise TableError(
            f"{path}: cannot read the CSV{f' (column {column!r})' if column else ''}: {message}. Fix: write "
            f"numbers as numbers and missing values as empty fields or NaN (py-feat's to_csv does)."
        ) from None


# ------------------------------------------------------------------------------------------------------ cleaning


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
    video = table.column(lay.video).to_numpy(zero_copy_only=False)
    if lay.video == INPUT_PATH_COLUMN:
        names, codes = np.unique(video.astype(str), return_inverse=True)
        video = np.array([video_stem(v) for v in names], dtype=object)[codes] if len(names) else video.astype(object)
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
        with NpyRowFile(span.source.mesh_npy) as f:
            rows = f.read(span.start, span.stop)
        mesh = np.ascontiguousarray(rows.astype(np.float32).transpose(0, 2, 1)).reshape(len(rows), -1)
    return Block(video.astype(str), frame_col.to_numpy().astype(np.int64), values, identity, mesh)


@dataclass(frozen=True)
class RatioHist:
    """A histogram of positive ratios in log10 bins of :data:`RATIO_BIN`, sparse (only the bins with counts: a source's
    faces fill a few dozen), so a source's measurement costs a few hundred bytes and merges over blocks and tasks.

    ``bins`` (k,) int32 sorted bin numbers (bin b holds log10 values in ``[b, b + 1) * RATIO_BIN``), ``counts`` (k,).
    """

    bins: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    counts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def __add__(self, other: RatioHist) -> RatioHist:
        if not len(other.bins):
            return self
        if not len(self.bins):
            return other
        bins, inverse = np.unique(np.r_[self.bins, other.bins], return_inverse=True)
        return RatioHist(bins.astype(np.int32), np.bincount(inverse, np.r_[self.counts, other.counts]).astype(np.int64))

    def median(self) -> float | None:
        """The median ratio (its bin's geometric centre: within ~1.2 %); None when empty."""
        total = int(self.counts.sum())
        if not total:
            return None
        k = int(np.searchsorted(np.cumsum(self.counts), (total + 1) / 2))
        return float(10 ** ((int(self.bins[k]) + 0.5) * RATIO_BIN))


@dataclass
class UnitStats:
    """One source's mesh units, summed over its blocks: what was converted and the face's proportions.

    ``xy``: "pixels" | "normalized" (| "mixed" when blocks of one source differ: refused by the ingest stage);
    ``z``: "pixels" | "chip" | "crop256" | "normalized"; the histograms count each face row's depth/height
    (:func:`depth_height`) in :class:`RatioHist` bins, as written (``before``), as ingested (``after``) and with z
    converted by the detector's crop (``crop``; empty unless the table is a detector's export with FaceRect).
    """

    detector: str = ""
    xy: str = ""
    z: str = ""
    rows: int = 0  # face rows kept
    rows_converted: int = 0  # rows whose mesh was rescaled (normalized, or z from a detector's crop units)
    rows_normalized: int = 0
    rows_z_converted: int = 0  # rows whose z was converted from the detector's crop units
    before: RatioHist = field(default_factory=lambda: RatioHist())
    after: RatioHist = field(default_factory=lambda: RatioHist())
    crop: RatioHist = field(default_factory=lambda: RatioHist())
    growth: np.ndarray = field(default_factory=lambda: np.zeros(5))  # :func:`growth_sums` of the rows

    def __add__(self, other: UnitStats) -> UnitStats:
        def unit(a: str, b: str) -> str:
            return a or b if not (a and b) or a == b else "mixed"

        return UnitStats(
            self.detector or other.detector,
            unit(self.xy, other.xy),
            unit(self.z, other.z),
            self.rows + other.rows,
            self.rows_converted + other.rows_converted,
            self.rows_normalized + other.rows_normalized,
            self.rows_z_converted + other.rows_z_converted,
            self.before + other.before,
            self.after + other.after,
            self.crop + other.crop,
            self.growth + other.growth,
        )

    def z_growth(self) -> float | None:
        """How z as written grows with the face's size (:func:`growth_slope`); None when the faces' sizes vary too
        little to tell."""
        return growth_slope(self.growth)

    def depth_height(self) -> tuple[float | None, float | None, float | None]:
        """Median face depth/height as written, as ingested and with z converted by the detector's crop; None
        where nothing was measured."""
        return self.before.median(), self.after.median(), self.crop.median()


@dataclass
class Counts:
    """What a span's cleaning dropped and converted, summed over spans."""

    rows_in: int = 0
    no_face: int = 0  # rows of frames without a face
    extra_faces: int = 0  # face rows dropped by data.face_selection (another face in the same frame)
    frames_several_faces: int = 0  # frames with more than one face row
    frames_without_subject: int = 0  # identity selection: frames where the video's subject is not seen
    rows_out: int = 0
    rows_normalized: int = 0  # rows whose mesh was converted from normalized image units to pixels
    rows_z_chip: int = 0  # rows whose z was converted from Detectorv2's chip units
    rows_z_crop256: int = 0  # rows whose z was converted from MPDetector's 256-px crop units
    identities: dict[str, dict[str, int]] = field(default_factory=dict)  # video -> Identity -> face rows
    units: dict[str, UnitStats] = field(default_factory=dict)  # source path -> its units
    labels: dict[str, set[str]] = field(default_factory=dict)  # source path -> Identity labels of kept rows

    def __add__(self, other: Counts) -> Counts:
        merged = {v: dict(c) for v, c in self.identities.items()}
        for v, c in other.identities.items():
            mine = merged.setdefault(v, {})
            for k, n in c.items():
                mine[k] = mine.get(k, 0) + n
        units = dict(self.units)
        for k, u in other.units.items():
            units[k] = units[k] + u if k in units else u
        labels = {k: set(names) for k, names in self.labels.items()}
        for k, names in other.labels.items():
            labels.setdefault(k, set()).update(names)
        dicts = ("identities", "units", "labels")
        sums = {f.name: getattr(self, f.name) + getattr(other, f.name) for f in fields(self) if f.name not in dicts}
        return Counts(**sums, identities=merged, units=units, labels=labels)

    def as_dict(self) -> dict[str, int]:
        out = {
            "rows_in": self.rows_in,
            "dropped_no_face": self.no_face,
            "dropped_extra_faces": self.extra_faces,
            "frames_with_several_faces": self.frames_several_faces,
            "dropped_frames_without_subject": self.frames_without_subject,
            "frames_out": self.rows_out,
            "rows_converted_from_normalized": self.rows_normalized,
            "rows_z_from_chip": self.rows_z_chip,
            "rows_z_from_crop256": self.rows_z_crop256,
        }
        if self.labels:  # py-feat's Identity column in some source
            out["identity_labels"] = sum(len(v) for v in self.labels.values())
        return out


def no_face_rows(block: Block, layout: pyfeat.Layout) -> np.ndarray:
    """(n,) bool: py-feat's rows for frames without a face: FaceScore 0, or every AU, pose and mesh value NaN."""
    measured = np.column_stack([block.values[c] for c in (*AU_COLUMNS, *POSE_COLUMNS)])
    empty = np.isnan(measured).all(axis=1) & np.isnan(block.mesh).all(axis=1)
    if layout.face_score:
        empty |= block.values[layout.face_score] == 0
    return empty


def frame_groups(block: Block) -> np.ndarray:
    """(n + 1,) starts of the runs of consecutive rows with the same (video, frame), and ``n`` at the end."""
    n = len(block)
    new = (
        np.r_[True, (block.video[1:] != block.video[:-1]) | (block.frame[1:] != block.frame[:-1])]
        if n
        else np.zeros(0, bool)
    )
    return np.r_[np.flatnonzero(new), n]


def face_areas(block: Block, layout: pyfeat.Layout) -> np.ndarray:
    """(n,) each face's box area: py-feat's FaceRectWidth x FaceRectHeight, else the mesh's x/y extent."""
    if layout.box_size:
        area = block.values[layout.box_size[0]] * block.values[layout.box_size[1]]
        if np.isfinite(area).all():
            return area
    x, y = block.mesh[:, :N_VERTICES], block.mesh[:, N_VERTICES : 2 * N_VERTICES]
    return (np.nanmax(x, axis=1) - np.nanmin(x, axis=1)).astype(np.float64) * (
        np.nanmax(y, axis=1) - np.nanmin(y, axis=1)
    )


def main_identities(identities: dict[str, dict[str, int]]) -> dict[str, str]:
    """Each video's subject: the Identity of most of its face rows (ties: the first name in sorted order)."""
    return {v: sorted(c.items(), key=lambda kv: (-kv[1], kv[0]))[0][0] for v, c in identities.items() if c}


def select_faces(
    block: Block, layout: pyfeat.Layout, how: str, subjects: dict[str, str] | None, where: str
) -> tuple[np.ndarray, Counts]:
    """Rows kept (one per frame) among face rows, by ``data.face_selection`` (``how``), and what was dropped.

    Parameters
    ----------
    block : face rows only (no-face rows removed), a frame's rows consecutive.
    subjects : video -> its subject's Identity (``how="identity"``).
    """
    groups = frame_groups(block)
    sizes = np.diff(groups)
    counts = Counts(frames_several_faces=int((sizes > 1).sum()))
    if how == "identity":
        if layout.identity is None:
            raise TableError(
                f"{where}: data.face_selection=identity needs py-feat's {pyfeat.IDENTITY!r} column. Fix: "
                f"keep it (detect computes it), or use data.face_selection=largest."
            )
        assert subjects is not None and block.identity is not None  # identity selection's first pass found them
        subject = np.array([subjects.get(v) for v in block.video], dtype=object)
        candidate = block.identity.astype(object) == subject
    else:
        candidate = np.ones(len(block), bool)
    if how == "error" and (sizes > 1).any():
        g = int(np.flatnonzero(sizes > 1)[0])
        row = groups[g]
        raise TableError(
            f"{where}: {int(sizes[g])} faces in frame {block.frame[row]} of video {block.video[row]!r} "
            f"({int((sizes > 1).sum())} such frames); data.face_selection=error keeps one face per frame only. Fix: "
            f"data.face_selection=largest (the largest face box) or identity (py-feat's Identity of the video's subject)."
        )
    area = np.where(candidate, face_areas(block, layout), -np.inf)
    # the largest candidate of each frame (ties: the first row): argmax within runs, as a sort by (group, -area)
    group_of = np.repeat(np.arange(len(sizes)), sizes)
    order = np.lexsort((np.arange(len(block)), -area, group_of))
    first = order[groups[:-1]]
    keep = first[candidate[first]]
    counts.frames_without_subject = int(len(first) - len(keep))
    counts.extra_faces = int(len(block) - len(first))
    return np.sort(keep), counts


def shape_extents(mesh: np.ndarray, axes: Sequence[int] = (0, 1, 2)) -> np.ndarray:
    """(n, len(axes)) spans along ``axes`` (0 x, 1 y, 2 z) of :data:`SHAPE_VERTICES` of axis-major meshes (n, 1434)
    (NaN where a vertex is)."""
    idx = np.add.outer(np.asarray(axes) * N_VERTICES, SHAPE_VERTICES)  # (a, k)
    part = np.sort(mesh[:, idx].astype(np.float64), axis=2)  # (n, a, k), NaN last
    # second-largest minus second-smallest: one wild vertex (a corrupt export, dropped later by prepare's
    # max_vertex_iod) neither judges the units nor flattens the face; the oval's vertices are ~5 % of it apart
    return part[:, :, -2] - part[:, :, 1]


def depth_height(extents: np.ndarray) -> np.ndarray:
    """(n,) face depth over face height, z- over y-extent (:func:`shape_extents`): yaw turns x into z, not y."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return extents[:, 2] / extents[:, 1]


def frontal(values: dict[str, np.ndarray]) -> np.ndarray:
    """(n,) bool: faces within :data:`GROWTH_MAX_POSE` radians of frontal in pitch and yaw (py-feat's pose columns)."""
    return (np.abs(values["Pitch"]) < GROWTH_MAX_POSE) & (np.abs(values["Yaw"]) < GROWTH_MAX_POSE)


def growth_sums(z_extent: np.ndarray, height: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(5,) n, sum x, sum y, sum x^2, sum x y of x = log face height (y-extent, pixels), y = log z-extent as written,
    over ``rows`` (near-frontal faces, :func:`frontal`: pitch turns height into depth, yaw width) where both are
    finite and positive: the sums of a least-squares slope, mergeable over blocks."""
    ok = rows & np.isfinite(z_extent) & np.isfinite(height) & (z_extent > 0) & (height > 0)
    x, y = np.log(height[ok]), np.log(z_extent[ok])
    return np.array([len(x), x.sum(), y.sum(), (x * x).sum(), (x * y).sum()])


def growth_slope(sums: np.ndarray) -> float | None:
    """The slope of log z-extent on log face height over a source's faces (:func:`growth_sums`), None below
    :data:`GROWTH_MIN_ROWS` faces or :data:`GROWTH_MIN_SPREAD`. In frame pixels a face's depth grows with its size
    (slope ~1); in py-feat's crop units it does not (~0: each face's crop is rescaled to the same chip, 0-1 or 256
    px). The height, not FaceRectWidth: MPDetector's crop width shrinks as the head turns while the depth grows. This
    tells the units apart where the depth/height ratio cannot (an MPDetector face ~256 px wide looks the same in
    either)."""
    n, sx, sy, sxx, sxy = (float(v) for v in sums)
    if n < GROWTH_MIN_ROWS:
        return None
    var = sxx / n - (sx / n) ** 2
    if var < GROWTH_MIN_SPREAD**2:
        return None
    return (sxy / n - sx * sy / n**2) / var


def ratio_hist(ratio: np.ndarray) -> RatioHist:
    """The finite values of ``ratio`` (n,) counted in :class:`RatioHist` bins."""
    r = np.abs(ratio[np.isfinite(ratio)])
    with np.errstate(divide="ignore"):
        logs = np.clip(np.log10(r), *RATIO_LOG_RANGE)
    bins, counts = np.unique(np.floor(logs / RATIO_BIN).astype(np.int32), return_counts=True)
    return RatioHist(bins, counts.astype(np.int64))


def normalized_rows(
    mesh: np.ndarray, rect_side: np.ndarray | None = None, extents: np.ndarray | None = None
) -> np.ndarray:
    """(n,) bool: rows whose mesh (n, 1434) is in normalized image units.

    The mesh's 2-D extent (the larger of its x and y spans over :data:`SHAPE_VERTICES`) is below
    :data:`NORMALIZED_MAX_EXTENT`, and, where the row has a FaceRect (``rect_side``: its longer side in pixels,
    (n,); NaN or 0 where py-feat wrote none), below :data:`NORMALIZED_MAX_RECT_FRACTION` of it. A face turned to
    profile keeps its height: its inter-ocular distance can fall below a pixel, its extent does not. ``extents``:
    its x, y spans (n, 2) when already measured (:func:`shape_extents`).
    """
    extent = (shape_extents(mesh, (0, 1)) if extents is None else extents).max(axis=1)
    normalized = extent < NORMALIZED_MAX_EXTENT
    if rect_side is not None:
        has_rect = np.isfinite(rect_side) & (rect_side > 0)
        normalized &= ~has_rect | (extent < NORMALIZED_MAX_RECT_FRACTION * np.where(has_rect, rect_side, 0.0))
    return normalized


def rect_side(block: Block, layout: pyfeat.Layout) -> np.ndarray | None:
    """(n,) the longer side of each row's FaceRect (None: the table has no FaceRect columns)."""
    if layout.box_size is None:
        return None
    w, h = (block.values[c] for c in layout.box_size)
    return np.fmax(w, h)


def to_pixels(block: Block, layout: pyfeat.Layout, normalized: np.ndarray, where: str) -> None:
    """Convert the ``normalized`` rows' meshes in place: x by FrameWidth, y by FrameHeight, z by FrameWidth
    (MediaPipe's z is on x's scale)."""
    if not normalized.any():
        return
    extent = float(np.median(shape_extents(block.mesh[normalized], (0, 1)).max(axis=1)))
    if layout.frame_size is None:
        raise TableError(
            f"{where}: the mesh is in normalized image units (0-1; median face extent {extent:.3g}), and the "
            f"table has no FrameWidth/FrameHeight to convert it. Fix: keep py-feat's FrameWidth and FrameHeight "
            f"columns, or multiply x and z by the frame width and y by its height before `dvc add data`."
        )
    width, height = (block.values[c][normalized] for c in layout.frame_size)
    bad = ~(np.isfinite(width) & np.isfinite(height) & (width > 0) & (height > 0))
    if bad.any():
        raise TableError(
            f"{where}: FrameWidth/FrameHeight are missing or not positive on {int(bad.sum())} rows whose "
            f"mesh is in normalized units. Fix: fill them with the video's frame size in pixels."
        )
    scale = np.column_stack([width, height, width]).astype(np.float32)  # (m, 3)
    m = block.mesh[normalized].reshape(-1, 3, N_VERTICES) * scale[:, :, None]
    block.mesh[normalized] = m.reshape(len(m), -1)


def z_scale(block: Block, layout: pyfeat.Layout, mesh_units: str, where: str) -> tuple[str, np.ndarray | None]:
    """The unit z is written in and the factor (n,) that takes it to frame pixels (None: z is pixels already).

    ``mesh_units="detector"``: Detectorv2's chip units (``z * FaceRectWidth``) and MPDetector's 256-px crop units
    (``z * FaceRectWidth / 256``), :data:`Z_CROP`; a ``table`` or ``split`` source, and ``mesh_units="pixels"``,
    are pixels.

    Raises
    ------
    TableError
        The conversion needs FaceRectWidth and a row has none (or not > 0): naming the file, the row's video and
        frame, and the fix.
    """
    if mesh_units == "pixels" or layout.detector not in Z_CROP:
        return "pixels", None
    unit, divisor = Z_CROP[layout.detector]
    width_col = pyfeat.FACE_BOX_SIZE[0]
    if layout.box_size is None:
        raise TableError(
            f"{where}: column {width_col!r} is missing: {layout.detector}'s z is in its crop's units "
            f"and FaceRectWidth (the crop in pixels) converts it. Fix: keep py-feat's FaceRect columns, or set "
            f"data.mesh_units=pixels if z is already in pixels."
        )
    width = block.values[width_col]
    bad = ~(np.isfinite(width) & (width > 0))
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise TableError(
            f"{where}: column {width_col!r} is {width[row]} on a face row (frame {int(block.frame[row])} of video "
            f"{str(block.video[row])!r}; {int(bad.sum())} such rows): {layout.detector}'s z is in its crop's units "
            f"and FaceRectWidth converts it. Fix: keep py-feat's FaceRect values as detect wrote them, or set "
            f"data.mesh_units=pixels if z is already in pixels."
        )
    return unit, width / divisor


def convert_units(block: Block, layout: pyfeat.Layout, mesh_units: str, where: str) -> UnitStats:
    """The kept rows' meshes to frame pixels, in place (module docstring, step 3); what was done, measured.

    The face's depth/height is measured as written and, after a conversion, again on the mesh as it leaves. For a
    detector's export the ratio with z converted by its crop (the written ratio x the row's factor: z scales, y does
    not) is kept whether or not the conversion was made (``UnitStats.crop``: the guard's "with the conversion").
    """
    extents = shape_extents(block.mesh)  # (n, 3): the units' judgement and the face's proportions
    normalized = normalized_rows(block.mesh, rect_side(block, layout), extents[:, :2])
    if normalized.any() and not normalized.all():
        row = int(np.flatnonzero(normalized != normalized[0])[0])
        raise TableError(
            f"{where}: mixes meshes in pixels and in normalized image units (frame {int(block.frame[row])} of "
            f"video {str(block.video[row])!r} differs from the first). Fix: export every video the same way."
        )
    ratio = depth_height(extents)
    n = len(block)
    stats = UnitStats(detector=layout.detector, rows=n, before=ratio_hist(ratio))
    stats.after = stats.before
    if n and normalized[0]:
        to_pixels(block, layout, normalized, where)
        stats.after = ratio_hist(depth_height(shape_extents(block.mesh)))  # measured on the mesh as it leaves
        stats.xy = stats.z = "normalized"
        stats.rows_converted = stats.rows_normalized = n
        return stats
    if layout.detector in Z_CROP and layout.box_size is not None:
        width = block.values[pyfeat.FACE_BOX_SIZE[0]]
        stats.crop = ratio_hist(ratio * width / Z_CROP[layout.detector][1])
        stats.growth = growth_sums(extents[:, 2], extents[:, 1], frontal(block.values))
    if n:
        unit, factor = z_scale(block, layout, mesh_units, where)
        stats.xy, stats.z = "pixels", unit
        if factor is not None:
            block.mesh[:, 2 * N_VERTICES :] *= factor.astype(np.float32)[:, None]
            extents[:, 2:] = shape_extents(block.mesh, (2,))  # measured on the mesh as it leaves (its z)
            stats.after = ratio_hist(depth_height(extents))
            stats.rows_converted = stats.rows_z_converted = n
    return stats


def clean_block(
    block: Block,
    layout: pyfeat.Layout,
    how: str,
    subjects: dict[str, str] | None,
    where: str,
    mesh_units: str = "detector",
) -> tuple[Block, Counts]:
    """No-face rows dropped, one face per frame, meshes in pixels (module docstring)."""
    empty = no_face_rows(block, layout)
    faces = block.take(np.flatnonzero(~empty))
    keep, counts = select_faces(faces, layout, how, subjects, where)
    out = faces.take(keep)
    stats = convert_units(out, layout, mesh_units, where)
    counts.rows_in, counts.no_face, counts.rows_out = len(block), int(empty.sum()), len(out)
    counts.rows_normalized = stats.rows_normalized
    counts.rows_z_chip = stats.rows_z_converted if stats.z == "chip" else 0
    counts.rows_z_crop256 = stats.rows_z_converted if stats.z == "crop256" else 0
    counts.units = {where: stats}
    if layout.identity is not None and out.identity is not None:
        counts.labels = {where: identity_labels(out.identity)}
    return out, counts


def identity_labels(identity: np.ndarray) -> set[str]:
    """The distinct Identity labels of some rows (py-feat writes NaN where it has none)."""
    return {str(v) for v in identity if v is not None and not (isinstance(v, float) and np.isnan(v))}


def identity_counts(block: Block, layout: pyfeat.Layout) -> dict[str, dict[str, int]]:
    """video -> Identity -> face rows of the block (``data.face_selection=identity``'s first pass)."""
    if layout.identity is None or block.identity is None:
        return {}
    face = ~no_face_rows(block, layout)
    out: dict[str, dict[str, int]] = {}
    for v, ident in zip(block.video[face], block.identity[face], strict=True):
        if ident is None or (isinstance(ident, float) and np.isnan(ident)):
            continue
        c = out.setdefault(str(v), {})
        c[str(ident)] = c.get(str(ident), 0) + 1
    return out


# ------------------------------------------------------------------------------------------------------- writing


def output_schema() -> pa.Schema:
    """The ingested tables' columns: video_id, frame, the AUs and pose (model order), the mesh axis-major, float32."""
    fields = [pa.field(VIDEO_COLUMN, pa.string()), pa.field(FRAME_COLUMN, pa.int64())]
    fields += [pa.field(c, pa.float64()) for c in (*AU_COLUMNS, *POSE_COLUMNS)]
    fields += [pa.field(name, pa.float32()) for name in pyfeat.MESH_NAMES["MPDetector"]]
    return pa.schema(fields)


def to_table(block: Block, schema: pa.Schema) -> pa.Table:
    arrays = [pa.array(block.video, pa.string()), pa.array(block.frame, pa.int64())]
    arrays += [pa.array(block.values[c]) for c in (*AU_COLUMNS, *POSE_COLUMNS)]
    arrays += [pa.array(col) for col in np.asarray(block.mesh, np.float32).T]
    return pa.Table.from_arrays(arrays, schema=schema)


def iter_clean_blocks(
    spans: Sequence[Span], how: str, subjects: dict[str, str] | None, mesh_units: str = "detector"
) -> Iterator[tuple[Block, Counts]]:
    """Each span read and cleaned (:func:`clean_block`)."""
    for span in spans:
        for rows, table in iter_span_tables(span):
            block = to_block(table, rows)
            yield clean_block(block, span.source.layout, how, subjects, str(span.source.path), mesh_units)


def write_clean(
    spans: Sequence[Span], out: Path, how: str, subjects: dict[str, str] | None, mesh_units: str = "detector"
) -> Counts:
    """Clean ``spans`` into one parquet ``out`` (uncompressed: the pipeline reads it a few times, at memory speed)."""
    schema = output_schema()
    total = Counts()
    writer = pq.ParquetWriter(out, schema, compression="none", use_dictionary=[VIDEO_COLUMN], write_statistics=False)
    try:
        for block, counts in iter_clean_blocks(spans, how, subjects, mesh_units):
            total = total + counts
            if len(block):
                writer.write_table(to_table(block, schema), row_group_size=ROW_GROUP_ROWS)
    finally:
        writer.close()
    return total


def span_identities(spans: Sequence[Span]) -> Counts:
    """Identity counts of ``spans`` (only the columns they need are read)."""
    total = Counts()
    for span in spans:
        lay = span.source.layout
        cols = [
            lay.video,
            FRAME_COLUMN,
            *AU_COLUMNS,
            *POSE_COLUMNS,
            *([lay.face_score] if lay.face_score else []),
            *([lay.identity] if lay.identity else []),
            *(lay.mesh or ()),
        ]
        for rows, table in iter_span_tables(span, cols):
            block = to_block(_with_missing(table, lay), rows)
            total = total + Counts(identities=identity_counts(block, lay))
    return total


def _with_missing(table: pa.Table, lay: pyfeat.Layout) -> pa.Table:
    """``table`` with the layout's numeric columns it was not read with, as NaN (only what a pass needs is read)."""
    for name in lay.numeric:
        if name not in table.column_names:
            table = table.append_column(name, pa.array(np.full(table.num_rows, np.nan)))
    return table


@dataclass(frozen=True)
class PassThrough:
    """A parquet table the pipeline reads as it is (already clean: one face row per frame, pixels).

    ``units``: its mesh units, the face's proportions measured on the rows the check read; ``labels``: py-feat's
    Identity labels (None without the column)."""

    clean: bool
    rows: int
    reason: str = ""
    units: UnitStats | None = None
    labels: set[str] | None = None


def check_clean(source: Source, mesh_units: str = "detector") -> PassThrough:
    """Whether a parquet source can be read in place: a mesh in pixels (the split layout, a ``table`` without py-feat's
    FaceRect, or any interleaved table with ``mesh_units="pixels"``), no no-face rows, one row per frame. Reads the id,
    AU and pose columns (and Identity) a batch at a time and the x, y, z of :data:`SHAPE_VERTICES` on up to the first
    :data:`ROW_GROUP_ROWS` rows (the units and the face's proportions): a fraction of one pass over the table."""
    lay = source.layout
    if lay.detector == "Detectorv2":
        return PassThrough(False, source.n_rows or 0, "Detectorv2 mesh columns")
    if lay.detector in Z_CROP and mesh_units == "detector":  # z in the crop's units: converted (Detectorv2 above)
        return PassThrough(False, source.n_rows or 0, "MPDetector z in its 256-px crop's units")
    n = source.n_rows or 0
    # a no-face row has every AU and pose value NaN: a row whose first AU and Pitch are NaN sends the table to be
    # cleaned, where the whole rule applies (a face row with only those missing is then the contract's error)
    cols = [lay.video, FRAME_COLUMN, AU_COLUMNS[0], POSE_COLUMNS[0], *([lay.face_score] if lay.face_score else [])]
    cols += [lay.identity] if lay.identity else []
    no_face, several, previous = 0, 0, None
    labels: set[str] | None = set() if lay.identity else None
    try:
        reader = pq.ParquetFile(source.path)
    except (pa.ArrowException, OSError) as err:
        raise corrupt_parquet(source.path, err) from None
    for table in _parquet_batches(source, cols, reader=reader):  # a batch at a time: memory flat in the table's rows
        empty = np.isnan(table.column(AU_COLUMNS[0]).to_numpy(zero_copy_only=False).astype(np.float64)) & np.isnan(
            table.column(POSE_COLUMNS[0]).to_numpy(zero_copy_only=False).astype(np.float64)
        )
        if lay.face_score:
            empty |= table.column(lay.face_score).to_numpy(zero_copy_only=False) == 0
        no_face += int(empty.sum())
        video, frame, m = table.column(lay.video), table.column(FRAME_COLUMN), table.num_rows
        if m:  # repeated (video, frame) keys, compared in Arrow (no Python string per row)
            same = pc.and_(
                pc.equal(video.slice(1), video.slice(0, m - 1)), pc.equal(frame.slice(1), frame.slice(0, m - 1))
            )
            several += int(pc.sum(same).as_py() or 0) + int((video[0].as_py(), frame[0].as_py()) == previous)
            previous = (video[m - 1].as_py(), frame[m - 1].as_py())
        if labels is not None and lay.identity:
            labels |= identity_labels(np.array(pc.unique(table.column(lay.identity)).drop_null().to_pylist()))
    if not n:  # an empty table: nothing to clean (prepare names empty input)
        return PassThrough(True, 0)
    if no_face:
        return PassThrough(False, n, f"{no_face} no-face rows")
    if several:
        return PassThrough(False, n, "several faces in a frame")
    rows = max(1, min(n, ROW_GROUP_ROWS))
    mesh = np.full((rows, 3 * N_VERTICES), np.nan, np.float32)
    rect = None
    if lay.mesh is not None:
        names = lay.mesh
        mesh_cols = [names[a * N_VERTICES + i] for a in range(3) for i in SHAPE_VERTICES]
        part = next(
            _parquet_batches(
                source, mesh_cols + list(lay.box_size or ()) + ["Pitch", "Yaw"], batch_rows=rows, reader=reader
            ),
            pa.table({}),
        )
        mesh = mesh[: part.num_rows]
        for name in mesh_cols:
            mesh[:, names.index(name)] = part.column(name).to_numpy(zero_copy_only=False)
        if lay.box_size is not None:
            w, h = (part.column(c).to_numpy(zero_copy_only=False).astype(np.float64) for c in lay.box_size)
            rect = np.fmax(w, h)
    else:
        assert source.mesh_npy is not None, source  # open_source pairs a table without mesh columns with its .npy
        with NpyRowFile(source.mesh_npy) as f:
            sample = f.read(0, rows)
        mesh = np.ascontiguousarray(sample.astype(np.float32).transpose(0, 2, 1)).reshape(len(sample), -1)
    extents = shape_extents(mesh)
    finite = np.isfinite(extents).all(axis=1)
    extents = extents[finite]
    if finite.any() and normalized_rows(mesh[finite], None if rect is None else rect[finite], extents[:, :2]).any():
        return PassThrough(False, n, "normalized image units", labels=labels)
    ratio = depth_height(extents)
    hist = ratio_hist(ratio)
    units = UnitStats(lay.detector, "pixels", "pixels", rows=n, before=hist, after=hist)
    if lay.detector in Z_CROP and rect is not None:  # z taken as pixels (mesh_units=pixels): the ratio converted
        assert lay.box_size is not None
        width = part.column(lay.box_size[0]).to_numpy(zero_copy_only=False).astype(np.float64)[finite]
        units.crop = ratio_hist(ratio * width / Z_CROP[lay.detector][1])
        pose = {c: part.column(c).to_numpy(zero_copy_only=False).astype(np.float64)[finite] for c in ("Pitch", "Yaw")}
        units.growth = growth_sums(extents[:, 2], extents[:, 1], frontal(pose))
    return PassThrough(True, n, units=units, labels=labels)
