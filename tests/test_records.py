"""Records: the shareable ones (promotion.json, model_card.json and the NPZ's metadata hold repo-relative locations
and run ids, never the workspace's absolute path: they are committed or sent to other machines), and the one record of
an evaluation run in MLflow (``aumesh.pipeline.run_record``), the same for the evaluate stage and a sweep child."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from aumesh import config
from aumesh.core import provenance


@pytest.mark.parametrize(
    "value, expected",
    [
        ("sqlite:///{ws}/mlflow.db", "sqlite:///mlflow.db"),
        ("sqlite:///{ws}/mlflow.db?timeout=30", "sqlite:///mlflow.db?timeout=30"),
        ("file://{ws}/mlartifacts/1/abc/artifacts/model", "mlartifacts/1/abc/artifacts/model"),
        ("{ws}/data.dvc", "data.dvc"),
        ("{ws}/.dvc/tmp/exps/tmpq1/data.dvc", ".dvc/tmp/exps/tmpq1/data.dvc"),
        ("http://user:secret@tracking.example:5000", "http://tracking.example:5000"),
        ("mlflow-artifacts:/1/abc/artifacts/model", "mlflow-artifacts:/1/abc/artifacts/model"),
        ("runs:/abc/model", "runs:/abc/model"),
        ("sqlite:////elsewhere/mlflow.db", "sqlite:////elsewhere/mlflow.db"),
        (None, None),
    ],
)
def test_shareable_location_forms(tmp_path, value, expected):
    ws = tmp_path / "ws"
    ws.mkdir()
    got = provenance.shareable_location(value.format(ws=ws) if value else value, [ws])
    assert got == expected


def test_store_of_the_workspace_is_relative_from_a_dvc_temporary_copy(tmp_path, monkeypatch):
    ws = tmp_path / "ws"
    copy = ws / ".dvc" / "tmp" / "exps" / "tmpq1"
    copy.mkdir(parents=True)
    (copy / "dvc.yaml").write_text("stages: {}\n")
    monkeypatch.chdir(copy)  # a queued experiment's stage runs here; the store is the workspace's
    assert provenance.shareable_location(f"sqlite:///{ws}/mlflow.db") == "sqlite:///mlflow.db"
    assert provenance.shareable_location(str(copy / "data.dvc")) == "data.dvc"


@pytest.mark.slow  # a sweep, a registered promotion, the evaluate and release stages (~7 s of CPU)
def test_promotion_card_and_npz_hold_no_absolute_workspace_path(tmp_path, monkeypatch):
    """A workspace with the default store (ws/mlflow.db, ws/mlartifacts): sweep children -> promote (registered)
    -> evaluate and release stages; every shared record is free of the workspace's absolute path."""
    from aumesh.experiments import promote, sweep_cache, sweep_child
    from aumesh.stages import evaluate, release
    from aumesh.tracking import runs as tracking
    from test_sweep import make_workspace

    ws = make_workspace(tmp_path / "ws")
    monkeypatch.chdir(ws)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)  # the default: the workspace's own store
    for var in ("DVC_ROOT", "DVC_EXP_NAME", "AUMESH_SWEEP_PARENT_RUN_ID"):
        monkeypatch.delenv(var, raising=False)
    parent = tracking.start_parent_run({}, "small sweep")
    cache = sweep_cache.SweepCache()
    for ov in (["model.n_components=2"], ["model.n_components=5"]):
        assert (
            sweep_child.run_configuration(config.compose(ov, config_dir=ws / "conf"), ov, parent, cache=cache, root=ws)[
                "status"
            ]
            == "FINISHED"
        )
    tracking.end_run(parent)
    record = promote.promote(parent, ws, {})
    cfg = config.load_params(ws / "params.yaml")
    with sweep_child.blas_threads():
        evaluate.main(cfg)
    release = release.main(cfg)

    assert (ws / "mlflow.db").is_file() and (ws / "mlartifacts").is_dir()  # the store really is in the workspace
    card = json.loads((release / "model_card.json").read_text())
    texts = {
        "promotion.json": (ws / "promotion.json").read_text(),
        "model_card.json": (release / "model_card.json").read_text(),
        "MODEL_CARD.md": (release / "MODEL_CARD.md").read_text(),
        "training_metadata": str(np.load(release / "au_to_mesh_pls.npz", allow_pickle=False)["training_metadata"]),
        "model_card (NPZ)": str(np.load(release / "au_to_mesh_pls.npz", allow_pickle=False)["model_card"]),
    }
    for name, text in texts.items():
        for absolute in {str(ws), str(ws.resolve()), str(tmp_path)}:
            assert absolute not in text, f"{name} holds the workspace path {absolute}"
    # what they hold instead: run ids and repo-relative locations
    assert record["run_id"] in texts["promotion.json"] and parent in texts["promotion.json"]
    assert record["tracking_uri"] == "sqlite:///mlflow.db"
    assert record["model_source"].startswith("mlartifacts/") and record["model_source"].endswith("/model")
    assert (ws / record["model_source"] / "MLmodel").is_file()  # an MLflow pyfunc model (aumesh.tracking.pyfunc)
    assert (ws / record["model_source"] / "artifacts" / "au_to_mesh_pls.npz").is_file()
    assert card["mlflow"]["tracking_uri"] == "sqlite:///mlflow.db" and card["mlflow"]["run_id"]
    assert card["data"]["digest"]["dvc_file"] == "data.dvc"
    assert card["promotion"]["run_id"] == record["run_id"]
    # one release, both runs: the promoted sweep child and the evaluate run that built the arrays, by id
    runs = card["runs"]
    assert runs["promoted"]["run_id"] == record["run_id"] and runs["promoted"]["parent_run_id"] == parent
    assert runs["build"]["run_id"] == card["mlflow"]["run_id"] != record["run_id"]
    assert runs["build"]["tracking_uri"] == "sqlite:///mlflow.db" and runs["build"]["run_name"]
    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri=f"sqlite:///{ws / 'mlflow.db'}")
    assert client.get_run(runs["build"]["run_id"]).info.run_name == runs["build"]["run_name"]
    assert client.get_run(runs["promoted"]["run_id"]).data.tags["mlflow.parentRunId"] == parent
    for run in runs.values():
        assert f"`{run['run_id']}`" in texts["MODEL_CARD.md"]
    assert json.loads(texts["training_metadata"])["runs"] == runs  # the viewer's data (training_metadata) too


# -------------------------------------------------------------------- what an evaluation run records
#: what only one caller records (pipeline/run_record.py's docstring says why); everything else is the one record
STAGE_ONLY = {"metrics": {"evaluate_seconds"}, "tags": set(), "params": set()}
SWEEP_ONLY = {
    "metrics": {"seconds_load", "seconds_statistics", "seconds_cv_fit", "seconds_job"},
    "tags": {
        "aumesh.role",
        "mlflow.parentRunId",
        "aumesh.sweep.overrides",
        "aumesh.prepared_dir",
        "aumesh.prepared.key",
        "aumesh.cache.statistics",
        "aumesh.cache.pass",  # the union's one statistics pass computed or reused (issue 46: one pass a sweep)
    },
    "params": set(),
}


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:Deflated X.T Y vanished")  # AU07 constant: 22 informative directions of 23
def test_the_evaluate_stage_and_a_sweep_child_record_the_same_keys(tmp_path_factory):
    """The evaluate stage's run and a sweep child of the same configuration on the same data, read back from one real
    MLflow store, log the same metric, param and tag keys but for the documented caller-specific ones, and agree on
    the values they share. The data have a constant AU and the configuration a clipped ``model.n_components``, so
    every conditional part of the record is there to compare."""
    import pandas as pd
    from mlflow import MlflowClient

    from aumesh.data import tables
    from aumesh.experiments import sweep_cache, sweep_child
    from aumesh.pipeline import integrity, model_files, prepare
    from aumesh.stages import evaluate
    from aumesh.tracking import registry
    from aumesh.tracking import runs as tracking
    from test_sweep import workspace_with_store

    overrides = ["features=au_pose"]  # 23 features: the default 83 components are clipped to 23
    with workspace_with_store(tmp_path_factory, "record") as ws:
        for table in sorted((ws / "data").rglob("*.parquet")):  # AU07 never moves: a constant input
            frame = pd.read_parquet(table)
            frame.assign(AU07=0.0).to_parquet(table, index=False)
        raw = config.compose(overrides, config_dir=ws / "conf")
        config.write_params(raw, ws / "params.yaml")
        cfg = config.load_params(ws / "params.yaml")
        found = tables.discover(ws / cfg.paths.data_dir, cfg.data.tables, cfg.data.mesh_npy)
        prepare.run(found, cfg, ws / cfg.paths.prepared_dir)
        summary = integrity.load_summary(ws / cfg.paths.prepared_dir)

        with sweep_child.blas_threads():
            evaluate.main(cfg)
        stage_id = json.loads((ws / cfg.paths.model_dir / model_files.TRACKING_JSON).read_text())["run_id"]
        parent = tracking.start_parent_run({}, "record sweep")
        result = sweep_child.run_configuration(raw, overrides, parent, cache=sweep_cache.SweepCache(), root=ws)
        tracking.end_run(parent)
        assert result["status"] == "FINISHED", result

        client = MlflowClient(os.environ["MLFLOW_TRACKING_URI"])
        stage, child = client.get_run(stage_id), client.get_run(result["run_id"])
        keys = {
            run.info.run_id: {
                "metrics": set(run.data.metrics),
                "tags": set(run.data.tags),
                "params": set(run.data.params),
            }
            for run in (stage, child)
        }
        for kind in ("metrics", "tags", "params"):
            only_stage = keys[stage_id][kind] - keys[child.info.run_id][kind]
            only_child = keys[child.info.run_id][kind] - keys[stage_id][kind]
            assert only_stage == STAGE_ONLY[kind], (kind, only_stage)
            assert only_child == SWEEP_ONLY[kind], (kind, only_child)

        npz = {}
        for run in (stage, child):
            rid = run.info.run_id
            artifacts = {a.path for a in client.list_artifacts(rid)}
            artifacts |= {a.path for d in ("plots", "model") for a in client.list_artifacts(rid, d)}
            assert {"config.yaml", "plots/r2_vs_n_components.png", "model/MLmodel"} <= artifacts, rid
            (dataset,) = run.inputs.dataset_inputs
            assert dataset.dataset.name == "frame_tables" and dataset.dataset.digest == run.data.tags["aumesh.data.md5"]
            curve = sorted(client.get_metric_history(rid, "r2_by_n_components"), key=lambda m: m.step)
            assert [m.step for m in curve] == list(range(1, 24))  # k = 1..23, the features of au_pose
            for name in ("r2", "mae", "vertex_error", "r2_displacement"):
                assert [m.step for m in client.get_metric_history(rid, name)] == [0, 1, 2], name
            local = registry.download_run_artifacts(rid, "model/artifacts/au_to_mesh_pls.npz", ws / "dl" / rid)
            npz[rid] = json.loads(str(np.load(local)["training_metadata"]))

    # the conditional parts are there on both sides, with the same values
    for run in (stage, child):
        tags, metrics = run.data.tags, run.data.metrics
        assert tags["aumesh.n_components_clipped"] == "83 -> 23 (features=au_pose)"
        assert tags["aumesh.constant_inputs"] == "AU07=0" and tags["aumesh.constant_features"] == "1"
        assert tags["aumesh.pose_learned"] == "true" and tags["aumesh.n_components.effective"] == "23"
        assert metrics["n_components"] == 23 and metrics["n_features"] == 23
        assert metrics["n_frames"] == summary["n_frames"]  # prepare's count, another route to the same number
        for key, value in summary["counts"].items():
            if key.startswith(("dropped", "videos_dropped")):
                assert metrics[f"data.{key}"] == float(value), key
        assert metrics["seconds_log_model"] > 0
    assert stage.data.tags["aumesh.stage"] == "evaluate" and child.data.tags["aumesh.stage"] == "sweep"
    shared = keys[stage_id]["metrics"] - STAGE_ONLY["metrics"] - {"seconds_log_model"}
    for name in shared:  # the same CV by two routes: evaluate() and the sweep's cached statistics
        assert stage.data.metrics[name] == pytest.approx(child.data.metrics[name], rel=1e-9, abs=1e-12), name
    for rid, metadata in npz.items():  # the run's model says where it came from and what it was trained on
        assert set(metadata) == {"mlflow_run_id", "config", "cv", "data"} and metadata["mlflow_run_id"] == rid
        assert metadata["config"]["features"]["name"] == "au_pose" and metadata["cv"]["n_components"] == 23
