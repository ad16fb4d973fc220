"""The MLflow experiment runs go to: created when missing (safe under races), described, and its runs page.

MLflow 3's UI shows an experiment's kind, its description (a tag) and a saved view of its runs table; aumesh sets them
from the provenance tags of the run that opens in it (:func:`experiment_tags`), keeps a description the user edited,
and links to the runs table sorted the way people compare aumesh's runs (:func:`runs_page_url`). Which store and
which client is :mod:`aumesh.tracking.mlflow_store`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from mlflow import MlflowClient


#: MLflow 3's experiment kind: the tag and value its UI and SDK (``mlflow.demo``, the UI's ``ExperimentKind``) use for a
#: model-training experiment, as opposed to ``genai_development`` (traces, judges).
EXPERIMENT_KIND_TAG = "mlflow.experimentKind"
MODEL_TRAINING_KIND = "custom_model_development"
#: The experiment's description: MLflow's UI shows this tag's Markdown above the runs table.
NOTE_TAG = "mlflow.note.content"
#: What people sort aumesh's runs by (metrics, then params), named in the description and the runs-page link.
SORT_METRICS = ("r2_mean", "r2_displacement_mean", "au_reliability_median")
SORT_PARAMS = ("preprocess.target", "features.name", "model.n_components")
#: MLflow's "share view" (the runs page's saved sort and columns) is an experiment tag ``mlflow.sharedViewState.<key>``
#: holding the page state as JSON, opened by ``?viewStateShareKey=<key>`` (MLflow 3.17's UI, ``viewStateShareKey``).
SHARED_VIEW_PREFIX = "mlflow.sharedViewState."
RUNS_VIEW_KEY = "aumesh-runs"


def runs_view_state(metric: str = SORT_METRICS[0]) -> dict[str, Any]:
    """The runs table aumesh's link opens: best *metric* first; the columns people sort by (metrics, then params)."""
    return {
        "searchFilter": "",
        "orderByKey": f"metrics.`{metric}`",
        "orderByAsc": False,
        "startTime": "ALL",
        "lifecycleFilter": "Active",
        "modelVersionFilter": "All Runs",
        "datasetsFilter": [],
        "selectedColumns": [f"metrics.`{m}`" for m in SORT_METRICS] + [f"params.`{p}`" for p in SORT_PARAMS],
    }


def experiment_tags(provenance_tags: Mapping[str, str]) -> dict[str, str]:
    """The experiment's kind, description and tags, from the provenance tags of a run opening in it.

    Parameters
    ----------
    provenance_tags : Mapping
        :func:`aumesh.tracking.runs.provenance_tags` (``aumesh.data.md5``, ``.nfiles``, ``.path``,
        ``aumesh.version``).

    Returns
    -------
    dict
        ``mlflow.experimentKind`` (model training), ``mlflow.note.content`` (what aumesh is, the data version,
        what to sort by, the README section), ``aumesh.project``, ``aumesh.data.md5`` (the latest run's tables),
        ``aumesh.version``.
    """
    md5 = provenance_tags.get("aumesh.data.md5")
    if md5:
        files = provenance_tags.get("aumesh.data.nfiles")
        data = (
            f"the frame tables tracked by DVC in `data.dvc` (`{provenance_tags.get('aumesh.data.path') or 'data'}/`, "
            f"md5 `{md5}`{f', {files} files' if files else ''}; each run's own is its dataset input and "
            "`aumesh.data.md5` tag)"
        )
    else:
        data = "frame tables outside a DVC workspace (no data version recorded)"
    note = (
        "**aumesh**: AU (+ head pose) -> MediaPipe FaceMesh. Each run fits the linear PLS model of the "
        '"AU+pose -> MP mesh PLS (v2)" model card on py-feat\'s per-frame tables (20 FACS AUs, Pitch/Yaw/Roll -> '
        "the 478-vertex mesh) and cross-validates it by video (GroupKFold).\n\n"
        f"**Data**: {data}.\n\n"
        "**Runs**: `dvc repro` / `dvc exp run` evaluations (tag `aumesh.stage` = evaluate) and `aumesh sweep` parents "
        "with one child per configuration. Sort by "
        + ", ".join(f"`{m}`" for m in SORT_METRICS)
        + " (CV R² within one target, the displacement R² across "
        "targets, AU-field reliability); the configuration is in the params "
        + ", ".join(f"`{p}`" for p in SORT_PARAMS)
        + ".\n\n"
        '**More**: the aumesh README, sections "Tracking" and "Sweeps and promotion".'
    )
    tags = {
        EXPERIMENT_KIND_TAG: MODEL_TRAINING_KIND,
        NOTE_TAG: note,
        "aumesh.project": "aumesh",
        SHARED_VIEW_PREFIX + RUNS_VIEW_KEY: json.dumps(runs_view_state()),
    }
    for key in ("aumesh.data.md5", "aumesh.version"):
        if provenance_tags.get(key):
            tags[key] = provenance_tags[key]
    return tags


def runs_page_url(server: str, experiment_id: str) -> str:
    """The MLflow UI's page of an experiment's runs, best ``r2_mean`` first with the columns people sort by
    (:func:`runs_view_state`, saved in the experiment by :func:`experiment_tags`), in the "Model training" view.

    MLflow 3.17's UI decides between its GenAI view (traces, "Overview") and "Model training" from the
    ``workflowType`` in the page's address, else from the browser's last choice (GenAI by default), not from the
    experiment's kind tag: this address opens the runs table in any browser.
    """
    return (
        f"{server.rstrip('/')}/#/experiments/{experiment_id}/runs?workflowType=machine_learning"
        f"&viewStateShareKey={RUNS_VIEW_KEY}"
    )


def describe_experiment(
    client: MlflowClient, experiment_id: str, tags: Mapping[str, str], current: Mapping[str, str] | None = None
) -> None:
    """Set the experiment *tags* whose value differs (an experiment made before, or by another tool, gets them too).

    *current* is the experiment's tags if already fetched. A user's own description (``mlflow.note.content`` not
    written by aumesh) is kept.
    """
    if current is None:
        current = client.get_experiment(experiment_id).tags
    for key, value in tags.items():
        if current.get(key) == value:
            continue
        if key == NOTE_TAG and current.get(key) and not current[key].startswith("**aumesh**"):
            continue  # edited in the UI: the user's text wins
        client.set_experiment_tag(experiment_id, key, value)


def ensure_experiment(
    client: MlflowClient, name: str, artifact_location: str | None = None, tags: Mapping[str, str] | None = None
) -> str:
    """Return the id of experiment *name*, creating it if needed (safe under races).

    Parameters
    ----------
    client : mlflow.MlflowClient
    name : str
        Experiment name.
    artifact_location : str, optional
        Used only when the experiment is created.
    tags : Mapping, optional
        Experiment tags (:func:`experiment_tags`): given when the experiment is created, and set on an existing one
        where they differ (:func:`describe_experiment`).

    Returns
    -------
    str
        The experiment id.

    Raises
    ------
    RuntimeError
        If the experiment exists but is deleted (fix: restore it or use another name).
    """
    from mlflow.exceptions import MlflowException

    exp = client.get_experiment_by_name(name)
    if exp is None:
        try:
            return client.create_experiment(name, artifact_location=artifact_location, tags=dict(tags or {}))
        except MlflowException:
            exp = client.get_experiment_by_name(name)  # created concurrently by another process
            if exp is None:
                raise
    if exp.lifecycle_stage == "deleted":
        raise RuntimeError(
            f"MLflow experiment {name!r} (id {exp.experiment_id}) is deleted in {client.tracking_uri}. "
            "Restore it (`mlflow experiments restore --experiment-id ...`) or set tracking.experiment "
            "to another name."
        )
    if tags:
        describe_experiment(client, exp.experiment_id, tags, exp.tags)
    return exp.experiment_id
