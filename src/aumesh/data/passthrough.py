"""A parquet table of ``data/`` read in place (:func:`check_clean`): the ingest stage's check that it is already clean
(one face row per frame, a mesh in pixels) and what it holds (units, identity labels, each video's frames), read a
few columns and a batch at a time instead of copied.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from aumesh.core.errors import corrupt_parquet
from aumesh.core.io import NpyRowFile
from aumesh.core.schema import AU_COLUMNS, FRAME_COLUMN, N_VERTICES, POSE_COLUMNS
from aumesh.data import video_frames
from aumesh.data.ingest import ROW_GROUP_ROWS, identity_labels
from aumesh.data.readers import Source, parquet_batches
from aumesh.data.units import (
    SHAPE_VERTICES,
    Z_CROP,
    UnitStats,
    depth_height,
    frontal,
    growth_sums,
    normalized_rows,
    ratio_hist,
    shape_extents,
)


@dataclass(frozen=True)
class PassThrough:
    """A parquet table the pipeline reads as it is (already clean: one face row per frame, pixels).

    ``units``: its mesh units, the face's proportions measured on the rows the check read; ``labels``: py-feat's
    Identity labels (None without the column); ``frame_ranges``: each video's frames
    (:mod:`aumesh.data.video_frames`); ``families``: per family its header holds, ``[rows measured, rows NaN, where
    the first NaN row is]`` as :attr:`aumesh.data.ingest.Counts.families` (judged on the family's first column: a
    row with only some of a family's values NaN is refused by prepare's check of the carried columns)."""

    clean: bool
    rows: int
    reason: str = ""
    units: UnitStats | None = None
    labels: set[str] | None = None
    frame_ranges: video_frames.FrameRanges | None = None
    families: dict[str, list] | None = None


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
    firsts = {family: columns[0] for family, columns in lay.families}  # a family's first column: measured or not
    cols += [c for c in firsts.values() if c not in cols]
    families: dict[str, list] = {family: [0, 0, ""] for family in firsts}
    no_face, several, previous = 0, 0, None
    labels: set[str] | None = set() if lay.identity else None
    ranges: video_frames.FrameRanges = {}
    try:
        reader = pq.ParquetFile(source.path)
    except (pa.ArrowException, OSError) as err:
        raise corrupt_parquet(source.path, err) from None
    for table in parquet_batches(source, cols, reader=reader):  # a batch at a time: memory flat in the table's rows
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
        video_frames.merge_into(ranges, _batch_ranges(table, lay.video, str(source.path)))
        for family, column in firsts.items():
            nan = np.isnan(table.column(column).to_numpy(zero_copy_only=False).astype(np.float64))
            seen = families[family]
            if nan.any() and not seen[2]:
                seen[2] = f"row {seen[0] + seen[1] + int(np.argmax(nan))}"
            seen[0], seen[1] = seen[0] + int((~nan).sum()), seen[1] + int(nan.sum())
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
            parquet_batches(
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
        with NpyRowFile(str(source.mesh_npy)) as f:  # local: open_source refuses a remote .npy
            sample = f.read(0, rows)
        mesh = np.ascontiguousarray(sample.astype(np.float32).transpose(0, 2, 1)).reshape(len(sample), -1)
    extents = shape_extents(mesh)
    finite = np.isfinite(extents).all(axis=1)
    extents = extents[finite]
    if finite.any() and normalized_rows(mesh[finite], None if rect is None else rect[finite], extents[:, :2]).any():
        return PassThrough(False, n, "normalized image units", labels=labels, frame_ranges=ranges)
    ratio = depth_height(extents)
    hist = ratio_hist(ratio)
    units = UnitStats(lay.detector, "pixels", "pixels", rows=n, before=hist, after=hist)
    if lay.detector in Z_CROP and rect is not None:  # z taken as pixels (mesh_units=pixels): the ratio converted
        assert lay.box_size is not None
        width = part.column(lay.box_size[0]).to_numpy(zero_copy_only=False).astype(np.float64)[finite]
        units.crop = ratio_hist(ratio * width / Z_CROP[lay.detector][1])
        pose = {c: part.column(c).to_numpy(zero_copy_only=False).astype(np.float64)[finite] for c in ("Pitch", "Yaw")}
        units.growth = growth_sums(extents[:, 2], extents[:, 1], frontal(pose))
    return PassThrough(True, n, units=units, labels=labels, frame_ranges=ranges, families=families or None)


def _batch_ranges(table: pa.Table, video: str, where: str) -> video_frames.FrameRanges:
    """Each video's first and last frame in a batch, computed in Arrow (no Python string per row); a video with a
    frame twice in the batch gets its range twice, so that the files holding it are checked frame by frame."""
    agg = (
        table.select([video, FRAME_COLUMN])
        .group_by(video)
        .aggregate(
            [(FRAME_COLUMN, "min"), (FRAME_COLUMN, "max"), (FRAME_COLUMN, "count"), (FRAME_COLUMN, "count_distinct")]
        )
    )
    out: video_frames.FrameRanges = {}
    for v, lo, hi, n, distinct in zip(
        *(agg.column(c).to_pylist() for c in (video, "frame_min", "frame_max", "frame_count", "frame_count_distinct")),
        strict=True,
    ):
        out[str(v)] = [(where, int(lo), int(hi))] * (1 if n == distinct else 2)
    return out
