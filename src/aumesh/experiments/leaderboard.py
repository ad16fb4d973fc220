"""A sweep's runs as a table, best first by the promotion criterion (``aumesh runs``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd


def runs_table(children: pd.DataFrame, metric: str | None = None) -> pd.DataFrame:
    """A sweep's children as a table, best first by the promotion criterion (see :mod:`aumesh.experiments.promote`).

    Parameters
    ----------
    children : DataFrame
        :func:`aumesh.experiments.tracking.list_child_runs` output.
    metric : str, optional
        Ranking metric; default: :func:`aumesh.experiments.promote.default_metric` of the finished runs' targets.

    Returns
    -------
    DataFrame
        ``rank``, ``run_id``, ``status``, config keys, ``r2_mean``, ``r2_std``,
        ``r2_displacement_mean``, ``mae_mean``, ``n_components`` (effective), ``error``;
        FINISHED runs ranked first, then the others. ``attrs["metric"]`` names the ranking metric.
    """
    import pandas as pd

    from aumesh.experiments import promote

    candidates = promote.candidates_from_frame(children)
    finished = [c for c in candidates if c.status == "FINISHED"]
    metric = metric or promote.default_metric({c.target for c in finished})
    ranked = promote.rank([c for c in finished if metric in c.metrics], metric) if finished else []
    order = [c.run_id for c in ranked] + [c.run_id for c in candidates if c.run_id not in {r.run_id for r in ranked}]
    by_id = {c.run_id: c for c in candidates}
    rows = []
    for i, rid in enumerate(order):
        c = by_id[rid]
        m = c.metrics
        rows.append({
            "rank": i + 1 if i < len(ranked) else None,
            "run_id": rid,
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
        })
    table = pd.DataFrame(rows, dtype=object)  # object: missing values stay None, integers stay integers
    table.attrs["metric"] = metric
    return table


def format_runs_table(table: pd.DataFrame) -> str:
    """Fixed-width text of :func:`runs_table` (short run ids, R² as mean ± std, k as requested->effective)."""
    if table.empty:
        return "(no child runs)"

    def missing(v) -> bool:
        return v is None or (isinstance(v, float) and v != v)

    def num(v, fmt: str = "{:.4f}") -> str:
        return "" if missing(v) else fmt.format(float(v))

    lines = [f"ranked by {table.attrs.get('metric', '?')} ({'desc' if not str(table.attrs.get('metric', '')).startswith('mae') else 'asc'}),"
             " ties -> fewer components; FAILED runs last",
             f"{'#':>3} {'run':8} {'status':8} {'target':8} {'neutral':7} {'features':20} "
             f"{'k':>6} {'r2_mean ± std':>17} {'r2_disp':>8} {'mae':>8}  error"]
    for r in table.to_dict(orient="records"):
        k = "" if missing(r["n_components_requested"]) else str(r["n_components_requested"])
        if not missing(r["n_components"]) and str(r["n_components"]) != k:
            k += f"->{r['n_components']}"
        r2 = "" if missing(r["r2_mean"]) else f"{num(r['r2_mean'])} ± {num(r['r2_std'])}"
        rank = "" if missing(r["rank"]) else str(r["rank"])
        lines.append(f"{rank:>3} {str(r['run_id'])[:8]:8} {r['status']:8} {str(r['target']):8} {str(r['neutral']):7} "
                     f"{str(r['features']):20} {k:>6} {r2:>17} {num(r['r2_displacement_mean']):>8} "
                     f"{num(r['mae_mean']):>8}  {'' if missing(r['error']) else r['error']}")
    return "\n".join(lines)
