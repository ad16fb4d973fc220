"""The probe a ``dask.distributed`` cluster's workers run when a stage connects: can they reach this run's files?

One cluster serves many workspaces: the stages hand their tasks absolute paths and per-run scratch folders, so every
worker must read the data and write the output folder at those paths. :func:`check_workers` runs :func:`_probe` on
each worker (``Client.run``) and turns the first worker that cannot into one line
(:class:`aumesh.core.errors.ClusterError`, exit 2) naming the worker, the path and the fix; :func:`first_line` is the
one line such an error quotes of an exception. The connection itself is :mod:`aumesh.pipeline.compute`'s.
"""

from __future__ import annotations

import hashlib
import os
import uuid
from pathlib import Path
from typing import Any

from aumesh.core import storage
from aumesh.core.errors import ClusterError
from aumesh.pipeline.compute.settings import local_fix


def first_line(err: BaseException) -> str:
    """``err`` in one line, as a :class:`~aumesh.core.errors.ClusterError` quotes it: its type and first line."""
    reason = getattr(err, "reason", None)  # distributed's FutureCancelledError: its reason, not its task's key
    text = [reason] if isinstance(reason, str) and reason else str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0]}" if text else type(err).__name__


#: Bytes of the data file's start and end the probe compares (a parquet table's first pages and its footer).
_PROBE_BYTES = 65536


def _fingerprint(path: str) -> tuple[int, str]:
    """``(size, sha256 of the first and last 64 KiB)`` of a file: the same file, or another at the same path."""
    where = storage.input_path(path)  # a local file, or an object's URL (paths.data_dir=s3://...)
    with storage.open_input(where) as fh:
        size = storage.size(where)
        digest = hashlib.sha256(fh.read(_PROBE_BYTES))
        if size > _PROBE_BYTES:
            fh.seek(max(_PROBE_BYTES, size - _PROBE_BYTES))
            digest.update(fh.read())
    return size, digest.hexdigest()


def _probe(read: str | None, write: str | None, token: str) -> dict[str, Any]:
    """On a worker (``Client.run``): the fingerprint of ``read``, and a file written into ``write`` (named by ``token``
    and this process), or the error of each."""
    out: dict[str, Any] = {}
    if read is not None:
        try:
            out["read"] = _fingerprint(read)
        except OSError as err:
            out["read_error"] = first_line(err)
    if write is not None:
        name = f".aumesh-probe-{token}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            with open(os.path.join(write, name), "x") as fh:
                fh.write(token)
            out["wrote"] = name
        except OSError as err:
            out["write_error"] = first_line(err)
    return out


def check_workers(client, read: str | Path | None, write: str | Path | None) -> None:
    """A probe on every worker of ``client``'s cluster: it reads ``read`` (the same bytes as this process: the first
    and last 64 KiB and the size) and writes a file into ``write`` that this process then sees.

    Raises
    ------
    ClusterError
        The first worker that cannot, named with the path: the folder must be on a filesystem every worker sees at
        the same path.
    """
    if read is None and write is None:
        return
    read = None if read is None else str(storage.absolute(storage.input_path(read)))
    write = None if write is None else os.path.abspath(write)
    token = uuid.uuid4().hex
    try:  # what the workers must read; a file this process cannot read is the stage's own error, when it reads it
        expected = _fingerprint(read) if read is not None else None
    except OSError:
        expected = None
    results = client.run(_probe, read, write, token, on_error="return")
    try:
        problems = (
            _probe_problem(worker, result, read, write, expected, token) for worker, result in sorted(results.items())
        )
        problem = next((p for p in problems if p), None)
    finally:
        for result in results.values():
            if write is not None and isinstance(result, dict) and "wrote" in result:
                (Path(write) / result["wrote"]).unlink(missing_ok=True)
    if problem is not None:
        raise ClusterError(problem)


def _probe_problem(
    worker: str, result: Any, read: str | None, write: str | None, expected: tuple[int, str] | None, token: str
) -> str | None:
    """What a worker's probe found wrong (:func:`_probe`), as the one line to print; None: nothing."""
    if isinstance(result, BaseException):  # the probe did not run: no aumesh there, or another version of it
        return (
            f"worker {worker} cannot run aumesh's probe ({first_line(result)}): every worker must run the aumesh "
            f"of this workspace. Fix: start the workers from the project's environment (.venv/bin/dask worker)."
        )
    if "read_error" in result:
        return _unseen(worker, "read", read, result["read_error"])
    if expected is not None and tuple(result["read"]) != expected:
        size = result["read"][0]
        return _unseen(
            worker,
            "read",
            read,
            f"another file there: {size} bytes, here {expected[0]}"
            if size != expected[0]
            else "another file there: other bytes",
        )
    if "write_error" in result:
        return _unseen(worker, "write into", write, result["write_error"])
    if write is not None and not _written_by_probe(Path(write) / result["wrote"], token):
        return _unseen(worker, "write into", write, "what it wrote there is not seen here")
    return None


def _written_by_probe(path: Path, token: str) -> bool:
    try:
        return path.read_text() == token
    except OSError:
        return False


def _unseen(worker: str, verb: str, path: str | None, cause: str) -> str:
    folder = path if verb == "write into" or path is None else os.path.dirname(path)
    return (
        f"worker {worker} cannot {verb} {path} ({cause}): the folder {folder} must be on a filesystem every worker "
        f"sees at the same path. Fix: start the workers where the workspace is mounted at that path (README, "
        f'"Scale out"), or {local_fix()}.'
    )
