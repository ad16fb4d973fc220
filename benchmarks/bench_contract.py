"""Cost of the data contract (aumesh.data.contract, pandera) next to one pyarrow read of the same tables.

What the contract adds to a run, measured on its own:

* ``validate_metadata`` (pandera schema: dtypes, NaN/inf, AU 0-1, pose within pi) on every table's
  metadata columns, ``check_pose_units`` and ``check_filter_shares`` on all of them;
* the schema-level checks of ``tables.discover`` (column names, mesh column types: parquet footers only).

Reference: one ``pyarrow.parquet.read_table`` of every table, all columns (what reading the data costs at
least). The metadata columns are read once before timing (the pipeline reads them anyway). Prints a markdown
table; no assertions. Default size: CelebV-HQ's 344,418 frames / 9,978 videos (``aumesh synth``, cached under
``--workdir``).

Example
-------
    python benchmarks/bench_contract.py --workdir /tmp/aumesh-bench
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import DEFAULT_OUT, ensure_data, environment_note  # noqa: E402


def _seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv=None) -> int:
    from aumesh.core.schema import AU_COLUMNS, FRAME_COLUMN, POSE_COLUMNS, VIDEO_COLUMN
    from aumesh.data import contract, tables

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=344_418)
    ap.add_argument("--videos", type=int, default=9_978)
    ap.add_argument("--workdir", type=Path, default=DEFAULT_OUT, help="where the synthetic tables are cached")
    ap.add_argument("--data", type=Path, default=None, help="use these tables instead of synthetic ones")
    ap.add_argument("--repeats", type=int, default=3, help="runs per timing; medians are printed")
    args = ap.parse_args(argv)
    data = args.data or ensure_data(args.workdir, args.frames, args.videos)[0]

    found = tables.discover(data, "**/*.parquet", "{stem}.npy")
    columns = [VIDEO_COLUMN, FRAME_COLUMN, *AU_COLUMNS, *POSE_COLUMNS]
    metas = [pq.read_table(t.path, columns=columns).to_pandas() for t in found]
    n = sum(len(m) for m in metas)

    def run_contract():
        checked = [contract.validate_metadata(m, t.path) for m, t in zip(metas, found, strict=True)]
        for m in checked:
            contract.check_pose_units(m[list(POSE_COLUMNS)].to_numpy(), data)
        contract.check_filter_shares(contract.filter_shares({"frames_in": n, "dropped_pose": 0}), 1.0, data)

    def run_read():
        for t in found:
            pq.read_table(t.path)

    t_schema = _seconds(lambda: tables.discover(data, "**/*.parquet", "{stem}.npy"), args.repeats)
    t_contract = _seconds(run_contract, args.repeats)
    t_read = _seconds(run_read, args.repeats)
    print(f"{n:,} frames in {len(found)} tables ({data}); {environment_note()}; median of {args.repeats}\n")
    print("| step | seconds | vs one pyarrow read |")
    print("|---|---:|---:|")
    for name, t in (
        ("contract: pandera metadata schema + pose units + filter shares", t_contract),
        ("schema checks of tables.discover (footers, mesh column types)", t_schema),
        ("one pyarrow read of every table, all columns", t_read),
    ):
        print(f"| {name} | {t:.2f} | {t / t_read:.1%} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
