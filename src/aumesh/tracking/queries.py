"""Reading the tracking store: sweeps, their child runs, runs by tag, by owner and by data version.

The other side of :mod:`aumesh.tracking.runs` (which writes runs): ``aumesh runs``, ``aumesh promote`` and
the sweep's summary read through these. Every function takes the ``tracking`` config group (store and experiment,
:func:`aumesh.tracking.mlflow_store.resolve_tracking_uri`) and returns plain dicts or a DataFrame, never MLflow
objects. Owner filters use the tags every run carries (:func:`aumesh.tracking.runs.provenance_tags`):
``aumesh.user`` (git ``user.email``, else the login) and ``aumesh.workspace.id`` (a stable id of the clone).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aumesh.tracking.mlflow_store import (
    DATA_TAG,
    DEFAULT_EXPERIMENT,
    ERROR_TAG,
    PARENT_TAG,
    ROLE_TAG,
    SWEEP_CHILD_ROLE,
    SWEEP_PARENT_ROLE,
    USER_TAG,
    WORKSPACE_TAG,
    get_client,
)
from aumesh.tracking.values import run_family

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd

#: The columns every run table starts with (:func:`list_child_runs`, :func:`finished_runs_on_data`).
BASE_COLUMNS = [
    "run_id",
    "run_name",
    "status",
    "start_time",
    "end_time",
    "error",
    "user",
    "workspace",
    "parent_run_id",
    "family",  # the input family (tag aumesh.family; runs from before it: their features.name's family)
]


# ------------------------------------------------------------------ who is asking
def current_owner(root: Path | None = None) -> dict[str, Any]:
    """This caller's ``user`` and ``workspace`` (id), as the tags of their runs hold them, and ``workspaces``: every
    id this clone's runs may carry (:func:`aumesh.core.provenance.workspace_ids`: the ids of before too), what the
    queries' ``workspace`` filter takes."""
    from aumesh.core import provenance

    root = Path(root) if root is not None else provenance.repo_root()
    ids = provenance.workspace_ids(root)
    return {"user": provenance.user_identity(root), "workspace": ids[0], "workspaces": ids}


def _quoted(value: str) -> str:
    """A string literal of MLflow's filter grammar (which has no escapes: the other quote when one is inside)."""
    value = str(value)
    if "'" not in value:
        return f"'{value}'"
    if '"' not in value:
        return f'"{value}"'
    raise ValueError(f"cannot search for {value!r}: it holds both quote characters")


def _filter(tags: Mapping[str, str | None], status: str | None = None) -> str:
    parts = [f"tags.`{k}` = {_quoted(v)}" for k, v in tags.items() if v is not None]
    if status:
        parts.append(f"attributes.status = '{status}'")
    return " and ".join(parts)


def _experiment_id(client, tracking_cfg: Mapping[str, Any] | None) -> str | None:
    exp = client.get_experiment_by_name(str((tracking_cfg or {}).get("experiment") or DEFAULT_EXPERIMENT))
    return exp.experiment_id if exp is not None else None


def _search_all(client, experiment_ids: list[str], filter_string: str, order_by: list[str] | None = None):
    """Every run matching the filter (MLflow pages results 1000 at a time)."""
    token = None
    while True:
        page = client.search_runs(
            experiment_ids, filter_string=filter_string, order_by=order_by, max_results=1000, page_token=token
        )
        yield from page
        token = page.token
        if not token:
            return


# ------------------------------------------------------------------ one run
def run_record(run_id: str, tracking_cfg: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """A plain-dict view of one run: ``run_id``, ``run_name``, ``status``, ``experiment_id``, ``artifact_uri``,
    ``start_time`` (ms), ``params``, ``metrics`` (latest values), ``tags``, ``user``, ``workspace``, ``family`` (the
    input family: :func:`aumesh.tracking.values.run_family`)."""
    return _record(get_client(tracking_cfg).get_run(run_id))


def _record(run) -> dict[str, Any]:
    tags = dict(run.data.tags)
    return {
        "run_id": run.info.run_id,
        "run_name": run.info.run_name,
        "status": run.info.status,
        "experiment_id": run.info.experiment_id,
        "artifact_uri": run.info.artifact_uri,
        "start_time": run.info.start_time,
        "params": dict(run.data.params),
        "metrics": dict(run.data.metrics),
        "tags": tags,
        "user": tags.get(USER_TAG),
        "workspace": tags.get(WORKSPACE_TAG),
        "family": run_family(run.data.params, tags),
    }


# ------------------------------------------------------------------ run tables
def _frame(runs) -> pd.DataFrame:
    """Runs as a DataFrame (:data:`BASE_COLUMNS`, then ``params.<key>`` strings and ``metrics.<key>`` latest values),
    oldest first."""
    import pandas as pd

    rows: list[dict[str, Any]] = []
    for run in runs:
        tags = run.data.tags
        row: dict[str, Any] = {
            "run_id": run.info.run_id,
            "run_name": run.info.run_name,
            "status": run.info.status,
            "start_time": pd.to_datetime(run.info.start_time, unit="ms", utc=True),
            "end_time": pd.to_datetime(run.info.end_time, unit="ms", utc=True) if run.info.end_time else pd.NaT,
            "error": tags.get(ERROR_TAG),
            "user": tags.get(USER_TAG),
            "workspace": tags.get(WORKSPACE_TAG),
            "parent_run_id": tags.get(PARENT_TAG),
            "family": run_family(run.data.params, tags),
        }
        row.update({f"params.{k}": v for k, v in sorted(run.data.params.items())})
        row.update({f"metrics.{k}": v for k, v in sorted(run.data.metrics.items())})
        rows.append(row)
    df = pd.DataFrame(rows, columns=None if rows else BASE_COLUMNS)
    if rows:
        df = df.sort_values("start_time", kind="stable").reset_index(drop=True)
    return df


def list_child_runs(parent_run_id: str, tracking_cfg: Mapping[str, Any] | None = None) -> pd.DataFrame:
    """Child runs of *parent_run_id* as a DataFrame (one row per child, oldest first).

    Returns
    -------
    pandas.DataFrame
        Columns ``run_id``, ``run_name``, ``status``, ``start_time``, ``end_time`` (UTC timestamps), ``error``
        (``aumesh.error`` tag or None), ``user``, ``workspace``, ``parent_run_id``, ``family``, then ``params.<key>`` (strings)
        and ``metrics.<key>`` (latest value).
    """
    client = get_client(tracking_cfg)
    parent = client.get_run(parent_run_id)
    return _frame(_search_all(client, [parent.info.experiment_id], _filter({PARENT_TAG: parent_run_id})))


def runs_frame(run_ids: Sequence[str], tracking_cfg: Mapping[str, Any] | None = None) -> pd.DataFrame:
    """The runs *run_ids* as :func:`list_child_runs` tables them (``aumesh promote --family F RUN``)."""
    from mlflow.exceptions import MlflowException

    from aumesh.core.errors import UserError

    client = get_client(tracking_cfg)
    runs = []
    for run_id in run_ids:
        try:
            runs.append(client.get_run(run_id))
        except MlflowException:
            raise UserError(
                f"run {run_id}: no such run in the tracking store ({client.tracking_uri}). Fix: copy a run id from "
                "`aumesh runs` (or `aumesh runs --sweeps`)."
            ) from None
    return _frame(runs)


def finished_runs_on_data(data_md5: str, tracking_cfg: Mapping[str, Any] | None = None) -> pd.DataFrame:
    """Every FINISHED model run (sweep children and pipeline evaluate runs) of the configured experiment that used
    the frame tables with DVC hash *data_md5*, whoever ran it (``aumesh promote --across``).

    Returns
    -------
    pandas.DataFrame
        As :func:`list_child_runs`; empty when the experiment does not exist.
    """
    client = get_client(tracking_cfg)
    exp = _experiment_id(client, tracking_cfg)
    if exp is None:
        return _frame([])
    runs = [
        r
        for r in _search_all(client, [exp], _filter({DATA_TAG: data_md5}, status="FINISHED"))
        if r.data.tags.get(ROLE_TAG) == SWEEP_CHILD_ROLE or r.data.tags.get("aumesh.stage") == "evaluate"
    ]
    return _frame(runs)


# ------------------------------------------------------------------ newest runs
def latest_runs_tagged(
    tag: str,
    value: str,
    tracking_cfg: Mapping[str, Any] | None = None,
    max_results: int = 20,
    user: str | None = None,
    workspace: str | Sequence[str] | None = None,
) -> list[dict[str, Any]]:
    """The newest runs of the configured experiment whose *tag* equals *value*, newest first.

    Parameters
    ----------
    tag, value : str
        E.g. ``("aumesh.role", "sweep-parent")`` (sweeps) or ``("aumesh.stage", "evaluate")`` (pipeline runs).
    tracking_cfg : Mapping, optional
        The ``tracking`` config group (``experiment`` names the experiment).
    max_results : int, default 20
    user, workspace : str, optional
        Only runs of this user (``aumesh.user``) / this clone (``aumesh.workspace.id``; a list: any of these ids,
        :func:`current_owner`'s ``workspaces``).

    Returns
    -------
    list of dict
        :func:`run_record` views (``start_time`` in ms since the epoch); empty when the experiment does not exist.
    """
    client = get_client(tracking_cfg)
    exp = _experiment_id(client, tracking_cfg)
    if exp is None:
        return []
    # MLflow's filter has no IN for tags: one search per id of the clone, merged newest first
    ids: list[str | None] = [workspace] if workspace is None or isinstance(workspace, str) else list(workspace)
    found = {}
    for one in ids:
        for run in client.search_runs(
            [exp],
            filter_string=_filter({tag: value, USER_TAG: user, WORKSPACE_TAG: one}),
            order_by=["attributes.start_time DESC"],
            max_results=max_results,
        ):
            found[run.info.run_id] = run
    runs = sorted(found.values(), key=lambda r: r.info.start_time, reverse=True)[:max_results]
    return [_record(run) for run in runs]


def sweeps(
    tracking_cfg: Mapping[str, Any] | None = None,
    limit: int = 20,
    user: str | None = None,
    workspace: str | Sequence[str] | None = None,
) -> list[dict[str, Any]]:
    """The newest sweep parent runs (of *user* / *workspace* when given), newest first (:func:`run_record` views)."""
    return latest_runs_tagged(ROLE_TAG, SWEEP_PARENT_ROLE, tracking_cfg, limit, user=user, workspace=workspace)


def latest_parent_run(
    tracking_cfg: Mapping[str, Any] | None = None,
    user: str | None = None,
    workspace: str | Sequence[str] | None = None,
) -> str | None:
    """Id of the most recently started sweep parent run of the configured experiment (of *user* / *workspace* when
    given); None when there is none."""
    runs = sweeps(tracking_cfg, 1, user=user, workspace=workspace)
    return runs[0]["run_id"] if runs else None


def latest_evaluate_run(
    tracking_cfg: Mapping[str, Any] | None = None,
    workspace: str | Sequence[str] | None = None,
    family: str = "au",
) -> dict[str, Any] | None:
    """The newest pipeline evaluate run of input *family* (of this *workspace* when given), or None.

    The evaluate stage logs one run per family it fits (the AU model's and each ``families.<family>``'s, tag
    :data:`aumesh.tracking.mlflow_store.FAMILY_TAG`); a family's promotion is overruled only by a run of its own
    family. Runs from before the tag count by their ``features.name``."""
    runs = latest_runs_tagged("aumesh.stage", "evaluate", tracking_cfg, 20, workspace=workspace)
    return next((r for r in runs if (r["family"] or "au") == family), None)
