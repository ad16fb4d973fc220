"""Stage ``ingest``: whatever ``data/`` holds -> the frame tables ``prepare`` reads (``paths.ingested_dir``).

py-feat's CSVs (either detector), a Fex saved as parquet and the card's split layout are all accepted as py-feat
writes them (:mod:`aumesh.data.ingest`: no-face rows dropped, one face per frame, pixels). The stage writes:

* ``tables/NNNNNN.parquet``: the cleaned rows of the sources that need it (every CSV; parquet with no-face rows,
  several faces in a frame, Detectorv2's columns or normalized units), only the contract's columns: video_id, frame,
  20 AUs, Pitch, Yaw, Roll, the mesh axis-major in float32; about a CSV range or ``PARQUET_RANGE_ROWS`` rows per task,
  packed to at least :data:`TASK_ROWS` rows a file;
* ``manifest.json``: the tables ``prepare`` reads, in order: those files, and clean parquet tables of ``data/`` in
  place (read as they are: a clean parquet costs only this stage's check, a few columns, not a copy); per source, what
  it held and what was dropped; the totals.

Cached by DVC: a change of recipe (``preprocess.*``, ``model.*``) reruns ``prepare`` on these files and never
re-parses a CSV. CSV ranges are parsed on the compute engine, several at once.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from aumesh.config import Config
from aumesh.data import ingest
from aumesh.pipeline import compute
from aumesh.utils.errors import TableError
from aumesh.utils.io import absolute, atomic_directory, atomic_write_json, recorded

log = logging.getLogger(__name__)

MANIFEST_FILE = "manifest.json"
TABLES_DIR = "tables"
#: CSV ranges or parquet spans packed into one task and one output file, up to about this many rows (a file per
#: task: per-video CSVs become a few large tables, not thousands of small ones whose footers each pass would parse).
TASK_ROWS = 32768
#: Bytes of py-feat CSV per row (2,045 columns of ~10 characters), to pack CSV ranges by rows before they are read.
CSV_BYTES_PER_ROW = 20_000


def find_sources(data_dir: Path, pattern: str, mesh_npy_pattern: str) -> list[ingest.Source]:
    """Every table under ``data_dir`` that ``data.tables`` matches (CSV, gzipped CSV, parquet), sorted by path."""
    if not data_dir.is_dir():
        raise TableError(
            f"{data_dir}: the data folder does not exist (paths.data_dir). Fix: `dvc pull data.dvc` for the demo tables, "
            f"or copy py-feat's CSVs (detector.detect(video, save=...)) into {data_dir}/ and run `dvc add {data_dir}`."
        )
    paths = sorted(p for p in data_dir.glob(pattern) if p.is_file() and ingest.is_table(p))
    if not paths:
        raise TableError(
            f"{data_dir}/{pattern}: no frame tables found (empty input; CSV, .csv.gz or parquet). Fix: copy py-feat's "
            f"CSVs (detector.detect(video, save=...)) into {data_dir}/ and run `dvc add {data_dir}`, or `dvc pull`."
        )
    return [ingest.open_source(p, mesh_npy_pattern) for p in paths]


def _span_rows(span: ingest.Span) -> int:
    return (
        max(1, (span.stop - span.start) // CSV_BYTES_PER_ROW) if span.source.kind == "csv" else span.stop - span.start
    )


def pack(spans: list[ingest.Span], task_rows: int = TASK_ROWS) -> list[tuple[ingest.Span, ...]]:
    """Consecutive spans packed into tasks of up to about ``task_rows`` rows (a span is never split)."""
    tasks: list[tuple[ingest.Span, ...]] = []
    current: list[ingest.Span] = []
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
    spans: tuple[ingest.Span, ...]
    out: Path


def _clean_task(task: Task, how: str, subjects: dict[str, str] | None) -> ingest.Counts:
    return ingest.write_clean(task.spans, task.out, how, subjects)


def _identity_task(task: Task) -> ingest.Counts:
    return ingest.span_identities(task.spans)


def run(cfg: Config, out_dir: str | Path) -> dict:
    """Ingest ``paths.data_dir`` into ``out_dir`` (replaced atomically). Returns the manifest."""
    data_dir, out_dir = Path(cfg.paths.data_dir), Path(out_dir)
    # the tasks get absolute paths (a cluster's workers run elsewhere); the manifest records them as given
    sources = [s.absolute() for s in find_sources(data_dir, cfg.data.tables, cfg.data.mesh_npy)]
    how = cfg.data.face_selection
    with atomic_directory(absolute(out_dir)) as tmp, compute.engine(cfg.compute, read=sources[0].path, write=tmp):
        parquet = [s for s in sources if s.kind == "parquet"]
        checks = dict(
            zip(
                [s.path for s in parquet],
                compute.map_gather(ingest.check_clean, parquet, desc="ingest: check parquet"),
                strict=True,
            )
        )
        entries, spans = [], []
        for source in sources:
            check = checks.get(source.path)
            if check is not None and check.clean:
                entries.append(
                    {
                        "source": recorded(source.path),
                        "table": recorded(source.path),
                        "rows": check.rows,
                        "mesh_npy": None if source.mesh_npy is None else recorded(source.mesh_npy),
                        "detector": source.layout.detector,
                        "read": "in place",
                    }
                )
                continue
            reason = "CSV" if check is None else check.reason
            entries.append(
                {"source": recorded(source.path), "detector": source.layout.detector, "read": f"cleaned ({reason})"}
            )
            # a parquet table is streamed whole by one task (batch by batch: memory flat in its rows)
            spans += ingest.csv_spans(source) if source.kind == "csv" else [ingest.Span(source, 0, source.n_rows or 0)]
        (tmp / TABLES_DIR).mkdir()
        tasks = [Task(group, tmp / TABLES_DIR / f"{i:06d}.parquet") for i, group in enumerate(pack(spans))]
        subjects = None
        if how == "identity" and tasks:  # the video's subject needs every face row first: a second read of the sources
            seen = compute.map_reduce(_identity_task, ingest.Counts.__add__, tasks, desc="ingest: identities")
            subjects = ingest.main_identities(seen.identities)
        counts = compute.map_gather(
            partial(_clean_task, how=how, subjects=subjects), tasks, desc="ingest: read + clean"
        )
        total = ingest.Counts()
        for task, c in zip(tasks, counts, strict=True):
            total = total + c
            if not c.rows_out:  # every row a no-face row
                task.out.unlink()
        tables = [e["table"] for e in entries if "table" in e]
        tables += [
            recorded(out_dir / TABLES_DIR / t.out.name) for t, c in zip(tasks, counts, strict=True) if c.rows_out
        ]
        in_place = sum(e["rows"] for e in entries if "table" in e)
        totals = total.as_dict()
        totals["rows_in"] += in_place
        totals["frames_out"] += in_place
        totals = {"tables_in": len(sources), **totals}
        manifest = {"tables": tables, "face_selection": how, "counts": totals, "sources": entries[:10000]}
        atomic_write_json(tmp / MANIFEST_FILE, manifest)
    log.info("ingest: %s", totals)
    return manifest


def load_manifest(ingested_dir: str | Path) -> dict:
    path = Path(ingested_dir) / MANIFEST_FILE
    if not path.exists():
        raise TableError(
            f"{path}: no ingested tables. Fix: `dvc repro` (runs the ingest stage first), or "
            f"`aumesh ingest --params params.yaml`."
        )
    with open(path) as fh:
        return json.load(fh)
