"""The MLflow store: which one, a client bound to it, the experiment, and values MLflow accepts.

* Everything goes through an explicit :class:`mlflow.MlflowClient` bound to the URI from
  :func:`resolve_tracking_uri`; nothing at import time (``mlflow`` is imported lazily, ~2 s).
* The default store is ``sqlite:///<workspace>/mlflow.db`` with artifacts in
  ``<workspace>/mlartifacts``, both absolute, so runs started from a subdirectory or from a DVC
  queued temp copy (``<ws>/.dvc/tmp/exps/tmpXXX``) land in the workspace store.
* Before the first client is built, telemetry and autologging are switched off.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aumesh.experiments import provenance

if TYPE_CHECKING:  # pragma: no cover
    from mlflow import MlflowClient

DEFAULT_EXPERIMENT = "aumesh"
DEFAULT_DB_NAME = "mlflow.db"
DEFAULT_ARTIFACT_DIR = "mlartifacts"

# MLflow limits (mlflow/utils/validation.py in 3.17).
MAX_PARAM_VALUE_LENGTH = 6000
MAX_TAG_VALUE_LENGTH = 8000
MAX_KEY_LENGTH = 250
MAX_BATCH = 100  # params/tags per log_batch call
MAX_METRICS_BATCH = 1000
MAX_DATASET_DIGEST_LENGTH = 36
MAX_INPUT_TAG_VALUE_LENGTH = 500
TRUNCATION_MARK = "...[truncated]"

_QUIETED = False


# --------------------------------------------------------------------------- setup
def _quiet_mlflow() -> None:
    """Disable MLflow telemetry and autologging (idempotent; env vars the user set win)."""
    global _QUIETED
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    os.environ.setdefault("DO_NOT_TRACK", "true")
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # the stages' own bars show the long passes
    if _QUIETED:
        return
    import logging

    import mlflow

    # "Creating initial MLflow database tables...", "Validating input example against model signature"
    for noisy in ("mlflow.store.db.utils", "alembic", "mlflow.pyfunc", "mlflow.models"):
        logging.getLogger(noisy).setLevel(logging.WARNING)

    try:  # mlflow builds its telemetry client at import; drop it if it was created
        from mlflow.telemetry import set_telemetry_client

        set_telemetry_client()
    except Exception:  # pragma: no cover - internal API moved
        pass
    try:
        mlflow.autolog(disable=True, silent=True)
    except Exception:  # pragma: no cover
        pass
    _QUIETED = True


def _absolute_local_uri(uri: str, root: Callable[[], Path]) -> str:
    """Make a relative ``sqlite:///`` / ``file:`` / plain-path URI absolute against ``root()``.

    ``root`` is only called for a relative path: an absolute store works outside any workspace
    (``benchmarks/*.py --workdir /elsewhere``).
    """
    if uri.startswith("sqlite:///"):
        rest = uri[len("sqlite:///"):]
        path, sep, query = rest.partition("?")
        if path and not path.startswith("/") and path != ":memory:":
            return f"sqlite:///{(root() / path).resolve().as_posix()}{sep}{query}"
        return uri
    if uri.startswith("file://"):
        return uri  # file:///abs or file://host/... : already absolute
    if uri.startswith("file:"):
        path = uri[len("file:"):]
        p = Path(path)
        return (p if p.is_absolute() else (root() / p).resolve()).as_uri()
    if "://" not in uri and ":" not in uri.split("/")[0]:
        p = Path(uri).expanduser()
        return (p if p.is_absolute() else (root() / p).resolve()).as_uri()
    return uri


def resolve_tracking_uri(tracking_cfg: Mapping[str, Any] | None = None) -> str:
    """Return the MLflow tracking URI to use.

    Parameters
    ----------
    tracking_cfg : Mapping, optional
        The ``tracking`` config group; only ``tracking_uri`` is read.

    Returns
    -------
    str
        1. ``MLFLOW_TRACKING_URI`` from the environment, verbatim, if set;
        2. else ``tracking_cfg["tracking_uri"]`` if set, with relative
           ``sqlite:///``, ``file:`` or plain paths made absolute against
           :func:`aumesh.experiments.provenance.repo_root`;
        3. else ``sqlite:///<repo_root()>/mlflow.db`` (absolute).
    """
    env = os.environ.get("MLFLOW_TRACKING_URI", "").strip()
    if env:
        return env
    cfg_uri = (tracking_cfg or {}).get("tracking_uri")
    if cfg_uri:
        cfg_uri = str(cfg_uri).strip()
        if cfg_uri.startswith(("http://", "https://", "databricks")):
            return cfg_uri
        return _absolute_local_uri(cfg_uri, provenance.repo_root)
    return f"sqlite:///{(provenance.repo_root() / DEFAULT_DB_NAME).as_posix()}"


def _default_artifact_location(uri: str, tracking_cfg: Mapping[str, Any] | None) -> str | None:
    """Artifact root for a *new* experiment: explicit cfg, else ``<ws>/mlartifacts`` for local stores."""
    cfg_loc = (tracking_cfg or {}).get("artifact_location")
    if cfg_loc:
        cfg_loc = str(cfg_loc)
        if "://" in cfg_loc:
            return cfg_loc
        p = Path(cfg_loc).expanduser()
        return (p if p.is_absolute() else provenance.repo_root() / p).resolve().as_uri()
    if uri.startswith(("sqlite:", "file:")) or "://" not in uri:
        # MLflow's default would be ./mlruns relative to the *current* directory,
        # i.e. inside a DVC temp copy that is deleted after the run.
        try:
            return (provenance.repo_root() / DEFAULT_ARTIFACT_DIR).as_uri()
        except FileNotFoundError:
            return None
    return None  # tracking server decides (e.g. mlflow-artifacts:/ proxy)


def get_client(tracking_cfg: Mapping[str, Any] | None = None) -> MlflowClient:
    """An :class:`mlflow.MlflowClient` bound to :func:`resolve_tracking_uri` (telemetry off).

    Parameters
    ----------
    tracking_cfg : Mapping, optional
        The ``tracking`` config group.

    Returns
    -------
    mlflow.MlflowClient
    """
    _quiet_mlflow()
    from mlflow import MlflowClient

    uri = resolve_tracking_uri(tracking_cfg)
    with _store_init_lock(uri):
        # MlflowClient() builds the store right away: schema creation + migrations
        # for a new SQLite file.
        return MlflowClient(tracking_uri=uri)


@contextlib.contextmanager
def _store_init_lock(uri: str) -> Iterator[None]:
    """Serialise MLflow store creation for a SQLite URI across processes.

    MLflow creates the schema (alembic) when a client is built on a new SQLite
    file; several processes doing that at once (parallel sweep jobs, ``dvc queue
    start -j N``) fail with ``alembic.util.exc.CommandError: Online migration
    expected to match one row``. The lock (``filelock``) is ``<database>.lock`` beside
    the store it guards (git-ignored next to the workspace's ``mlflow.db``). Later
    writes are safe: MLflow sets ``PRAGMA busy_timeout = 20000`` on every SQLite
    session. No-op for other URIs.
    """
    if not uri.startswith("sqlite:///"):
        yield
        return
    from filelock import FileLock

    db_path = Path(os.path.abspath(uri[len("sqlite:///"):].partition("?")[0]))
    db_path.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(f"{db_path}.lock"):
        yield


#: MLflow 3's experiment kind: the tag and value its UI and SDK (``mlflow.demo``, the UI's ``ExperimentKind``) use for a
#: model-training experiment, as opposed to ``genai_development`` (traces, judges).
EXPERIMENT_KIND_TAG = "mlflow.experimentKind"
MODEL_TRAINING_KIND = "custom_model_development"
#: The experiment's description: MLflow's UI shows this tag's Markdown above the runs table.
NOTE_TAG = "mlflow.note.content"
#: What people sort aumesh's runs by (metrics, then params), named in the description and the runs-page link.
SORT_METRICS = ("r2_mean", "r2_displacement_mean", "au_reliability_median")
SORT_PARAMS = ("preprocess.target", "features.name", "model.n_components")
#: MLflow's "share view" (the runs page's saved sort and columns) is an experiment tag ``mlflow.sharedViewState.<key>``
#: holding the page state as JSON, opened by ``?viewStateShareKey=<key>`` (MLflow 3.17's UI, ``viewStateShareKey``).
SHARED_VIEW_PREFIX = "mlflow.sharedViewState."
RUNS_VIEW_KEY = "aumesh-runs"


def runs_view_state(metric: str = SORT_METRICS[0]) -> dict[str, Any]:
    """The runs table aumesh's link opens: best *metric* first; the columns people sort by (metrics, then params)."""
    return {"searchFilter": "", "orderByKey": f"metrics.`{metric}`", "orderByAsc": False, "startTime": "ALL",
            "lifecycleFilter": "Active", "modelVersionFilter": "All Runs", "datasetsFilter": [],
            "selectedColumns": [f"metrics.`{m}`" for m in SORT_METRICS] + [f"params.`{p}`" for p in SORT_PARAMS]}


def experiment_tags(provenance_tags: Mapping[str, str]) -> dict[str, str]:
    """The experiment's kind, description and tags, from the provenance tags of a run opening in it.

    Parameters
    ----------
    provenance_tags : Mapping
        :func:`aumesh.experiments.tracking.provenance_tags` (``aumesh.data.md5``, ``.nfiles``, ``.path``,
        ``aumesh.version``).

    Returns
    -------
    dict
        ``mlflow.experimentKind`` (model training), ``mlflow.note.content`` (what aumesh is, the data version,
        what to sort by, the README section), ``aumesh.project``, ``aumesh.data.md5`` (the latest run's tables),
        ``aumesh.version``.
    """
    md5 = provenance_tags.get("aumesh.data.md5")
    if md5:
        files = provenance_tags.get("aumesh.data.nfiles")
        data = (f"the frame tables tracked by DVC in `data.dvc` (`{provenance_tags.get('aumesh.data.path') or 'data'}/`, "
                f"md5 `{md5}`{f', {files} files' if files else ''}; each run's own is its dataset input and "
                "`aumesh.data.md5` tag)")
    else:
        data = "frame tables outside a DVC workspace (no data version recorded)"
    note = (
        "**aumesh**: AU (+ head pose) -> MediaPipe FaceMesh. Each run fits the linear PLS model of the "
        "\"AU+pose -> MP mesh PLS (v2)\" model card on py-feat's per-frame tables (20 FACS AUs, Pitch/Yaw/Roll -> "
        "the 478-vertex mesh) and cross-validates it by video (GroupKFold).\n\n"
        f"**Data**: {data}.\n\n"
        "**Runs**: `dvc repro` / `dvc exp run` evaluations (tag `aumesh.stage` = evaluate) and `aumesh sweep` parents "
        "with one child per configuration. Sort by "
        + ", ".join(f"`{m}`" for m in SORT_METRICS) + " (CV R² within one target, the displacement R² across "
        "targets, AU-field reliability); the configuration is in the params "
        + ", ".join(f"`{p}`" for p in SORT_PARAMS) + ".\n\n"
        "**More**: the aumesh README, sections \"Tracking\" and \"Sweeps and promotion\"."
    )
    tags = {EXPERIMENT_KIND_TAG: MODEL_TRAINING_KIND, NOTE_TAG: note, "aumesh.project": "aumesh",
            SHARED_VIEW_PREFIX + RUNS_VIEW_KEY: json.dumps(runs_view_state())}
    for key in ("aumesh.data.md5", "aumesh.version"):
        if provenance_tags.get(key):
            tags[key] = provenance_tags[key]
    return tags


def runs_page_url(server: str, experiment_id: str) -> str:
    """The MLflow UI's page of an experiment's runs, best ``r2_mean`` first with the columns people sort by
    (:func:`runs_view_state`, saved in the experiment by :func:`experiment_tags`), in the "Model training" view.

    MLflow 3.17's UI decides between its GenAI view (traces, "Overview") and "Model training" from the
    ``workflowType`` in the page's address, else from the browser's last choice (GenAI by default), not from the
    experiment's kind tag: this address opens the runs table in any browser.
    """
    return (f"{server.rstrip('/')}/#/experiments/{experiment_id}/runs?workflowType=machine_learning"
            f"&viewStateShareKey={RUNS_VIEW_KEY}")


def describe_experiment(client: MlflowClient, experiment_id: str, tags: Mapping[str, str],
                        current: Mapping[str, str] | None = None) -> None:
    """Set the experiment *tags* whose value differs (an experiment made before, or by another tool, gets them too).

    *current* is the experiment's tags if already fetched. A user's own description (``mlflow.note.content`` not
    written by aumesh) is kept.
    """
    if current is None:
        current = client.get_experiment(experiment_id).tags
    for key, value in tags.items():
        if current.get(key) == value:
            continue
        if key == NOTE_TAG and current.get(key) and not current[key].startswith("**aumesh**"):
            continue  # edited in the UI: the user's text wins
        client.set_experiment_tag(experiment_id, key, value)


def ensure_experiment(client: MlflowClient, name: str, artifact_location: str | None = None,
                      tags: Mapping[str, str] | None = None) -> str:
    """Return the id of experiment *name*, creating it if needed (safe under races).

    Parameters
    ----------
    client : mlflow.MlflowClient
    name : str
        Experiment name.
    artifact_location : str, optional
        Used only when the experiment is created.
    tags : Mapping, optional
        Experiment tags (:func:`experiment_tags`): given when the experiment is created, and set on an existing one
        where they differ (:func:`describe_experiment`).

    Returns
    -------
    str
        The experiment id.

    Raises
    ------
    RuntimeError
        If the experiment exists but is deleted (fix: restore it or use another name).
    """
    from mlflow.exceptions import MlflowException

    exp = client.get_experiment_by_name(name)
    if exp is None:
        try:
            return client.create_experiment(name, artifact_location=artifact_location, tags=dict(tags or {}))
        except MlflowException:
            exp = client.get_experiment_by_name(name)  # created concurrently by another process
            if exp is None:
                raise
    if exp.lifecycle_stage == "deleted":
        raise RuntimeError(
            f"MLflow experiment {name!r} (id {exp.experiment_id}) is deleted in {client.tracking_uri}. "
            "Restore it (`mlflow experiments restore --experiment-id ...`) or set tracking.experiment "
            "to another name."
        )
    if tags:
        describe_experiment(client, exp.experiment_id, tags, exp.tags)
    return exp.experiment_id


# ------------------------------------------------------------------ value hygiene
def _truncate(value: str, limit: int) -> str:
    if len(value) <= limit:
        return value
    return value[: limit - len(TRUNCATION_MARK)] + TRUNCATION_MARK


def _clean_key(key: str) -> str:
    """Make *key* a valid MLflow param/metric name (``[/\\w.\\- :]``, <= 250 chars)."""
    out = "".join(c if (c.isalnum() or c in "_-. /:") else "_" for c in str(key))
    return out[:MAX_KEY_LENGTH] or "_"


def _str_value(value: Any, limit: int) -> str:
    if isinstance(value, (dict, list, tuple)):
        value = json.dumps(value, default=str)
    return _truncate(str(value), limit)


def prepare_params(params: Mapping[str, Any]) -> dict[str, str]:
    """Flatten *params* and make every key/value MLflow-safe.

    Parameters
    ----------
    params : Mapping
        Nested config.

    Returns
    -------
    dict
        ``{dotted.key: str}`` with values truncated to 6000 characters (ending in
        ``"...[truncated]"``) and invalid key characters replaced by ``_``.
    """
    return {
        _clean_key(k): _str_value(v, MAX_PARAM_VALUE_LENGTH)
        for k, v in provenance.flatten(params).items()
    }


def _metric_value(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"metric value {value!r} is not a number") from exc
