"""The ``aumesh`` command: DVC stage entry points and user tools.

As DVC's own ``dvc/commands/``, one module per command family, each with its ``add_parser(subparsers)`` beside its
handlers: :mod:`~aumesh.cli.stages` (``compose-params``, ``synth``, ``ingest``, ``prepare``, ``evaluate``,
``release``), :mod:`~aumesh.cli.tools` (``render``, ``predict``, ``view``, ``animate``), :mod:`~aumesh.cli.experiments`
(``sweep``, ``runs``, ``promote``, ``server``), :mod:`~aumesh.cli.info` (``info``, ``--version``); and
:mod:`~aumesh.cli.console` (stderr and logging). This module builds the parser and holds :func:`main`, the one place
an error becomes an exit status, and :func:`run`, the console script and ``python -m aumesh``. ``cli/`` is the only
package that prints and the only importer of ``argparse``; the handlers import the library when they run.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import logging
import os
import signal
import sys
from typing import Any

from aumesh.cli import experiments, info, stages, tools
from aumesh.cli.console import configure_logging, say
from aumesh.cli.info import print_versions

DEBUG_ENV = "AUMESH_DEBUG"


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
    """The ``aumesh`` parser: the global options, then each family's commands in the order ``aumesh --help`` lists."""
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

    info.add_parser(sub)
    stages.add_parser(sub)
    tools.add_parser(sub)
    experiments.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one command. An input, configuration or path error (``UserError``) prints its message and
    returns 2, with the traceback only under ``--debug`` or ``AUMESH_DEBUG=1``; other errors keep theirs."""
    from aumesh.core.errors import UserError

    parser = build_parser()
    args = parser.parse_args(argv)
    if args.version:
        print_versions(verbose=args.verbose > 0)
        return 0
    if args.command is None:
        parser.error("a COMMAND is required (`aumesh --help` lists them; `aumesh --version` prints the version)")
    configure_logging((logging.WARNING, logging.INFO, logging.DEBUG)[min(args.verbose, 2)])
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
        say(f"aumesh {args.command}: error: {err}" + (f"\n{note}" if note else ""))
        return 2
    except KeyboardInterrupt as err:  # Ctrl-C, SIGTERM, DVC gone: cleaned up on the way out (temporaries, run KILLED)
        from aumesh.core.signals import Interrupted, Terminated

        note = _dvc_note(args)
        if debug:
            raise
        if isinstance(err, Interrupted):  # already described (a sweep: how far it got, what was marked KILLED)
            say(f"aumesh {args.command}: {err}" + (f"\n{note}" if note else ""))
            return 128 + err.signum
        why = f"stopped: {err}" if isinstance(err, Terminated) else "interrupted (Ctrl-C)"
        say(f"aumesh {args.command}: {why}; {_kept(args.command)}" + (f"\n{note}" if note else ""))
        return 128 + (signal.SIGTERM if isinstance(err, Terminated) else signal.SIGINT)
    except OSError as err:
        line = _os_error_line(err)  # a full disk or a read-only folder outside the atomic writers
        if line is None or debug:
            raise
        note = _dvc_note(args)
        say(f"aumesh {args.command}: error: {line}" + (f"\n{note}" if note else ""))
        return 2
    except BaseException:  # a bug: the traceback stays; still say how to get DVC's removed outputs back
        note = _dvc_note(args)
        if note:
            say(note)
        raise


def _os_error_line(err: OSError) -> str | None:
    """The one line for a full disk or an unwritable path that reached :func:`main` unnamed (not through the atomic
    writers, which name their folder): the file when the error has one, the mount ``df`` must look at; None for any
    other ``OSError`` (a bug: its traceback stays)."""
    import errno
    import tempfile
    from pathlib import Path

    from aumesh.core.paths import mount_of, recorded
    from aumesh.core.write_errors import NOT_WRITABLE

    if err.errno not in (errno.ENOSPC, errno.EDQUOT, *NOT_WRITABLE):
        return None
    if err.errno in NOT_WRITABLE:
        if not err.filename:
            return None
        folder = recorded(Path(err.filename).parent)
        return (
            f"{recorded(err.filename)}: {err.strerror} (a read-only workspace or folder?). Fix: make {folder}/ "
            f"writable (`ls -ld {folder}` shows its owner and mode; `chmod -R u+w {folder}`) and run again."
        )
    if err.filename:
        folder = recorded(Path(err.filename).parent)
        where = f"while writing {recorded(err.filename)} "
        hint = f"`df -h {folder}`: the filesystem mounted at {mount_of(folder)}"
    else:  # the OS named no file: the workspace's device or the temporary folder's
        tmp = tempfile.gettempdir()
        where = ""
        hint = f"`df -h . {tmp}`: the workspace is on {mount_of('.')}, the temporary folder {tmp} on {mount_of(tmp)}"
    kept = "" if os.environ.get("DVC_STAGE") else ", so the previous ones are intact"  # under DVC: _dvc_note's line
    return (
        f"no space left on the device {where}(outputs are swapped in only when complete{kept}). "
        f"Fix: free space ({hint}) and run again."
    )


#: Exit statuses of a command that was stopped (128 + SIGINT, SIGTERM, SIGHUP)
STOPPED_CODES = frozenset(128 + int(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP))

#: Commands that stop cleanly on SIGTERM (and, under DVC, when DVC dies): the stages and the sweep.
STOPPABLE = ("ingest", "prepare", "evaluate", "release", "sweep")


def _kept(command: str) -> str:
    if command == "evaluate":
        return "nothing was swapped in; its MLflow run is marked KILLED"
    if command in ("ingest", "prepare", "evaluate", "release"):
        # under dvc repro, DVC removed them before the stage ran (not release/: persist): _dvc_note's line says so
        removed = os.environ.get("DVC_STAGE") and command != "release"
        return "nothing was swapped in" + ("" if removed else ", the previous outputs are intact")
    return "nothing was written"


def run() -> None:
    """The ``aumesh`` command (console script and ``python -m aumesh``): :func:`main`, then exit with its status."""
    from aumesh.pipeline.compute.memory import prefer_system_arrow_pool

    prefer_system_arrow_pool()  # before anything imports pyarrow
    code = main()
    if code in STOPPED_CODES:
        # stopped (Ctrl-C, SIGTERM, DVC gone) and already cleaned up on the way out (temporaries removed, the MLflow
        # run KILLED): leave now, not after the compute threads' tasks in flight, which the interpreter's exit would
        # wait for (Dask's thread pool is joined at exit: 10-37 s after DVC was killed, issue 44)
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):
                stream.flush()
        logging.shutdown()
        os._exit(code)
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
