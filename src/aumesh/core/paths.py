"""Paths as the outputs record them (workspace-relative) and where a path lives (its mount)."""

from __future__ import annotations

import os
from pathlib import Path


def recorded(path: str | Path, root: str | Path | None = None) -> str:
    """``path`` as the outputs record it: relative to ``root`` (default: the current directory, the workspace) when
    inside it, else unchanged. Records are shared (committed, pushed to a DVC remote) and never hold this machine's
    workspace path."""
    text = str(path)
    if not os.path.isabs(text):
        return text
    base = os.path.abspath(root if root is not None else os.getcwd())
    rel = os.path.relpath(text, base)
    return text if rel == os.pardir or rel.startswith(os.pardir + os.sep) else rel


def mount_of(path: str | Path) -> str:
    """The mount point of the filesystem that holds ``path`` (its nearest existing ancestor, symlinks followed): where
    ``df`` must look when ``build/`` or ``release/`` lives on another device than the workspace."""
    current = Path(os.path.realpath(path))
    while not current.exists() and current != current.parent:
        current = current.parent
    while not os.path.ismount(current) and current != current.parent:
        current = current.parent
    return str(current)
