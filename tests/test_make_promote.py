"""`make promote` goes through the refusal that protects a newer evaluate run (it passed `--latest`, which skips it).

The repository's Makefile run for real (`make -f Makefile promote`, its venv and stamp pointed at this checkout's) in a
promotion workspace holding a sweep and, after it, an evaluate run of this clone on another configuration: the
refusal's line, a failing exit, nothing written; `aumesh promote --latest`, the explicit way past it, still promotes.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from aumesh import config
from aumesh.tracking import runs as tracking
from test_promote import _log_fake_sweep

REPO = Path(__file__).resolve().parents[1]


def _make(ws: Path, target: str) -> subprocess.CompletedProcess:
    """``make <target>`` of the repository's Makefile in ``ws``, its venv this interpreter's (stamp up to date)."""
    for name in ("requirements.lock", "pyproject.toml"):
        (ws / name).touch()
    stamp = ws / "installed.stamp"
    stamp.touch()
    os.utime(stamp, (stamp.stat().st_mtime + 10, stamp.stat().st_mtime + 10))  # newer than its prerequisites
    venv = Path(sys.executable).parent.parent
    return subprocess.run(
        ["make", "-s", "-f", str(REPO / "Makefile"), target, f"VENV={venv}", f"STAMP={stamp}"],
        cwd=ws,
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.mark.slow
def test_make_promote_refuses_to_overrule_a_newer_evaluate_run(conf_ws, tmp_path):
    sweep, _ = _log_fake_sweep(
        tmp_path, conf_ws / "conf", [({"model.n_components": 5}, {"r2_mean": 0.7, "n_components": 5.0}, "FINISHED")]
    )
    pipeline = config.compose(["model.n_components=9"], config_dir=conf_ws / "conf")
    with tracking.tracked_run({}, "evaluate after the sweep", pipeline, tags={"aumesh.stage": "evaluate"}):
        pass
    before = (conf_ws / "promotion.json").read_text()
    proc = _make(conf_ws, "promote")
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0, out
    refusal = [line for line in out.splitlines() if line.startswith("aumesh promote: error: sweep ")]
    assert len(refusal) == 1 and "would overrule it" in refusal[0], out
    assert "model.n_components=9 there, 5 in the sweep's best run" in refusal[0]
    assert (conf_ws / "promotion.json").read_text() == before
    assert not (conf_ws / "conf" / "experiment" / "promoted.yaml").exists()
    runs = _make(conf_ws, "runs")
    assert runs.returncode == 0 and f"sweep {sweep}" in runs.stdout, runs.stdout + runs.stderr
