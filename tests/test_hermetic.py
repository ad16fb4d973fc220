"""Tests compose a fixed configuration: a user's `aumesh promote` (conf/experiment/promoted.yaml + a
recomposed params.yaml) must not change what the suite tests."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

from aumesh import config
from aumesh.experiments import promoted_config
from conftest import REPO

# tests that read the configuration and fail if it is not the card's (n_components=83 is OLS on 83 features)
CONFIG_SENSITIVE = [
    "tests/test_pipeline.py::test_full_rank_final_fit_is_ordinary_least_squares",
    "tests/test_config.py",
]


@pytest.mark.slow  # a second pytest in a subprocess, which builds the 3,000-frame recovery set again
def test_suite_passes_in_a_checkout_with_a_promoted_experiment(tmp_path):
    repo = tmp_path / "repo"
    repo.mkdir()
    for name in ("pyproject.toml", "dvc.yaml", "promotion.json"):
        shutil.copy(REPO / name, repo / name)
    for name in ("conf", "tests"):
        shutil.copytree(REPO / name, repo / name, ignore=shutil.ignore_patterns("__pycache__", "promoted.yaml"))
    # what `aumesh promote` leaves behind: a promoted run with another design and n_components, params.yaml recomposed
    (repo / "conf" / "experiment").mkdir(exist_ok=True)
    (repo / "conf" / "experiment" / "promoted.yaml").write_text(
        promoted_config.experiment_yaml({"features.name": "au", "model.n_components": 19})
    )
    config.write_params(config.compose(config_dir=repo / "conf"), repo / "params.yaml")
    assert config.load_params(repo / "params.yaml").model.n_components == 19  # the promotion is in effect

    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *CONFIG_SENSITIVE],
        cwd=repo,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
