"""The tracking server's connection: checked before any work, MLflow's retries bounded, a lost server in one line.

MLflow's own defaults retry an HTTP request 7 times with a backoff factor of 2 and a 120 s timeout
(``mlflow.environment_variables``: ``MLFLOW_HTTP_REQUEST_MAX_RETRIES``, ``..._BACKOFF_FACTOR``, ``..._TIMEOUT``): a wrong
port took 4.5 min and a server stopped mid-evaluate 25 min of retry warnings, each ending in a ~100-line traceback.
Here:

* :func:`check_server` (called through :func:`aumesh.tracking.mlflow_store.check_tracking` by every command that
  tracks, before any work): ``GET /health`` of an ``http(s)`` server, a connect to a database URI, each within
  ``tracking.check_timeout_s``; a failure is one :class:`TrackingServerError` naming the URI and where it came from
  (:func:`aumesh.tracking.mlflow_store.locate_tracking_uri`).
* :func:`bound_requests` sets MLflow's retry and timeout variables from ``tracking.request_timeout_s``,
  ``tracking.max_retries`` and ``tracking.backoff_factor`` in this process (and so in the tracking helper process,
  which builds its client the same way), unless the user set the variable.
* :class:`ServerClient` turns a request that failed after those retries into the same one line.

No MLflow import here: the check runs before the stage has imported anything heavy.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import threading
from collections.abc import Callable, Iterator, Mapping
from typing import TYPE_CHECKING, Any

from aumesh.core.errors import UserError

if TYPE_CHECKING:  # pragma: no cover
    from mlflow import MlflowClient

#: ``tracking.*`` keys -> (MLflow's environment variable, default). The defaults bound one request to a server that
#: stopped answering at (max_retries + 1) x request_timeout_s + the backoff (0, 2, 4... x backoff_factor s, + up to
#: 1 s of MLflow's jitter each): 3 x 20 + 2 + 2 = 64 s; a server that is gone (connection refused) fails in ~3 s.
REQUEST_BOUNDS = {
    "request_timeout_s": ("MLFLOW_HTTP_REQUEST_TIMEOUT", 20),
    "max_retries": ("MLFLOW_HTTP_REQUEST_MAX_RETRIES", 2),
    "backoff_factor": ("MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR", 1),
}
DEFAULT_CHECK_TIMEOUT_S = 5.0
_SET_HERE: dict[str, str] = {}  # the variables this process set (a later config may change them; the user's, never)
log = logging.getLogger(__name__)


#: where a tracking URI came from (:func:`aumesh.tracking.mlflow_store.locate_tracking_uri`), as messages name it
ENV_SOURCE = "the MLFLOW_TRACKING_URI environment variable"
LOCAL_SOURCE = "tracking.tracking_uri in {path}"
CONF_SOURCE = "tracking.tracking_uri of the configuration (conf/tracking/mlflow.yaml, params.yaml)"
DEFAULT_SOURCE = "the default: the workspace's own store"


class TrackingServerError(UserError):
    """The tracking server or database cannot be reached, or stopped answering; the message names the URI, where it
    came from, what happened and (last) the fix."""

    def __init__(self, message: str, fix: str = "") -> None:
        super().__init__(message, fix)  # both in args: the error crosses from the tracking helper process pickled
        self.message, self.fix = message, fix

    def __str__(self) -> str:
        return f"{self.message}. {self.fix}." if self.fix else self.message

    @property
    def names_run(self) -> bool:
        """Whether the message already says what became of the MLflow run (:func:`run_fate`)."""
        return _RUN_NOTE in self.message or _NO_RUN in self.message

    def noted(self, note: str) -> TrackingServerError:
        """The same error with ``note`` (what became of the run, of the outputs) before the fix."""
        return TrackingServerError(f"{self.message}; {note}", self.fix)


_RUN_NOTE, _NO_RUN = "MLflow run ", "no MLflow run was opened"


def run_fate(run_id: str | None, marked: bool | None) -> str:
    """What became of the MLflow run after its server was lost, for the one line (``marked``: whether it could be
    marked FAILED; None: no run was opened)."""
    if marked is None or run_id is None:
        return _NO_RUN
    if marked:
        return f"{_RUN_NOTE}{run_id} marked FAILED"
    return (
        f"{_RUN_NOTE}{run_id} could not be marked FAILED (the server does not answer; the next run on this machine "
        "marks it KILLED)"
    )


# --------------------------------------------------------------------------- naming the store
def shown_uri(uri: str) -> str:
    """``uri`` as a message shows it: the password (``user:secret@host``) replaced by ``***``."""
    from urllib.parse import urlsplit, urlunsplit

    parts = urlsplit(uri)
    if not parts.password:
        return uri
    user = parts.username or ""
    host = parts.hostname or ""
    netloc = f"{user}:***@{host}" + (f":{parts.port}" if parts.port else "")
    return urlunsplit(parts._replace(netloc=netloc))


def is_server(uri: str) -> bool:
    """An MLflow tracking server (``http(s)://``), as opposed to a database or a local store."""
    return uri.startswith(("http://", "https://"))


#: database URI schemes (SQLAlchemy's, with or without ``+driver``) checked by a connect, and their driver's timeout
#: keyword: libpq's ``connect_timeout`` (psycopg2, psycopg) covers the whole connection, authentication included
_DATABASES = {"postgresql": "connect_timeout", "postgres": "connect_timeout", "mysql": "connect_timeout"}


def database_scheme(uri: str) -> str | None:
    """``postgresql`` for ``postgresql+psycopg2://...`` (a database :func:`check_server` connects to), else None."""
    scheme = uri.partition("://")[0].split("+")[0]
    return scheme if "://" in uri and scheme in _DATABASES else None


def _fix(uri: str, source: str) -> str:
    """What to change, where the URI came from (:func:`aumesh.tracking.mlflow_store.locate_tracking_uri`)."""
    what = "the server" if is_server(uri) else "the database"
    if source == ENV_SOURCE:
        where = "correct MLFLOW_TRACKING_URI (unset, the workspace's own store is used)"
    elif source.startswith(LOCAL_SOURCE.partition("{")[0]):
        where = f"correct {source}"
    else:
        where = "correct tracking.tracking_uri in conf/tracking/mlflow.yaml (aumesh.local.yaml for this machine only)"
    return f"Fix: start {what} (README, Tracking) or {where}, then run again"


# --------------------------------------------------------------------------- the check before any work
def check_timeout(tracking_cfg: Mapping[str, Any] | None) -> float:
    """Seconds :func:`check_server` waits: ``tracking.check_timeout_s`` (default 5)."""
    value = (tracking_cfg or {}).get("check_timeout_s")
    return DEFAULT_CHECK_TIMEOUT_S if value is None else max(0.1, float(value))


def check_server(
    uri: str, source: str, timeout: float = DEFAULT_CHECK_TIMEOUT_S, consequence: str = "nothing was run"
) -> None:
    """Check that a tracking server or database answers, within ``timeout`` seconds in all (name lookup included).

    Parameters
    ----------
    uri : str
        The resolved tracking URI: ``http(s)://`` (``GET /health``, MLflow's liveness endpoint: 200 ``OK``; 401/403
        also pass, an authenticating proxy answered) or a database URI (a SQLAlchemy connect with the driver's
        connect timeout). Other stores (SQLite, ``file:``, ``databricks``) are not checked here.
    source : str
        Where ``uri`` came from (named in the message).
    timeout : float
    consequence : str
        What the message says became of the command's work (default: nothing was run: the check before any work).

    Raises
    ------
    TrackingServerError
        Refused, unknown host, no answer within ``timeout`` (something else listening?), an HTTP error or a database
        that refuses the connection; one line naming the URI, its source and the fix.
    """
    if is_server(uri):
        probe: Callable[[], str | None] = lambda: _probe_http(uri, timeout)  # noqa: E731
        what = "tracking server"
    elif database_scheme(uri):
        probe = lambda: _probe_database(uri, timeout)  # noqa: E731
        what = "tracking database"
    else:
        return
    outcome: list[str | None] = []
    failure: list[BaseException] = []

    def run() -> None:
        try:
            outcome.append(probe())
        except BaseException as exc:  # pragma: no cover - the probes catch what they expect
            failure.append(exc)

    # a thread, so that the bound covers the host name lookup too (getaddrinfo has no timeout of its own)
    worker = threading.Thread(target=run, name="aumesh-tracking-check", daemon=True)
    worker.start()
    worker.join(timeout + 1.0)
    if failure:
        raise failure[0]
    problem = outcome[0] if outcome else f"did not answer within {timeout:g} s (tracking.check_timeout_s)"
    if problem:
        raise TrackingServerError(
            f"{what} {shown_uri(uri)} (from {source}) {problem}; {consequence}", _fix(uri, source)
        )


def _probe_http(uri: str, timeout: float) -> str | None:
    """None when ``GET <uri>/health`` answers as an MLflow server does, else what went wrong (for the message)."""
    import socket
    import urllib.error
    import urllib.request
    from urllib.parse import urlsplit

    port = urlsplit(uri).port or (443 if uri.startswith("https") else 80)
    context = None
    if uri.startswith("https"):  # as MLflow's client verifies the server (its environment variables)
        import ssl

        if os.environ.get("MLFLOW_TRACKING_INSECURE_TLS", "").lower() == "true":
            context = ssl._create_unverified_context()
        elif os.environ.get("MLFLOW_TRACKING_SERVER_CERT_PATH"):
            context = ssl.create_default_context(cafile=os.environ["MLFLOW_TRACKING_SERVER_CERT_PATH"])
    try:
        with urllib.request.urlopen(f"{uri.rstrip('/')}/health", timeout=timeout, context=context) as resp:
            resp.read(64)
        return None
    except urllib.error.HTTPError as err:
        if err.code in (401, 403):  # an authenticating proxy in front of the server answered: it is there
            return None
        return f"answered GET /health with HTTP {err.code} {err.reason} (another service on port {port}?)"
    except urllib.error.URLError as err:
        reason = err.reason
        if isinstance(reason, socket.gaierror):
            return f"has a host name that does not resolve ({reason.strerror or reason})"
        if isinstance(reason, ConnectionRefusedError):
            return f"refused the connection (nothing listens on port {port})"
        if isinstance(reason, TimeoutError):
            return _silent(timeout, port)
        return f"could not be reached ({reason})"
    except TimeoutError:
        return _silent(timeout, port)
    except (ConnectionError, OSError) as err:  # reset or closed by something that is not an HTTP server
        return (
            f"did not answer GET /health as an HTTP server ({type(err).__name__}: {err}; another service on port "
            f"{port}?)"
        )


def _silent(timeout: float, port: int) -> str:
    return (
        f"accepted the connection but did not answer GET /health within {timeout:g} s (tracking.check_timeout_s; "
        f"another service on port {port}, or a server that hangs?)"
    )


def _probe_database(uri: str, timeout: float) -> str | None:
    """None when the database accepts a connection within ``timeout``, else the driver's first line."""
    from sqlalchemy import create_engine
    from sqlalchemy.exc import ArgumentError, NoSuchModuleError, SQLAlchemyError
    from sqlalchemy.pool import NullPool

    keyword = _DATABASES[str(database_scheme(uri))]
    try:
        engine = create_engine(uri, poolclass=NullPool, connect_args={keyword: max(2, math.ceil(timeout))})
        with engine.connect():
            pass
        engine.dispose()
        return None
    except (ArgumentError, NoSuchModuleError) as err:
        return f"is not a URI SQLAlchemy can open ({err})"
    except SQLAlchemyError as err:
        inner = getattr(err, "orig", None) or err
        first = str(inner).strip().splitlines()[0] if str(inner).strip() else type(inner).__name__
        return f"did not accept a connection ({first.removeprefix('(psycopg2.OperationalError) ')})"


# --------------------------------------------------------------------------- MLflow's retries, bounded
def request_bounds(tracking_cfg: Mapping[str, Any] | None) -> dict[str, str]:
    """MLflow's environment variables for ``tracking.request_timeout_s``, ``max_retries`` and ``backoff_factor``
    (whole numbers: MLflow reads them as ``int``)."""
    cfg = tracking_cfg or {}
    bounds = {}
    for key, (variable, default) in REQUEST_BOUNDS.items():
        value = cfg.get(key)
        value = default if value is None else value
        bounds[variable] = str(max(1 if key == "request_timeout_s" else 0, math.ceil(float(value))))
    return bounds


def bound_requests(tracking_cfg: Mapping[str, Any] | None) -> dict[str, str]:
    """Set :func:`request_bounds` in this process's environment, except a variable the user set; return what is in
    force. Also keeps urllib3's "Retrying (Retry(total=...))" warnings, one per attempt, off the console (``-vv``
    shows them): the failure is one line at the end."""
    for variable, value in request_bounds(tracking_cfg).items():
        if variable not in os.environ or os.environ[variable] == _SET_HERE.get(variable):
            os.environ[variable] = _SET_HERE[variable] = value
    retries = logging.getLogger("urllib3.connectionpool")
    if retries.level == logging.NOTSET and logging.getLogger().getEffectiveLevel() > logging.DEBUG:
        retries.setLevel(logging.ERROR)
    return {variable: os.environ[variable] for variable, _ in REQUEST_BOUNDS.values()}


def bound_description() -> str:
    """The bounds in force, as the message names them (``3 tries of up to 20 s``)."""
    tries = int(os.environ.get("MLFLOW_HTTP_REQUEST_MAX_RETRIES", REQUEST_BOUNDS["max_retries"][1])) + 1
    timeout = os.environ.get("MLFLOW_HTTP_REQUEST_TIMEOUT", REQUEST_BOUNDS["request_timeout_s"][1])
    return f"{tries} tr{'y' if tries == 1 else 'ies'} of up to {timeout} s (tracking.max_retries, request_timeout_s)"


@contextlib.contextmanager
def no_retries() -> Iterator[None]:
    """One attempt per request inside (the server was lost: marking the run FAILED is tried once, not retried for the
    whole bound again); the variable as it was after."""
    variable = REQUEST_BOUNDS["max_retries"][0]
    before = os.environ.get(variable)
    os.environ[variable] = "0"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop(variable, None)
        else:
            os.environ[variable] = before


# --------------------------------------------------------------------------- a server lost mid-run
def lost_reason(exc: BaseException | None) -> str | None:
    """What MLflow's client met when the server stopped answering (``connection refused``, ``no answer within
    20 s``...), None for any other error (a bug, a refused value: its own message stands).

    MLflow's REST client raises ``MlflowException("API request to <url> failed with exception ...")`` after its
    retries (``mlflow.utils.rest_utils.http_request``), with the ``requests`` error as its context; a database
    store raises SQLAlchemy's ``OperationalError``.
    """
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        text = str(exc)
        name = type(exc).__name__
        if isinstance(exc, TrackingServerError):
            return None
        if text.startswith("API request to ") and " failed with " in text:
            lowered = text.lower()
            if "refused" in lowered:
                return "connection refused"
            if "timeout" in lowered or "timed out" in lowered:
                return f"no answer within {os.environ.get('MLFLOW_HTTP_REQUEST_TIMEOUT', '?')} s"
            if "name or service not known" in lowered or "nodename nor servname" in lowered:
                return "host name does not resolve"
            if "error code 5" in lowered:
                return "the server answers with an HTTP 5xx error (its database?)"
            return "connection lost"
        if name == "OperationalError" and type(exc).__module__.startswith(("sqlalchemy", "psycopg", "pymysql")):
            first = text.strip().splitlines()[0] if text.strip() else name
            return f"database error: {first.removeprefix('(psycopg2.OperationalError) ')}"
        exc = exc.__cause__ or exc.__context__
    return None


def lost_error(uri: str, source: str, exc: BaseException) -> TrackingServerError:
    """The one line for a server or database that stopped answering during a command."""
    what = "tracking server" if is_server(uri) else "tracking store"
    bound = f" after {bound_description()}" if is_server(uri) else ""
    return TrackingServerError(
        f"{what} {shown_uri(uri)} (from {source}) stopped answering ({lost_reason(exc)}){bound}", _fix(uri, source)
    )


class ServerClient:
    """An :class:`mlflow.MlflowClient` on a server or database whose calls raise :class:`TrackingServerError` (one
    line) when the server stopped answering after MLflow's bounded retries; everything else is the client's own."""

    def __init__(self, client: MlflowClient, uri: str, source: str) -> None:
        self._client, self._uri, self._source = client, uri, source

    def __getattr__(self, name: str) -> Any:
        attr = getattr(self._client, name)
        if not callable(attr):
            return attr

        def call(*args: Any, **kwargs: Any) -> Any:
            try:
                return attr(*args, **kwargs)
            except Exception as exc:
                if lost_reason(exc) is None:
                    raise
                raise lost_error(self._uri, self._source, exc) from exc

        return call

    def __repr__(self) -> str:
        return f"ServerClient({shown_uri(self._uri)!r})"
