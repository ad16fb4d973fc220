"""What every stage does around its work: its outputs, the leftovers of a killed run, the data's digest."""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from aumesh.config import Config, PathsConfig
from aumesh.core import provenance
from aumesh.core.io import remove_stale_temporaries
from aumesh.pipeline.prepared_files import FRAMES_FILE, scratch_path

log = logging.getLogger(__name__)


def data_digest(dvc_file: str = "data.dvc") -> dict[str, Any]:
    """The DVC hash of the frame tables; outside a DVC workspace, a marked placeholder (never silently absent)."""
    try:
        return provenance.data_digest(Path.cwd(), dvc_file)
    except FileNotFoundError as err:
        log.warning("%s", err)
        return {"md5": None, "note": f"{dvc_file} not found: data not tracked by DVC"}


def stage_outputs(stage: str, paths: PathsConfig) -> list[str]:
    """The outputs ``dvc.yaml`` declares for ``stage`` (prepare, evaluate, release)."""
    return {
        "ingest": [paths.ingested_dir],
        "prepare": [paths.prepared_dir],
        "evaluate": [paths.model_dir, paths.metrics_file, paths.error_curve_file, paths.r2_curve_file],
        "release": [paths.release_dir],
    }.get(stage, [])


def start_stage(stage: str, cfg: Config) -> None:
    """Remove what a killed earlier run of ``stage`` left behind (temp folders and files of its outputs, and the
    evaluate passes' scratch folders)."""
    if stage in (
        "evaluate",
        "release",
        "release_family",
    ):  # they read what promotion writes (params.yaml; promotion.json)
        finish_promotion(cfg)
    scratch: list[str | Path] = []
    if stage == "evaluate":
        scratch.append(scratch_path(cfg.paths.prepared_dir))
    for out in [*stage_outputs(stage, cfg.paths), *scratch]:
        for path in remove_stale_temporaries(out):
            log.info("removed %s, left by a killed run", path)


def finish_promotion(cfg: Config) -> None:
    """Complete or roll back a promotion of this workspace that was killed half-way, saying which in one line
    (:mod:`aumesh.experiments.promotion_journal`); when that changed ``params.yaml`` or the promotion file, this run
    started from the old ones: stop (exit 2) and say to run again."""
    from aumesh.core.errors import UserError
    from aumesh.experiments import promotion_journal

    line, changed = promotion_journal.recover(Path.cwd(), say=lambda text: log.warning("%s", text))
    stale = [f for f in changed if f in ("params.yaml", cfg.paths.promotion_file)]
    if stale:
        raise UserError(
            f"{' and '.join(stale)} changed by that ({line.split(' (')[0] if line else ''}), after this run had read "
            f"them. Fix: run again (`dvc repro`: it now sees the promotion's params)."
        )


def removed_by_dvc(stage: str, lock_file: str | Path = "dvc.lock") -> str | None:
    """When DVC runs ``stage`` (``DVC_STAGE``) and removed outputs that ``dvc.lock`` records (a last good version in
    DVC's cache), the one command that brings them back. ``release/`` is ``persist: true``: DVC never removes it."""
    import yaml

    if os.environ.get("DVC_STAGE", "").rsplit(":", 1)[-1] != stage or not Path(lock_file).exists():
        return None
    try:
        locked = yaml.safe_load(Path(lock_file).read_text())["stages"][stage]["outs"]
    except (KeyError, TypeError, yaml.YAMLError):
        return None
    missing = [out["path"] for out in locked if not Path(out["path"]).exists()]
    if not missing:
        return None
    return f"DVC removed {', '.join(missing)} before running {stage}: `dvc checkout {stage}` brings back the last good one."


def check_columns(cfg: Config, columns: list[str] | None = None, where: str | None = None) -> None:
    """Keys of the configuration that name a column, checked against the data before any work (``columns``: the
    data's columns, read from ``where``; default: the prepared frames' ``frames.parquet`` schema).

    ``cv.group``: the cross-validation keeps each group's frames in one fold, and its per-video statistics (the
    neutral meshes, the displacement target) make the video the only grouping it can run; an unknown name was
    ignored before (the same CV ran, and the name was printed in the card as if it had been used).
    """
    from aumesh.core.errors import ConfigError
    from aumesh.core.schema import VIDEO_COLUMN

    group = cfg.cv.group
    if group == VIDEO_COLUMN:
        return
    if columns is None:
        import pyarrow.parquet as pq

        path = Path(cfg.paths.prepared_dir) / FRAMES_FILE
        where = where or str(path)
        columns = pq.read_schema(path).names if path.exists() else []
    import re

    mesh = [c for c in columns if re.fullmatch(r"[xyz]_\d+", c)]  # 1,434 mesh columns: named as a range
    names = ", ".join(
        [repr(c) for c in columns if c not in set(mesh)] + (["the mesh columns x_0..z_477"] if mesh else [])
    )
    if group not in columns:
        raise ConfigError(
            f"cv.group={group!r} names no column of {where} (its columns: {names}). "
            f"Fix: cv.group={VIDEO_COLUMN} (the video column: the only grouping the CV supports)."
        )
    raise ConfigError(
        f"cv.group={group!r}: the cross-validation groups frames by video only (each video's frames in "
        f"one fold; its per-video neutral meshes need that). Fix: cv.group={VIDEO_COLUMN}."
    )
