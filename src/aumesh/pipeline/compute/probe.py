"""The probe a ``dask.distributed`` cluster's workers run: do they run this stage's aumesh and reach its files?

One cluster serves many workspaces (and many clones): the stages hand their tasks absolute paths and per-run scratch
folders, so every worker must read the data and write the output folder at those paths, and the tasks run the
functions of whatever aumesh the worker imports, so that must be this stage's code. :func:`check_workers` runs
:func:`_probe` on each worker when the stage connects (``Client.run``) and turns the first worker that cannot, or runs
other code, into one line (:class:`aumesh.core.errors.ClusterError`, exit 2) naming the worker, the path or both codes,
and the fix; :class:`LateWorkers` runs the same probe on every worker that joins later (a worker plugin), and stops
the run when one fails it. :func:`first_line` is the one line such an error quotes of an exception. The connection
itself is :mod:`aumesh.pipeline.compute`'s.

The probe travels by value (:func:`_by_value`): its functions are pickled with their code (cloudpickle), not by
their name, so a worker whose aumesh has no such function (an older aumesh, or none) runs it as well and is named
in one line, where it raised ``AttributeError`` before.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import sys
import threading
import uuid
from pathlib import Path
from typing import Any

from aumesh.core import storage
from aumesh.core.errors import ClusterError
from aumesh.pipeline.compute.settings import local_fix

log = logging.getLogger(__name__)


def first_line(err: BaseException) -> str:
    """``err`` in one line, as a :class:`~aumesh.core.errors.ClusterError` quotes it: its type and first line."""
    reason = getattr(err, "reason", None)  # distributed's FutureCancelledError: its reason, not its task's key
    text = [reason] if isinstance(reason, str) and reason else str(err).strip().splitlines()
    return f"{type(err).__name__}: {text[0]}" if text else type(err).__name__


#: Bytes of the data file's start and end the probe compares (a parquet table's first pages and its footer).
_PROBE_BYTES = 65536


def _fingerprint(path: str) -> tuple[int, str]:
    """``(size, sha256 of the first and last 64 KiB)`` of a file: the same file, or another at the same path.

    A local file is read with the standard library alone, so the probe (sent by value, :func:`_by_value`) runs on a
    worker whatever aumesh it has; an object's URL (``paths.data_dir=s3://...``) through :mod:`aumesh.core.storage`,
    imported here, on the worker, only then."""
    if "://" not in path:
        with open(path, "rb") as fh:
            return _hash_ends(fh, os.fstat(fh.fileno()).st_size)
    from aumesh.core import storage

    where = storage.input_path(path)
    with storage.open_input(where) as fh:
        return _hash_ends(fh, storage.size(where))


def _hash_ends(fh, size: int) -> tuple[int, str]:
    """``(size, sha256 of the first and last _PROBE_BYTES)`` of the open binary file ``fh`` of ``size`` bytes."""
    digest = hashlib.sha256(fh.read(_PROBE_BYTES))
    if size > _PROBE_BYTES:
        fh.seek(max(_PROBE_BYTES, size - _PROBE_BYTES))
        digest.update(fh.read())
    return size, digest.hexdigest()


def _aumesh_code() -> dict[str, Any]:
    """The ``aumesh`` package this process imports: ``{"path": its folder, "digest": sha256 of its .py files (their
    paths in the package and their sha256), "files": {path in the package: sha256}}``; path None: no aumesh here.

    The whole package, not the stage's ``dvc.yaml`` deps: the tasks run functions of the stage's import closure (which
    ``dvc.yaml`` lists, tests/test_dvc_deps.py), but the probe has no stage (a sweep, ``aumesh prepare`` outside a DVC
    workspace) and the worker no ``dvc.yaml`` of the driver's; the whole package needs neither, catches every
    difference a pickled-by-reference function could bring (any module) and lets the line name the files that differ.
    Its cost: a change the stage never imports (the CLI) refuses the cluster too, and the fix is the same. Only the
    standard library and the package's files on disk (``importlib``'s spec: the aumesh ``import aumesh`` gets, the
    one already imported if any), so an older aumesh on a worker is digested the same way. ~10 ms for the package's
    ~140 files: on the driver once per process (:func:`_driver_code`), on a worker at each probe (the function
    arrives by value, with no state of its own there).
    """
    import importlib.util

    try:
        spec = importlib.util.find_spec("aumesh")
    except (ImportError, ValueError):
        spec = None
    locations = list(spec.submodule_search_locations or []) if spec is not None else []
    if not locations:
        return {"path": None, "digest": None, "files": {}}
    root = os.path.abspath(locations[0])
    files: dict[str, str] = {}
    for folder, dirs, names in os.walk(root):
        dirs[:] = [d for d in dirs if d != "__pycache__"]
        for name in names:
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                with open(path, "rb") as fh:
                    files[os.path.relpath(path, root).replace(os.sep, "/")] = hashlib.sha256(fh.read()).hexdigest()
    whole = hashlib.sha256("".join(f"{k}\0{v}\n" for k, v in sorted(files.items())).encode())
    return {"path": root, "digest": whole.hexdigest(), "files": files}


@functools.cache
def _driver_code() -> dict[str, Any]:
    """:func:`_aumesh_code` of this (the stage's) process, once."""
    return _aumesh_code()


def _probe(read: str | None, write: str | None, token: str) -> dict[str, Any]:
    """On a worker (``Client.run``, or :class:`LateWorkers`' plugin): its aumesh code (:func:`_aumesh_code`), the
    fingerprint of ``read``, and a file written into ``write`` (named by ``token`` and this process), or the error of
    each (any exception: whatever fails, the code is still compared)."""
    out: dict[str, Any] = {}
    try:
        out["code"] = _aumesh_code()
    except Exception as err:
        out["code_error"] = first_line(err)
    if read is not None:
        try:
            out["read"] = list(_fingerprint(read))
        except Exception as err:
            out["read_error"] = first_line(err)
    if write is not None:
        name = f".aumesh-probe-{token}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        try:
            with open(os.path.join(write, name), "x") as fh:
                fh.write(token)
            out["wrote"] = name
        except Exception as err:
            out["write_error"] = first_line(err)
    return out


def _by_value() -> None:
    """Pickle this module's functions with their code when they are sent to the workers (``cloudpickle``'s
    ``register_pickle_by_value``; ``distributed`` pickles with cloudpickle what comes from such a module), so a worker
    need not import them from its own aumesh: one with an older aumesh, or none, runs the probe too."""
    import cloudpickle  # type: ignore[import-untyped]  # no stubs in the lock

    cloudpickle.register_pickle_by_value(sys.modules[__name__])


def check_workers(client, read: str | Path | None, write: str | Path | None) -> None:
    """A probe on every worker of ``client``'s cluster: it runs this process's aumesh code (the same
    :func:`_aumesh_code` digest), reads ``read`` (the same bytes as this process: the first and last 64 KiB and the
    size) and writes a file into ``write`` that this process then sees.

    Raises
    ------
    ClusterError
        The first worker that cannot, named with its code and this process's, or with the path: the folder must be on
        a filesystem every worker sees at the same path.
    """
    read, write, expected = _expected(read, write)
    token = uuid.uuid4().hex
    _by_value()
    results = client.run(_probe, read, write, token, on_error="return")
    problem = None
    for worker, result in sorted(results.items()):
        problem = problem or _probe_problem(worker, result, read, write, expected, token)
        _remove_probe_file(write, result)
    if problem is not None:
        raise ClusterError(problem)


def _expected(read, write) -> tuple[str | None, str | None, tuple[int, str] | None]:
    """``read`` and ``write`` as absolute paths, and the fingerprint the workers must find at ``read``."""
    read = None if read is None else str(storage.absolute(storage.input_path(read)))
    write = None if write is None else os.path.abspath(write)
    try:  # what the workers must read; a file this process cannot read is the stage's own error, when it reads it
        expected = _fingerprint(read) if read is not None else None
    except OSError:
        expected = None
    return read, write, expected


def _remove_probe_file(write: str | None, result: Any) -> None:
    if write is not None and isinstance(result, dict) and isinstance(result.get("wrote"), str):
        (Path(write) / result["wrote"]).unlink(missing_ok=True)


class LateWorkers:
    """The probe of every worker that joins the cluster while the stage runs (:func:`check_workers`' checks, run by a
    ``distributed`` worker plugin registered by this process, whose ``setup`` runs on each worker as it registers
    with the scheduler, before it takes any task), each result published to this process (a scheduler event).

    A worker that fails it stops the run: :attr:`problem` is its line, every pending result of this client is
    cancelled, and :meth:`check` (after every computation and at the end) raises it. Stopped rather than retired: on a
    shared cluster the worker may be another workspace's, and a scheduler hands any task to any worker, so a cluster
    of two codes serves neither safely (retiring it would take it from the other run too). No result of such a worker
    lands: the worker publishes its probe before it runs a task (``distributed`` sets its plugins up before it
    listens to the scheduler), the scheduler forwards that event to this client before any result of the worker, and
    :meth:`check` runs after the client has handled both.
    """

    def __init__(self, client, read: str | Path | None, write: str | Path | None):
        self.client = client
        self.read, self.write, self.expected = _expected(read, write)
        self.token = uuid.uuid4().hex
        self.topic = self.name = f"aumesh-probe-{self.token}"
        self.problem: str | None = None
        self.joined: list[str] = []
        self._lock = threading.Lock()

    def start(self) -> None:
        """Subscribe to the probes' events, then register the plugin (workers present run it too: probed again)."""
        _by_value()
        self.client.subscribe_topic(self.topic, self._on_probe)
        self.client.register_plugin(_plugin(self.read, self.write, self.token, self.topic), name=self.name)

    def _on_probe(self, event) -> None:
        """A worker's probe result (in the client's event loop): its problem stops the run."""
        msg = event[1] if isinstance(event, (tuple, list)) and len(event) == 2 else event
        worker = str(msg.get("worker")) if isinstance(msg, dict) else "?"
        result = msg.get("result") if isinstance(msg, dict) else None
        problem = _probe_problem(worker, result, self.read, self.write, self.expected, self.token)
        _remove_probe_file(self.write, result)
        with self._lock:
            self.joined.append(worker)
            if problem is None or self.problem is not None:
                return
            self.problem = problem
        for state in list(self.client.futures.values()):  # wake the computation waiting on them
            state.cancel(reason=problem)

    def check(self) -> None:
        """Raise the line of a worker that failed the probe after joining, if any."""
        if self.problem is not None:
            raise ClusterError(self.problem)

    def stop(self) -> None:
        """Unregister the plugin (the scheduler would run it on every later worker) and remove probe files left."""

        def unregister() -> None:
            try:
                self.client.unsubscribe_topic(self.topic)
                self.client.unregister_worker_plugin(self.name)
            except Exception as err:  # the scheduler gone: the plugin went with it
                log.debug("compute: could not unregister %s: %s", self.name, first_line(err))

        # the scheduler drops the plugin at once, then waits for every worker to drop it: a worker that does not
        # answer (paused, or lost) would hold the stage's end, so that wait is bounded
        done = threading.Thread(target=unregister, name="aumesh-unregister", daemon=True)
        done.start()
        done.join(_UNREGISTER_WAIT)
        if self.write is not None:
            for path in Path(self.write).glob(f".aumesh-probe-{self.token}-*"):
                path.unlink(missing_ok=True)


#: Seconds :meth:`LateWorkers.stop` waits for the workers to drop the plugin (the scheduler has dropped it already).
_UNREGISTER_WAIT = 2.0


def _plugin(read: str | None, write: str | None, token: str, topic: str):
    """The worker plugin of :class:`LateWorkers`: a class made here, so that it is pickled by value too (and
    ``distributed`` is imported only when a cluster is used)."""
    from distributed import WorkerPlugin

    class AumeshProbe(WorkerPlugin):
        idempotent = False

        def setup(self, worker) -> None:
            try:
                result: dict[str, Any] = _probe(read, write, token)
            except BaseException as err:  # never a worker left unprobed: the error is its result
                result = {"error": first_line(err)}
            worker.log_event(topic, {"worker": worker.address, "result": result})

    return AumeshProbe()


def _probe_problem(
    worker: str, result: Any, read: str | None, write: str | None, expected: tuple[int, str] | None, token: str
) -> str | None:
    """What a worker's probe found wrong (:func:`_probe`), as the one line to print; None: nothing."""
    if isinstance(result, BaseException):
        cause: str | None = first_line(result)
    elif not isinstance(result, dict):
        cause = f"it returned {result!r:.100}"
    else:
        cause = str(result["error"]) if "error" in result else None
    if cause is not None:
        return (
            f"worker {worker} cannot run aumesh's probe ({cause}): every worker must run the aumesh of this "
            f"workspace. Fix: start the workers from the project's environment (.venv/bin/dask worker), or "
            f"{local_fix()}."
        )
    code = _other_code(worker, result)
    if code is not None:
        return code
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


def _other_code(worker: str, result: dict[str, Any]) -> str | None:
    """The line for a worker whose aumesh is not this process's (:func:`_aumesh_code`); None: the same code."""
    ours = _driver_code()
    theirs = result.get("code")
    if isinstance(theirs, dict) and theirs.get("digest") == ours["digest"]:
        return None
    here = f"this stage's {ours['path']} (code {str(ours['digest'])[:12]})"
    fix = (
        f"Fix: start the workers with this workspace's aumesh (its environment's `dask worker`, or "
        f"PYTHONPATH={os.path.dirname(str(ours['path']))}), or {local_fix()}."
    )
    if not isinstance(theirs, dict):
        return (
            f"worker {worker} cannot digest its aumesh ({result.get('code_error', '?')}) to compare with {here}. {fix}"
        )
    if theirs.get("path") is None:
        return f"worker {worker} imports no aumesh, where {here} sends it tasks. {fix}"
    files = theirs.get("files") or {}
    differ = sorted(k for k in {*files, *ours["files"]} if files.get(k) != ours["files"].get(k))
    shown = ", ".join(differ[:3]) + (f" and {len(differ) - 3} more" if len(differ) > 3 else "")
    return (
        f"worker {worker} runs other aumesh code: {theirs['path']} (code {str(theirs['digest'])[:12]}), not "
        f"{here}; they differ in {shown}. Its results would be another code's. {fix}"
    )


def _written_by_probe(path: Path, token: str) -> bool:
    try:
        return path.read_text() == token
    except OSError:
        return False


def _unseen(worker: str, verb: str, path: str | None, cause: str) -> str:
    # an object store: the cause (core.storage's line) carries its own fix
    if path is not None and storage.is_url(path):
        return f"worker {worker} cannot {verb} {path}: {cause}"
    folder = path if verb == "write into" or path is None else os.path.dirname(path)
    return (
        f"worker {worker} cannot {verb} {path} ({cause}): the folder {folder} must be on a filesystem every worker "
        f"sees at the same path. Fix: start the workers where the workspace is mounted at that path (README, "
        f'"Scale out"), or {local_fix()}.'
    )
