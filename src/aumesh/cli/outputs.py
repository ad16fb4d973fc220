"""The one guard of every command that writes a path the user names (``--out``, ``--truth``): never into the release.

``release/`` (``paths.release_dir``) is the release stage's output, tracked by DVC: ``aumesh animate --out
release/au_to_mesh.glb`` would overwrite the release's own rig, ``aumesh predict --out release/au_to_mesh_pls.npz``
its NPZ, and ``dvc status`` would then call the release modified with nothing saying why. A path inside it (the
folder itself or any file under it, after resolving ``..`` and symbolic links) is refused in one line naming the path
and the fix, unless ``--force``.
"""

from __future__ import annotations

import os
from pathlib import Path

from aumesh.core.errors import UserError

#: Where the release folder is named when the workspace has no ``params.yaml`` (the config's default).
DEFAULT_RELEASE_DIR = "release"


def release_dir(params: str | os.PathLike = "params.yaml") -> Path:
    """The workspace's release folder, resolved: ``paths.release_dir`` of ``params`` when it exists and names one,
    else :data:`DEFAULT_RELEASE_DIR` (relative paths are the current folder's, as the stages read them)."""
    name: str = DEFAULT_RELEASE_DIR
    params = Path(params)
    if params.is_file():
        import yaml

        try:
            data = yaml.safe_load(params.read_text()) or {}
        except (OSError, yaml.YAMLError):
            data = {}  # a broken params.yaml is the stages' to report; the guard keeps the default
        paths = data.get("paths") if isinstance(data, dict) else None
        if isinstance(paths, dict) and isinstance(paths.get("release_dir"), str) and paths["release_dir"].strip():
            name = paths["release_dir"]
    return Path(name).resolve()


def inside_release(path: str | os.PathLike, params: str | os.PathLike = "params.yaml") -> Path | None:
    """The resolved release folder when ``path`` is it or lies under it, else None."""
    release = release_dir(params)
    target = Path(path).resolve()
    return release if target == release or release in target.parents else None


def refuse_release_path(option: str, path: str | os.PathLike | None, *, force: bool) -> None:
    """Raise :class:`UserError` when ``path`` (the value of ``option``, e.g. ``--out``) is inside the release folder
    and ``force`` is False; None paths (an option not given) pass.

    Raises
    ------
    UserError
        One line: the path, the release folder it is in, and the fix (another path, or ``--force``).
    """
    if path is None or force:
        return
    release = inside_release(path)
    if release is not None:
        raise UserError(
            f"{option} {path}: inside the release folder {release} (the release stage's output, tracked by DVC); "
            f"writing there overwrites the release's own files. Fix: write outside it, or add --force"
        )


def add_force(parser) -> None:
    """The ``--force`` flag of a command guarded by :func:`refuse_release_path`."""
    parser.add_argument(
        "--force",
        action="store_true",
        help="write even into the release folder (paths.release_dir, e.g. release/); refused without it",
    )


__all__ = ["add_force", "inside_release", "refuse_release_path", "release_dir"]
