"""`aumesh --version` and `aumesh info` print what the installed package metadata says."""

from __future__ import annotations

import os
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest

import aumesh
from aumesh import cli

SRC = Path(__file__).resolve().parents[1] / "src"


def _aumesh(*argv: str) -> subprocess.CompletedProcess:
    """The command as a user runs it (a fresh interpreter: nothing imported beforehand)."""
    env = dict(os.environ, PYTHONPATH=f"{SRC}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    return subprocess.run([sys.executable, "-m", "aumesh", *argv], capture_output=True, text=True, env=env, timeout=60)


def test_version_is_the_package_metadata():
    out = _aumesh("--version")
    assert out.returncode == 0, out.stderr
    assert out.stdout == f"aumesh {metadata.version('aumesh')}\n"
    assert metadata.version("aumesh") == aumesh.__version__  # pyproject.toml and the module agree


@pytest.mark.parametrize("argv", [["--version", "--verbose"], ["-v", "--version"], ["info"]])
def test_verbose_version_lists_the_libraries(argv):
    out = _aumesh(*argv)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert lines[0] == f"aumesh {metadata.version('aumesh')}"
    listed = dict(line.split() for line in lines[1:])
    for dist in ("dvc", "mlflow", "hydra-core", "dask", "numpy"):
        assert listed[dist] == metadata.version(dist), dist
    assert listed["python"] == ".".join(map(str, sys.version_info[:3]))


def test_a_command_is_still_required(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main([])
    assert exc.value.code == 2
    assert "a COMMAND is required" in capsys.readouterr().err
