"""The pipeline's commands: ``compose-params`` (conf/ -> params.yaml), ``synth`` (synthetic input tables with a
known truth) and the DVC stages ``check_params``, ``ingest``, ``prepare``, ``evaluate``, ``release``,
``release_family`` (each a one-line
summary of what :mod:`aumesh.stages` did)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

from aumesh.cli.outputs import add_force, refuse_release_path
from aumesh.core.families import PYFEAT_FEATURE

if TYPE_CHECKING:
    from aumesh.config import Config


def _params(args) -> Config:
    from aumesh.config import load_params

    return load_params(args.params)


def _cmd_compose_params(args) -> int:
    from aumesh.config import compose, from_dict, write_params

    refuse_release_path("--out", args.out, force=args.force)
    data = compose(args.overrides, config_dir=args.config_dir)
    from_dict(data)  # validate before writing
    write_params(data, args.out)
    print(f"wrote {args.out} from {args.config_dir}/ {' '.join(args.overrides)}".rstrip())
    return 0


def _cmd_synth(args) -> int:
    from aumesh.synthetic.tables import SynthSpec, realistic_noise_spec, write_tables, write_truth_sigma_u

    refuse_release_path("--out", args.out, force=args.force)
    refuse_release_path("--truth", args.truth, force=args.force)

    fields = dict(
        layout=args.layout,
        reversed_aus=tuple(args.reverse or ()),
        identity_au_coupling=args.identity_au_coupling,
        instrument_noise_sd=args.instrument_noise_sd,
    )
    if args.realistic:
        sd = 0.07 if args.au_noise_sd is None else args.au_noise_sd
        spec = realistic_noise_spec(args.frames, args.videos, args.seed, au_noise_sd=sd, **fields)
    else:
        spec = SynthSpec(args.frames, args.videos, args.seed, au_noise_sd=args.au_noise_sd or 0.0, **fields)
    families = None
    if args.families:
        from aumesh.synthetic.family_truth import family_source

        families = family_source(spec)
    summary = write_tables(args.out, spec, args.truth, families=families)
    if args.truth is not None and spec.au_noise_sd > 0:
        summary["sigma_u"] = str(write_truth_sigma_u(args.truth))
    print(json.dumps(summary, indent=2))
    return 0


def _cmd_ingest(args) -> int:
    from aumesh.stages import ingest

    cfg = _params(args)
    c = ingest.main(cfg)["counts"]
    ambiguous = c.get("frames_ambiguous_faces", 0)
    print(
        f"ingest: {c['frames_out']:,} frames from {c['rows_in']:,} rows of {c['tables_in']:,} tables "
        f"(no face -{c['dropped_no_face']:,}, other faces -{c['dropped_extra_faces']:,} in "
        f"{c['frames_with_several_faces']:,} frames"
        + (f" ({ambiguous:,} ambiguous: faces of about the same size, the video's track followed)" if ambiguous else "")
        + f", converted from normalized units {c['rows_converted_from_normalized']:,}, "
        f"z from Detectorv2's chip {c.get('rows_z_from_chip', 0):,}, from MPDetector's 256-px crop "
        f"{c.get('rows_z_from_crop256', 0):,}) "
        f"-> {cfg.paths.ingested_dir}"
    )
    return 0


def _cmd_prepare(args) -> int:
    from aumesh.stages import prepare

    cfg = _params(args)
    c = prepare.main(cfg)["counts"]
    print(
        f"prepare: kept {c['frames_kept']:,} of {c['frames_in']:,} frames, {c['videos_kept']:,} of {c['videos_in']:,} videos "
        f"(pose filter -{c['dropped_pose']:,}, alignment outliers -{c['dropped_alignment_outliers']:,}) "
        f"-> {cfg.paths.prepared_dir}"
    )
    return 0


def _cmd_evaluate(args) -> int:
    from aumesh.stages import evaluate

    cfg = _params(args)
    m = evaluate.main(cfg)
    print(
        f"evaluate: CV R2 = {m['r2_mean']:.4f} +/- {m['r2_std']:.4f} (folds {' '.join(f'{v:.4f}' for v in m['r2_folds'])}), "
        f"MAE = {m['mae_mean']:.4f}, n_components = {m['n_components']} -> {cfg.paths.model_dir}, {cfg.paths.metrics_file}"
    )
    return 0


def _cmd_check_params(args) -> int:
    from aumesh.stages import check_params

    check_params.main(args.params)
    print(f"check_params: {args.params} sets no compute or tracking value other than conf/'s")
    return 0


def _cmd_release(args) -> int:
    from aumesh.stages import release

    out = release.main(_params(args))
    files = [f for f in out.rglob("*") if f.is_file()]
    print(f"release: {out} ({len(files)} files, {sum(f.suffix == '.png' for f in files)} figures)")
    return 0


def _cmd_release_family(args) -> int:
    from aumesh.stages import release_family

    out = release_family.main(_params(args), args.family)
    files = [f for f in out.rglob("*") if f.is_file()]
    print(f"release_family: {out} ({len(files)} files, {sum(f.suffix == '.png' for f in files)} figures)")
    return 0


def add_parser(subparsers) -> None:
    """Add ``compose-params``, ``synth`` and the stages ``ingest``, ``prepare``, ``evaluate``, ``release``."""
    p = subparsers.add_parser(
        "compose-params", help="compose conf/ (+ Hydra overrides) into params.yaml, as `dvc exp run` does"
    )
    p.add_argument(
        "overrides",
        nargs="*",
        metavar="KEY=VALUE",
        help="Hydra overrides, e.g. model.n_components=40 features=au_pose (default: none, the conf/ defaults)",
    )
    p.add_argument("--config-dir", default="conf", help="the Hydra configuration folder")
    p.add_argument("--out", default="params.yaml", help="the composed configuration file the DVC stages read")
    add_force(p)
    p.set_defaults(func=_cmd_compose_params)

    p = subparsers.add_parser("synth", help="write synthetic frame tables with a known ground truth")
    p.add_argument("--out", required=True, type=Path, help="folder for the parquet tables (created)")
    p.add_argument("--frames", type=int, default=4000, help="number of frames (table rows) in all")
    p.add_argument("--videos", type=int, default=100, help="number of videos (identities) the frames are spread over")
    p.add_argument("--seed", type=int, default=0, help="random seed: same seed, same tables")
    p.add_argument(
        "--layout",
        choices=["columns", "pyfeat"],
        default="columns",
        help="columns: mesh columns x_i, y_i, z_i inside the parquet; pyfeat: py-feat's split layout, "
        "an AU/pose parquet plus an [N, 478, 3] <stem>.npy beside it",
    )
    p.add_argument(
        "--truth", type=Path, default=None, help="also save the ground-truth map (NPZ) here (default: not saved)"
    )
    p.add_argument(
        "--reverse",
        nargs="*",
        default=[],
        metavar="AU",
        help="AUs whose true direction is deliberately reversed, to test the AU-direction check",
    )
    p.add_argument(
        "--identity-au-coupling",
        type=float,
        default=0.0,
        metavar="C",
        help="couple each video's AU baselines to the person's identity shape, as real detectors do "
        "(baseline = C * softplus(resemblance of the identity to the AU's field), e.g. 0.15; default: 0 = off)",
    )
    p.add_argument(
        "--au-noise-sd",
        type=float,
        default=None,
        metavar="SD",
        help="AU detector noise on the recorded AUs (sd, AR(1) 0.7 in time, correlated within AU pairs; the mesh "
        "follows the true AUs); with --truth its within-video covariance is also saved as sigma_u.npy beside the "
        "truth file, for model.eiv.sigma_u (default: 0 = off; 0.07 with --realistic)",
    )
    p.add_argument(
        "--instrument-noise-sd",
        type=float,
        default=0.0,
        metavar="SD",
        help="also write a second detector's AUs on the same frames, AU01_2 ... AU43_2, with their own independent "
        "noise of this sd (for model.eiv.instrument_aus='{au}_2'; default: 0 = not written)",
    )
    p.add_argument(
        "--realistic",
        action="store_true",
        help="the issue-43 preset: co-activated AUs (AU09/AU10 r ~0.9, AU06/AU12, AU01/AU02, AU25/AU24) read by a "
        "noisy detector (--au-noise-sd 0 gives its no-noise control)",
    )
    p.add_argument(
        "--families",
        action="store_true",
        help="also write the 52 MediaPipe blendshapes and 7 emotions (py-feat's names; blendshapes in [0, 1], "
        "emotions a softmax) with a known field each on the mesh, for the blendshape and emotion models; with "
        "--truth their fields are saved too (default: not written, the tables as before)",
    )
    add_force(p)
    p.set_defaults(func=_cmd_synth)

    for name, func, text in (
        (
            "check_params",
            _cmd_check_params,
            "stage: refuse a params.yaml with a scheduler or tracking store of its own",
        ),
        ("ingest", _cmd_ingest, "stage: py-feat's CSV/parquet tables -> clean frame tables"),
        ("prepare", _cmd_prepare, "stage: filter and align the frame tables"),
        ("evaluate", _cmd_evaluate, "stage: cross-validate and fit; log an MLflow run"),
        ("release", _cmd_release, "stage: write the release (NPZ, model card, figures)"),
    ):
        p = subparsers.add_parser(name, help=text)
        p.add_argument(
            "--params",
            default="params.yaml",
            help="the composed configuration to read (`aumesh compose-params` or `dvc exp run` write it)",
        )
        p.set_defaults(func=func)

    # release_family@<family> (dvc.yaml foreach): one family's release in py-feat's format -> releases/<family>/
    p = subparsers.add_parser(
        "release_family", help="stage: write a family's release (py-feat's NPZ, model card, figures) to releases/"
    )
    p.add_argument("family", choices=list(PYFEAT_FEATURE), help="the input family to release")
    p.add_argument(
        "--params",
        default="params.yaml",
        help="the composed configuration to read (`aumesh compose-params` or `dvc exp run` write it)",
    )
    p.set_defaults(func=_cmd_release_family)
