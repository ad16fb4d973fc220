"""The evaluate stage's families (issue 46): what fitting the blendshape and emotion models beside the AU model costs,
and what one shared statistics pass saves over a pass per model.

    python benchmarks/bench_families.py [--frames 344418] [--videos 9978] [--repeats 3] [--workdir /tmp/bench46]

Three variants, side by side, each run ``--repeats`` times in a fresh process (``python bench_families.py --variant
...``; its wall time excludes the imports, its peak RSS is the process's ``ru_maxrss``), on the same prepared data:

* ``au``: the AU model only (the stage with its families' fits skipped: :func:`aumesh.pipeline.evaluate.
  cross_validate_and_fit` of ``features``, the pass of the AU design alone);
* ``shared``: the AU model and every ``families.<f>`` model from ONE statistics pass over the union of their designs
  (:class:`aumesh.pipeline.evaluate.SharedPass`, as the stage runs them);
* ``separate``: the same fits, each from a statistics pass of its own design (what sharing saves).

Each fit also streams its own scoring pass (pass B: MAE and the per-frame errors), whatever the variant. MLflow is
off (the fits, not the tracking store, are measured). The tables (``aumesh synth --families``) and the prepared data
(``aumesh ingest``, ``aumesh prepare``) are cached in ``--workdir``, keyed by size, and reused when present.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
AUMESH = [sys.executable, "-m", "aumesh"]
VARIANTS = ("au", "shared", "separate")


def workspace(workdir: Path, frames: int, videos: int, seed: int) -> Path:
    """A workspace with the family tables ingested and prepared (built once, reused when ``build/prepared`` is
    complete)."""
    ws = workdir / f"f{frames}_v{videos}_s{seed}"
    if (ws / "build/prepared/summary.json").exists():
        return ws
    ws.mkdir(parents=True, exist_ok=True)
    env = os.environ | {"PYTHONPATH": str(REPO / "src")}
    params = ws / "params.yaml"
    run = dict(cwd=ws, env=env, check=True)
    compose = ["compose-params", "--config-dir", str(REPO / "conf"), "--out", str(params), "tracking.enabled=false"]
    subprocess.run([*AUMESH, *compose], **run)
    if not (ws / "data").exists():
        t = time.perf_counter()
        synth = ["synth", "--out", "data", "--frames", str(frames), "--videos", str(videos), "--seed", str(seed)]
        subprocess.run([*AUMESH, *synth, "--families"], **run)
        print(f"synth: {time.perf_counter() - t:.0f} s", flush=True)
    for stage in ("ingest", "prepare"):
        t = time.perf_counter()
        subprocess.run([*AUMESH, stage, "--params", str(params)], **run)
        print(f"{stage}: {time.perf_counter() - t:.0f} s", flush=True)
    return ws


def run_variant(variant: str, ws: Path) -> dict:
    """One variant in this process: its wall seconds (after the imports), statistics passes and peak RSS (MiB)."""
    from aumesh import config
    from aumesh.pipeline import compute
    from aumesh.pipeline import evaluate as ev
    from aumesh.pipeline.evaluate import statistics_pass
    from aumesh.pipeline.evaluate.prepared_data import load_prepared, workers_check
    from aumesh.stages.evaluate import family_configs

    os.chdir(ws)
    cfg = config.load_params(ws / "params.yaml")
    families = family_configs(cfg)
    passes = []
    original = statistics_pass.design_statistics

    def counted(*args, **kwargs):
        passes.append(1)
        return original(*args, **kwargs)

    statistics_pass.design_statistics = counted
    ev.design_statistics = counted  # SharedPass's reference
    t0 = time.perf_counter()
    prepared = load_prepared(cfg.paths.prepared_dir)
    r2 = {}
    if variant == "au":
        cv, _ = ev.cross_validate_and_fit(prepared, cfg)
        r2["au"] = cv.metrics()["r2_mean"]
    elif variant == "shared":
        shared = ev.SharedPass([f.features.name for _, f, _ in families])
        for family, fcfg in (("au", cfg), *((name, f) for name, f, _ in families)):
            cv, _ = ev.cross_validate_and_fit(prepared, fcfg, shared)
            r2[family] = cv.metrics()["r2_mean"]
    else:
        for family, fcfg in (("au", cfg), *((name, f) for name, f, _ in families)):
            with compute.engine(fcfg.compute, **workers_check(prepared)):
                fold = ev.video_folds(prepared.videos.count, fcfg.cv.n_splits)
                stats = statistics_pass.accumulate(prepared, fcfg, fold)  # a pass of this design alone
                cv, _ = ev.cross_validate_and_fit_from_statistics(prepared, fcfg, stats)
            r2[family] = cv.metrics()["r2_mean"]
    wall = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"variant": variant, "wall_s": wall, "passes": len(passes), "maxrss_mib": rss, "r2": r2,
            "frames": prepared.n_frames}  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=344_418)
    parser.add_argument("--videos", type=int, default=9_978)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/bench46"))
    parser.add_argument("--variant", choices=VARIANTS, help=argparse.SUPPRESS)  # one run, in its own process
    parser.add_argument("--workspace", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.variant:
        print(json.dumps(run_variant(args.variant, args.workspace)))
        return

    ws = workspace(args.workdir, args.frames, args.videos, args.seed)
    env = os.environ | {"PYTHONPATH": str(REPO / "src")}
    runs: dict[str, list[dict]] = {v: [] for v in VARIANTS}
    for _ in range(args.repeats):  # interleaved, so a change of the machine's load spreads over the variants
        for variant in VARIANTS:
            out = subprocess.run(
                [sys.executable, __file__, "--variant", variant, "--workspace", str(ws)],
                env=env, check=True, capture_output=True, text=True,
            )  # fmt: skip
            runs[variant].append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(f"  {variant}: {runs[variant][-1]['wall_s']:.1f} s", flush=True)

    med = {v: statistics.median(r["wall_s"] for r in rs) for v, rs in runs.items()}
    frames = runs["au"][0]["frames"]
    print(f"\n{frames:,} frames, {args.videos:,} videos; medians of {args.repeats}; load {os.getloadavg()[0]:.1f}")
    header = f"{'variant':10} {'models':>6} {'passes':>6} {'wall s':>8} {'x au':>6} {'peak RSS MiB':>13}  r2_mean"
    print(header + "\n" + "-" * (len(header) + 30))
    for v, rs in runs.items():
        r2 = " ".join(f"{k}={x:.3f}" for k, x in rs[0]["r2"].items())
        rss = max(r["maxrss_mib"] for r in rs)
        print(
            f"{v:10} {len(rs[0]['r2']):6d} {rs[0]['passes']:6d} {med[v]:8.1f} {med[v] / med['au']:6.2f} {rss:13.0f}  {r2}"
        )
    print(f"\nsharing the pass: separate / shared = {med['separate'] / med['shared']:.2f}x; "
          f"the families add {(med['shared'] - med['au']) / med['au']:.0%} to the AU-only evaluation")  # fmt: skip


if __name__ == "__main__":
    main()
