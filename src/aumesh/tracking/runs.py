"""MLflow tracking for aumesh: the only module that talks to MLflow.

Design
------
* The store, its client and its value limits are :mod:`aumesh.tracking.mlflow_store`;
  the model registry is :mod:`aumesh.tracking.registry`. No fluent "active run", no
  ``mlflow.set_tracking_uri``: use the handle yielded by :func:`tracked_run` to log.
* The evaluate stage logs through :func:`tracked_run_beside`: a helper process imports MLflow and holds
  the run while the stage computes (the stage process never imports MLflow); sweeps, which log many
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
:func:`tracked_run_beside` (the evaluate stage), :func:`tracked_run` (one sweep configuration),
:func:`start_parent_run` / :func:`finish_sweep` (a sweep), :func:`tracking_uri` and :func:`store_label` (where runs
go, and how a shareable record names it). Reading runs back (sweeps, children, owners, data versions) is
:mod:`aumesh.tracking.queries`.

Whose and where: every run is tagged ``aumesh.user`` (and ``mlflow.user``, which the UI shows) with git's
``user.email`` (else the login) and ``aumesh.workspace.id`` with a stable id of the clone
(:func:`aumesh.core.provenance.workspace_id`), so a team's runs on one server can be told apart.

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
import time
import traceback
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aumesh.core import provenance
from aumesh.core.signals import check_supervisor, process_gone
from aumesh.tracking.mlflow_store import (
    DEFAULT_EXPERIMENT,
    ERROR_TAG,
    HOST_TAG,
    MAX_BATCH,
    MAX_DATASET_DIGEST_LENGTH,
    MAX_INPUT_TAG_VALUE_LENGTH,
    MAX_KEY_LENGTH,
    MAX_METRICS_BATCH,
    MAX_TAG_VALUE_LENGTH,
    PARENT_TAG,
    PID_TAG,
    ROLE_TAG,
    USER_TAG,
    WORKSPACE_TAG,
    _clean_key,
    _default_artifact_location,
    _metric_value,
    _str_value,
    _truncate,
    ensure_experiment,
    experiment_tags,
    get_client,
    prepare_params,
)

if TYPE_CHECKING:  # pragma: no cover
    from concurrent.futures import Future, ProcessPoolExecutor

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
        The process whose end ends the run (``aumesh.pid``); default this one (:func:`tracked_run_beside` logs from a
        helper process on behalf of the stage's).

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


# ----------------------------------------------------------------------- handle
class TrackedRun:
    """Handle for one MLflow run; every method logs to this run explicitly.

    Attributes
    ----------
    run_id : str
    experiment_id : str
    tracking_uri : str
    client : mlflow.MlflowClient
    """

    enabled = True

    def __init__(self, client: MlflowClient, run_id: str, experiment_id: str) -> None:
        self.client = client
        self.run_id = run_id
        self.experiment_id = experiment_id
        self.tracking_uri = client.tracking_uri

    def __repr__(self) -> str:
        return f"TrackedRun(run_id={self.run_id!r}, tracking_uri={self.tracking_uri!r})"

    # -- params / tags / metrics
    def log_params(self, params: Mapping[str, Any]) -> dict[str, str]:
        """Log flattened, truncated params (see :func:`prepare_params`); returns what was logged."""
        from mlflow.entities import Param

        flat = prepare_params(params)
        items = [Param(k, v) for k, v in flat.items()]
        for i in range(0, len(items), MAX_BATCH):
            self.client.log_batch(self.run_id, params=items[i : i + MAX_BATCH])
        return flat

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        """Set run tags (values stringified, truncated to 8000 characters)."""
        from mlflow.entities import RunTag

        items = [RunTag(str(k)[:MAX_KEY_LENGTH], _str_value(v, MAX_TAG_VALUE_LENGTH)) for k, v in tags.items()]
        for i in range(0, len(items), MAX_BATCH):
            self.client.log_batch(self.run_id, tags=items[i : i + MAX_BATCH])

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        """Log scalar metrics ``{name: value}`` (numpy scalars accepted) at *step* (default 0)."""
        from mlflow.entities import Metric

        ts = int(time.time() * 1000)
        items = [Metric(_clean_key(k), _metric_value(v), ts, int(step or 0)) for k, v in metrics.items()]
        for i in range(0, len(items), MAX_METRICS_BATCH):
            self.client.log_batch(self.run_id, metrics=items[i : i + MAX_METRICS_BATCH])

    def log_metric_history(self, name: str, values: Any, first_step: int = 0) -> None:
        """Log a whole metric history in one batch: ``values[i]`` at step ``first_step + i``.

        E.g. the R²-vs-n_components curve with ``first_step=1`` (step = number of components);
        one database transaction instead of one per step.
        """
        from mlflow.entities import Metric

        ts = int(time.time() * 1000)
        key = _clean_key(name)
        items = [Metric(key, _metric_value(v), ts, first_step + i) for i, v in enumerate(values)]
        for i in range(0, len(items), MAX_METRICS_BATCH):
            self.client.log_batch(self.run_id, metrics=items[i : i + MAX_METRICS_BATCH])

    def log_fold_metrics(self, name_to_list: Mapping[str, Any], summary: bool = False) -> None:
        """Log per-fold values: ``{"r2": [f0, f1, f2]}`` -> metric ``r2`` at steps 0, 1, 2.

        Parameters
        ----------
        name_to_list : Mapping
            Metric name -> sequence of per-fold values (index = fold = step).
        summary : bool, default False
            Also log ``<name>_mean`` and ``<name>_std`` (population std) at step 0.
        """
        from mlflow.entities import Metric

        ts = int(time.time() * 1000)
        items = []
        means: dict[str, float] = {}
        for name, values in name_to_list.items():
            vals = [_metric_value(v) for v in values]
            key = _clean_key(name)
            items += [Metric(key, v, ts, fold) for fold, v in enumerate(vals)]
            if summary and vals:
                mean = sum(vals) / len(vals)
                means[f"{key}_mean"] = mean
                means[f"{key}_std"] = (sum((v - mean) ** 2 for v in vals) / len(vals)) ** 0.5
        for i in range(0, len(items), MAX_METRICS_BATCH):
            self.client.log_batch(self.run_id, metrics=items[i : i + MAX_METRICS_BATCH])
        if means:
            self.log_metrics(means)

    # -- artifacts
    def log_dict(self, obj: Any, artifact_file: str) -> None:
        """Log a JSON/YAML-serialisable object as *artifact_file* (``.json`` or ``.yaml``)."""
        self.client.log_dict(self.run_id, provenance._plain(obj), artifact_file)

    def log_text(self, text: str, artifact_file: str) -> None:
        """Log a string as *artifact_file*."""
        self.client.log_text(self.run_id, text, artifact_file)

    def log_figure(self, figure: Any, artifact_file: str) -> None:
        """Log a matplotlib (or plotly) figure as *artifact_file* (e.g. ``"plots/cv.png"``)."""
        self.client.log_figure(self.run_id, figure, artifact_file)

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None:
        """Copy a local file or directory into the run's artifacts (under *artifact_path*)."""
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"log_artifact: {path} does not exist")
        if path.is_dir():
            self.client.log_artifacts(self.run_id, str(path), artifact_path)
        else:
            self.client.log_artifact(self.run_id, str(path), artifact_path)

    def log_config(self, resolved_cfg: Any, artifact_file: str = "config.yaml") -> None:
        """Log the resolved config (dict or OmegaConf) as ``config.yaml``."""
        import yaml

        try:  # resolve interpolations if an OmegaConf container was passed
            from omegaconf import DictConfig, ListConfig, OmegaConf

            if isinstance(resolved_cfg, (DictConfig, ListConfig)):
                resolved_cfg = OmegaConf.to_container(resolved_cfg, resolve=True)
        except ImportError:  # pragma: no cover
            pass
        text = yaml.safe_dump(provenance._plain(resolved_cfg), sort_keys=False, default_flow_style=False)
        self.client.log_text(self.run_id, text, artifact_file)

    # -- dataset
    def log_dataset(
        self,
        digest: Mapping[str, Any],
        source: str,
        name: str = "frame_tables",
        context: str = "training",
    ) -> None:
        """Record the DVC-tracked data as an MLflow dataset input of this run.

        An :class:`mlflow.data.meta_dataset.MetaDataset` (metadata only, no data
        copied) whose ``digest`` is the DVC hash (``digest["md5"]``, e.g.
        ``"<32 hex>.dir"``, exactly MLflow's 36-char digest limit; longer values
        are cut and the full value kept in the input tags) and whose source is
        *source*: a local path (stored absolute, source type ``local``) or an
        ``http(s)``/``s3``/... URI. Input tags: ``mlflow.data.context`` and
        ``dvc.md5``/``dvc.size``/``dvc.nfiles``/``dvc.path``/``dvc.file``.

        Parameters
        ----------
        digest : Mapping
            Output of :func:`aumesh.core.provenance.data_digest`.
        source : str
            Where the data lives (e.g. the ``data`` directory).
        name : str, default "frame_tables"
        context : str, default "training"
        """
        from mlflow.data.meta_dataset import MetaDataset
        from mlflow.entities import DatasetInput, InputTag

        if not digest.get("md5"):
            raise ValueError("log_dataset: digest has no 'md5' key; pass aumesh.core.provenance.data_digest(...)")
        md5 = str(digest["md5"])
        # MLflow's stubs declare MetaDataset.profile abstract, but the class is concrete (it returns None) and MLflow's
        # own docs construct it this way
        dataset = MetaDataset(  # type: ignore[abstract]
            _dataset_source(source), name=name, digest=md5[:MAX_DATASET_DIGEST_LENGTH]
        )
        tags = [InputTag("mlflow.data.context", context)]
        for key, tag in (
            ("md5", "dvc.md5"),
            ("size", "dvc.size"),
            ("nfiles", "dvc.nfiles"),
            ("path", "dvc.path"),
            ("dvc_file", "dvc.file"),
        ):
            if digest.get(key) is not None:
                tags.append(InputTag(tag, _truncate(str(digest[key]), MAX_INPUT_TAG_VALUE_LENGTH)))
        self.client.log_inputs(self.run_id, datasets=[DatasetInput(dataset._to_mlflow_entity(), tags=tags)])


class _NullRun(TrackedRun):
    """No-op handle used when ``tracking.enabled`` is false."""

    enabled = False

    def __init__(self) -> None:  # noqa: D107 - nothing to bind
        self.client = None  # type: ignore[assignment]
        self.run_id = None  # type: ignore[assignment]
        self.experiment_id = None  # type: ignore[assignment]
        self.tracking_uri = None

    def __getattribute__(self, item: str) -> Any:
        if item.startswith("log_") or item in ("set_tags", "call"):
            return lambda *a, **k: None
        return object.__getattribute__(self, item)

    def call(self, fn, *args, **kwargs) -> None:
        """:meth:`RunBeside.call` with tracking off: nothing to run (``__getattribute__`` answers first; declared
        so that the handle :func:`tracked_run_beside` yields has one interface)."""


def _dataset_source(source: str):
    """MLflow DatasetSource for a path or URI (paths become absolute, source type ``local``)."""
    import warnings

    from mlflow.data.dataset_source_registry import resolve_dataset_source

    src = str(source)
    if "://" not in src:
        src = Path(src).expanduser().absolute().as_posix()
    if src.startswith(("http://", "https://")):
        from mlflow.data.http_dataset_source import HTTPDatasetSource

        return HTTPDatasetSource(src)
    with warnings.catch_warnings():  # two "local" sources are registered; either is fine
        warnings.simplefilter("ignore")
        try:
            return resolve_dataset_source(src)
        except Exception:
            from mlflow.data.code_dataset_source import CodeDatasetSource

            return CodeDatasetSource({"source": src})


# ------------------------------------------------------------------------- runs
def _enabled(tracking_cfg: Mapping[str, Any] | None) -> bool:
    value = (tracking_cfg or {}).get("enabled", True)
    return value if isinstance(value, bool) else str(value).lower() not in {"0", "false", "no", "off"}


def _open_run(
    tracking_cfg: Mapping[str, Any] | None,
    run_name: str | None,
    tags: Mapping[str, Any] | None,
    parent_run_id: str | None,
    owner_pid: int | None = None,
) -> TrackedRun:
    client = get_client(tracking_cfg)
    uri = client.tracking_uri
    name = str((tracking_cfg or {}).get("experiment") or DEFAULT_EXPERIMENT)
    all_tags = provenance_tags(tracking_cfg, owner_pid)
    exp_id = ensure_experiment(client, name, _default_artifact_location(uri, tracking_cfg), experiment_tags(all_tags))
    close_orphaned_runs(client, exp_id, all_tags.get("aumesh.workspace"))
    if parent_run_id:
        all_tags[PARENT_TAG] = parent_run_id
    all_tags.update({str(k): v for k, v in (tags or {}).items()})
    clean = {str(k)[:MAX_KEY_LENGTH]: _str_value(v, MAX_TAG_VALUE_LENGTH) for k, v in all_tags.items()}
    run = client.create_run(exp_id, run_name=run_name, tags=clean)
    return TrackedRun(client, run.info.run_id, exp_id)


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


def _fail(handle: TrackedRun, exc: BaseException) -> None:
    _end_failed(handle, *_failure(exc))


def _end_failed(handle: TrackedRun, status: str, error: str, tb: str) -> None:
    """Tag the run with ``error`` (``aumesh.error``), log ``tb`` as ``error.txt`` and terminate it as ``status``."""
    with contextlib.suppress(Exception):
        handle.client.set_tag(handle.run_id, ERROR_TAG, _truncate(error, MAX_TAG_VALUE_LENGTH))
    with contextlib.suppress(Exception):
        handle.client.log_text(handle.run_id, tb, "error.txt")
    with contextlib.suppress(Exception):
        handle.client.set_terminated(handle.run_id, status)


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
    handle = _open_run(tracking_cfg, run_name, tags, parent_run_id)
    token = _ACTIVE_RUNS.set(_ACTIVE_RUNS.get() + (handle.run_id,))
    try:
        if params:
            handle.log_params(params)
        yield handle
    except BaseException as exc:
        _fail(handle, exc)
        raise
    else:
        handle.client.set_terminated(handle.run_id, "FINISHED")
    finally:
        _ACTIVE_RUNS.reset(token)


# ------------------------------------------------------- a run beside the work
class RunBeside:
    """The handle of :func:`tracked_run_beside`: :class:`TrackedRun`'s ``log_*`` and ``set_tags`` methods, each
    queued to the helper process that holds the run and run there in the order they were called; they return at once
    (a :class:`concurrent.futures.Future`). ``run_id``, ``experiment_id`` and ``tracking_uri`` wait for the run to be
    open."""

    enabled = True

    def __init__(self, helper: ProcessPoolExecutor, opened: Future) -> None:
        self._helper = helper
        self._opened = opened  # of (run_id, experiment_id, tracking_uri)
        self._queued = [opened]

    def __repr__(self) -> str:
        return f"RunBeside(opened={self._opened.done()}, queued={len(self._queued)})"

    run_id = property(lambda self: self._opened.result()[0])
    experiment_id = property(lambda self: self._opened.result()[1])
    tracking_uri = property(lambda self: self._opened.result()[2])

    def call(self, fn, *args, **kwargs):
        """Queue ``fn(handle, *args, **kwargs)`` with the helper's :class:`TrackedRun` ``handle`` (``fn`` and its
        arguments are pickled: a module-level function); returns its Future."""
        future = self._helper.submit(_call_beside, fn, args, kwargs)
        self._queued.append(future)
        return future

    def __getattr__(self, name: str):
        if name.startswith("log_") or name == "set_tags":
            method = getattr(TrackedRun, name)
            return lambda *args, **kwargs: self.call(method, *args, **kwargs)
        raise AttributeError(f"{type(self).__name__} has no attribute {name!r}")

    def wait(self) -> None:
        """Wait for everything queued; raise the first error the helper met."""
        for future in self._queued:
            future.result()

    def end(self, error: BaseException | None = None) -> None:
        """End the run FINISHED, or with ``error`` as :func:`tracked_run` does (nothing to end if it never opened)."""
        if error is None:
            self._helper.submit(_end_beside, "FINISHED").result()
        elif self._opened.exception() is None:
            with contextlib.suppress(Exception):
                self._helper.submit(_end_beside, *_failure(error)).result()


_BESIDE: TrackedRun | None = None  # the helper process's open run


def _start_helper(owner_pid: int) -> None:
    """In the helper: Ctrl-C (which a terminal sends to the whole process group) is the stage's to handle, so the run
    can still be marked KILLED; and the helper ends when its stage process is gone (e.g. killed alone)."""
    import signal
    import threading

    # SIGTERM/SIGHUP too: a stage stops on them as on Ctrl-C (aumesh.core.signals), and this helper, forked after the
    # stage installed that handler, must stay to mark the run KILLED when a whole process group is told to stop
    for sig in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if sig is not None:
            signal.signal(sig, signal.SIG_IGN)

    def watch() -> None:
        while os.getppid() == owner_pid:
            time.sleep(0.5)
        os._exit(1)  # the run stays RUNNING under the stage's pid: the next run marks it KILLED

    threading.Thread(target=watch, name="aumesh-owner-watch", daemon=True).start()


def _open_beside(tracking_cfg, run_name, params, tags, owner_pid: int) -> tuple[str, str, str]:
    global _BESIDE
    handle = _open_run(tracking_cfg, run_name, tags, None, owner_pid)
    try:
        if params:
            handle.log_params(params)
    except BaseException as exc:
        _fail(handle, exc)
        raise
    _BESIDE = handle
    return handle.run_id, handle.experiment_id, handle.tracking_uri


def _call_beside(fn, args, kwargs):
    if _BESIDE is None:
        raise RuntimeError("the MLflow run did not open (see the first error)")
    return fn(_BESIDE, *args, **kwargs)


def _end_beside(status: str, error: str = "", tb: str = "") -> None:
    if _BESIDE is None:  # the run never opened: the opening error is what the caller reports
        return
    if status == "FINISHED":
        _BESIDE.client.set_terminated(_BESIDE.run_id, status)
    else:
        _end_failed(_BESIDE, status, error, tb)


@contextlib.contextmanager
def tracked_run_beside(
    tracking_cfg: Mapping[str, Any] | None,
    run_name: str | None,
    params: Mapping[str, Any] | None,
    tags: Mapping[str, Any] | None = None,
) -> Iterator[RunBeside | _NullRun]:
    """:func:`tracked_run` held by a helper process, so MLflow is never imported here and works beside the caller.

    MLflow 3's import (its GenAI, gateway and data modules, pandas, SQLAlchemy: ~4 s of CPU) ran on one core before
    the evaluate stage's first pass, while the other idled; beside it, the stage at 344k frames takes 0.82x the time.
    The helper (one
    worker of a :class:`concurrent.futures.ProcessPoolExecutor`, forked on Linux) imports MLflow and opens
    the run while the caller computes; the caller's logging is queued to it, in order
    (:class:`RunBeside`). The run is the same as :func:`tracked_run`'s: params, provenance tags (``aumesh.pid`` is the
    caller's), FINISHED on normal exit; if the body raises, or a queued call failed, the run gets the ``aumesh.error``
    tag and ``error.txt``, is FAILED (KILLED for ``KeyboardInterrupt``) and the error is raised here. If the caller is
    killed the helper ends too, and the next run marks the run KILLED (:func:`close_orphaned_runs`).

    Yields
    ------
    RunBeside
        Or the no-op handle (``enabled=False``) when ``tracking.enabled`` is false.
    """
    if not _enabled(tracking_cfg):
        yield _NullRun()
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    # fork (Linux): the helper inherits the imports (NumPy, pandas); elsewhere spawn, the platforms' safe default
    context = multiprocessing.get_context("fork" if sys.platform == "linux" else "spawn")
    owner = os.getpid()
    with ProcessPoolExecutor(1, mp_context=context, initializer=_start_helper, initargs=(owner,)) as helper:
        run = RunBeside(helper, helper.submit(_open_beside, dict(tracking_cfg or {}), run_name, params, tags, owner))
        try:
            yield run
            run.wait()
            check_supervisor()  # under DVC: a run whose DVC was stopped is KILLED, never FINISHED by an orphan
        except BaseException as exc:
            run.end(exc)
            raise
        run.end()


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
    handle = _open_run(tracking_cfg, run_name, {ROLE_TAG: "sweep-parent", **(tags or {})}, None)
    try:
        if params:
            handle.log_params(params)
    except BaseException as exc:
        _fail(handle, exc)
        raise
    return handle.run_id


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
