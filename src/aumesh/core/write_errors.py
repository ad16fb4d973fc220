"""The one-line errors of a write that failed for want of space or permission, naming the folder, its mount and the
fix (instead of ``[Errno 28] No space left on device`` with no path, or a ``PermissionError`` traceback)."""

from __future__ import annotations

import errno
import shutil
from pathlib import Path

from aumesh.core.errors import DiskFullError, NotWritableError
from aumesh.core.paths import mount_of, recorded

#: errnos of a folder that cannot be written: no permission, or a read-only filesystem
NOT_WRITABLE = (errno.EACCES, errno.EPERM, errno.EROFS)


def unwritable(err: BaseException) -> bool:
    return isinstance(err, OSError) and err.errno in NOT_WRITABLE


def not_writable(path: str | Path, err: OSError) -> Exception:
    """The one line for a ``path`` that cannot be written (its folder, or the file, read-only or not the user's)."""
    folder = Path(recorded(Path(path).parent))
    why = "a read-only filesystem" if err.errno == errno.EROFS else "permission denied"
    return NotWritableError(
        err.errno,
        f"{folder}/: cannot write {recorded(path)} there ({why}: a read-only workspace, or a folder that is not "
        f"yours). Fix: make {folder}/ writable (`chmod -R u+w {folder}`, `ls -ld {folder}` shows its owner; a "
        "read-only mount must be remounted) or work in a writable clone, and run again.",
    )


def _no_space(err: BaseException) -> bool:
    return isinstance(err, OSError) and err.errno in (errno.ENOSPC, errno.EDQUOT)


def _is_disk_full_error(err: BaseException) -> bool:
    return isinstance(err, DiskFullError)


def _allocated_bytes(path: Path) -> int:
    """Bytes a file or folder takes on its device (allocated blocks: a sparse ``.npy`` takes what was written)."""
    try:
        if path.is_dir() and not path.is_symlink():
            return sum(p.lstat().st_blocks * 512 for p in path.rglob("*"))
        return path.lstat().st_blocks * 512
    except OSError:
        return 0


def _size(path: Path) -> int:
    try:
        if path.is_dir():
            return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
        return path.stat().st_size if path.exists() else 0
    except OSError:
        return 0


def disk_full(path: str | Path, written: int, scratch: bool = False) -> Exception:
    """The one line for ``ENOSPC`` while ``path`` was being written atomically (its temporary copy already removed):
    the folder, the filesystem's mount (``df`` of that folder, not of the workspace: ``build/`` may live elsewhere),
    what the new output had taken and what it needs, and that the previous output is intact; ``scratch``: a working
    file written in place (a pass's rows), not an output."""
    path = Path(path)
    try:
        free = shutil.disk_usage(path.parent).free
    except OSError:
        free = 0
    previous = _size(path)
    exists = path.exists()
    mount = mount_of(path)
    path = Path(recorded(path))  # named as the user names it: relative to the workspace (a stage's paths are absolute)
    folder = path.parent
    kept = f"the previous {path} is intact (nothing was swapped in)" if exists else f"nothing was written to {path}"
    if scratch:  # a file written in place (a pass's rows): inside an output's temporary folder, or a scratch folder
        kept = "it is a working file of this run, removed with it; the outputs in place are intact"
        previous = 0
    need = (
        f"a complete one takes about {previous:,} bytes (the previous one's size), {free:,} are free"
        if previous
        else f"it needs more than the {free:,} bytes free"
    )
    taken = f"the new output had taken {written:,} bytes when the disk filled; " if written else ""
    err = DiskFullError(
        errno.ENOSPC,
        f"{folder}/: no space left on the device while writing {path} ({taken}{need}); "
        f"{kept}. Fix: free space on the "
        f"device of {folder}/ (`df -h {folder}`: the filesystem mounted at {mount}) or point the output elsewhere in "
        "params.yaml, and run again.",
    )
    return err
