"""Frames scaling: wall time, CPU time and peak RSS of each stage from ~100k to ~3M frames, before/after side by side.

The sets are py-feat's layout (AU/pose parquet + float16 ``[N, 478, 3]`` .npy), built from the cached
344,418-frame synthetic set (``aumesh synth``, seed 0, generated once under ``--workdir``): its meshes are
converted once to float16 (~1 GiB), and a size is ``copies`` copies of its first ``files`` tables, copy ``c``
renaming its videos (``c<c>_``) and linking the same .npy files. So 3M frames cost ~1 GiB of disk, and
every size has the same per-video statistics (~34.5 frames a video):

    4 files x 1  ~100k frames | 14 x 1  344,418 | 14 x 3  ~1.03M | 14 x 9  ~3.1M

For every size: the read floor (one pyarrow read of the tables, all columns, and their .npy), then each
source tree's three stages as subprocesses (``benchmarks/_common.py``): ``--baseline-src`` (e.g. the code
before a change) and the installed aumesh (or ``--src``), alternating, so both see the same machine: one run
folder per set, the variants' order swapped from one set to the next.

Prints markdown tables; no assertions. Not a timed test.

Examples
--------
    python benchmarks/bench_scaling.py --workdir /work/bench --baseline-src /work/wt/base/src
    python benchmarks/bench_scaling.py --sets 4x1 14x1                 # ~100k and 344k only
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    DEFAULT_OUT,
    STAGES,
    compose_params,
    dir_size,
    ensure_data,
    environment_note,
    fmt_table,
    load,
    pyfeat_replicas,
    read_floor,
    run_stages,
    source_env,
)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--sets",
        nargs="+",
        default=["4x1", "14x1", "14x3", "14x9"],
        help="FILESxCOPIES: copies of the first FILES tables of the 344,418-frame set",
    )
    ap.add_argument("--workdir", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--src", default=None, help="source tree to benchmark (default: the installed aumesh)")
    ap.add_argument("--baseline-src", default=None, help="also run this source tree, side by side")
    ap.add_argument(
        "--baseline-sets", nargs="+", default=None, help="run --baseline-src only on these sets (default: all)"
    )
    ap.add_argument(
        "--stages",
        nargs="+",
        default=list(STAGES),
        choices=STAGES,
        help="stages to run (release does not depend on the number of frames)",
    )
    ap.add_argument("--repeats", type=int, default=1, help="runs per size; medians are printed")
    ap.add_argument("--clean", action="store_true", help="delete each size's set after its runs")
    ap.add_argument("--json", type=Path, default=None, help="also write the measurements here")
    args = ap.parse_args(argv)

    print(environment_note())
    columns, _ = ensure_data(args.workdir, 344_418, 9_978)
    variants = ([("before", args.baseline_src)] if args.baseline_src else []) + [("after", args.src)]
    results = []
    for spec in args.sets:
        files, copies = (int(x) for x in spec.split("x"))
        data = pyfeat_replicas(args.workdir, columns, copies, files)
        floor_s, floor_gib = read_floor(data)
        rec = {"set": spec, "read_floor_s": floor_s, "variants": {}}
        print(
            f"{spec}: {data} ({dir_size(data) / 2**30:.2f} GiB of parquet + linked .npy); read floor {floor_s:.1f} s "
            f"({floor_gib:.2f} GiB decoded) | load {load()}",
            flush=True,
        )
        # one run folder for both variants (a second folder's prepare took ~1 s more system time), and the variants'
        # order alternates from set to set (the second of two back-to-back pipelines ran slower)
        run_dir = args.workdir / f"scaling_{spec}"
        for name, src in variants if len(results) % 2 == 0 else variants[::-1]:
            if name == "before" and args.baseline_sets and spec not in args.baseline_sets:
                continue
            params = compose_params(run_dir, data, src=src, name=f"params_{name}.yaml")
            runs = []
            for _ in range(args.repeats):
                ms = run_stages(run_dir, params, source_env(src), stages=args.stages)
                runs.append(ms)
                print(
                    f"  {name}: "
                    + ", ".join(
                        f"{m.stage} {m.wall_s:.1f} s ({m.cpu_s:.0f} s CPU) / {m.maxrss_mib:,.0f} MiB"
                        f" (tree {m.tree_rss_mib:,.0f})"
                        for m in ms
                    )
                    + f" | load {load()}",
                    flush=True,
                )
            summary = json.loads((run_dir / "prepared" / "summary.json").read_text())
            rec["frames"] = summary["counts"]["frames_in"]
            v = {
                "stages": {
                    s: {
                        k: statistics.median(getattr(run[i], k) for run in runs)
                        for k in ("wall_s", "cpu_s", "maxrss_mib", "tree_rss_mib")
                    }
                    for i, s in enumerate(args.stages)
                }
            }
            v["total_wall_s"] = statistics.median(sum(m.wall_s for m in run) for run in runs)
            v["total_cpu_s"] = statistics.median(sum(m.cpu_s for m in run) for run in runs)
            v["peak_rss_mib"] = max(st["maxrss_mib"] for st in v["stages"].values())
            v["peak_tree_rss_mib"] = max(st["tree_rss_mib"] for st in v["stages"].values())
            rec["variants"][name] = v
        shutil.rmtree(run_dir, ignore_errors=True)
        results.append(rec)
        if args.clean:
            shutil.rmtree(data, ignore_errors=True)

    print()
    print(
        f"Frames scaling (median of {args.repeats} run(s)); wall and CPU s of the three stages, peak RSS = max over "
        f"stages of the stage process's ru_maxrss (tree: sampled sum over its processes); load average now {load()}"
    )
    head = ["frames", "read floor s"]
    for name, _ in variants:
        head += [f"{name}: total s", f"{name}: CPU s", f"{name}: peak RSS MiB", f"{name}: tree RSS MiB"]
    rows = []
    for r in results:
        row = [f"{r['frames']:,}", r["read_floor_s"]]
        for name, _ in variants:
            v = r["variants"].get(name)
            row += [v["total_wall_s"], v["total_cpu_s"], v["peak_rss_mib"], v["peak_tree_rss_mib"]] if v else ["-"] * 4
        rows.append(row)
    print(f"stages: {', '.join(args.stages)}")
    print(fmt_table(head, rows))
    for name, _ in variants:
        print()
        print(f"{name}: per stage, wall s / CPU s / peak RSS MiB")
        print(
            fmt_table(
                ["frames", *args.stages],
                [
                    [f"{r['frames']:,}"]
                    + [
                        f"{r['variants'][name]['stages'][s]['wall_s']:.1f} / "
                        f"{r['variants'][name]['stages'][s]['cpu_s']:.1f} / "
                        f"{r['variants'][name]['stages'][s]['maxrss_mib']:,.0f}"
                        for s in args.stages
                    ]
                    for r in results
                    if name in r["variants"]
                ],
            )
        )
    if args.json:
        args.json.write_text(json.dumps({"env": environment_note(), "results": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
