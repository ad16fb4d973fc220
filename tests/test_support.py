"""What a release's data supports (issue 41, items 4, 5 and 7): the input ranges prepare records, the card's and the
NPZ's record of them, and the warnings beyond them."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from conftest import default_config

from aumesh.data.schema import AU_COLUMNS, INPUT_COLUMNS, POSE_COLUMNS
from aumesh.model import support


def _expected_ranges(frames: pd.DataFrame) -> dict:
    """The independent reference: np.quantile and a count over the prepared frames, column by column."""
    out = {}
    for name in INPUT_COLUMNS:
        v = frames[name].to_numpy(np.float64)
        out[name] = {
            "min": float(v.min()),
            "p1": float(np.quantile(v, 0.01)),
            "p50": float(np.quantile(v, 0.5)),
            "p99": float(np.quantile(v, 0.99)),
            "max": float(v.max()),
            "active_fraction": float(np.mean(v > 0.1)) if name in AU_COLUMNS else None,
        }
    return out


def test_prepared_input_ranges_are_numpys_quantiles_of_the_fitted_frames(recovery_prepared):
    """summary.json's input_ranges: np.quantile (and the share above 0.1) of each input over frames.parquet, the
    frames the model is fitted on, exactly."""
    prepared = recovery_prepared / "prepared"
    summary = json.loads((prepared / "summary.json").read_text())
    frames = pd.read_parquet(prepared / "frames.parquet")
    assert len(frames) == summary["n_frames"]
    assert summary["input_ranges"] == _expected_ranges(frames)


def test_ranges_over_several_partitions_equal_one_quantile_of_the_kept_frames(small_tables, tmp_path):
    """Partitions of 64 rows (many row groups, outliers dropped in each): still np.quantile of the kept frames."""
    import pyarrow.parquet as pq

    from aumesh.data import tables

    for path in small_tables.glob("*.parquet"):  # row groups of 37 rows: partitions are whole row groups
        pq.write_table(pq.read_table(path), path, row_group_size=37)
    from aumesh.pipeline import prepare

    cfg = default_config(**{"paths.data_dir": str(small_tables), "compute.partition_rows": 64})
    found = tables.discover(small_tables, cfg.data.tables, cfg.data.mesh_npy)
    summary = prepare.run(found, cfg, tmp_path / "prepared", detectors={"MPDetector": 2})
    frames = pd.read_parquet(tmp_path / "prepared" / "frames.parquet")
    assert pq.ParquetFile(tmp_path / "prepared" / "frames.parquet").metadata.num_row_groups > 1  # one per partition
    assert summary["counts"]["dropped_alignment_outliers"] > 0  # the ranges are over the kept frames only
    assert summary["input_ranges"] == _expected_ranges(frames)
    assert summary["detector"]["name"] == "MPDetector"
    assert summary["detector"]["au_meaning"] == support.AU_MEANING["MPDetector"]
