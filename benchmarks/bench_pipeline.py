"""End-to-end pipeline benchmark: wall time and peak RSS of each stage on a synthetic CelebV-HQ-scale set.

Generates (or reuses, cached by size under ``--workdir``) a synthetic set of ``--frames``
frames of ``--videos`` videos, composes a params file whose paths all point into the workdir,
then runs ``aumesh prepare``, ``aumesh evaluate`` and ``aumesh release`` as separate
subprocesses, measuring each (see ``benchmarks/_common.py``). With ``--dvc`` it also runs the
same pipeline through ``dvc repro`` in a temporary DVC workspace (``dvc init --no-scm``, this
repo's ``dvc.yaml``; data as an absolute external dependency), timing every stage command with
``/usr/bin/time`` and the whole ``dvc repro`` (hashing, caching of outputs included), after DVC has hashed
the tables once (``dvc status``, as ``dvc add`` or a pull leaves a workspace; that first hash is printed apart).

With ``--baseline-src`` (or ``--workers``) the variants take turns, run by run, in one run folder, in orders that
alternate from run to run (use an even ``--repeats``), and the median of the runs' ratios of total wall
time to the first variant's is printed beside the medians. Before each run the writes of earlier runs are flushed
(``sync``) and a stage's outputs are deleted before it, as ``dvc repro`` does; none of that is timed.

Prints a markdown table; no assertions. Not a timed test.

Examples
--------
    python benchmarks/bench_pipeline.py                         # 344,418 frames / 9,978 videos
    python benchmarks/bench_pipeline.py --frames 20000 --videos 580 --repeats 3
    python benchmarks/bench_pipeline.py --dvc                   # also the `dvc repro` form
    python benchmarks/bench_pipeline.py --src /path/to/other/src  # benchmark another source tree
    python benchmarks/bench_pipeline.py --baseline-src /tmp/old/src --workers 1 2 --dvc   # before/after, worker scaling
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    AUMESH,
    DEFAULT_OUT,
    REPO,
    STAGES,
    compose_params,
    conf_dir,
    dir_size,
    ensure_data,
    environment_note,
    fmt_table,
    init_tracking_store,
    load,
    read_floor,
    run_measured,
    run_stages,
    source_env,
    write_data_dvc,
)


def run_dvc(workdir: Path, data_dir: Path, src: str | None) -> dict:
    """``dvc repro`` of the source tree's dvc.yaml in a temporary DVC workspace; per-stage /usr/bin/time."""
    env = source_env(src)
    checkout = Path(src).resolve().parent if src else REPO
    ws = workdir / "dvc_ws"
    shutil.rmtree(ws, ignore_errors=True)
    ws.mkdir(parents=True)
    dvc = str(Path(sys.executable).parent / "dvc")
    subprocess.run([dvc, "init", "--no-scm", "-q"], cwd=ws, check=True, env=env)
    # the checkout's cache settings (link type: hardlinks instead of copying the prepared meshes into the cache)
    cache_type = subprocess.run(
        [dvc, "config", "cache.type"], cwd=checkout, capture_output=True, text=True, env=env
    ).stdout.strip()
    if cache_type:
        subprocess.run([dvc, "config", "cache.type", cache_type], cwd=ws, check=True, env=env)
    (ws / "src").symlink_to(checkout / "src")
    write_data_dvc(ws, data_dir)
    (ws / "promotion.json").write_text(json.dumps({"promoted": None}))
    text = (checkout / "dvc.yaml").read_text()
    for stage in STAGES:
        text = text.replace(
            f"cmd: ${{aumesh}} {stage} ",
            f"cmd: /usr/bin/time -f '%e %M' -o {stage}.time {sys.executable} -m aumesh {stage} ",
        )
    (ws / "dvc.yaml").write_text(text)
    init_tracking_store(ws / "mlflow.db", env)  # as in a workspace after its first run (creation printed apart)
    subprocess.run(
        AUMESH
        + [
            "compose-params",
            "--config-dir",
            str(conf_dir(src)),
            "--out",
            str(ws / "params.yaml"),
            f"paths.data_dir={data_dir}",
            f"tracking.tracking_uri=sqlite:///{ws / 'mlflow.db'}",
        ],
        check=True,
        stdout=subprocess.DEVNULL,
        env=env,
    )
    env = dict(env, PATH=str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", ""))
    # DVC's first hash of the tables (2.4 GB at 344k frames): a workspace pays it once per data version, when it
    # `dvc add`s or pulls the data (DVC keeps the hashes in its state). Timed apart, so `dvc repro` is measured as in
    # a workspace whose data is tracked; the sum of the two is a first `dvc repro` on untracked data.
    t0 = time.perf_counter()
    subprocess.run([dvc, "status", "-q"], cwd=ws, env=env, check=False, stdout=subprocess.DEVNULL)
    data_hash_s = time.perf_counter() - t0
    m = run_measured([str(Path(sys.executable).parent / "dvc"), "repro"], ws, ws / "dvc_repro.log", env, "dvc repro")
    if m.returncode != 0:
        raise RuntimeError(f"dvc repro failed:\n{(ws / 'dvc_repro.log').read_text()[-3000:]}")
    stages = {}
    for stage in STAGES:  # a source tree before the ingest stage has no ingest.time
        wall, kib = (ws / f"{stage}.time").read_text().split()[-2:] if (ws / f"{stage}.time").exists() else (0, 0)
        stages[stage] = (float(wall), int(kib) / 1024.0)
    return {"total": m, "stages": stages, "workspace": ws, "data_hash_s": data_hash_s}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=344_418)
    ap.add_argument("--videos", type=int, default=9_978)
    ap.add_argument(
        "--workdir", type=Path, default=DEFAULT_OUT, help="cache of synthetic sets and run folders (git-ignored)"
    )
    ap.add_argument("--repeats", type=int, default=1, help="runs of the stages; medians are printed")
    ap.add_argument("--dvc", action="store_true", help="also run the `dvc repro` form in a temporary DVC workspace")
    ap.add_argument("--src", default=None, help="PYTHONPATH source tree to benchmark instead of the installed aumesh")
    ap.add_argument(
        "--baseline-src",
        default=None,
        help="also run this source tree (e.g. the code before a change), side by side in the same run",
    )
    ap.add_argument(
        "--workers",
        type=int,
        nargs="+",
        default=None,
        help="also run with compute.n_workers=N for each N (worker scaling; not for --baseline-src)",
    )
    ap.add_argument("--tag", default="", help="suffix of the run folder (keep runs of different sources apart)")
    ap.add_argument("--keep", action="store_true", help="keep the run folder (prepared meshes etc.) afterwards")
    ap.add_argument("--json", type=Path, default=None, help="also write the measurements here")
    args = ap.parse_args(argv)

    args.workdir.mkdir(parents=True, exist_ok=True)
    data, gen_s = ensure_data(args.workdir, args.frames, args.videos)
    print(environment_note())
    print(
        f"data: {data} ({dir_size(data) / 2**30:.2f} GiB parquet)"
        + (f", generated in {gen_s:.0f} s" if gen_s is not None else ", reused")
    )
    first_s, floor_gib = read_floor(data)
    print(
        f"read floor: one pyarrow read of every table, all columns: {first_s:.1f} s ({floor_gib:.2f} GiB in memory); "
        f"read again before every run (the median of those is the floor)",
        flush=True,
    )
    floors = []
    args.workdir.joinpath("store_probe.db").unlink(missing_ok=True)
    store_s = init_tracking_store(args.workdir / "store_probe.db")
    args.workdir.joinpath("store_probe.db").unlink(missing_ok=True)
    print(
        f"MLflow SQLite store creation (a workspace's first run only; not in the stage times below): {store_s:.1f} s",
        flush=True,
    )

    variants = [("before", args.baseline_src, [])] if args.baseline_src else []
    variants.append(("after", args.src, []))
    variants += [(f"after, {w} worker(s)", args.src, [f"compute.n_workers={w}"]) for w in args.workers or []]
    record = {
        "frames": args.frames,
        "videos": args.videos,
        "env": environment_note(),
        "mlflow_store_creation_s": store_s,
        "variants": {},
    }
    # the variants take turns, run by run, so a machine that speeds up or slows down during the benchmark weighs on
    # every variant alike; in one run folder (the prepared meshes' 2 GB in the same place on disk: a second folder's
    # prepare took ~1 s more system time, whichever code ran there); and in turn orders that alternate (before, after |
    # after, before | ...): an even --repeats gives each variant each place equally often
    run_dir = args.workdir / f"run_{args.frames}{'_' + args.tag if args.tag else ''}"
    params = [
        compose_params(run_dir, data, overrides, src=src, name=f"params_{i}.yaml")
        for i, (_, src, overrides) in enumerate(variants)
    ]
    runs: dict[str, list] = {name: [] for name, _, _ in variants}
    outcome: dict[str, dict] = {}
    for r in range(args.repeats):
        turns = list(zip(variants, params, strict=True))
        for (name, src, _), run_params in turns if r % 2 == 0 else turns[::-1]:
            floors.append(read_floor(data)[0])  # beside every run: the floor sees the same machine as the stages
            ms = run_stages(run_dir, run_params, source_env(src))
            runs[name].append(ms)
            metrics = json.loads((run_dir / "metrics.json").read_text())
            outcome[name] = {
                "metrics": {
                    k: metrics[k] for k in ("r2_mean", "mae_mean", "vertex_error_mean", "r2_displacement_mean")
                },
                "kept": json.loads((run_dir / "prepared" / "summary.json").read_text())["n_frames"],
            }
            print(
                f"{name} run {r + 1}: "
                + ", ".join(f"{m.stage} {m.wall_s:.1f} s ({m.cpu_s:.0f} s CPU) / {m.maxrss_mib:,.0f} MiB" for m in ms)
                + f" | read floor before it {floors[-1]:.1f} s | load {load()}",
                flush=True,
            )
    for name, _, _ in variants:
        rec = {"stages": {}} | outcome[name]
        for i, stage in enumerate(STAGES):
            rec["stages"][stage] = {
                key: statistics.median(getattr(run[i], key) for run in runs[name])
                for key in ("wall_s", "cpu_s", "maxrss_mib", "tree_rss_mib")
            }
        total = statistics.median(sum(m.wall_s for m in run) for run in runs[name])
        cpu = statistics.median(sum(m.cpu_s for m in run) for run in runs[name])
        peak = max(v["maxrss_mib"] for v in rec["stages"].values())
        rec |= {"total_wall_s": total, "total_cpu_s": cpu, "peak_rss_mib": peak}
        record["variants"][name] = rec
    if not args.keep:
        shutil.rmtree(run_dir, ignore_errors=True)
    if len(variants) > 1:  # the first variant against each other, run by run: robust to the machine's drift
        base = [sum(m.wall_s for m in run) for run in runs[variants[0][0]]]
        for name, _, _ in variants[1:]:
            ratio = statistics.median(sum(m.wall_s for m in run) / b for run, b in zip(runs[name], base, strict=True))
            record["variants"][name]["total_wall_ratio"] = ratio
            print(
                f"{name} / {variants[0][0]}, total wall time: {ratio:.3f}x (median of the {args.repeats} runs' ratios)"
            )
    floor_s = statistics.median(floors)
    record |= {"read_floor_s": floor_s, "read_floor_runs_s": floors}
    rows = [
        [
            name,
            *(rec["stages"][s]["wall_s"] for s in STAGES),
            rec["total_wall_s"],
            rec["total_cpu_s"],
            rec["peak_rss_mib"],
            max(v["tree_rss_mib"] for v in rec["stages"].values()),
            f"{rec['total_wall_s'] / floor_s:.1f}x",
            f"{rec['metrics']['r2_mean']:.6f}",
        ]
        for name, rec in record["variants"].items()
    ]
    print()
    print(
        f"{args.frames:,} frames, {args.videos:,} videos; median of {args.repeats} run(s); read floor {floor_s:.1f} s "
        f"(median of {len(floors)}, {min(floors):.1f}-{max(floors):.1f}); load average now {load()}"
    )
    print(
        fmt_table(
            [
                "code",
                *(f"{s} s" for s in STAGES),
                "total s",
                "CPU s",
                "peak RSS MiB",
                "peak tree RSS MiB",
                "total / read floor",
                "CV R2",
            ],
            rows,
        )
    )

    if args.dvc:
        drows = []
        for name, src, _ in variants[: 1 + bool(args.baseline_src)]:
            res = run_dvc(args.workdir, data, src)
            drows.append(
                [
                    name,
                    *(res["stages"][s][0] for s in STAGES),
                    res["total"].wall_s,
                    max(r for _, r in res["stages"].values()),
                    res["data_hash_s"],
                ]
            )
            record["variants"][name]["dvc"] = {
                "total_wall_s": res["total"].wall_s,
                "stages": res["stages"],
                "data_hash_s": res["data_hash_s"],
            }
            shutil.rmtree(res["workspace"], ignore_errors=True)
        print()
        print(
            "`dvc repro` in a temporary DVC workspace whose tables DVC has hashed once (`dvc status`, as `dvc add` or a "
            "pull leaves it; that first hash timed apart), stage commands under /usr/bin/time; the total includes "
            "DVC's hashing and caching of the outputs:"
        )
        print(
            fmt_table(
                [
                    "code",
                    *(f"{s} s" for s in STAGES),
                    "dvc repro total s",
                    "peak RSS MiB",
                    "first hash of the tables s",
                ],
                drows,
            )
        )
    if args.json:
        args.json.write_text(json.dumps(record, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
