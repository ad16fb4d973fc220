"""A fresh clone, as a user gets it: `make demo` leaves it clean, and the stages run with the project's
interpreter however DVC is started.

Slow (pipeline runs on the demo data): `make test-slow`. Runs in a temporary `git clone` of this checkout's
HEAD (committed code only) with this checkout's venv linked in as the clone's `.venv/`, never in the working tree.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

# `make -o STAMP`: the linked venv and the node tools count as installed (no rebuild, no npm in the test)
MAKE = ["make", "-o", ".venv/.installed", "-o", "node_modules/.package-lock.json"]


def _run(args, cwd: Path, env: dict, timeout: float = 1200.0) -> str:
    proc = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{args} failed ({proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    return proc.stdout + proc.stderr


def test_make_demo_leaves_the_clone_clean_and_stages_run_however_dvc_is_started(fresh_clone):
    ws, env = fresh_clone
    assert subprocess.run(["bash", "-c", "command -v aumesh"], env=env, capture_output=True).returncode != 0, (
        "the venv's bin must not be on PATH for this test"
    )
    out = _run([*MAKE, "demo"], ws, env)
    assert (ws / "release" / "au_to_mesh_pls.npz").exists()
    # the demo remote holds the committed lock's outputs: nothing is rebuilt, nothing changes
    assert "Running stage" not in out, out
    assert _run(["git", "status", "--porcelain"], ws, env) == ""

    out = _run([".venv/bin/dvc", "repro", "-f", "-s", "release"], ws, env)  # not activated
    assert "Running stage 'release'" in out and "command not found" not in out, out
    card = json.loads((ws / "release" / "model_card.json").read_text())
    assert card["provenance"]["dirty"] is False  # a rewritten dvc.lock is DVC's, not an uncommitted change

    out = _run(["bash", "-c", "source .venv/bin/activate && dvc repro -f -s release"], ws, env)  # activated
    assert "Running stage 'release'" in out, out

    _run([".venv/bin/python", "-m", "aumesh", "compose-params", "model.n_components=10"], ws, env)
    out = _run([*MAKE, "repro"], ws, env)
    assert "Running stage 'evaluate'" in out and "Running stage 'release'" in out, out
    assert "n_components: 10" in (ws / "dvc.lock").read_text()
