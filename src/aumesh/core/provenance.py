"""Provenance helpers: where the workspace is, which code and data a run used.

Nothing here runs at import time; every function is cheap and side-effect free
(``git`` is invoked as a subprocess only by :func:`git_commit`).

DVC queued / temporary experiments (researched against DVC 3.67.1)
------------------------------------------------------------------
``dvc exp run --queue`` followed by ``dvc queue start`` (Celery queue) and
``dvc exp run --temp`` (standalone temp-dir queue) do **not** run stages in the
workspace. ``dvc/repo/experiments/executor/local.py::TempDirExecutor`` creates a
fresh directory with ``mkdtemp(dir=<wdir or repo.tmp_dir/"exps">)`` where
``repo.tmp_dir`` is ``<workspace>/.dvc/tmp``; so stages run in

* ``<workspace>/.dvc/tmp/exps/tmpXXXXXXXX/``            (``dvc queue start``)
* ``<workspace>/.dvc/tmp/exps/standalone/tmpXXXXXXXX/`` (``dvc exp run --temp``)

The copy is a brand-new Git repository (``dulwich`` init) into which DVC pushes
the experiment refs, checks out ``EXEC_HEAD`` detached (the workspace HEAD at
queue time) and applies the queued changes (e.g. ``-S`` param edits) *without
committing*; the working tree of the copy is therefore dirty by design, it has
its own ``.git`` and ``dvc.yaml``, and the whole directory is removed after the
run. Anything written relative to the current directory (``./mlflow.db``,
``./mlruns``) is lost, which is why the workspace root must be recovered from the
path.

Environment variables set for stage commands
(``dvc/repo/experiments/queue/base.py::_stash_exp`` -> ``run_env``, applied in
``dvc/stage/run.py::prepare_kwargs``):

* ``DVC_EXP_BASELINE_REV`` -- full SHA of the baseline commit of the experiment.
* ``DVC_EXP_NAME`` -- the experiment name (given with ``-n`` or generated).
* ``DVC_ROOT`` -- for queued/temp runs explicitly overridden to the *parent*
  (workspace) repo root, "not an executor tempdir root" (DVC source comment);
  for plain ``dvc repro`` it is the repo root as well.
* ``DVC_STAGE`` -- the stage address, set for every stage command.

Checked end to end with DVC 3.67.1 on a scratch repo (``dvc exp run --temp -S``
and ``dvc exp run --queue -S`` + ``dvc queue start``): the stage ran in
``<ws>/.dvc/tmp/exps/standalone/tmpenfb26ty`` resp. ``<ws>/.dvc/tmp/exps/tmpqx_n7hh8``
with ``DVC_ROOT=<ws>``, ``DVC_EXP_BASELINE_REV=<HEAD sha>``, ``DVC_EXP_NAME`` and
``DVC_STAGE`` set; ``git rev-parse HEAD`` in the copy gave the baseline and
``git status --porcelain`` showed ``M params.yaml``, ``A dvc.lock``,
``?? .gitignore``; :func:`repo_root` returned ``<ws>`` and the MLflow run landed in
``<ws>/mlflow.db``.

These variables are only present inside stage commands run by DVC, and the
queue does not forward arbitrary variables from the calling shell (DVC issue
#10464), so code must not rely on e.g. ``MLFLOW_TRACKING_URI`` being inherited by
queued runs.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from aumesh.core.git import run_git as _git

#: Path fragment under which DVC creates temporary copies of the repository.
DVC_EXPS_MARKER = "/.dvc/tmp/exps/"

#: Distributions reported by :func:`library_versions` (distribution names).
_LIBRARIES = (
    "numpy",
    "scipy",
    "scikit-learn",
    "pandas",
    "pyarrow",
    "mlflow",
    "dvc",
    "hydra-core",
)


def _workspace_from_temp_copy(path: Path) -> Path | None:
    """Return the workspace root if *path* lies inside a DVC temp copy, else None."""
    text = path.as_posix()
    probe = text if text.endswith("/") else text + "/"
    idx = probe.find(DVC_EXPS_MARKER)
    if idx < 0:
        return None
    return Path(probe[:idx] or "/")


def in_dvc_temp_copy(start: Path | None = None) -> bool:
    """Whether *start* (default: the current directory) is inside a DVC temp copy.

    Parameters
    ----------
    start : Path, optional
        Directory to test; defaults to :func:`os.getcwd`.

    Returns
    -------
    bool
        True when the absolute path contains ``/.dvc/tmp/exps/``.
    """
    path = Path(start) if start is not None else Path.cwd()
    return _workspace_from_temp_copy(path.absolute()) is not None


def repo_root(start: Path | None = None) -> Path:
    """Return the *workspace* root of the project.

    Resolution order:

    1. If *start* (default: the current directory) is inside a DVC temporary
       copy, i.e. its absolute path contains ``/.dvc/tmp/exps/`` (queued
       experiments run by ``dvc queue start`` and ``dvc exp run --temp``; see the
       module docstring), the workspace root is the part of the path before
       ``/.dvc/tmp/exps/``. Checked first because the copy has its own ``.git``
       and ``dvc.yaml`` and would otherwise be mistaken for the root.
    2. Otherwise the nearest ancestor (including *start*) containing
       ``dvc.yaml`` or ``.git``.
    3. Otherwise, if ``start`` is None and the ``DVC_ROOT`` environment variable
       (set by DVC for every stage command, pointing at the workspace even for
       queued runs) names an existing directory, that directory.

    Parameters
    ----------
    start : Path, optional
        Where to start looking; defaults to the current working directory.

    Returns
    -------
    Path
        Absolute path of the workspace root.

    Raises
    ------
    FileNotFoundError
        When no root can be found; the message names the start directory and the fix.
    """
    origin = Path(start) if start is not None else Path.cwd()
    origin = origin.expanduser().absolute()
    for candidate in (origin, origin.resolve()):
        ws = _workspace_from_temp_copy(candidate)
        if ws is not None:
            return ws
    here = origin.resolve()
    for directory in (here, *here.parents):
        if (directory / "dvc.yaml").exists() or (directory / ".git").exists():
            return directory
    env_root = os.environ.get("DVC_ROOT")
    if start is None and env_root and Path(env_root).is_dir():
        root = Path(env_root).absolute()
        return _workspace_from_temp_copy(root) or root
    raise FileNotFoundError(
        f"Cannot find the aumesh workspace root from {origin}: no ancestor contains "
        "'dvc.yaml' or '.git' and it is not inside '<workspace>/.dvc/tmp/exps/'. "
        "Run from inside the aumesh checkout (or pass start=<path inside it>)."
    )


def dvc_written_paths(directory: Path | str) -> list[str]:
    """What DVC itself rewrites in *directory*: ``dvc.lock`` and every stage output it records.

    ``dvc repro`` rewrites ``dvc.lock`` (and with ``core.autostage`` stages it) and the git-tracked
    outputs declared ``cache: false`` (the metrics and plot data); cached outputs are git-ignored
    anyway. None of that is an uncommitted source, config or data change.

    Parameters
    ----------
    directory : Path or str
        The workspace (or DVC temp copy) whose ``dvc.lock`` is read.

    Returns
    -------
    list of str
        ``"dvc.lock"`` followed by the ``outs`` paths of every stage in ``dvc.lock`` (relative to
        *directory*); just ``["dvc.lock"]`` when there is no readable lock file.
    """
    import yaml

    paths = ["dvc.lock"]
    try:
        doc = yaml.safe_load((Path(directory) / "dvc.lock").read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError):
        return paths
    stages = doc.get("stages") if isinstance(doc, Mapping) else None
    for stage in (stages or {}).values():
        for out in (stage or {}).get("outs") or []:
            if isinstance(out, Mapping) and out.get("path"):
                paths.append(str(out["path"]))
    return paths


def git_commit(root: Path | str) -> dict[str, Any]:
    """Describe the code version a run used; never raises.

    Parameters
    ----------
    root : Path or str
        Workspace root (see :func:`repo_root`).

    Returns
    -------
    dict
        ``commit`` : str or None
            Full SHA. Inside a DVC experiment (``DVC_EXP_BASELINE_REV`` set, which
            DVC does for queued, temp and workspace ``dvc exp run``) this is the
            experiment's baseline commit, not whatever the workspace HEAD is now.
        ``dirty`` : bool
            Uncommitted source, config or data changes (tracked or untracked,
            ``git status --porcelain``) in the tree the code actually runs from:
            the DVC temp copy when the current directory is one (dirty whenever
            the experiment changed params, by design), else *root*. What DVC
            itself rewrites (:func:`dvc_written_paths`: ``dvc.lock``, the metrics
            and plot files) does not count. True when the tree exists but its
            status could not be read; False when git is unavailable.
        ``branch`` : str or None
            Current branch of *root*; None when detached or unknown.
        ``dvc_exp_name`` : str or None
            ``DVC_EXP_NAME`` when running as a DVC experiment.
        ``source`` : str
            ``"git"``, ``"dvc-experiment"`` (baseline from the env var) or
            ``"unavailable"`` (no git, not a repository, ...).
    """
    root = Path(root)
    cwd = Path.cwd()
    exec_dir = cwd if in_dvc_temp_copy(cwd) else root
    baseline = os.environ.get("DVC_EXP_BASELINE_REV") or None

    head = _git(["rev-parse", "HEAD"], exec_dir)
    status = _git(
        ["status", "--porcelain", "--", ".", *(f":(exclude){p}" for p in dvc_written_paths(exec_dir))], exec_dir
    )
    branch = _git(["rev-parse", "--abbrev-ref", "HEAD"], root)
    if branch == "HEAD":
        branch = None

    commit = baseline or head
    # A repository whose status could not be read (timeout, ...) is reported dirty:
    # claiming a clean tree we did not see would be wrong provenance.
    dirty = bool(status) if status is not None else head is not None
    if baseline:
        source = "dvc-experiment"
    elif head:
        source = "git"
    else:
        source = "unavailable"
    return {
        "commit": commit,
        "dirty": dirty,
        "branch": branch or None,
        "dvc_exp_name": os.environ.get("DVC_EXP_NAME") or None,
        "source": source,
    }


USER_ENV = "AUMESH_USER"


def user_identity(root: Path | str | None = None) -> str:
    """Who runs this: ``$AUMESH_USER``, else git's ``user.email`` in *root* (a teammate's commits name them so too),
    else the login name, else ``"unknown"``; never raises."""
    if os.environ.get(USER_ENV, "").strip():
        return os.environ[USER_ENV].strip()
    email = _git(["config", "user.email"], Path(root) if root is not None else Path.cwd())
    if email:
        return email
    import getpass

    try:
        return getpass.getuser()
    except Exception:  # no user in some containers
        return "unknown"


def workspace_id(root: Path | str) -> str:
    """A stable id of this clone (16 hex digits), kept in its git folder: the same after a change of the remote URL's
    spelling or a move, another for a copy (:mod:`aumesh.core.workspace_id`). Stable across runs, commits and DVC
    temporary copies (they resolve to the workspace, :func:`repo_root`)."""
    from aumesh.core import workspace_id as ids

    return ids.workspace_id(root)


def workspace_ids(root: Path | str) -> list[str]:
    """:func:`workspace_id` and the ids this clone's runs were tagged with before
    (:func:`aumesh.core.workspace_id.workspace_ids`): what a query for "this clone's runs" matches."""
    from aumesh.core import workspace_id as ids

    return ids.workspace_ids(root)


def data_digest(root: Path | str, dvc_file: str = "data.dvc") -> dict[str, Any]:
    """Read the DVC hash of the tracked data from a ``.dvc`` file.

    Parameters
    ----------
    root : Path or str
        Workspace root; *dvc_file* is resolved against it unless absolute.
    dvc_file : str, default "data.dvc"
        The ``.dvc`` file written by ``dvc add data``.

    Returns
    -------
    dict
        ``md5`` (e.g. ``"3f2a...9c.dir"`` for a directory), ``size`` (bytes or
        None), ``nfiles`` (int or None), ``path`` (as recorded), ``hash`` (hash
        algorithm name, e.g. ``"md5"``) and ``dvc_file`` (the file read, relative to *root* when inside it).

    Raises
    ------
    FileNotFoundError
        When the ``.dvc`` file does not exist (fix: ``dvc add data``).
    ValueError
        When the file is not valid YAML or lacks ``outs[0].md5``.
    """
    import yaml

    path = Path(dvc_file)
    if not path.is_absolute():
        path = Path(root) / path
    if not path.is_file():
        raise FileNotFoundError(
            f"DVC data file not found: {path}. Track the data with `dvc add data` "
            "(or `dvc pull` to fetch it) and commit the resulting .dvc file."
        )
    try:
        doc = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as exc:
        raise ValueError(f"{path} is not valid YAML ({exc}); regenerate it with `dvc add data`.") from exc
    outs = doc.get("outs") if isinstance(doc, Mapping) else None
    if not outs or not isinstance(outs, list) or not isinstance(outs[0], Mapping):
        raise ValueError(f"{path} has no 'outs' list; regenerate it with `dvc add data`.")
    out = outs[0]
    md5 = out.get("md5")
    if not md5:
        raise ValueError(
            f"{path}: key 'outs[0].md5' is missing (data not hashed yet?); run `dvc add data` "
            "or `dvc commit` to record the hash."
        )
    return {
        "md5": str(md5),
        "size": out.get("size"),
        "nfiles": out.get("nfiles"),
        "path": out.get("path"),
        "hash": out.get("hash", "md5"),
        "dvc_file": shareable_location(str(path.absolute()), [Path(root)]),
    }


def library_versions() -> dict[str, str | None]:
    """Versions of the libraries that shape results, plus Python and aumesh.

    Returns
    -------
    dict
        Distribution name -> version string (None when not installed), with keys
        numpy, scipy, scikit-learn, pandas, pyarrow, mlflow, dvc, hydra-core,
        python and aumesh.
    """
    from importlib import metadata

    versions: dict[str, str | None] = {}
    for dist in _LIBRARIES:
        try:
            versions[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            versions[dist] = None
    versions["python"] = platform.python_version()
    try:
        versions["aumesh"] = metadata.version("aumesh")
    except metadata.PackageNotFoundError:
        from aumesh import __version__

        versions["aumesh"] = __version__
    return versions


def _plain(value: Any) -> Any:
    """Convert mappings/sequences (incl. OmegaConf containers) to dict/list recursively."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)) or (
        isinstance(value, Sequence) and not isinstance(value, (str, bytes, bytearray))
    ):
        return [_plain(v) for v in value]
    if hasattr(value, "tolist") and callable(value.tolist):  # numpy scalars and arrays
        return _plain(value.tolist()) if hasattr(value, "shape") else value
    return value


def flatten(cfg: Mapping[str, Any], sep: str = ".") -> dict[str, Any]:
    """Flatten a nested config into ``{"a.b.c": scalar}`` for MLflow params.

    Parameters
    ----------
    cfg : Mapping
        Nested mapping (plain dict or OmegaConf ``DictConfig``; resolve
        interpolations first, e.g. ``OmegaConf.to_container(cfg, resolve=True)``).
    sep : str, default "."
        Separator between nested keys.

    Returns
    -------
    dict
        Flat mapping whose values are str, int, float, bool or None. Lists and
        tuples become JSON strings (``[10, 9, 8]``); empty mappings become ``"{}"``;
        other objects become ``str(obj)``.
    """
    flat: dict[str, Any] = {}

    def walk(prefix: str, node: Any) -> None:
        if isinstance(node, Mapping):
            if not node and prefix:
                flat[prefix] = "{}"
            for key, child in node.items():
                walk(f"{prefix}{sep}{key}" if prefix else str(key), child)
            return
        node = _plain(node)
        if isinstance(node, list):
            flat[prefix] = json.dumps(node, default=str)
        elif node is None or isinstance(node, (str, int, float, bool)):
            flat[prefix] = node
        else:
            flat[prefix] = str(node)

    if not isinstance(cfg, Mapping):
        raise TypeError(f"flatten() needs a mapping, got {type(cfg).__name__}")
    walk("", cfg)
    return flat


def shareable_location(value: str | None, roots: Sequence[Path | str] | None = None) -> str | None:
    """A path or store URI as records meant to be shared hold it: never this machine's workspace path.

    ``promotion.json`` (committed) and ``model_card.json`` / the NPZ's ``training_metadata`` (shared)
    go to other machines, where the workspace's absolute path means nothing.

    Parameters
    ----------
    value : str or None
        A local path, a ``sqlite:///``, ``file:`` URI, or any other URI.
    roots : sequence of Path, optional
        Folders a local path is made relative to, the first that contains it wins. Default: the
        current directory (a stage's workspace, also a DVC temporary copy) and :func:`repo_root`.

    Returns
    -------
    str or None
        Inside a root: the repo-relative form (``sqlite:///mlflow.db``, ``mlartifacts/1/<run>/artifacts/model``,
        ``data.dvc``). A URL with a host (a tracking server): the same URL without user name and password.
        Anything else (``runs:/``, ``models:/``, ``mlflow-artifacts:/`` URIs, paths outside every root) unchanged.
    """
    from urllib.parse import unquote, urlsplit, urlunsplit

    if value is None:
        return None
    text = str(value)
    if roots is None:
        roots = [Path.cwd()]
        with contextlib.suppress(FileNotFoundError):
            roots.append(repo_root())

    def relative(path: str) -> str | None:
        p = Path(path)
        if not p.is_absolute():
            return None
        for root in roots:
            for base in (Path(root).absolute(), Path(root).resolve()):
                with contextlib.suppress(ValueError):
                    return p.relative_to(base).as_posix() or "."
                with contextlib.suppress(ValueError):
                    return p.resolve().relative_to(base).as_posix() or "."
        return None

    if text.startswith("sqlite:///"):
        path, sep, query = text[len("sqlite:///") :].partition("?")
        rel = relative(path)
        return f"sqlite:///{rel}{sep}{query}" if rel else text
    if text.startswith("file:"):
        rel = relative(unquote(urlsplit(text).path))
        return rel or text
    parts = urlsplit(text)
    if parts.scheme and parts.netloc and "@" in parts.netloc:  # a server: keep host and path, drop credentials
        return urlunsplit(parts._replace(netloc=parts.netloc.rsplit("@", 1)[1]))
    if not parts.scheme or len(parts.scheme) == 1:  # a plain path (or a Windows drive letter)
        return relative(text) or text
    return text


OUTSIDE = "<outside the workspace>"


def record_location(value: str | None, roots: Sequence[Path | str] | None = None) -> str | None:
    """:func:`shareable_location`, and a local path still absolute (outside every root: a store the user named with
    ``MLFLOW_TRACKING_URI``) keeps only its file name, ``<outside the workspace>/mlflow.db``: a record
    (``promotion.json``, ``model_card.json``) never holds an absolute path."""
    from urllib.parse import unquote, urlsplit

    text = shareable_location(value, roots)
    if text is None:
        return None
    if text.startswith("sqlite:///"):
        path, sep, query = text[len("sqlite:///") :].partition("?")
        return f"sqlite:///{OUTSIDE}/{Path(path).name}{sep}{query}" if path.startswith("/") else text
    if text.startswith("file:"):
        return f"{OUTSIDE}/{Path(unquote(urlsplit(text).path)).name}"
    if text.startswith("/"):
        return f"{OUTSIDE}/{Path(text).name}"
    return text
