"""One video of a py-feat table as a clip over time: its frames, their times, and per frame the AUs, head pose and the
recorded MediaPipe mesh (NaN where the detector found no face).

The table is read by the ingest's readers (:mod:`aumesh.data.readers`: py-feat's CSV, ``.csv.gz`` or parquet, either
detector's mesh layout, the split layout's ``.npy``), and cleaned by its rules, but frame by frame and without
dropping anything: a frame py-feat wrote only as a no-face row stays in the clip with ``has_face`` False; of several
faces in a frame one is kept (``face_selection``, as ``data.face_selection``: the largest face box by default).

**Units** (docs/conventions.md, "py-feat's mesh units"): the recorded mesh leaves in frame pixels on every axis, by
the ingest's own functions on the clip's face rows (:func:`aumesh.data.units.convert_units`), so it equals the
ingest's cleaned mesh of the same frames: Detectorv2's z (0-1 of its chip) x FaceRectWidth, MPDetector's z (pixels of
its 256-px crop) x FaceRectWidth / 256, each row by its own FaceRect; normalized image units, judged from the face's
2-D extent against its FaceRect (:func:`~aumesh.data.units.normalized_rows`: a profile face is tens of pixels tall
even where its inter-ocular distance is below a pixel), x and z x FrameWidth, y x FrameHeight. ``mesh_units="pixels"``
takes a detector's z as pixels (a table rescaled after py-feat). What was done is :attr:`Clip.mesh_units`
(:data:`MESH_UNIT_NOTES` says it in words). One difference from the ingest: a mesh in normalized units in a table
without FrameWidth/FrameHeight is kept as written (``"normalized-raw"``) where the ingest refuses it: the clip still
plays, and the viewer says the comparison is skewed.

**Time.** py-feat numbers a video's frames from 0 (``frame``: the decoder's index, so ``skip_frames=k`` writes
0, k, 2k, ...) and writes ``approx_time`` as ``"MM:SS"``, the frame's time truncated to whole seconds
(``feat.data.VideoDataset.calc_approx_frame_time``). A frame's time is ``frame / fps``. The frame rate is ``fps`` when
given; else the one ``approx_time`` allows (:func:`fps_from_approx_time`); else 25.

**Gaps** (:func:`bridge`): a frame without a face gets the linear interpolation, in time, of the values of the face
frames before and after it when those two are at most ``max_gap_s`` apart (:data:`MAX_GAP_S`, 0.5 s: a blink, a hand
passing); in a longer gap it holds the last face frame's values (the face freezes, then moves on to the next face
frame). Frames before the first face frame hold the first one's values.
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from aumesh.core.errors import MissingFileError, TableError, UserError, corrupt_parquet
from aumesh.core.schema import AU_COLUMNS, INPUT_PATH_COLUMN, N_VERTICES, POSE_COLUMNS
from aumesh.data import ingest, pyfeat, readers
from aumesh.data.clip_time import DEFAULT_FPS, fps_from_approx_time
from aumesh.data.units import Z_CROP, convert_units, normalized_rows, rect_side

log = logging.getLogger(__name__)

APPROX_TIME = "approx_time"
#: A no-face gap whose neighbouring face frames are further apart than this holds the last pose (seconds).
MAX_GAP_S = 0.5
FACE_SELECTIONS = ("largest", "identity", "error")
#: How a clip reads z (``--mesh-units`` of ``aumesh view --clip``), as the ingest's ``data.mesh_units``.
MESH_UNITS = ("detector", "pixels")
#: :attr:`Clip.mesh_units` -> what was done to the recorded mesh, in words (the viewer's status line shows it).
MESH_UNIT_NOTES = {
    "chip": "in frame pixels: z from Detectorv2's chip units \u00d7 FaceRectWidth",
    "crop256": "in frame pixels: z from MPDetector's 256-px crop units \u00d7 FaceRectWidth / 256",
    "normalized": "in frame pixels: x, z \u00d7 FrameWidth and y \u00d7 FrameHeight, from normalized image units",
    "pixels": "in frame pixels as written (not a detector's export: no crop units to convert)",
    "pixels-asked": "z taken as frame pixels as written (--mesh-units pixels)",
    "normalized-raw": "in normalized image units, not converted (the table has no FrameWidth/FrameHeight): the "
    "comparison is skewed by the frame's aspect ratio",
    "none": "none",
}


@dataclass(frozen=True)
class Clip:
    """One video of a py-feat table, one row per frame (ascending frame numbers).

    Attributes
    ----------
    source : the table's file name (no folder: outputs never hold an absolute path).
    video : the video's name as shown: the stem of py-feat's ``input`` where the table has no other video of that stem,
        else its shortest distinguishing path (:func:`aumesh.data.pyfeat.video_names`), or ``video_id``.
    frame : (n,) int64 py-feat's frame numbers, ascending, unique.
    time : (n,) float64 seconds, ``frame / fps`` (``skip_frames`` gaps respected).
    fps : the frame rate used; ``fps_source`` says where it came from: ``"--fps"``, ``"approx_time"`` or
        ``"default (25)"``.
    has_face : (n,) bool.
    aus : (n, 20) float64 in :data:`~aumesh.core.schema.AU_COLUMNS` order, NaN where no face.
    pose : (n, 3) float64 radians, the model's order Pitch, Yaw, Roll, NaN where no face.
    mesh : (n, 478, 3) float64 recorded MediaPipe mesh in frame pixels on every axis (the image's frame: x right,
        y down), converted as the ingest converts it (module docstring, "Units"), NaN rows where no face; None when
        the table has no mesh (or ``mesh_units=None`` was asked).
    detector : the table's layout (``MPDetector``, ``Detectorv2``, ``table``, ``split``, or ``none`` without a mesh).
    frames_several_faces : frames where py-feat found several faces (one kept, by ``face_selection``).
    frame_size : the video's ``FrameWidth, FrameHeight`` in pixels (the first row's that has them), None when the
        table has none.
    mesh_units : what was done to the mesh, a key of :data:`MESH_UNIT_NOTES`: ``chip``, ``crop256``, ``normalized``,
        ``pixels``, ``pixels-asked``, ``normalized-raw`` or ``none``.
    video_id : the video's identity: py-feat's ``input`` path as written (or ``video_id``), as the ingest names it.
    family : the inputs that drive the clip's rig: ``au`` (the AUs, ``aus``) or a family of
        :data:`aumesh.core.families.FAMILIES` (issue 46: ``blendshapes``, ``emotions``), read by name
        (:func:`aumesh.core.families.family_columns`: Detectorv2's ``Happy`` is ``happiness``) into ``inputs``.
    inputs : (n, k) float64 the family's inputs in its order, NaN where no face; None for ``family="au"``.
    """

    source: str
    video: str
    frame: np.ndarray
    time: np.ndarray
    fps: float
    fps_source: str
    has_face: np.ndarray
    aus: np.ndarray
    pose: np.ndarray
    mesh: np.ndarray | None
    detector: str = ""
    frames_several_faces: int = 0
    frame_size: tuple[float, float] | None = None
    mesh_units: str = "none"
    video_id: str = ""
    family: str = "au"
    inputs: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def weights(self) -> np.ndarray:
        """(n, k) what drives the clip's rig: the family's ``inputs``, or the AUs (NaN where no face)."""
        return self.aus if self.inputs is None else self.inputs

    @property
    def duration(self) -> float:
        """Seconds from the first frame to the last."""
        return float(self.time[-1] - self.time[0]) if len(self.time) else 0.0

    def gaps(self, max_gap_s: float = MAX_GAP_S) -> tuple[int, int]:
        """``(bridged, held)``: runs of no-face frames between two face frames that are interpolated, and those held
        (their neighbouring face frames more than ``max_gap_s`` apart, or at the clip's start or end)."""
        runs = _no_face_runs(self.has_face)
        bridged = sum(0 < a and b < len(self) and self.time[b] - self.time[a - 1] <= max_gap_s for a, b in runs)
        return int(bridged), len(runs) - int(bridged)


def _no_face_runs(has_face: np.ndarray) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` row ranges of consecutive frames without a face."""
    edges = np.diff(np.r_[0, (~has_face).astype(np.int8), 0])
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(), strict=True))


# ------------------------------------------------------------------------------------------------------------ reading


def read_clip(
    path: str | Path,
    *,
    video: str | None = None,
    fps: float | None = None,
    face_selection: str = "largest",
    mesh_npy: str = "{stem}.npy",
    mesh_units: str | None = "detector",
    family: str = "au",
) -> Clip:
    """One video of a py-feat table as a :class:`Clip` (module docstring: time, faces, gaps).

    Parameters
    ----------
    path : py-feat's CSV (``detect(..., save=)``), ``.csv.gz``, or a Fex saved as parquet (either detector; a
        parquet without mesh columns with an ``[N, 478, 3]`` ``<stem>.npy`` beside it is the split layout). A table
        without a mesh is read too (``Clip.mesh`` None).
    video : the video to read: py-feat's ``input`` path as written, or its stem (``clip01`` for
        ``videos/clip01.mp4``) when no other video of the table has that stem; needed when the table holds several.
    fps : the video's frame rate (default: from ``approx_time`` where it allows one, else 25).
    face_selection : ``largest`` (the largest face box of a frame), ``identity`` (py-feat's ``Identity`` seen in
        most of the video's face rows) or ``error``, as the pipeline's ``data.face_selection``.
    mesh_units : ``detector`` (z converted by the detector the columns name) or ``pixels`` (z as written), as the
        ingest's ``data.mesh_units``; None: the recorded mesh is not needed (``aumesh animate``): ``Clip.mesh`` None,
        nothing converted, so nothing about it can refuse the table.
    family : ``au`` (default), or ``blendshapes`` / ``emotions``: also read that family's columns by name
        (``Clip.inputs``; ``aumesh animate --family``).

    Raises
    ------
    MissingFileError
        No such file.
    TableError
        Not a table, a required column missing (frame, the 20 AUs, Pitch, Yaw, Roll, input), several videos and no
        ``video``, an unknown ``video`` or the stem of several, no frame with a face, a face row with some AU or pose values missing; the
        ingest's unit errors (a detector's z without FaceRectWidth to convert it, pixels and normalized units mixed).
    UserError
        ``fps`` not a positive number, unknown ``face_selection`` or ``mesh_units``.
    """
    _check_options(fps, face_selection, mesh_units)  # before the table is read
    table = read_table(path, mesh_npy=mesh_npy)
    where = str(table.path)
    ids = table.videos
    if video is None and len(ids) > 1:
        names = sorted(table.names.values())
        shown = ", ".join(names[:10]) + (f" and {len(names) - 10} more" if len(names) > 10 else "")
        raise TableError(f"{where}: holds {len(ids)} videos ({shown}). Fix: pick one with --video NAME.")
    return table.clip(
        video if video is not None else ids[0],
        fps=fps,
        face_selection=face_selection,
        mesh_units=mesh_units,
        family=family,
    )


@dataclass(frozen=True)
class ClipTable:
    """A py-feat table read once (:func:`read_table`), to cut into one :class:`Clip` per video."""

    path: Path
    source: readers.Source
    has_mesh: bool
    block: readers.Block  # every row, in the table's order
    approx: np.ndarray | None  # approx_time of every row, None when the table has none

    @property
    def videos(self) -> list[str]:
        """The videos the table holds (their ids: py-feat's ``input`` paths as written, or ``video_id``), sorted."""
        return sorted(set(self.block.video.tolist()))

    @property
    def names(self) -> dict[str, str]:
        """Each video id -> the name it is shown by: py-feat's ``input`` path by its stem where unique
        (:func:`aumesh.data.pyfeat.video_names`); a ``video_id`` as it is."""
        if self.source.layout.video != INPUT_PATH_COLUMN:
            return {v: v for v in self.videos}
        return pyfeat.video_names(self.videos)

    def clip(
        self,
        name: str,
        *,
        fps: float | None = None,
        face_selection: str = "largest",
        mesh_units: str | None = "detector",
        family: str = "au",
    ) -> Clip:
        """Video ``name`` (one of :attr:`videos`, or its stem where unique) as a :class:`Clip`: :func:`read_clip`
        without reading again.

        Raises
        ------
        TableError
            No such video, or ``name`` is the stem of several (listed); the video has no frame with a face, or a face row with some AU or pose values missing, or a unit error
            (:func:`read_clip`).
        """
        return _video_clip(self, name, fps, face_selection, mesh_units, family)


def read_table(path: str | Path, *, mesh_npy: str = "{stem}.npy") -> ClipTable:
    """Every row of a py-feat table, read once (:func:`read_clip`'s formats and checks of the file).

    Raises
    ------
    MissingFileError, TableError
        As :func:`read_clip`.
    """
    path = Path(path)
    if not path.is_file():
        raise MissingFileError(
            f"{path}: no such file. Fix: give the py-feat table (CSV, .csv.gz or parquet) that "
            f"detect(..., save=) or Fex.to_parquet wrote."
        )
    if not readers.is_table(path):
        raise TableError(f"{path}: not a py-feat table. Fix: give a .csv, .csv.gz or .parquet file.")
    source, has_mesh = _open(path, mesh_npy)
    block, approx = _read(source, has_mesh)
    if not len(block):
        raise TableError(f"{path}: no rows. Fix: export the video's frames with py-feat first.")
    return ClipTable(path, source, has_mesh, block, approx)


def _check_options(fps: float | None, face_selection: str, mesh_units: str | None = "detector") -> None:
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise UserError(f"--fps {fps}: the frame rate must be a positive number of frames per second, e.g. 25.")
    if face_selection not in FACE_SELECTIONS:
        raise UserError(f"face_selection={face_selection!r}: use one of {', '.join(FACE_SELECTIONS)}.")
    if mesh_units is not None and mesh_units not in MESH_UNITS:
        raise UserError(f"--mesh-units {mesh_units}: use one of {', '.join(MESH_UNITS)}.")


def to_frame_pixels(faces: readers.Block, layout: pyfeat.Layout, mesh_units: str, where: str) -> str:
    """The face rows' meshes ``faces.mesh`` (m, 1434) axis-major to frame pixels in place, by the ingest's
    :func:`~aumesh.data.units.convert_units` (the same rows give the ingest's cleaned meshes, bit for bit); returns
    what was done, a key of :data:`MESH_UNIT_NOTES`.

    A mesh in normalized units without FrameWidth/FrameHeight columns is left as written (``"normalized-raw"``).

    Raises
    ------
    TableError
        The ingest's: pixels and normalized rows mixed, a detector's z without a FaceRectWidth (> 0) to convert it,
        normalized rows without a frame size; the fix named for ``aumesh view``'s ``--mesh-units``.
    """
    if not len(faces):
        return "none"
    normalized = normalized_rows(faces.mesh, rect_side(faces, layout))
    if normalized.all() and layout.frame_size is None:
        return "normalized-raw"
    try:
        stats = convert_units(faces, layout, mesh_units, where)
    except TableError as err:  # the ingest names its config key; here the same choice is a command-line option
        raise TableError(str(err).replace("data.mesh_units=pixels", "--mesh-units pixels")) from None
    if stats.z in ("chip", "crop256", "normalized"):
        return stats.z
    return "pixels-asked" if layout.detector in Z_CROP else "pixels"


def _video_clip(
    table: ClipTable,
    name: str,
    fps: float | None,
    face_selection: str,
    mesh_units: str | None = "detector",
    family: str = "au",
) -> Clip:
    _check_options(fps, face_selection, mesh_units)
    block, approx, source, has_mesh, where = table.block, table.approx, table.source, table.has_mesh, str(table.path)
    video = pyfeat.resolve_video(name, table.videos, where, paths=source.layout.video == INPUT_PATH_COLUMN)
    name = table.names[video]  # shown by its stem where unique
    rows = np.flatnonzero(block.video == video)
    rows = rows[np.argsort(block.frame[rows], kind="stable")]  # select_faces needs a frame's rows consecutive
    block, approx = block.take(rows), None if approx is None else approx[rows]

    lay = source.layout
    empty = ingest.no_face_rows(block, lay)
    faces = block.take(np.flatnonzero(~empty))
    subjects = ingest.main_identities(ingest.identity_counts(block, lay)) if face_selection == "identity" else None
    with warnings.catch_warnings():  # a table without face boxes nor mesh: areas are NaN (the first face is kept)
        warnings.simplefilter("ignore", RuntimeWarning)
        keep, counts = ingest.select_faces(faces, lay, face_selection, subjects, where)
    chosen = faces.take(keep)
    if not len(chosen):
        raise TableError(
            f"{where}: video {name!r} has no frame with a face ({len(block)} rows, all without a face). "
            f"Fix: pick another video (--video) or check py-feat's face detection on it."
        )
    aus = np.column_stack([chosen.values[c] for c in AU_COLUMNS])
    pose = np.column_stack([chosen.values[c] for c in POSE_COLUMNS])
    family_inputs = _family_inputs(table, chosen, family, name, where)
    bad = np.isnan(np.hstack([aus, pose]))
    if bad.any():
        row, col = (int(v[0]) for v in np.nonzero(bad))
        column = (*AU_COLUMNS, *POSE_COLUMNS)[col]
        raise TableError(
            f"{where}: column {column!r} is empty in frame {chosen.frame[row]} of video {name!r}, a row with a "
            f"face. Fix: a face row needs all 20 AUs and Pitch, Yaw, Roll (py-feat writes them; a frame without "
            f"a face has every one empty)."
        )

    frames = np.unique(block.frame).astype(np.int64)
    at = np.searchsorted(frames, chosen.frame)
    n = len(frames)
    has_face = np.zeros(n, bool)
    has_face[at] = True
    out_aus = np.full((n, len(AU_COLUMNS)), np.nan)
    out_pose = np.full((n, len(POSE_COLUMNS)), np.nan)
    out_aus[at], out_pose[at] = aus, pose
    out_inputs = None
    if family_inputs is not None:
        out_inputs = np.full((n, family_inputs.shape[1]), np.nan)
        out_inputs[at] = family_inputs
    mesh, units = None, "none"
    if has_mesh and mesh_units is not None:
        units = to_frame_pixels(chosen, lay, mesh_units, where)  # chosen is a copy (take): the table is untouched
        mesh = np.full((n, N_VERTICES, 3), np.nan)
        mesh[at] = chosen.mesh.reshape(len(chosen), 3, N_VERTICES).transpose(0, 2, 1)

    if fps is not None:
        rate, how = float(fps), "--fps"
    else:
        inferred = None if approx is None else fps_from_approx_time(block.frame, approx)
        rate, how = (inferred, APPROX_TIME) if inferred is not None else (DEFAULT_FPS, f"default ({DEFAULT_FPS:g})")
    return Clip(
        source=table.path.name,
        video=name,
        frame=frames,
        time=frames / rate,
        fps=rate,
        fps_source=how,
        has_face=has_face,
        aus=out_aus,
        pose=out_pose,
        mesh=mesh,
        detector=lay.detector if has_mesh else "none",
        frames_several_faces=counts.frames_several_faces,
        frame_size=_frame_size(block, lay),
        mesh_units=units,
        video_id=video,
        family=family,
        inputs=out_inputs,
    )


def _family_inputs(table: ClipTable, chosen: readers.Block, family: str, name: str, where: str) -> np.ndarray | None:
    """(m, k) ``family``'s inputs of the chosen face rows, read by name with the layout's families
    (:attr:`aumesh.data.pyfeat.Layout.families`: Detectorv2's ``Happy`` is ``happiness``); None for the AUs. A table
    without the family, or a face row missing one of its values, is one line naming the column and the fix."""
    if family == "au":
        return None
    from aumesh.core.families import check_family, family_columns

    held = dict(table.source.layout.families)
    if family not in held:  # not in the header: family_columns names the first missing input and the fix
        family_columns(table.source.header, family, where)
        raise TableError(f"{where}: no {family} columns. Fix: export the table with py-feat's MPDetector or Detectorv2")
    values = np.column_stack([chosen.values[c] for c in held[family]])
    bad = np.isnan(values)
    if bad.any():
        row, col = (int(v[0]) for v in np.nonzero(bad))
        raise TableError(
            f"{where}: column {held[family][col]!r} is empty in frame {chosen.frame[row]} of video {name!r}, a row "
            f"with a face. Fix: a face row needs all {len(check_family(family))} {family} columns (py-feat writes "
            f"them on every face row)."
        )
    return values


def _frame_size(block: readers.Block, layout: pyfeat.Layout) -> tuple[float, float] | None:
    """The first finite, positive ``FrameWidth, FrameHeight`` of the rows, None when the table has none."""
    if layout.frame_size is None:
        return None
    width, height = (block.values[c] for c in layout.frame_size)
    ok = np.flatnonzero(np.isfinite(width) & np.isfinite(height) & (width > 0) & (height > 0))
    return (float(width[ok[0]]), float(height[ok[0]])) if len(ok) else None


def _names(path: Path) -> tuple[str, list[str], int | None]:
    """``(kind, column names, rows)`` of a table (rows: parquet only)."""
    if path.name.endswith(readers.CSV_SUFFIXES):
        return "csv", readers.csv_header(path), None
    try:
        md = pq.read_metadata(path)
    except Exception as err:  # pyarrow raises several types for a bad file
        raise corrupt_parquet(path, err) from None
    return "parquet", md.schema.to_arrow_schema().names, md.num_rows


def _open(path: Path, mesh_npy: str) -> tuple[readers.Source, bool]:
    """The table as the ingest's :class:`~aumesh.data.readers.Source`, and whether it has a mesh. A table without one
    (no 478-vertex columns, no ``.npy`` beside it) is the split layout without its ``.npy``: AUs and pose only."""
    kind, names, n_rows = _names(path)
    present = set(names)
    npy = path.with_name(mesh_npy.format(stem=path.stem))
    if (
        set(pyfeat.MESH_NAMES["Detectorv2"]) <= present
        or "z_0" in present  # MPDetector's mesh (the 68-point block has no z): the ingest checks its 478 vertices
        or (kind == "parquet" and npy.exists())
    ):
        return readers.open_source(path, mesh_npy), True
    lay = pyfeat.layout(names, str(path), split_mesh=True)
    return readers.Source(path, kind, lay, tuple(names), None, n_rows), False


def _read(source: readers.Source, has_mesh: bool) -> tuple[readers.Block, np.ndarray | None]:
    """Every row of the table as one :class:`~aumesh.data.readers.Block`, and its ``approx_time`` values (None when
    absent). A table without a mesh gets NaN mesh columns (what the ingest's no-face and face-size rules read)."""
    lay = source.layout
    columns = list(lay.columns) + ([APPROX_TIME] if APPROX_TIME in source.header else [])
    spans = readers.csv_spans(source) if source.kind == "csv" else [readers.Span(source, 0, source.n_rows or 0)]
    parts = [part for span in spans for part in readers.iter_span_tables(span, columns)]
    blocks, approx = [], []
    for span, table in parts:
        if not has_mesh:
            names = pyfeat.MESH_NAMES["MPDetector"]
            nan = pa.array(np.full(table.num_rows, np.nan, np.float32))
            table = pa.Table.from_arrays([*table.columns, *([nan] * len(names))], [*table.column_names, *names])
            span = replace(span, source=replace(source, layout=replace(lay, mesh=tuple(names))))
        blocks.append(readers.to_block(table, span))
        if APPROX_TIME in table.column_names:
            approx.append(table.column(APPROX_TIME).to_numpy(zero_copy_only=False))
    block = _concat(blocks)
    return block, (np.concatenate(approx) if approx else None)


def _concat(blocks: Sequence[readers.Block]) -> readers.Block:
    if len(blocks) == 1:
        return blocks[0]
    if not blocks:
        return readers.Block(
            np.zeros(0, str), np.zeros(0, np.int64), {}, None, np.zeros((0, 3 * N_VERTICES), np.float32)
        )
    first = blocks[0]
    return readers.Block(
        np.concatenate([b.video for b in blocks]),
        np.concatenate([b.frame for b in blocks]),
        {k: np.concatenate([b.values[k] for b in blocks]) for k in first.values},
        None if first.identity is None else np.concatenate([b.identity for b in blocks]),
        np.concatenate([b.mesh for b in blocks]),
    )


# -------------------------------------------------------------------------------------------------------------- gaps


def bridge(values: np.ndarray, has_face: np.ndarray, time: np.ndarray, max_gap_s: float = MAX_GAP_S) -> np.ndarray:
    """``values`` (n, k) with the no-face rows filled (module docstring, "Gaps").

    A no-face row between face rows ``p`` and ``q`` (the nearest before and after) gets
    ``v[p] + (t - t[p]) / (t[q] - t[p]) * (v[q] - v[p])`` when ``t[q] - t[p] <= max_gap_s``, else ``v[p]`` (held).
    Rows before the first face row hold its values, rows after the last hold the last's.
    """
    values = np.asarray(values, np.float64)
    face = np.flatnonzero(has_face)
    if not len(face):
        raise ValueError("no frame with a face: nothing to bridge from")
    out = values.copy()
    rows = np.flatnonzero(~np.asarray(has_face, bool))
    if not len(rows):
        return out
    k = np.searchsorted(face, rows)
    p = face[np.maximum(k - 1, 0)]
    q = face[np.minimum(k, len(face) - 1)]
    start, end = k == 0, k == len(face)
    out[rows] = values[p]
    out[rows[start]] = values[face[0]]
    inside = ~start & ~end
    span = time[q] - time[p]
    short = inside & (span <= max_gap_s)
    a = ((time[rows] - time[p]) / np.where(span > 0, span, 1.0))[short, None]
    out[rows[short]] = (1 - a) * values[p[short]] + a * values[q[short]]
    return out


def bridged_weights(clip: Clip, max_gap_s: float = MAX_GAP_S) -> np.ndarray:
    """(n_frames, k) what drives the clip's rig (:attr:`Clip.weights`: its 20 AU intensities, or its family's k
    inputs) with its no-face frames bridged (:func:`bridge`): the morph-target weights of its animation."""
    return bridge(clip.weights, clip.has_face, clip.time, max_gap_s)


def bridged_pose(clip: Clip, max_gap_s: float = MAX_GAP_S) -> np.ndarray:
    """(n_frames, 3) Pitch, Yaw, Roll (radians) with the no-face frames bridged as the weights are."""
    return bridge(clip.pose, clip.has_face, clip.time, max_gap_s)


def smooth(values: np.ndarray, n: int) -> np.ndarray:
    """Centred moving average over ``n`` frames (odd; 1 = unchanged) along axis 0, the window shortened at the ends
    (the first frame averages itself and the ``n // 2`` after it). Frames, not seconds: ``skip_frames`` rows count
    as neighbours."""
    if n < 1 or n % 2 == 0:
        raise UserError(f"--smooth {n}: use an odd number of frames >= 1 (e.g. 3 or 5; 1 = no smoothing).")
    values = np.asarray(values, np.float64)
    if n == 1 or len(values) < 2:
        return values.copy()
    half = n // 2
    c = np.concatenate([np.zeros((1,) + values.shape[1:]), np.cumsum(values, axis=0)])
    i = np.arange(len(values))
    a, b = np.maximum(i - half, 0), np.minimum(i + half + 1, len(values))
    shape = (-1,) + (1,) * (values.ndim - 1)
    return (c[b] - c[a]) / (b - a).reshape(shape)


__all__ = [
    "APPROX_TIME",
    "Clip",
    "DEFAULT_FPS",
    "MAX_GAP_S",
    "MESH_UNITS",
    "MESH_UNIT_NOTES",
    "bridge",
    "bridged_pose",
    "bridged_weights",
    "fps_from_approx_time",
    "read_clip",
    "smooth",
]
