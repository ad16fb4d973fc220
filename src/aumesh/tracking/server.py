"""A team's MLflow tracking server: ``aumesh server`` / ``make mlflow-server-postgres``.

One ``mlflow server`` with a database backend (PostgreSQL for a team; SQLite works for one person) and served
artifacts: clients upload and download run artifacts through the server (``mlflow-artifacts:/``), so nobody needs the
server's disk mounted. The backend URI gets the installed PostgreSQL driver
(:func:`aumesh.tracking.mlflow_store.database_uri`). Clients point at it with ``MLFLOW_TRACKING_URI`` or
``aumesh.local.yaml`` (:mod:`aumesh.core.settings`).
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator, Sequence
from pathlib import Path


def server_command(
    backend_store_uri: str,
    artifacts_destination: str,
    host: str = "127.0.0.1",
    port: int = 5000,
    workers: int = 2,
    allowed_hosts: str | None = None,
    extra: Sequence[str] = (),
) -> list[str]:
    """The ``mlflow server`` command line (this interpreter's MLflow).

    Parameters
    ----------
    backend_store_uri : str
        ``postgresql://user@host:5432/db`` (password: ``~/.pgpass`` or ``PGPASSWORD``, not the command line),
        or ``sqlite:///path``.
    artifacts_destination : str
        Where the server keeps artifacts: a folder (made absolute) or an object store URI (``s3://bucket/mlflow``).
    host, port : str, int
        The address to listen on: ``0.0.0.0`` serves the lab's network.
    workers : int
        Server worker processes.
    allowed_hosts : str, optional
        MLflow's DNS-rebinding guard accepts ``localhost`` and private IPs by default; a host name teammates use
        (``mlflow.lab.example:5000``) must be listed.
    extra : sequence of str
        More ``mlflow server`` options, as they are.
    """
    from aumesh.tracking.mlflow_store import database_uri

    if "://" not in artifacts_destination:
        artifacts_destination = str(Path(artifacts_destination).expanduser().resolve())
    cmd = [
        sys.executable,
        "-m",
        "mlflow",
        "server",
        "--backend-store-uri",
        database_uri(backend_store_uri),
        "--serve-artifacts",
        "--artifacts-destination",
        artifacts_destination,
        "--host",
        host,
        "--port",
        str(port),
        "--workers",
        str(workers),
    ]
    if allowed_hosts:
        cmd += ["--allowed-hosts", allowed_hosts]
    return cmd + list(extra)


def server_environment() -> dict[str, str]:
    """The server's environment: telemetry off, no GenAI job runner (it halves start-up time and CPU)."""
    return dict(
        os.environ, MLFLOW_DISABLE_TELEMETRY="true", DO_NOT_TRACK="true", MLFLOW_SERVER_ENABLE_JOB_EXECUTION="false"
    )


def scoring_command(
    model_uri: str, host: str = "127.0.0.1", port: int = 5001, workers: int = 1, timeout_s: int | None = None
) -> list[str]:
    """The ``mlflow models serve`` command line of README "Use the model" (this interpreter's MLflow, the model run in
    this environment: ``--env-manager local``, since it imports aumesh).

    Parameters
    ----------
    model_uri : str
        ``models:/aumesh-au-to-mesh@champion``, ``runs:/<id>/model`` or a model folder.
    host, port : str, int
        The address to listen on.
    workers : int
        Scoring worker processes (uvicorn's).
    timeout_s : int, optional
        Seconds a request may take before the server answers HTTP 504 (``--timeout``; MLflow's default 60).
    """
    return [
        sys.executable,
        "-m",
        "mlflow",
        "models",
        "serve",
        "-m",
        model_uri,
        "--env-manager",
        "local",
        "-h",
        host,
        "-p",
        str(port),
        "-w",
        str(workers),
        *(["-t", str(int(timeout_s))] if timeout_s is not None else []),
    ]


def scoring_environment() -> dict[str, str]:
    """The scoring server's environment: this interpreter's ``bin/`` first on PATH (MLflow execs ``uvicorn`` from PATH,
    as in an activated venv) and telemetry off."""
    env = server_environment()
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    return env


@contextlib.contextmanager
def scoring_server(
    model_uri: str, log_path: str | Path, timeout_s: int | None = None, start_timeout_s: float = 180.0
) -> Iterator[str]:
    """:func:`scoring_command` started on a free loopback port (its own process group, output to ``log_path``) and
    waited for until ``/ping`` answers; yields its URL, stops the whole group (uvicorn's workers too) after.

    Raises
    ------
    RuntimeError
        The server exited, or did not answer within ``start_timeout_s``: the end of its log.
    """
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    url = f"http://127.0.0.1:{port}"
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            scoring_command(model_uri, port=port, timeout_s=timeout_s),
            env=scoring_environment(),
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            deadline = time.monotonic() + start_timeout_s
            while True:
                try:
                    with urllib.request.urlopen(f"{url}/ping", timeout=2) as resp:
                        if resp.status == 200:
                            break
                except (urllib.error.URLError, ConnectionError, OSError):
                    pass
                if proc.poll() is not None or time.monotonic() > deadline:
                    why = "exited" if proc.poll() is not None else f"did not answer in {start_timeout_s:g} s"
                    raise RuntimeError(f"mlflow models serve {why}: {Path(log_path).read_text()[-3000:]}")
                time.sleep(0.5)
            yield url
        finally:
            _stop_group(proc)


def _stop_group(proc: subprocess.Popen) -> None:
    """SIGTERM to the process group, SIGKILL after 10 s; reaped."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        if proc.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=10)
