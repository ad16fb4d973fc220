"""The experiment commands: ``sweep`` (a Hydra sweep, one MLflow child run per configuration), ``runs`` (a sweep's
runs, or the team's sweeps), ``promote`` (a sweep's best run into conf/ and the registry), ``exp apply`` (``dvc exp
apply`` once the experiment's outputs are known to be restorable) and ``server`` (a team's MLflow tracking server)."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from collections.abc import Mapping
from datetime import UTC
from typing import Any

from aumesh.cli.console import say


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


def _check_tracking(tracking_cfg: Mapping[str, Any], consequence: str = "nothing was run") -> dict[str, Any]:
    """The tracking store checked before the command does anything (one line, exit 2, naming its URI and where it came
    from: :func:`aumesh.tracking.mlflow_store.check_tracking`); returns ``tracking_cfg``."""
    from aumesh.tracking import mlflow_store

    mlflow_store.check_tracking(tracking_cfg, consequence)
    return dict(tracking_cfg)


def _sweep_tracking_cfg(overrides: list[str]) -> dict[str, Any]:
    """The tracking group a sweep composes: params.yaml's (from conf/), with the sweep's own ``tracking.KEY=VALUE``
    overrides (one value each: a tracking key is never swept)."""
    import yaml

    cfg = _tracking_cfg(argparse.Namespace())
    for item in overrides:
        key, sep, value = item.lstrip("+").partition("=")
        if sep and key.startswith("tracking.") and "," not in value:
            with contextlib.suppress(yaml.YAMLError):
                cfg[key.removeprefix("tracking.")] = yaml.safe_load(value)
    return cfg


def _parent_id(args, tracking_cfg: Mapping[str, Any]) -> str:
    """The sweep a command is about: ``--sweep ID``, else this clone's latest sweep (never a teammate's)."""
    from aumesh.core.errors import UserError
    from aumesh.tracking import queries

    if args.parent:
        return args.parent
    me = queries.current_owner()
    parent = queries.latest_parent_run(tracking_cfg, workspace=me["workspaces"])
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
    import warnings

    from aumesh.experiments import sweep

    allow = ALLOW_FAILURES in args.overrides
    tracking_cfg = _sweep_tracking_cfg(args.overrides)
    if not {"--help", "-h", "--cfg", "-c", "--info", "--hydra-help"} & set(args.overrides):  # Hydra's, no runs
        _check_tracking(tracking_cfg)
    with warnings.catch_warnings():
        # a server lost mid-sweep: Hydra turns the sweep's end (its parent run) into a warning; the line below says it
        warnings.filterwarnings("ignore", r"Callback SweepCallback\.\w+ raised TrackingServerError", UserWarning)
        outcome = sweep.run_sweep([a for a in args.overrides if a != ALLOW_FAILURES])
    if not outcome.n_failed:
        return 0
    # configurations failed: because the server went away? then that is the one line (exit 2), not "see aumesh runs"
    _check_tracking(
        tracking_cfg,
        f"{outcome.n_failed} of {outcome.n_jobs} configurations of the sweep failed (its runs left RUNNING are marked "
        "KILLED by the next run on this machine)",
    )
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

    tracking_cfg = _check_tracking(_tracking_cfg(args))
    _finish_promotion()
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
    table = leaderboard.runs_table(children, args.metric, family=args.family)
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


def _finish_promotion() -> None:
    """A promotion of this workspace killed half-way is completed or rolled back, in one line
    (:mod:`aumesh.experiments.promotion_journal`; ``aumesh promote`` does it itself)."""
    from aumesh.core import provenance
    from aumesh.experiments import promotion_journal

    try:
        root = provenance.repo_root()
    except (FileNotFoundError, ValueError):  # outside a workspace: no promotion to finish
        return
    try:
        promotion_journal.recover(root, say=say)
    except promotion_journal.PromotionBusy:  # a promotion running now, not an interrupted one: only listing here
        pass


def _cmd_promote(args) -> int:
    from aumesh.core import provenance
    from aumesh.experiments import promote
    from aumesh.tracking import queries

    tracking_cfg = _check_tracking(_tracking_cfg(args))
    root = provenance.repo_root()
    newer = parent = None
    family = None if args.family in (None, "au") else args.family
    if args.run and (args.parent or args.across):
        from aumesh.core.errors import UserError

        raise UserError(f"run {args.run} is named: --sweep and --across choose among runs. Fix: drop one of them.")
    if not args.across and not args.run:
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
            evaluate = queries.latest_evaluate_run(
                tracking_cfg, workspace=queries.current_owner(root)["workspaces"], family=family or "au"
            )
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
        say=say,
        family=family,
        run_id=args.run,
    )
    print(json.dumps(record, indent=2, default=str))
    if args.across:
        me = queries.current_owner(root)
        whose = "your own" if record["workspace"] in me["workspaces"] else f"{record['user']}'s"
        print(
            f"\nacross the team's runs on this data, {whose} run {record['run_id']} won "
            f"({record['metric']} = {record['value']:.6f}, of sweep {record['parent_run_id']})."
        )
    if family:
        print(
            f"\nwrote families.{family} into conf/experiment/promoted.yaml and promotion.json (the AU promotion and "
            f"the other families' as they were), and params.yaml; now `dvc repro` rebuilds the {family} release."
        )
        return 0
    print(
        "\nwrote conf/experiment/promoted.yaml, params.yaml and promotion.json; now `dvc repro` rebuilds that release."
    )
    return 0


def _cmd_exp_apply(args) -> int:
    from aumesh.core import provenance
    from aumesh.experiments import exp_apply

    return exp_apply.apply(provenance.repo_root(), args.name, force=args.force, say=say)


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


def add_parser(subparsers) -> None:
    """Add ``sweep``, ``runs``, ``promote``, ``exp apply`` and ``server`` to the ``aumesh`` command."""
    from aumesh.core.families import FAMILIES
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
        p.add_argument(
            "--family",
            choices=list(FAMILIES),
            default=None,
            help=(
                "only this input family's runs (default: every family's; runs are always ranked within their "
                "family: an emotion model's R² and an AU model's answer different questions)"
                if name == "runs"
                else "promote this input family's model (its best run, into families.<family> of "
                "conf/experiment/promoted.yaml and promotion.json, registered as aumesh-<family>); the AU "
                "promotion and the other families' are left as they are (default: au, the AU model)"
            ),
        )
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
            p.add_argument(
                "run",
                nargs="?",
                default=None,
                metavar="RUN",
                help="promote this run (FINISHED, of the --family promoted) instead of the best of a sweep "
                "(default: the best run of the sweep)",
            )
            p.add_argument(
                "--model-name",
                default=None,
                help="registered model name (default: aumesh-au-to-mesh; with --family F: aumesh-F)",
            )
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

    p = subparsers.add_parser("exp", help="DVC experiments, guarded: `aumesh exp apply NAME`")
    actions = p.add_subparsers(dest="exp_command", required=True, metavar="ACTION")
    apply = actions.add_parser(
        "apply",
        help="`dvc exp apply NAME`, refused (exit 2) when an output of the experiment is in neither DVC's cache nor "
        "the default remote (dvc exp apply would delete it from the workspace)",
    )
    apply.add_argument("name", help="the experiment, as `dvc exp list` names it (or its refs/exps/... ref)")
    apply.add_argument(
        "--force",
        action="store_true",
        help="apply even so (the missing outputs are deleted; `git checkout dvc.lock params.yaml metrics && dvc "
        "checkout` restores the workspace)",
    )
    apply.set_defaults(func=_cmd_exp_apply)

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
