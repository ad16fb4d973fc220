"""py-feat's files as users have them -> the pipeline's frame tables: one row per (video, frame), pixels, only the
contract's columns. Pure functions on a block of rows, what a block's cleaning counted (:class:`Counts`), and the
writer at the edge; the files are read by :mod:`aumesh.data.readers`.

What a block goes through (:func:`clean_block`), in order:

1. **no face**: py-feat writes a frame without a face as one row with ``FaceScore`` 0 (MPDetector) or with every
   measurement NaN (Detectorv2: its FaceScore is NaN too). Such rows are dropped and counted. A row with only *some*
   values missing is kept, and the data contract refuses it downstream: that is corruption, not a missing face;
2. **several faces**: py-feat writes one row per face, the rows of one frame consecutive (same ``input`` and
   ``frame``). ``data.face_selection`` keeps one: ``largest`` (the largest face box; where two boxes are about the
   same size, the face that continues the video's track: :mod:`aumesh.data.face_track`), ``identity`` (py-feat's
   ``Identity`` seen in most of the video's face rows; frames without that person are dropped) or ``error``;
3. **units** (docs/conventions.md, "py-feat's mesh units"): the mesh leaves in frame pixels, x, y and z
   (:func:`aumesh.data.units.convert_units`: normalized image units by the frame size, z from the detector's crop
   units by FaceRectWidth, the face's proportions measured for the ingest stage's guard);
4. **families** (issue 46, docs/families.md): the 52 blendshapes and 7 emotions a source's header holds are carried
   under the family's names (:attr:`aumesh.data.pyfeat.Layout.families`); in each kept face row a family is measured
   (every value finite) or not (every value NaN: MPDetector run with ``emotion_model=None`` writes its 7 emotions so
   in every row), counted per source (:attr:`Counts.families`); a row with only some of them NaN is refused, as a
   face row with only some AUs missing is (:func:`family_rows`). Which families the stage then carries is the
   ingest stage's decision over all sources (:func:`aumesh.pipeline.ingest.carried_families`).

A clean parquet table is read in place (:func:`check_clean`) instead of being written again.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, fields
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from aumesh.core.errors import TableError
from aumesh.core.families import CARRIED_FAMILIES, FAMILIES
from aumesh.core.schema import AU_COLUMNS, FRAME_COLUMN, N_VERTICES, POSE_COLUMNS, VIDEO_COLUMN
from aumesh.data import face_track, pyfeat, video_frames
from aumesh.data.readers import (
    Block,
    Span,
    iter_span_groups,
    iter_span_tables,
    row_place,
    to_block,
)
from aumesh.data.units import (
    UnitStats,
    convert_units,
)

#: Rows of an output row group (prepare packs whole row groups into its partitions).
ROW_GROUP_ROWS = 8192


@dataclass
class Counts:
    """What a span's cleaning dropped and converted, summed over spans."""

    rows_in: int = 0
    no_face: int = 0  # rows of frames without a face
    extra_faces: int = 0  # face rows dropped by data.face_selection (another face in the same frame)
    frames_several_faces: int = 0  # frames with more than one face row
    frames_without_subject: int = 0  # identity selection: frames where the video's subject is not seen
    frames_ambiguous: int = 0  # frames with two faces of about the same size (face_track.AMBIGUOUS_AREA_RATIO)
    rows_out: int = 0
    rows_normalized: int = 0  # rows whose mesh was converted from normalized image units to pixels
    rows_z_chip: int = 0  # rows whose z was converted from Detectorv2's chip units
    rows_z_crop256: int = 0  # rows whose z was converted from MPDetector's 256-px crop units
    identities: dict[str, dict[str, int]] = field(default_factory=dict)  # video -> Identity -> face rows
    units: dict[str, UnitStats] = field(default_factory=dict)  # source path -> its units
    labels: dict[str, set[str]] = field(default_factory=dict)  # source path -> Identity labels of kept rows
    frame_ranges: video_frames.FrameRanges = field(default_factory=dict)  # video -> (source, first, last frame) kept
    # source path -> family -> [face rows measured, face rows all NaN, where the first all-NaN row is ("" if none)]
    families: dict[str, dict[str, list]] = field(default_factory=dict)

    def __add__(self, other: Counts) -> Counts:
        total = Counts()
        total += self
        total += other
        return total

    def __iadd__(self, other: Counts) -> Counts:
        """``other`` added into these counts (a sum over thousands of sources' counts in linear time: a new
        :class:`Counts` per addition copied every source's units and labels each time). ``other``'s objects are never
        changed, nor shared where this sum changes them."""
        for f in fields(self):
            if f.name not in ("identities", "units", "labels", "frame_ranges", "families"):
                setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))
        for v, c in other.identities.items():
            mine = self.identities.get(v)
            if mine is None:
                mine = self.identities[v] = {}
            for k, n in c.items():
                mine[k] = mine.get(k, 0) + n
        for k, u in other.units.items():
            self.units[k] = self.units[k] + u if k in self.units else u  # UnitStats.__add__: a new object
        for k, names in other.labels.items():
            self.labels.setdefault(k, set()).update(names)
        video_frames.merge_into(self.frame_ranges, other.frame_ranges)
        for k, held in other.families.items():
            mine_f = self.families.setdefault(k, {})
            for family, (measured, unmeasured, first) in held.items():
                have = mine_f.get(family, [0, 0, ""])
                mine_f[family] = [have[0] + measured, have[1] + unmeasured, have[2] or first]
        return self

    def as_dict(self) -> dict[str, int]:
        out = {
            "rows_in": self.rows_in,
            "dropped_no_face": self.no_face,
            "dropped_extra_faces": self.extra_faces,
            "frames_with_several_faces": self.frames_several_faces,
            "dropped_frames_without_subject": self.frames_without_subject,
            "frames_ambiguous_faces": self.frames_ambiguous,
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


def face_centres(block: Block, layout: pyfeat.Layout) -> np.ndarray:
    """(n, 2) each face's box centre: py-feat's FaceRectX + Width / 2, FaceRectY + Height / 2, else the centre of the
    mesh's x/y extent (as :func:`face_areas`)."""
    if layout.box_origin and layout.box_size:
        (x, y), (w, h) = ([block.values[c] for c in cols] for cols in (layout.box_origin, layout.box_size))
        centre = np.column_stack([x + w / 2, y + h / 2])
        if np.isfinite(centre).all():
            return centre
    x, y = block.mesh[:, :N_VERTICES], block.mesh[:, N_VERTICES : 2 * N_VERTICES]
    return np.column_stack(
        [(np.nanmax(x, axis=1) + np.nanmin(x, axis=1)) / 2, (np.nanmax(y, axis=1) + np.nanmin(y, axis=1)) / 2]
    ).astype(np.float64)


def main_identities(identities: dict[str, dict[str, int]]) -> dict[str, str]:
    """Each video's subject: the Identity of most of its face rows (ties: the first name in sorted order)."""
    return {v: sorted(c.items(), key=lambda kv: (-kv[1], kv[0]))[0][0] for v, c in identities.items() if c}


def select_faces(
    block: Block,
    layout: pyfeat.Layout,
    how: str,
    subjects: dict[str, str] | None,
    where: str,
    tracks: dict[str, face_track.Face] | None = None,
) -> tuple[np.ndarray, Counts]:
    """Rows kept (one per frame) among face rows, by ``data.face_selection`` (``how``), and what was dropped.

    Parameters
    ----------
    block : face rows only (no-face rows removed), a frame's rows consecutive, a video's frames in order.
    subjects : video -> its subject's Identity (``how="identity"``).
    tracks : video -> the face kept in its last frame of the block before, of the same range of the file (updated in
        place); None: the block starts each video's track (:mod:`aumesh.data.face_track`).
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
    areas = face_areas(block, layout)
    area = np.where(candidate, areas, -np.inf)
    # the largest candidate of each frame (ties: the first row): argmax within runs, as a sort by (group, -area)
    group_of = np.repeat(np.arange(len(sizes)), sizes)
    order = np.lexsort((np.arange(len(block)), -area, group_of))
    first = order[groups[:-1]]
    # two faces of about the same size: the one that continues the video's track (tracks carried: always followed)
    if (sizes > 1).any() or tracks is not None:
        first, counts.frames_ambiguous = face_track.follow(
            block.video,
            groups,
            first,
            candidate,
            areas,
            face_centres(block, layout),
            block.identity,
            {} if tracks is None else tracks,
        )
    keep = first[candidate[first]]
    counts.frames_without_subject = int(len(first) - len(keep))
    counts.extra_faces = int(len(block) - len(first))
    return np.sort(keep), counts


def clean_block(
    block: Block,
    layout: pyfeat.Layout,
    how: str,
    subjects: dict[str, str] | None,
    where: str,
    mesh_units: str = "detector",
    tracks: dict[str, face_track.Face] | None = None,
    place: Callable[[int], str] | None = None,
) -> tuple[Block, Counts]:
    """No-face rows dropped, one face per frame, meshes in pixels (module docstring); the kept rows' values checked
    (:func:`check_face_values`). ``tracks`` as :func:`select_faces`'s; ``place``: where a row of ``block`` (as read)
    is in the user's file ("line 7"; default "row 5" of the block)."""
    empty = no_face_rows(block, layout)
    face_rows = np.flatnonzero(~empty)
    faces = block.take(face_rows)
    keep, counts = select_faces(faces, layout, how, subjects, where, tracks)
    out = faces.take(keep)
    check_face_values(out, layout, where, face_rows[keep], place or (lambda row: f"row {row}"))
    families = family_rows(out, layout, where, face_rows[keep], place or (lambda row: f"row {row}"))
    stats = convert_units(out, layout, mesh_units, where)
    counts.rows_in, counts.no_face, counts.rows_out = len(block), int(empty.sum()), len(out)
    counts.rows_normalized = stats.rows_normalized
    counts.rows_z_chip = stats.rows_z_converted if stats.z == "chip" else 0
    counts.rows_z_crop256 = stats.rows_z_converted if stats.z == "crop256" else 0
    counts.units = {where: stats}
    counts.frame_ranges = video_frames.block_ranges(out.video, out.frame, where)
    if layout.identity is not None and out.identity is not None:
        counts.labels = {where: identity_labels(out.identity)}
    if families:
        counts.families = {where: families}
    return out, counts


def family_rows(
    block: Block, layout: pyfeat.Layout, where: str, rows: np.ndarray, place: Callable[[int], str]
) -> dict[str, list]:
    """Per family the kept face rows of ``block`` that measured it (every value finite) and that did not (every value
    NaN), and where the first of those is: ``{family: [measured, unmeasured, place or ""]}``.

    NaN in a family column of a face row is treated as in the AU columns: a row with only some values missing is
    corruption, refused; a row with the whole family NaN is that family not measured there (py-feat writes a family
    it did not run so: MPDetector's ``emotion_model=None`` gives NaN emotions in every row, as a no-face row has NaN
    AUs). Whether a source that mixes the two is refused is the ingest stage's call over the whole source
    (:func:`aumesh.pipeline.ingest.carried_families`).

    Raises
    ------
    TableError
        One line naming ``where``, the column, the row's line and the fix.
    """
    out: dict[str, list] = {}
    for family, columns in layout.families:
        x = np.column_stack([block.values[c] for c in columns]) if len(block) else np.zeros((0, len(columns)))
        nan = np.isnan(x)
        finite = np.isfinite(x)
        measured, unmeasured = finite.all(axis=1), nan.all(axis=1)
        bad = ~(measured | unmeasured)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            j = int(np.flatnonzero(~finite[i])[0])
            raise TableError(
                f"{where}: {family} column {columns[j]!r} is {x[i, j]} at {place(int(rows[i]))}, a face row whose other "
                f"{family} columns hold values ({int(bad.sum())} such rows). Fix: drop those frames before `dvc add "
                f"data`, or drop every {family} column to train without them."
            )
        first = place(int(rows[int(np.flatnonzero(unmeasured)[0])])) if unmeasured.any() else ""
        out[family] = [int(measured.sum()), int(unmeasured.sum()), first]
    return out


def check_face_values(
    block: Block, layout: pyfeat.Layout, where: str, rows: np.ndarray, place: Callable[[int], str]
) -> None:
    """The data contract on the face rows ingest keeps, where the user's file and its lines are known: AUs finite and
    in 0-1, pose finite within ±π (:func:`aumesh.data.contract.validate_metadata`, the check prepare applies to
    every table), instrument AUs and the mesh finite. An ingested table is then never the first place such a value is
    found (prepare's check stays the guard of the parquet tables of ``data/`` read in place).

    Parameters
    ----------
    block : (n,) kept rows.
    rows : (n,) each kept row's row in the block as read; ``place(row)`` names it in the user's file ("line 7").

    Raises
    ------
    TableError
        The contract's one line (the column, the value and the fix), naming ``where`` and the row's line.
    """
    names = [*AU_COLUMNS, *POSE_COLUMNS]
    x = np.column_stack([block.values[c] for c in names]) if len(block) else np.zeros((0, len(names)))
    au, pose = x[:, : len(AU_COLUMNS)], x[:, len(AU_COLUMNS) :]
    with np.errstate(invalid="ignore"):
        fine = np.isfinite(x).all() and (au >= 0).all() and (au <= 1).all() and (np.abs(pose) <= np.pi).all()
    if not fine:
        from aumesh.data import contract  # pandera: imported only when a value is refused

        frame = pd.DataFrame(
            {VIDEO_COLUMN: block.video, FRAME_COLUMN: block.frame} | {c: block.values[c] for c in names}
        )
        contract.validate_metadata(frame, where, row_name=lambda i: place(int(rows[i])))
    if layout.instruments and not all(np.isfinite(block.values[c]).all() for c in layout.instruments):
        from aumesh.data import contract

        frame = pd.DataFrame({c: block.values[c] for c in layout.instruments})
        contract.check_instrument_values(frame, layout.instruments, where, row_name=lambda i: place(int(rows[i])))
    finite = np.isfinite(block.mesh)
    if not finite.all():
        i, j = (int(k[0]) for k in np.nonzero(~finite))
        column = layout.mesh[j] if layout.mesh is not None else f"{'xyz'[j // N_VERTICES]}_{j % N_VERTICES}"
        raise TableError(
            f"{where}: mesh column {column} is NaN/inf at {place(int(rows[i]))}, a row with a face. Fix: drop frames "
            f"where the face mesh failed (rows with NaN landmarks) before `dvc add data`."
        )


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


def output_schema(instruments: Sequence[str] = (), families: Sequence[str] = ()) -> pa.Schema:
    """The ingested tables' columns: video_id, frame, the AUs and pose (model order), the instrument AUs
    (``model.eiv.instrument_aus``, only when configured: none by default), the ``families``' columns under the
    family's names (:data:`aumesh.core.families.FAMILIES`, float64), the mesh axis-major, float32."""
    fields = [pa.field(VIDEO_COLUMN, pa.string()), pa.field(FRAME_COLUMN, pa.int64())]
    names = [c for f in families for c in FAMILIES[f]]
    fields += [pa.field(c, pa.float64()) for c in (*AU_COLUMNS, *POSE_COLUMNS, *instruments, *names)]
    fields += [pa.field(name, pa.float32()) for name in pyfeat.MESH_NAMES["MPDetector"]]
    return pa.schema(fields)


def task_families(spans: Sequence[Span]) -> tuple[str, ...]:
    """The families every source of ``spans`` holds (:attr:`aumesh.data.pyfeat.Layout.families`): those an ingested
    table written from them carries. A family a source of the task lacks is not carried by any table of the stage
    (:func:`aumesh.pipeline.ingest.carried_families`), so nothing is filled in for it."""
    held = [set(s.source.layout.family_names) for s in spans]
    return tuple(f for f in CARRIED_FAMILIES if held and all(f in h for h in held))


def renamed(block: Block, layout: pyfeat.Layout, families: Sequence[str]) -> Block:
    """``block`` with only the columns an ingested table holds (:func:`output_schema`), the ``families``' under the
    family's names (Detectorv2's ``Happy`` as ``happiness``): blocks of sources of either detector then concatenate."""
    values = {k: block.values[k] for k in (*AU_COLUMNS, *POSE_COLUMNS, *layout.instruments)}
    values |= {name: block.values[col] for name, col in layout.family_renames(families)}
    return Block(block.video, block.frame, values, block.identity, block.mesh)


def to_table(block: Block, schema: pa.Schema) -> pa.Table:
    """``block`` as a table of ``schema`` (:func:`output_schema`: its float64 columns are the block's values, the
    families' under the family's names: :func:`renamed`)."""
    numeric = [f.name for f in schema if f.type == pa.float64()]
    arrays = [pa.array(block.video, pa.string()), pa.array(block.frame, pa.int64())]
    arrays += [pa.array(block.values[c]) for c in numeric]
    arrays += [pa.array(col) for col in np.asarray(block.mesh, np.float32).T]
    return pa.Table.from_arrays(arrays, schema=schema)


#: ``(source path, span start)`` -> the face tracks a carried span starts from (:func:`carried_tracks`).
Seeds = dict[tuple[str, int], dict[str, face_track.Face]]


def iter_clean_blocks(
    spans: Sequence[Span],
    how: str,
    subjects: dict[str, str] | None,
    mesh_units: str = "detector",
    seeds: Seeds | None = None,
    families: Sequence[str] | None = None,
) -> Iterator[tuple[Block, Counts]]:
    """Each span read and cleaned (:func:`clean_block`), source by source; the small CSV ranges of many files
    parsed together (:func:`aumesh.data.readers.iter_span_groups`). A span starts its videos' face tracks afresh (the
    batches of one span carry them), or, when it starts inside a run of frames with several faces
    (``Span.carried``), from the tracks ``seeds`` gives it (:func:`carried_tracks`): the rows kept do not depend on
    how the file is cut into spans nor on how spans are packed into tasks. ``families``: the blocks' columns of these
    families under the family's names (:func:`renamed`; None: as the sources name them)."""
    key, tracks = None, {}
    for table, parts in iter_span_groups(spans):
        block = to_block(table, parts[0][1])
        for span, rows, first, stop in parts:
            if (str(span.source.path), span.start) != key:  # a new span: its own tracks
                key = (str(span.source.path), span.start)
                tracks = dict((seeds or {}).get(key, {}))
            part = block if (first, stop) == (0, len(block)) else block.take(np.arange(first, stop))
            src = span.source
            out, counts = clean_block(
                part, src.layout, how, subjects, str(src.path), mesh_units, tracks, partial(row_place, rows)
            )
            yield (out if families is None else renamed(out, src.layout, families)), counts


def concat_blocks(blocks: Sequence[Block]) -> Block:
    """The rows of ``blocks`` in order, as one :class:`~aumesh.data.readers.Block` (same columns)."""
    if len(blocks) == 1:
        return blocks[0]
    identity = None if blocks[0].identity is None else np.concatenate([b.identity for b in blocks])
    return Block(
        np.concatenate([b.video for b in blocks]),
        np.concatenate([b.frame for b in blocks]),
        {k: np.concatenate([b.values[k] for b in blocks]) for k in blocks[0].values},
        identity,
        np.concatenate([b.mesh for b in blocks]),
    )


#: Cleaned blocks smaller than this are written together, up to :data:`ROW_GROUP_ROWS` rows a row group: a row group
#: per block of a one-row CSV (py-feat's one file per video) cost ~25 ms to write and ~250 KB of footer metadata each,
#: held by the writer to the end (2.6 MB a file in all). A larger block (a range of a long CSV) is its own row group.
SMALL_BLOCK_ROWS = 1024


def write_clean(
    spans: Sequence[Span],
    out: Path,
    how: str,
    subjects: dict[str, str] | None,
    mesh_units: str = "detector",
    seeds: Seeds | None = None,
) -> Counts:
    """Clean ``spans`` into one parquet ``out`` (uncompressed: the pipeline reads it a few times, at memory speed).
    The sources' instrument columns (their layout's, ``model.eiv.instrument_aus``) are carried beside the AUs, and
    the families every source of ``spans`` holds (:func:`task_families`) under the family's names;
    ``seeds``: the face tracks of carried spans (:func:`carried_tracks`). Blocks of fewer than
    :data:`SMALL_BLOCK_ROWS` rows are written together."""
    families = task_families(spans)
    schema = output_schema(spans[0].source.layout.instruments if spans else (), families)
    total = Counts()
    pending: list[Block] = []
    writer = pq.ParquetWriter(out, schema, compression="none", use_dictionary=[VIDEO_COLUMN], write_statistics=False)

    def flush() -> int:
        if pending:
            writer.write_table(to_table(concat_blocks(pending), schema), row_group_size=ROW_GROUP_ROWS)
            pending.clear()
        return 0

    try:
        rows = 0  # in pending
        for block, counts in iter_clean_blocks(spans, how, subjects, mesh_units, seeds, families):
            total += counts
            if len(block) >= SMALL_BLOCK_ROWS:
                flush()
                pending.append(block)
                rows = flush()
            elif len(block):
                pending.append(block)
                rows += len(block)
                if rows >= SMALL_BLOCK_ROWS:
                    rows = flush()
        flush()
    finally:
        writer.close()
    return total


def track_chains(spans: Sequence[Span]) -> list[tuple[Span, ...]]:
    """The runs of consecutive spans of one source that a carried span (``Span.carried``) needs followed in order:
    the span before the first carried one, then each carried one. Empty when no span is carried."""
    chains: list[list[Span]] = []
    for i, span in enumerate(spans):
        if not span.carried or i == 0 or spans[i - 1].source.path != span.source.path:
            continue
        if chains and chains[-1][-1] == spans[i - 1]:
            chains[-1].append(span)
        else:
            chains.append([spans[i - 1], span])
    return [tuple(c) for c in chains]


def carried_tracks(chain: Sequence[Span], how: str, subjects: dict[str, str] | None) -> Seeds:
    """The face tracks each carried span of ``chain`` (:func:`track_chains`) starts from: the chain's spans followed in
    order, as one pass over the file would (only face selection: no units, nothing written). Only runs of frames
    with several faces longer than a CSV range need it (:func:`aumesh.data.readers.csv_spans`)."""
    out: Seeds = {}
    tracks: dict[str, face_track.Face] = {}
    for span in chain[:-1]:
        for rows, table in iter_span_tables(span):
            block = to_block(table, rows)
            faces = block.take(np.flatnonzero(~no_face_rows(block, span.source.layout)))
            select_faces(faces, span.source.layout, how, subjects, str(span.source.path), tracks)
        nxt = chain[chain.index(span) + 1]
        out[(str(nxt.source.path), nxt.start)] = dict(tracks)
    return out


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
            total += Counts(identities=identity_counts(block, lay))
    return total


def _with_missing(table: pa.Table, lay: pyfeat.Layout) -> pa.Table:
    """``table`` with the layout's numeric columns it was not read with, as NaN (only what a pass needs is read)."""
    for name in lay.numeric:
        if name not in table.column_names:
            table = table.append_column(name, pa.array(np.full(table.num_rows, np.nan)))
    return table
