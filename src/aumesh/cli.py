"""The ``aumesh`` command: DVC stage entry points and user tools."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path


def _params(args) -> "Config":  # noqa: F821
    from aumesh.config import load_params

    return load_params(args.params)


def _cmd_compose_params(args) -> int:
    from aumesh.config import compose, from_dict, write_params

    data = compose(args.overrides, config_dir=args.config_dir)
    from_dict(data)  # validate before writing
    write_params(data, args.out)
    print(f"wrote {args.out} from {args.config_dir}/ {' '.join(args.overrides)}".rstrip())
    return 0


def _cmd_synth(args) -> int:
    from aumesh.synth import SynthSpec, write_tables

    spec = SynthSpec(n_frames=args.frames, n_videos=args.videos, seed=args.seed, layout=args.layout,
                     reversed_aus=tuple(args.reverse or ()))
    print(json.dumps(write_tables(args.out, spec, args.truth), indent=2))
    return 0


def _cmd_prepare(args) -> int:
    from aumesh.stages import prepare_stage

    summary = prepare_stage(_params(args))
    print(json.dumps(summary["counts"], indent=2))
    return 0


def _cmd_evaluate(args) -> int:
    from aumesh.stages import evaluate_stage

    metrics = evaluate_stage(_params(args))
    print(f"CV R2 = {metrics['r2_mean']:.4f} +/- {metrics['r2_std']:.4f}  folds {[round(v, 4) for v in metrics['r2_folds']]}  "
          f"MAE = {metrics['mae_mean']:.4f}")
    return 0


def _cmd_release(args) -> int:
    from aumesh.stages import release_stage

    print(f"release written to {release_stage(_params(args)).resolve()}")
    return 0


def _cmd_render(args) -> int:
    from aumesh import render

    return render.main([str(args.npz), "--out", str(args.out)] + (["--cv", str(args.cv)] if args.cv else []))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="aumesh", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("compose-params", help="compose conf/ (+ Hydra overrides) into params.yaml, as `dvc exp run` does")
    p.add_argument("overrides", nargs="*")
    p.add_argument("--config-dir", default="conf")
    p.add_argument("--out", default="params.yaml")
    p.set_defaults(func=_cmd_compose_params)

    p = sub.add_parser("synth", help="write synthetic frame tables with a known ground truth")
    p.add_argument("--out", required=True, type=Path)
    p.add_argument("--frames", type=int, default=4000)
    p.add_argument("--videos", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--layout", choices=["columns", "pyfeat"], default="columns")
    p.add_argument("--truth", type=Path, default=None, help="also save the ground-truth map (NPZ) here")
    p.add_argument("--reverse", nargs="*", help="AUs whose true direction is deliberately reversed")
    p.set_defaults(func=_cmd_synth)

    for name, func, text in (("prepare", _cmd_prepare, "stage: filter and align the frame tables"),
                             ("evaluate", _cmd_evaluate, "stage: cross-validate and fit; log an MLflow run"),
                             ("release", _cmd_release, "stage: write the release (NPZ, model card, figures)")):
        p = sub.add_parser(name, help=text)
        p.add_argument("--params", default="params.yaml")
        p.set_defaults(func=func)

    p = sub.add_parser("render", help="render a release NPZ's figures and AU-direction report")
    p.add_argument("npz", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--cv", type=Path, default=None)
    p.set_defaults(func=_cmd_render)

    try:  # sweeps, runs and promotion live in aumesh.sweep
        from aumesh import sweep

        sweep.add_commands(sub)
    except ImportError:
        pass
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
