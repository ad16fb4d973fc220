"""py-feat's table layouts, by column name: which columns of a Fex table the pipeline needs, and nothing else.

py-feat 2.1.5 writes one of two layouts (its ``detect(..., save=)`` CSV, or a Fex saved as parquet):

* **MPDetector** (``landmark_model="mp_facemesh_v2"``): the 478-vertex mesh interleaved ``x_0, y_0, z_0 .. z_477``;
* **Detectorv2**: the mesh axis-major ``mesh_x_0 .. mesh_x_477, mesh_y_*, mesh_z_*`` beside a 68-point
  ``x_0..x_67, y_0..y_67`` block (a subset of the mesh, in 2-D: never the mesh);

and the card's training layout, a table without mesh columns plus an ``[N, 478, 3]`` ``.npy`` beside it. Both
detectors also write ``FaceRectX/Y/Width/Height``, ``FaceScore``, the 20 AUs, ``Pitch, Roll, Yaw`` (Fex order),
``FrameWidth``/``FrameHeight``, ``input`` (the video path), ``frame``, ``approx_time`` and ``Identity``; the 52
blendshapes and 7 emotions when the header holds them (:attr:`Layout.families`, mapped by name with
:func:`aumesh.core.families.header_families`: Detectorv2's ``Happy`` is the family's ``happiness``); identity
embeddings, gaze and the rest (about 1,900 columns) are never read.

The detector is named from the columns (:attr:`Layout.detector`): ``mesh_x_*`` is Detectorv2; the interleaved mesh
beside py-feat's ``FaceRectWidth``/``FaceRectHeight`` is MPDetector; the interleaved mesh without them is ``table``
(not a py-feat export: a hand-made or converted table, its mesh taken as pixels); no mesh columns is ``split``. The
detector decides the units of z (:mod:`aumesh.data.units`, docs/conventions.md "py-feat's mesh units").
"""

from __future__ import annotations

import difflib
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass

from aumesh.core.errors import TableError
from aumesh.core.families import FAMILIES, header_families
from aumesh.core.schema import AU_COLUMNS, FRAME_COLUMN, INPUT_PATH_COLUMN, N_VERTICES, POSE_COLUMNS, VIDEO_COLUMN
from aumesh.data import csv_text

FACE_SCORE = "FaceScore"
FACE_BOX_SIZE = ("FaceRectWidth", "FaceRectHeight")
FACE_BOX_ORIGIN = ("FaceRectX", "FaceRectY")
IDENTITY = "Identity"
FRAME_SIZE = ("FrameWidth", "FrameHeight")

#: The detectors' mesh column names, axis-major ``[x_0..x_477 | y_.. | z_..]`` (the model's layout).
MESH_NAMES = {
    "MPDetector": [f"{axis}_{i}" for axis in "xyz" for i in range(N_VERTICES)],
    "Detectorv2": [f"mesh_{axis}_{i}" for axis in "xyz" for i in range(N_VERTICES)],
}
POINT_COLUMN = re.compile(r"^([xyz])_(\d+)$")
#: Every column name the pipeline may read besides the mesh's (:attr:`Layout.columns`, clip's ``approx_time``).
READ_COLUMNS = frozenset(
    {VIDEO_COLUMN, INPUT_PATH_COLUMN, FRAME_COLUMN, *AU_COLUMNS, *POSE_COLUMNS, FACE_SCORE, IDENTITY, "approx_time"}
    | {*FACE_BOX_ORIGIN, *FACE_BOX_SIZE, *FRAME_SIZE}
)
_READ_MESH = re.compile(r"^(mesh_)?[xyz]_\d+$")


def video_stem(path: str) -> str:
    """The file name of py-feat's ``input`` path without the extension, as ``pathlib``'s ``stem``, without a Path:
    pathlib interns every component it parses, and the interpreter's table of interned strings grows with them and
    never shrinks (3.7 MiB held to the end of the prepare stage for 88k videos' paths). A name to *show* a video by
    (:func:`video_names`), never its identity: ``a/clip01.mp4`` and ``b/clip01.mp4`` are two videos."""
    name = os.path.basename(path.rstrip("/"))
    dot = name.rfind(".")
    return name[:dot] if 0 < dot < len(name) - 1 else name


def video_names(videos: Sequence[str]) -> dict[str, str]:
    """Each video id (py-feat's ``input`` path as written, or ``video_id``) -> the name to show it by: its stem
    (:func:`video_stem`) where no other of ``videos`` has that stem, else its shortest trailing part of the path that
    no other has, the last part's extension dropped (``a/clip01``, ``b/clip01``), else the id itself."""
    ids = sorted(set(videos))
    parts = {v: v.rstrip("/").split("/") for v in ids}
    out: dict[str, str] = {}
    for k in range(1, max((len(p) for p in parts.values()), default=0) + 1):
        trail = {v: "/".join([*p[-k:-1], video_stem(p[-1])]) for v, p in parts.items() if v not in out}
        seen: dict[str, int] = {}
        for name in trail.values():
            seen[name] = seen.get(name, 0) + 1
        out |= {v: name for v, name in trail.items() if seen[name] == 1}
    shown = set()
    for v in ids:  # a name that is another video's id (or repeats): the id itself
        name = out.get(v, v)
        out[v] = v if (name != v and name in parts) or name in shown else name
        shown.add(out[v])
    return out


def resolve_video(name: str, videos: Sequence[str], where: str, paths: bool = True) -> str:
    """The video of ``videos`` (ids) that ``name`` means: its id, else its shown name or stem (:func:`video_names`)
    when that names one video only (``paths`` False: the ids are ``video_id`` values, not paths; only an id).

    Raises
    ------
    TableError
        One line naming ``where``: no such video (the videos it holds), or ``name`` is the stem of several (listed).
    """
    if name in videos:
        return name
    names = video_names(videos) if paths else {v: v for v in videos}
    hits = sorted({v for v in videos if names[v] == name or (paths and video_stem(v) == name)})
    if len(hits) == 1:
        return hits[0]
    if hits:
        shown = ", ".join(hits[:10]) + (f" and {len(hits) - 10} more" if len(hits) > 10 else "")
        raise TableError(
            f"{where}: {len(hits)} videos are named {name!r} ({shown}). Fix: --video with the path py-feat wrote in "
            f"'input' (or {names[hits[0]]!r})."
        )
    held = sorted(names.values())
    listed = ", ".join(held[:10]) + (f" and {len(held) - 10} more" if len(held) > 10 else "")
    raise TableError(f"{where}: no video {name!r} (the table holds {listed}). Fix: --video one of those.")


@dataclass(frozen=True)
class Layout:
    """Where a table keeps what the pipeline needs.

    ``mesh`` is None in the split layout (the mesh is an ``.npy`` beside the table). ``video`` is ``video_id`` or
    py-feat's ``input`` (the video's path as written: the video's identity; its stem only shows it,
    :func:`video_names`). The optional columns are None when absent.
    """

    detector: str  # MPDetector | Detectorv2 | table | split
    video: str
    mesh: tuple[str, ...] | None
    face_score: str | None
    box_size: tuple[str, str] | None
    identity: str | None
    frame_size: tuple[str, str] | None
    instruments: tuple[str, ...] = ()  # a second detector's AU columns (model.eiv.instrument_aus), AU_COLUMNS order
    box_origin: tuple[str, str] | None = None  # FaceRectX, FaceRectY: with box_size, where a face is (its track)
    # the carried families the header holds whole (issue 46): (family, its header columns in the family's order)
    families: tuple[tuple[str, tuple[str, ...]], ...] = ()

    @property
    def family_names(self) -> tuple[str, ...]:
        """The families of :attr:`families`, in order."""
        return tuple(family for family, _ in self.families)

    def family_renames(self, families: Sequence[str]) -> list[tuple[str, str]]:
        """``(family name, header column)`` of each input of ``families`` (each one of :attr:`families`), in order:
        what an ingested table's column of that name holds."""
        held = dict(self.families)
        return [(name, col) for f in families for name, col in zip(FAMILIES[f], held[f], strict=True)]

    @property
    def numeric(self) -> list[str]:
        """The numeric columns read besides the video and frame (AUs, pose, instrument AUs, the families' columns as
        the header names them, face score and box, frame size)."""
        out = [*AU_COLUMNS, *POSE_COLUMNS, *self.instruments, *(c for _, cols in self.families for c in cols)]
        out += [self.face_score] if self.face_score else []
        out += list(self.box_size or ()) + list(self.frame_size or ()) + list(self.box_origin or ())
        return out

    @property
    def columns(self) -> list[str]:
        """Every column the pipeline reads of the table (mesh last, axis-major)."""
        out = [self.video, FRAME_COLUMN, *self.numeric]
        out += [self.identity] if self.identity else []
        return out + list(self.mesh or ())


def suggest(name: str, names: Sequence[str]) -> str:
    """A likely misspelling of column ``name`` among ``names`` (case first, then similar spelling), as the
    `` (found 'x': rename it to 'name')`` an error appends; "" when none. The required Fex columns are never offered
    for one another (a missing AU14 is not "AU12 misspelled")."""
    required = {VIDEO_COLUMN, FRAME_COLUMN, *AU_COLUMNS, *POSE_COLUMNS}
    loose = [c for c in names if c not in required]
    close = [c for c in loose if c.lower() == name.lower()] or difflib.get_close_matches(name, loose, n=1, cutoff=0.6)
    return f" (found {close[0]!r}: rename it to {name!r})" if close else ""


def check_unique_names(names: Sequence[str], where: str, also: Sequence[str] = ()) -> None:
    """No column the pipeline reads (:data:`READ_COLUMNS`, the mesh's, ``also``: e.g. the instrument AUs) named twice.

    A CSV header may repeat a name (``AU12`` twice), and so may a parquet schema (pyarrow writes duplicate field
    names): Arrow and pandas then read one of them (the first, or a renamed ``AU12.1``) without a word. Names nothing
    reads (py-feat's ~2,000 other columns) may repeat.

    Raises
    ------
    TableError
        One line naming ``where``, the repeated column(s) and the fix.
    """
    seen: dict[str, int] = {}
    for name in names:
        seen[name] = seen.get(name, 0) + 1
    read = set(also)
    repeated = [n for n, k in seen.items() if k > 1 and (n in READ_COLUMNS or n in read or _READ_MESH.match(n))]
    if repeated:
        shown = ", ".join(f"{n!r} ({seen[n]} times)" for n in repeated[:5])
        more = f" and {len(repeated) - 5} more" if len(repeated) > 5 else ""
        raise TableError(
            f"{where}: duplicated column name{'s' if len(repeated) > 1 else ''} {shown}{more} in the header: "
            f"which one is the measurement is unknown. Fix: keep one column of each name (delete or rename the "
            f"others) and save the table again."
        )


def fex_video_column(names: Sequence[str], where: str) -> str:
    """The column naming each row's video (``video_id``, else py-feat's ``input`` path), after checking that the Fex
    columns every table needs (frame, the 20 AUs, the 3 pose angles) are there, each once
    (:func:`check_unique_names`).

    Raises
    ------
    TableError
        Naming ``where``, the missing or repeated column, a likely misspelling and the fix.
    """
    check_unique_names(names, where)
    present = set(names)
    if VIDEO_COLUMN in present:
        video = VIDEO_COLUMN
    elif INPUT_PATH_COLUMN in present:
        video = INPUT_PATH_COLUMN
    else:
        raise TableError(
            f"{where}: column {VIDEO_COLUMN!r} is missing{suggest(VIDEO_COLUMN, names)}. Fix: keep "
            f"py-feat's {INPUT_PATH_COLUMN!r} column (the video path names the video), or add {VIDEO_COLUMN!r}."
        )
    for col in (FRAME_COLUMN, *AU_COLUMNS, *POSE_COLUMNS):
        if col not in present:
            raise TableError(
                f"{where}: column {col!r} is missing{suggest(col, names)}. Fix: the table needs py-feat's Fex columns "
                f"{FRAME_COLUMN}, {', '.join(AU_COLUMNS)}, {', '.join(POSE_COLUMNS)} (pose in radians)."
            )
    return video


def check_instruments(names: Sequence[str], instruments: Sequence[str], where: str) -> None:
    """Every instrument column (``model.eiv.instrument_aus``, :func:`aumesh.core.schema.instrument_columns`) is in
    the table.

    Raises
    ------
    TableError
        Naming ``where``, the first missing column (with a likely misspelling) and the fix.
    """
    check_unique_names(names, where, instruments)
    present = set(names)
    missing = [c for c in instruments if c not in present]
    if missing:
        more = f" ({len(missing) - 1} more instrument columns missing)" if len(missing) > 1 else ""
        raise TableError(
            f"{where}: column {missing[0]!r} is missing{suggest(missing[0], names)}{more}. Fix: model/eiv=instruments "
            f"needs the second detector's AUs on the same frames in every table, named by model.eiv.instrument_aus "
            f"(e.g. '{{au}}_2' for AU01_2 .. AU28_2); add them, correct the pattern, or use model/eiv=none."
        )


def layout(names: Sequence[str], where: str, split_mesh: bool = False, instruments: Sequence[str] = ()) -> Layout:
    """The layout of a table with columns ``names`` (``where`` names the file in errors).

    Parameters
    ----------
    names : the table's column names, in any order.
    split_mesh : an ``.npy`` mesh lies beside the table (the split layout): the table needs no mesh columns.
    instruments : a second detector's AU columns the table must hold (``model.eiv.instrument_aus``; default none).

    Raises
    ------
    TableError
        A required column is missing (with the closest name the table has), the 68-point landmark block is the
        only mesh, or a mesh has the wrong vertex count.
    """
    present = set(names)
    csv_text.check_names(names, where)  # a CSV header misread (a byte-order mark, ';' separators) named as such
    video = fex_video_column(names, where)
    check_instruments(names, instruments, where)
    held = header_families(names, where)  # by name; a family half present is refused here, one absent left out
    check_unique_names(names, where, [c for cols in held.values() for c in cols.values()])
    mesh, detector = None, "split"
    if set(MESH_NAMES["Detectorv2"]) <= present:
        mesh, detector = MESH_NAMES["Detectorv2"], "Detectorv2"
    elif not split_mesh:
        # py-feat's MPDetector always writes its crop box beside the interleaved mesh (MPDetector.forward's
        # feat_faceboxes): without FaceRect the table is not its export, and nothing says z is in its crop's units
        mesh = mesh_point_columns(names, where)
        detector = "MPDetector" if set(FACE_BOX_SIZE) <= present else "table"

    def optional(*cols: str):
        return cols if all(c in present for c in cols) else None

    return Layout(
        detector=detector,
        video=video,
        mesh=None if mesh is None else tuple(mesh),
        face_score=FACE_SCORE if FACE_SCORE in present else None,
        box_size=optional(*FACE_BOX_SIZE),
        identity=IDENTITY if IDENTITY in present else None,
        frame_size=optional(*FRAME_SIZE),
        instruments=tuple(instruments),
        box_origin=optional(*FACE_BOX_ORIGIN) if set(FACE_BOX_SIZE) <= present else None,
        families=tuple((f, tuple(cols.values())) for f, cols in held.items()),
    )


def mesh_point_columns(names: Sequence[str], where: str) -> list[str]:
    """MPDetector's ``x_i, y_i, z_i`` (any order), checked: 478 vertices on every axis; the 68-point block is named."""
    vertices: dict[str, set[int]] = {"x": set(), "y": set(), "z": set()}
    for name in names:
        m = POINT_COLUMN.match(name)
        if m:
            vertices[m.group(1)].add(int(m.group(2)))
    if not any(vertices.values()):
        raise TableError(
            f"{where}: no mesh columns (MPDetector's x_0..z_477 or Detectorv2's mesh_x_0..mesh_z_477) and no mesh .npy "
            f"beside it. Fix: export with py-feat's MPDetector (landmark_model='mp_facemesh_v2') or Detectorv2, or save "
            f"the [N, 478, 3] landmarks as an .npy named by data.mesh_npy."
        )
    if not vertices["z"] and len(vertices["x"]) == 68:
        raise TableError(
            f"{where}: the only landmarks are a 68-point 2-D block (x_0..x_67, y_0..y_67), not the 478-vertex mesh. "
            f"Fix: keep Detectorv2's mesh_x_*/mesh_y_*/mesh_z_* columns, or detect with MPDetector "
            f"(landmark_model='mp_facemesh_v2')."
        )
    expected = set(range(N_VERTICES))
    for axis, found in vertices.items():
        if found != expected:
            missing, extra = sorted(expected - found), sorted(found - expected)
            detail = (
                [f"missing {axis}_{missing[0]}" + (f" and {len(missing) - 1} more" if len(missing) > 1 else "")]
                if missing
                else []
            )
            detail += (
                [f"unexpected {axis}_{extra[0]}" + (f" and {len(extra) - 1} more" if len(extra) > 1 else "")]
                if extra
                else []
            )
            raise TableError(
                f"{where}: wrong vertex count in column {axis}_i: found {len(found)} vertices, need {N_VERTICES} "
                f"({'; '.join(detail)}). Fix: export the 478-vertex MediaPipe FaceMesh (with irises, py-feat's "
                f"mp_facemesh_v2), columns x_0..x_477, y_0..y_477, z_0..z_477."
            )
    return MESH_NAMES["MPDetector"]
