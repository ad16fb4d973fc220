"""End-to-end: a real ``mlflow server`` on 127.0.0.1 with a SQLite backend, runs logged over HTTP."""

from __future__ import annotations

from pathlib import Path

import pytest

from aumesh.tracking import mlflow_store, queries
from aumesh.tracking import runs as tracking
from aumesh.tracking.experiment import SORT_METRICS, SORT_PARAMS, runs_page_url

pytestmark = pytest.mark.server


@pytest.mark.slow  # starting the real server is most of its ~8 s of CPU
def test_parent_and_children_over_http(mlflow_server, tmp_path, monkeypatch):
    from mlflow import MlflowClient

    monkeypatch.setenv("MLFLOW_TRACKING_URI", mlflow_server)
    monkeypatch.chdir(Path(__file__).resolve().parents[1])  # provenance tags from the project checkout
    cfg = {"enabled": True, "experiment": "server-test"}
    assert mlflow_store.resolve_tracking_uri(cfg) == mlflow_server

    parent = tracking.start_parent_run(cfg, "sweep", params={"sweep": {"k": [2, 4]}})
    children = []
    for k in (2, 4):
        with tracking.tracked_run(cfg, f"k={k}", {"model": {"n_components": k}}, parent_run_id=parent) as run:
            run.log_fold_metrics({"r2": [0.1 * k, 0.1 * k + 0.01, 0.1 * k + 0.02]})
            run.log_config({"model": {"n_components": k}})
            children.append(run.run_id)
    tracking.end_run(parent, cfg)

    client = MlflowClient(tracking_uri=mlflow_server)
    assert client.get_run(parent).info.status == "FINISHED"
    for rid, k in zip(children, (2, 4), strict=True):
        got = client.get_run(rid)
        assert got.info.status == "FINISHED"
        assert got.data.tags["mlflow.parentRunId"] == parent
        assert got.data.params["model.n_components"] == str(k)
        assert [m.step for m in sorted(client.get_metric_history(rid, "r2"), key=lambda m: m.step)] == [0, 1, 2]
        assert "config.yaml" in {a.path for a in client.list_artifacts(rid)}  # proxied upload via the server
    df = queries.list_child_runs(parent, cfg)
    assert sorted(df["run_id"]) == sorted(children)


@pytest.mark.slow
def test_ui_opens_the_experiment_on_its_runs(mlflow_server, browser, monkeypatch):
    """MLflow's own UI (Chromium, network limited to the server) on the runs table of a model-training experiment,
    with its description and the columns people sort by; the screenshot is kept for a person to look at."""
    from mlflow import MlflowClient

    from conftest import SCREENSHOTS as SHOTS
    from conftest import default_config

    monkeypatch.setenv("MLFLOW_TRACKING_URI", mlflow_server)
    monkeypatch.chdir(Path(__file__).resolve().parents[1])  # provenance (data.dvc's hash) from the project checkout
    tracking_cfg = {"enabled": True, "experiment": "ui-test"}
    names = {}
    for k, r2 in ((10, 0.412345), (83, 0.587654)):
        cfg = default_config(**{"model.n_components": k})
        with tracking.tracked_run(tracking_cfg, f"absolute au_pose_interactions k={k}", cfg.to_dict()) as run:
            run.log_metrics(
                {"r2_mean": r2, "r2_displacement_mean": r2 - 0.1, "au_reliability_median": 0.9, "mae_mean": 1.0}
            )
        names[run.run_id] = f"absolute au_pose_interactions k={k}"
    experiment = MlflowClient(tracking_uri=mlflow_server).get_experiment_by_name("ui-test")
    assert experiment.tags["mlflow.experimentKind"] == "custom_model_development"
    url = runs_page_url(mlflow_server, experiment.experiment_id)
    context = browser.new_context(viewport={"width": 1920, "height": 800})
    try:
        context.route(
            "**/*",
            lambda route: route.continue_() if route.request.url.startswith(mlflow_server) else route.abort(),
        )  # nothing but the server: the UI must not need the network
        page = context.new_page()
        page.goto(url)
        best = page.get_by_text(names[run.run_id], exact=True)  # the k=83 run, the best r2_mean
        best.first.wait_for(timeout=90_000)
        # the grid's columns and the best run's r2_mean shown: waited for, not a settling time (90 s: a cap)
        page.wait_for_function(
            """([columns, value]) => {
                const shown = [...document.querySelectorAll("[role=columnheader]")].map((h) => h.innerText);
                return columns.every((c) => shown.includes(c)) && document.body.innerText.includes(value);
            }""",
            arg=[[*SORT_METRICS, *SORT_PARAMS], "0.587654"],
            timeout=90_000,
        )
        SHOTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=SHOTS / "mlflow_experiment_runs.png")
        text = page.inner_text("body")
        headers = page.locator("[role=columnheader]").all_inner_texts()
    finally:
        context.close()
    assert "Model training" in text and "/runs" in page.url
    assert "No data available" not in text and "Detect Issues" not in text  # not the GenAI overview of traces
    assert all(name in text for name in names.values())
    assert text.index(names[run.run_id]) < text.index("k=10")  # best r2_mean first
    assert "aumesh" in text and "AU (+ head pose)" in text  # the description above the table
    assert "Sort: r2_mean" in text  # sorted by the metric people sort by (best first, checked above)
    for column in (*SORT_METRICS, *SORT_PARAMS):  # the columns people sort by, shown
        assert column in headers, (column, headers)
    assert "0.587654" in text  # the best run's r2_mean in its column
