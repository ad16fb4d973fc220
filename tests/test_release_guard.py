"""Issue 44: no command writes a user-given path into the release folder (``aumesh animate --out
release/au_to_mesh.glb`` overwrote the release's own rig) unless ``--force``: one line naming the path and the fix."""

from __future__ import annotations

import os

import numpy as np
import pytest

from aumesh import cli
from test_predict_fex import fex_table, write_release, write_table

RIG = b"the release's own rig"


@pytest.fixture
def workspace(tmp_path, monkeypatch):
    """A workspace folder (the current one) with a release folder holding a rig and a model."""
    monkeypatch.chdir(tmp_path)
    release = tmp_path / "release"
    release.mkdir()
    (release / "au_to_mesh.glb").write_bytes(RIG)
    return tmp_path


# Every command that writes a path the user gives, with that path inside release/ (the inputs need not exist: the
# guard runs before anything is read).
COMMANDS = {
    "animate": ["animate", "clip.csv", "--out", "{p}"],
    "predict": ["predict", "clip.csv", "--out", "{p}"],
    "view": ["view", "model.npz", "--out", "{p}"],
    "render": ["render", "model.npz", "--out", "{p}"],
    "synth --out": ["synth", "--frames", "20", "--videos", "2", "--out", "{p}"],
    "synth --truth": ["synth", "--frames", "20", "--videos", "2", "--out", "tables", "--truth", "{p}"],
    "compose-params": ["compose-params", "--out", "{p}"],
    "dvc-plots-template": ["dvc-plots-template", "--out", "{p}"],
}
# The release folder reached directly, through "..", and through a symbolic link: the resolved path decides.
SPELLINGS = ["release/au_to_mesh.glb", "sub/../release/au_to_mesh.glb", "link/au_to_mesh.glb", "release"]


@pytest.mark.parametrize("spelling", SPELLINGS)
@pytest.mark.parametrize("command", list(COMMANDS))
def test_writing_into_the_release_is_refused_in_one_line(workspace, capsys, command, spelling):
    (workspace / "sub").mkdir()
    os.symlink(workspace / "release", workspace / "link")
    before = sorted(p.name for p in (workspace / "release").iterdir())
    argv = [a.format(p=spelling) for a in COMMANDS[command]]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    option = "--truth" if command == "synth --truth" else "--out"
    assert f"{option} {spelling}: inside the release folder {workspace / 'release'}" in err
    assert "Fix: write outside it, or add --force" in err
    assert (workspace / "release" / "au_to_mesh.glb").read_bytes() == RIG  # untouched
    assert sorted(p.name for p in (workspace / "release").iterdir()) == before
    assert not (workspace / "tables").exists()  # synth --truth refused before writing its tables


def test_force_writes_into_the_release_and_other_paths_pass(workspace, capsys):
    release = write_release(workspace)
    table = write_table(fex_table("mp", np.random.default_rng(0)), workspace / "clip.csv")
    # a path beside the release (a name that only starts like it) is not inside it
    assert cli.main(["predict", str(table), "--release", str(release), "--out", "release-copy/m.npz"]) == 0
    assert cli.main(["predict", str(table), "--release", str(release), "--out", "release/m.npz"]) == 2
    assert not (workspace / "release" / "m.npz").exists()
    assert cli.main(["predict", str(table), "--release", str(release), "--out", "release/m.npz", "--force"]) == 0
    with np.load(workspace / "release" / "m.npz") as forced, np.load(workspace / "release-copy" / "m.npz") as beside:
        np.testing.assert_array_equal(forced["meshes"], beside["meshes"])


def test_the_release_folder_is_the_workspaces_paths_release_dir(workspace, capsys):
    """A workspace whose params.yaml moves the release: that folder is guarded, release/ is then an ordinary one."""
    (workspace / "params.yaml").write_text("paths:\n  release_dir: out/model-release\n")
    argv = ["synth", "--frames", "20", "--videos", "2", "--out"]
    assert cli.main([*argv, "out/model-release/tables"]) == 2
    assert f"inside the release folder {workspace / 'out' / 'model-release'}" in capsys.readouterr().err
    assert cli.main([*argv, "release/tables"]) == 0
    assert any((workspace / "release" / "tables").iterdir())
