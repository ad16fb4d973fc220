"""Scaling benchmark: wall time, CPU time and peak RSS of each stage at 100k, 344,418 and 1,000,000 frames.

Videos scale with frames (~34.5 frames per video, CelebV-HQ's ratio). For every size the
synthetic set is generated once and cached under ``--workdir`` (1M frames: ~7 GiB parquet;
the run folder adds ~5.5 GiB of prepared meshes while it runs). Each stage runs as its own
subprocess (see ``benchmarks/_common.py``); time per 100k frames shows linearity, and peak RSS
should not grow with the number of frames (only per-frame metadata does: ~0.5 KB a frame).

Prints markdown tables; no assertions. Not a timed test.

Examples
--------
    python benchmarks/bench_scaling.py                         # 100k, 344,418, 1M
    python benchmarks/bench_scaling.py --sizes 20000 100000 --repeats 2
    python benchmarks/bench_scaling.py --clean                 # delete the synthetic sets afterwards
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (DEFAULT_OUT, STAGES, compose_params, dir_size, ensure_data, environment_note,  # noqa: E402
                     fmt_table, run_stages, videos_for)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 344_418, 1_000_000])
    ap.add_argument("--workdir", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--repeats", type=int, default=1, help="runs per size; medians are printed")
    ap.add_argument("--clean", action="store_true", help="delete each synthetic set after its runs")
    ap.add_argument("--json", type=Path, default=None, help="also write the measurements here")
    args = ap.parse_args(argv)

    print(environment_note())
    results = []
    for n in args.sizes:
        v = 9_978 if n == 344_418 else videos_for(n)
        data, gen_s = ensure_data(args.workdir, n, v)
        print(f"{n:,} frames / {v:,} videos: {data} ({dir_size(data) / 2**30:.2f} GiB)"
              + (f", generated in {gen_s:.0f} s" if gen_s is not None else ", reused"), flush=True)
        run_dir = args.workdir / f"scaling_{n}"
        params = compose_params(run_dir, data)
        runs = []
        for r in range(args.repeats):
            ms = run_stages(run_dir, params)
            runs.append(ms)
            print("  " + ", ".join(f"{m.stage} {m.wall_s:.1f} s ({m.cpu_s:.0f} s CPU) / {m.maxrss_mib:,.0f} MiB"
                                   for m in ms), flush=True)
        kept = json.loads((run_dir / "prepared" / "summary.json").read_text())["n_frames"]
        rec = {"frames": n, "videos": v, "kept": kept, "stages": {}}
        for i, stage in enumerate(STAGES):
            rec["stages"][stage] = {key: statistics.median(getattr(run[i], key) for run in runs)
                                    for key in ("wall_s", "cpu_s", "maxrss_mib")}
        rec["total_wall_s"] = statistics.median(sum(m.wall_s for m in run) for run in runs)
        rec["total_cpu_s"] = statistics.median(sum(m.cpu_s for m in run) for run in runs)
        results.append(rec)
        shutil.rmtree(run_dir, ignore_errors=True)
        if args.clean:
            shutil.rmtree(data, ignore_errors=True)

    print()
    head = ["frames"] + [f"{s} s" for s in STAGES] + ["total s", "total s / 100k frames", "total CPU s",
                                                      "CPU s / 100k frames"]
    rows = [[f"{r['frames']:,}"] + [r["stages"][s]["wall_s"] for s in STAGES]
            + [r["total_wall_s"], r["total_wall_s"] / r["frames"] * 1e5, r["total_cpu_s"], r["total_cpu_s"] / r["frames"] * 1e5]
            for r in results]
    print("Wall time per stage (median of %d run(s))" % args.repeats)
    print(fmt_table(head, rows))
    print()
    print("Peak RSS per stage, MiB (ru_maxrss of the stage process)")
    print(fmt_table(["frames"] + list(STAGES) + ["max"],
                    [[f"{r['frames']:,}"] + [r["stages"][s]["maxrss_mib"] for s in STAGES]
                     + [max(r["stages"][s]["maxrss_mib"] for s in STAGES)] for r in results]))
    print()
    print("Per-stage time per 100k frames (wall s; CPU s in brackets)")
    print(fmt_table(["frames"] + list(STAGES),
                    [[f"{r['frames']:,}"] + [f"{r['stages'][s]['wall_s'] / r['frames'] * 1e5:.1f} "
                                             f"({r['stages'][s]['cpu_s'] / r['frames'] * 1e5:.1f})" for s in STAGES]
                     for r in results]))
    if args.json:
        args.json.write_text(json.dumps({"env": environment_note(), "results": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
