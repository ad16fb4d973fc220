"""Shareable records: promotion.json, model_card.json and the NPZ's metadata hold repo-relative locations and
run ids, never the workspace's absolute path (they are committed or sent to other machines)."""

from __future__ import annotations

import json

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
    from aumesh.experiments import promote, sweep
    from aumesh.stages import evaluate, release
    from aumesh.tracking import runs as tracking
    from test_sweep import make_workspace

    ws = make_workspace(tmp_path / "ws")
    monkeypatch.chdir(ws)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)  # the default: the workspace's own store
    for var in ("DVC_ROOT", "DVC_EXP_NAME", "AUMESH_SWEEP_PARENT_RUN_ID"):
        monkeypatch.delenv(var, raising=False)
    parent = tracking.start_parent_run({}, "small sweep")
    cache = sweep.SweepCache()
    for ov in (["model.n_components=2"], ["model.n_components=5"]):
        assert (
            sweep.run_configuration(config.compose(ov, config_dir=ws / "conf"), ov, parent, cache=cache, root=ws)[
                "status"
            ]
            == "FINISHED"
        )
    tracking.end_run(parent)
    record = promote.promote(parent, ws, {})
    cfg = config.load_params(ws / "params.yaml")
    with sweep.blas_threads():
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
