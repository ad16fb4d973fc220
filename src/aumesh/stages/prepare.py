"""The prepare stage: the ingested tables -> aligned, filtered frames and their reference (``paths.prepared_dir``)."""

from __future__ import annotations

import logging

from aumesh.config import Config
from aumesh.stages.common import check_columns, start_stage

log = logging.getLogger(__name__)


def main(cfg: Config) -> dict:
    """Prepare the ingested tables into ``paths.prepared_dir``; returns ``summary.json``'s record (counts per
    filter, frames and videos kept)."""
    from aumesh.core.schema import instrument_columns
    from aumesh.data import tables
    from aumesh.pipeline import ingest
    from aumesh.pipeline import prepare as prep

    start_stage("prepare", cfg)
    manifest = ingest.load_manifest(cfg.paths.ingested_dir)
    # the families the ingest stage carries (issue 46; a manifest of before: none), read by name from every table
    families = manifest.get("families") or {"carried": [], "not_carried": {}}
    found = tables.check_tables(
        manifest["tables"],
        cfg.data.mesh_npy,
        cfg.data.coerce_numeric,
        instrument_columns(cfg.model.eiv.instrument_aus),
        families["carried"],
    )
    if found:  # keys naming a column, before the passes (the first table's columns: the contract makes them alike)
        import pyarrow.parquet as pq

        check_columns(cfg, pq.read_schema(found[0].path).names, str(found[0].path))
    from aumesh.model import support

    summary = prep.run(
        found,
        cfg,
        cfg.paths.prepared_dir,
        ingested=manifest["counts"],
        detectors=support.detector_counts(manifest),
        families=families,
    )
    log.info("prepared %d frames of %d videos: %s", summary["n_frames"], summary["n_videos"], summary["counts"])
    return summary
