"""Fault injection: bad tables, bad configuration, interrupted stages.

Every case asserts the exit code, that the message names the file, column or key, and that the
previous outputs (``release/`` bit for bit, ``build/``) and the MLflow store are unchanged or consistent.
The fast cases run the ``aumesh`` command in-process on a copy of one good workspace; the slow ones
interrupt ``dvc repro`` (SIGINT, SIGKILL) in each stage.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from aumesh import cli
from aumesh.config import write_params
from aumesh.core.schema import AU_COLUMNS
from aumesh.synthetic.tables import SynthSpec, write_tables

TABLE = "data/frames_0000.parquet"


def tree_digest(root: Path) -> dict[str, str]:
    """sha256 of every file under ``root`` (relative path -> digest): 'bit for bit'."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def run_cli(args: list[str], cwd: Path, capsys) -> tuple[int, str]:
    old = Path.cwd()
    os.chdir(cwd)
    try:
        code = cli.main(args)
    finally:
        os.chdir(old)
    out = capsys.readouterr()
    return code, out.err


def dvc_env(ws: Path) -> dict[str, str]:
    """The environment `dvc repro` runs in a test workspace with: the project's venv first on PATH (its stages run
    ``aumesh``), the workspace's own MLflow store."""
    from test_dvc_pipeline import BIN

    return {
        **os.environ,
        "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}",
        "MLFLOW_TRACKING_URI": f"sqlite:///{ws / 'mlflow.db'}",
    }


def mlflow_runs(ws: Path) -> pd.DataFrame:
    import mlflow

    client = mlflow.MlflowClient(tracking_uri=f"sqlite:///{ws / 'mlflow.db'}")
    exps = [e.experiment_id for e in client.search_experiments()]
    runs = client.search_runs(exps)
    return pd.DataFrame({"run_id": [r.info.run_id for r in runs], "status": [r.info.status for r in runs]})


# ---------------------------------------------------------------------------------------------- table faults
def _table(ws: Path) -> pd.DataFrame:
    return pd.read_parquet(ws / TABLE)


def _save(ws: Path, df: pd.DataFrame) -> None:
    df.to_parquet(ws / TABLE, index=False)


def still_subject_in_degrees(ws):
    df = _table(ws)
    for c in ("Pitch", "Yaw", "Roll"):  # a near-still subject: every value in degrees below pi
        df[c] = np.clip(np.rad2deg(df[c]) / 12.0, -3.1, 3.1)
    _save(ws, df)


def pose_in_degrees(ws):
    df = _table(ws)
    df["Yaw"] = np.rad2deg(df["Yaw"])
    _save(ws, df)


def numeric_strings(column):
    def inject(ws):
        df = _table(ws)
        df[column] = df[column].map(repr)  # a CSV round trip
        _save(ws, df)

    return inject


def text_value(column, value, row=7):
    def inject(ws):
        df = _table(ws)
        df[column] = df[column].map(repr)  # text, as a CSV round trip leaves it, with one value that is no number
        df.loc[row, column] = value
        _save(ws, df)

    return inject


def set_value(column, value, row=5):
    def inject(ws):
        df = _table(ws)
        df.loc[row, column] = value
        _save(ws, df)

    return inject


def openface_scale(ws):
    df = _table(ws)
    df[list(AU_COLUMNS)] *= 5.0
    _save(ws, df)


def all_nan(column):
    return lambda ws: _save(ws, _table(ws).assign(**{column: np.nan}))


def corrupt_bytes(ws):
    path = ws / TABLE
    raw = bytearray(path.read_bytes())
    rng = np.random.default_rng(0)
    for pos in rng.integers(len(raw) // 4, len(raw) // 2, 64):  # inside the column chunks, not the footer
        raw[pos] ^= 0xFF
    path.write_bytes(bytes(raw))


def zero_bytes(ws):
    (ws / TABLE).write_bytes(b"")


def truncated(ws):
    path = ws / TABLE
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def missing_folder(ws):
    shutil.rmtree(ws / "data")


def missing_column(ws):
    _save(ws, _table(ws).rename(columns={"AU12": "au12"}))


def duplicate_frames(ws):
    df = _table(ws)
    _save(ws, pd.concat([df, df.iloc[:3]], ignore_index=True))


def empty_table(ws):
    _save(ws, _table(ws).iloc[:0])


TABLE_FAULTS = {
    # the list: these trained a wrong model with exit 0, or said the wrong thing
    "still subject in degrees": (
        still_subject_in_degrees,
        [TABLE.split("/")[0], "degrees", "preprocess.max_drop_fraction"],
    ),
    "AU stored as numeric strings": (
        numeric_strings("AU12"),
        [TABLE, "'AU12'", "stored as text", "data.coerce_numeric"],
    ),
    "mesh stored as numeric strings": (
        numeric_strings("x_10"),
        [TABLE, "'x_10'", "stored as text", "data.coerce_numeric"],
    ),
    "AU 'n/a'": (text_value("AU04", "n/a"), [TABLE, "'AU04'", "row 7", "'n/a'"]),
    "AU ''": (text_value("AU04", ""), [TABLE, "'AU04'", "row 7", "''"]),
    "mesh 'n/a'": (text_value("y_33", "n/a"), [TABLE, "'y_33'", "row 7", "'n/a'"]),
    "AUs on OpenFace's 0-5 scale": (openface_scale, [TABLE, "'AU01'", "divide every AU column by 5"]),
    "all-NaN column": (all_nan("AU07"), [TABLE, "'AU07'", "empty (all"]),
    "bytes corrupted inside the parquet": (corrupt_bytes, [TABLE, "corrupt"]),
    "missing data folder": (missing_folder, ["data: the data folder does not exist", "dvc pull"]),
    # already handled before: they must stay handled
    "pose in degrees (beyond pi)": (pose_in_degrees, [TABLE, "'Yaw'", "looks like degrees"]),
    "missing column": (missing_column, [TABLE, "'AU12' is missing", "'au12'"]),
    "NaN in an AU": (set_value("AU04", np.nan), [TABLE, "'AU04'", "NaN/inf", "row 5"]),
    "inf in pose": (set_value("Yaw", np.inf), [TABLE, "'Yaw'", "NaN/inf", "row 5"]),
    "NaN in the mesh": (set_value("z_263", np.nan), [TABLE, "z_263", "NaN/inf", "row 5"]),
    "zero-byte file": (zero_bytes, [TABLE, "corrupt or truncated"]),
    "truncated file": (truncated, [TABLE, "corrupt or truncated"]),
    "duplicate frames": (duplicate_frames, [TABLE, "(video_id, frame)"]),
    "empty table": (empty_table, ["0 rows", "empty input"]),
}


def run_data_stages(cwd: Path, capsys) -> tuple[int, str]:
    """``ingest`` then ``prepare``, as ``dvc repro`` runs them: the first failure's exit code and stderr."""
    for stage in ("ingest", "prepare"):
        code, err = run_cli([stage], cwd, capsys)
        if code:
            return code, err
    return 0, ""


@pytest.mark.slow
@pytest.mark.parametrize("case", list(TABLE_FAULTS))
def test_bad_table_exits_2_naming_file_and_column_and_keeps_outputs(workspace, case, capsys):
    inject, expected = TABLE_FAULTS[case]
    kept = ("release", "build/prepared", "build/model")
    before = {d: tree_digest(workspace / d) for d in kept}
    inject(workspace)
    code, err = run_data_stages(workspace, capsys)
    assert code == 2, err
    lines = err.strip().splitlines()
    assert re.match(r"aumesh (ingest|prepare): error: ", lines[0]) and len(lines) <= 2, err
    for text in expected:
        assert text in err, f"{text!r} not in {err!r}"
    assert "Traceback" not in err
    assert {d: tree_digest(workspace / d) for d in kept} == before


def test_debug_flag_and_env_show_the_traceback(workspace, capsys, monkeypatch):
    all_nan("AU07")(workspace)
    from aumesh.core.errors import TableError

    with pytest.raises(TableError, match="AU07"):
        run_cli(["--debug", "prepare"], workspace, capsys)
    monkeypatch.setenv(cli.DEBUG_ENV, "1")
    with pytest.raises(TableError, match="AU07"):
        run_cli(["prepare"], workspace, capsys)


def test_numbers_as_text_are_converted_only_when_asked_and_give_the_same_frames(workspace, capsys):
    numeric_strings("AU12")(workspace)
    numeric_strings("x_10")(workspace)
    params = yaml.safe_load((workspace / "params.yaml").read_text())
    params["data"]["coerce_numeric"] = True
    params["paths"]["prepared_dir"] = "build/coerced"
    write_params(params, workspace / "params.yaml")
    code, err = run_data_stages(workspace, capsys)
    assert code == 0, err
    for name in ("frames.parquet", "meshes.npy"):
        a, b = workspace / "build/prepared" / name, workspace / "build/coerced" / name
        if name.endswith(".npy"):
            np.testing.assert_array_equal(np.load(a), np.load(b))
        else:
            pd.testing.assert_frame_equal(pd.read_parquet(a), pd.read_parquet(b))


def test_filter_shares_are_reported_in_summary_card_and_mlflow(good_workspace):
    import json

    import mlflow

    card = json.loads((good_workspace / "release/model_card.json").read_text())
    counts = card["data"]["counts"]
    assert counts["dropped_pose_fraction"] == pytest.approx(counts["dropped_pose"] / counts["frames_in"])
    assert (
        counts["videos_dropped_no_frames_left_fraction"]
        == counts["videos_dropped_no_frames_left"] / counts["videos_in"]
    )
    md = (good_workspace / "release/MODEL_CARD.md").read_text()
    assert f"{counts['dropped_pose']:,} frames dropped ({counts['dropped_pose_fraction']:.1%})" in md
    run = mlflow.MlflowClient(tracking_uri=f"sqlite:///{good_workspace / 'mlflow.db'}").get_run(
        card["mlflow"]["run_id"]
    )
    assert run.data.metrics["data.dropped_pose_fraction"] == pytest.approx(counts["dropped_pose_fraction"])
    assert run.data.metrics["data.dropped_alignment_outliers"] == counts["dropped_alignment_outliers"]


# --------------------------------------------------------------------------------------------- config faults
def edit_params(**changes):
    """Set dotted keys of params.yaml (``None`` value with key ``+``: add a key)."""

    def inject(ws):
        params = yaml.safe_load((ws / "params.yaml").read_text())
        for dotted, value in changes.items():
            *head, last = dotted.split("__")
            node = params
            for key in head:
                node = node[key]
            node[last] = value
        (ws / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))

    return inject


CONFIG_FAULTS = {
    "n_components 'ten'": (edit_params(model__n_components="ten"), ["model.n_components='ten'", "an integer"]),
    "n_components 10.5": (edit_params(model__n_components=10.5), ["model.n_components=10.5", "an integer"]),
    "scale 'nope'": (edit_params(model__scale="nope"), ["model.scale='nope'", "true or false"]),
    "old features.pose 'false'": (edit_params(features__pose="false"), ["features.pose", "features=au_pose"]),
    "unknown key": (edit_params(model__n_componets=3), ["model.n_componets", "known keys"]),
    "bad target": (edit_params(preprocess__target="absolut"), ["preprocess.target='absolut'", "'absolute'"]),
    "n_components above features, no clipping": (
        edit_params(model__n_components=1000, model__clip_n_components=False),
        ["model.n_components=1000", "model.clip_n_components=true"],
    ),
    "section not a mapping": (edit_params(model=5), ["'model' must be a mapping"]),
}


@pytest.mark.parametrize("case", list(CONFIG_FAULTS))
def test_bad_config_exits_2_naming_key_before_any_work_or_run(workspace, case, capsys):
    inject, expected = CONFIG_FAULTS[case]
    before = {d: tree_digest(workspace / d) for d in ("release", "build")}
    runs_before = mlflow_runs(workspace)
    inject(workspace)
    for stage in ("prepare", "evaluate", "release"):
        code, err = run_cli([stage], workspace, capsys)
        assert code == 2, err
        assert err.startswith(f"aumesh {stage}: error: params.yaml: ") and len(err.strip().splitlines()) <= 2, err
        for text in expected:
            assert text in err, f"{text!r} not in {err!r}"
    assert {d: tree_digest(workspace / d) for d in ("release", "build")} == before
    pd.testing.assert_frame_equal(mlflow_runs(workspace), runs_before)  # no run was opened


@pytest.mark.parametrize(
    "override,expected",
    [
        ("model.n_components=ten", ["model.n_components='ten'", "an integer"]),
        ("model.scale=maybe", ["model.scale='maybe'", "true or false"]),
        ("model.n_componets=3", ["model.n_componets"]),
        ("features=au_pos", ["features", "au_pos"]),
    ],
)
def test_compose_params_refuses_bad_overrides_and_keeps_params(workspace, override, expected, capsys):
    from conftest import REPO

    before = (workspace / "params.yaml").read_bytes()
    code, err = run_cli(["compose-params", "--config-dir", str(REPO / "conf"), override], workspace, capsys)
    assert code == 2, err
    for text in expected:
        assert text in err, f"{text!r} not in {err!r}"
    assert (workspace / "params.yaml").read_bytes() == before


def test_clipped_n_components_is_said_on_the_console_and_in_mlflow(workspace, capsys, caplog):
    import json

    import mlflow

    edit_params(model__n_components=1000)(workspace)
    code, err = run_cli(["evaluate"], workspace, capsys)
    assert code == 0, err
    assert "model.n_components=1000 clipped to 83" in caplog.text
    run_id = json.loads((workspace / "build/model/tracking.json").read_text())["run_id"]
    run = mlflow.MlflowClient(tracking_uri=f"sqlite:///{workspace / 'mlflow.db'}").get_run(run_id)
    assert run.data.tags["aumesh.n_components_clipped"] == "1000 -> 83 (features=au_pose_interactions)"


# ------------------------------------------------------------------------------ debris and orphaned runs
def test_temporaries_of_dead_processes_are_removed_and_live_ones_kept(tmp_path):
    import socket
    import subprocess
    import sys

    from aumesh.core.io import atomic_directory, remove_stale_temporaries

    host = socket.gethostname()
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)
    # release/ in place: the copy aside is debris of a finished swap (a missing release/ gets it back instead:
    # tests/test_crash_swap.py)
    (tmp_path / "release").mkdir()
    (tmp_path / f".release.tmp-{dead_pid}-{host}-abc").mkdir()
    (tmp_path / f".release.old-{dead_pid}-{host}-x").mkdir()
    (tmp_path / f".metrics.json.tmp-{dead_pid}-{host}-q1.tmp").write_text("{")
    live = tmp_path / f".release.tmp-{os.getpid()}-{host}-def"
    live.mkdir()
    other_host = tmp_path / f".release.tmp-{dead_pid}-elsewhere-ghi"
    other_host.mkdir()
    removed = remove_stale_temporaries(tmp_path / "release") + remove_stale_temporaries(tmp_path / "metrics.json")
    assert sorted(p.name for p in removed) == sorted(
        [
            f".release.tmp-{dead_pid}-{host}-abc",
            f".release.old-{dead_pid}-{host}-x",
            f".metrics.json.tmp-{dead_pid}-{host}-q1.tmp",
        ]
    )
    assert live.exists() and other_host.exists()
    with atomic_directory(tmp_path / "release") as tmp:  # its own temporaries carry this process and host
        assert tmp.name.startswith(f".release.tmp-{os.getpid()}-{host}-")


@pytest.mark.slow
def test_a_run_whose_process_is_gone_is_marked_killed_by_the_next_run(tmp_path, monkeypatch):
    import signal
    import subprocess
    import sys

    import mlflow

    from aumesh.tracking import runs as tracking

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    code = (
        "from aumesh.tracking import runs as tracking; import os, time\n"
        "with tracking.tracked_run({'experiment': 'e'}, 'victim', {'a': 1}) as run:\n"
        "    print(run.run_id, flush=True); time.sleep(600)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env=os.environ)
    victim = proc.stdout.readline().strip()
    client = mlflow.MlflowClient(uri)
    assert client.get_run(victim).info.status == "RUNNING"
    with tracking.tracked_run({"experiment": "e"}, "alive-check", None):  # the victim still lives: untouched
        assert client.get_run(victim).info.status == "RUNNING"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    with tracking.tracked_run({"experiment": "e"}, "next", None) as run:
        pass
    after = client.get_run(victim)
    assert after.info.status == "KILLED" and "ended without closing" in after.data.tags[tracking.ERROR_TAG]
    assert client.get_run(run.run_id).data.tags[tracking.PID_TAG] == str(os.getpid())


# ------------------------------------------------------------------------- interrupted and failed dvc repro
def _stale(ws: Path, stage: str) -> None:
    """Make ``stage`` (and what follows) out of date."""
    params = yaml.safe_load((ws / "params.yaml").read_text())
    if stage == "prepare":
        params["preprocess"]["alignment"]["gpa_tol"] = 1e-9
    elif stage == "evaluate":
        params["model"]["n_components"] = 40
    if stage in ("prepare", "evaluate"):
        (ws / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    else:
        (ws / "promotion.json").write_text('{"promoted": null, "note": "changed"}\n')


def _in_work(ws: Path, stage: str) -> bool:
    """The stage is past its imports, in the middle of its work: its temp output folder exists (prepare, release) or
    its MLflow run is open (evaluate)."""
    import sqlite3

    if stage == "evaluate":
        if not (ws / "mlflow.db").exists():
            return False
        with contextlib.closing(sqlite3.connect(ws / "mlflow.db", timeout=1)) as db:
            try:
                return db.execute("select count(*) from runs where status = 'RUNNING'").fetchone()[0] > 0
            except sqlite3.Error:
                return False
    out = {"prepare": ws / "build", "release": ws}[stage]
    name = {"prepare": "prepared", "release": "release"}[stage]
    return any(out.glob(f".{name}.tmp-*"))


def _interrupt_stage(ws: Path, stage: str, sig: int) -> tuple[int, str]:
    """Start `dvc repro`, wait until ``stage`` is in the middle of its work, send ``sig`` to the whole process
    group (what Ctrl-C in a terminal does; SIGKILL: what `kill -9` of the group or the OOM killer does)."""
    import signal
    import subprocess
    import time

    from test_dvc_pipeline import BIN

    env = dvc_env(ws)
    # a user's terminal delivers Ctrl-C to processes with the default SIGINT action; a test run started in the
    # background by a non-interactive shell (`cmd &`) inherits SIGINT ignored, which `dvc repro` would inherit too
    proc = subprocess.Popen(
        [BIN / "dvc", "repro"],
        cwd=ws,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 900
    sent = False
    while proc.poll() is None and time.monotonic() < deadline:
        if _in_work(ws, stage):
            os.killpg(proc.pid, sig)
            sent = True
            break
        time.sleep(0.02)
    out, _ = proc.communicate(timeout=300)
    assert sent, f"stage {stage} never got to work:\n{out}"
    return proc.returncode, out


def _cmdline(p) -> list[str]:
    import psutil

    try:
        return p.cmdline()
    except psutil.Error:
        return []


def _dvc(ws: Path, *args: str) -> str:
    from test_dvc_pipeline import BIN, _run

    return _run([BIN / "dvc", *args], ws)


@pytest.mark.slow
@pytest.mark.parametrize("signame", ["SIGINT", "SIGKILL"])
@pytest.mark.parametrize("stage", ["prepare", "evaluate", "release"])
def test_interrupted_dvc_repro_keeps_the_release_bit_for_bit(dvc_workspace, tmp_path, stage, signame):
    import signal

    import mlflow

    from aumesh.config import load_params
    from aumesh.stages import common
    from aumesh.tracking import runs as tracking

    ws = tmp_path / "ws"
    shutil.copytree(dvc_workspace, ws, symlinks=True)
    release = tree_digest(ws / "release")
    _stale(ws, stage)
    code, out = _interrupt_stage(ws, stage, getattr(signal, signame))
    assert code != 0, out
    assert tree_digest(ws / "release") == release, out  # the previous release, bit for bit
    status = _dvc(ws, "status")
    assert f"{stage}:" in status, status  # dvc status names what is stale
    cfg = load_params(ws / "params.yaml")
    os.chdir(ws)
    try:
        removed = [o for o in common.stage_outputs(stage, cfg.paths) if not (ws / o).exists()]
        if signame == "SIGINT" and removed:  # the stage said how to get DVC's removed outputs back
            assert f"`dvc checkout {stage}` brings back the last good one" in out, out
        debris = sorted(
            p.name for o in common.stage_outputs(stage, cfg.paths) for p in (ws / o).parent.glob(f".{Path(o).name}.*-*")
        )
        if signame == "SIGINT":
            assert not debris, debris  # cleaned up on the way out
        common.start_stage(stage, cfg)  # what the next run does first
        assert not [
            p for o in common.stage_outputs(stage, cfg.paths) for p in (ws / o).parent.glob(f".{Path(o).name}.*-*")
        ]
        client = mlflow.MlflowClient(f"sqlite:///{ws / 'mlflow.db'}")
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{ws / 'mlflow.db'}")
            with tracking.tracked_run(cfg.to_dict()["tracking"], "next run", None):
                pass
        runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
        assert all(r.info.status in ("FINISHED", "KILLED") for r in runs), [
            (r.info.run_name, r.info.status) for r in runs
        ]
        if stage == "evaluate":
            assert sum(r.info.status == "KILLED" for r in runs) == 1
        if removed:
            _dvc(ws, "checkout", stage)
            assert all((ws / o).exists() for o in common.stage_outputs(stage, cfg.paths)), _dvc(ws, "status")
    finally:
        os.chdir(Path(__file__).parent)


@pytest.mark.slow
@pytest.mark.parametrize("fault", ["bad table", "bad config"])
def test_failed_dvc_repro_keeps_the_release_and_names_the_fault(dvc_workspace, tmp_path, fault):
    import subprocess

    from test_dvc_pipeline import BIN

    ws = tmp_path / "ws"
    shutil.copytree(dvc_workspace, ws, symlinks=True)
    release = tree_digest(ws / "release")
    if fault == "bad table":
        all_nan("AU07")(ws)
        stage, expected = "prepare", ["frames_0000.parquet", "'AU07' is empty", "dvc checkout prepare"]
    else:
        edit_params(model__n_components="ten")(ws)
        stage, expected = "evaluate", ["model.n_components='ten'", "dvc checkout evaluate"]
    env = dvc_env(ws)
    proc = subprocess.run([BIN / "dvc", "repro"], cwd=ws, env=env, capture_output=True, text=True)
    assert proc.returncode != 0
    for text in expected:
        assert text in proc.stdout + proc.stderr, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    assert tree_digest(ws / "release") == release
    assert f"{stage}:" in _dvc(ws, "status")


def test_a_killed_unreaped_child_counts_as_gone():
    """A SIGKILLed stage whose parent died too stays a zombie where nobody reaps it (containers): its pid still
    "exists", but its temporaries and RUNNING run are debris. A live process is not gone; a pid created after the
    temporary was written is a reused pid."""
    import subprocess
    import time

    import psutil

    from aumesh.core.signals import process_gone

    child = subprocess.Popen(["sleep", "30"])
    child.kill()
    deadline = time.monotonic() + 60  # a cap for a kill that never lands, not a time it must keep
    while psutil.Process(child.pid).status() != psutil.STATUS_ZOMBIE and time.monotonic() < deadline:
        time.sleep(0.05)
    try:
        assert psutil.pid_exists(child.pid)  # what the old check asked: the zombie looked alive
        assert process_gone(child.pid, time.time() - 60)
    finally:
        child.wait()
    assert process_gone(child.pid, time.time() - 60)  # reaped: no such process
    me = psutil.Process()
    assert not process_gone(me.pid, me.create_time() + 5)  # live, started before its temporary
    assert process_gone(me.pid, me.create_time() - 60)  # a process newer than the temporary: the pid was reused


# --------------------------------------------------------------- issue 34: damaged files, full disks, hostile text
PREPARED = "build/prepared"


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _flip_byte(path: Path, where: float = 0.5) -> None:
    raw = bytearray(path.read_bytes())
    raw[int(len(raw) * where)] ^= 0x01
    path.write_bytes(bytes(raw))


def _nan_model_intercept(ws: Path) -> None:
    path = ws / "build/model/model.npz"
    arrays = dict(np.load(path))
    arrays["mesh_intercept"] = arrays["mesh_intercept"].copy()
    arrays["mesh_intercept"][5] = np.nan
    np.savez(path, **arrays)


FIX_PREPARE = "dvc repro -f prepare"
DAMAGED_FILES = {
    # the "mmap length is greater than file size" and its kin: one line naming the file and the fix
    "truncated meshes.npy": (
        lambda ws: _truncate(ws / PREPARED / "meshes.npy"),
        "evaluate",
        [f"{PREPARED}/meshes.npy: truncated", "needs", FIX_PREPARE],
    ),
    "truncated neutral_low_au.npy": (
        lambda ws: _truncate(ws / PREPARED / "neutral_low_au.npy"),
        "evaluate",
        [f"{PREPARED}/neutral_low_au.npy: truncated", FIX_PREPARE],
    ),
    "truncated reference.npz": (
        lambda ws: _truncate(ws / PREPARED / "reference.npz"),
        "release",
        [f"{PREPARED}/reference.npz", "truncated or replaced", FIX_PREPARE],
    ),
    # a byte flipped in place (with DVC's hardlinked cache, in the cache too): caught by prepare's checksums
    "one byte flipped in meshes.npy": (
        lambda ws: _flip_byte(ws / PREPARED / "meshes.npy"),
        "evaluate",
        [f"{PREPARED}/meshes.npy: bytes", "xxh3_128 checksum", FIX_PREPARE],
    ),
    "one byte flipped in a file hard-linked into a cache": (
        lambda ws: (os.link(ws / PREPARED / "meshes.npy", ws / "cache-copy"), _flip_byte(ws / PREPARED / "meshes.npy")),
        "evaluate",
        [f"{PREPARED}/meshes.npy: bytes", "hard-linked into DVC's cache", "find .dvc/cache -inum ", FIX_PREPARE],
    ),
    "one byte flipped in frames.parquet": (
        lambda ws: _flip_byte(ws / PREPARED / "frames.parquet", 0.3),
        "evaluate",
        [f"{PREPARED}/frames.parquet: bytes", "checksum", FIX_PREPARE],
    ),
    "one byte flipped in video_ids.npy": (
        lambda ws: _flip_byte(ws / PREPARED / "video_ids.npy", 0.9),
        "evaluate",
        [f"{PREPARED}/video_ids.npy", "checksum", FIX_PREPARE],
    ),
    "summary.json not JSON": (
        lambda ws: (ws / PREPARED / "summary.json").write_text('{"counts": '),
        "evaluate",
        [f"{PREPARED}/summary.json: not readable JSON", FIX_PREPARE],
    ),
    # a release is finite or refused
    "NaN in model.npz's intercept": (
        _nan_model_intercept,
        "release",
        ["build/model/model.npz", "'intercept' has 1 NaN/inf value(s)", "dvc repro -f evaluate"],
    ),
}

#: Cases whose bytes lie in a row group of meshes.npy: refused by evaluate's first pass, before any fit.
REFUSED_BY_THE_FIRST_PASS = {"one byte flipped in meshes.npy", "one byte flipped in a file hard-linked into a cache"}


@pytest.mark.parametrize("case", list(DAMAGED_FILES))
def test_damaged_file_exits_2_naming_it_and_keeps_release(workspace, case, capsys):
    inject, stage, expected = DAMAGED_FILES[case]
    release = tree_digest(workspace / "release")
    runs = mlflow_runs(workspace)
    inject(workspace)
    code, err = run_cli([stage], workspace, capsys)
    assert code == 2, err
    assert err.startswith(f"aumesh {stage}: error: ") and len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err
    for text in expected:
        assert text in err, f"{text!r} not in {err!r}"
    assert tree_digest(workspace / "release") == release
    after = mlflow_runs(workspace)
    if case in REFUSED_BY_THE_FIRST_PASS:  # meshes.npy's rows are verified as pass A reads them: the run opened beside
        new = after[~after.run_id.isin(runs.run_id)]  # it is FAILED, never FINISHED (tests/test_integrity.py)
        assert list(new.status) == ["FAILED"], after
        after = after[after.run_id.isin(runs.run_id)].reset_index(drop=True)
    pd.testing.assert_frame_equal(after, runs)  # refused before a run was opened


def test_truncated_split_layout_npy_in_data_names_it(workspace, capsys):
    """py-feat's split layout (a parquet plus its [N, 478, 3] .npy): a short .npy is one line before any work."""
    shutil.rmtree(workspace / "data")
    write_tables(workspace / "data", SynthSpec(n_frames=400, n_videos=40, seed=3, layout="pyfeat"))
    npy = workspace / "data/frames_0000.npy"
    _truncate(npy)
    release = tree_digest(workspace / "release")
    code, err = run_cli(["ingest"], workspace, capsys)
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    for text in ("data/frames_0000.npy: truncated", "(400, 478, 3)", "dvc checkout data"):
        assert text in err, err
    assert tree_digest(workspace / "release") == release


def _mesh_columns(ws: Path, change) -> None:
    df = _table(ws)
    change(df)
    _save(ws, df)


def _mirror(df: pd.DataFrame) -> None:
    z = [c for c in df.columns if c.startswith("z_")]
    df[z] = -df[z]


def _swap_xy(df: pd.DataFrame) -> None:
    x = [c for c in df.columns if c.startswith("x_")]
    y = ["y_" + c[2:] for c in x]
    df[x + y] = df[y + x].to_numpy()


@pytest.mark.slow
@pytest.mark.parametrize("change", [_mirror, _swap_xy], ids=["z negated", "x and y swapped"])
def test_mirrored_mesh_is_refused_by_prepare_before_any_fit(workspace, change, capsys):
    kept = {d: tree_digest(workspace / d) for d in ("release", PREPARED)}
    runs = mlflow_runs(workspace)
    _mesh_columns(workspace, change)
    code, err = run_data_stages(workspace, capsys)
    assert code == 2, err
    assert err.startswith("aumesh prepare: error: ") and len(err.strip().splitlines()) == 1, err
    for text in (TABLE, "mirrored (400 of 400 frames", "negate one axis"):
        assert text in err, err
    assert {d: tree_digest(workspace / d) for d in kept} == kept
    pd.testing.assert_frame_equal(mlflow_runs(workspace), runs)


def test_handedness_test_agrees_with_the_release_frame():
    """:func:`mirrored` (prepare's early check on a few landmarks) says what ``canonical_frame`` (the release's) says."""
    from scipy.spatial.transform import Rotation

    from aumesh.geometry.face import canonical_template
    from aumesh.geometry.frame import HANDEDNESS_LANDMARKS, canonical_frame, mirrored

    rng = np.random.default_rng(0)
    template = canonical_template()
    for k in range(60):
        mesh = template @ Rotation.random(random_state=k).as_matrix().T * rng.uniform(0.1, 500) + rng.normal(size=3)
        mesh = (mesh, mesh * [1, 1, -1], mesh[:, [1, 0, 2]])[k % 3]
        try:
            canonical_frame(mesh)
            refused = False
        except ValueError:
            refused = True
        assert mirrored(mesh[list(HANDEDNESS_LANDMARKS)][None])[0] == refused == (k % 3 != 0)


@pytest.mark.parametrize("group", ["<img src=x onerror=alert(1)>", "AU12"])
def test_cv_group_must_name_the_video_column(workspace, group, capsys):
    """An unknown cv.group was ignored (and pasted raw into the card); a known column other than the video's cannot
    group this CV. Both: exit 2 before any work, listing the columns."""
    release = tree_digest(workspace / "release")
    runs = mlflow_runs(workspace)
    edit_params(cv__group=group)(workspace)
    for stage in ("prepare", "evaluate", "release"):
        code, err = run_cli([stage], workspace, capsys)
        assert code == 2, err
        assert err.startswith(f"aumesh {stage}: error: cv.group={group!r}") and len(err.strip().splitlines()) == 1, err
        assert "cv.group=video_id" in err
        if group != "AU12":  # the columns that exist, the mesh's 1,434 as a range
            assert "(its columns: " in err and "'video_id'" in err and "'AU01'" in err and "'x_0'" not in err, err
    assert tree_digest(workspace / "release") == release
    pd.testing.assert_frame_equal(mlflow_runs(workspace), runs)


CONFIG_FAULTS["anchor vertex 999"] = (
    edit_params(preprocess__alignment__anchor_indices=[999, 9, 8, 151, 6, 168]),
    ["anchor_indices: [999] name no vertex", "0..477"],
)


# ------------------------------------------------------------------------------------------------ full disks
class _Tmpfs:
    """A tmpfs of ``size`` bytes mounted on ``where`` (its files copied in), or the test is skipped (needs root)."""

    def __init__(self, where: Path, slack: int):
        self.where, self.slack = where, slack

    def __enter__(self):
        import subprocess

        if os.geteuid() != 0 or not shutil.which("mount"):
            pytest.skip("mounting a small tmpfs needs root")
        saved = self.where.with_name(self.where.name + ".saved")
        self.where.rename(saved)
        self.where.mkdir()
        used = sum(p.stat().st_size for p in saved.rglob("*") if p.is_file())
        proc = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={used + self.slack + (64 << 12)}", "tmpfs", self.where],
            capture_output=True,
        )
        if proc.returncode:
            self.where.rmdir()
            saved.rename(self.where)
            pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.decode().strip()}")
        shutil.copytree(saved, self.where, dirs_exist_ok=True, copy_function=shutil.copy2)
        shutil.rmtree(saved)
        return self

    def __exit__(self, *exc):
        import subprocess

        kept = self.where.with_name(self.where.name + ".kept")
        shutil.copytree(self.where, kept, copy_function=shutil.copy2)
        subprocess.run(["umount", self.where], check=True)
        self.where.rmdir()
        kept.rename(self.where)


@pytest.mark.parametrize("stage", ["prepare", "release"])
def test_full_disk_is_one_line_naming_the_folder_and_keeps_outputs(workspace, stage, capsys):
    """A real full device (a small tmpfs): the stage names the folder, what a complete output takes, and that the
    previous one is intact; no temporaries are left."""
    if stage == "release":  # the release folder's parent gets the small device
        (workspace / "out").mkdir()
        (workspace / "release").rename(workspace / "out/release")
        edit_params(paths__release_dir="out/release")(workspace)
    folder = workspace / ("build" if stage == "prepare" else "out")
    out = workspace / (PREPARED if stage == "prepare" else "out/release")
    before = tree_digest(out)
    with _Tmpfs(folder, slack=150_000):
        code, err = run_cli([stage], workspace, capsys)
        debris = sorted(p.name for p in folder.glob(f".{out.name}.*"))
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    name = "build" if stage == "prepare" else "out"
    for text in (
        f"{name}/: no space left on the device while writing {out.relative_to(workspace)}",
        "a complete one takes about",
        f"the previous {out.relative_to(workspace)} is intact",
    ):
        assert text in err, err
    assert not debris, debris
    assert tree_digest(out) == before


def test_full_disk_inside_a_pass_is_one_line(workspace, capsys, monkeypatch):
    """Without root: ENOSPC from the OS call that writes the aligned meshes (pass 3's pwrite, in a worker thread)."""
    import errno

    from aumesh.core import io as aio

    def full(fd, data, offset):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    before = tree_digest(workspace / PREPARED)
    code, err = run_cli(["ingest"], workspace, capsys)
    assert code == 0, err
    monkeypatch.setattr(aio.os, "pwrite", full)
    code, err = run_cli(["prepare"], workspace, capsys)
    assert code == 2, err
    assert err.startswith("aumesh prepare: error: build/: no space left on the device while writing build/prepared")
    assert "the previous build/prepared is intact" in err and len(err.strip().splitlines()) == 1, err
    assert tree_digest(workspace / PREPARED) == before
    assert not list((workspace / "build").glob(".prepared.*"))


# ------------------------------------------------------------------------------------------ hostile text, card
HOSTILE = ("</script><script>alert(1)</script>", "<!--<script>", "<img src=x onerror=alert(1)>")


def _rendered_card(ws: Path) -> tuple[str, str]:
    """MODEL_CARD.md rendered by a CommonMark renderer with raw HTML passed through (the worst case: GitHub sanitizes,
    editors' previews and MLflow's UI may not): the HTML and its text."""
    import html

    from markdown_it import MarkdownIt

    out = MarkdownIt("commonmark", {"html": True}).enable("table").render((ws / "release/MODEL_CARD.md").read_text())
    text = html.unescape(re.sub(r"<[^>]*>", "", out))
    return out, text


# each case runs the release stage (its figures: ~4 s of CPU); the first in the fast suite, the others in the slow one
@pytest.mark.parametrize("hostile", [HOSTILE[0], *(pytest.param(h, marks=pytest.mark.slow) for h in HOSTILE[1:])])
def test_strings_from_promotion_and_config_are_text_in_the_card(workspace, hostile, capsys):
    import json

    (workspace / "promotion.json").write_text(
        json.dumps(
            {
                "promoted": {
                    "run_id": hostile,
                    "parent_run_id": hostile + "p",
                    "criterion": "best " + hostile,
                    "compared": hostile + " | x",
                }
            }
        )
    )
    edit_params(tracking__experiment=hostile)(workspace)
    code, err = run_cli(["release"], workspace, capsys)
    assert code == 0, err
    md = (workspace / "release/MODEL_CARD.md").read_text()
    for raw in ("<script", "<img", "<!--"):
        assert raw not in md, raw
    out, text = _rendered_card(workspace)
    assert not re.search(r"<script\b|<!--|<img[^>]*onerror", out), out  # the figures' own <img> tags stay
    assert "<h2>Provenance</h2>" in out and "<h2>Frame</h2>" in out  # nothing after the strings was swallowed (<!--)
    for shown in (
        f"Promoted run {hostile} of sweep {hostile}p",
        f"Criterion: best {hostile}",
        f"Compared: {hostile} | x",
        f"experiment {hostile}",
    ):
        assert shown in text, (shown, text)


# ------------------------------------------------------------------------------------------- degenerate inputs
def _all_stages(ws: Path, capsys) -> str:
    err_all = ""
    for stage in ("ingest", "prepare", "evaluate", "release"):
        code, err = run_cli([stage], ws, capsys)
        assert code == 0, err
        err_all += err
    return err_all


# each case runs all four stages (~4.5 s of CPU): one AU in the fast suite, the pose columns in the slow one
@pytest.mark.parametrize(
    "columns",
    [("AU07",), pytest.param(("Pitch", "Yaw", "Roll"), marks=pytest.mark.slow)],
    ids=["AU07 always 0", "pose always 0"],
)
@pytest.mark.slow
def test_constant_inputs_are_said_aloud_and_get_zero_coefficients(workspace, columns, capsys, caplog):
    import json

    import mlflow

    _save(workspace, _table(workspace).assign(**{c: 0.0 for c in columns}))
    _all_stages(workspace, capsys)
    listed = ", ".join(f"{c}=0" for c in columns)
    assert f"evaluate: {listed} constant in every one of the" in caplog.text
    card = json.loads((workspace / "release/model_card.json").read_text())
    run = mlflow.MlflowClient(tracking_uri=f"sqlite:///{workspace / 'mlflow.db'}").get_run(card["mlflow"]["run_id"])
    assert run.data.tags["aumesh.constant_inputs"] == listed
    pose = columns[0] == "Pitch"
    assert run.data.tags["aumesh.pose_learned"] == ("false" if pose else "true")
    assert run.data.tags["aumesh.constant_features"] == str(63 if pose else 4)  # AU07 + its 3 pose products
    md = (workspace / "release/MODEL_CARD.md").read_text()
    assert f"**Constant inputs**: {', '.join(f'{c} = 0' for c in columns)} in every training frame" in md
    assert f"= 83 features, of which {63 if pose else 4} have no variance" in md
    assert ("**Pose was not learned**" in md) == pose
    release = np.load(workspace / "release/au_to_mesh_pls.npz")
    rows = release["input_columns"].tolist()
    for c in columns:  # the engine's zero-variance path: exactly 0, as dropping the column would give
        assert not release["coef"][rows.index(c)].any()
    full = release["input_columns_full"].tolist()
    dead = [j for j, name in enumerate(full) if any(c in name.split("*") for c in columns)]
    assert not release["coef_full"][dead].any() and release["coef_full"].any()
    assert np.isfinite(release["coef_full"]).all()


# ------------------------------------------------------------------------------------- finite releases only
@pytest.mark.parametrize("key", ["coef", "coef_full", "intercept"])
def test_load_release_and_predict_refuse_a_non_finite_release(good_workspace, tmp_path, key, capsys):
    from aumesh.model.release_check import ReleaseError, load_release

    arrays = dict(np.load(good_workspace / "release/au_to_mesh_pls.npz"))
    arrays[key] = arrays[key].copy()
    arrays[key].flat[7] = np.nan if key != "coef" else np.inf
    npz = tmp_path / "bad.npz"
    np.savez(npz, **arrays)
    with pytest.raises(ReleaseError, match=rf"{re.escape(str(npz))}: '{key}' has 1 NaN/inf value\(s\)"):
        load_release(npz)
    pd.DataFrame({"AU12": [1.0]}).to_csv(tmp_path / "one.csv", index=False)
    code, err = run_cli(["predict", "one.csv", "--release", str(npz), "--out", "one.npz"], tmp_path, capsys)
    assert code == 2 and f"'{key}' has 1 NaN/inf" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "one.npz").exists()
