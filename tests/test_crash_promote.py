"""``aumesh promote`` is one transaction: killed (SIGKILL) at any step, the next command that touches promotion
(here ``aumesh runs``) completes or rolls it back and says which in one line, so that the registry alias,
``conf/experiment/promoted.yaml``, ``params.yaml`` and ``promotion.json`` are all the old promotion's or all the new
one's. An error on the way rolls back at once."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from aumesh import cli, config
from aumesh.experiments import promote, promotion_journal
from aumesh.tracking import mlflow_store, registry
from test_promote import _log_fake_sweep

NAME = promote.DEFAULT_MODEL_NAME

CHILD = textwrap.dedent(
    """
    import os, signal, sys
    from pathlib import Path
    from mlflow import MlflowClient
    from aumesh.experiments import promote

    point, root, parent = sys.argv[1:4]

    def die():
        os.kill(os.getpid(), signal.SIGKILL)

    create, set_alias, replace = MlflowClient.create_model_version, MlflowClient.set_registered_model_alias, os.replace

    def create_model_version(self, *args, **kwargs):
        if point == "before registering":
            die()
        return create(self, *args, **kwargs)

    def set_registered_model_alias(self, *args, **kwargs):
        if point == "after registering":  # the version exists, the alias still points at the old one
            die()
        set_alias(self, *args, **kwargs)
        if point == "after the alias":
            die()

    def os_replace(src, dst):
        replace(src, dst)
        if Path(dst).name == point:  # a file written: promoted.yaml, params.yaml, promotion.json
            die()

    MlflowClient.create_model_version = create_model_version
    MlflowClient.set_registered_model_alias = set_registered_model_alias
    os.replace = os_replace
    promote.promote(parent, Path(root), {})
    """
)


def _state(ws: Path) -> dict:
    """What promotion writes: the alias's version and run, and the three files (None: absent)."""
    alias = registry.model_version_by_alias(NAME, "champion", {})
    files = {
        rel: (ws / rel).read_text() if (ws / rel).exists() else None
        for rel in ("conf/experiment/promoted.yaml", "params.yaml", "promotion.json")
    }
    return {"alias": alias and (alias["version"], alias["run_id"]), **files}


def _consistent_new(ws: Path, run_id: str) -> None:
    """All four are the new promotion's, checked against each other (not against a recorded copy)."""
    record = json.loads((ws / "promotion.json").read_text())["promoted"]
    alias = registry.model_version_by_alias(NAME, "champion", {})
    assert record["run_id"] == run_id == alias["run_id"]
    assert record["model_version"] == alias["version"]
    composed = config.compose(config_dir=ws / "conf")  # conf/ with the new experiment file
    assert config.load_params(ws / "params.yaml") == config.from_dict(composed)
    assert f"model.n_components={composed['model']['n_components']}" in record["config_overrides"]


@pytest.fixture
def promoted_once(conf_ws, tmp_path):
    """A workspace after one promotion (version 1 is the champion) and a second sweep to promote."""
    first, _ = _log_fake_sweep(
        tmp_path, conf_ws / "conf", [({"model.n_components": 10}, {"r2_mean": 0.6, "n_components": 10.0}, "FINISHED")]
    )
    promote.promote(first, conf_ws, {})
    second, ids = _log_fake_sweep(
        tmp_path, conf_ws / "conf", [({"model.n_components": 5}, {"r2_mean": 0.7, "n_components": 5.0}, "FINISHED")]
    )
    return conf_ws, second, ids[0]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("point", "outcome"),
    [
        ("before registering", "rolled back"),
        ("after registering", "completed"),
        ("after the alias", "completed"),  # the issue's case, with promoted.yaml: the next two points
        ("promoted.yaml", "completed"),
        ("params.yaml", "completed"),
        ("promotion.json", "completed"),
    ],
)
def test_a_promotion_killed_at_any_step_is_completed_or_rolled_back_by_the_next_command(
    promoted_once, point, outcome, capsys
):
    ws, sweep, winner = promoted_once
    old = _state(ws)
    child = subprocess.run(
        [sys.executable, "-c", CHILD, point, str(ws), sweep], cwd=ws, capture_output=True, text=True, timeout=300
    )
    assert child.returncode == -9, child.stderr  # killed there, not finished or failed
    assert (ws / promotion_journal.JOURNAL).exists()
    capsys.readouterr()
    assert cli.main(["runs", "--sweep", sweep]) == 0  # the next command that touches promotion
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if "interrupted promotion" in ln]
    assert len(lines) == 1 and lines[0].startswith(f"aumesh: {outcome} the interrupted promotion"), err
    assert not (ws / promotion_journal.JOURNAL).exists()
    if outcome == "rolled back":
        assert _state(ws) == old
    else:
        _consistent_new(ws, winner)
    assert cli.main(["runs", "--sweep", sweep]) == 0
    assert "interrupted promotion" not in capsys.readouterr().err  # said once


def test_a_promotion_that_fails_half_way_rolls_back_at_once(promoted_once, monkeypatch):
    """An error after the registry and the experiment file (params.yaml cannot be written): the alias is back on
    version 1 and every file is the old one; the new version stays registered, without the alias, and promoting again
    takes it (registry.register_model_version is idempotent per run: no third version of two runs)."""
    ws, sweep, _ = promoted_once
    old = _state(ws)
    real = promotion_journal.atomic_write_text

    def failing(path, text):
        if Path(path).name == "params.yaml":
            raise PermissionError(13, "Permission denied", str(path))
        return real(path, text)

    monkeypatch.setattr(promotion_journal, "atomic_write_text", failing)
    with pytest.raises(PermissionError):
        promote.promote(sweep, ws, {})
    monkeypatch.setattr(promotion_journal, "atomic_write_text", real)
    assert _state(ws) == old
    assert not (ws / promotion_journal.JOURNAL).exists()
    assert registry.find_version(NAME, _state(ws)["alias"][1], "aumesh.parent_run_id", "x", {}) is None
    # the failed promotion's version exists, unaliased; promoting again takes the alias to it, registering nothing new
    promote.promote(sweep, ws, {})
    run_id = json.loads((ws / "promotion.json").read_text())["promoted"]["run_id"]
    versions = mlflow_store.get_client({}).search_model_versions(f"run_id = '{run_id}'")
    assert [str(v.version) for v in versions if v.name == NAME] == ["2"]
    assert _state(ws)["alias"][0] == "2"


def test_a_journal_without_a_registry_step_is_rolled_forward(conf_ws, capsys):
    """Recovery from the journal alone (no registry): the files get their new text, one line says so."""
    new = {"conf/experiment/promoted.yaml": "# @package _global_\nmodel:\n  n_components: 7\n"}
    composed = config.compose(config_dir=conf_ws / "conf")
    composed["model"]["n_components"] = 7
    new["params.yaml"] = config.params_text(composed)
    new["promotion.json"] = json.dumps({"promoted": {"run_id": "r1"}})
    journal = promotion_journal.new_journal(conf_ws, new, {"run_id": "r1"}, "promotion.json", None, {})
    (conf_ws / promotion_journal.JOURNAL).write_text(json.dumps(journal))
    (conf_ws / "conf/experiment").mkdir(exist_ok=True)
    (conf_ws / "conf/experiment/promoted.yaml").write_text(new["conf/experiment/promoted.yaml"])  # killed after it
    line, changed = promotion_journal.recover(conf_ws)
    assert line.startswith("completed the interrupted promotion (run r1") and changed == [
        "params.yaml",
        "promotion.json",
    ]
    assert config.load_params(conf_ws / "params.yaml") == config.from_dict(config.compose(config_dir=conf_ws / "conf"))
    assert config.load_params(conf_ws / "params.yaml").model.n_components == 7
    assert promotion_journal.recover(conf_ws) == (None, [])


def test_a_live_promotion_is_not_taken_for_an_interrupted_one(conf_ws):
    (conf_ws / promotion_journal.JOURNAL).write_text("{}")
    with (
        promotion_journal.lock(conf_ws),
        pytest.raises(promotion_journal.PromotionBusy, match="another `aumesh promote`"),
    ):
        promotion_journal.recover(conf_ws)
    assert (conf_ws / promotion_journal.JOURNAL).exists()
