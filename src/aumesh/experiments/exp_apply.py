"""``aumesh exp apply NAME``: ``dvc exp apply`` only when the experiment's outputs can be checked out.

``dvc exp apply NAME`` writes the experiment's ``dvc.lock``, ``params.yaml`` and ``metrics/`` into the workspace and
then checks its outputs out of DVC's cache. An experiment whose outputs are in neither the local cache nor a remote
(run on another machine and never ``dvc exp push``-ed with its cache, or whose cache was garbage-collected) loses
them: DVC deletes ``release/``, ``build/model`` and ``build/prepared`` and cannot bring them back, and ``dvc
checkout`` afterwards fails too (the workspace's ``dvc.lock`` is now the experiment's). Before DVC touches anything,
:func:`missing_outputs` reads the experiment's ``dvc.lock`` from its git ref (``git show <ref>:dvc.lock``) and looks
every cached output up -- a directory's ``.dir`` manifest and each file in it -- in the local cache and the default
remote (DVC's own object databases: ``dvc.repo.Repo().cache`` and ``Repo().cloud.get_remote_odb()``); when something
is in neither, :func:`apply` refuses in one line naming the outputs and the fixes. The recovery after an apply that
went wrong anyway (``--force``, or plain ``dvc exp apply``) is ``git checkout dvc.lock params.yaml metrics && dvc
checkout`` (README, "Comparing experiments in DVC").
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aumesh.core.errors import UserError

EXPS_REFS = "refs/exps/"
RECOVERY = "git checkout dvc.lock params.yaml metrics && dvc checkout"


class ExperimentOutputsMissing(UserError):
    """``aumesh exp apply`` refused: some of the experiment's outputs are in neither the cache nor the remote."""


@dataclass(frozen=True)
class LockedOutput:
    """One cached output of a ``dvc.lock``: its path, its md5 (``<md5>.dir`` for a folder) and hash name."""

    stage: str
    path: str
    md5: str
    hash_name: str


def _git(root: Path, *args: str) -> str:
    proc = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True)
    if proc.returncode != 0:
        raise UserError(f"git {' '.join(args)} in {root}: {proc.stderr.strip().splitlines()[-1:] or ['failed']}")
    return proc.stdout


def experiment_ref(root: Path, name: str) -> str:
    """The git ref of the experiment ``name`` (its name, as ``dvc exp list`` shows it, or its full ref).

    Raises
    ------
    UserError
        No experiment has that name, or several do (then the full ref is needed).
    """
    if name.startswith(EXPS_REFS):
        return name
    refs = _git(root, "for-each-ref", "--format=%(refname)", EXPS_REFS).split()
    found = [r for r in refs if r.rsplit("/", 1)[-1] == name]
    if not found:
        raise UserError(f"no experiment named {name!r} in {root} (`dvc exp list --all-commits` lists them).")
    if len(found) > 1:
        raise UserError(f"several experiments are named {name!r}: {', '.join(found)}; name one by its ref.")
    return found[0]


def locked_outputs(lock: Mapping[str, Any], in_git: Iterable[str] = ()) -> list[LockedOutput]:
    """The cached outputs a ``dvc.lock`` (loaded) records: every ``outs`` entry with an md5, except the files git
    holds (``in_git``: the ``cache: false`` metrics and plots, committed with the experiment)."""
    tracked = set(in_git)
    out = []
    for stage, spec in sorted((lock.get("stages") or {}).items()):
        for entry in (spec or {}).get("outs") or []:
            if entry.get("md5") and entry["path"] not in tracked:
                out.append(LockedOutput(stage, entry["path"], entry["md5"], entry.get("hash", "md5-dos2unix")))
    return out


def _missing_in(odbs: list, output: LockedOutput) -> str | None:
    """What of ``output`` none of ``odbs`` holds, in words (``"the file"``, ``"its file list"``, ``"3 of 8 files"``),
    or None when all of it is held."""
    from dvc_data.hashfile.hash_info import HashInfo
    from dvc_data.hashfile.tree import Tree

    def held(oid: str) -> bool:
        return any(odb is not None and odb.exists(oid) for odb in odbs)

    is_dir = output.md5.endswith(".dir")
    if not held(output.md5):
        return "its file list" if is_dir else "the file"
    if not is_dir:
        return None
    odb = next(o for o in odbs if o is not None and o.exists(output.md5))
    files = [hi.value for _, _, hi in Tree.load(odb, HashInfo("md5", output.md5)) if hi is not None and hi.value]
    lacking = sum(not held(oid) for oid in files)
    return f"{lacking} of {len(files)} files" if lacking else None


@dataclass(frozen=True)
class OutputsCheck:
    """Where an experiment's cached outputs are: each output with objects in neither the local cache nor the default
    remote (and what of it, in words), the outputs only the remote holds (``dvc pull`` after the apply), and where it looked."""

    missing: list[tuple[LockedOutput, str]]
    remote_only: list[LockedOutput]
    where: str


def missing_outputs(root: Path, ref: str) -> OutputsCheck:
    """Look the cached outputs of the experiment at ``ref`` up in the local cache and the default remote.

    Parameters
    ----------
    root : Path
        The DVC workspace.
    ref : str
        The experiment's git ref (:func:`experiment_ref`).

    Returns
    -------
    OutputsCheck
    """
    import yaml
    from dvc.repo import Repo

    lock = yaml.safe_load(_git(root, "show", f"{ref}:dvc.lock")) or {}
    paths = [e["path"] for s in (lock.get("stages") or {}).values() for e in (s or {}).get("outs") or []]
    in_git = _git(root, "ls-tree", "-r", "--name-only", ref, "--", *paths).split() if paths else []
    with Repo(str(root)) as repo:
        name = repo.config["core"].get("remote")
        where = (
            f"in neither the cache nor remote '{name}' ({repo.config['remote'][name]['url']})"
            if name
            else "not in the cache (and no default DVC remote)"
        )
        missing, remote_only = [], []
        for output in locked_outputs(lock, in_git):
            # DVC 3 outputs (`hash: md5`) live in files/md5/, older ones (md5-dos2unix) in the legacy layout
            local = repo.cache.local if output.hash_name == "md5" else repo.cache.legacy
            if not _missing_in([local], output):
                continue
            remote = repo.cloud.get_remote_odb(name, "exp apply", hash_name=output.hash_name) if name else None
            lacking = _missing_in([local, remote], output)
            if lacking:
                missing.append((output, lacking))
            else:
                remote_only.append(output)
    return OutputsCheck(missing, remote_only, where)


def refusal(name: str, missing: list[tuple[LockedOutput, str]], where: str) -> ExperimentOutputsMissing:
    """The one line :func:`apply` refuses with."""
    listed = ", ".join(f"{o.path} ({o.stage}: {what})" for o, what in missing)
    return ExperimentOutputsMissing(
        f"experiment {name}: {listed} {where}, so `dvc exp apply` would delete them from the workspace "
        f"and `dvc checkout` could not bring them back. Fix: `dvc exp push <git remote> {name}` where it ran, then "
        f"`dvc exp pull <git remote> {name}` here; or run it again here (`dvc exp run -S ...`); or `aumesh exp apply "
        f"{name} --force` (recovery: `{RECOVERY}`)."
    )


def apply(root: str | Path, name: str, force: bool = False, say=print) -> int:
    """Check the experiment ``name``'s outputs (:func:`missing_outputs`), then run ``dvc exp apply name``.

    Parameters
    ----------
    root : Path
        The DVC workspace.
    name : str
        The experiment (``dvc exp list``'s name, or its ref).
    force : bool, default False
        Apply even when outputs are missing (they are deleted; :data:`RECOVERY` restores the workspace).
    say : callable
        Where the ``--force`` warning goes.

    Returns
    -------
    int
        ``dvc exp apply``'s exit status.

    Raises
    ------
    ExperimentOutputsMissing
        Outputs missing and not ``force``.
    """
    root = Path(root)
    ref = experiment_ref(root, name)
    check = missing_outputs(root, ref)
    if check.missing and not force:
        raise refusal(name, check.missing, check.where)
    if check.missing:
        say(f"warning: {refusal(name, check.missing, check.where)}".replace(" Fix: ", " Applying anyway (--force); "))
    dvc = [sys.executable, "-m", "dvc"]
    code = subprocess.run([*dvc, "exp", "apply", ref.rsplit("/", 1)[-1]], cwd=root).returncode
    if check.remote_only:  # dvc exp apply checks out from the cache only (and says it failed for these): pull them
        say(f"{', '.join(o.path for o in check.remote_only)}: only in the remote; `dvc pull`")
        code = subprocess.run([*dvc, "pull"], cwd=root).returncode
    return code
