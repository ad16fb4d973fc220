"""The ``aumesh`` command: DVC stage entry points and user tools."""

from __future__ import annotations

import argparse
import contextlib
import gc
import json
import logging
import os
import signal
import sys
from collections.abc import Mapping
from datetime import UTC
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from aumesh.config import Config

DEBUG_ENV = "AUMESH_DEBUG"


def _params(args) -> Config:
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
    from aumesh.synthetic.tables import SynthSpec, write_tables

    spec = SynthSpec(
        n_frames=args.frames,
        n_videos=args.videos,
        seed=args.seed,
        layout=args.layout,
        reversed_aus=tuple(args.reverse or ()),
        identity_au_coupling=args.identity_au_coupling,
    )
    print(json.dumps(write_tables(args.out, spec, args.truth), indent=2))
    return 0


def _cmd_ingest(args) -> int:
    from aumesh.stages import ingest

    cfg = _params(args)
    c = ingest.main(cfg)["counts"]
    print(
        f"ingest: {c['frames_out']:,} frames from {c['rows_in']:,} rows of {c['tables_in']:,} tables "
        f"(no face -{c['dropped_no_face']:,}, other faces -{c['dropped_extra_faces']:,} in "
        f"{c['frames_with_several_faces']:,} frames, converted from normalized units {c['rows_converted_from_normalized']:,}, "
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


def _cmd_release(args) -> int:
    from aumesh.stages import release

    out = release.main(_params(args))
    files = [f for f in out.rglob("*") if f.is_file()]
    print(f"release: {out} ({len(files)} files, {sum(f.suffix == '.png' for f in files)} figures)")
    return 0


def _cmd_render(args) -> int:
    from aumesh.card import render

    return render.main([str(args.npz), "--out", str(args.out)] + (["--cv", str(args.cv)] if args.cv else []))


def _cmd_predict(args) -> int:
    from aumesh.pipeline.predict import predict_table

    out, n = predict_table(args.release, args.table, args.out, args.ignore, strict=args.strict)
    print(f"wrote {n} mesh(es) to {out}")
    return 0


def _cmd_view(args) -> int:
    from aumesh.export import viewer
    from aumesh.model.inference import load_release

    clips = viewer.table_clips(args.clip, args.video, args.fps, args.mesh_units) if args.clip else None
    out = viewer.write_viewer(load_release(args.npz), args.out, source=args.npz.name, clips=clips)
    played = f"; plays {len(clips)} video(s) of {args.clip.name}" if clips else ""
    print(f"wrote {out} (open it in a browser; works offline{played})")
    return 0


def _cmd_animate(args) -> int:
    from aumesh.export.gltf_clip import animate

    summary = animate(
        args.table,
        args.release,
        args.out,
        video=args.video,
        fps=args.fps,
        pose=args.pose,
        smooth_frames=args.smooth,
    )
    print(summary.line())
    return 0


# ------------------------------------------------------------------ versions
#: What ``aumesh --version --verbose`` and ``aumesh info`` list after aumesh itself (distribution names, as pip has them).
VERSION_LIBRARIES = (
    "dvc",
    "mlflow",
    "hydra-core",
    "dask",
    "distributed",
    "numpy",
    "scipy",
    "scikit-learn",
    "pandas",
    "pyarrow",
)


def versions(libraries: tuple[str, ...] = VERSION_LIBRARIES) -> dict[str, str]:
    """``{"aumesh": ..., "python": ..., <dist>: ...}`` from the installed package metadata (``importlib.metadata``).

    A library that is not installed is ``"not installed"``; aumesh without metadata (a source tree on
    ``PYTHONPATH`` only) falls back to ``aumesh.__version__``.
    """
    import platform
    from importlib import metadata

    def one(dist: str) -> str:
        try:
            return metadata.version(dist)
        except metadata.PackageNotFoundError:
            return "not installed"

    out = {"aumesh": one("aumesh")}
    if out["aumesh"] == "not installed":
        from aumesh import __version__

        out["aumesh"] = __version__
    out["python"] = platform.python_version()
    return out | {dist: one(dist) for dist in libraries}


def _print_versions(verbose: bool) -> None:
    found = versions()
    print(f"aumesh {found.pop('aumesh')}")
    if verbose:
        width = max(map(len, found))
        for dist, ver in found.items():
            print(f"  {dist:<{width}}  {ver}")


def _cmd_info(args) -> int:
    _print_versions(verbose=True)
    return 0


# ------------------------------------------------------------------ experiments: sweep, runs, promote
def _tracking_cfg(args) -> dict[str, Any]:
    """The tracking group of the workspace's params.yaml (defaults if absent), ``--experiment`` wins."""
    from aumesh.config import load_params
    from aumesh.core import provenance

    cfg: dict[str, Any] = {}
    with contextlib.suppress(FileNotFoundError, ValueError):
        cfg = dict(load_params(provenance.repo_root() / "params.yaml").tracking.__dict__)
    if getattr(args, "experiment", None):
        cfg["experiment"] = args.experiment
    return cfg


def _parent_id(args, tracking_cfg: Mapping[str, Any]) -> str:
    """The sweep a command is about: ``--sweep ID``, else this clone's latest sweep (never a teammate's)."""
    from aumesh.core.errors import UserError
    from aumesh.tracking import queries

    if args.parent:
        return args.parent
    me = queries.current_owner()
    parent = queries.latest_parent_run(tracking_cfg, workspace=me["workspace"])
    if parent is None:
        raise UserError(
            f"no sweep of this workspace (user {me['user']}, workspace {me['workspace'][:8]}) in experiment "
            f"{tracking_cfg.get('experiment') or 'aumesh'}. Fix: run `aumesh sweep -m ...`, or name a "
            "teammate's sweep with --sweep ID (`aumesh runs --sweeps` lists the team's)"
            + (", or rank everyone's runs with --across" if args.command == "promote" else "")
            + "."
        )
    return parent


ALLOW_FAILURES = "--allow-failures"


def _cmd_sweep(args) -> int:
    from aumesh.experiments import sweep

    allow = ALLOW_FAILURES in args.overrides
    outcome = sweep.run_sweep([a for a in args.overrides if a != ALLOW_FAILURES])
    if not outcome.n_failed:
        return 0
    print(
        f"{outcome.n_failed} of {outcome.n_jobs} configurations failed (errors: `aumesh runs --sweep "
        f"{outcome.parent_run_id}`); "
        + ("exit 0 (--allow-failures)" if allow else f"exit 1 ({ALLOW_FAILURES} keeps 0)"),
        file=sys.stderr,
    )
    return 0 if allow else 1


def _utc(ms: float) -> str:
    from datetime import datetime

    return datetime.fromtimestamp(ms / 1000, tz=UTC).strftime("%Y-%m-%d %H:%M UTC")


def _cmd_runs(args) -> int:
    from aumesh.experiments import leaderboard
    from aumesh.tracking import queries

    tracking_cfg = _tracking_cfg(args)
    if args.sweeps:
        user = queries.current_owner()["user"] if args.mine else args.user
        sweeps = leaderboard.sweeps_table(tracking_cfg, limit=args.limit, user=user)
        print(
            sweeps.to_json(orient="records", indent=2, date_format="iso", double_precision=15)
            if args.json
            else leaderboard.format_sweeps_table(sweeps)
        )
        return 0
    if args.mine or args.user:
        from aumesh.core.errors import UserError

        raise UserError("--mine and --user filter the list of sweeps: `aumesh runs --sweeps --mine`.")
    parent = _parent_id(args, tracking_cfg)
    record = queries.run_record(parent, tracking_cfg)
    children = queries.list_child_runs(parent, tracking_cfg)
    table = leaderboard.runs_table(children, args.metric)
    if args.json:
        print(table.to_json(orient="records", indent=2))
        return 0
    tags = record["tags"]
    n_failed = int((children["status"] != "FINISHED").sum()) if len(children) else 0
    print(
        f"sweep {parent} ({record['status']}, {record['run_name']}, by {record['user'] or '?'}): {len(children)} runs, "
        f"{n_failed} not finished"
        + (f", wall {tags['aumesh.sweep.wall_seconds']} s" if "aumesh.sweep.wall_seconds" in tags else "")
    )
    if tags.get("aumesh.sweep.overrides"):
        print(f"  overrides: {tags['aumesh.sweep.overrides']}")
    print(leaderboard.format_runs_table(table))
    return 0


def _cmd_promote(args) -> int:
    from aumesh.core import provenance
    from aumesh.experiments import promote
    from aumesh.tracking import queries

    tracking_cfg = _tracking_cfg(args)
    root = provenance.repo_root()
    newer = parent = None
    if not args.across:
        parent = _parent_id(args, tracking_cfg)
    if (
        parent is not None and not args.parent
    ):  # your latest sweep: say which, and do not overrule your newer pipeline run
        sweep = queries.run_record(parent, tracking_cfg)
        n_runs = sweep["tags"].get("aumesh.sweep.n_children", "?")
        print(
            f"your latest sweep: {parent} (started {_utc(sweep['start_time'])}, {n_runs} runs, "
            f"swept {sweep['tags'].get('aumesh.sweep.overrides') or 'nothing'}); "
            "--sweep ID promotes another, --across ranks the team's runs (`aumesh runs --sweeps` lists them)"
        )
        if not args.latest:  # only this clone's pipeline runs: a teammate's `dvc exp run` is theirs
            evaluate = queries.latest_evaluate_run(tracking_cfg, workspace=queries.current_owner(root)["workspace"])
            if evaluate and evaluate["start_time"] > sweep["start_time"]:
                newer = evaluate
    record = promote.promote(
        parent,
        root,
        tracking_cfg,
        metric=args.metric,
        target=args.target,
        model_name=args.model_name,
        register=not args.no_register,
        newer_run=newer,
        across=args.across,
        partial=args.partial,
        skip_missing=args.skip_missing,
        say=_say,
    )
    print(json.dumps(record, indent=2, default=str))
    if args.across:
        me = queries.current_owner(root)
        whose = "your own" if record["workspace"] == me["workspace"] else f"{record['user']}'s"
        print(
            f"\nacross the team's runs on this data, {whose} run {record['run_id']} won "
            f"({record['metric']} = {record['value']:.6f}, of sweep {record['parent_run_id']})."
        )
    print(
        "\nwrote conf/experiment/promoted.yaml, params.yaml and promotion.json; now `dvc repro` rebuilds that release."
    )
    return 0


def _cmd_server(args) -> int:
    from aumesh.tracking import server

    cmd = server.server_command(
        args.backend_store_uri,
        args.artifacts_destination,
        args.host,
        args.port,
        args.workers,
        args.allowed_hosts,
        args.mlflow_args,
    )
    print("starting: " + " ".join(cmd[2:]), flush=True)
    os.execve(cmd[0], cmd, server.server_environment())  # the server is this process: Ctrl-C and kill reach it
    return 0  # pragma: no cover - execve does not return


def add_experiment_commands(subparsers) -> None:
    """Add ``sweep``, ``runs`` and ``promote`` to the ``aumesh`` command."""
    from aumesh.core.schema import TARGETS

    p = subparsers.add_parser(
        "sweep",
        add_help=False,
        prefix_chars="\0",
        help="Hydra sweep over conf/ in-process, one MLflow child run per configuration; exits 1 when a configuration "
        "failed, after logging and ranking the rest (--allow-failures: exit 0) "
        "(e.g. `aumesh sweep -m model.n_components=10,40`; `aumesh sweep --help` is Hydra's help)",
    )
    p.add_argument(
        "overrides",
        nargs=argparse.REMAINDER,
        help="Hydra's arguments: -m and KEY=V1,V2 sweeps over conf/ (default: one run of conf/ as it is)",
    )
    p.set_defaults(func=_cmd_sweep)

    for name, func, text in (
        ("runs", _cmd_runs, "table of a sweep's runs, best first; --sweeps lists past sweeps"),
        ("promote", _cmd_promote, "promote a sweep's best run into conf/ (+ model registry alias)"),
    ):
        p = subparsers.add_parser(name, help=text)
        who = p.add_mutually_exclusive_group()
        who.add_argument(
            "--sweep",
            "--parent",
            dest="parent",
            metavar="ID",
            help="the sweep's parent run id, anyone's (default: this workspace's latest sweep)",
        )
        if name == "runs":
            who.add_argument(
                "--latest", action="store_true", help="this workspace's latest sweep (what happens without --sweep)"
            )
            who.add_argument(
                "--sweeps",
                action="store_true",
                help="list past sweeps instead, the team's: id, start, user, workspace, runs, failed, "
                "best run, what they swept",
            )
            p.add_argument("--limit", type=int, default=20, help="how many of the newest sweeps --sweeps lists")
            mine = p.add_mutually_exclusive_group()
            mine.add_argument(
                "--mine",
                action="store_true",
                help="with --sweeps: only your sweeps (your git user.email, else your login)",
            )
            mine.add_argument(
                "--user", default=None, help="with --sweeps: only this user's sweeps (default: everyone's)"
            )
        else:
            who.add_argument(
                "--latest",
                action="store_true",
                help="promote your latest sweep even when a newer evaluate run of this workspace "
                "evaluated another configuration (without it, promote refuses to overrule that run)",
            )
            who.add_argument(
                "--across",
                action="store_true",
                help="rank every finished run on this workspace's data version (DVC hash of data.dvc), "
                "whoever ran it, and say whose won",
            )
        p.add_argument(
            "--metric",
            default=None,
            help="ranking metric (default: r2_mean if all runs share the target, else r2_displacement_mean; "
            "au_reliability_median / au_reliability_min / n_aus_facs_pass rank by AU-field reliability)",
        )
        p.add_argument("--experiment", default=None, help="MLflow experiment (default: tracking.experiment)")
        p.set_defaults(func=func)
        if name == "runs":
            p.add_argument("--json", action="store_true", help="print the table as JSON records")
        else:
            p.add_argument(
                "--target",
                choices=list(TARGETS),
                default=None,
                help="only consider runs with this preprocess.target (default: runs of every target)",
            )
            p.add_argument("--model-name", default=None, help="registered model name (default: aumesh-au-to-mesh)")
            p.add_argument("--no-register", action="store_true", help="do not touch the MLflow model registry")
            p.add_argument(
                "--partial",
                action="store_true",
                help="promote from a sweep that did not finish (interrupted, killed): the best of the runs "
                "that finished, named in the output and promotion.json (without it, refused)",
            )
            p.add_argument(
                "--skip-missing",
                action="store_true",
                help="when the best run's model artifacts were deleted, promote the next best run whose "
                "artifacts exist, and say so (without it, refused naming the run and the path)",
            )

    p = subparsers.add_parser(
        "server",
        help="start a team's MLflow tracking server (database backend, served artifacts); clients set "
        "MLFLOW_TRACKING_URI or aumesh.local.yaml to http://HOST:PORT",
    )
    p.add_argument(
        "--backend-store-uri",
        required=True,
        help="the database: postgresql://USER@DBHOST:5432/DB (password in ~/.pgpass or PGPASSWORD; the "
        "installed driver is added) or sqlite:///PATH",
    )
    p.add_argument(
        "--artifacts-destination",
        required=True,
        help="where the server stores run artifacts: a folder on the server, or s3://... ",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: the lab's network)")
    p.add_argument("--port", type=int, default=5000, help="port to listen on")
    p.add_argument("--workers", type=int, default=2, help="server worker processes")
    p.add_argument(
        "--allowed-hosts",
        default=None,
        help="host names clients use, e.g. mlflow.lab.example:5000 (default: localhost and private IPs)",
    )
    p.add_argument(
        "mlflow_args",
        nargs="*",
        metavar="-- MLFLOW_OPTION",
        help="more `mlflow server` options after `--` (default: none)",
    )
    p.set_defaults(func=_cmd_server)


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Every option's help ends with its default, unless the text already says it (``default: ...``).

    Flags (``store_true``) are off unless given, required options have none: both are left as written.
    """

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if (
            "default" in text
            or any(action.default is v for v in (None, False, argparse.SUPPRESS))
            or action.required
            or not (action.option_strings or action.nargs in ("?", "*"))
        ):
            return text
        default = " ".join(map(str, action.default)) if isinstance(action.default, (list, tuple)) else "%(default)s"
        return f"{text} (default: {default or 'none'})"


class Parser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` with :class:`HelpFormatter`; sub-commands inherit it."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="aumesh",
        description="aumesh: AU (+ head pose) -> MediaPipe FaceMesh, the pipeline's stages "
        "and tools. `aumesh COMMAND --help` lists a command's options and their defaults.",
    )
    parser.add_argument(
        "-v",
        "--verbose",
        action="count",
        default=0,
        help="log the library's progress messages: -v info, -vv debug (default: warnings only)",
    )
    parser.add_argument(
        "--debug",
        action="store_true",
        help=f"show the traceback of input and configuration errors too (or set {DEBUG_ENV}=1)",
    )
    parser.add_argument(
        "--version",
        action="store_true",
        help="print aumesh's version and exit; with -v also python, dvc, mlflow, hydra-core, dask, "
        "numpy and the other libraries that shape results (as `aumesh info`)",
    )
    # not required=True: `aumesh --version` has no command; main() asks for one otherwise
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser(
        "info",
        help="versions of aumesh, python and the libraries that shape results (dvc, mlflow, "
        "hydra-core, dask, numpy, ...), from the installed package metadata",
    )
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser(
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
    p.set_defaults(func=_cmd_compose_params)

    p = sub.add_parser("synth", help="write synthetic frame tables with a known ground truth")
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
    p.set_defaults(func=_cmd_synth)

    for name, func, text in (
        ("ingest", _cmd_ingest, "stage: py-feat's CSV/parquet tables -> clean frame tables"),
        ("prepare", _cmd_prepare, "stage: filter and align the frame tables"),
        ("evaluate", _cmd_evaluate, "stage: cross-validate and fit; log an MLflow run"),
        ("release", _cmd_release, "stage: write the release (NPZ, model card, figures)"),
    ):
        p = sub.add_parser(name, help=text)
        p.add_argument(
            "--params",
            default="params.yaml",
            help="the composed configuration to read (`aumesh compose-params` or `dvc exp run` write it)",
        )
        p.set_defaults(func=func)

    p = sub.add_parser("render", help="render a release NPZ's figures and AU-direction report")
    p.add_argument("npz", type=Path, help="a release NPZ in the card's format (ours or another)")
    p.add_argument(
        "--out", type=Path, required=True, help="folder for the PNGs, au_directions.json and au_directions.md (created)"
    )
    p.add_argument(
        "--cv",
        type=Path,
        default=None,
        help="CV arrays NPZ with r2_per_vertex and vertex_error or the cumulative error curve, "
        "e.g. build/model/cv.npz "
        "(default: none, so no R² and error figures)",
    )
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser(
        "predict",
        help="meshes from a CSV/parquet table of AU (+ pose) rows (py-feat's own output too), with a release NPZ",
    )
    p.add_argument(
        "table",
        type=Path,
        help="CSV or parquet, one row per mesh, columns by name: a whole py-feat table (MPDetector or "
        "Detectorv2; only AU01..AU43, Pitch, Yaw, Roll (radians) and FaceScore are read, all 20 AUs "
        "needed, AUs 0..1), or input columns only (missing AUs are 0; no Pitch, Yaw, Roll: pose 0). "
        "A row without a face (FaceScore 0, or every AU and pose value NaN) gets a NaN mesh and "
        "no_face=True; a row only partly NaN is an error. Pose beyond pi/2 is refused as degrees, "
        "Pitch/Yaw beyond the training range is a warning",
    )
    p.add_argument(
        "--out",
        type=Path,
        required=True,
        help="output file: .npz (meshes (N, 478, 3), no_face (N,)), or .obj / .ply for a one-row table",
    )
    p.add_argument("--release", type=Path, default=Path("release/au_to_mesh_pls.npz"), help="release NPZ")
    p.add_argument(
        "--ignore",
        nargs="*",
        default=[],
        metavar="COLUMN",
        help="table columns to leave out, e.g. Pitch Yaw Roll for frontal meshes (default: none)",
    )
    p.add_argument(
        "--strict",
        action="store_true",
        help="every column (after --ignore) must be an input column, AU01..AU43, Pitch, Yaw, Roll "
        "(default: other columns are ignored)",
    )
    p.set_defaults(func=_cmd_predict)

    p = sub.add_parser("view", help="write an offline interactive viewer (one HTML file) of a release NPZ")
    p.add_argument("npz", type=Path, help="release NPZ, e.g. release/au_to_mesh_pls.npz")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("viewer.html"),
        help="HTML file to write (default: %(default)s); needs three.js from `make tools`",
    )
    p.add_argument(
        "--clip",
        type=Path,
        metavar="TABLE",
        help="embed a py-feat table (CSV, .csv.gz or parquet) to play: the AUs over time beside the recorded mesh "
        "(default: none; the page can still open a CSV itself)",
    )
    p.add_argument("--video", help="with --clip: the one video to embed (default: every video of the table)")
    p.add_argument("--fps", type=float, help="with --clip: the video's frame rate (default: from approx_time, else 25)")
    p.add_argument(
        "--mesh-units",
        choices=("detector", "pixels"),
        default="detector",
        help="with --clip: z of the recorded mesh as the detector writes it, converted to frame pixels "
        "(Detectorv2: z x FaceRectWidth; MPDetector: z x FaceRectWidth / 256), or 'pixels': z already in pixels "
        "(a table rescaled after py-feat), as the ingest's data.mesh_units (default: %(default)s)",
    )
    p.set_defaults(func=_cmd_view)

    p = sub.add_parser(
        "animate",
        help="a video's AUs over time as an animated glTF (.glb): the release's rig with a morph-weight animation",
    )
    p.add_argument(
        "table",
        type=Path,
        help="py-feat's table of a video (CSV, .csv.gz or parquet; MPDetector or Detectorv2): one row per frame "
        "and face; frames without a face are bridged (interpolated up to 0.5 s, held beyond), of several faces "
        "in a frame the largest is used",
    )
    p.add_argument("--out", type=Path, required=True, help="the .glb to write (binary glTF 2.0)")
    p.add_argument("--release", type=Path, default=Path("release/au_to_mesh_pls.npz"), help="release NPZ")
    p.add_argument(
        "--video",
        default=None,
        help="the video to animate when the table holds several (the stem of py-feat's input, e.g. clip01 for "
        "videos/clip01.mp4; default: the table's only video)",
    )
    p.add_argument(
        "--fps",
        type=float,
        default=None,
        help="the video's frame rate; a frame's time is frame / fps (default: from approx_time where it tells, else 25)",
    )
    p.add_argument(
        "--pose",
        action="store_true",
        help="also turn the head by Pitch, Yaw, Roll (a rotation channel, Rotation.from_euler('xyz', ...)); "
        "default: off, the face stays pose-canonical",
    )
    p.add_argument(
        "--smooth",
        type=int,
        default=1,
        metavar="N",
        help="centred moving average over N frames (odd) against detector jitter (default: 1, no smoothing)",
    )
    p.set_defaults(func=_cmd_animate)

    add_experiment_commands(sub)
    return parser


class _StderrHandler(logging.StreamHandler):
    """A handler on whatever ``sys.stderr`` is when a record is written: a handler bound to the stream of its time
    writes into a closed stream once that is replaced (a second ``main()`` in one process, as in the tests)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler.__init__ assigns it
        pass


def _configure_logging(level: int) -> None:
    """``logging.basicConfig`` (the root logger, configured only when nothing configured it), on :class:`_StderrHandler`."""
    root = logging.getLogger()
    if root.handlers:
        return
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root.addHandler(handler)
    root.setLevel(level)


def main(argv: list[str] | None = None) -> int:
    """Run one command. An input, configuration or path error (``UserError``) prints its message and
    returns 2, with the traceback only under ``--debug`` or ``AUMESH_DEBUG=1``; other errors keep theirs."""
    from aumesh.core.errors import UserError

    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        _print_versions(verbose=args.verbose > 0)
        return 0
    if args.command is None:
        parser.error("a COMMAND is required (`aumesh --help` lists them; `aumesh --version` prints the version)")
    _configure_logging((logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)])
    debug = args.debug or os.environ.get(DEBUG_ENV, "").strip() not in ("", "0")
    if args.command in STOPPABLE:
        from aumesh.core.signals import install_stage_signals

        install_stage_signals()  # SIGTERM as Ctrl-C; under DVC, stop when DVC is gone
    try:
        return args.func(args)
    except UserError as err:
        note = _dvc_note(args)
        if debug:
            raise
        _say(f"aumesh {args.command}: error: {err}" + (f"\n{note}" if note else ""))
        return 2
    except KeyboardInterrupt as err:  # Ctrl-C, SIGTERM, DVC gone: cleaned up on the way out (temporaries, run KILLED)
        from aumesh.core.signals import Interrupted, Terminated

        note = _dvc_note(args)
        if debug:
            raise
        if isinstance(err, Interrupted):  # already described (a sweep: how far it got, what was marked KILLED)
            _say(f"aumesh {args.command}: {err}" + (f"\n{note}" if note else ""))
            return 128 + err.signum
        why = f"stopped: {err}" if isinstance(err, Terminated) else "interrupted (Ctrl-C)"
        _say(f"aumesh {args.command}: {why}; {_kept(args.command)}" + (f"\n{note}" if note else ""))
        return 128 + (signal.SIGTERM if isinstance(err, Terminated) else signal.SIGINT)
    except OSError as err:
        import errno

        if err.errno not in (errno.ENOSPC, errno.EDQUOT) or debug:  # a full disk outside the atomic writers (scratch)
            raise
        note = _dvc_note(args)
        where = f" while writing {err.filename}" if err.filename else ""
        _say(
            f"aumesh {args.command}: error: no space left on the device{where}; outputs are swapped in only when "
            f"complete, so the previous ones are intact. Fix: free space (`df -h .`) and run again."
            + (f"\n{note}" if note else "")
        )
        return 2
    except BaseException:  # a bug: the traceback stays; still say how to get DVC's removed outputs back
        note = _dvc_note(args)
        if note:
            _say(note)
        raise


#: Commands that stop cleanly on SIGTERM (and, under DVC, when DVC dies): the stages and the sweep.
STOPPABLE = ("ingest", "prepare", "evaluate", "release", "sweep")


def _kept(command: str) -> str:
    if command == "evaluate":
        return "nothing was swapped in; its MLflow run is marked KILLED"
    if command in ("ingest", "prepare", "evaluate", "release"):
        return "nothing was swapped in, the previous outputs are intact"
    return "nothing was written"


def _say(text: str) -> None:
    """Print to stderr; a reader that is gone (DVC killed, its pipe closed) is no reason for a traceback."""
    try:
        print(text, file=sys.stderr, flush=True)
    except (OSError, ValueError):
        pass


def run() -> None:
    """The ``aumesh`` command (console script and ``python -m aumesh``): :func:`main`, then exit with its status."""
    from aumesh.pipeline.compute_memory import prefer_system_arrow_pool

    prefer_system_arrow_pool()  # before anything imports pyarrow
    code = main()
    # At exit the interpreter's last garbage collections walk every object of the ~2,900 modules the evaluate stage
    # imports (MLflow, SQLAlchemy, scikit-learn): 0.6-0.8 s a stage at any data size. Frozen objects are skipped
    # (gc.freeze); everything is still released by reference counting, atexit handlers run and files are flushed.
    gc.freeze()
    sys.exit(code)


def _dvc_note(args) -> str | None:
    """Under ``dvc repro``: the command that restores the outputs DVC removed before this stage (None otherwise)."""
    if args.command not in ("ingest", "prepare", "evaluate", "release") or not os.environ.get("DVC_STAGE"):
        return None
    from aumesh.stages.common import removed_by_dvc

    return removed_by_dvc(args.command)


if __name__ == "__main__":
    run()
