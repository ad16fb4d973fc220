"""Checksums of the prepared data: ``prepare`` records them in ``summary.json``, ``evaluate`` and ``release`` verify
them before they use the files.

Why: DVC's cache is linked into the workspace (``cache.type = hardlink`` in ``.dvc/config``), so a byte flipped in
``build/prepared/meshes.npy`` is a byte flipped in DVC's cache too, and DVC's run cache restores it as it is; nothing
else would notice and ``evaluate`` would train on it with exit 0.

A file's record is a list of byte ranges and the digest of each (``{"algorithm": "xxh3_128", "size": n, "blocks":
[[start, stop, hex], ...]}``). ``meshes.npy``, the one large file, is hashed while pass 3 writes it: each partition
hashes the rows it writes, in order (its rows are one contiguous range of the file, and one row group of
``frames.parquet``), so the check costs no extra read in ``prepare``; its header is one more block. The other files
(per-video and per-frame metadata, 1-3 % of the bytes) are hashed when written, read back from the page cache in
64 MiB blocks.

``evaluate`` verifies the small files and the header up front (:func:`verify_prepared`), and each partition's block of
``meshes.npy`` while its first pass reads that partition anyway (:class:`StreamedCheck`, :class:`RangeDigests`): the
partition's task hashes the bytes it read, wherever it runs, and the driver compares the digests before any model is
fitted. Reading the ~2 GB of meshes at 344k frames once more up front cost the stage 14 %.

XXH3-128 (``xxhash``), not SHA-256: a checksum against corruption (a flipped bit, a truncated or swapped block), not
against an adversary who could rewrite ``summary.json`` too. It hashes ~14 GB/s a core here against SHA-256's ~1.6
and BLAKE2b's ~0.9, so the ~2 GB of meshes cost ~0.15 CPU s instead of ~1.2. Records made with SHA-256 (prepared data
of an earlier aumesh) still verify: each record names its algorithm. Both release the GIL.
"""

from __future__ import annotations

import bisect
import hashlib
import os
from collections.abc import Hashable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from aumesh.core.errors import CorruptFileError

#: The algorithm of new records (:func:`new_hash`); :data:`ALGORITHMS` are the ones a record may name.
ALGORITHM = "xxh3_128"
ALGORITHMS = ("xxh3_128", "sha256")
#: Bytes a block of a file hashed after writing covers (the unit verified in parallel).
BLOCK_BYTES = 64 << 20
#: Bytes read at a time while hashing (in cache; hashlib releases the GIL above 2 KiB).
READ_BYTES = 4 << 20

#: The fix a damaged prepared file names: recompute. With hard links (``cache.type = hardlink``) DVC's cached copy *is*
#: the workspace file, so `dvc checkout -f prepare` cannot restore it: it relinks the same bytes and then reports the
#: workspace up to date (tried with DVC 3.67). See :func:`prepared_fix` for a file that is hard-linked into the cache.
PREPARED_FIX = "rebuild the prepared data with `dvc repro -f prepare` (or `aumesh prepare`)"


def prepared_fix(path: str | Path) -> str:
    """:data:`PREPARED_FIX`, preceded by removing DVC's cached copy when ``path`` has other hard links (DVC's cache):
    DVC skips storing an object whose name is already in its cache, so the damaged copy would stay there and come back
    with the next `dvc checkout`."""
    try:
        st = os.stat(path)
    except OSError:
        return PREPARED_FIX
    if st.st_nlink > 1:
        return (
            f"it is hard-linked into DVC's cache, whose copy is damaged too: remove that copy "
            f"(`find .dvc/cache -inum {st.st_ino} -delete`), then {PREPARED_FIX}"
        )
    return PREPARED_FIX


class StreamingHash(Protocol):
    """What :func:`new_hash` returns: hashlib's and xxhash's common interface."""

    def update(self, data: Any, /) -> None: ...
    def hexdigest(self) -> str: ...


def new_hash(algorithm: str = ALGORITHM) -> StreamingHash:
    """A streaming hash object (``update``, ``hexdigest``) of ``algorithm`` (one of :data:`ALGORITHMS`)."""
    if algorithm == "xxh3_128":
        import xxhash

        return xxhash.xxh3_128()
    if algorithm not in ALGORITHMS:
        raise ValueError(f"checksum algorithm {algorithm!r} unknown to this aumesh (known: {', '.join(ALGORITHMS)})")
    return hashlib.new(algorithm)


def hash_range(path: str | Path, start: int, stop: int, algorithm: str = ALGORITHM) -> str:
    """Hex digest of bytes ``start:stop`` of ``path`` (short if the file ends first: the size check says so)."""
    h = new_hash(algorithm)
    buf = bytearray(min(READ_BYTES, max(stop - start, 1)))
    view = memoryview(buf)
    fd = os.open(path, os.O_RDONLY)
    try:
        pos = start
        while pos < stop:
            n = os.preadv(fd, [view[: min(len(buf), stop - pos)]], pos)
            if not n:
                break
            h.update(view[:n])
            pos += n
    finally:
        os.close(fd)
    return h.hexdigest()


def file_record(path: str | Path, blocks: list[tuple[int, int, str]] | None = None) -> dict:
    """The record of ``path``: ``blocks`` as hashed while it was written, or else the file read back in
    :data:`BLOCK_BYTES` blocks."""
    size = os.path.getsize(path)
    if blocks is None:
        bounds = list(range(0, size, BLOCK_BYTES)) + [size]
        blocks = [(a, b, hash_range(path, a, b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)] or [
            (0, 0, new_hash().hexdigest())
        ]
    covered = sorted((int(a), int(b)) for a, b, _ in blocks)
    if (
        covered[0][0] != 0
        or covered[-1][1] != size
        or any(b != c for (_, b), (c, _) in zip(covered[:-1], covered[1:], strict=True))
    ):
        raise ValueError(f"{path}: checksum blocks do not cover the file's {size} bytes exactly")
    return {"algorithm": ALGORITHM, "size": size, "blocks": [[int(a), int(b), h] for a, b, h in sorted(blocks)]}


def _check_record(path: Path, rec: dict) -> str:
    """The algorithm of record ``rec`` of ``path``, after checking it is known and the file has the recorded size."""
    algorithm = rec.get("algorithm", "sha256")  # the records before XXH3 all named theirs (sha256)
    if algorithm not in ALGORITHMS:
        raise CorruptFileError(f"{path}: checksum algorithm {algorithm!r} unknown to this aumesh. Fix: {PREPARED_FIX}.")
    size = path.stat().st_size
    if size != rec["size"]:
        raise CorruptFileError(
            f"{path}: {size:,} bytes, but prepare wrote {rec['size']:,} (checksum in summary.json): "
            f"the file was truncated or replaced. Fix: {prepared_fix(path)}."
        )
    return algorithm


def mismatch(path: Path, start: int, stop: int, algorithm: str) -> CorruptFileError:
    """The one-line error of bytes ``start:stop`` of ``path`` that do not match their checksum."""
    return CorruptFileError(
        f"{path}: bytes {start:,}-{stop:,} do not match the {algorithm} checksum prepare recorded "
        f"in summary.json: the file changed after it was written (disk or cache corruption, "
        f"an edit). Fix: {prepared_fix(path)}."
    )


def verify(
    directory: str | Path,
    records: dict[str, dict],
    names: list[str] | None = None,
    threads: int | None = None,
    streamed: Mapping[str, Mapping[Any, tuple[int, int]]] | None = None,
) -> dict[str, StreamedCheck]:
    """Check files ``names`` (default: every recorded one) of ``directory`` against ``records``; the first mismatch is a
    :class:`CorruptFileError` naming the file, where it differs and :data:`PREPARED_FIX`.

    ``streamed[name]`` (partition -> byte range ``[start, stop)``): the ranges of file ``name`` that a pass will read
    whole anyway. The recorded blocks inside one of them are not read here but returned, to be hashed as the pass reads
    them (:class:`StreamedCheck`); the rest of the file (its header, blocks no range holds) is verified here.
    """
    directory = Path(directory)
    names = list(records) if names is None else [n for n in names if n in records]
    jobs, deferred = [], {}
    for name in names:
        rec, path = records[name], directory / name
        algorithm = _check_record(path, rec)
        ranges = sorted(((a, b), key) for key, (a, b) in (streamed or {}).get(name, {}).items())
        later: dict[Hashable, list[tuple[int, int, str]]] = {}
        for a, b, h in rec["blocks"]:
            # the range starting last at or before the block's start is the only one that can hold it
            k = bisect.bisect_right(ranges, ((a, float("inf")),)) - 1
            if k >= 0 and ranges[k][0][0] <= a and b <= ranges[k][0][1] and b > a:
                later.setdefault(ranges[k][1], []).append((int(a), int(b), h))
            else:
                jobs.append((path, algorithm, a, b, h))
        if name in (streamed or {}):
            deferred[name] = StreamedCheck(path, algorithm, later)
    with ThreadPoolExecutor(max_workers=threads or min(len(jobs), os.cpu_count() or 1) or 1) as pool:
        got = list(pool.map(lambda j: hash_range(j[0], j[2], j[3], j[1]), jobs))
    for (path, algorithm, a, b, want), have in zip(jobs, got, strict=True):
        if have != want:
            raise mismatch(path, a, b, algorithm)
    return deferred


@dataclass(frozen=True)
class StreamedCheck:
    """The recorded blocks of one file that a pass verifies as it reads them (from :func:`verify`).

    The pass's task for partition ``key`` hashes the bytes it reads (:class:`RangeDigests` over :meth:`ranges`), on
    whatever worker it runs, and returns the digests; the driver then calls :meth:`check` with all of them, before
    anything computed from the bytes is used.
    """

    path: Path
    algorithm: str
    blocks: dict[Hashable, list[tuple[int, int, str]]]  # partition -> the recorded blocks it reads, in file order

    def ranges(self, key: Hashable) -> list[tuple[int, int]]:
        """The byte ranges partition ``key``'s task hashes (none: nothing to hash)."""
        return [(a, b) for a, b, _ in self.blocks.get(key, [])]

    def check(self, digests: Mapping[tuple[int, int], str]) -> None:
        """Compare the digests the tasks computed (``(start, stop) -> hex``) with the record: the first mismatch in
        the file's order is a :class:`CorruptFileError` (:func:`mismatch`)."""
        blocks = sorted(b for blocks in self.blocks.values() for b in blocks)
        missing = [(a, b) for a, b, _ in blocks if (a, b) not in digests]
        if missing:  # a pass that skipped bytes: a bug, never a pass
            raise RuntimeError(f"{self.path}: bytes {missing[0][0]:,}-{missing[0][1]:,} were not hashed by the pass")
        for a, b, want in blocks:
            if digests[(a, b)] != want:
                raise mismatch(self.path, a, b, self.algorithm)


class RangeDigests:
    """Digests of byte ranges of a file from its bytes as a pass reads them, fed in the file's order (contiguous
    pieces; the bytes between ranges are skipped). ``digests`` (``(start, stop) -> hex``) holds each finished range.

    Parameters
    ----------
    ranges : list of (start, stop)
        Disjoint byte ranges (:meth:`StreamedCheck.ranges`).
    algorithm : str
    """

    def __init__(self, ranges: list[tuple[int, int]], algorithm: str = ALGORITHM):
        self._ranges = sorted((int(a), int(b)) for a, b in ranges if b > a)
        self._algorithm = algorithm
        self._next = 0  # the range being (or next to be) hashed
        self._hash: StreamingHash | None = None
        self._pos: int | None = None  # where the next piece must start
        self.digests: dict[tuple[int, int], str] = {}

    def update(self, position: int, data) -> None:
        """Feed bytes ``data`` (a bytes-like object, e.g. ``memoryview(rows).cast("B")``) found at byte ``position``
        of the file; each piece must start where the last one ended."""
        if self._pos is not None and position != self._pos:
            raise RuntimeError(f"checksum: bytes fed out of order (at {position:,}, expected {self._pos:,})")
        view = memoryview(data).cast("B")
        end = position + len(view)
        self._pos = end
        while self._next < len(self._ranges):
            a, b = self._ranges[self._next]
            if a >= end:
                return
            if self._hash is None:
                if a < position:  # the range began before the first piece: it cannot be hashed
                    self._next += 1
                    continue
                self._hash = new_hash(self._algorithm)
            self._hash.update(view[max(a, position) - position : min(b, end) - position])
            if b > end:
                return
            self.digests[(a, b)] = self._hash.hexdigest()
            self._hash = None
            self._next += 1


def load_summary(prepared_dir: str | Path) -> dict:
    """``summary.json`` of the prepared data; unreadable JSON is a :class:`CorruptFileError` naming it."""
    import json

    path = Path(prepared_dir) / "summary.json"
    try:
        return json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as err:
        raise CorruptFileError(f"{path}: not readable JSON ({err}). Fix: {PREPARED_FIX}.") from None


def verify_prepared(
    prepared_dir: str | Path,
    summary: dict,
    names: list[str] | None = None,
    streamed: Mapping[str, Mapping[Any, tuple[int, int]]] | None = None,
) -> dict[str, StreamedCheck]:
    """Every ``.npy`` of the prepared data complete (:func:`aumesh.core.io.check_npy`), then files ``names`` (default
    all) against the checksums ``summary`` records, but for the byte ranges ``streamed`` defers to a pass
    (:func:`verify`: their checks are returned). Prepared data from before the checksums were recorded is checked
    for completeness only (a warning says so; nothing is returned)."""
    import logging

    from aumesh.core.io import check_npy
    from aumesh.pipeline.prepared_files import MESHES_FILE, NEUTRAL_FILES, VIDEO_IDS_FILE

    d = Path(prepared_dir)
    for name in (MESHES_FILE, VIDEO_IDS_FILE, *NEUTRAL_FILES.values()):
        if names is None or name in names:
            check_npy(d / name, prepared_fix(d / name) + ".")
    records = summary.get("checksums")
    if not records:
        logging.getLogger(__name__).warning(
            "%s: summary.json records no checksums (prepared by an older aumesh): the "
            "files' contents are not verified; `dvc repro -f prepare` records them",
            d,
        )
        return {}
    return verify(d, records, names, streamed=streamed)


def load_reference(prepared_dir: str | Path) -> dict:
    """The arrays of ``reference.npz``; a damaged archive is a :class:`CorruptFileError` naming it."""
    import zipfile

    import numpy as np

    path = Path(prepared_dir) / "reference.npz"
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, EOFError, OSError) as err:
        if isinstance(err, FileNotFoundError):
            raise
        raise CorruptFileError(f"{path}: not a readable .npz ({err}). Fix: {prepared_fix(path)}.") from None
