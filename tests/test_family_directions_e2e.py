"""End to end (issue 46, item 4 / contract 4): a Detectorv2 table whose emotion columns are permuted goes through
ingest -> prepare -> evaluate -> release_family and the release is refused with the permutation named (exit 2, one
line); the same tables correctly labelled are released.

The tables are :func:`aumesh.synthetic.pyfeat.write_pyfeat_tables`' Detectorv2 CSVs with the family truth (each
emotion moves the mesh by its EMFACS AU fields, :mod:`aumesh.synthetic.family_truth`); the permuted copy has the
values of ``Happy`` and ``Surprise`` swapped under their names, what a detector writing its columns in the wrong order
gives. Slow: the four stages on a few hundred frames.
"""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from aumesh.synthetic.pyfeat import write_pyfeat_tables
from aumesh.synthetic.tables import SynthSpec
from conftest import default_config, new_store

SPEC = SynthSpec(n_frames=600, n_videos=12, seed=3)


@pytest.fixture(scope="module")
def v2_tables(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("v2_families")
    write_pyfeat_tables(folder, SPEC, detector="v2", family_truth=True, videos_per_file=4)
    return folder


def _workspace(root: Path, tables: Path, swap: tuple[str, str] | None) -> Path:
    from aumesh.config import write_params

    ws = root / "ws"
    (ws / "data").mkdir(parents=True)
    for f in sorted(tables.glob("*.csv")):
        df = pd.read_csv(f)
        if swap:
            a, b = swap
            df[[a, b]] = df[[b, a]].to_numpy()
        df.to_csv(ws / "data" / f.name, index=False)
    write_params(default_config().to_dict(), ws / "params.yaml")
    return ws


@pytest.mark.slow
@pytest.mark.parametrize("swap", [None, ("Happy", "Surprise")], ids=["correct", "happy-surprise-swapped"])
def test_a_permuted_emotion_table_fails_the_family_release_naming_the_swap(
    tmp_path, v2_tables, monkeypatch, capsys, swap
):
    from aumesh import cli

    ws = _workspace(tmp_path, v2_tables, swap)
    monkeypatch.chdir(ws)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{new_store(ws / 'mlflow.db')}")
    for stage in ("ingest", "prepare", "evaluate"):
        assert cli.main([stage]) == 0, capsys.readouterr().err
    capsys.readouterr()
    code = cli.main(["release_family", "emotions"])
    err = capsys.readouterr().err
    if swap is None:
        assert code == 0, err
        report = json.loads((ws / "releases" / "emotions" / "emotions_directions.json").read_text())
        assert report["verdict"] != "fail", report["message"]
        assert report["summary"]["happiness"] == "pass" and report["summary"]["surprise"] == "pass"
        # the blendshapes of the same tables: released too (their shapes move the way their names say)
        assert cli.main(["release_family", "blendshapes"]) == 0, capsys.readouterr().err
        report = json.loads((ws / "releases" / "blendshapes" / "blendshapes_directions.json").read_text())
        assert report["verdict"] != "fail", report["message"]
        assert not [n for n, v in report["summary"].items() if v == "fail"]
        return
    assert code == 2
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert "emotion columns labelled happiness and surprise look swapped" in lines[0]
    assert "'happiness' moves like surprise, 'surprise' moves like happiness" in lines[0]
    assert "emotion_to_mesh_pls.npz" in lines[0] and "Fix: check the detector's column names and order" in lines[0]
    assert not (ws / "releases" / "emotions" / "emotion_to_mesh_pls.npz").exists()  # nothing released
