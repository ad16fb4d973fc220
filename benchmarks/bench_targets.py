"""preprocess.target on synthetic data whose AU baselines follow the person's identity (``aumesh synth
--identity-au-coupling``): AU-field cosine to the truth (median, worst AU), CV R² in the target's own space,
``r2_displacement`` (same space for every target), AU-field reliability, FACS passes, and what each target costs.

    python benchmarks/bench_targets.py [--frames 50000] [--videos 1000] [--coupling 0.15] [--workdir /tmp/aumesh-bench-targets]

The tables and the prepared data are cached in ``--workdir`` (keyed by size, seed and coupling). Time per target:
``statistics`` = deriving the target's per-fold statistics from the one shared pass (what a target adds);
``checks`` = the AU-field reliability (one fit per fold) and the FACS check, which every run now does;
``evaluate`` = the whole evaluation of the configuration (pass, fits, scoring pass, checks).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from aumesh import config
from aumesh.core.schema import AU_COLUMNS
from aumesh.data import tables
from aumesh.pipeline import evaluate as ev
from aumesh.pipeline import prepare
from aumesh.pipeline.evaluate import statistics_pass
from aumesh.pipeline.evaluate.prepared_data import load_prepared
from aumesh.synthetic import tables as synth
from aumesh.synthetic import truth

REPO = Path(__file__).resolve().parents[1]
TARGETS = ("absolute", "neutral", "within", "within_neutral")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=50_000)
    parser.add_argument("--videos", type=int, default=1_000)
    parser.add_argument("--coupling", type=float, default=0.15, help="aumesh synth --identity-au-coupling")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/aumesh-bench-targets"))
    parser.add_argument("--targets", nargs="*", default=list(TARGETS))
    args = parser.parse_args(argv)

    work = args.workdir / f"f{args.frames}_v{args.videos}_s{args.seed}_c{args.coupling:g}"
    data, prepared_dir, truth_path = work / "data", work / "prepared", work / "truth.npz"
    cfg = config.from_dict(config.compose([f"paths.data_dir={data}"], config_dir=REPO / "conf"))
    if not truth_path.exists():
        t = time.perf_counter()
        synth.write_tables(
            data,
            synth.SynthSpec(
                n_frames=args.frames, n_videos=args.videos, seed=args.seed, identity_au_coupling=args.coupling
            ),
            truth_path=truth_path,
        )
        print(f"synth: {time.perf_counter() - t:.1f} s", flush=True)
    if not (prepared_dir / "summary.json").exists():
        t = time.perf_counter()
        prepare.run(tables.discover(data, cfg.data.tables, cfg.data.mesh_npy), cfg, prepared_dir)
        print(f"prepare: {time.perf_counter() - t:.1f} s", flush=True)
    prepared = load_prepared(prepared_dir)
    true = dict(np.load(truth_path))
    fold = ev.video_folds(prepared.videos.count, cfg.cv.n_splits)
    t = time.perf_counter()
    design = statistics_pass.design_statistics(prepared, fold, cfg.cv.n_splits, cfg.data.chunk_rows)
    print(
        f"{prepared.n_frames:,} frames, {len(prepared.video_ids):,} videos, coupling {args.coupling:g}; "
        f"the shared statistics pass: {time.perf_counter() - t:.1f} s\n",
        flush=True,
    )

    header = (
        f"{'target':15} {'cos median':>10} {'cos worst':>15} {'r2 (own)':>9} {'r2_disp':>8} "
        f"{'rel median':>10} {'rel min':>8} {'FACS':>5} {'stats s':>8} {'checks s':>8} {'eval s':>7}"
    )
    print(header + "\n" + "-" * len(header))
    for target in args.targets:
        tcfg = config.from_dict(
            config.compose([f"paths.data_dir={data}", f"preprocess.target={target}"], config_dir=REPO / "conf")
        )
        t = time.perf_counter()
        stats = statistics_pass.accumulate(prepared, tcfg, fold, design=design)
        t_stats = time.perf_counter() - t
        t = time.perf_counter()
        cv, final = ev.cross_validate_and_fit(prepared, tcfg)
        t_eval = time.perf_counter() - t
        t = time.perf_counter()
        ev.au_field_reliability(ev.fit_models(tcfg, stats).alone)
        ev.facs_passes(prepared, final)
        t_checks = time.perf_counter() - t
        cos = truth.au_field_cosines(final.coef, final.feature_columns, true, prepared.reference["reference_anchors"])
        m = cv.metrics()
        worst = int(np.argmin(cos))
        print(
            f"{target:15} {np.median(cos):10.4f} {cos[worst]:8.4f} ({AU_COLUMNS[worst]}) {m['r2_mean']:9.4f} "
            f"{m['r2_displacement_mean']:8.4f} {m['au_reliability_median']:10.4f} {m['au_reliability_min']:8.4f} "
            f"{m['n_aus_facs_pass']:5d} {t_stats:8.2f} {t_checks:8.2f} {t_eval:7.1f}",
            flush=True,
        )
        del stats


if __name__ == "__main__":
    main()
