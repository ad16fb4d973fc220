"""Atomic writes: a temp file in the same folder, then ``os.replace``; nothing half-written survives."""

from __future__ import annotations

import functools
import glob
import io
import json
import logging
import os
import re
import shutil
import socket
import tempfile
import threading
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.core import swap
from aumesh.core.paths import recorded  # noqa: F401  (re-exported: callers import it from here)
from aumesh.core.signals import check_supervisor, process_gone
from aumesh.core.write_errors import (
    _allocated_bytes,
    _is_disk_full_error,
    _no_space,
    disk_full,
    not_writable,
    unwritable,
)


@contextmanager
def atomic_path(path: str | Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temp path beside ``path``; on success rename it over ``path``, on error delete it."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path, "tmp"), suffix=suffix or ".tmp", dir=path.parent)
    except OSError as err:  # a read-only workspace or folder: one line naming it (a full disk: disk_full)
        if unwritable(err):
            raise not_writable(path, err) from None
        if _no_space(err):
            raise disk_full(path, 0) from None
        raise
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600; published files get the usual mode
    try:
        yield tmp_path
        check_supervisor()
        os.replace(tmp_path, path)
    except BaseException as err:
        written = _allocated_bytes(tmp_path)
        tmp_path.unlink(missing_ok=True)
        if _no_space(err) and not _is_disk_full_error(err):
            raise disk_full(path, written) from err
        raise


def _temp_prefix(path: Path, kind: str) -> str:
    """``.<name>.<kind>-<pid>-<host>-``: the temporaries of ``path`` carry their process, so the next run can tell
    whether it is gone (:func:`remove_stale_temporaries`)."""
    return f".{path.name}.{kind}-{os.getpid()}-{socket.gethostname()}-"


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Delete the temporaries of ``path`` (``.<name>.tmp-*``, ``.<name>.old-*``) left by a killed process of this
    host; those of live processes (a concurrent run) stay. Returns what was removed."""
    path = Path(path)
    restore_previous(path)
    pattern = re.compile(rf"^\.{re.escape(path.name)}\.(?:tmp|old)-(\d+)-(.+)-[^-]*$")
    removed = []
    for candidate in path.parent.glob(f".{glob.escape(path.name)}.*-*") if path.parent.is_dir() else ():
        m = pattern.match(candidate.name)
        if not m or m.group(2) != socket.gethostname() or not process_gone(int(m.group(1)), candidate.lstat().st_mtime):
            continue
        if candidate.is_dir() and not candidate.is_symlink():
            shutil.rmtree(candidate, ignore_errors=True)
        else:
            candidate.unlink(missing_ok=True)
        removed.append(candidate)
    return removed


def restore_previous(path: str | Path) -> Path | None:
    """Put the previous copy of folder ``path`` back when ``path`` is missing and a killed process of this host left
    it aside (``.<name>.old-<pid>-<host>-x``: killed between :func:`atomic_directory`'s two renames, on a filesystem
    without ``RENAME_EXCHANGE``); says so in one warning line. Returns the restored path, or None."""
    path = Path(path)
    if path.exists() or path.is_symlink() or not path.parent.is_dir():
        return None
    pattern = re.compile(rf"^\.{re.escape(path.name)}\.old-(\d+)-(.+)-[^-]*$")
    aside = [
        c
        for c in path.parent.glob(f".{glob.escape(path.name)}.old-*")
        if (m := pattern.match(c.name))
        and m.group(2) == socket.gethostname()
        and process_gone(int(m.group(1)), c.lstat().st_mtime)
    ]
    if not aside:
        return None
    newest = max(aside, key=lambda c: c.lstat().st_mtime)
    os.replace(newest, path)
    logging.getLogger(__name__).warning(
        "%s was missing: restored the previous copy (%s), left aside by a run killed while swapping in a new one",
        recorded(path),
        newest.name,
    )
    return path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | Path, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def atomic_write_json(path: str | Path, obj: Any) -> Path:
    return atomic_write_text(path, json_text(obj))


def json_text(obj: Any) -> str:
    """The text :func:`atomic_write_json` writes for ``obj`` (indented, NumPy scalars and paths as JSON values)."""
    return json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n"


def atomic_savez(path: str | Path, **arrays: Any) -> Path:
    """``np.savez`` atomically (the temp name keeps the .npz suffix so numpy does not append one)."""
    with atomic_path(path, suffix=".npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    return Path(path)


def scratch_directory(path: str | Path) -> Path:
    """A new temporary folder beside ``path``, named as its temporaries (``.<name>.tmp-<pid>-<host>-*``): the caller
    removes it, and if its process is killed first, :func:`remove_stale_temporaries` of ``path`` does."""
    return _new_folder(Path(path))


def _new_folder(path: Path) -> Path:
    """A new temporary folder beside ``path`` (its parents made); an unwritable place is one line naming it."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=_temp_prefix(path, "tmp"), dir=path.parent))
    except OSError as err:
        if unwritable(err):
            raise not_writable(path, err) from None
        if _no_space(err):
            raise disk_full(path, 0) from None
        raise


@contextmanager
def atomic_directory(path: str | Path) -> Iterator[Path]:
    """Build a whole folder in a temp sibling, then swap it in; a failure leaves the old folder as it was."""
    path = Path(path)
    tmp = _new_folder(path)
    os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes 0700; a published folder gets the usual mode
    old = None
    try:
        yield tmp
        check_supervisor()  # under DVC: never swap in an output as the orphan of a stopped DVC
        if path.exists() and swap.exchange(tmp, path):
            # one atomic step: ``path`` is the new folder, ``tmp`` now holds the previous one (a kill from here on
            # leaves the new folder and a temporary that the next run's remove_stale_temporaries deletes)
            shutil.rmtree(tmp, ignore_errors=True)
            return
        if path.exists():  # no exchange on this filesystem: two renames, the previous copy aside in between
            old = path.with_name(_temp_prefix(path, "old") + "x")
            os.replace(path, old)
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException as err:
        written = _allocated_bytes(tmp)
        # interrupted (Ctrl-C, SIGTERM) between the two renames: the previous folder goes back, not a hole
        if old is not None and old.exists() and not path.exists():
            os.replace(old, path)
        shutil.rmtree(tmp, ignore_errors=True)
        if _no_space(err):  # named here, for the whole folder (an atomic file inside it named its temporary copy)
            raise disk_full(path, written) from err
        raise


def absolute(path: str | Path) -> Path:
    """``path`` made absolute against the current directory (the stage's workspace), without following symlinks.

    What a stage hands to its partition tasks: a ``dask.distributed`` worker runs in a directory of its own (and may
    serve several workspaces), so a relative path there names another file or none (README, "Scale out"). Symlinks
    stay as they are (DVC may link the tables into its cache; an error should name the workspace's file)."""
    return Path(os.path.abspath(path))


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def create_npy(path: str | Path, dtype, shape: tuple[int, ...]) -> int:
    """An ``.npy`` of ``shape`` (zero-filled, sparse on disk) whose rows are written later with :func:`write_rows`.

    Returns the byte offset of the data (after the header).
    """
    header = np.lib.format.open_memmap(path, mode="w+", dtype=dtype, shape=shape)
    offset = header.offset
    del header
    return offset


# CPython 3.11 keeps the AST constructor's recursion depth in interpreter-wide state, reset by every parse: numpy
# parses each .npy header with ast.literal_eval, and when a garbage collection during one thread's parse lets
# another thread parse, the first raises "SystemError: AST constructor recursion depth mismatch"
# (python/cpython#106905; it failed a prepare on the threads scheduler in this project's CI). Every .npy or .npz
# read inside a partition task goes through this lock (the arrays read whole under it are small).
_NUMPY_HEADER_LOCK = threading.Lock()


def load_npy(path: str | Path) -> np.ndarray:
    """``np.load`` of an ``.npy``, safe in threads (one header parse at a time: see ``_NUMPY_HEADER_LOCK``)."""
    with _NUMPY_HEADER_LOCK:
        return np.load(path, allow_pickle=False)


#: what a damaged ``.npz`` raises while it is opened or a member read: a bad or cut zip (``BadZipFile``, a CRC
#: mismatch included), a cut member (``EOFError``, ``ValueError``), a bad deflate stream (``zlib.error``)
_NPZ_ERRORS: tuple[type[BaseException], ...] = (zipfile.BadZipFile, EOFError, ValueError, zlib.error, OSError)
NPZ_FIX = (
    "restore the tracked copy (`dvc pull --force <its folder>`, or `dvc checkout --force`) or rebuild it (`dvc repro`)"
)


def read_npz(
    path: str | Path,
    keys: tuple[str, ...] | list[str] | None = None,
    fix: str = NPZ_FIX,
    what: str = "not a readable .npz",
) -> dict:
    """Arrays ``keys`` (None: all) of an ``.npz``, read whole (no pickle), safe in threads.

    A damaged file (truncated, a CRC error, not a zip) or a missing key is a
    :class:`aumesh.core.errors.CorruptFileError` of one line naming the file and ``fix``, not numpy's or zipfile's
    traceback; a missing file stays a ``FileNotFoundError``.
    """
    from aumesh.core.errors import CorruptFileError

    try:
        with _NUMPY_HEADER_LOCK, np.load(path, allow_pickle=False) as arrays:
            missing = [k for k in keys or () if k not in arrays.files]
            if missing:
                raise CorruptFileError(
                    f"{path}: no array {', '.join(map(repr, missing))} in this .npz (it has {sorted(arrays.files)}): "
                    f"damaged or of another version. Fix: {fix}"
                )
            return {k: arrays[k] for k in (keys if keys is not None else arrays.files)}
    except CorruptFileError:
        raise
    except _NPZ_ERRORS as err:
        if isinstance(err, FileNotFoundError):
            raise
        first = (str(err).splitlines() or [""])[0]
        raise CorruptFileError(
            f"{path}: {what}: corrupt or truncated ({type(err).__name__}: {first}). Fix: {fix}"
        ) from None


def load_npz(path: str | Path, keys: tuple[str, ...] | list[str]) -> list[np.ndarray]:
    """Arrays ``keys`` of an ``.npz``, safe in threads (one header parse at a time: see ``_NUMPY_HEADER_LOCK``); a
    damaged file is one line (:func:`read_npz`)."""
    arrays = read_npz(path, keys)
    return [arrays[k] for k in keys]


def npy_layout(path: str | Path) -> tuple[int, np.dtype, tuple[int, ...]]:
    """``(data offset, dtype, shape)`` of a C-ordered ``.npy`` (read from its header only).

    The header's bytes are read each call (a file may be replaced); parsing them (``ast.literal_eval``)
    is cached by those bytes, since the streaming passes call this for every chunk they read or write.
    """
    with open(path, "rb") as fh:
        prefix = fh.read(12)  # magic (6), version (2), header length (2 in v1.0, 4 in v2/v3)
        if len(prefix) < 10 or prefix[:6] != b"\x93NUMPY":
            raise ValueError(f"{path}: not an .npy file")
        size = (
            10 + int.from_bytes(prefix[8:10], "little")
            if prefix[6] == 1
            else 12 + int.from_bytes(prefix[8:12], "little")
        )
        header = prefix + fh.read(size - len(prefix))
    return _parse_npy_header(header, str(path))


def check_npy(path: str | Path, fix: str) -> tuple[int, np.dtype, tuple[int, ...]]:
    """:func:`npy_layout` of an ``.npy`` whose data is all on disk: a header numpy cannot parse, or a file shorter
    than its header's shape needs (a truncated copy, an interrupted ``np.save``), is a
    :class:`aumesh.core.errors.CorruptFileError` naming the file, both sizes and ``fix`` (instead of numpy's
    "mmap length is greater than file size" or an ``EOFError`` deep inside a pass)."""
    from aumesh.core.errors import CorruptFileError, TruncatedFileError

    path = Path(path)
    try:
        with open(path, "rb") as fh:  # numpy's own header reader
            version = np.lib.format.read_magic(fh)
            read_header = (
                np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            )
            shape, fortran, dtype = read_header(fh)
            offset = fh.tell()
    except (ValueError, SyntaxError, EOFError) as err:
        raise CorruptFileError(f"{path}: not a readable .npy file ({err}). Fix: {fix}") from None
    if fortran and len(shape) > 1:
        raise fortran_order(path)
    need = offset + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    size = path.stat().st_size
    if size < need:
        raise TruncatedFileError(
            f"{path}: truncated: {size:,} bytes on disk, its header ({shape} {dtype}) needs {need:,}. Fix: {fix}"
        )
    return offset, dtype, shape


@functools.lru_cache(maxsize=64)
def _parse_npy_header(header: bytes, path: str) -> tuple[int, np.dtype, tuple[int, ...]]:
    fh = io.BytesIO(header)
    version = np.lib.format.read_magic(fh)
    read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    with _NUMPY_HEADER_LOCK:
        shape, fortran, dtype = read_header(fh)
    if fortran and len(shape) > 1:
        raise fortran_order(path)
    return len(header), dtype, shape


def fortran_order(path: str | Path) -> Exception:
    """The one line for an ``.npy`` saved in Fortran order (``np.save`` of a transposed array or of
    ``np.asfortranarray``): its rows are not contiguous on disk, and the passes read rows with plain file I/O (a
    transposing read would hold the whole array in memory: refused rather than read slowly)."""
    from aumesh.core.errors import TableError

    return TableError(
        f"{path}: saved in Fortran order (fortran_order: True in its .npy header): its rows are not contiguous on "
        f"disk and cannot be read as rows. Fix: rewrite it C-ordered, np.save(path, np.ascontiguousarray(a)) "
        f"(e.g. a = np.load(path); np.save(path, np.ascontiguousarray(a)))."
    )


class NpyRowFile:
    """An ``.npy`` opened once for reading and writing rows with plain file I/O (``pread``/``pwrite``; never
    memory-mapped: a map would keep every page read resident in the process).

    For a pass that reads or writes many blocks of one file: the header is parsed and the file opened once, not per
    block. Several processes may write disjoint rows of one file at once. A context manager (closes the file).

    Parameters
    ----------
    path : str or Path
        A C-ordered ``.npy`` (:func:`create_npy` makes one to fill).
    writable : bool, default False
        Open for :meth:`write` too.
    """

    def __init__(self, path: str | Path, writable: bool = False):
        self.path = Path(path)
        self.offset, self.dtype, self.shape = npy_layout(self.path)
        self.row_bytes = int(np.prod(self.shape[1:], dtype=np.int64)) * self.dtype.itemsize
        self._fd = os.open(self.path, os.O_RDWR if writable else os.O_RDONLY)

    def read(self, start: int, stop: int, out: np.ndarray | None = None) -> np.ndarray:
        """Rows ``start:stop`` (clipped to the file), into ``out`` (its first rows) when given."""
        n = max(0, min(stop, self.shape[0]) - start)
        out = np.empty((n, *self.shape[1:]), dtype=self.dtype) if out is None else out[:n]
        view = memoryview(out.data).cast("B")
        pos, got = self.offset + start * self.row_bytes, 0
        while got < len(view):
            k = os.preadv(self._fd, [view[got:]], pos + got)
            if not k:  # the file shrank after its size was checked (check_npy), or was never checked
                from aumesh.core.errors import TruncatedFileError

                raise TruncatedFileError(
                    f"{self.path}: truncated at row {start + got // max(self.row_bytes, 1)} of "
                    f"{self.shape[0]}. Fix: restore or rewrite the file"
                )
            got += k
        return out

    def take(self, rows: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Rows ``rows`` (row numbers in any order) in that order, into ``out`` (its first rows) when given: one read
        per run of consecutive row numbers, so rows wanted in another order than the file's cost no extra copy."""
        out = np.empty((len(rows), *self.shape[1:]), dtype=self.dtype) if out is None else out[: len(rows)]
        for j, (lo, hi) in row_runs(np.asarray(rows)):
            self.read(lo, hi, out[j : j + hi - lo])
        return out

    def write(self, first_row: int, rows: np.ndarray) -> None:
        """Write ``rows`` (the file's dtype and row shape) from row ``first_row`` on."""
        view = memoryview(np.ascontiguousarray(rows).data).cast("B")
        pos, done = self.offset + first_row * self.row_bytes, 0
        try:
            while done < len(view):
                done += os.pwrite(self._fd, view[done:], pos + done)
        except OSError as err:  # pwrite's error names no file: name it, its folder and its mount
            if _no_space(err):
                raise disk_full(self.path, _allocated_bytes(self.path), scratch=True) from None
            raise

    def write_row_map(self, rows: dict[int, np.ndarray]) -> None:
        """Write each ``rows[r]`` (one row, the file's dtype) at row ``r``, one write per run of consecutive row
        numbers (rows finished a few at a time, e.g. per-video sums: a write per row was ~20k small writes at 344k
        frames)."""
        numbers = np.array(sorted(rows), dtype=np.int64)
        for j, (lo, hi) in row_runs(numbers):
            self.write(lo, np.stack([rows[r] for r in numbers[j : j + hi - lo].tolist()]))

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> NpyRowFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def write_rows(path: str | Path, first_row: int, rows: np.ndarray) -> None:
    """Write ``rows`` (C-contiguous, the file's dtype) into an ``.npy`` from row ``first_row`` on (one call;
    a pass writing many blocks keeps an :class:`NpyRowFile` open instead)."""
    with NpyRowFile(path, writable=True) as f:
        f.write(first_row, rows)


def read_rows(path: str | Path, start: int, stop: int, out: np.ndarray | None = None) -> np.ndarray:
    """Rows ``start:stop`` of an ``.npy`` (one call; a pass reading many blocks keeps an :class:`NpyRowFile` open)."""
    with NpyRowFile(path) as f:
        return f.read(start, stop, out)


def read_row_set(path: str | Path, rows: np.ndarray) -> np.ndarray:
    """Rows ``rows`` (any order, repeats allowed) of an ``.npy``, read run by run from one open file."""
    rows = np.asarray(rows, dtype=np.int64)
    with NpyRowFile(path) as f:
        out = np.empty((len(rows), *f.shape[1:]), dtype=f.dtype)
        if len(rows) == 0:
            return out
        order = np.argsort(rows, kind="stable")
        sorted_rows = rows[order]
        unique, first = np.unique(sorted_rows, return_index=True)
        block = np.empty((len(unique), *f.shape[1:]), dtype=f.dtype)
        for j, (lo, hi) in row_runs(unique):
            f.read(lo, hi, block[j : j + hi - lo])
    counts = np.diff(np.r_[first, len(sorted_rows)])
    out[order] = np.repeat(block, counts, axis=0)
    return out


def row_runs(sorted_values: np.ndarray) -> list[tuple[int, tuple[int, int]]]:
    """``(position, (first, stop))`` of each run of consecutive integers in ``sorted_values``: the row ranges
    of a sorted set of rows that one :class:`NpyRowFile` read or write each can move (a run is a stretch of
    ``n, n + 1, ...``: the values need only be sorted within each run)."""
    if len(sorted_values) == 0:
        return []
    breaks = np.flatnonzero(np.diff(sorted_values) != 1) + 1
    return [
        (int(lo), (int(sorted_values[lo]), int(sorted_values[hi - 1]) + 1))
        for lo, hi in zip(np.r_[0, breaks], np.r_[breaks, len(sorted_values)], strict=True)
    ]


class NpyRows:
    """Rows of an ``.npy`` on disk, read on demand with plain file I/O (never memory-mapped, never whole
    unless asked): ``rows[v]``, ``rows[v, cols]``, ``rows[a:b]`` for row index arrays/slices; ``np.asarray(rows)``
    reads it all. For per-video arrays too large to hold whole at many videos.
    """

    def __init__(self, path: str | Path):
        self.path = Path(path)
        _, self.dtype, self.shape = npy_layout(self.path)

    def __len__(self) -> int:
        return self.shape[0]

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def __getitem__(self, key):
        rest: tuple = ()
        if isinstance(key, tuple):
            key, rest = key[0], key[1:]
        if isinstance(key, slice):
            start, stop, step = key.indices(self.shape[0])
            out = (
                read_rows(self.path, start, stop)[::step]
                if step > 0
                else read_row_set(self.path, np.arange(start, stop, step))
            )
        elif np.isscalar(key):
            out = read_row_set(self.path, np.array([int(key)]))[0]
        else:
            key = np.asarray(key)
            out = read_row_set(self.path, np.flatnonzero(key) if key.dtype == bool else key)
        return out[(slice(None), *rest)] if rest and not np.isscalar(key) else (out[rest] if rest else out)

    def __array__(self, dtype=None, copy=None):
        out = read_rows(self.path, 0, self.shape[0])
        return out if dtype is None else out.astype(dtype)

    def astype(self, dtype) -> np.ndarray:
        return np.asarray(self).astype(dtype)


#: Per-row data a computation reads by rows: an array in memory, or an ``.npy`` read on demand (:class:`NpyRows`).
RowArray = np.ndarray | NpyRows
