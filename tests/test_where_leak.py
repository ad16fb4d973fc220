"""Where a run executes is not what it computes: ``compute.*`` and ``tracking.*`` never reach a record.

Fast: the one list of those groups (:data:`aumesh.config.WHERE_GROUPS`) read against every form of a Hydra
override, and the ``check_params`` stage's comparison with ``conf/``. Slow: the real path, a sweep given
``compute.address=`` of a real ``dask scheduler`` (and ``tracking.experiment=``) on its command line, promoted,
evaluated and released, then every record grepped for the address; and a real ``dvc exp run -S compute.address=...``
on a built workspace, refused in one line before anything runs, with no experiment made.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
import yaml

from aumesh import config
from aumesh.core.errors import ConfigError
from aumesh.stages import check_params


# ------------------------------------------------------------------ fast
@pytest.mark.parametrize(
    ("override", "where"),
    [
        ("compute=distributed", True),
        ("compute.address=tcp://10.0.0.5:8786", True),
        ("+compute.extra=1", True),
        ("~compute.address", True),
        ("tracking.experiment=x", True),
        ("tracking=mlflow", True),
        ("compute/sub=x", True),  # a nested group of compute, were there one
        ("model.n_components=10", False),
        ("features=au_pose", False),
        ("computeX.address=1", False),  # a group whose name only starts like one
        ("model/eiv=corrected", False),
        ("seed=3", False),
    ],
)
def test_where_overrides_are_named_by_their_group(override, where):
    assert config.is_where(override) is where
    assert config.recorded_overrides([override]) == ([] if where else [override])


def test_without_where_keeps_every_other_key_nested_or_flat(fixed_conf):
    composed = config.compose(["compute=distributed", "compute.address=tcp://10.0.0.5:8786"], config_dir=fixed_conf)
    kept = config.without_where(composed)
    assert set(kept) == set(composed) - {"compute", "tracking"}
    flat = config.flatten(composed)
    kept_flat = config.without_where(flat)
    assert kept_flat == {k: v for k, v in flat.items() if not k.startswith(("compute.", "tracking."))}


def test_child_run_name_never_holds_the_address():
    from aumesh.experiments.sweep_child import run_name

    assert (
        run_name(["compute=distributed", "compute.address=tcp://10.0.0.5:8786", "model.n_components=10", "+seed=2"])
        == "n_components=10,seed=2"
    )
    assert run_name(["tracking.experiment=x"]) == "base"


def test_check_params_names_each_where_value_that_differs_from_conf(fixed_conf, tmp_path):
    base = config.compose(config_dir=fixed_conf)
    assert check_params.where_differences(base, base) == {}
    moved = config.compose(
        ["compute=distributed", "compute.address=tcp://10.0.0.5:8786", "tracking.experiment=mine"],
        config_dir=fixed_conf,
    )
    differ = check_params.where_differences(moved, base)
    assert differ["compute.address"] == ("tcp://10.0.0.5:8786", None)
    assert differ["compute.scheduler"] == ("distributed", base["compute"]["scheduler"])
    assert differ["tracking.experiment"] == ("mine", base["tracking"]["experiment"])
    assert not any(k.split(".")[0] not in config.WHERE_GROUPS for k in differ)  # model keys are not its business
    changed_model = config.compose(["model.n_components=7"], config_dir=fixed_conf)
    assert check_params.where_differences(changed_model, base) == {}
    path = tmp_path / "params.yaml"
    config.write_params(moved, path)
    with pytest.raises(ConfigError, match=r"compute.address=tcp://10.0.0.5:8786 .*AUMESH_COMPUTE_ADDRESS") as err:
        check_params.main(path, fixed_conf)
    assert "\n" not in str(err.value)
    config.write_params(changed_model, path)
    check_params.main(path, fixed_conf)  # a model change passes


def test_locked_outputs_are_the_cached_outputs_of_a_lock_not_the_files_git_holds():
    from aumesh.experiments.exp_apply import LockedOutput, locked_outputs

    lock = {
        "schema": "2.0",
        "stages": {
            "evaluate": {
                "outs": [
                    {"path": "build/model", "md5": "a" * 32 + ".dir", "hash": "md5"},
                    {"path": "metrics/metrics.json", "md5": "b" * 32, "hash": "md5"},  # cache: false, in git
                ]
            },
            "release": {"outs": [{"path": "release", "md5": "c" * 32 + ".dir"}]},  # an older lock: no `hash`
            "check_params": {"deps": [{"path": "params.yaml", "md5": "d" * 32}]},  # no outputs
        },
    }
    assert locked_outputs(lock, ["metrics/metrics.json"]) == [
        LockedOutput("evaluate", "build/model", "a" * 32 + ".dir", "md5"),
        LockedOutput("release", "release", "c" * 32 + ".dir", "md5-dos2unix"),
    ]


# ------------------------------------------------------------------ slow: the real path
def _every_record(ws: Path) -> dict[str, str]:
    """Every file a promotion and a release write, by name."""
    files = {
        "promotion.json": ws / "promotion.json",
        "promoted.yaml": ws / "conf" / "experiment" / "promoted.yaml",
        "params.yaml": ws / "params.yaml",
        "model_card.json": ws / "release" / "model_card.json",
        "MODEL_CARD.md": ws / "release" / "MODEL_CARD.md",
        "viewer.html": ws / "release" / "viewer.html",
        "au_directions.json": ws / "release" / "au_directions.json",
    }
    return {name: path.read_text() for name, path in files.items()}


def _every_mlflow_string() -> dict[str, str]:
    """Every run's name, params, tags and logged config, and every registered version's tags, of every experiment."""
    from aumesh.tracking import mlflow_store

    client = mlflow_store.get_client({})
    out: dict[str, str] = {}
    experiments = client.search_experiments()
    for run in client.search_runs([e.experiment_id for e in experiments], max_results=1000):
        rid = run.info.run_id
        out[f"run {rid} name"] = str(run.info.run_name)
        out[f"run {rid} params"] = json.dumps(dict(run.data.params))
        out[f"run {rid} tags"] = json.dumps({k: v for k, v in run.data.tags.items() if k != "mlflow.log-model.history"})
        names = [a.path for a in client.list_artifacts(rid)]
        if "config.yaml" in names:
            out[f"run {rid} config.yaml"] = Path(client.download_artifacts(rid, "config.yaml")).read_text()
    for version in client.search_model_versions():
        out[f"model version {version.version} tags"] = json.dumps(dict(version.tags))
    return out


@pytest.fixture
def sweep_workspace(tmp_path, monkeypatch):
    from conftest import new_store
    from test_sweep import make_workspace

    ws = make_workspace(tmp_path / "ws")
    (tmp_path / "aumesh-test-store").mkdir()
    store = new_store(tmp_path / "aumesh-test-store" / "mlflow.db")
    monkeypatch.chdir(ws)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{store}")
    for var in ("DVC_ROOT", "DVC_EXP_NAME", "AUMESH_SWEEP_PARENT_RUN_ID", "AUMESH_COMPUTE_ADDRESS"):
        monkeypatch.delenv(var, raising=False)
    return ws


@pytest.mark.slow
def test_a_sweep_on_a_real_scheduler_records_no_address_anywhere(sweep_workspace, tmp_path):
    """``aumesh sweep -m compute=distributed compute.address=tcp://127.0.0.1:PORT tracking.experiment=...`` on a real
    ``dask scheduler`` and worker started elsewhere; promoted, evaluated, released: neither the address nor the
    experiment given on the command line is in a run's name, params, tags or config, a registered version's tags,
    promotion.json, conf/, params.yaml or any release file."""
    from aumesh import cli
    from aumesh.tracking import queries
    from test_cluster import Cluster

    (tmp_path / "elsewhere").mkdir()
    c = Cluster(tmp_path / "elsewhere", n_workers=1)
    address = c.address.removeprefix("tcp://")
    experiment = "where-leak-experiment-marker"
    try:
        argv = ["sweep", "-m", "compute=distributed", f"compute.address={c.address}", "compute.partition_rows=250"]
        assert cli.main([*argv, f"tracking.experiment={experiment}", "model.n_components=2,3"]) == 0
    finally:
        c.stop()
    parent = queries.latest_parent_run({"experiment": experiment})
    children = queries.list_child_runs(parent, {"experiment": experiment})
    assert sorted(children["run_name"]) == ["n_components=2", "n_components=3"]
    assert cli.main(["promote", "--sweep", parent]) == 0
    assert cli.main(["evaluate"]) == 0
    assert cli.main(["release"]) == 0
    records = {**_every_record(sweep_workspace), **_every_mlflow_string()}
    assert any(parent in text for text in records.values())  # the grep reads the sweep's records
    leaks = {name: marker for name, text in records.items() for marker in (address, experiment) if marker in text}
    assert leaks == {}
    promotion = json.loads(records["promotion.json"])["promoted"]
    assert promotion["run_name"] in ("n_components=2", "n_components=3")
    assert all(not o.startswith(("compute", "tracking")) for o in promotion["config_overrides"])


# ------------------------------------------------------------------ slow: dvc exp run -S compute.address
@pytest.mark.slow
def test_dvc_exp_run_with_a_scheduler_address_is_refused_before_any_stage(tmp_path, fixed_conf):
    """On a built and committed workspace (every stage up to date), ``dvc exp run -S compute=distributed -S
    compute.address=...`` would rerun nothing and commit the address as an experiment: check_params refuses it in one
    line (exit != 0), no experiment is made and no other stage ran; the same run with the address in the environment
    is a no-op that records nothing."""
    from test_cluster import BIN, _env, _run, make_workspace

    ws = make_workspace(tmp_path / "ws", fixed_conf, seed=3, n_frames=900)
    config.write_params(config.compose(config_dir=ws / "conf"), ws / "params.yaml")  # conf/'s, as `make params`
    _run([BIN / "dvc", "repro", "-q"], ws, _env())
    _run(["git", "add", "-A"], ws, _env())
    _run(["git", "commit", "-qm", "built"], ws, _env())
    lock = (ws / "dvc.lock").read_text()
    address = "tcp://127.0.0.1:9"
    proc = subprocess.run(
        [BIN / "dvc", "exp", "run", "-S", "compute=distributed", "-S", f"compute.address={address}"],
        cwd=ws,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0, out
    errors = [line for line in out.splitlines() if line.startswith("aumesh check_params: error:")]
    assert len(errors) == 1 and f"compute.address={address}" in errors[0] and "AUMESH_COMPUTE_ADDRESS" in errors[0], out
    assert "Running stage 'ingest'" not in out and "Running stage 'evaluate'" not in out
    listed = _run([BIN / "dvc", "exp", "list", "--name-only"], ws, _env()).stdout
    assert listed.strip() == ""
    assert (ws / "dvc.lock").read_text() == lock
    # the fix the line names: params.yaml from conf/, the address from the environment -> nothing reruns, nothing kept
    _run([BIN / "aumesh", "compose-params"], ws, _env())
    ok = _run([BIN / "dvc", "exp", "run"], ws, _env(AUMESH_COMPUTE_ADDRESS=address))
    assert "Running stage" not in ok.stdout + ok.stderr or "check_params" in ok.stdout
    assert address not in (ws / "params.yaml").read_text() + (ws / "dvc.lock").read_text()
    assert yaml.safe_load((ws / "params.yaml").read_text())["compute"]["address"] is None


# ------------------------------------------------------------------ slow: aumesh exp apply of an unpushed experiment
def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _cache_objects(ws: Path, lock_text: str) -> set[Path]:
    """The cache files of every cached output a dvc.lock records (a folder's .dir manifest and each file in it)."""

    def obj(md5: str) -> Path:
        return ws / ".dvc" / "cache" / "files" / "md5" / md5[:2] / md5[2:]

    found = set()
    for stage in yaml.safe_load(lock_text)["stages"].values():
        for out in stage.get("outs", []):
            if not obj(out["md5"]).exists():  # a `cache: false` metrics or plot file: in git
                continue
            found.add(obj(out["md5"]))
            if out["md5"].endswith(".dir"):
                found |= {obj(e["md5"]) for e in json.loads(obj(out["md5"]).read_text())}
    return found


@pytest.mark.slow
def test_exp_apply_of_an_experiment_whose_outputs_are_not_cached_is_refused_and_the_recovery_works(
    tmp_path, fixed_conf
):
    """A real ``dvc exp run`` whose outputs then leave the cache (as on a machine that never got them): ``aumesh exp
    apply`` refuses in one line (exit 2) naming them and leaves the workspace as it was; plain ``dvc exp apply``
    deletes release/ and ``dvc checkout`` then fails; ``git checkout dvc.lock params.yaml metrics && dvc checkout``
    brings release/ back byte for byte."""
    from test_cluster import BIN, _env, _run, make_workspace

    ws = make_workspace(tmp_path / "ws", fixed_conf, seed=4, n_frames=900)
    config.write_params(config.compose(config_dir=ws / "conf"), ws / "params.yaml")
    env = _env()
    _run([BIN / "dvc", "repro", "-q"], ws, env)
    _run(["git", "add", "-A"], ws, env)
    _run(["git", "commit", "-qm", "built"], ws, env)
    before, lock = _tree(ws / "release"), (ws / "dvc.lock").read_text()
    _run([BIN / "dvc", "exp", "run", "-q", "-n", "leaky", "-S", "model.n_components=4"], ws, env)
    exp_lock = (ws / "dvc.lock").read_text()
    assert _tree(ws / "release") != before
    _run(["bash", "-c", "git checkout dvc.lock params.yaml metrics && dvc checkout -q"], ws, env)
    assert _tree(ws / "release") == before
    for path in _cache_objects(ws, exp_lock) - _cache_objects(ws, lock):  # the experiment's own objects leave
        path.unlink()

    proc = subprocess.run([BIN / "aumesh", "exp", "apply", "leaky"], cwd=ws, env=env, capture_output=True, text=True)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("aumesh exp: error: experiment leaky:"), proc.stderr
    for text in ("release (release: its file list)", "build/model (evaluate: its file list)", "not in the cache"):
        assert text in lines[0], lines[0]
    for text in ("dvc exp push", "--force", "git checkout dvc.lock params.yaml metrics && dvc checkout"):
        assert text in lines[0], lines[0]
    assert "build/prepared" not in lines[0] and "build/ingested" not in lines[0]  # shared with the baseline: cached
    assert _tree(ws / "release") == before and (ws / "dvc.lock").read_text() == lock

    # what the refusal prevents, and the README's recovery
    subprocess.run([BIN / "dvc", "exp", "apply", "leaky"], cwd=ws, env=env, capture_output=True, text=True)
    assert _tree(ws / "release") != before  # release/ deleted (or not the baseline's)
    assert subprocess.run([BIN / "dvc", "checkout"], cwd=ws, env=env, capture_output=True).returncode != 0
    _run(["bash", "-c", "git checkout dvc.lock params.yaml metrics && dvc checkout"], ws, env)
    assert _tree(ws / "release") == before
    assert (ws / "dvc.lock").read_text() == lock

    # an experiment whose outputs are only in the default remote: applied, then pulled
    (tmp_path / "remote").mkdir()
    _run([BIN / "dvc", "remote", "add", "-d", "team", tmp_path / "remote"], ws, env)
    _run([BIN / "dvc", "exp", "run", "-q", "-n", "pushed", "-S", "model.n_components=5"], ws, env)
    pushed, pushed_lock = _tree(ws / "release"), (ws / "dvc.lock").read_text()
    _run([BIN / "dvc", "push", "-q"], ws, env)  # the experiment's outputs (the workspace holds them now)
    _run(["bash", "-c", "git checkout dvc.lock params.yaml metrics && dvc checkout -q"], ws, env)
    for path in _cache_objects(ws, pushed_lock) - _cache_objects(ws, lock):
        path.unlink()
    proc = subprocess.run([BIN / "aumesh", "exp", "apply", "pushed"], cwd=ws, env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "only in the remote; `dvc pull`" in proc.stdout + proc.stderr
    assert _tree(ws / "release") == pushed and (ws / "dvc.lock").read_text() == pushed_lock
