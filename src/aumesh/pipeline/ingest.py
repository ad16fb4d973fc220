"""Stage ``ingest``: whatever ``data/`` holds -> the frame tables ``prepare`` reads (``paths.ingested_dir``).

py-feat's CSVs (either detector), a Fex saved as parquet and the card's split layout are all accepted as py-feat
writes them (:mod:`aumesh.data.ingest`: no-face rows dropped, one face per frame, frame pixels on every axis: z
converted from the detector's crop units by ``data.mesh_units``). Each source's faces must then have a face's
proportions (:func:`check_units`). The stage writes:

* ``tables/NNNNNN.parquet``: the cleaned rows of the sources that need it (every CSV; parquet with no-face rows,
  several faces in a frame, Detectorv2's columns or normalized units), only the contract's columns: video_id, frame,
  20 AUs, Pitch, Yaw, Roll, the mesh axis-major in float32; about a CSV range or ``PARQUET_RANGE_ROWS`` rows per task,
  packed to at least :data:`TASK_ROWS` rows a file;
* ``manifest.json``: ``families``: the families (52 blendshapes, 7 emotions) the tables carry under the family's
  names and those held by some sources only, with why (:func:`carried_families`, docs/families.md); the tables
  ``prepare`` reads, in order: those files, and clean parquet tables of ``data/`` in
  place (read as they are: a clean parquet costs only this stage's check, a few columns, not a copy); per source, what
  it held, what was dropped and its ``mesh_units`` (what was converted, how, for how many rows); the totals
  (``rows_z_from_chip``, ``rows_z_from_crop256``, ``identity_labels``, ``frames_ambiguous_faces``: frames with two
  faces of about the same size, :mod:`aumesh.data.face_track`) and ``detectors`` (sources per detector).

Each video (py-feat's ``input`` path as written, or ``video_id``) must have each frame once across ``data/``
(:func:`check_frames_once`); a range of a CSV cut inside a run of frames with several faces starts from the face track
of the range before (:func:`aumesh.data.ingest.carried_tracks`).

Cached by DVC: a change of recipe (``preprocess.*``, ``model.*``) reruns ``prepare`` on these files and never
re-parses a CSV. CSV ranges are parsed on the compute engine, several at once. py-feat's one CSV per video costs what
the same rows in one CSV do: the files share one header and :class:`~aumesh.data.pyfeat.Layout`, their small ranges
are parsed together (:func:`aumesh.data.readers.iter_span_groups`) and written as one row group
(:func:`aumesh.data.ingest.write_clean`); each source keeps only its units and manifest entry (a few KB).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from aumesh.config import Config
from aumesh.core import storage
from aumesh.core.errors import TableError
from aumesh.core.families import CARRIED_FAMILIES
from aumesh.core.io import absolute, atomic_directory, atomic_write_json, recorded
from aumesh.core.schema import FRAME_COLUMN, instrument_columns
from aumesh.data import ingest, passthrough, readers, units, video_frames
from aumesh.pipeline import compute

log = logging.getLogger(__name__)

MANIFEST_FILE = "manifest.json"
TABLES_DIR = "tables"
#: CSV ranges or parquet spans packed into one task and one output file, up to about this many rows (a file per
#: task: per-video CSVs become a few large tables, not thousands of small ones whose footers each pass would parse).
TASK_ROWS = 32768
#: Bytes of py-feat CSV per row (2,045 columns of ~10 characters), to pack CSV ranges by rows before they are read.
CSV_BYTES_PER_ROW = 20_000


def find_sources(
    data_dir: str | Path | storage.ObjectPath, pattern: str, mesh_npy_pattern: str, instruments: Sequence[str] = ()
) -> list[readers.Source]:
    """Every table under ``data_dir`` (a folder, or an object store's ``s3://bucket/prefix``:
    :mod:`aumesh.core.storage`) that ``data.tables`` matches (CSV, gzipped CSV, parquet), sorted by path; each must
    hold the ``instruments`` columns (``model.eiv.instrument_aus``), which the ingested tables then carry."""
    data_dir = storage.input_path(data_dir)
    found = storage.list_inputs(data_dir, pattern)
    if found is None and isinstance(data_dir, storage.ObjectPath):
        raise TableError(
            f"{data_dir}: no object under this prefix (paths.data_dir). Fix: upload py-feat's CSVs there "
            f"(`aws s3 sync DIR {data_dir}`), or correct paths.data_dir."
        )
    if found is None:
        raise TableError(
            f"{data_dir}: the data folder does not exist (paths.data_dir). Fix: `dvc pull data.dvc` for the demo tables, "
            f"or copy py-feat's CSVs (detector.detect(video, save=...)) into {data_dir}/ and run `dvc add {data_dir}`."
        )
    paths = [p for p in found if readers.is_table(p)]
    if not paths:
        raise TableError(
            f"{data_dir}/{pattern}: no frame tables found (empty input; CSV, .csv.gz or parquet). Fix: copy py-feat's "
            f"CSVs (detector.detect(video, save=...)) into {data_dir}/ and run `dvc add {data_dir}`, or `dvc pull`."
        )
    layouts: dict = {}  # one header and one Layout per distinct header (py-feat's one CSV per video: one for all)
    return [readers.open_source(p, mesh_npy_pattern, instruments, layouts) for p in paths]


def _span_rows(span: readers.Span) -> int:
    return (
        max(1, (span.stop - span.start) // CSV_BYTES_PER_ROW) if span.source.kind == "csv" else span.stop - span.start
    )


def pack(spans: list[readers.Span], task_rows: int = TASK_ROWS) -> list[tuple[readers.Span, ...]]:
    """Consecutive spans packed into tasks of up to about ``task_rows`` rows (a span is never split)."""
    tasks: list[tuple[readers.Span, ...]] = []
    current: list[readers.Span] = []
    rows = 0
    for span in spans:
        n = _span_rows(span)
        if current and rows + n > task_rows:
            tasks.append(tuple(current))
            current, rows = [], 0
        current.append(span)
        rows += n
    if current:
        tasks.append(tuple(current))
    return tasks


@dataclass(frozen=True)
class Task:
    spans: tuple[readers.Span, ...]
    out: Path


def _clean_task(
    task: Task, how: str, subjects: dict[str, str] | None, mesh_units: str, seeds: ingest.Seeds | None = None
) -> ingest.Counts:
    mine = {k: v for k, v in (seeds or {}).items() if any((str(s.source.path), s.start) == k for s in task.spans)}
    return ingest.write_clean(task.spans, task.out, how, subjects, mesh_units, mine)


def _identity_task(task: Task) -> ingest.Counts:
    return ingest.span_identities(task.spans)


def run(cfg: Config, out_dir: str | Path) -> dict:
    """Ingest ``paths.data_dir`` into ``out_dir`` (replaced atomically). Returns the manifest."""
    data_dir, out_dir = storage.input_path(cfg.paths.data_dir), Path(out_dir)
    # the tasks get absolute paths (a cluster's workers run elsewhere); the manifest records them as given
    instruments = instrument_columns(cfg.model.eiv.instrument_aus)  # () unless model/eiv=instruments
    sources = [s.absolute() for s in find_sources(data_dir, cfg.data.tables, cfg.data.mesh_npy, instruments)]
    how, mesh_units = cfg.data.face_selection, cfg.data.mesh_units
    with atomic_directory(absolute(out_dir)) as tmp, compute.engine(cfg.compute, read=str(sources[0].path), write=tmp):
        # a parquet table on an object store is copied once into the ingested tables (as a CSV's rows are), never
        # read in place: prepare's passes read their tables several times, from local disk
        parquet = [s for s in sources if s.kind == "parquet" and not storage.is_url(s.path)]
        checks = dict(
            zip(
                [s.path for s in parquet],
                compute.map_gather(
                    partial(passthrough.check_clean, mesh_units=mesh_units), parquet, desc="ingest: check parquet"
                ),
                strict=True,
            )
        )
        entries, spans = [], []
        for source in sources:
            check = checks.get(source.path)
            if check is not None and check.clean:
                entries.append(
                    {
                        "source": recorded(str(source.path)),
                        "table": recorded(str(source.path)),
                        "rows": check.rows,
                        "mesh_npy": None if source.mesh_npy is None else recorded(str(source.mesh_npy)),
                        "detector": source.layout.detector,
                        "read": "in place",
                    }
                )
                continue
            reason = (
                check.reason
                if check is not None
                else "CSV"
                if source.kind == "csv"
                else "on object storage: copied once, not read in place"
            )
            entries.append(
                {
                    "source": recorded(str(source.path)),
                    "detector": source.layout.detector,
                    "read": f"cleaned ({reason})",
                }
            )
            # a parquet table is streamed whole by one task (batch by batch: memory flat in its rows)
            spans += (
                readers.csv_spans(source) if source.kind == "csv" else [readers.Span(source, 0, source.n_rows or 0)]
            )
        (tmp / TABLES_DIR).mkdir()
        tasks = [Task(group, tmp / TABLES_DIR / f"{i:06d}.parquet") for i, group in enumerate(pack(spans))]
        subjects = None
        if how == "identity" and tasks:  # the video's subject needs every face row first: a second read of the sources
            seen = compute.map_reduce(_identity_task, ingest.Counts.__add__, tasks, desc="ingest: identities")
            subjects = ingest.main_identities(seen.identities)
        seeds: ingest.Seeds = {}
        chains = ingest.track_chains(spans)  # ranges cut inside a run of frames with several faces (rare)
        if chains:
            tracks = partial(ingest.carried_tracks, how=how, subjects=subjects)
            for found in compute.map_gather(tracks, chains, desc="ingest: face tracks"):
                seeds |= found
        counts = compute.map_gather(
            partial(_clean_task, how=how, subjects=subjects, mesh_units=mesh_units, seeds=seeds),
            tasks,
            desc="ingest: read + clean",
        )
        total = ingest.Counts()
        for task, c in zip(tasks, counts, strict=True):
            total += c
            if not c.rows_out:  # every row a no-face row
                task.out.unlink()
        tables = [e["table"] for e in entries if "table" in e]
        tables += [
            recorded(out_dir / TABLES_DIR / t.out.name) for t, c in zip(tasks, counts, strict=True) if c.rows_out
        ]
        in_place = sum(e["rows"] for e in entries if "table" in e)
        for source in sources:  # the units of the tables read in place, measured by their check
            check = checks.get(source.path)
            if check is not None and check.clean:
                passed = ingest.Counts(
                    units={str(source.path): check.units} if check.units else {},
                    labels={str(source.path): check.labels} if check.labels is not None else {},
                    frame_ranges=check.frame_ranges or {},
                )
                total += passed
        in_place_paths = {s.path for s in sources if (c := checks.get(s.path)) is not None and c.clean}
        check_frames_once(
            total.frame_ranges,
            sources,
            spans,
            in_place_paths,
            partial(ingest.iter_clean_blocks, how=how, subjects=subjects, mesh_units=mesh_units, seeds=seeds),
        )
        total.frame_ranges = {}
        # sources with too few faces to judge alone (py-feat's one CSV per short video): judged together, by kind
        few: dict[tuple[str, str, str], tuple[units.UnitStats, int, list[str]]] = {}
        for source, entry in zip(sources, entries, strict=True):
            stats = total.units.get(str(source.path)) or units.UnitStats(source.layout.detector)
            if stats.rows >= UNIT_CHECK_ROWS:
                check_units(recorded(str(source.path)), source.layout.detector, stats, mesh_units)
            elif stats.rows:
                key = (source.layout.detector, stats.xy, stats.z)
                pooled, n, shown = few.get(key, (units.UnitStats(source.layout.detector), 0, []))
                if len(shown) < 3:
                    shown.append(recorded(str(source.path)))
                few[key] = (pooled + stats, n + 1, shown)
            entry["mesh_units"] = units_record(source, stats, mesh_units)
            before, after, _ = stats.depth_height()
            entry["face_depth_over_height"] = {"as_written": _rounded(before), "ingested": _rounded(after)}
        for (detector, _, _), (pooled, n, shown) in few.items():
            where = (
                shown[0]
                if n == 1
                else (
                    f"{n:,} files of fewer than {UNIT_CHECK_ROWS} face rows each ({', '.join(shown)}"
                    f"{', ...' if n > len(shown) else ''}), judged together"
                )
            )
            check_units(where, detector, pooled, mesh_units)
        families = carried_families(
            [
                (
                    str(recorded(str(s.path))),
                    (total.units.get(str(s.path)) or units.UnitStats(s.layout.detector)).rows,
                    (
                        total.families.get(str(s.path))
                        if checks.get(s.path) is None or not checks[s.path].clean
                        else checks[s.path].families
                    )
                    or {},
                )
                for s in sources
            ]
        )
        for family, why in families["not_carried"].items():
            log.warning("ingest: %s not carried: %s", family, why)
        totals = total.as_dict()
        totals["rows_in"] += in_place
        totals["frames_out"] += in_place
        totals = {"tables_in": len(sources), **totals}
        detectors: dict[str, int] = {}
        for source in sources:
            detectors[source.layout.detector] = detectors.get(source.layout.detector, 0) + 1
        manifest = {
            "tables": tables,
            "families": families,
            "face_selection": how,
            "mesh_units": mesh_units,
            "counts": totals,
            "detectors": detectors,
            "sources": entries[:10000],
        }
        atomic_write_json(tmp / MANIFEST_FILE, manifest)
    log.info("ingest: %s", totals)
    return manifest


def carried_families(held: Sequence[tuple[str, int, dict[str, list]]]) -> dict:
    """Which families the ingested tables carry, from what each source held.

    Parameters
    ----------
    held : per source, ``(name, face rows kept, {family: [rows measured, rows all NaN, where the first NaN row is]})``
        for the families its header holds whole (:attr:`aumesh.data.ingest.Counts.families`,
        :attr:`aumesh.data.passthrough.PassThrough.families`).

    Returns
    -------
    dict
        ``{"carried": [family, ...], "not_carried": {family: why}}``: a family is carried when every source with a
        kept face row measured it in every such row. A family no source holds (or measured) is simply absent; one that
        some sources hold and others lack (or wrote NaN: MPDetector without an emotion model) is not carried, and
        ``not_carried`` names the first source without it. Not refused: the AU model must not depend on an optional
        family, and carrying it for part of the frames would mean filling the others in or fitting the family on
        other frames than the AUs; a fit of that family is refused later, naming the file (docs/families.md).

    Raises
    ------
    TableError
        A source that measured a family in some face rows and wrote it NaN in others: one line naming the file, the
        first NaN row and the fix.
    """
    for name, _, families in held:
        for family, (measured, unmeasured, first) in families.items():
            if measured and unmeasured:
                raise TableError(
                    f"{name}: the {family} columns are NaN in {unmeasured:,} of {measured + unmeasured:,} face rows "
                    f"(first at {first}) and hold values in the others. Fix: drop the frames without {family} from "
                    f"the table before `dvc add data`, or drop every {family} column to train without them."
                )
    with_rows = [(name, families) for name, rows, families in held if rows]
    carried: list[str] = []
    not_carried: dict[str, str] = {}
    for family in CARRIED_FAMILIES:
        measured = [name for name, f in with_rows if f.get(family, [0])[0]]
        if not measured:
            nan = [name for name, f in with_rows if family in f]
            if nan:  # the columns are there, never measured (MPDetector's emotions with emotion_model=None)
                not_carried[family] = (
                    f"{nan[0]} writes the {family} columns NaN in every face row"
                    + (f" (as do {len(nan) - 1:,} more sources)" if len(nan) > 1 else "")
                    + f": not measured. Fix: detect with a {family} model (MPDetector(emotion_model='resmasknet') "
                    f"or Detectorv2)"
                )
            continue
        lacking = [name for name, f in with_rows if not f.get(family, [0])[0]]
        if not lacking:
            carried.append(family)
            continue
        first = lacking[0]
        how = "writes them NaN (not measured)" if family in dict(with_rows)[first] else f"has no {family} columns"
        not_carried[family] = (
            f"{first} {how}"
            + (f" (and {len(lacking) - 1:,} more sources)" if len(lacking) > 1 else "")
            + f", while {len(measured):,} of {len(with_rows):,} sources hold them. Fix: export every video with "
            f"py-feat's MPDetector (emotion_model='resmasknet' for emotions) or Detectorv2, or leave out the tables "
            f"without them"
        )
    return {"carried": carried, "not_carried": not_carried}


def check_frames_once(
    ranges: video_frames.FrameRanges,
    sources: Sequence[readers.Source],
    spans: Sequence[readers.Span],
    in_place: set[storage.InputPath],
    clean: Callable[[list[readers.Span]], Iterator[tuple[readers.Block, ingest.Counts]]],
) -> None:
    """Each video's frames kept once across ``data/`` (:mod:`aumesh.data.video_frames`): the files of the videos whose
    frame ranges overlap are read again (``clean``: :func:`aumesh.data.ingest.iter_clean_blocks` with the run's
    options, or the video and frame columns of a table read in place) and compared frame by frame.

    Raises
    ------
    TableError
        A frame of a video kept twice: the user's files (as given), the video and the frame.
    """
    clash = video_frames.overlapping(ranges)
    if not clash:
        return
    wanted = set(clash)
    by_path = {str(s.path): s for s in sources}
    frames: dict[str, dict[str, list[np.ndarray]]] = {v: {} for v in clash}
    for name in sorted({f for files in clash.values() for f in files}):
        source = by_path[name]
        where = str(recorded(str(source.path)))
        if source.path in in_place:
            batches = readers.parquet_batches(source, [source.layout.video, FRAME_COLUMN])
            blocks = ((b.column(0).to_numpy(zero_copy_only=False), b.column(1).to_numpy()) for b in batches)
        else:
            mine = [s for s in spans if s.source.path == source.path]
            blocks = ((b.video, b.frame) for b, _ in clean(mine))
        for video, frame in blocks:
            video = np.asarray(video, dtype=str)
            for v in wanted.intersection(np.unique(video).tolist()):
                frames[v].setdefault(where, []).append(np.asarray(frame)[video == v])
    for v in sorted(clash):
        err = video_frames.duplicates(v, frames[v])
        if err is not None:
            raise err


#: ``mesh_units.how`` of a source, by its z unit (docs/conventions.md "py-feat's mesh units").
UNITS_HOW = {
    "chip": "x, y in frame pixels as written; z converted from Detectorv2's 0-1 chip units: z × FaceRectWidth "
    "(feat/detector_v2.py _mesh_to_original_frame returns z unchanged; FaceRect is the square chip)",
    "crop256": "x, y in frame pixels as written; z converted from MPDetector's 256-px crop units: z × "
    "FaceRectWidth / 256 (feat/MPDetector.py forward leaves z in the crop's scale; FaceRect is the crop box)",
    "normalized": "converted from normalized image units: x and z × FrameWidth, y × FrameHeight",
}


def _rounded(value: float | None) -> float | None:
    return None if value is None else float(f"{value:.3g}")


def units_record(source: readers.Source, stats: units.UnitStats, mesh_units: str) -> dict:
    """A source's ``mesh_units`` in the manifest: xy, z, rows kept, rows converted and how (one sentence)."""
    why = {
        "split": "the split layout's .npy",
        "table": "an interleaved mesh without py-feat's FaceRect: not a detector export",
    }.get(source.layout.detector, "data.mesh_units=pixels" if mesh_units == "pixels" else "")
    how = UNITS_HOW.get(stats.z) or (
        f"x, y, z in pixels as written ({why})" if stats.rows else "no face rows: nothing measured"
    )
    return {
        "xy": stats.xy or "pixels",
        "z": stats.z or "pixels",
        "rows": stats.rows,
        "rows_converted": stats.rows_converted,
        "how": how,
    }


#: Face rows a source needs for its units to be judged on its own (:func:`check_units`): the median depth/height of
#: one or two faces is a single draw, so the sources with fewer (py-feat's one CSV per short video) are judged together,
#: by detector and units, as one table would be.
UNIT_CHECK_ROWS = 30


def check_units(where: str, det: str, stats: units.UnitStats, mesh_units: str) -> None:
    """The guard on a source's units: one unit for all its rows; a face's proportions after the conversion (the
    median over its faces of depth/height within :data:`aumesh.data.units.DEPTH_HEIGHT_RANGE`); and, for a
    detector's export, z as written growing with the face's size as pixels do, or not, as the units say
    (:func:`aumesh.data.units.growth_slope`, where enough near-frontal faces vary enough in size: what sees an
    MPDetector export taken as pixels, whose depth/height can look like a face's).

    Raises
    ------
    TableError
        One line naming the file, what was measured (the ratio with and without the conversion, or z's growth) and
        the likely fix.
    """
    if stats.xy == "mixed" or stats.z == "mixed":
        raise TableError(
            f"{where}: mixes meshes in pixels and in normalized image units (some rows of the file differ from "
            f"others). Fix: export every video the same way."
        )
    before, after, crop = stats.depth_height()
    lo, hi = units.DEPTH_HEIGHT_RANGE
    if after is not None and not lo <= after <= hi:
        if stats.z in ("chip", "crop256"):
            done = f"after converting z from {det}'s {stats.z} units ({before:.3g} without the conversion)"
            fix = (
                f"if this table's z is already in pixels (rescaled after py-feat), set data.mesh_units=pixels; "
                f"otherwise check that it is {det}'s export as py-feat wrote it (its FaceRect and mesh columns)"
            )
        elif det in units.Z_CROP and mesh_units == "pixels":
            with_crop = "" if crop is None else f"; {crop:.3g} with z converted from {det}'s crop units"
            done = f"with z taken as pixels (data.mesh_units=pixels{with_crop})"
            fix = f"this is {det}'s export with z in its own units as py-feat writes them: set data.mesh_units=detector"
        else:
            done = "with z as written" + (" (normalized units converted)" if stats.z == "normalized" else " (pixels)")
            fix = (
                "write z in the same pixels as x (MediaPipe's z is on x's scale), or keep py-feat's FaceRect columns "
                "so aumesh converts its detector's z"
            )
        raise TableError(
            f"{where}: the faces do not have a face's proportions: median depth/height {after:.3g} {done}; a face is "
            f"{lo:g}-{hi:g} (MediaPipe's canonical face ~0.55, a flat face ~0.001). Fix: {fix}."
        )
    growth = stats.z_growth()
    if growth is None:
        return
    told = (
        f"{where}: z as written grows with the face's size as {growth:.2f} (slope of log z-extent on log face height "
        f"over {int(stats.growth[0]):,} near-frontal faces; frame pixels give ~1, {det}'s crop units ~0)"
    )
    if stats.z in ("chip", "crop256") and growth > 0.5:
        raise TableError(
            f"{told}: z is already in pixels, and converting it again would scale each face's depth by its crop. "
            f"Fix: set data.mesh_units=pixels."
        )
    if stats.z == "pixels" and mesh_units == "pixels" and growth < 0.5:
        raise TableError(
            f"{told}: z is in {det}'s crop units as py-feat writes them, not pixels. Fix: set "
            f"data.mesh_units=detector (the default)."
        )


def load_manifest(ingested_dir: str | Path) -> dict:
    path = Path(ingested_dir) / MANIFEST_FILE
    if not path.exists():
        raise TableError(
            f"{path}: no ingested tables. Fix: `dvc repro` (runs the ingest stage first), or "
            f"`aumesh ingest --params params.yaml`."
        )
    with open(path) as fh:
        return json.load(fh)
