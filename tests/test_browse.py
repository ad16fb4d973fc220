"""MLflow as a user browses it, with a real local SQLite store: pipeline runs named by what tells them apart,
`aumesh runs --sweeps`, `aumesh promote` naming the sweep it takes and refusing to overrule a newer evaluate run,
and a sweep with failed configurations exiting non-zero (`--allow-failures` keeps 0)."""

from __future__ import annotations

import json

import pytest

from aumesh import cli, config
from aumesh.experiments import promote
from aumesh.pipeline.model_files import TRACKING_JSON
from aumesh.stages import evaluate
from aumesh.tracking import mlflow_store, queries
from test_sweep import workspace_with_store

FAILING = ["features=au", "model.n_components=2,25", "model.clip_n_components=false"]  # 25 > 20 features: FAILED


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    with workspace_with_store(tmp_path_factory, "browse") as ws:
        yield ws


@pytest.fixture(scope="module")
def sweeps(workspace):
    """Two sweeps, oldest first, each with a failing configuration: exit 1, then exit 0 with --allow-failures."""
    ids, codes = [], []
    for argv in (["-m", *FAILING], ["-m", *FAILING, "--allow-failures"]):
        codes.append(cli.main(["sweep", *argv]))
        ids.append(queries.latest_parent_run({}))
    return ids, codes


def _evaluate(workspace) -> dict:
    evaluate.main(config.load_params(workspace / "params.yaml"))
    run_id = json.loads((workspace / "build" / "model" / TRACKING_JSON).read_text())["run_id"]
    return queries.run_record(run_id, {})


@pytest.fixture(scope="module")
def newer_evaluate(sweeps, workspace):
    """The pipeline's evaluate stage after the sweeps, as `dvc exp run` runs it (DVC_EXP_NAME set)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DVC_EXP_NAME", "bumpy-tods")
        return _evaluate(workspace)


@pytest.mark.slow
def test_a_sweep_with_failed_configurations_exits_1_unless_allowed(sweeps, capsys):
    ids, codes = sweeps
    assert codes == [1, 0]
    assert len(set(ids)) == 2
    for parent in ids:  # the failures were logged and the rest still ran
        statuses = sorted(queries.list_child_runs(parent, {})["status"])
        assert statuses == ["FAILED", "FINISHED"]


@pytest.mark.slow
def test_runs_sweeps_lists_every_sweep_newest_first_with_size_and_best(sweeps, capsys):
    ids, _ = sweeps
    capsys.readouterr()
    assert cli.main(["runs", "--sweeps"]) == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln.split() and ln.split()[0] in ids]
    assert [ln.split()[0] for ln in lines] == ids[::-1]
    assert cli.main(["runs", "--sweeps", "--json"]) == 0
    rows = {r["sweep"]: r for r in json.loads(capsys.readouterr().out)}
    for parent in ids:  # against the store itself: size, failures, the best r2_mean (ties: fewer components)
        children = queries.list_child_runs(parent, {})
        done = children[children["status"] == "FINISHED"]
        best = done.sort_values(["metrics.r2_mean", "metrics.n_components"], ascending=[False, True]).iloc[0]
        r = rows[parent]
        assert (r["n_runs"], r["n_failed"]) == (len(children), len(children) - len(done))
        assert r["metric"] == "r2_mean" and r["best_value"] == pytest.approx(best["metrics.r2_mean"], rel=1e-12)
        assert r["best_run"] == best["run_id"]
        line = next(ln for ln in lines if ln.startswith(parent))
        assert f"r2_mean={best['metrics.r2_mean']:.4f} ({best['run_id'][:8]})" in line
    assert "model.n_components=2,25" in next(ln for ln in lines if ln.startswith(ids[0]))


@pytest.mark.slow
def test_evaluate_runs_are_named_by_what_tells_them_apart(newer_evaluate, workspace):
    cfg = config.load_params(workspace / "params.yaml")
    assert (cfg.preprocess.target, cfg.features.name, cfg.model.n_components) == (
        "absolute",
        "au_pose_interactions",
        83,
    )
    assert newer_evaluate["run_name"] == "bumpy-tods: absolute au_pose_interactions k=83"
    neutral = config.from_dict(
        config.compose(
            ["preprocess.target=neutral", "preprocess.neutral.method=mean", "features=au", "model.n_components=5"],
            config_dir=workspace / "conf",
        )
    )
    assert evaluate.evaluate_run_name(neutral) == "neutral(mean) au k=5"
    corrected = config.from_dict(
        config.compose(
            ["preprocess.target=within", "model/eiv=corrected", "model.eiv.sigma_u=v.npy"],
            config_dir=workspace / "conf",
        )
    )
    assert evaluate.evaluate_run_name(corrected) == "within au_pose_interactions k=83 eiv=corrected"


@pytest.mark.slow
def test_promote_names_its_sweep_and_refuses_to_overrule_a_newer_evaluate_run(
    sweeps, newer_evaluate, workspace, capsys
):
    ids, _ = sweeps
    latest = ids[-1]
    promoted = workspace / "conf" / "experiment" / "promoted.yaml"
    before = (workspace / "promotion.json").read_text()
    newer = newer_evaluate  # the pipeline's configuration (83 components, all features), after every sweep
    capsys.readouterr()
    with pytest.raises(promote.OverruleError) as exc:
        cli.main(["--debug", "promote", "--no-register"])
    message = str(exc.value)
    assert cli.main(["promote", "--no-register"]) == 2  # a user error: one line on stderr, exit 2
    err = capsys.readouterr().err
    assert err.startswith("aumesh promote: error: sweep ") and message in err
    assert f"sweep {latest} is older than evaluate run {newer['run_id']}" in message
    assert "model.n_components=83 there, 2 in the sweep's best run" in message
    assert "--sweep ID" in message and "--latest" in message
    assert cli.main(["promote", "--no-register"]) == 2
    assert f"your latest sweep: {latest}" in capsys.readouterr().out  # it said which sweep it took
    assert not promoted.exists() and (workspace / "promotion.json").read_text() == before  # nothing written

    assert cli.main(["promote", "--latest", "--no-register"]) == 0  # the flag to promote it anyway
    record = json.loads((workspace / "promotion.json").read_text())["promoted"]
    assert record["parent_run_id"] == latest and promoted.exists()
    # once the pipeline has evaluated the promoted configuration, promoting the same sweep overrules nothing
    again = _evaluate(workspace)
    assert again["params"]["model.n_components"] == "2" and again["params"]["features.name"] == "au"
    assert cli.main(["promote", "--no-register"]) == 0
    # a sweep named with --parent is never second-guessed
    assert cli.main(["promote", "--parent", ids[0], "--no-register"]) == 0
    assert json.loads((workspace / "promotion.json").read_text())["promoted"]["parent_run_id"] == ids[0]
    assert mlflow_store.get_client({}).get_run(ids[0]).info.status == "FINISHED"
