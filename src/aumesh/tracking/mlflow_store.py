"""The MLflow store: which one, a client bound to it, a damaged, busy or moved SQLite store, and the run tags.

* Everything goes through an explicit :class:`mlflow.MlflowClient` bound to the URI from
  :func:`resolve_tracking_uri`; nothing at import time (``mlflow`` is imported lazily, ~2 s).
* The default store is ``sqlite:///<workspace>/mlflow.db`` with artifacts in
  ``<workspace>/mlartifacts``, both absolute, so runs started from a subdirectory or from a DVC
  queued temp copy (``<ws>/.dvc/tmp/exps/tmpXXX``) land in the workspace store.
* Before the first client is built, telemetry and autologging are switched off.
* A damaged SQLite store is one line (:class:`TrackingStoreError`), a locked one is retried with backoff for
  ``tracking.busy_timeout_s`` seconds first, and a copied or moved workspace's store is pointed at its own
  artifacts (:func:`relocate_artifacts`).
* Where the URI came from (:func:`locate_tracking_uri`) and the check every command that tracks makes before any work
  (:func:`check_tracking`); a server or database that does not answer, and MLflow's retries bounded, are
  :mod:`aumesh.tracking.connection`.

The experiment runs go to is :mod:`aumesh.tracking.experiment`; the values MLflow accepts (params cleaning, its
limits) are :mod:`aumesh.tracking.values`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple, cast

from aumesh.core import provenance
from aumesh.core.errors import UserError

if TYPE_CHECKING:  # pragma: no cover
    from mlflow import MlflowClient

DEFAULT_EXPERIMENT = "aumesh"
DEFAULT_DB_NAME = "mlflow.db"
DEFAULT_ARTIFACT_DIR = "mlartifacts"

# Run tags both sides read (the logging side writes them, :mod:`aumesh.tracking.queries` filters on them).
PARENT_TAG = "mlflow.parentRunId"
ROLE_TAG = "aumesh.role"
ERROR_TAG = "aumesh.error"
HOST_TAG, PID_TAG = "aumesh.host", "aumesh.pid"  # the process that owns a RUNNING run
USER_TAG = "aumesh.user"  # git user.email, else the login (provenance.user_identity)
WORKSPACE_TAG = "aumesh.workspace.id"  # a stable id of the clone (provenance.workspace_id)
DATA_TAG = "aumesh.data.md5"  # the DVC hash of the frame tables the run used
# the input family a model run fitted (au, blendshapes, emotions: features.family, issue 46); set on every run opened
# with a config (aumesh.tracking.runs._open_run), derived from param features.name for runs made before the tag
FAMILY_TAG = "aumesh.family"
SWEEP_PARENT_ROLE, SWEEP_CHILD_ROLE = "sweep-parent", "sweep-child"

_QUIETED = False
log = logging.getLogger(__name__)


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
        rest = uri[len("sqlite:///") :]
        path, sep, query = rest.partition("?")
        if path and not path.startswith("/") and path != ":memory:":
            return f"sqlite:///{(root() / path).resolve().as_posix()}{sep}{query}"
        return uri
    if uri.startswith("file://"):
        return uri  # file:///abs or file://host/... : already absolute
    if uri.startswith("file:"):
        path = uri[len("file:") :]
        p = Path(path)
        return (p if p.is_absolute() else (root() / p).resolve()).as_uri()
    if "://" not in uri and ":" not in uri.split("/")[0]:
        p = Path(uri).expanduser()
        return (p if p.is_absolute() else (root() / p).resolve()).as_uri()
    return uri


class TrackingURI(NamedTuple):
    """A resolved tracking URI and where it came from (``source``, as messages name it)."""

    uri: str
    source: str


def locate_tracking_uri(tracking_cfg: Mapping[str, Any] | None = None) -> TrackingURI:
    """:func:`resolve_tracking_uri` and where the URI came from.

    Returns
    -------
    TrackingURI
        ``source`` is :data:`aumesh.tracking.connection.ENV_SOURCE` (``MLFLOW_TRACKING_URI``), ``LOCAL_SOURCE``
        with the path of ``aumesh.local.yaml``, ``CONF_SOURCE`` (``tracking.tracking_uri``) or ``DEFAULT_SOURCE``.
    """
    from aumesh.core import settings
    from aumesh.tracking import connection

    env = os.environ.get("MLFLOW_TRACKING_URI", "").strip()
    local = None if env else settings.local_value("tracking", "tracking_uri")
    if env:
        uri, source = env, connection.ENV_SOURCE
    elif local:
        uri, source = str(local), connection.LOCAL_SOURCE.format(path=settings.settings_path())
    elif (tracking_cfg or {}).get("tracking_uri"):
        uri, source = str((tracking_cfg or {})["tracking_uri"]), connection.CONF_SOURCE
    else:
        return TrackingURI(
            f"sqlite:///{(provenance.repo_root() / DEFAULT_DB_NAME).as_posix()}", connection.DEFAULT_SOURCE
        )
    uri = uri.strip()
    if uri.startswith(("http://", "https://", "databricks")):
        return TrackingURI(uri, source)
    if env:  # the environment's value as given (a path there is the caller's, relative to where they are)
        return TrackingURI(database_uri(uri), source)
    return TrackingURI(database_uri(_absolute_local_uri(uri, provenance.repo_root)), source)


def resolve_tracking_uri(tracking_cfg: Mapping[str, Any] | None = None) -> str:
    """Return the MLflow tracking URI to use (where it came from too: :func:`locate_tracking_uri`).

    Parameters
    ----------
    tracking_cfg : Mapping, optional
        The ``tracking`` config group; only ``tracking_uri`` is read.

    Returns
    -------
    str
        The first of (see :mod:`aumesh.core.settings`):

        1. ``MLFLOW_TRACKING_URI`` from the environment;
        2. ``tracking.tracking_uri`` in the workspace's git-ignored ``aumesh.local.yaml``;
        3. ``tracking_cfg["tracking_uri"]`` (``conf/``, committed: a repo-relative store);
        4. ``sqlite:///<repo_root()>/mlflow.db``.

        Relative ``sqlite:///``, ``file:`` or plain paths are made absolute against
        :func:`aumesh.core.provenance.repo_root`; a driverless ``postgresql://`` gets the driver that is
        installed (:func:`database_uri`).
    """
    return locate_tracking_uri(tracking_cfg).uri


def tracking_enabled(tracking_cfg: Mapping[str, Any] | None) -> bool:
    """``tracking.enabled`` (default true; ``"false"``, ``"0"``, ``"no"``, ``"off"`` as text are false)."""
    value = (tracking_cfg or {}).get("enabled", True)
    return value if isinstance(value, bool) else str(value).lower() not in {"0", "false", "no", "off"}


def check_tracking(tracking_cfg: Mapping[str, Any] | None, consequence: str = "nothing was run") -> TrackingURI | None:
    """The check every command that tracks makes before any work (nothing when ``tracking.enabled`` is false).

    A SQLite store: damaged or locked (:func:`check_store`); a server or database: answers within
    ``tracking.check_timeout_s`` (:func:`aumesh.tracking.connection.check_server`; ``consequence``: what its message
    says became of the command's work). MLflow's retries and timeouts are bounded from here on
    (:func:`aumesh.tracking.connection.bound_requests`).

    Returns
    -------
    TrackingURI or None
        The store checked; None with tracking off.

    Raises
    ------
    TrackingStoreError, aumesh.tracking.connection.TrackingServerError
        One line naming the store, where its URI came from and the fix.
    """
    from aumesh.tracking import connection

    if not tracking_enabled(tracking_cfg):
        return None
    located = locate_tracking_uri(tracking_cfg)
    connection.bound_requests(tracking_cfg)
    if sqlite_path(located.uri) is not None:
        check_store(located.uri, busy_timeout(tracking_cfg))
    else:
        connection.check_server(located.uri, located.source, connection.check_timeout(tracking_cfg), consequence)
    return located


POSTGRES_SCHEMES = ("postgresql", "postgres")


def database_uri(uri: str) -> str:
    """A SQLAlchemy database URI MLflow can open with the driver that is installed.

    SQLAlchemy 2 reads a driverless ``postgresql://`` as psycopg 3 (``psycopg``), while the usual install (and this
    project's ``postgres`` extra) is ``psycopg2-binary``: with only psycopg2 present the URI becomes
    ``postgresql+psycopg2://``. A URI naming its driver (``postgresql+psycopg://``) is left alone.

    Raises
    ------
    aumesh.core.errors.ConfigError
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
    from aumesh.core.errors import ConfigError

    raise ConfigError(
        f"tracking URI {scheme}://...: no PostgreSQL driver is installed. Fix: "
        "`pip install 'aumesh[postgres]'` (psycopg2-binary), or point at the team's tracking server "
        "(http://host:5000) instead of its database."
    )


def store_label(uri: str, root: Path | None = None) -> str:
    """How shareable records (``model_card.json``, ``promotion.json``) name a tracking store.

    The workspace's own store repo-relative (``sqlite:///mlflow.db``); any other store, a server's address or a
    local path outside the workspace, is not written down (it means nothing on a teammate's machine and would commit
    an address): :data:`EXTERNAL_STORE`. The run id is what finds the run on the team's server.
    """
    label = provenance.shareable_location(uri, [root] if root is not None else None)
    if label is None:
        return EXTERNAL_STORE
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

    For a SQLite store: checked first (:func:`check_store`), pointed at this workspace's ``mlartifacts/`` when the
    workspace was copied or moved (:func:`relocate_artifacts`), and wrapped in :class:`StoreClient`, whose calls retry
    a locked store for ``tracking.busy_timeout_s`` seconds and name a damaged one (:class:`TrackingStoreError`). For
    a server or database: MLflow's retries and timeouts bounded (:func:`aumesh.tracking.connection.bound_requests`)
    and the client wrapped in :class:`aumesh.tracking.connection.ServerClient`, whose calls name a server that stopped
    answering in one line (:class:`aumesh.tracking.connection.TrackingServerError`).

    Parameters
    ----------
    tracking_cfg : Mapping, optional
        The ``tracking`` config group.

    Returns
    -------
    mlflow.MlflowClient or StoreClient or ServerClient
    """
    from aumesh.tracking import connection

    uri, source = locate_tracking_uri(tracking_cfg)
    limit = busy_timeout(tracking_cfg)
    check_store(uri, limit)  # before MLflow's import (seconds): a damaged store says so at once
    connection.bound_requests(tracking_cfg)  # MLflow reads them at each request: before the first
    _quiet_mlflow()
    from mlflow import MlflowClient

    with _store_init_lock(uri):
        _with_store_retry(lambda: relocate_artifacts(uri), uri, limit)
        # MlflowClient() builds the store right away: schema creation + migrations
        # for a new SQLite file.
        client = _with_store_retry(lambda: MlflowClient(tracking_uri=uri), uri, limit)
    # StoreClient forwards every MlflowClient method (retrying a busy store), ServerClient too (a server that stopped
    # answering is one line): an MlflowClient to their callers
    if sqlite_path(uri):
        return cast("MlflowClient", StoreClient(client, uri, limit))
    return cast("MlflowClient", connection.ServerClient(client, uri, source))


# --------------------------------------------------------------------------- a damaged or busy store
DEFAULT_BUSY_TIMEOUT_S = 60.0
_BUSY = ("database is locked", "database table is locked", "database schema is locked")
_DAMAGED = ("malformed", "file is not a database", "disk image", "unsupported file format")
_CHECKED: set[str] = set()  # stores checked by this process (check_store: once each)
_RELOCATED: set[str] = set()  # stores relocate_artifacts looked at in this process


class TrackingStoreError(UserError):
    """The MLflow tracking store is damaged or stays locked; the message names the file, the cause and the fix."""


def busy_timeout(tracking_cfg: Mapping[str, Any] | None) -> float:
    """Seconds to keep retrying a locked store: ``tracking.busy_timeout_s`` (default about a minute)."""
    value = (tracking_cfg or {}).get("busy_timeout_s")
    return DEFAULT_BUSY_TIMEOUT_S if value is None else max(0.0, float(value))


def sqlite_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///`` URI (None for other stores and in-memory databases)."""
    if not uri.startswith("sqlite:///"):
        return None
    path = uri[len("sqlite:///") :].partition("?")[0]
    return Path(os.path.abspath(path)) if path and path != ":memory:" else None


def _named(path: Path) -> str:
    """``path`` as a message names it: relative to the current directory when inside it."""
    with contextlib.suppress(ValueError):
        return str(path.relative_to(Path.cwd()))
    return str(path)


def store_fault(exc: BaseException | None) -> str | None:
    """``"busy"`` or ``"damaged"`` when ``exc`` (or an exception it was raised from) is SQLite saying so, else None."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        text = str(exc).lower()
        if any(word in text for word in _BUSY):
            return "busy"
        if any(word in text for word in _DAMAGED) and (
            "sqlite" in text or type(exc).__module__ == "sqlite3" or "database" in text
        ):
            return "damaged"
        exc = exc.__cause__ or exc.__context__
    return None


def _cause(exc: BaseException) -> str:
    """SQLite's own words, the first line of the innermost error (``database disk image is malformed``)."""
    inner = exc.__cause__ or exc.__context__
    while inner is not None:
        exc, inner = inner, inner.__cause__ or inner.__context__
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


def damaged_error(db: Path, exc: BaseException | str) -> TrackingStoreError:
    name = _named(db)
    return TrackingStoreError(
        f"{name}: the MLflow tracking store is damaged ({exc if isinstance(exc, str) else _cause(exc)}). Fix: move it "
        f"aside (`mv {name} {name}.damaged`) and rerun, which starts a new store (the release and DVC's outputs do not "
        "depend on it; past runs stay in the moved file), or restore it from a backup; `sqlite3 "
        f"{name}.damaged .recover | sqlite3 {name}` may save what is readable."
    )


def busy_error(db: Path, waited: float, tries: int, limit: float) -> TrackingStoreError:
    name = _named(db)
    return TrackingStoreError(
        f"{name}: the MLflow tracking store is locked by another process (database is locked) and stayed locked for "
        f"{waited:.0f} s ({tries} tries). Fix: let that process finish or stop it (`fuser {name}` names it), then "
        f"rerun; tracking.busy_timeout_s={limit:g} sets how long to wait."
    )


def _with_store_retry(call: Callable[[], Any], uri: str, limit: float) -> Any:
    """``call()``; a locked SQLite store is retried with backoff (0.25 s doubling to 8 s) for up to ``limit``
    seconds, then :class:`TrackingStoreError`; a damaged one is :class:`TrackingStoreError` at once."""
    db = sqlite_path(uri)
    if db is None:
        return call()
    start, delay, tries = time.monotonic(), 0.25, 0
    while True:
        tries += 1
        try:
            return call()
        except Exception as exc:
            fault = store_fault(exc)
            if fault == "damaged":
                raise damaged_error(db, exc) from exc
            if fault != "busy":
                raise
            waited = time.monotonic() - start
            if waited + delay > limit:
                raise busy_error(db, waited, tries, limit) from exc
            # one word on the console when the wait starts (it may last tracking.busy_timeout_s), the rest in debug
            (log.warning if tries == 1 else log.debug)(
                "%s is locked by another process: retrying for up to %g s (tracking.busy_timeout_s)", _named(db), limit
            )
            time.sleep(delay)
            delay = min(2 * delay, 8.0)


def check_store(uri: str, limit: float = DEFAULT_BUSY_TIMEOUT_S) -> None:
    """Check a SQLite store before any work (stdlib ``sqlite3``, no MLflow import; once per process and store).

    ``PRAGMA quick_check`` (milliseconds for a store of a few MB) finds a damaged file; a store locked by another
    process is retried as :func:`_with_store_retry` does.

    Raises
    ------
    TrackingStoreError
        Damaged, or locked for longer than ``limit`` seconds.
    """
    import sqlite3

    db = sqlite_path(uri)
    if db is None or str(db) in _CHECKED or not db.exists():
        return

    def quick_check() -> None:
        with contextlib.closing(sqlite3.connect(f"{db.as_uri()}?mode=ro", uri=True, timeout=min(1.0, limit))) as con:
            verdict = [row[0] for row in con.execute("PRAGMA quick_check(3)")]
        if verdict != ["ok"]:
            raise damaged_error(db, "; ".join(map(str, verdict)))

    _with_store_retry(quick_check, uri, limit)
    _CHECKED.add(str(db))


class StoreClient:
    """An :class:`mlflow.MlflowClient` whose calls retry a locked SQLite store and name a damaged one
    (:func:`_with_store_retry`); everything else is the client's own."""

    def __init__(self, client: MlflowClient, uri: str, limit: float) -> None:
        self._client, self._uri, self._limit = client, uri, limit

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._client, name)
        if not callable(attr):
            return attr
        return lambda *args, **kwargs: _with_store_retry(lambda: attr(*args, **kwargs), self._uri, self._limit)

    def __repr__(self) -> str:
        return f"StoreClient({self._uri!r})"


# --------------------------------------------------------------------------- a copied or moved workspace
# MLflow's columns that hold artifact locations (schema of MLflow 3.x; a column missing in another version is skipped)
_LOCATION_COLUMNS = (
    ("experiments", "artifact_location"),
    ("runs", "artifact_uri"),
    ("model_versions", "source"),
    ("model_versions", "storage_location"),
    ("logged_models", "artifact_location"),
)


def relocate_artifacts(uri: str) -> dict[str, int]:
    """Point a copied or moved workspace's own store at its own ``mlartifacts/``.

    MLflow stores absolute artifact locations (``file:///old/ws/mlartifacts/...``). After ``cp -a`` or ``mv`` of a
    workspace, its ``mlflow.db`` still names the old folder: new runs would log, and ``aumesh promote`` register, the
    *old* workspace's artifacts (or nothing, once it is deleted). When the store is the workspace's own (its file
    inside :func:`aumesh.core.provenance.repo_root`) and an experiment's artifact location is another folder's
    ``mlartifacts``, every location under that folder is rewritten to this workspace's ``mlartifacts`` (one
    transaction, under the store's creation lock). Stores outside the workspace (shared stores) are left alone.

    Returns
    -------
    dict
        ``{old prefix: rows rewritten}`` (empty when nothing moved).
    """
    import sqlite3
    from urllib.parse import unquote, urlsplit

    db = sqlite_path(uri)
    if db is None or not db.exists() or str(db) in _RELOCATED:
        return {}
    _RELOCATED.add(str(db))  # once per process: a workspace does not move while a command runs
    try:
        root = provenance.repo_root().resolve()
    except FileNotFoundError:
        return {}
    if not db.resolve().is_relative_to(root):
        return {}
    own = (root / DEFAULT_ARTIFACT_DIR).as_uri()
    moved: dict[str, int] = {}
    with contextlib.closing(sqlite3.connect(db, timeout=5.0)) as con:
        tables = {row[0] for row in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        if "experiments" not in tables:
            return {}  # not an MLflow store yet
        locations = [row[0] for row in con.execute("SELECT artifact_location FROM experiments")]
        olds = set()
        for loc in locations:
            if not loc or not str(loc).startswith("file://"):
                continue
            path = Path(unquote(urlsplit(loc).path))
            base = next((p for p in (path, *path.parents) if p.name == DEFAULT_ARTIFACT_DIR), None)
            if base is not None and base.as_uri() != own and not base.is_relative_to(root):
                olds.add(base.as_uri())
        if not olds:
            return {}
        with con:
            for old in sorted(olds):
                n = 0
                for table, column in _LOCATION_COLUMNS:
                    if table not in tables or column not in {r[1] for r in con.execute(f"PRAGMA table_info({table})")}:
                        continue
                    n += con.execute(
                        f"UPDATE {table} SET {column} = ? || substr({column}, ?) "
                        f"WHERE {column} = ? OR substr({column}, 1, ?) = ?",
                        (own, len(old) + 1, old, len(old) + 1, old + "/"),
                    ).rowcount
                moved[old] = n
    for old, n in moved.items():
        log.warning(
            "this workspace's MLflow store named the artifacts of %s (a copied or moved workspace): "
            "%d locations now point to %s",
            unquote(urlsplit(old).path),
            n,
            own,
        )
    return moved


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

    db_path = Path(os.path.abspath(uri[len("sqlite:///") :].partition("?")[0]))
    db_path.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(f"{db_path}.lock"):
        yield
