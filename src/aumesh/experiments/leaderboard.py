"""A sweep's runs as a table, best first by the promotion criterion (``aumesh runs``); past sweeps (``aumesh runs --sweeps``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd


def runs_table(children: pd.DataFrame, metric: str | None = None, family: str | None = None) -> pd.DataFrame:
    """A sweep's children as a table, best first by the promotion criterion (see :mod:`aumesh.experiments.ranking`),
    ranked within each input family (an emotion model's R² and an AU model's answer different questions).

    Parameters
    ----------
    children : DataFrame
        :func:`aumesh.tracking.queries.list_child_runs` output.
    metric : str, optional
        Ranking metric; default: :func:`aumesh.experiments.ranking.default_metric` of each family's finished runs'
        targets.
    family : str, optional
        Only the runs of this input family (``au``, ``blendshapes``, ``emotions``).

    Returns
    -------
    DataFrame
        ``family``, ``rank`` (within the family), ``run_id``, ``status``, config keys, ``r2_mean``, ``r2_std``,
        ``r2_displacement_mean``, ``mae_mean``, ``n_components`` (effective), ``error``; family by family
        (:data:`aumesh.experiments.ranking.FAMILY_ORDER`), FINISHED runs ranked first, then the others.
        ``attrs["metric"]`` names the ranking metric (the first family's), ``attrs["metrics"]`` each family's.
    """
    import pandas as pd

    from aumesh.experiments import ranking

    candidates = ranking.candidates_from_frame(children)
    if family is not None:
        candidates = [c for c in candidates if c.input_family == family]
    rows = []
    metrics: dict[str, str] = {}
    for fam, group in ranking.by_family(candidates).items():
        finished = [c for c in group if c.status == "FINISHED"]
        metrics[fam] = fam_metric = metric or ranking.default_metric({c.target for c in finished})
        ranked = ranking.rank([c for c in finished if fam_metric in c.metrics], fam_metric) if finished else []
        done = {r.run_id for r in ranked}
        order = ranked + [c for c in group if c.run_id not in done]
        rows += [_row(fam, i + 1 if i < len(ranked) else None, c) for i, c in enumerate(order)]
    table = pd.DataFrame(rows, dtype=object)  # object: missing values stay None, integers stay integers
    table.attrs["metric"] = next(iter(metrics.values()), metric or ranking.default_metric(()))
    table.attrs["metrics"] = metrics
    return table


def _row(family: str, rank: int | None, c) -> dict[str, Any]:
    """One line of :func:`runs_table`."""
    m = c.metrics
    return {
        "family": family,
        "rank": rank,
        "run_id": c.run_id,
        "status": c.status,
        "target": c.params.get("preprocess.target"),
        "neutral": c.params.get("preprocess.neutral.method"),
        "features": c.params.get("features.name"),
        "n_components_requested": c.params.get("model.n_components"),
        "n_components": int(m["n_components"]) if "n_components" in m else None,
        "r2_mean": m.get("r2_mean"),
        "r2_std": m.get("r2_std"),
        "r2_displacement_mean": m.get("r2_displacement_mean"),
        "mae_mean": m.get("mae_mean"),
        "error": (c.error or "")[:90] or None,
    }


def format_runs_table(table: pd.DataFrame) -> str:
    """Fixed-width text of :func:`runs_table` (short run ids, R² as mean ± std, k as requested->effective)."""
    if table.empty:
        return "(no child runs)"

    def missing(v) -> bool:
        return v is None or (isinstance(v, float) and v != v)

    def num(v, fmt: str = "{:.4f}") -> str:
        return "" if missing(v) else fmt.format(float(v))

    by = {table.attrs.get("metric", "?")}
    if len(set(table.attrs.get("metrics", {}).values()) | by) > 1:
        by = {", ".join(f"{f}: {m}" for f, m in table.attrs["metrics"].items())}
    metric = by.pop()
    lines = [
        f"ranked by {metric} ({'desc' if not metric.startswith('mae') else 'asc'}),"
        " ties -> fewer components; FAILED runs last"
        + ("; ranked within each input family (# is the rank in its family)" if table["family"].nunique() > 1 else ""),
        f"{'#':>3} {'run':8} {'status':8} {'family':11} {'target':8} {'neutral':7} {'features':30} "
        f"{'k':>6} {'r2_mean ± std':>17} {'r2_disp':>8} {'mae':>8}  error",
    ]
    for r in table.to_dict(orient="records"):
        k = "" if missing(r["n_components_requested"]) else str(r["n_components_requested"])
        if not missing(r["n_components"]) and str(r["n_components"]) != k:
            k += f"->{r['n_components']}"
        r2 = "" if missing(r["r2_mean"]) else f"{num(r['r2_mean'])} ± {num(r['r2_std'])}"
        rank = "" if missing(r["rank"]) else str(r["rank"])
        lines.append(
            f"{rank:>3} {str(r['run_id'])[:8]:8} {r['status']:8} {str(r['family']):11} {str(r['target']):8} "
            f"{str(r['neutral']):7} {str(r['features']):30} {k:>6} {r2:>17} {num(r['r2_displacement_mean']):>8} "
            f"{num(r['mae_mean']):>8}  {'' if missing(r['error']) else r['error']}"
        )
    return "\n".join(lines)


def sweeps_table(
    tracking_cfg: Mapping[str, Any] | None = None,
    limit: int = 20,
    user: str | None = None,
    workspace: str | None = None,
) -> pd.DataFrame:
    """Past sweeps of the configured experiment, newest first, each with its size and best run (``aumesh runs --sweeps``).

    Parameters
    ----------
    tracking_cfg : Mapping, optional
        The ``tracking`` config group (store and experiment).
    limit : int, default 20
        How many of the newest sweeps.
    user, workspace : str, optional
        Only the sweeps of this user (``aumesh.user``) / this clone (``aumesh.workspace.id``).

    Returns
    -------
    DataFrame
        ``sweep`` (parent run id), ``started`` (UTC timestamp), ``user`` (whose), ``workspace`` (which clone: its
        id), ``status``, ``n_runs``, ``n_failed`` (children
        not FINISHED), ``metric`` (the ranking metric, as :func:`runs_table`), ``best_value``, ``best_run``,
        ``best`` (the best run's target, features and components), ``overrides`` (what the sweep varied).
    """
    import pandas as pd

    from aumesh.tracking import queries

    rows = []
    for parent in queries.sweeps(tracking_cfg, limit, user=user, workspace=workspace):
        children = queries.list_child_runs(parent["run_id"], tracking_cfg)
        table = runs_table(children) if len(children) else pd.DataFrame()
        best = table.iloc[0].to_dict() if len(table) and table.iloc[0]["rank"] == 1 else None
        metric = table.attrs.get("metric") if best else None
        rows.append(
            {
                "sweep": parent["run_id"],
                "started": pd.to_datetime(parent["start_time"], unit="ms", utc=True),
                "user": parent["user"],
                "workspace": parent["workspace"],
                "status": parent["status"],
                "n_runs": len(children),
                "n_failed": int((children["status"] != "FINISHED").sum()) if len(children) else 0,
                "metric": metric,
                "best_value": best.get(metric) if best else None,
                "best_run": best["run_id"] if best else None,
                "best": (f"{best['target']} {best['features']} k={best['n_components_requested']}" if best else None),
                "overrides": parent["tags"].get("aumesh.sweep.overrides", ""),
            }
        )
    columns = [
        "sweep",
        "started",
        "user",
        "workspace",
        "status",
        "n_runs",
        "n_failed",
        "metric",
        "best_value",
        "best_run",
        "best",
        "overrides",
    ]
    return pd.DataFrame(rows, columns=columns, dtype=object)


def format_sweeps_table(table: pd.DataFrame) -> str:
    """Fixed-width text of :func:`sweeps_table` (full sweep ids: they are what ``--sweep`` takes; the workspace id's
    first 8 digits)."""
    if table.empty:
        return "(no sweeps: run `aumesh sweep -m ...`)"
    lines = [
        f"{'sweep (--sweep)':32}  {'started (UTC)':16}  {'user':24} {'workspace':9} {'status':8} {'runs':>4} "
        f"{'failed':>6}  "
        f"{'best (run)':35} {'best configuration':38}  swept"
    ]
    for r in table.to_dict(orient="records"):
        best = (
            f"{r['metric']}={float(r['best_value']):.4f} ({str(r['best_run'])[:8]})"
            if r["best_value"] is not None
            else "-"
        )
        lines.append(
            f"{r['sweep']:32}  {r['started']:%Y-%m-%d %H:%M}  {str(r['user'] or '-')[:24]:24} "
            f"{str(r['workspace'] or '-')[:8]:9} {r['status']:8} {r['n_runs']:>4} {r['n_failed']:>6}  "
            f"{best:35} {r['best'] or '-':38}  {r['overrides']}"
        )
    return "\n".join(lines)
