"""Issue 46: each input family tracked, ranked and promoted on its own.

Against a real MLflow store (the tests' SQLite one): every model run carries tag ``aumesh.family`` (sweep children
included; runs from before the tag get their features.name's family), ``aumesh runs`` ranks within a family,
``aumesh promote --family`` picks the best run of that family only into ``families.<family>`` of
``conf/experiment/promoted.yaml`` and ``promotion.json`` (registered as ``aumesh-<family>``) and leaves the AU
promotion and the other families' as they were; a run of another family is refused in one line; ``make promote
FAMILY=...`` runs it through the repository's Makefile.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from aumesh import config
from aumesh.core.errors import UserError
from aumesh.experiments import leaderboard, promote, promotion_journal
from aumesh.tracking import queries, registry
from aumesh.tracking import runs as tracking
from test_promote import _log_fake_sweep

REPO = Path(__file__).resolve().parents[1]

# (overrides, metrics): the best run overall is an emotions run, the best blendshapes run is not the best overall,
# and the AU runs are the worst: a ranking across families would pick the wrong run for every family
ROWS = [
    ({"features": "au", "model.n_components": 10}, {"r2_mean": 0.55, "n_components": 10.0}),
    ({"features": "au_pose", "model.n_components": 10}, {"r2_mean": 0.58, "n_components": 10.0}),
    ({"features": "blendshapes", "model.n_components": 10}, {"r2_mean": 0.62, "n_components": 10.0}),
    ({"features": "blendshapes_pose", "model.n_components": 12}, {"r2_mean": 0.70, "n_components": 12.0}),
    ({"features": "emotions_pose", "model.n_components": 40}, {"r2_mean": 0.80, "n_components": 10.0}),
    ({"features": "emotions", "model.n_components": 5}, {"r2_mean": 0.40, "n_components": 5.0}),
]


def _sweep(tmp_path: Path, conf: Path, rows=ROWS) -> tuple[str, dict[str, str]]:
    """A constructed sweep of ``rows`` (all FINISHED): the parent id and {features option: run id}."""
    parent, ids = _log_fake_sweep(tmp_path, conf, [(ov, m, "FINISHED") for ov, m in rows])
    return parent, {ov["features"]: rid for (ov, _), rid in zip(rows, ids, strict=True)}


def _texts(ws: Path) -> dict[str, str | None]:
    files = ("conf/experiment/promoted.yaml", "params.yaml", "promotion.json")
    return {f: (ws / f).read_text() if (ws / f).exists() else None for f in files}


# ---------------------------------------------------------------- the tag
def test_every_model_run_is_tagged_with_its_family_and_old_runs_get_it_from_features(conf_ws):
    conf = conf_ws / "conf"
    expected = {"au_pose": "au", "blendshapes_pose_interactions": "blendshapes", "emotions": "emotions"}
    got = {}
    for option in expected:
        raw = config.compose([f"features={option}"], config_dir=conf)
        with tracking.tracked_run({}, option, raw) as run:
            got[option] = run.run_id
    for option, family in expected.items():
        record = queries.run_record(got[option], {})
        assert record["tags"]["aumesh.family"] == family, option
    # a sweep's parent spans families: no family tag
    parent = tracking.start_parent_run({}, "sweep", params=config.compose(config_dir=conf))
    assert "aumesh.family" not in queries.run_record(parent, {})["tags"]
    tracking.end_run(parent)
    # a run logged before the tag existed (params only): its family from features.name
    from mlflow import MlflowClient

    client = MlflowClient()
    exp = client.get_experiment_by_name("aumesh").experiment_id
    old = client.create_run(exp, tags={"mlflow.parentRunId": parent}).info.run_id
    client.log_param(old, "features.name", "emotions_pose")
    client.set_terminated(old)
    assert "aumesh.family" not in client.get_run(old).data.tags
    assert queries.run_record(old, {})["family"] == "emotions"
    assert queries.list_child_runs(parent, {}).set_index("run_id").loc[old, "family"] == "emotions"


@pytest.mark.slow
def test_sweep_children_carry_the_family_tag(tmp_path, monkeypatch):
    """Real sweep children (sweep_child.run_configuration): the AU one finishes, the blendshape one fails on these
    AU-only tables, and both say their family."""
    from aumesh.experiments import sweep_cache, sweep_child
    from test_sweep import make_workspace

    ws = make_workspace(tmp_path / "ws")
    monkeypatch.chdir(ws)
    parent = tracking.start_parent_run({}, "family sweep")
    cache = sweep_cache.SweepCache()
    results = {}
    for ov in (["features=au", "model.n_components=2"], ["features=blendshapes_pose", "model.n_components=2"]):
        raw = config.compose(ov, config_dir=ws / "conf")
        results[ov[0]] = sweep_child.run_configuration(raw, ov, parent, cache=cache, root=ws)
    tracking.end_run(parent)
    assert results["features=au"]["status"] == "FINISHED", results
    children = queries.list_child_runs(parent, {}).set_index("run_id")
    tags = {rid: queries.run_record(rid, {})["tags"] for rid in children.index}
    assert tags[results["features=au"]["run_id"]]["aumesh.family"] == "au"
    assert tags[results["features=blendshapes_pose"]["run_id"]]["aumesh.family"] == "blendshapes"
    assert all(t["aumesh.role"] == "sweep-child" for t in tags.values())


# ---------------------------------------------------------------- aumesh runs
def test_runs_table_ranks_within_each_family_and_filters_by_family(conf_ws, tmp_path):
    parent, ids = _sweep(tmp_path, conf_ws / "conf")
    table = leaderboard.runs_table(queries.list_child_runs(parent, {}))
    ranks = {(r["family"], r["rank"]): r["run_id"] for r in table.to_dict(orient="records")}
    # each family's ranking by its own r2_mean (ROWS): no rank is shared across families' runs
    assert ranks == {
        ("au", 1): ids["au_pose"],
        ("au", 2): ids["au"],
        ("blendshapes", 1): ids["blendshapes_pose"],
        ("blendshapes", 2): ids["blendshapes"],
        ("emotions", 1): ids["emotions_pose"],
        ("emotions", 2): ids["emotions"],
    }
    assert list(table["family"]) == ["au", "au", "blendshapes", "blendshapes", "emotions", "emotions"]
    text = leaderboard.format_runs_table(table)
    assert "ranked within each input family" in text and "blendshapes_pose" in text
    only = leaderboard.runs_table(queries.list_child_runs(parent, {}), family="emotions")
    assert list(only["run_id"]) == [ids["emotions_pose"], ids["emotions"]] and list(only["rank"]) == [1, 2]


def test_choose_refuses_to_rank_runs_of_different_families():
    from aumesh.experiments import ranking
    from test_promote import cand

    au, bs = cand("a", 0.5, 10), cand("b", 0.9, 10)
    bs = ranking.Candidate(**{**bs.__dict__, "params": {**bs.params, "features.name": "blendshapes"}})
    with pytest.raises(ValueError, match="span input families"):
        ranking.choose([au, bs])
    assert ranking.choose([au, bs], family="au").run_id == "a"
    blend = ranking.choose([au, bs], family="blendshapes")
    assert blend.run_id == "b" and "only runs of the blendshapes family competed" in blend.compared


# ---------------------------------------------------------------- aumesh promote --family
@pytest.mark.slow
def test_promote_family_best_of_its_family_only_leaving_the_others(conf_ws, tmp_path):
    conf = conf_ws / "conf"
    parent, ids = _sweep(tmp_path, conf)

    bs = promote.promote(parent, conf_ws, {}, family="blendshapes")
    assert bs["run_id"] == ids["blendshapes_pose"]  # 0.70: not the emotions run's 0.80, not the AU runs
    assert (bs["family"], bs["features"], bs["n_components"]) == ("blendshapes", "blendshapes_pose", 12)
    assert bs["registered_model"] == "aumesh-blendshapes" and bs["model_version"] == "1"
    exp = yaml.safe_load((conf / "experiment" / "promoted.yaml").read_text())
    assert exp == {"families": {"blendshapes": {"features": "blendshapes_pose", "n_components": 12}}}
    doc = json.loads((conf_ws / "promotion.json").read_text())
    assert doc == {"promoted": None, "families": {"blendshapes": bs}}
    cfg = config.from_dict(config.compose(config_dir=conf))
    fams = dict(cfg.families.items())
    assert (fams["blendshapes"].features, fams["blendshapes"].n_components) == ("blendshapes_pose", 12)
    assert fams["emotions"].features == "emotions_pose_interactions"  # the other family: conf/families/default.yaml
    assert cfg.features.name == "au_pose_interactions"  # the AU model: as conf/ has it
    assert config.load_params(conf_ws / "params.yaml") == cfg
    assert registry.model_version_by_alias("aumesh-blendshapes", "champion", {})["run_id"] == bs["run_id"]
    assert registry.model_version_by_alias("aumesh-au-to-mesh", "champion", {}) is None

    # the AU promotion of the same sweep: the best AU run, and the blendshapes promotion kept
    au = promote.promote(parent, conf_ws, {})
    assert au["run_id"] == ids["au_pose"] and "family" not in au
    exp = yaml.safe_load((conf / "experiment" / "promoted.yaml").read_text())
    assert exp["features"]["name"] == "au_pose" and exp["model"]["n_components"] == 10
    assert exp["families"] == {"blendshapes": {"features": "blendshapes_pose", "n_components": 12}}
    doc = json.loads((conf_ws / "promotion.json").read_text())
    assert doc == {"promoted": au, "families": {"blendshapes": bs}}
    assert registry.model_version_by_alias("aumesh-au-to-mesh", "champion", {})["run_id"] == au["run_id"]

    # the emotions promotion: the AU promotion's lines and the blendshapes family untouched
    before = (conf / "experiment" / "promoted.yaml").read_text()
    em = promote.promote(parent, conf_ws, {}, family="emotions")
    assert em["run_id"] == ids["emotions_pose"] and em["n_components"] == 10  # effective: clipped from 40
    after = (conf / "experiment" / "promoted.yaml").read_text()
    assert after.startswith(before.split("\nfeatures:")[0])  # header and the AU provenance lines as they were
    exp = yaml.safe_load(after)
    assert exp["features"]["name"] == "au_pose" and exp["families"]["blendshapes"]["features"] == "blendshapes_pose"
    assert exp["families"]["emotions"] == {"features": "emotions_pose", "n_components": 10}
    assert json.loads((conf_ws / "promotion.json").read_text()) == {
        "promoted": au,
        "families": {"blendshapes": bs, "emotions": em},
    }
    cfg = config.from_dict(config.compose(config_dir=conf))
    assert (cfg.features.name, cfg.model.n_components) == ("au_pose", 10)
    assert dict(cfg.families.items())["emotions"].features == "emotions_pose"
    assert registry.model_version_by_alias("aumesh-blendshapes", "champion", {})["run_id"] == bs["run_id"]


def test_promote_family_refuses_a_run_of_another_family_writing_nothing(conf_ws, tmp_path):
    parent, ids = _sweep(tmp_path, conf_ws / "conf")
    before = _texts(conf_ws)
    with pytest.raises(UserError, match=r"is a blendshapes run \(features.name=blendshapes\), not a emotions run") as e:
        promote.promote(None, conf_ws, {}, family="emotions", run_id=ids["blendshapes"], register=False)
    assert "\n" not in str(e.value) and "--family blendshapes" in str(e.value)
    with pytest.raises(UserError, match="is a emotions run"):  # the AU promotion of a named run: AU runs only
        promote.promote(None, conf_ws, {}, run_id=ids["emotions"], register=False)
    assert _texts(conf_ws) == before
    # the run named, of the family: promoted, though not the family's best
    rec = promote.promote(None, conf_ws, {}, family="blendshapes", run_id=ids["blendshapes"], register=False)
    assert (rec["run_id"], rec["parent_run_id"], rec["features"]) == (ids["blendshapes"], parent, "blendshapes")


def test_promote_family_refuses_a_run_fitted_with_other_shared_settings(conf_ws, tmp_path):
    rows = [({"features": "emotions", "preprocess.target": "neutral"}, {"r2_mean": 0.3, "n_components": 7.0})]
    parent, _ = _sweep(tmp_path, conf_ws / "conf", rows)
    before = _texts(conf_ws)
    with pytest.raises(UserError, match=r"preprocess.target=neutral \(workspace: absolute\)"):
        promote.promote(parent, conf_ws, {}, family="emotions", register=False)
    assert _texts(conf_ws) == before


def test_promotion_document_replaces_only_its_own_part():
    current = {"promoted": {"run_id": "au1"}, "families": {"emotions": {"run_id": "e1"}}}
    assert promotion_journal.promotion_document({}, {"run_id": "x"}, None) == {"promoted": {"run_id": "x"}}
    assert promotion_journal.promotion_document({"promoted": None}, {"run_id": "x"}, None) == {
        "promoted": {"run_id": "x"}
    }
    new = promotion_journal.promotion_document(current, {"run_id": "b1"}, "blendshapes")
    assert new == {
        "promoted": {"run_id": "au1"},
        "families": {"emotions": {"run_id": "e1"}, "blendshapes": {"run_id": "b1"}},
    }
    new = promotion_journal.promotion_document(current, {"run_id": "au2"}, None)
    assert new == {"promoted": {"run_id": "au2"}, "families": {"emotions": {"run_id": "e1"}}}


# ---------------------------------------------------------------- make promote FAMILY=...
@pytest.mark.slow
def test_make_promote_family_through_the_makefile(conf_ws, tmp_path):
    import os

    parent, ids = _sweep(tmp_path, conf_ws / "conf")
    for name in ("requirements.lock", "pyproject.toml"):
        (conf_ws / name).touch()
    stamp = conf_ws / "installed.stamp"
    stamp.touch()
    os.utime(stamp, (stamp.stat().st_mtime + 10, stamp.stat().st_mtime + 10))  # newer than its prerequisites
    venv = Path(sys.executable).parent.parent
    proc = subprocess.run(
        ["make", "-s", "-f", str(REPO / "Makefile"), "promote", "FAMILY=blendshapes", f"VENV={venv}", f"STAMP={stamp}"],
        cwd=conf_ws,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    doc = json.loads((conf_ws / "promotion.json").read_text())
    assert doc["promoted"] is None and doc["families"]["blendshapes"]["run_id"] == ids["blendshapes_pose"]
    assert doc["families"]["blendshapes"]["parent_run_id"] == parent
    exp = yaml.safe_load((conf_ws / "conf" / "experiment" / "promoted.yaml").read_text())
    assert exp == {"families": {"blendshapes": {"features": "blendshapes_pose", "n_components": 12}}}
    assert "families.blendshapes" in proc.stdout
    # the command line: a run of another family refused in one line (exit 2), nothing written; runs by family
    before = _texts(conf_ws)
    aumesh = [sys.executable, "-m", "aumesh"]
    refused = subprocess.run(
        [*aumesh, "promote", "--family", "emotions", ids["blendshapes"], "--no-register"],
        cwd=conf_ws,
        capture_output=True,
        text=True,
        timeout=300,
    )
    lines = [ln for ln in refused.stderr.splitlines() if ln.startswith("aumesh promote: error:")]
    assert refused.returncode == 2 and len(lines) == 1, refused.stdout + refused.stderr
    assert f"run {ids['blendshapes']} is a blendshapes run" in lines[0]
    assert _texts(conf_ws) == before
    listed = subprocess.run(
        [*aumesh, "runs", "--family", "emotions"], cwd=conf_ws, capture_output=True, text=True, timeout=300
    )
    assert listed.returncode == 0, listed.stderr
    assert ids["emotions"][:8] in listed.stdout and ids["blendshapes"][:8] not in listed.stdout


# ---------------------------------------------------------------- one transaction, as the AU promotion
@pytest.mark.slow
def test_a_family_promotion_killed_after_registering_is_completed_keeping_the_au_promotion(conf_ws, tmp_path, capsys):
    """SIGKILL between the new aumesh-blendshapes version and its alias: the next `aumesh runs` completes it, and
    promotion.json gets the family's record (with the version) beside the AU promotion's, which stays as it was."""
    from aumesh import cli
    from test_crash_promote import CHILD

    parent, ids = _sweep(tmp_path, conf_ws / "conf")
    au = promote.promote(parent, conf_ws, {})
    child = CHILD.replace(
        "promote.promote(parent, Path(root), {})", 'promote.promote(parent, Path(root), {}, family="blendshapes")'
    )
    proc = subprocess.run(
        [sys.executable, "-c", child, "after registering", str(conf_ws), parent],
        cwd=conf_ws,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == -9, proc.stderr
    assert (conf_ws / promotion_journal.JOURNAL).exists()
    assert cli.main(["runs", "--sweep", parent]) == 0
    assert "aumesh: completed the interrupted promotion" in capsys.readouterr().err
    doc = json.loads((conf_ws / "promotion.json").read_text())
    assert doc["promoted"] == au
    bs = doc["families"]["blendshapes"]
    champion = registry.model_version_by_alias("aumesh-blendshapes", "champion", {})
    assert bs["run_id"] == ids["blendshapes_pose"] == champion["run_id"] and bs["model_version"] == champion["version"]
    exp = yaml.safe_load((conf_ws / "conf" / "experiment" / "promoted.yaml").read_text())
    assert exp["features"]["name"] == "au_pose" and exp["families"]["blendshapes"]["features"] == "blendshapes_pose"
    assert config.load_params(conf_ws / "params.yaml") == config.from_dict(config.compose(config_dir=conf_ws / "conf"))
