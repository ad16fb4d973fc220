"""aumesh promote: the criterion on constructed candidates, a constructed sweep in MLflow (choice, conf/,
params.yaml, promotion.json, registry alias), and a real promoted configuration refitted by the evaluate stage."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from aumesh import config
from aumesh.core import provenance
from aumesh.core.schema import INPUT_COLUMNS
from aumesh.experiments import promote, promoted_config, ranking
from aumesh.experiments.ranking import Candidate
from aumesh.tracking import registry
from aumesh.tracking import runs as tracking

REPO = Path(__file__).resolve().parents[1]


def cand(rid, value, k, target="absolute", status="FINISHED", disp=None, **extra) -> Candidate:
    metrics = {"r2_mean": value, "n_components": float(k)}
    if disp is not None:
        metrics["r2_displacement_mean"] = disp
    metrics.update(extra)
    return Candidate(
        run_id=rid,
        run_name=rid,
        status=status,
        params={"preprocess.target": target, "model.n_components": str(k), "cv.n_splits": "3"},
        metrics=metrics,
        start_time=0.0,
    )


# ---------------------------------------------------------------- the criterion (pure)
def test_highest_r2_wins_ties_go_to_fewer_components_failed_ignored():
    runs = [
        cand("a", 0.50, 10),
        cand("b", 0.70, 40),
        cand("c", 0.70 + 1e-12, 23),
        cand("d", 0.69, 5),
        cand("e", 0.99, 10, status="FAILED"),
    ]
    choice = ranking.choose(runs)
    assert choice.run_id == "c"  # tied with b within 1e-9, fewer components
    assert choice.metric == "r2_mean"
    assert [r for r, _ in choice.ranking] == ["c", "b", "d", "a"]
    assert choice.n_candidates == 4 and choice.n_excluded == 1
    assert "target=absolute" in choice.compared and "same space" in choice.compared
    # a real difference beats fewer components
    assert ranking.choose([cand("x", 0.70, 40), cand("y", 0.6999, 5)]).run_id == "x"


def test_corrected_and_uncorrected_runs_are_not_compared_on_r2():
    def eiv_cand(rid, value, method):
        c = cand(rid, value, 83, target="within")
        return Candidate(**{**c.__dict__, "params": {**c.params, "model.eiv.method": method}})

    # the uncorrected run has the higher R² by design; the corrected one is promoted, and the card says why
    runs = [
        eiv_cand("plain", 0.30, "none"),
        eiv_cand("fixed", 0.27, "corrected"),
        eiv_cand("fixed2", 0.26, "corrected"),
    ]
    choice = ranking.choose(runs)
    assert choice.run_id == "fixed" and [r for r, _ in choice.ranking] == ["fixed", "fixed2"]
    assert "R² does not compare corrected and uncorrected runs" in choice.compared
    assert "none: 1" in choice.compared and "corrected: 2" in choice.compared
    # runs from before the option (no model.eiv.method param) count as uncorrected; one method: no note
    assert (
        "model.eiv"
        not in ranking.choose([cand("old", 0.3, 83, target="within"), eiv_cand("new", 0.2, "none")]).compared
    )
    with pytest.raises(ValueError, match="different detector-noise corrections"):
        ranking.choose([eiv_cand("a", 0.3, "corrected"), eiv_cand("b", 0.2, "instruments")])


def test_mixed_targets_are_compared_on_displacement_r2():
    runs = [
        cand("abs", 0.90, 10, "absolute", disp=0.30),
        cand("neu", 0.40, 10, "neutral", disp=0.50),
        cand("abs2", 0.95, 40, "absolute", disp=0.31),
    ]
    choice = ranking.choose(runs)
    assert choice.run_id == "neu" and choice.metric == "r2_displacement_mean"
    assert "differ in preprocess.target" in choice.compared and "not compared" in choice.compared
    assert choice.targets == ("absolute", "neutral")
    with pytest.raises(ValueError, match="not comparable"):
        ranking.choose(runs, metric="r2_mean")
    restricted = ranking.choose(runs, target="absolute")
    assert restricted.run_id == "abs2" and restricted.metric == "r2_mean"
    assert "restricted to preprocess.target=absolute" in restricted.compared


def test_mixed_targets_can_be_ranked_by_au_field_reliability():
    runs = [
        cand("abs", 0.90, 83, "absolute", disp=0.30, au_reliability_median=0.70, au_reliability_min=0.2),
        cand("neu", 0.40, 83, "neutral", disp=0.32, au_reliability_median=0.75, au_reliability_min=0.4),
        cand("win", 0.50, 83, "within", disp=0.31, au_reliability_median=0.90, au_reliability_min=0.3),
    ]
    assert ranking.choose(runs).run_id == "neu"  # default: r2_displacement_mean across targets
    best = ranking.choose(runs, metric="au_reliability_median")
    assert best.run_id == "win" and "cosine between AU fields" in best.compared
    assert best.targets == ("absolute", "neutral", "within")
    assert ranking.choose(runs, metric="au_reliability_min").run_id == "neu"
    with pytest.raises(ValueError, match="au_reliability_median.*--target absolute\\|neutral\\|within"):
        ranking.choose(runs, metric="mae_mean")


def test_error_metrics_are_minimised_and_nothing_to_promote_is_an_error():
    runs = [cand("a", 0.5, 10, mae_mean=1.2), cand("b", 0.4, 10, mae_mean=1.1)]
    assert ranking.choose(runs, metric="mae_mean").run_id == "b"
    with pytest.raises(ValueError, match="no FINISHED run"):
        ranking.choose([cand("f", 0.9, 3, status="FAILED")])
    with pytest.raises(ValueError, match="logged by none"):
        ranking.choose(runs, metric="no_such_metric")


# ---------------------------------------------------------------- the experiment file and the defaults list


def test_promoted_experiment_overrides_groups_and_cli_overrides_win(conf_ws):
    promoted_config.check_defaults_entry(conf_ws / "conf")
    text = promoted_config.experiment_yaml(
        {"features.name": "au_pose", "model.n_components": 7, "preprocess.target": "neutral"}
    )
    assert text.startswith("# @package _global_")
    (conf_ws / "conf" / "experiment").mkdir(exist_ok=True)
    (conf_ws / "conf" / "experiment" / "promoted.yaml").write_text(text)
    c = config.from_dict(config.compose(config_dir=conf_ws / "conf"))
    assert (c.features.interactions, c.model.n_components, c.preprocess.target) == (False, 7, "neutral")
    assert c.features.pose is True  # untouched keys keep the group default
    c2 = config.from_dict(config.compose(["model.n_components=9"], config_dir=conf_ws / "conf"))
    assert c2.model.n_components == 9 and c2.features.interactions is False


def test_missing_defaults_entry_is_a_clear_error(conf_ws):
    path = conf_ws / "conf" / "config.yaml"
    path.write_text("\n".join(ln for ln in path.read_text().splitlines() if "experiment" not in ln) + "\n")
    with pytest.raises(ValueError, match="optional experiment: promoted"):
        promoted_config.check_defaults_entry(conf_ws / "conf")


# ---------------------------------------------------------------- a constructed sweep in MLflow
def _log_fake_sweep(tmp_path: Path, conf_dir: Path, rows: list[tuple[dict, dict, str]]) -> tuple[str, list[str]]:
    """Parent + children with the full flattened config (plus overrides), given metrics and a model/ artifact."""
    parent = tracking.start_parent_run({}, "constructed sweep")
    ids = []
    art = tmp_path / "au_to_mesh_pls.npz"
    np.savez(art, coef=np.zeros((23, 1434), np.float32))
    for overrides, metrics, status in rows:
        raw = config.compose([f"{k}={v}" for k, v in overrides.items()], config_dir=conf_dir)
        try:
            with tracking.tracked_run(
                {}, "child", raw, tags={"aumesh.role": "sweep-child"}, parent_run_id=parent
            ) as run:
                ids.append(run.run_id)
                run.log_metrics(metrics)
                run.log_artifact(art, "model")
                if status == "FAILED":
                    raise RuntimeError("constructed failure")
        except RuntimeError:
            pass
    tracking.end_run(parent)
    return parent, ids


@pytest.mark.slow
def test_promote_constructed_sweep_writes_conf_params_card_record_and_registry(conf_ws, tmp_path):
    conf = conf_ws / "conf"
    rows = [
        ({"model.n_components": 40}, {"r2_mean": 0.61, "r2_displacement_mean": 0.3, "n_components": 40.0}, "FINISHED"),
        (
            {"model.n_components": 10, "features.name": "au_pose"},
            {"r2_mean": 0.64, "r2_displacement_mean": 0.2, "n_components": 10.0},
            "FINISHED",
        ),
        ({"model.n_components": 23}, {"r2_mean": 0.64, "r2_displacement_mean": 0.2, "n_components": 23.0}, "FINISHED"),
        ({"model.n_components": 83}, {"r2_mean": 0.99, "n_components": 83.0}, "FAILED"),
    ]
    parent, ids = _log_fake_sweep(tmp_path, conf, rows)
    record = promote.promote(parent, conf_ws, {})
    assert record["run_id"] == ids[1]  # 0.64 tie -> 10 components; the FAILED 0.99 does not count
    assert record["parent_run_id"] == parent and record["metric"] == "r2_mean" and record["value"] == 0.64
    assert "features.name=au_pose" in record["config_overrides"]
    assert "model.n_components=10" in record["config_overrides"]

    exp = yaml.safe_load((conf / "experiment" / "promoted.yaml").read_text())
    assert exp["model"]["n_components"] == 10 and exp["features"]["name"] == "au_pose"
    composed = config.from_dict(config.compose(config_dir=conf))  # conf/ now builds the promoted run
    assert (composed.model.n_components, composed.features.interactions) == (10, False)
    params = config.load_params(conf_ws / "params.yaml")
    assert params == composed
    assert json.loads((conf_ws / "promotion.json").read_text())["promoted"] == record

    champion = registry.model_version_by_alias("aumesh-au-to-mesh", "champion", {})
    assert champion["run_id"] == ids[1] and champion["version"] == record["model_version"] == "1"
    assert champion["source"].endswith("/model")

    # a second sweep's promotion adds version 2 and moves the alias
    # (composed from the promoted conf/, as a sweep after a promotion is)
    parent2, ids2 = _log_fake_sweep(
        tmp_path,
        conf,
        [
            (
                {"model.n_components": 5, "features.name": "au_pose_interactions"},
                {"r2_mean": 0.7, "n_components": 5.0},
                "FINISHED",
            )
        ],
    )
    record2 = promote.promote(parent2, conf_ws, {})
    assert record2["model_version"] == "2"
    assert registry.model_version_by_alias("aumesh-au-to-mesh", "champion", {})["run_id"] == ids2[0]
    # the new experiment file replaces the old one
    c = config.from_dict(config.compose(config_dir=conf))
    assert (c.model.n_components, c.features.interactions) == (5, True)


def test_promotion_refuses_a_run_on_other_data(conf_ws, tmp_path):
    parent, _ = _log_fake_sweep(
        tmp_path,
        conf_ws / "conf",
        [({"paths.data_dir": "/elsewhere"}, {"r2_mean": 0.5, "n_components": 83.0}, "FINISHED")],
    )
    with pytest.raises(ValueError, match="paths.data_dir"):
        promote.promote(parent, conf_ws, {}, register=False)
    assert not (conf_ws / "conf" / "experiment" / "promoted.yaml").exists()


# ---------------------------------------------------------------- the real thing, small
@pytest.mark.slow
def test_promoted_configuration_refits_to_the_champion_coefficients(tmp_path, monkeypatch):
    """sweep children -> promote -> the evaluate stage on the recomposed params.yaml: same coefficients as the
    registered NPZ, and the card built by the release stage names the promoted run."""
    from aumesh.experiments import sweep_cache, sweep_child
    from aumesh.pipeline import model_files
    from aumesh.pipeline.release import build_card
    from aumesh.stages import evaluate
    from test_sweep import make_workspace

    ws = make_workspace(tmp_path / "ws")
    monkeypatch.chdir(ws)
    parent = tracking.start_parent_run({}, "small sweep")
    cache = sweep_cache.SweepCache()
    for ov in (["model.n_components=2"], ["model.n_components=6", "features=au_pose"]):
        r = sweep_child.run_configuration(config.compose(ov, config_dir=ws / "conf"), ov, parent, cache=cache, root=ws)
        assert r["status"] == "FINISHED", r
    tracking.end_run(parent)
    record = promote.promote(parent, ws, {})
    cfg = config.load_params(ws / "params.yaml")
    assert record["run_id"] == registry.model_version_by_alias("aumesh-au-to-mesh")["run_id"]
    with sweep_child.blas_threads():
        evaluate.main(cfg)
    model = np.load(ws / cfg.paths.model_dir / model_files.MODEL_NPZ)
    npz = np.load(
        registry.download_run_artifacts(record["run_id"], "model/artifacts/au_to_mesh_pls.npz", tmp_path / "dl")
    )
    coef_full = npz["coef_full"] if "coef_full" in npz else None
    if coef_full is not None:
        np.testing.assert_array_equal(coef_full, model["coef"].T.astype(np.float32))
    from aumesh.model.release import release_arrays

    ref = dict(np.load(ws / cfg.paths.prepared_dir / "reference.npz"))
    fresh = release_arrays(
        model["coef"],
        model["mesh_intercept"],
        model["feature_columns"].tolist(),
        int(model["n_components"]),
        ref,
        card_text="",
        metadata={},
    )
    np.testing.assert_array_equal(fresh["coef"], npz["coef"])
    np.testing.assert_array_equal(fresh["intercept"], npz["intercept"])
    promotion = json.loads((ws / cfg.paths.promotion_file).read_text())["promoted"]
    card = build_card(cfg, ws / cfg.paths.model_dir, ws / cfg.paths.prepared_dir, promotion)
    assert card["promotion"]["run_id"] == record["run_id"]
    assert card["promotion"]["parent_run_id"] == parent
    assert card["promotion"]["criterion"] and card["promotion"]["compared"]
    assert provenance.repo_root() == ws
    # the registered MLflow Model (MLflow's own loader, by alias) predicts the registered NPZ's meshes
    import mlflow.pyfunc
    import pandas as pd

    df = pd.DataFrame(np.random.default_rng(0).uniform(0.0, 1.0, (5, 23)), columns=list(INPUT_COLUMNS))
    df.loc[:1, ["Pitch", "Yaw", "Roll"]] = 0.0
    df.loc[2:, ["Pitch", "Yaw", "Roll"]] *= 0.3  # radians
    pred = mlflow.pyfunc.load_model("models:/aumesh-au-to-mesh@champion").predict(df)
    assert pred.shape == (5, 1434)
    names = npz["input_columns_full"].tolist() if "input_columns_full" in npz else list(INPUT_COLUMNS)
    coef = npz["coef_full"] if "input_columns_full" in npz else npz["coef"]
    # the design by hand: inputs by name, "Pitch*AU01" = product (the NPZ's own column names)
    x = np.stack([np.prod([df[part].to_numpy() for part in n.split("*")], axis=0) for n in names], axis=1)
    expected = x @ coef.astype(np.float64) + npz["intercept"].astype(np.float64)
    np.testing.assert_allclose(pred, expected, rtol=0, atol=1e-9 * np.abs(expected).max())
    # at pose 0 that is the card's snippet with the 23-row coef
    snippet = df.to_numpy()[:2] @ npz["coef"].astype(np.float64) + npz["intercept"].astype(np.float64)
    np.testing.assert_allclose(pred[:2], snippet, rtol=0, atol=1e-9 * np.abs(snippet).max())
