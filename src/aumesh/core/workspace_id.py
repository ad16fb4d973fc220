"""A stable id of a clone (the ``aumesh.workspace.id`` tag of its runs): "your latest sweep" is this clone's.

The id was SHA-256 of the clone's path and its git remote's URL as written, so it changed with the spelling of the
URL (``/x/origin.git`` against ``file:///x/origin.git``, a trailing slash, ``git@host:x`` against
``ssh://git@host/x``) and when the clone moved, and "your latest sweep" then found nothing. Now it is a random id
created once, on first use, in the clone's own git folder (:data:`ID_FILE` in ``git rev-parse --absolute-git-dir``:
``.git/`` of a clone, ``.git/worktrees/<name>/`` of a worktree; never committed, never pushed), beside the path it
was created at:

* a moved clone (``mv``) carries its ``.git/`` and so its id; the new path is recorded;
* a copied clone (``cp -r``) carries it too, but the original still holds the same id at the recorded path: the copy
  is another workspace and gets a new id (the original keeps its own);
* a clone whose git folder cannot be written (or no git) falls back to SHA-256 of its path and its remote's
  normalised URL (:func:`normalise_remote_url`), stable across spellings.

Runs logged before keep the old id: :func:`workspace_ids` lists this clone's id and the old ids it had (the one of
its path and remote as written, and those recorded when the id was created or the clone moved), and the queries that
match a workspace (:mod:`aumesh.tracking.queries`) match any of them.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import secrets
from pathlib import Path
from typing import Any

from aumesh.core.git import run_git as _git

ID_FILE = "aumesh-workspace-id.json"
_SCP = re.compile(r"^(?:[^@/]+@)?(?P<host>[^:/]+):(?P<path>.*)$")  # git@host:x/y (git's scp-like syntax)


def normalise_remote_url(url: str | None, root: Path | None = None) -> str:
    """One spelling of a git remote URL: ``host/path`` for a network URL, the absolute path of a local one.

    ``/x/origin.git``, ``/x/origin.git/``, ``/x/origin`` and ``file:///x/origin.git`` give ``/x/origin``;
    ``git@host:x/y.git``, ``ssh://git@host/x/y``, ``ssh://git@host:22/x/y`` and ``https://host/x/y.git`` give
    ``host/x/y`` (the user, the default port and the scheme are how one reaches the repository, not which it is). A
    relative path is resolved against ``root`` (as git does). None or empty: ``""``.
    """
    from urllib.parse import urlsplit

    text = (url or "").strip()
    if not text:
        return ""
    text = text.rstrip("/")
    text = text.removesuffix(".git").rstrip("/")
    parts = urlsplit(text)
    if parts.scheme == "file":
        return os.path.normpath(parts.path)
    if parts.scheme and parts.netloc:
        host = (parts.hostname or "").lower()
        port = f":{parts.port}" if parts.port and parts.port not in (22, 80, 443, 9418) else ""
        return f"{host}{port}/{parts.path.lstrip('/').removeprefix('~/')}"
    scp = _SCP.match(text)
    if scp and not os.path.isabs(text) and "/" not in text.split(":", 1)[0]:
        return f"{scp['host'].lower()}/{scp['path'].lstrip('/').removeprefix('~/')}"
    path = Path(text)
    if not path.is_absolute() and root is not None:
        path = Path(root) / path
    return os.path.normpath(path)


def legacy_workspace_id(root: Path) -> str:
    """The id runs were tagged with before: SHA-256 of the path and the remote URL as written (16 hex digits)."""
    remote = _git(["config", "--get", "remote.origin.url"], root) or ""
    return hashlib.sha256(f"{root.as_posix()}\n{remote}".encode()).hexdigest()[:16]


def _fallback_id(root: Path) -> str:
    remote = normalise_remote_url(_git(["config", "--get", "remote.origin.url"], root), root)
    return hashlib.sha256(f"{root.as_posix()}\n{remote}".encode()).hexdigest()[:16]


def _id_file(root: Path) -> Path | None:
    git_dir = _git(["rev-parse", "--absolute-git-dir"], root)
    return Path(git_dir) / ID_FILE if git_dir else None


def _read(path: Path | None) -> dict[str, Any] | None:
    if path is None:
        return None
    with contextlib.suppress(OSError, ValueError):
        record = json.loads(path.read_text())
        if isinstance(record, dict) and isinstance(record.get("id"), str) and isinstance(record.get("path"), str):
            return record
    return None


def _write(path: Path, record: dict[str, Any], create: bool) -> dict[str, Any]:
    """Write ``record``; ``create``: only if no other process wrote one first (then that one is returned)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(record, indent=1) + "\n")
    try:
        if create:
            try:
                os.link(tmp, path)  # fails if it exists: two first uses at once agree on one id
            except FileExistsError:
                return _read(path) or record
        else:
            os.replace(tmp, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    return record


def _record(root: Path) -> dict[str, Any] | None:
    """This clone's id record, created or updated (moved, copied) as the module docstring says; None when it cannot
    be stored."""
    path = _id_file(root)
    if path is None:
        return None
    record = _read(path)
    here = root.as_posix()
    try:
        if record is None:
            fresh = {"id": secrets.token_hex(8), "path": here, "legacy": [legacy_workspace_id(root)]}
            return _write(path, fresh, create=True)
        if record["path"] == here:
            return record
        original = Path(record["path"])
        copied = original.is_dir() and (_read(_id_file(original)) or {}).get("id") == record["id"]
        legacy = sorted({*record.get("legacy", []), legacy_workspace_id(root)})
        if copied:  # the original still holds this id where it was made: this is another workspace
            return _write(path, {"id": secrets.token_hex(8), "path": here, "legacy": []}, create=False)
        return _write(path, {**record, "path": here, "legacy": legacy}, create=False)  # moved
    except OSError:  # a git folder that cannot be written: the stored id if any, else the fallback
        return record if record is not None and record["path"] == here else None


def workspace_id(root: Path | str) -> str:
    """This clone's id (16 hex digits; see the module docstring)."""
    root = Path(root).resolve()
    record = _record(root)
    return str(record["id"]) if record is not None else _fallback_id(root)


def workspace_ids(root: Path | str) -> list[str]:
    """Every id this clone's runs may carry: :func:`workspace_id` first, then the ids of before (the old formula on
    the path and remote as they are now, and those recorded when the id was made or the clone moved)."""
    root = Path(root).resolve()
    record = _record(root) or {}
    ids = [workspace_id(root), *record.get("legacy", []), legacy_workspace_id(root), _fallback_id(root)]
    return list(dict.fromkeys(ids))
