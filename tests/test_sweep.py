"""aumesh sweep: a real Hydra multirun on a tiny synthetic workspace, logged to a temporary MLflow store.

One module-scoped workspace (conf/ + dvc.yaml copied from the repo, 600 synthetic frames prepared
into build/prepared, params.yaml composed) and one module-scoped store; the sweep runs once.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
from collections.abc import Iterator
from functools import partial
from pathlib import Path

import mlflow.models
import numpy as np
import pytest

from aumesh import config
from aumesh.core.schema import INPUT_COLUMNS
from aumesh.data import tables
from aumesh.pipeline import integrity, prepare
from aumesh.synthetic import tables as synth
from aumesh.tracking import mlflow_store, queries, registry
from aumesh.tracking import runs as tracking
from conftest import built_once, default_config, new_store

REPO = Path(__file__).resolve().parents[1]
SPEC = synth.SynthSpec(n_frames=600, n_videos=60, seed=11)
# 2 x 3 = 6 configurations over every feature set; without clipping, 25 components exceed the 20 and 23
# features of `au` and `au_pose` (2 FAILED children), while every feature set itself is valid
GRID = ["-m", "model.n_components=2,25", "features=au,au_pose,au_pose_interactions", "model.clip_n_components=false"]


def make_workspace(root: Path, spec: synth.SynthSpec = SPEC) -> Path:
    """A throw-away aumesh workspace: conf/ (without a promoted experiment), dvc.yaml, data, prepared data, params.yaml.

    A copy of one built once per test run and ``spec`` (:func:`conftest.built_once`; the prepare stage takes ~1.5 s,
    the copy ~0.1 s): the same files :func:`build_workspace` writes into ``root``, the prepare record naming
    ``root``'s tables."""
    template = built_once(
        f"workspace-{hashlib.sha1(repr(spec).encode()).hexdigest()[:12]}", partial(build_workspace, spec=spec)
    )
    shutil.copytree(template, root, dirs_exist_ok=True)
    summary = root / "build" / "prepared" / "summary.json"
    summary.write_text(summary.read_text().replace(str(template), str(root)))
    return root


def build_workspace(root: Path, spec: synth.SynthSpec = SPEC) -> Path:
    """What :func:`make_workspace` copies, written into ``root``."""
    root.mkdir(parents=True, exist_ok=True)
    shutil.copytree(REPO / "conf", root / "conf", ignore=shutil.ignore_patterns("promoted.yaml"))
    shutil.copy(REPO / "dvc.yaml", root / "dvc.yaml")
    synth.write_tables(root / "data", spec)
    data = config.compose(config_dir=root / "conf")
    config.write_params(data, root / "params.yaml")
    cfg = config.from_dict(data)
    found = tables.discover(root / cfg.paths.data_dir, cfg.data.tables, cfg.data.mesh_npy)
    prepare.run(found, cfg, root / cfg.paths.prepared_dir)
    (root / "promotion.json").write_text('{"promoted": null}\n')
    # what `dvc add data` records (a placeholder hash: these tests do not run DVC)
    (root / "data.dvc").write_text(
        "outs:\n- md5: 0123456789abcdef0123456789abcdef.dir\n  size: 1\n  nfiles: 1\n  hash: md5\n  path: data\n"
    )
    return root


@contextlib.contextmanager
def workspace_with_store(tmp_path_factory, name: str) -> Iterator[Path]:
    """:func:`make_workspace` with its own SQLite store, as the current directory (for module-scoped fixtures)."""
    ws = make_workspace(tmp_path_factory.mktemp(f"{name}-ws") / "ws")
    store = new_store(tmp_path_factory.mktemp(f"aumesh-test-{name}-store") / "mlflow.db")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(ws)
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{store}")  # "aumesh-test" in the path: conftest keeps it
        for var in ("DVC_ROOT", "DVC_EXP_NAME", "AUMESH_SWEEP_PARENT_RUN_ID"):
            mp.delenv(var, raising=False)
        yield ws


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    with workspace_with_store(tmp_path_factory, "sweep") as ws:
        yield ws


@pytest.fixture(scope="module")
def swept(workspace):
    """Run the grid through `aumesh sweep` (the CLI entry point, in-process Hydra multirun)."""
    from aumesh import cli

    assert cli.main(["sweep", *GRID]) == 1  # 2 configurations fail: logged and ranked, then exit 1
    parent = queries.latest_parent_run({})
    assert parent is not None
    return parent, queries.list_child_runs(parent, {})


def test_sweep_one_parent_and_a_child_per_configuration(swept, workspace):
    parent, children = swept
    client = mlflow_store.get_client({})
    exp = client.get_experiment_by_name("aumesh")
    parents = client.search_runs([exp.experiment_id], filter_string=f"tags.`{tracking.ROLE_TAG}` = 'sweep-parent'")
    assert [r.info.run_id for r in parents] == [parent]
    p = client.get_run(parent)
    assert p.info.status == "FINISHED"
    assert p.data.tags["aumesh.sweep.n_children"] == "6"
    assert p.data.tags["aumesh.sweep.n_failed"] == "2"
    assert Path(p.data.tags["aumesh.sweep.dir"]).parent == (workspace / "build" / "sweeps").resolve()
    assert not (workspace / "multirun").exists()
    assert len(children) == 6
    from aumesh.experiments.sweep import count_jobs

    assert count_jobs(GRID[1:]) == len(children)  # the progress bar's total is what Hydra launched
    assert sorted(children["status"]) == ["FAILED"] * 2 + ["FINISHED"] * 4


def test_failed_configuration_is_recorded_and_sweep_continues(swept):
    _, children = swept
    failed = children[children["status"] == "FAILED"]
    assert set(failed["params.features.name"]) == {"au", "au_pose"}
    assert set(failed["params.model.n_components"]) == {"25"}
    assert all("model.n_components=25 exceeds the" in e for e in failed["error"])
    # no feature set is an invalid corner: every one of them trains
    small = children[children["params.model.n_components"] == "2"]
    assert sorted(small["params.features.name"]) == ["au", "au_pose", "au_pose_interactions"]
    assert set(small["status"]) == {"FINISHED"}
    # the jobs launched after the first failure still ran and finished
    order = children.sort_values("start_time")["status"].tolist()
    first_fail = order.index("FAILED")
    assert "FINISHED" in order[first_fail + 1 :]


def test_children_log_per_fold_metrics_curve_figure_and_model(swept):
    parent, children = swept
    client = mlflow_store.get_client({})
    finished = children[children["status"] == "FINISHED"]
    for row in finished.to_dict(orient="records"):
        rid = row["run_id"]
        run = client.get_run(rid)
        assert run.data.tags["mlflow.parentRunId"] == parent
        assert run.data.tags["aumesh.role"] == "sweep-child"
        assert "aumesh.git.commit" in run.data.tags
        assert run.data.params["preprocess.target"] == "absolute"  # flattened params
        for name in ("r2", "mae", "vertex_error", "r2_displacement"):
            hist = sorted(client.get_metric_history(rid, name), key=lambda m: m.step)
            assert [m.step for m in hist] == [0, 1, 2], name
            assert np.isclose(np.mean([m.value for m in hist]), run.data.metrics[f"{name}_mean"]), name
        reliability = {k: v for k, v in run.data.metrics.items() if k.startswith("au_reliability_")}
        assert len(reliability) == 22 and 0 <= run.data.metrics["n_aus_facs_pass"] <= 20  # per AU + median + min
        assert reliability["au_reliability_min"] == min(v for k, v in reliability.items() if k[-4:-2] == "AU")
        k = int(run.data.metrics["n_components"])
        curve = client.get_metric_history(rid, "r2_by_n_components")
        assert sorted(m.step for m in curve) == list(range(1, k + 1))
        assert np.isclose(max(curve, key=lambda m: m.step).value, run.data.metrics["r2_mean"], atol=1e-9)
        arts = {a.path for a in client.list_artifacts(rid, "plots")} | {
            a.path for a in client.list_artifacts(rid, "model")
        }
        assert {"plots/r2_vs_n_components.png", "model/MLmodel", "model/input_example.json"} <= arts
        # the model is an MLflow pyfunc model with the card's signature
        info = mlflow.models.get_model_info(f"runs:/{rid}/model")
        assert info.flavors.keys() >= {"python_function"}
        assert info.signature.inputs.input_names() == list(INPUT_COLUMNS)
        assert info.signature.outputs.inputs[0].shape == (-1, 1434)
        assert run.data.metrics["seconds_log_model"] > 0


def test_statistics_are_reused_across_n_components(swept):
    _, children = swept
    client = mlflow_store.get_client({})
    finished = children[children["status"] == "FINISHED"]
    reuse = [client.get_run(r).data.tags["aumesh.cache.statistics"] for r in finished["run_id"]]
    # 3 feature sets x 1 target: computed once each; au_pose_interactions reuses them for its second n_components
    assert sorted(reuse) == ["computed"] * 3 + ["reused"]


def test_child_equals_a_fresh_fit(swept, workspace):
    """A sweep child's metrics and NPZ coefficients equal evaluate.evaluate of the same configuration."""
    from aumesh.experiments import sweep_child
    from aumesh.model.release import release_arrays
    from aumesh.pipeline import evaluate as ev
    from aumesh.pipeline.evaluate.prepared_data import load_prepared

    _, children = swept
    row = children[
        (children["status"] == "FINISHED")
        & (children["params.features.name"] == "au_pose_interactions")
        & (children["params.model.n_components"] == "25")
    ].iloc[0]
    cfg = config.from_dict(
        config.compose(
            ["model.n_components=25", "features=au_pose_interactions", "model.clip_n_components=false"],
            config_dir=workspace / "conf",
        )
    )
    prepared = load_prepared(workspace / cfg.paths.prepared_dir)
    with sweep_child.blas_threads():
        cv, final = ev.cross_validate_and_fit(prepared, cfg)
    assert row["metrics.r2_mean"] == pytest.approx(cv.metrics()["r2_mean"], abs=1e-12)
    local = registry.download_run_artifacts(
        row["run_id"], "model/artifacts/au_to_mesh_pls.npz", workspace / "build" / "dl"
    )
    npz = np.load(local)
    # the fresh fit's release (in the card's frame, as every released NPZ)
    fresh = release_arrays(
        final.coef,
        final.mesh_intercept,
        final.feature_columns,
        final.n_components,
        prepared.reference,
        card_text="",
        metadata={},
    )
    np.testing.assert_array_equal(npz["coef_full"], fresh["coef_full"])
    np.testing.assert_array_equal(npz["intercept"], fresh["intercept"])
    assert int(npz["n_components"]) == 25


def test_runs_command_best_first(swept, capsys):
    from aumesh import cli

    parent, children = swept
    assert cli.main(["runs", "--parent", parent]) == 0
    out = capsys.readouterr().out
    finished = children[children["status"] == "FINISHED"].copy()
    finished["k"] = finished["metrics.n_components"]
    best = finished.sort_values(["metrics.r2_mean", "k"], ascending=[False, True]).iloc[0]["run_id"]
    lines = [ln for ln in out.splitlines() if ln.strip().startswith("1 ")]
    assert lines and lines[0].split()[1] == best[:8]
    assert sum(1 for ln in out.splitlines() if ln.split()[1:3] and "FAILED" in ln.split()[:3]) == 2
    assert cli.main(["runs", "--latest"]) == 0  # the same sweep
    assert best[:8] in capsys.readouterr().out


@pytest.mark.slow
def test_prepare_relevant_override_prepares_into_a_cache_dir(workspace):
    """A sweep value of a prepare key (pose filter) may not reuse build/prepared: prepared once, stamped, reused."""
    from aumesh.experiments import sweep_cache, sweep_child

    cache = sweep_cache.SweepCache()
    raw = config.compose(
        ["preprocess.pose_filter.max_abs_yaw_deg=30", "model.n_components=3"], config_dir=workspace / "conf"
    )
    r1 = sweep_child.run_configuration(raw, ["preprocess.pose_filter.max_abs_yaw_deg=30"], cache=cache, root=workspace)
    assert r1["status"] == "FINISHED", r1
    run = mlflow_store.get_client({}).get_run(r1["run_id"])
    prepared_dir = Path(run.data.tags["aumesh.prepared_dir"])
    assert prepared_dir.parent == (workspace / sweep_cache.PREPARED_CACHE_DIR).resolve()
    assert (prepared_dir / sweep_cache.PREPARE_STAMP).exists()
    summary = integrity.load_summary(prepared_dir)
    assert summary["n_frames"] < integrity.load_summary(workspace / "build" / "prepared")["n_frames"]
    raw2 = config.compose(
        ["preprocess.pose_filter.max_abs_yaw_deg=30", "model.n_components=4"], config_dir=workspace / "conf"
    )
    r2 = sweep_child.run_configuration(raw2, ["model.n_components=4"], cache=cache, root=workspace)
    assert mlflow_store.get_client({}).get_run(r2["run_id"]).data.tags["aumesh.cache.statistics"] == "reused"


def test_runtime_failure_is_recorded(workspace, monkeypatch):
    from aumesh.experiments import sweep_cache, sweep_child

    def boom(*a, **k):
        raise RuntimeError("synthetic failure inside the fit")

    monkeypatch.setattr(sweep_cache, "evaluate_configuration", boom)
    raw = config.compose(["model.n_components=3"], config_dir=workspace / "conf")
    result = sweep_child.run_configuration(raw, ["model.n_components=3"], root=workspace)
    assert result["status"] == "FAILED" and "synthetic failure" in result["error"]
    run = mlflow_store.get_client({}).get_run(result["run_id"])
    assert run.info.status == "FAILED"
    assert "synthetic failure" in run.data.tags[tracking.ERROR_TAG]


@pytest.mark.slow
def test_joblib_launcher_children_find_the_parent(workspace):
    """Parallel jobs in loky worker processes attach to the parent the callback created."""
    from aumesh import cli

    assert cli.main(["sweep", "-m", "model.n_components=2,3", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2"]) == 0
    parent = queries.latest_parent_run({})
    children = queries.list_child_runs(parent, {})
    assert len(children) == 2 and set(children["status"]) == {"FINISHED"}
    assert mlflow_store.get_client({}).get_run(parent).data.tags["aumesh.sweep.launcher"].endswith("JoblibLauncher")


@pytest.mark.slow
@pytest.mark.server
def test_small_sweep_and_promotion_against_a_real_server(workspace, mlflow_server, monkeypatch):
    """Over loopback HTTP: parent + children with artifacts, then promote registers the NPZ (the server checks
    the source lies in the run's artifacts) and sets the champion alias."""
    from aumesh.experiments import promote, sweep_cache, sweep_child

    monkeypatch.setenv("MLFLOW_TRACKING_URI", mlflow_server)
    cfg = {"experiment": "server-sweep"}
    parent = tracking.start_parent_run(cfg, "server sweep")
    cache = sweep_cache.SweepCache()
    results = []
    for ov in (
        ["model.n_components=2"],
        ["model.n_components=4"],
        ["features=au", "model.n_components=30", "model.clip_n_components=false"],
    ):
        raw = config.compose(ov + ["tracking.experiment=server-sweep"], config_dir=workspace / "conf")
        results.append(sweep_child.run_configuration(raw, ov, parent, cache=cache, root=workspace))
    tracking.end_run(parent, cfg)
    assert [r["status"] for r in results] == ["FINISHED", "FINISHED", "FAILED"]  # 30 components > 20 features
    children = queries.list_child_runs(parent, cfg)
    assert sorted(children["status"]) == ["FAILED", "FINISHED", "FINISHED"]
    record = promote.promote(parent, workspace, cfg, model_name="aumesh-server-test")
    champion = registry.model_version_by_alias("aumesh-server-test", "champion", cfg)
    assert champion["run_id"] == record["run_id"] and champion["source"].startswith("mlflow-artifacts:")


@pytest.mark.slow
def test_a_sweep_over_the_correction_fits_each_and_promotion_does_not_rank_them_on_r2(tmp_path_factory, capsys):
    """``aumesh sweep -m model/eiv=none,corrected``: one statistics pass, two models (the cached result of the
    uncorrected fit is not reused for the corrected one), and promotion picks the corrected run, saying why."""
    import numpy as np

    from aumesh import cli
    from aumesh.experiments import ranking

    with workspace_with_store(tmp_path_factory, "eiv-sweep") as ws:
        (ws / "validation").mkdir()
        np.save(ws / "validation" / "sigma_u.npy", 0.03**2 * np.eye(20))
        assert cli.main(["sweep", "-m", "model/eiv=none,corrected", "preprocess.target=within"]) == 0
        parent = queries.latest_parent_run({})
        children = queries.list_child_runs(parent, {})
        assert sorted(children["params.model.eiv.method"]) == ["corrected", "none"]
        assert set(children["status"]) == {"FINISHED"}
        client = mlflow_store.get_client({})
        tags = {r: client.get_run(r).data.tags for r in children["run_id"]}
        assert sorted(t["aumesh.cache.statistics"] for t in tags.values()) == ["computed", "reused"]
        assert not any("aumesh.cache.result" in t for t in tags.values())
        r2 = dict(zip(children["params.model.eiv.method"], children["metrics.r2_mean"], strict=True))
        assert r2["corrected"] != r2["none"]
        choice = ranking.choose(ranking.candidates_from_frame(children))
        corrected = children[children["params.model.eiv.method"] == "corrected"]["run_id"].iloc[0]
        assert choice.run_id == corrected and "R² does not compare corrected and uncorrected runs" in choice.compared
        assert cli.main(["promote"]) == 0
        record = json.loads((ws / "promotion.json").read_text())["promoted"]
        assert record["run_id"] == corrected and "model.eiv" in record["compared"]


def test_a_sweep_that_re_prepares_from_an_object_store_is_one_line(tmp_path):
    """A sweep over prepare's values re-prepares from paths.data_dir's parquet tables, a local folder only: with an
    s3:// data_dir it stops in one line naming the URL and the ways out, before it reads anything."""
    from aumesh.core.errors import ConfigError
    from aumesh.experiments.sweep_cache import PreparedSource, ensure_prepared

    cfg = default_config(**{"paths.data_dir": "s3://lab-tables/celebv"})
    source = PreparedSource(tmp_path / "prepared", False, {"preprocess.target": "within"}, "k")
    with pytest.raises(ConfigError) as err:
        ensure_prepared(source, cfg)
    line = str(err.value)
    assert "\n" not in line and line.startswith("paths.data_dir=s3://lab-tables/celebv: this sweep re-prepares")
    assert "aws s3 sync" in line
    assert not (tmp_path / "prepared").exists() or not any((tmp_path / "prepared").iterdir())
