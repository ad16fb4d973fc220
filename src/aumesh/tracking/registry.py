"""The MLflow model registry: register a run's model as a version, point an alias at it, fetch artifacts."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from aumesh.tracking.mlflow_store import get_client
from aumesh.tracking.values import MAX_TAG_VALUE_LENGTH, _str_value

CHAMPION_ALIAS = "champion"


def register_model_version(
    run_id: str,
    artifact_path: str,
    name: str,
    tracking_cfg: Mapping[str, Any] | None = None,
    alias: str | None = CHAMPION_ALIAS,
    tags: Mapping[str, Any] | None = None,
    description: str | None = None,
) -> dict[str, Any]:
    """Register a run's artifact directory as a version of registered model *name*: one version per run.

    Idempotent: a run already registered under *name* is not registered again; its (lowest) version gets *tags* and
    *alias*. Two registrations of one run at once (two clones promoting the same sweep on one server; a workspace's
    promotion lock does not reach another clone) may both create a version: each then looks again
    (:func:`_versions_of_run`) and the one whose version is not the lowest deletes its own, so both end on the same
    version and the registry holds one.

    The source is ``<run artifact_uri>/<artifact_path>``: a ``file://`` URI inside the
    run's artifact directory for a local store, an ``mlflow-artifacts:/`` URI for a
    tracking server; both pass MLflow's source-in-run validation and need no network
    beyond the tracking URI. aumesh runs log an MLflow pyfunc model there
    (:mod:`aumesh.tracking.pyfunc`), so ``models:/<name>@<alias>`` loads with
    ``mlflow.pyfunc.load_model``.

    Parameters
    ----------
    run_id : str
        The run that produced the artifact.
    artifact_path : str
        Artifact directory of the run (e.g. ``"model"``); must exist.
    name : str
        Registered model name (created if missing).
    tracking_cfg : Mapping, optional
    alias : str or None, default "champion"
        Alias to point at the new version; None sets none.
    tags : Mapping, optional
        Model version tags.
    description : str, optional
        Model version description.

    Returns
    -------
    dict
        ``name``, ``version`` (str), ``source``, ``alias``, ``run_id``, ``reused`` (True when the run was registered
        before, by another promotion or a concurrent one).

    Raises
    ------
    FileNotFoundError
        If the run has no artifact at *artifact_path*.
    """
    from mlflow.exceptions import MlflowException

    client = get_client(tracking_cfg)
    run = client.get_run(run_id)
    if not client.list_artifacts(run_id, artifact_path):
        raise FileNotFoundError(
            f"run {run_id} has no artifacts under {artifact_path!r} ({run.info.artifact_uri}); "
            "evaluate runs and sweep children log their model there (aumesh.tracking.pyfunc)."
        )
    try:
        client.get_registered_model(name)
    except MlflowException:
        try:
            client.create_registered_model(
                name, description="aumesh AU(+pose) -> 478-vertex mesh PLS (release-format NPZ)"
            )
        except MlflowException:
            client.get_registered_model(name)  # created concurrently; re-raise if it still does not exist
    source = f"{run.info.artifact_uri.rstrip('/')}/{artifact_path.strip('/')}"
    clean_tags = {str(k): _str_value(v, MAX_TAG_VALUE_LENGTH) for k, v in (tags or {}).items()}
    before = _versions_of_run(client, name, run_id)
    if before:
        mv, reused = before[0], True
    else:
        mine = client.create_model_version(
            name, source, run_id=run_id, tags=clean_tags or None, description=description
        )
        mv = _versions_of_run(client, name, run_id)[0]  # the lowest: another registration's if it came first
        reused = str(mv.version) != str(mine.version)
        if reused:  # a concurrent registration of this run got the lower version: ours goes
            client.delete_model_version(name, mine.version)
    if reused:  # the run's version, as this promotion names it (its journal finds it by these tags)
        for key, value in clean_tags.items():
            client.set_model_version_tag(name, mv.version, key, value)
    if alias:
        client.set_registered_model_alias(name, alias, mv.version)
    return {
        "name": name,
        "version": str(mv.version),
        "source": mv.source,
        "alias": alias,
        "run_id": run_id,
        "reused": reused,
    }


def _versions_of_run(client, name: str, run_id: str) -> list:
    """The versions of registered model *name* made from run *run_id*, lowest version first."""
    found = [mv for mv in client.search_model_versions(f"run_id = '{run_id}'") if mv.name == name]
    return sorted(found, key=lambda mv: int(mv.version))


def model_version_by_alias(
    name: str, alias: str = CHAMPION_ALIAS, tracking_cfg: Mapping[str, Any] | None = None
) -> dict[str, Any] | None:
    """``{"name", "version", "run_id", "source"}`` of the version *alias* points to, or None."""
    from mlflow.exceptions import MlflowException

    client = get_client(tracking_cfg)
    try:
        mv = client.get_model_version_by_alias(name, alias)
    except MlflowException:
        return None
    return {"name": name, "version": str(mv.version), "run_id": mv.run_id, "source": mv.source}


def download_run_artifacts(
    run_id: str, artifact_path: str, dst_dir: str | Path, tracking_cfg: Mapping[str, Any] | None = None
) -> Path:
    """Download a run's artifact (file or directory) into *dst_dir*; return the local path."""
    Path(dst_dir).mkdir(parents=True, exist_ok=True)
    return Path(get_client(tracking_cfg).download_artifacts(run_id, artifact_path, str(dst_dir)))


def set_alias(name: str, alias: str, version: str | None, tracking_cfg: Mapping[str, Any] | None = None) -> None:
    """Point *alias* of registered model *name* at *version*; None removes the alias (a promotion rolled back to
    "no champion yet")."""
    from mlflow.exceptions import MlflowException

    client = get_client(tracking_cfg)
    if version is not None:
        client.set_registered_model_alias(name, alias, version)
        return
    try:
        client.delete_registered_model_alias(name, alias)
    except MlflowException:  # no such model or alias: nothing points anywhere already
        pass


def find_version(
    name: str, run_id: str, tag: str, value: str, tracking_cfg: Mapping[str, Any] | None = None
) -> dict[str, Any] | None:
    """The version of *name* registered from run *run_id* with tag ``tag == value`` (e.g. the promotion that created
    it), as :func:`register_model_version` returns it (``alias`` None), or None."""
    client = get_client(tracking_cfg)
    for mv in client.search_model_versions(f"run_id = '{run_id}'"):
        if mv.name == name and (mv.tags or {}).get(tag) == value:
            return {"name": name, "version": str(mv.version), "source": mv.source, "alias": None, "run_id": run_id}
    return None
