"""Issue 46: the families are comparable in `dvc exp show`: metrics/families.json's keys beside metrics/metrics.json's.

A tiny git + DVC workspace (as tests/test_dvc_pipeline.py's) on synthetic tables with the blendshape and emotion
families (`write_tables(..., families=family_truth.family_source(spec))`): `dvc repro evaluate` committed as the baseline, then a real
`dvc exp run evaluate -S families.emotions.features=emotions_pose`. `dvc exp show --json` lists, for the baseline and
the experiment, every family's metrics under metrics/families.json with metrics/metrics.json's keys (its CV keys at
least); the
experiment's values are those of the file it wrote (the same numbers by another route), only the emotions model's
changed (the AU model and the blendshapes model are fitted as before), and its swept parameter is in its row.

Slow (two evaluate runs in DVC): `make test-slow`. Skipped when the evaluate stage does not declare
metrics/families.json (before the evaluate part of issue 46 is merged).
"""

from __future__ import annotations

import inspect
import json
import shutil

import pytest
import yaml

from aumesh.config import compose, write_params
from aumesh.synthetic import family_truth
from aumesh.synthetic.tables import SynthSpec, write_tables
from conftest import REPO
from test_dvc_pipeline import BIN, _run

pytestmark = pytest.mark.slow

PATHS = yaml.safe_load((REPO / "conf" / "paths" / "default.yaml").read_text())
FAMILIES_METRICS = PATHS.get("families_metrics_file", "metrics/families.json")
METRICS = PATHS["metrics_file"]
# the CV keys every model's metrics have (what `aumesh runs` and promotion rank by)
CV_KEYS = {"r2_mean", "r2_std", "r2_displacement_mean", "mae_mean", "n_components"}


def _declared() -> bool:
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    outs = [next(iter(m)) if isinstance(m, dict) else m for m in stages["evaluate"].get("metrics", [])]
    return "${paths.families_metrics_file}" in outs and "families" in inspect.signature(write_tables).parameters


@pytest.fixture
def family_workspace(tmp_path, fixed_conf):
    if not _declared():
        pytest.skip("the evaluate stage does not write metrics/families.json here (issue 46's evaluate part)")
    ws = tmp_path / "ws"
    ws.mkdir()
    for name in ("dvc.yaml", ".gitignore"):
        shutil.copy(REPO / name, ws / name)
    shutil.copytree(fixed_conf, ws / "conf")
    shutil.copytree(REPO / "validation", ws / "validation")
    write_params(compose(config_dir=ws / "conf"), ws / "params.yaml")
    (ws / "promotion.json").write_text('{"promoted": null}\n')
    shutil.copytree(REPO / "src", ws / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    _run(["git", "init", "-q"], ws)
    _run(["git", "config", "user.email", "t@example.com"], ws)
    _run(["git", "config", "user.name", "test"], ws)
    _run([BIN / "dvc", "init", "-q"], ws)
    shutil.copy(REPO / ".dvc" / "config", ws / ".dvc" / "config")
    _run([BIN / "dvc", "remote", "remove", "demo"], ws)
    spec = SynthSpec(n_frames=600, n_videos=60, seed=11)
    write_tables(ws / "data", spec, families=family_truth.family_source(spec))
    _run([BIN / "dvc", "add", "-q", "data"], ws)
    _run(["git", "add", "-A"], ws)
    _run(["git", "commit", "-qm", "init"], ws)
    return ws


def _rows(shown: list, head: str) -> dict[str, dict]:
    """``{"baseline" | experiment name: {"params", "metrics", "families"}}`` of `dvc exp show --json`."""
    rows = {}
    for commit in shown:
        nodes = [("baseline" if commit["rev"] == head else commit["rev"], commit)]
        nodes += [(exp["name"], exp["revs"][0]) for exp in commit.get("experiments") or []]
        for name, node in nodes:
            data = node.get("data") or {}
            metrics = data.get("metrics") or {}
            rows[name] = {
                "params": data["params"]["params.yaml"]["data"],
                "metrics": (metrics.get(METRICS) or {}).get("data"),
                "families": (metrics.get(FAMILIES_METRICS) or {}).get("data"),
            }
    return rows


def test_exp_show_lists_each_familys_metrics_beside_the_au_models(family_workspace):
    ws = family_workspace
    _run([BIN / "dvc", "repro", "evaluate"], ws)
    _run(["git", "add", "-A"], ws)
    _run(["git", "commit", "-qm", "baseline"], ws)
    head = _run(["git", "rev-parse", "HEAD"], ws, stdout_only=True).strip()
    _run([BIN / "dvc", "exp", "run", "evaluate", "-S", "families.emotions.features=emotions_pose"], ws)
    written = json.loads((ws / FAMILIES_METRICS).read_text())  # the experiment's own file (dvc exp run leaves it)

    rows = _rows(json.loads(_run([BIN / "dvc", "exp", "show", "--json"], ws, stdout_only=True)), head)
    (name,) = [n for n in rows if n not in ("baseline", "workspace")]
    base, exp = rows["baseline"], rows[name]
    assert base["params"]["families"]["emotions"]["features"] == "emotions_pose_interactions"
    assert exp["params"]["families"]["emotions"]["features"] == "emotions_pose"
    for row in (base, exp):
        assert set(row["families"]) == {"blendshapes", "emotions"}
        for family in ("blendshapes", "emotions"):  # the AU model's keys (less its AU-only ones: reliability, ...)
            assert CV_KEYS <= set(row["families"][family]) <= set(row["metrics"]), family
    # the same numbers as the file (DVC shows scalars: the per-fold lists are left out of its table)
    assert exp["families"] == {
        f: {k: v for k, v in m.items() if not isinstance(v, (list, dict))} for f, m in written.items()
    }
    assert exp["metrics"] == base["metrics"]  # the AU model: fitted as before
    assert exp["families"]["blendshapes"] == base["families"]["blendshapes"]
    assert exp["families"]["emotions"]["r2_mean"] != base["families"]["emotions"]["r2_mean"]
    # the table a user reads: the families' columns beside the AU model's
    header = _run([BIN / "dvc", "exp", "show", "--csv"], ws, stdout_only=True).splitlines()[0].split(",")
    assert "r2_mean" in header and "emotions.r2_mean" in header and "blendshapes.r2_mean" in header, header
