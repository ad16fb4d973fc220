"""This machine's settings: what differs between teammates' clones and must never be committed.

Where a run executes (the tracking server, a cluster) is not what it computes, so it is no part of ``conf/`` or
``params.yaml`` (both committed, both read by DVC). It lives in a git-ignored YAML file at the workspace root,
:data:`LOCAL_SETTINGS` (``aumesh.local.yaml``), with the same keys as ``conf/``::

    tracking:
      tracking_uri: http://mlflow.lab.example:5000

Which tracking store a run uses (:func:`aumesh.tracking.mlflow_store.resolve_tracking_uri`), first found wins:

1. the ``MLFLOW_TRACKING_URI`` environment variable;
2. ``tracking.tracking_uri`` in ``aumesh.local.yaml``;
3. ``tracking.tracking_uri`` of the composed configuration (``conf/tracking/mlflow.yaml``; meant for a
   repo-relative store, it is committed);
4. ``sqlite:///<workspace>/mlflow.db``.

``AUMESH_LOCAL_SETTINGS`` names another file (tests, several settings side by side).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

LOCAL_SETTINGS = "aumesh.local.yaml"
SETTINGS_ENV = "AUMESH_LOCAL_SETTINGS"
#: The groups the local settings may hold: where a run is logged (where it computes, ``compute``, belongs here too
#: once the compute engine reads it: :func:`local_value`).
KNOWN_GROUPS = frozenset({"tracking"})


def settings_path(root: Path | None = None) -> Path | None:
    """The local settings file: ``$AUMESH_LOCAL_SETTINGS``, else ``<workspace>/aumesh.local.yaml`` (None outside a
    workspace)."""
    if os.environ.get(SETTINGS_ENV):
        return Path(os.environ[SETTINGS_ENV]).expanduser()
    if root is None:
        from aumesh.core import provenance

        try:
            root = provenance.repo_root()
        except FileNotFoundError:
            return None
    return Path(root) / LOCAL_SETTINGS


def local_settings(root: Path | None = None) -> dict[str, Any]:
    """The local settings as a nested dict (empty when there is no file).

    Raises
    ------
    aumesh.core.errors.ConfigError
        The file is not YAML, not a mapping, or has a key aumesh does not read; the message names the file.
    """
    import yaml

    from aumesh.core.errors import ConfigError

    path = settings_path(root)
    if path is None or not path.is_file():
        return {}
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({err}). Fix the file or remove it.") from None
    if not isinstance(data, Mapping):
        raise ConfigError(f"{path}: must be a mapping such as `tracking: {{tracking_uri: http://host:5000}}`.")
    unknown = sorted(set(data) - KNOWN_GROUPS)
    if unknown:
        raise ConfigError(
            f"{path}: unknown group(s) {', '.join(unknown)}; it holds {', '.join(sorted(KNOWN_GROUPS))} "
            "(where runs are logged, never what they compute)."
        )
    return {str(k): dict(v or {}) for k, v in data.items()}


def local_value(group: str, key: str, root: Path | None = None) -> Any:
    """``<group>.<key>`` from the local settings, None when unset."""
    return local_settings(root).get(group, {}).get(key)
