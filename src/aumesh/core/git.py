"""Running ``git`` for a record: its output, or None on any failure (no git, not a repository, a slow disk)."""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path

GIT_TIMEOUT_S = 30.0  # git status in a fresh DVC temp copy can be slow on a loaded box


def run_git(args: Sequence[str], cwd: Path) -> str | None:
    """Run ``git <args>`` in *cwd*; return stripped stdout or None on any failure."""
    exe = shutil.which("git")
    if exe is None:
        return None
    try:
        out = subprocess.run(
            [exe, *args],
            cwd=str(cwd),
            capture_output=True,
            text=True,
            timeout=GIT_TIMEOUT_S,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    if out.returncode != 0:
        return None
    return out.stdout.strip()
