"""MLflow runs for aumesh: opened with provenance tags, closed with the right status, sweeps' parents.

Design
------
* The store, its client and its run tags are :mod:`aumesh.tracking.mlflow_store`, the experiment
  :mod:`aumesh.tracking.experiment`, the values MLflow accepts :mod:`aumesh.tracking.values`; the model registry is
  :mod:`aumesh.tracking.registry`. No fluent "active run", no ``mlflow.set_tracking_uri``: use the handle
  (:class:`aumesh.tracking.handle.TrackedRun`) yielded by :func:`tracked_run` to log.
* The evaluate stage logs through :func:`aumesh.tracking.beside.tracked_run_beside`: a helper process imports MLflow
  and holds the run while the stage computes (the stage process never imports MLflow); sweeps, which log many
  runs from one process, use :func:`tracked_run`.
* The store: ``MLFLOW_TRACKING_URI``, else the git-ignored ``aumesh.local.yaml`` (:mod:`aumesh.core.settings`), else
  ``tracking.tracking_uri``, else ``sqlite:///<workspace>/mlflow.db`` with artifacts in
  ``<workspace>/mlartifacts``, both absolute so runs started from a
  subdirectory or from a DVC queued temp copy (``<ws>/.dvc/tmp/exps/tmpXXX``,
  deleted after the run) land in the workspace store.
* Before the first client is built, telemetry is switched off
  (``MLFLOW_DISABLE_TELEMETRY=true`` and ``DO_NOT_TRACK=true``, which is what
  ``mlflow.telemetry.utils.is_telemetry_disabled`` checks in MLflow 3.17) and
  autologging is disabled (``mlflow.autolog(disable=True)``). No models are
  logged here.

The interface of the pipeline's stages and sweeps (nothing else of MLflow's is theirs to call):
:func:`aumesh.tracking.beside.tracked_run_beside` (the evaluate stage), :func:`tracked_run` (one sweep
configuration),
:func:`start_parent_run` / :func:`finish_sweep` (a sweep), :func:`tracking_uri` and :func:`store_label` (where runs
go, and how a shareable record names it). Reading runs back (sweeps, children, owners, data versions) is
:mod:`aumesh.tracking.queries`.

Whose and where: every run is tagged ``aumesh.user`` (and ``mlflow.user``, which the UI shows) with git's
``user.email`` (else the login) and ``aumesh.workspace.id`` with a stable id of the clone
(:func:`aumesh.core.provenance.workspace_id`), so a team's runs on one server can be told apart. Every run opened
with a configuration (not a sweep's parent, which spans them) is tagged ``aumesh.family`` with its input family
(``au``, ``blendshapes``, ``emotions``: :func:`aumesh.tracking.values.run_family` of its ``features.name``; a tag
the caller gives wins), so ``aumesh runs`` and ``aumesh promote --family`` rank within a family (issue 46).

Config keys (``tracking`` group, all optional): ``enabled`` (default True; when
False :func:`tracked_run` yields a no-op handle), ``tracking_uri``,
``experiment`` (default ``"aumesh"``), ``artifact_location`` (only used when the
experiment is created), ``dvc_file`` (default ``"data.dvc"``, read for the data
digest tag).
"""

from __future__ import annotations

import contextlib
import contextvars
import logging
import os
import socket
import sys
import traceback
from collections.abc import Iterator, Mapping
from typing import TYPE_CHECKING, Any, NoReturn

from aumesh.core import provenance
from aumesh.core.signals import process_gone
from aumesh.tracking.experiment import ensure_experiment, experiment_tags
from aumesh.tracking.handle import TrackedRun, _NullRun
from aumesh.tracking.mlflow_store import (
    DEFAULT_EXPERIMENT,
    ERROR_TAG,
    FAMILY_TAG,
    HOST_TAG,
    PARENT_TAG,
    PID_TAG,
    ROLE_TAG,
    SWEEP_PARENT_ROLE,
    USER_TAG,
    WORKSPACE_TAG,
    _default_artifact_location,
    get_client,
    tracking_enabled,
)
from aumesh.tracking.values import MAX_KEY_LENGTH, MAX_TAG_VALUE_LENGTH, _str_value, _truncate, run_family

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd
    from mlflow import MlflowClient

log = logging.getLogger(__name__)


# Innermost-last stack of runs opened by tracked_run in this context (for nested=True).
_ACTIVE_RUNS: contextvars.ContextVar[tuple[str, ...]] = contextvars.ContextVar("aumesh_active_runs", default=())


def provenance_tags(tracking_cfg: Mapping[str, Any] | None = None, owner_pid: int | None = None) -> dict[str, str]:
    """Tags describing code, data and environment; never raises.

    Parameters
    ----------
    tracking_cfg : Mapping, optional
        ``dvc_file`` (default ``"data.dvc"``) names the DVC file to digest.
    owner_pid : int, optional
        The process whose end ends the run (``aumesh.pid``); default this one
        (:func:`aumesh.tracking.beside.tracked_run_beside` logs from a helper process on behalf of the stage's).

    Returns
    -------
    dict
        ``aumesh.git.commit``/``.dirty``/``.branch``/``.source``,
        ``mlflow.source.git.commit`` (shown by the UI), ``aumesh.data.md5``/
        ``.size``/``.nfiles``/``.path`` (or ``aumesh.data.error``),
        ``aumesh.version``, ``aumesh.lib.<dist>`` for each library,
        ``aumesh.workspace``, ``dvc.exp_name``/``dvc.stage``/``dvc.baseline_rev``
        when DVC set them, ``aumesh.host``/``aumesh.pid`` (the process running it, see
        :func:`close_orphaned_runs`), ``mlflow.source.name``/``mlflow.source.type``, ``aumesh.user`` = ``mlflow.user``
        (:func:`aumesh.core.provenance.user_identity`) and ``aumesh.workspace.id``
        (:func:`aumesh.core.provenance.workspace_id`).
    """
    tags: dict[str, str] = {}
    try:
        root = provenance.repo_root()
    except FileNotFoundError as exc:
        root = None
        tags["aumesh.workspace.error"] = str(exc)
    if root is not None:
        tags["aumesh.workspace"] = str(root)
        tags[WORKSPACE_TAG] = provenance.workspace_id(root)
        git = provenance.git_commit(root)
        tags["aumesh.git.commit"] = git["commit"] or "unknown"
        tags["aumesh.git.dirty"] = str(git["dirty"]).lower()
        tags["aumesh.git.branch"] = git["branch"] or ""
        tags["aumesh.git.source"] = git["source"]
        if git["commit"]:
            tags["mlflow.source.git.commit"] = git["commit"]
        try:
            digest = provenance.data_digest(root, (tracking_cfg or {}).get("dvc_file") or "data.dvc")
            for key in ("md5", "size", "nfiles", "path"):
                if digest.get(key) is not None:
                    tags[f"aumesh.data.{key}"] = str(digest[key])
        except (FileNotFoundError, ValueError) as exc:
            tags["aumesh.data.error"] = str(exc)
    versions = provenance.library_versions()
    tags["aumesh.version"] = versions.get("aumesh") or "unknown"
    for dist, ver in versions.items():
        if dist != "aumesh":
            tags[f"aumesh.lib.{dist}"] = ver or "not installed"
    for env, tag in (
        ("DVC_EXP_NAME", "dvc.exp_name"),
        ("DVC_STAGE", "dvc.stage"),
        ("DVC_EXP_BASELINE_REV", "dvc.baseline_rev"),
    ):
        if os.environ.get(env):
            tags[tag] = os.environ[env]
    tags[HOST_TAG], tags[PID_TAG] = socket.gethostname(), str(owner_pid or os.getpid())
    tags["mlflow.source.name"] = sys.argv[0] if sys.argv and sys.argv[0] else "python"
    tags["mlflow.source.type"] = "LOCAL"
    # whose run: on a shared server the Unix login (MLflow's own mlflow.user) says nothing; the UI shows mlflow.user
    tags[USER_TAG] = tags["mlflow.user"] = provenance.user_identity(root)
    return tags


# ------------------------------------------------------------------------- runs
def _enabled(tracking_cfg: Mapping[str, Any] | None) -> bool:
    return tracking_enabled(tracking_cfg)


def _open_run(
    tracking_cfg: Mapping[str, Any] | None,
    run_name: str | None,
    tags: Mapping[str, Any] | None,
    parent_run_id: str | None,
    owner_pid: int | None = None,
    params: Mapping[str, Any] | None = None,
) -> TrackedRun:
    """A new RUNNING run with the provenance tags, ``tags`` and ``params``; a failure to log the params marks it
    FAILED before the error goes on (every way of opening a run: :func:`tracked_run`, :func:`start_parent_run`,
    :func:`aumesh.tracking.beside.tracked_run_beside`)."""
    client = get_client(tracking_cfg)
    uri = client.tracking_uri
    name = str((tracking_cfg or {}).get("experiment") or DEFAULT_EXPERIMENT)
    all_tags = provenance_tags(tracking_cfg, owner_pid)
    exp_id = ensure_experiment(client, name, _default_artifact_location(uri, tracking_cfg), experiment_tags(all_tags))
    close_orphaned_runs(client, exp_id, all_tags.get("aumesh.workspace"))
    if parent_run_id:
        all_tags[PARENT_TAG] = parent_run_id
    all_tags.update({str(k): v for k, v in (tags or {}).items()})
    # every model run says its input family (the family fits of the evaluate stage, sweep children, evaluate runs):
    # `aumesh runs` and `aumesh promote --family` rank within a family; a sweep's parent spans families, so has none
    family = run_family(params) if params and all_tags.get(ROLE_TAG) != SWEEP_PARENT_ROLE else None
    if family is not None:
        all_tags.setdefault(FAMILY_TAG, family)
    clean = {str(k)[:MAX_KEY_LENGTH]: _str_value(v, MAX_TAG_VALUE_LENGTH) for k, v in all_tags.items()}
    run = client.create_run(exp_id, run_name=run_name, tags=clean)
    handle = TrackedRun(client, run.info.run_id, exp_id)
    try:
        if params:
            handle.log_params(params)
    except BaseException as exc:
        _fail_and_raise(handle, exc)
    return handle


def close_orphaned_runs(client: MlflowClient, experiment_id: str, workspace: str | None) -> list[str]:
    """Mark KILLED the RUNNING runs of this host (and workspace) whose process is gone (e.g. SIGKILL).

    Returns
    -------
    list of str
        The run ids marked KILLED (each also tagged ``aumesh.error``).
    """
    host = socket.gethostname()
    runs = client.search_runs(
        [experiment_id],
        filter_string=f"attributes.status = 'RUNNING' and tags.`{HOST_TAG}` = '{host}'",
        max_results=1000,
    )
    killed = []
    for run in runs:
        tags = run.data.tags
        if workspace and tags.get("aumesh.workspace") not in (None, workspace):
            continue
        pid = tags.get(PID_TAG, "")
        if not pid.isdigit() or not process_gone(int(pid), (run.info.start_time or 0) / 1000.0):
            continue
        with contextlib.suppress(Exception):
            client.set_tag(
                run.info.run_id, ERROR_TAG, f"process {pid} on {host} ended without closing the run (killed)"
            )
            client.set_terminated(run.info.run_id, "KILLED")
            killed.append(run.info.run_id)
            log.warning(
                "MLflow run %s was left RUNNING by process %s, which is gone: marked KILLED", run.info.run_id, pid
            )
    return killed


def _failure(exc: BaseException) -> tuple[str, str, str]:
    """``(status, "Type: message", traceback)`` of the exception that ends a run (KILLED for ``KeyboardInterrupt``)."""
    status = "KILLED" if isinstance(exc, KeyboardInterrupt) else "FAILED"
    return (
        status,
        f"{type(exc).__name__}: {exc}",
        "".join(traceback.format_exception(type(exc), exc, exc.__traceback__)),
    )


def _fail(handle: TrackedRun, exc: BaseException) -> bool:
    return _end_failed(handle, *_failure(exc))


def _fail_and_raise(handle: TrackedRun, exc: BaseException) -> NoReturn:
    """End the run as ``exc`` says and raise it; a lost server's line also says what became of the run."""
    from aumesh.tracking.connection import TrackingServerError, run_fate

    marked = _fail(handle, exc)
    if isinstance(exc, TrackingServerError) and not exc.names_run:
        raise exc.noted(run_fate(handle.run_id, marked)) from exc
    raise exc


def _end_failed(handle: TrackedRun, status: str, error: str, tb: str) -> bool:
    """Tag the run with ``error`` (``aumesh.error``), log ``tb`` as ``error.txt`` and terminate it as ``status``;
    whether the run could be terminated (a server that stopped answering: not).

    After a server was lost (``error`` is a :class:`aumesh.tracking.connection.TrackingServerError`) the status is
    set first, each request tried once (not with MLflow's retries again), and the tag and traceback only if it was."""
    from aumesh.tracking.connection import TrackingServerError, no_retries

    if error.startswith(TrackingServerError.__name__):
        with no_retries():
            try:
                handle.client.set_terminated(handle.run_id, status)
            except Exception:
                return False
            with contextlib.suppress(Exception):
                handle.client.set_tag(handle.run_id, ERROR_TAG, _truncate(error, MAX_TAG_VALUE_LENGTH))
            with contextlib.suppress(Exception):
                handle.client.log_text(handle.run_id, tb, "error.txt")
        return True
    with contextlib.suppress(Exception):
        handle.client.set_tag(handle.run_id, ERROR_TAG, _truncate(error, MAX_TAG_VALUE_LENGTH))
    with contextlib.suppress(Exception):
        handle.client.log_text(handle.run_id, tb, "error.txt")
    try:
        handle.client.set_terminated(handle.run_id, status)
    except Exception:
        return False
    return True


@contextlib.contextmanager
def tracked_run(
    tracking_cfg: Mapping[str, Any] | None,
    run_name: str | None,
    params: Mapping[str, Any] | None,
    tags: Mapping[str, Any] | None = None,
    parent_run_id: str | None = None,
    nested: bool = False,
) -> Iterator[TrackedRun]:
    """Open an MLflow run, log params and provenance tags, close it with the right status.

    Parameters
    ----------
    tracking_cfg : Mapping or None
        The ``tracking`` config group (``enabled``, ``tracking_uri``,
        ``experiment``, ``artifact_location``, ``dvc_file``); None = defaults.
    run_name : str or None
        Display name of the run.
    params : Mapping or None
        Nested config; logged flattened (``a.b.c``), lists as JSON, values
        truncated to MLflow's 6000-character limit.
    tags : Mapping, optional
        Extra run tags (override the provenance tags of the same key).
    parent_run_id : str, optional
        Make this run a child of *parent_run_id* (``mlflow.parentRunId`` tag, so
        the UI nests it). May be in another process.
    nested : bool, default False
        If True and *parent_run_id* is None, use the innermost ``tracked_run``
        currently open in this context as the parent. With False, an enclosing
        run is ignored and an independent run is created.

    Yields
    ------
    TrackedRun
        Handle with ``run_id`` and ``log_*`` methods. A no-op handle
        (``enabled=False``, ``run_id=None``) when ``tracking.enabled`` is false.

    Notes
    -----
    On normal exit the run is FINISHED. If the body raises, the run gets the
    ``aumesh.error`` tag and an ``error.txt`` traceback artifact, is terminated
    as FAILED (KILLED for ``KeyboardInterrupt``) and the exception is re-raised.
    Tags logged at start: see :func:`provenance_tags`.
    """
    if not _enabled(tracking_cfg):
        yield _NullRun()
        return
    if parent_run_id is None and nested and _ACTIVE_RUNS.get():
        parent_run_id = _ACTIVE_RUNS.get()[-1]
    handle = _open_run(tracking_cfg, run_name, tags, parent_run_id, params=params)
    token = _ACTIVE_RUNS.set(_ACTIVE_RUNS.get() + (handle.run_id,))
    try:
        yield handle
    except BaseException as exc:
        _fail_and_raise(handle, exc)
    else:
        handle.client.set_terminated(handle.run_id, "FINISHED")
    finally:
        _ACTIVE_RUNS.reset(token)


# ------------------------------------------------------------------------ sweeps
def start_parent_run(
    tracking_cfg: Mapping[str, Any] | None,
    run_name: str,
    params: Mapping[str, Any] | None = None,
    tags: Mapping[str, Any] | None = None,
) -> str | None:
    """Create the parent run of a sweep and leave it RUNNING; return its id.

    Children are created with ``tracked_run(..., parent_run_id=<id>)`` (possibly
    in other processes); finish the parent with :func:`end_run` or
    :func:`mark_failed`. For an in-process sweep, ``with tracked_run(...,
    tags={"aumesh.role": "sweep-parent"})`` is the context-managed equivalent.

    Parameters
    ----------
    tracking_cfg : Mapping or None
    run_name : str
    params : Mapping, optional
        Sweep-level params (e.g. the sweep definition), flattened.
    tags : Mapping, optional
        Extra tags; ``aumesh.role=sweep-parent`` is always set.

    Returns
    -------
    str or None
        The run id; None when ``tracking.enabled`` is false.
    """
    if not _enabled(tracking_cfg):
        return None
    return _open_run(tracking_cfg, run_name, {ROLE_TAG: "sweep-parent", **(tags or {})}, None, params=params).run_id


def run_handle(run_id: str, tracking_cfg: Mapping[str, Any] | None = None) -> TrackedRun:
    """A :class:`TrackedRun` handle for an existing run (e.g. a sweep parent)."""
    client = get_client(tracking_cfg)
    run = client.get_run(run_id)
    return TrackedRun(client, run_id, run.info.experiment_id)


def end_run(run_id: str, tracking_cfg: Mapping[str, Any] | None = None, status: str = "FINISHED") -> None:
    """Terminate *run_id* with *status* (``FINISHED``, ``FAILED`` or ``KILLED``)."""
    if run_id is None:
        return
    get_client(tracking_cfg).set_terminated(run_id, status)


def mark_failed(run_id: str, error: BaseException | str, tracking_cfg: Mapping[str, Any] | None = None) -> None:
    """Tag *run_id* with the error (``aumesh.error``) and terminate it as FAILED.

    Parameters
    ----------
    run_id : str
    error : BaseException or str
        Exceptions are recorded as ``"Type: message"`` plus an ``error.txt``
        traceback artifact.
    tracking_cfg : Mapping, optional
    """
    if run_id is None:
        return
    client = get_client(tracking_cfg)
    if isinstance(error, BaseException):
        run = client.get_run(run_id)
        _fail(TrackedRun(client, run_id, run.info.experiment_id), error)
        return
    client.set_tag(run_id, ERROR_TAG, _truncate(str(error), MAX_TAG_VALUE_LENGTH))
    client.set_terminated(run_id, "FAILED")


def set_run_tags(run_id: str, tags: Mapping[str, Any], tracking_cfg: Mapping[str, Any] | None = None) -> None:
    """Set tags on an existing run (e.g. a sweep parent's child counts)."""
    run_handle(run_id, tracking_cfg).set_tags(tags)


def finish_sweep(
    parent_run_id: str, tracking_cfg: Mapping[str, Any] | None = None, wall_seconds: float | None = None
) -> tuple[pd.DataFrame | None, dict[str, Any]]:
    """End a sweep's parent run FINISHED, tagged with its children's counts (and ``sweep_wall_seconds``).

    Returns
    -------
    (DataFrame or None, dict)
        The children (:func:`aumesh.tracking.queries.list_child_runs`; None if they could not be read) and the
        tags set. The parent is ended even when counting fails.
    """
    from aumesh.tracking import queries

    children, tags = None, {}
    try:
        children = queries.list_child_runs(parent_run_id, tracking_cfg)
        statuses = children["status"].value_counts().to_dict() if len(children) else {}
        tags = {
            "aumesh.sweep.n_children": len(children),
            "aumesh.sweep.n_finished": statuses.get("FINISHED", 0),
            "aumesh.sweep.n_failed": len(children) - statuses.get("FINISHED", 0),
        }
        if wall_seconds is not None:
            tags["aumesh.sweep.wall_seconds"] = f"{wall_seconds:.2f}"
        handle = run_handle(parent_run_id, tracking_cfg)
        handle.set_tags(tags)
        if wall_seconds is not None:
            handle.log_metrics({"sweep_wall_seconds": wall_seconds})
    finally:
        end_run(parent_run_id, tracking_cfg, "FINISHED")
    return children, tags


def tracking_uri(tracking_cfg: Mapping[str, Any] | None = None) -> str:
    """The store runs go to (environment, ``aumesh.local.yaml``, ``conf/``, default: see :mod:`aumesh.core.settings`)."""
    from aumesh.tracking.mlflow_store import resolve_tracking_uri

    return resolve_tracking_uri(tracking_cfg)


def store_label(tracking_cfg: Mapping[str, Any] | None = None) -> str:
    """The store as shareable records name it: ``sqlite:///mlflow.db`` for the workspace's own, never a server's
    address or a path outside the workspace (:func:`aumesh.tracking.mlflow_store.store_label`)."""
    from aumesh.tracking.mlflow_store import store_label as label

    return label(tracking_uri(tracking_cfg))
