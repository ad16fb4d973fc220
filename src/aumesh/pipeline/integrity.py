"""Checksums of the prepared data: ``prepare`` records them in ``summary.json``, ``evaluate`` and ``release`` verify
them before they use the files.

Why: DVC's cache is linked into the workspace (``cache.type = hardlink`` in ``.dvc/config``), so a byte flipped in
``build/prepared/meshes.npy`` is a byte flipped in DVC's cache too, and DVC's run cache restores it as it is; nothing
else would notice and ``evaluate`` would train on it with exit 0.

A file's record is a list of byte ranges and the SHA-256 of each (``{"size": n, "blocks": [[start, stop, hex],
...]}``). ``meshes.npy``, the one large file, is hashed while pass 3 writes it: each partition hashes the rows it
writes, in order (its rows are one contiguous range of the file), so the check costs no extra read in ``prepare``;
its header is one more block. The other files (per-video and per-frame metadata, 1-3 % of the bytes) are hashed when
written, read back from the page cache in 64 MiB blocks. SHA-256, not BLAKE2: with the SHA extensions of current
x86 and ARM CPUs it hashes ~1.8 GB/s a core against BLAKE2b's ~0.9 (measured here; ``xxhash`` is not a dependency).
Blocks are verified in parallel threads (hashlib and ``pread`` release the GIL).
"""

from __future__ import annotations

import hashlib
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from aumesh.utils.errors import CorruptFileError

ALGORITHM = "sha256"
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


def new_hash():
    return hashlib.new(ALGORITHM)


def hash_range(path: str | Path, start: int, stop: int) -> str:
    """Hex digest of bytes ``start:stop`` of ``path`` (short if the file ends first: the size check says so)."""
    h = new_hash()
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


def verify(
    directory: str | Path, records: dict[str, dict], names: list[str] | None = None, threads: int | None = None
) -> None:
    """Check files ``names`` (default: every recorded one) of ``directory`` against ``records``; the first mismatch is a
    :class:`CorruptFileError` naming the file, where it differs and :data:`PREPARED_FIX`."""
    directory = Path(directory)
    names = list(records) if names is None else [n for n in names if n in records]
    jobs = []
    for name in names:
        rec, path = records[name], directory / name
        if rec.get("algorithm", ALGORITHM) != ALGORITHM:
            raise CorruptFileError(
                f"{path}: checksum algorithm {rec.get('algorithm')!r} unknown to this aumesh. Fix: {PREPARED_FIX}."
            )
        size = path.stat().st_size
        if size != rec["size"]:
            raise CorruptFileError(
                f"{path}: {size:,} bytes, but prepare wrote {rec['size']:,} (checksum in summary.json): "
                f"the file was truncated or replaced. Fix: {prepared_fix(path)}."
            )
        jobs += [(name, path, a, b, h) for a, b, h in rec["blocks"]]
    with ThreadPoolExecutor(max_workers=threads or min(len(jobs), os.cpu_count() or 1) or 1) as pool:
        got = list(pool.map(lambda j: hash_range(j[1], j[2], j[3]), jobs))
    for (_name, path, a, b, want), have in zip(jobs, got, strict=True):
        if have != want:
            raise CorruptFileError(
                f"{path}: bytes {a:,}-{b:,} do not match the {ALGORITHM} checksum prepare recorded "
                f"in summary.json: the file changed after it was written (disk or cache corruption, "
                f"an edit). Fix: {prepared_fix(path)}."
            )


def load_summary(prepared_dir: str | Path) -> dict:
    """``summary.json`` of the prepared data; unreadable JSON is a :class:`CorruptFileError` naming it."""
    import json

    path = Path(prepared_dir) / "summary.json"
    try:
        return json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as err:
        raise CorruptFileError(f"{path}: not readable JSON ({err}). Fix: {PREPARED_FIX}.") from None


def verify_prepared(prepared_dir: str | Path, summary: dict, names: list[str] | None = None) -> None:
    """Every ``.npy`` of the prepared data complete (:func:`aumesh.utils.io.check_npy`), then files ``names`` (default
    all) against the checksums ``summary`` records. Prepared data from before the checksums were recorded is checked
    for completeness only (a warning says so)."""
    import logging

    from aumesh.pipeline.prepared_files import MESHES_FILE, NEUTRAL_FILES, VIDEO_IDS_FILE
    from aumesh.utils.io import check_npy

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
        return
    verify(d, records, names)


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
