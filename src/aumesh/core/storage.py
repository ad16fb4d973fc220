"""Where the input tables are read: a local folder, or an object store (``paths.data_dir=s3://bucket/prefix``).

The seam every reader of ``paths.data_dir`` goes through (the ingest stage's listing, its headers, byte ranges and
parquet footers, the Dask workers' tasks and the cluster probe): :func:`list_inputs`, :func:`open_input`,
:func:`read_range`, :func:`size`, :func:`exists`. A local path keeps its own fast path (``open``, ``os.stat``,
``Path.glob``: the same calls as before the seam); a URL (``scheme://...``) is read through fsspec (``s3://``:
s3fs, installed by the ``s3`` extra of the lock).

Credentials and the endpoint come from the environment, never the config (``params.yaml`` is committed and recorded
in MLflow): ``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY`` (or a profile, ``AWS_PROFILE``), ``AWS_ENDPOINT_URL``
for a server other than AWS (MinIO, Ceph, moto), ``AWS_DEFAULT_REGION``; botocore reads them, in the stage and in
each Dask worker (the workers' own environment: nothing is shipped to them). A missing bucket or key, no
credentials, a refused request or an endpoint that does not answer is one line, a :class:`StorageError` naming the
URL and the fix.

A URL is held as an :class:`ObjectPath` (``pathlib`` would fold ``s3://`` into ``s3:/``); :func:`input_path` gives
``Path`` for a local path and :class:`ObjectPath` for a URL.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from aumesh.core.errors import UserError
from aumesh.core.io import absolute as _absolute

_SCHEME = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*)://")
#: Seconds botocore waits for a connection to the endpoint, and attempts in all: an endpoint that is down or a wrong
#: ``AWS_ENDPOINT_URL`` fails in seconds (botocore's defaults: 60 s and several retries with backoff).
CONNECT_TIMEOUT = 5
MAX_ATTEMPTS = 2
#: Bytes a remote file fetches ahead of a read (fsspec's readahead cache): a CSV header, a parquet footer and its
#: column chunks in a few requests each (s3fs's default, 50 MB, would fetch far more than a footer needs).
BLOCK_SIZE = 8 << 20
ENV_FIX = (
    "set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY (or AWS_PROFILE), and AWS_ENDPOINT_URL for a server other than "
    "AWS, in the environment of the stage and of every Dask worker (never in the config)"
)


class StorageError(UserError, OSError):
    """An object store that cannot serve an input: no bucket, no such key, no credentials, access refused, the
    endpoint unreachable; the message names the URL and the fix. An ``OSError`` too, as a local file's failure is
    (the cluster probe reports it per worker)."""

    def __str__(self) -> str:  # the message alone, not OSError's "[Errno ...]"
        return str(self.args[0]) if self.args else ""


@dataclass(frozen=True)
class ObjectPath:
    """An object's URL (``s3://bucket/prefix/name.csv``) with the few ``pathlib`` names the readers use."""

    url: str

    @property
    def name(self) -> str:
        return self.url.rstrip("/").rsplit("/", 1)[-1]

    @property
    def suffix(self) -> str:
        name = self.name
        return name[name.rfind(".") :] if "." in name.lstrip(".") else ""

    @property
    def stem(self) -> str:
        return self.name[: len(self.name) - len(self.suffix)]

    @property
    def parent(self) -> ObjectPath:
        return ObjectPath(self.url.rstrip("/").rsplit("/", 1)[0])

    def with_name(self, name: str) -> ObjectPath:
        return self.parent / name

    def __truediv__(self, other: str) -> ObjectPath:
        return ObjectPath(f"{self.url.rstrip('/')}/{other}")

    def __str__(self) -> str:
        return self.url

    def __lt__(self, other: ObjectPath) -> bool:  # by parts, as Path sorts: the same order as the tables on disk
        return self.url.split("/") < other.url.split("/")


InputPath = Path | ObjectPath


def is_url(path: str | Path | ObjectPath) -> bool:
    """``path`` names an object store (``scheme://...``), not a local file."""
    return isinstance(path, ObjectPath) or (isinstance(path, str) and _SCHEME.match(path) is not None)


def input_path(path: str | Path | ObjectPath) -> InputPath:
    """``path`` as the readers hold it: an :class:`ObjectPath` for a URL, else a ``Path``."""
    if isinstance(path, ObjectPath | Path):
        return path
    return ObjectPath(path.rstrip("/")) if is_url(path) else Path(path)


def absolute(path: InputPath) -> InputPath:
    """:func:`aumesh.core.io.absolute` of a local path (what a Dask worker elsewhere needs); a URL as it is."""
    return path if isinstance(path, ObjectPath) else _absolute(path)


def _protocol(url: str) -> str:
    match = _SCHEME.match(url)
    return match.group(1) if match else "file"


def filesystem(url: str) -> Any:
    """The fsspec filesystem of ``url``'s scheme, configured from the environment (endpoint, credentials), with
    :data:`CONNECT_TIMEOUT` and :data:`MAX_ATTEMPTS`. fsspec caches one instance per process and arguments (a
    forked worker makes its own)."""
    protocol = _protocol(url)
    try:
        import fsspec

        if protocol in ("s3", "s3a"):
            endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL") or None
            config = {
                "connect_timeout": CONNECT_TIMEOUT,
                "retries": {"max_attempts": MAX_ATTEMPTS, "mode": "standard"},
            }
            return fsspec.filesystem("s3", endpoint_url=endpoint, config_kwargs=config, default_block_size=BLOCK_SIZE)
        return fsspec.filesystem(protocol)
    except ImportError as err:
        raise StorageError(
            f"{url}: reading {protocol}:// needs its fsspec plugin ({err}). Fix: install the lock's s3 extra "
            f"(`make venv` does; or pip install 'aumesh[s3]')."
        ) from None
    except ValueError as err:
        raise StorageError(
            f"{url}: no filesystem for {protocol}:// ({err}). Fix: use an s3:// URL or a local path."
        ) from None


def _key(url: str) -> str:
    return _SCHEME.sub("", url)


def storage_error(url: str, err: BaseException) -> StorageError:
    """The one line for a failed request on ``url``: what failed (bucket, key, credentials, access, the endpoint) and
    the fix."""
    if isinstance(err, StorageError):
        return err
    name = type(err).__name__
    first = (str(err).strip().splitlines() or [""])[0][:200]
    bucket = _key(url).split("/", 1)[0]
    endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL") or "AWS's endpoint"
    if name in ("NoCredentialsError", "PartialCredentialsError", "NoAuthTokenError", "CredentialRetrievalError"):
        return StorageError(f"{url}: no credentials for the object store ({name}: {first}). Fix: {ENV_FIX}.")
    if "bucket does not exist" in first or "NoSuchBucket" in first:
        return StorageError(
            f"{url}: no bucket {bucket!r} at {endpoint} ({name}: {first}). Fix: create it, or correct "
            f"paths.data_dir (or AWS_ENDPOINT_URL)."
        )
    if isinstance(err, FileNotFoundError):
        return StorageError(
            f"{url}: no such object in bucket {bucket!r} at {endpoint}. Fix: upload it there (the tables as py-feat "
            f"wrote them), or correct paths.data_dir."
        )
    if isinstance(err, PermissionError) or "AccessDenied" in first or "Forbidden" in first:
        return StorageError(
            f"{url}: access refused ({name}: {first}). Fix: {ENV_FIX}, with a key allowed to list and read the bucket."
        )
    if "InvalidAccessKeyId" in first or "SignatureDoesNotMatch" in first:
        return StorageError(f"{url}: credentials refused ({name}: {first}). Fix: {ENV_FIX}.")
    return StorageError(
        f"{url}: cannot reach the object store at {endpoint} ({name}: {first}). Fix: check that it runs and that "
        f"AWS_ENDPOINT_URL names it (in the environment of the stage and of every Dask worker)."
    )


#: Where the exceptions of a failed request come from (botocore's and aiohttp's own types, besides ``OSError``): a
#: ``TypeError`` or the like stays a bug with its traceback.
_REQUEST_MODULES = ("botocore", "aiobotocore", "aiohttp", "s3fs", "fsspec", "urllib3")


def _call(url: str, fn, *args, **kwargs):
    try:
        return fn(*args, **kwargs)
    except Exception as err:  # botocore and s3fs raise many types: each turned into one line naming the URL
        if isinstance(err, OSError | TimeoutError) or type(err).__module__.split(".")[0] in _REQUEST_MODULES:
            raise storage_error(url, err) from None
        raise


#: Bytes fetched ahead for a CSV's header and the frame boundaries of its ranges (py-feat's header ~30 KB, a row
#: ~20 KB): a request of this size each, not :data:`BLOCK_SIZE`.
LINE_BLOCK_SIZE = 1 << 20


def open_input(path: InputPath, mode: str = "rb", block_size: int | None = None) -> IO:
    """``path`` opened for reading: ``open`` for a local file, fsspec's file for a URL (its size and existence
    checked at once: a missing key or bucket fails here, as :class:`StorageError`), fetching ``block_size`` bytes
    ahead (default :data:`BLOCK_SIZE`; local files ignore it)."""
    if not isinstance(path, ObjectPath):
        return open(path, mode)
    fs = filesystem(path.url)
    return _call(path.url, fs.open, path.url, mode, block_size=block_size or BLOCK_SIZE)


def read_range(path: InputPath, start: int, length: int) -> bytes:
    """Bytes ``[start, start + length)`` of ``path`` (one ranged GET for a URL)."""
    if not isinstance(path, ObjectPath):
        with open(path, "rb") as fh:
            fh.seek(start)
            return fh.read(length)
    if length <= 0:
        return b""
    fs = filesystem(path.url)
    return _call(path.url, fs.cat_file, path.url, start=start, end=start + length)


def size(path: InputPath) -> int:
    """``path``'s size in bytes."""
    if not isinstance(path, ObjectPath):
        return path.stat().st_size
    fs = filesystem(path.url)
    return int(_call(path.url, fs.size, path.url))


def exists(path: InputPath) -> bool:
    """``path`` is a file (an object); a missing bucket or no credentials is a :class:`StorageError`."""
    if not isinstance(path, ObjectPath):
        return path.exists()
    fs = filesystem(path.url)
    return bool(_call(path.url, fs.isfile, path.url))


def list_inputs(root: InputPath, pattern: str) -> list[InputPath] | None:
    """The files under ``root`` that ``pattern`` (a glob, e.g. ``**/*``) matches, sorted as ``Path`` sorts; None
    when ``root`` is no folder (no object under that prefix)."""
    if not isinstance(root, ObjectPath):
        if not root.is_dir():
            return None
        return sorted(p for p in root.glob(pattern) if p.is_file())
    fs = filesystem(root.url)
    prefix = _key(root.url).rstrip("/")
    scheme = root.url[: len(root.url) - len(_key(root.url))]
    if not _call(root.url, fs.isdir, prefix):
        _call(root.url, fs.ls, prefix.split("/", 1)[0])  # a missing bucket or no credentials: their own line
        return None
    found = _call(root.url, fs.glob, f"{prefix}/{pattern}", detail=True)
    # a glob of ``**`` also yields the "folders" (common prefixes) of the keys: files only, as Path.is_file
    return sorted(ObjectPath(scheme + key) for key, info in found.items() if info.get("type") == "file")
