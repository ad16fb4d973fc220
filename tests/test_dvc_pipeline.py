"""`dvc repro` on a fresh workspace: the whole pipeline, an up-to-date second run, and retraining on new tables."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from aumesh.config import compose, write_params
from aumesh.synthetic.tables import SynthSpec, write_tables
from conftest import REPO

BIN = Path(sys.executable).parent


def _run(args, cwd, stdout_only=False, **kw):
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}"}
    proc = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, **kw)
    assert proc.returncode == 0, f"{' '.join(map(str, args))} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout if stdout_only else proc.stdout + proc.stderr


@pytest.fixture
def workspace(tmp_path, fixed_conf):
    """A new git + DVC workspace with the repo's pipeline and code, the fixed conf/ (the card's defaults, no
    promotion) composed into params.yaml, and small synthetic tables."""
    ws = tmp_path / "ws"
    ws.mkdir()
    for name in ("dvc.yaml", ".gitignore"):
        shutil.copy(REPO / name, ws / name)
    shutil.copytree(fixed_conf, ws / "conf")
    shutil.copytree(REPO / "validation", ws / "validation")  # evaluate's dep (paths.validation_dir), as in a clone
    write_params(compose(config_dir=ws / "conf"), ws / "params.yaml")
    (ws / "promotion.json").write_text('{"promoted": null}\n')
    shutil.copytree(REPO / "src", ws / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    _run(["git", "init", "-q"], ws)
    _run(["git", "config", "user.email", "t@example.com"], ws)
    _run(["git", "config", "user.name", "test"], ws)
    _run([BIN / "dvc", "init", "-q"], ws)
    shutil.copy(REPO / ".dvc" / "config", ws / ".dvc" / "config")
    shutil.copytree(REPO / ".dvc" / "plots", ws / ".dvc" / "plots")  # the offline plots page .dvc/config names
    _run([BIN / "dvc", "remote", "remove", "demo"], ws)
    write_tables(ws / "data", SynthSpec(n_frames=600, n_videos=60, seed=11))
    _run([BIN / "dvc", "add", "-q", "data"], ws)
    _run(["git", "add", "-A"], ws)
    _run(["git", "commit", "-qm", "init"], ws)
    return ws


def _digest(ws):
    return yaml.safe_load((ws / "data.dvc").read_text())["outs"][0]["md5"]


# slow (make test-slow): three full `dvc repro`s, a `dvc exp run` and two `dvc plots show` (~40 s of CPU, the
# fast suite's heaviest test); the fast suite keeps DVC's own repro/link check below
@pytest.mark.slow
def test_dvc_repro_builds_the_release_then_is_up_to_date_then_follows_params_and_new_tables(workspace):
    ws = workspace
    _run([BIN / "dvc", "repro"], ws)
    m = np.load(ws / "release" / "au_to_mesh_pls.npz", allow_pickle=False)
    assert m["coef"].shape == (23, 1434) and m["intercept"].shape == (1434,)
    card = json.loads((ws / "release" / "model_card.json").read_text())
    assert card["data"]["digest"]["md5"] == _digest(ws)
    assert card["provenance"]["git_commit"] == _run(["git", "rev-parse", "HEAD"], ws).strip()
    assert card["mlflow"]["run_id"] and len(card["cv"]["r2_folds"]) == 3
    assert card["data"]["counts"]["frames_in"] == 600
    assert (ws / "release" / "MODEL_CARD.md").read_text().count("figures/") >= 4
    assert (ws / "release" / "au_to_mesh.glb").read_bytes()[:4] == b"glTF"  # the blendshape rig (tests/test_gltf.py)
    assert "up to date" in _run([BIN / "dvc", "repro"], ws)
    # where runs are logged and where the passes run are not what a stage computes: no stage param, nothing stale
    params_text = (ws / "params.yaml").read_text()
    moved = yaml.safe_load(params_text)
    moved["tracking"]["tracking_uri"] = "http://10.0.0.5:5000"
    moved["compute"].update(scheduler="distributed", address="tcp://10.0.0.5:8786")
    (ws / "params.yaml").write_text(yaml.safe_dump(moved, sort_keys=False))
    status = _run([BIN / "dvc", "status"], ws)  # only the check of params.yaml (stages/check_params.py), which refuses
    assert "check_params:" in status and not any(
        f"{s}:" in status for s in ("ingest", "prepare", "evaluate", "release")
    )
    (ws / "params.yaml").write_text(params_text)
    # bytecode a plain `python` run writes beside the stages' source deps is not part of them (.dvcignore)
    shutil.copy(REPO / ".dvcignore", ws / ".dvcignore")
    (ws / "src" / "aumesh" / "model" / "__pycache__").mkdir(exist_ok=True)
    (ws / "src" / "aumesh" / "model" / "__pycache__" / "pls.cpython-311.pyc").write_bytes(b"bytecode")
    assert "up to date" in _run([BIN / "dvc", "repro"], ws)

    # `dvc plots show` draws the two curves the evaluate stage writes (declared `plots:` in dvc.yaml)
    paths = yaml.safe_load((ws / "params.yaml").read_text())["paths"]
    plots = json.loads(_run([BIN / "dvc", "plots", "show", "--json"], ws, stdout_only=True))["data"]
    err, r2 = plots[paths["error_curve_file"]][0]["content"], plots[paths["r2_curve_file"]][0]["content"]
    assert [float(v["fraction_of_frames"]) for v in err["data"]["values"]][-1] == 1.0
    assert [int(v["n_components"]) for v in r2["data"]["values"]] == list(range(1, 84))
    assert err["encoding"]["x"]["field"] == "vertex_error" and r2["encoding"]["x"]["field"] == "n_components"
    _run([BIN / "dvc", "plots", "show", "-o", "plots_html"], ws)
    html = (ws / "plots_html" / "index.html").read_text()
    assert "Cumulative vertex error" in html and "CV R2 vs n_components" in html

    # `dvc exp run -S` recomposes params.yaml from conf/ (Hydra) and reruns what depends on it
    out = _run([BIN / "dvc", "exp", "run", "-S", "model.n_components=7", "-S", "preprocess.target=within"], ws)
    assert "Stage 'prepare' didn't change" in out
    assert yaml.safe_load((ws / "params.yaml").read_text())["model"]["n_components"] == 7
    metrics = json.loads((ws / paths["metrics_file"]).read_text())
    assert metrics["n_components"] == 7
    assert (
        len(metrics["au_reliability"]) == 20
        and -1 <= metrics["au_reliability_min"] <= metrics["au_reliability_median"] <= 1
    )
    assert json.loads((ws / "release" / "model_card.json").read_text())["config"]["preprocess"]["target"] == "within"
    assert "## AU-field reliability" in (ws / "release" / "MODEL_CARD.md").read_text()
    assert int(np.load(ws / "release" / "au_to_mesh_pls.npz")["n_components"]) == 7

    # the documented retraining path: new tables in the same schema, `dvc add data`, `dvc repro`
    shutil.rmtree(ws / "data")
    write_tables(ws / "data", SynthSpec(n_frames=500, n_videos=50, seed=12))
    _run([BIN / "dvc", "add", "-q", "data"], ws)
    _run([BIN / "dvc", "repro"], ws)
    card2 = json.loads((ws / "release" / "model_card.json").read_text())
    assert card2["data"]["digest"]["md5"] == _digest(ws) != card["data"]["digest"]["md5"]
    assert card2["data"]["counts"]["frames_in"] == 500
    assert not np.array_equal(np.load(ws / "release" / "au_to_mesh_pls.npz")["coef"], m["coef"])


@pytest.mark.slow
def test_dvc_links_a_stage_output_into_its_cache_without_copying_it(tmp_path):
    """The repo's ``cache.type``: DVC moves a new stage output into its cache by a link, the stage's own file
    (``Output.commit`` links only when the first cache type is ``hardlink``; with ``reflink`` first, on a
    filesystem without reflinks, it wrote a copy, 2 GB of prepared meshes at 344k frames, then linked that back)."""
    ws = tmp_path / "ws"
    ws.mkdir()
    _run(["git", "init", "-q"], ws)  # the repo's .dvc/config autostages in git
    _run([BIN / "dvc", "init", "-q"], ws)
    shutil.copy(REPO / ".dvc" / "config", ws / ".dvc" / "config")
    shutil.copytree(REPO / ".dvc" / "plots", ws / ".dvc" / "plots")  # the offline plots page .dvc/config names
    _run([BIN / "dvc", "remote", "remove", "demo"], ws)
    (ws / "make.py").write_text(
        "import os\nos.makedirs('out')\nwith open('out/meshes.bin', 'wb') as f:\n"
        "    f.write(os.urandom(1 << 20))\nprint(os.stat('out/meshes.bin').st_ino, file=open('inode', 'w'))\n"
    )
    _run(
        [BIN / "dvc", "stage", "add", "-q", "-n", "make", "-d", "make.py", "-o", "out", f"{sys.executable} make.py"], ws
    )
    _run([BIN / "dvc", "repro", "-q"], ws)
    written = ws / "out" / "meshes.bin"
    assert written.stat().st_ino == int((ws / "inode").read_text())  # the stage's file itself, not a copy of it
    assert written.stat().st_nlink == 2  # shared with the cache's object


@pytest.mark.slow
def test_pyfeat_csvs_copied_into_data_train_with_dvc_repro_as_the_hand_cleaned_tables(workspace, tmp_path):
    """The README's own-data path: py-feat's CSVs of both detectors copied into data/ unchanged, `dvc add data`,
    `dvc repro`; the release matches the same frames cleaned by hand; a recipe change never re-reads the CSVs."""
    from aumesh.synthetic.pyfeat import write_pyfeat_tables

    ws = workspace
    spec = SynthSpec(n_frames=1200, n_videos=40, seed=21)
    shutil.rmtree(ws / "data")
    made = write_pyfeat_tables(
        ws / "data", spec, detector="mp", fmt="csv", videos_per_file=20, clean_dir=tmp_path / "clean"
    )
    v2 = tmp_path / "v2"  # the second file of videos as Detectorv2 writes it, in normalized units
    write_pyfeat_tables(v2, spec, detector="v2", fmt="csv", videos_per_file=20, normalized=True)
    (ws / "data" / "clip_0001.csv").unlink()
    shutil.copy(v2 / "clip_0001.csv", ws / "data" / "clip_0001_v2.csv")
    _run([BIN / "dvc", "add", "-q", "data"], ws)
    out = _run([BIN / "dvc", "repro"], ws)
    assert "ingest:" in out and f"no face -{made['n_no_face']:,}" in out
    card = json.loads((ws / "release" / "model_card.json").read_text())
    counts = card["data"]["counts"]
    assert counts["rows_in"] == made["n_rows"] and counts["dropped_no_face"] == made["n_no_face"]
    assert counts["dropped_extra_faces"] == made["n_extra_faces"] and counts["frames_in"] == made["n_face_frames"]
    assert counts["rows_converted_from_normalized"] > 0
    md = (ws / "release" / "MODEL_CARD.md").read_text()
    assert "frames without a face (py-feat's no-face rows) dropped" in md and "converted from normalized" in md

    # a change of recipe reruns prepare on the ingested tables, never the CSV ingest
    out = _run([BIN / "dvc", "exp", "run", "-S", "preprocess.alignment.outlier_quantile=0.98"], ws)
    assert "Stage 'ingest' didn't change" in out

    # the same frames cleaned by hand, through the same pipeline: the same model
    r2 = card["cv"]["r2_mean"]
    shutil.rmtree(ws / "data")
    shutil.copytree(tmp_path / "clean", ws / "data")
    _run([BIN / "dvc", "add", "-q", "data"], ws)
    _run([BIN / "dvc", "exp", "run", "-S", "preprocess.alignment.outlier_quantile=0.99"], ws)
    clean = json.loads((ws / "release" / "model_card.json").read_text())
    assert clean["data"]["counts"]["frames_in"] == made["n_face_frames"]
    assert abs(clean["cv"]["r2_mean"] - r2) < 0.01
