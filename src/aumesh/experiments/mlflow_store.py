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

# Run tags both sides read (the logging side writes them, :mod:`aumesh.experiments.queries` filters on them).
PARENT_TAG = "mlflow.parentRunId"
ROLE_TAG = "aumesh.role"
ERROR_TAG = "aumesh.error"
HOST_TAG, PID_TAG = "aumesh.host", "aumesh.pid"  # the process that owns a RUNNING run
USER_TAG = "aumesh.user"  # git user.email, else the login (provenance.user_identity)
WORKSPACE_TAG = "aumesh.workspace.id"  # a stable id of the clone (provenance.workspace_id)
DATA_TAG = "aumesh.data.md5"  # the DVC hash of the frame tables the run used
SWEEP_PARENT_ROLE, SWEEP_CHILD_ROLE = "sweep-parent", "sweep-child"

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
        The first of (see :mod:`aumesh.settings`):

        1. ``MLFLOW_TRACKING_URI`` from the environment;
        2. ``tracking.tracking_uri`` in the workspace's git-ignored ``aumesh.local.yaml``;
        3. ``tracking_cfg["tracking_uri"]`` (``conf/``, committed: a repo-relative store);
        4. ``sqlite:///<repo_root()>/mlflow.db``.

        Relative ``sqlite:///``, ``file:`` or plain paths are made absolute against
        :func:`aumesh.experiments.provenance.repo_root`; a driverless ``postgresql://`` gets the driver that is
        installed (:func:`database_uri`).
    """
    from aumesh import settings

    env = os.environ.get("MLFLOW_TRACKING_URI", "").strip()
    uri = env or settings.local_value("tracking", "tracking_uri") or (tracking_cfg or {}).get("tracking_uri")
    if not uri:
        return f"sqlite:///{(provenance.repo_root() / DEFAULT_DB_NAME).as_posix()}"
    uri = str(uri).strip()
    if uri.startswith(("http://", "https://", "databricks")):
        return uri
    if env:  # the environment's value as given (a path there is the caller's, relative to where they are)
        return database_uri(uri)
    return database_uri(_absolute_local_uri(uri, provenance.repo_root))


POSTGRES_SCHEMES = ("postgresql", "postgres")


def database_uri(uri: str) -> str:
    """A SQLAlchemy database URI MLflow can open with the driver that is installed.

    SQLAlchemy 2 reads a driverless ``postgresql://`` as psycopg 3 (``psycopg``), while the usual install (and this
    project's ``postgres`` extra) is ``psycopg2-binary``: with only psycopg2 present the URI becomes
    ``postgresql+psycopg2://``. A URI naming its driver (``postgresql+psycopg://``) is left alone.

    Raises
    ------
    aumesh.utils.errors.ConfigError
        A PostgreSQL URI and no driver installed; the message says what to install.
    """
    import importlib.util

    scheme, sep, rest = uri.partition("://")
    if not sep or scheme not in POSTGRES_SCHEMES:
        return uri
    if importlib.util.find_spec("psycopg") is not None:
        return f"postgresql+psycopg://{rest}"
    if importlib.util.find_spec("psycopg2") is not None:
        return f"postgresql+psycopg2://{rest}"
    from aumesh.utils.errors import ConfigError

    raise ConfigError(f"tracking URI {scheme}://...: no PostgreSQL driver is installed. Fix: "
                      "`pip install 'aumesh[postgres]'` (psycopg2-binary), or point at the team's tracking server "
                      "(http://host:5000) instead of its database.")


def store_label(uri: str, root: Path | None = None) -> str:
    """How shareable records (``model_card.json``, ``promotion.json``) name a tracking store.

    The workspace's own store repo-relative (``sqlite:///mlflow.db``); any other store, a server's address or a
    local path outside the workspace, is not written down (it means nothing on a teammate's machine and would commit
    an address): :data:`EXTERNAL_STORE`. The run id is what finds the run on the team's server.
    """
    label = provenance.shareable_location(uri, [root] if root is not None else None)
    if label.startswith("sqlite:///") and not label.startswith("sqlite:////"):  # sqlite:///mlflow.db
        return label
    if ":" not in label and not Path(label).is_absolute():  # a file store inside the workspace, made relative
        return label
    return EXTERNAL_STORE


#: What shareable records hold instead of a store outside the workspace (a server, a path elsewhere).
EXTERNAL_STORE = "external (MLFLOW_TRACKING_URI or aumesh.local.yaml; not recorded)"


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


def ensure_experiment(client: MlflowClient, name: str, artifact_location: str | None = None) -> str:
    """Return the id of experiment *name*, creating it if needed (safe under races).

    Parameters
    ----------
    client : mlflow.MlflowClient
    name : str
        Experiment name.
    artifact_location : str, optional
        Used only when the experiment is created.

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
            return client.create_experiment(name, artifact_location=artifact_location)
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
