"""py-feat's CSVs through the pipeline, beside one pyarrow CSV read of the same files and the parquet path.

Generates (or reuses, cached under ``--workdir``) py-feat-shaped CSVs of ``--frames`` frames with MPDetector's full
column set (~2,045 columns: blendshapes, emotions, 512 identity columns, gaze...; ``aumesh.synthetic.pyfeat``), with
no-face runs and background faces, and the same frames cleaned by hand as parquet (the main face of every frame with a
face). Then, run by run, alternating the order:

* **CSV read floor**: one multi-threaded ``pyarrow.csv.read_csv`` of every CSV, all columns (the least any reader of
  these files spends parsing them);
* **CSV path**: the four stages (ingest, prepare, evaluate, release) on the CSVs;
* **parquet path**: the four stages on the hand-cleaned parquet (ingest lists them to be read in place).

Target (issue 32): CSV path <= CSV read floor + 1.2 x parquet path. Prints a markdown table of medians and the
median of the runs' ratios; no assertions. With ``--dvc`` also ``dvc repro`` of both in temporary DVC workspaces.

Examples
--------
    python benchmarks/bench_ingest.py                      # ~100k frames, 3 runs
    python benchmarks/bench_ingest.py --frames 20000 --repeats 1
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    DEFAULT_OUT,
    STAGES,
    compose_params,
    dir_size,
    environment_note,
    fmt_table,
    load,
    run_stages,
    videos_for,
)


def ensure_pyfeat_data(workdir: Path, n_frames: int, videos_per_file: int) -> tuple[Path, Path, dict]:
    """(CSV folder, hand-cleaned parquet folder, generation summary), generated once and cached."""
    from aumesh.synthetic.pyfeat import write_pyfeat_tables
    from aumesh.synthetic.tables import SynthSpec

    # "_cropz": z in MPDetector's 256-px crop units, as py-feat writes it (a cache of the generator's earlier tables,
    # z in pixels, is refused by the ingest's units guard: data.mesh_units=pixels)
    root = workdir / f"pyfeat_{n_frames}_{videos_per_file}_cropz"
    summary_file = root / "summary.json"
    if not summary_file.exists():
        shutil.rmtree(root, ignore_errors=True)
        t0 = time.perf_counter()
        made = write_pyfeat_tables(
            root / "csv",
            SynthSpec(n_frames=n_frames, n_videos=videos_for(n_frames)),
            detector="mp",
            fmt="csv",
            clean_dir=root / "clean",
            videos_per_file=videos_per_file,
        )
        made = {k: v for k, v in made.items() if not k.endswith("files")} | {"generated_s": time.perf_counter() - t0}
        summary_file.write_text(json.dumps(made))
    return root / "csv", root / "clean", json.loads(summary_file.read_text())


def csv_read_floor(csv_dir: Path) -> float:
    """Wall seconds of one multi-threaded pyarrow CSV read of every CSV under ``csv_dir``, all columns."""
    import pyarrow.csv as pacsv

    t0 = time.perf_counter()
    for path in sorted(csv_dir.glob("*.csv")):
        table = pacsv.read_csv(path, read_options=pacsv.ReadOptions(use_threads=True))
        del table
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=100_000)
    ap.add_argument("--videos-per-file", type=int, default=250, help="videos in one CSV (one detect(..., save=) call)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--workdir", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--dvc", action="store_true", help="also `dvc repro` of both paths in temporary DVC workspaces")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    args.workdir.mkdir(parents=True, exist_ok=True)
    csv_dir, clean_dir, made = ensure_pyfeat_data(args.workdir, args.frames, args.videos_per_file)
    print(environment_note())
    print(
        f"py-feat CSVs: {csv_dir} ({dir_size(csv_dir) / 2**30:.2f} GiB, {made['n_rows']:,} rows: "
        f"{made['n_no_face']:,} no-face, {made['n_extra_faces']:,} background faces); hand-cleaned parquet: "
        f"{dir_size(clean_dir) / 2**30:.2f} GiB, {made['n_face_frames']:,} frames",
        flush=True,
    )
    paths = {"csv": csv_dir, "parquet": clean_dir}
    run_dirs = {name: args.workdir / f"ingest_run_{name}" for name in paths}
    params = {name: compose_params(run_dirs[name], data) for name, data in paths.items()}
    floors, runs = [], {name: [] for name in paths}
    for r in range(args.repeats):
        order = list(paths) if r % 2 == 0 else list(paths)[::-1]
        floors.append(csv_read_floor(csv_dir))
        for name in order:
            ms = run_stages(run_dirs[name], params[name])
            runs[name].append(ms)
            print(
                f"run {r + 1} {name}: "
                + ", ".join(f"{m.stage} {m.wall_s:.1f} s / {m.maxrss_mib:,.0f} MiB" for m in ms)
                + f" | CSV read floor {floors[-1]:.1f} s | load {load()}",
                flush=True,
            )
    totals = {name: [sum(m.wall_s for m in run) for run in runs[name]] for name in paths}
    ratio = statistics.median((c - f) / p for c, f, p in zip(totals["csv"], floors, totals["parquet"], strict=True))
    rows = []
    for name in paths:
        med = [statistics.median(run[i].wall_s for run in runs[name]) for i in range(len(STAGES))]
        peak = max(m.maxrss_mib for run in runs[name] for m in run)
        r2 = json.loads((run_dirs[name] / "metrics.json").read_text())["r2_mean"]
        rows.append([f"{name} path", *med, statistics.median(totals[name]), peak, f"{r2:.6f}"])
    print()
    print(
        f"{made['n_face_frames']:,} frames ({made['n_rows']:,} py-feat rows); median of {args.repeats} run(s); CSV read "
        f"floor {statistics.median(floors):.1f} s ({min(floors):.1f}-{max(floors):.1f}); load average now {load()}"
    )
    print(fmt_table(["input", *(f"{s} s" for s in STAGES), "total s", "peak RSS MiB", "CV R2"], rows))
    print(f"\n(CSV path - CSV read floor) / parquet path: {ratio:.2f} (median of the runs' ratios; target <= 1.2)")
    record = {"made": made, "floors_s": floors, "totals_s": totals, "ratio": ratio, "env": environment_note()}
    if args.dvc:
        from bench_pipeline import run_dvc

        for name, data in paths.items():
            res = run_dvc(args.workdir, data, None)
            record[f"dvc_{name}_s"] = res["total"].wall_s
            print(
                f"`dvc repro` of the {name} path: {res['total'].wall_s:.1f} s ("
                + ", ".join(f"{s} {res['stages'][s][0]:.1f} s" for s in STAGES)
                + ")"
            )
            shutil.rmtree(res["workspace"], ignore_errors=True)
    for d in run_dirs.values():
        shutil.rmtree(d, ignore_errors=True)
    if args.json:
        args.json.write_text(json.dumps(record, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
