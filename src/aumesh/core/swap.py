"""Swap a finished folder in for the previous one in one step, where the filesystem can.

Linux's ``renameat2(..., RENAME_EXCHANGE)`` (``man 2 rename``; glibc >= 2.28, Linux >= 3.15) exchanges two paths
atomically: there is no moment at which the target is missing, so a SIGKILL can leave only the old folder or the new
one under the target's name. Filesystems without it (some network and FUSE filesystems; other systems) answer
``EINVAL``/``ENOSYS``/``EOPNOTSUPP``, and the caller falls back to two renames (target aside, new folder in); a kill
between those two leaves the previous copy aside, which :func:`aumesh.core.io.restore_previous` puts back on the next
start.
"""

from __future__ import annotations

import ctypes
import errno
import functools
import os
from pathlib import Path

RENAME_EXCHANGE = 2  # <linux/fs.h>
_AT_FDCWD = -100
#: errnos that mean "this filesystem or kernel cannot exchange": fall back to two renames
UNSUPPORTED = frozenset({errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP, getattr(errno, "ENOTSUP", errno.EOPNOTSUPP)})


@functools.cache
def _renameat2():
    """libc's ``renameat2``, or None (not Linux, or a libc without it)."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


def exchange(a: str | Path, b: str | Path) -> bool:
    """Exchange paths ``a`` and ``b`` (both must exist) atomically.

    Returns
    -------
    bool
        True when exchanged; False when this system or filesystem cannot (the caller renames instead).

    Raises
    ------
    OSError
        Any other failure (permissions, a missing path), with the errno and both paths.
    """
    fn = _renameat2()
    if fn is None:
        return False
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in UNSUPPORTED:
        return False
    raise OSError(err, os.strerror(err), str(a), None, str(b))
