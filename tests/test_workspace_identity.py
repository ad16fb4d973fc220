"""A clone's id (``aumesh.workspace.id``) survives the remote URL's spelling and a move, not a copy; old runs are found.

Real git repositories in a temporary folder: the remote URL rewritten in each spelling, the clone moved with ``mv``
and copied with ``cp -r``; the ids compared with each other and with the formula of before (SHA-256 of the path and
the URL as written), and a sweep tagged with the old id found by "your latest sweep" in a real SQLite store.
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
from pathlib import Path

import pytest

from aumesh.core import provenance
from aumesh.core import workspace_id as ids


def _git(cwd: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def _clone(path: Path, remote: str) -> Path:
    path.mkdir(parents=True)
    _git(path, "init", "-q")
    _git(path, "remote", "add", "origin", remote)
    return path


def _old_formula(root: Path, remote: str) -> str:
    """What aumesh tagged runs with before (core/provenance.py: SHA-256 of the path and the URL as written)."""
    return hashlib.sha256(f"{root.resolve().as_posix()}\n{remote}".encode()).hexdigest()[:16]


@pytest.mark.parametrize(
    ("spellings", "expected"),
    [
        (["/x/origin.git", "/x/origin.git/", "/x/origin", "file:///x/origin.git", "file:///x/origin/"], "/x/origin"),
        (
            [
                "git@host.example:lab/aumesh.git",
                "ssh://git@host.example/lab/aumesh",
                "ssh://git@host.example:22/lab/aumesh.git",
                "https://host.example/lab/aumesh.git",
                "https://user@HOST.example/lab/aumesh/",
            ],
            "host.example/lab/aumesh",
        ),
    ],
)
def test_every_spelling_of_a_remote_normalises_to_one(spellings, expected):
    assert {ids.normalise_remote_url(s) for s in spellings} == {expected}


def test_different_remotes_stay_different():
    assert ids.normalise_remote_url("ssh://git@host:2222/x") != ids.normalise_remote_url("ssh://git@host/x")
    assert ids.normalise_remote_url("/x/a.git") != ids.normalise_remote_url("/x/b.git")
    assert ids.normalise_remote_url("../origin", Path("/srv/lab/ws")) == "/srv/lab/origin"


def test_the_id_survives_the_remote_spelling_and_a_move_and_a_copy_gets_its_own(tmp_path):
    a = _clone(tmp_path / "a", "/x/origin.git")
    first = provenance.workspace_id(a)
    assert first == provenance.workspace_id(a)  # stored, not redrawn
    assert first != _old_formula(a, "/x/origin.git")
    for spelling in ("file:///x/origin.git", "/x/origin/", "/x/origin"):
        _git(a, "remote", "set-url", "origin", spelling)
        assert provenance.workspace_id(a) == first, spelling
    moved = tmp_path / "moved"
    shutil.move(a, moved)
    assert provenance.workspace_id(moved) == first
    copy = tmp_path / "copy"
    shutil.copytree(moved, copy)
    other = provenance.workspace_id(copy)
    assert other != first
    assert provenance.workspace_id(moved) == first and provenance.workspace_id(copy) == other
    # the ids of before: the old formula at the original path (recorded) and at the path now
    known = provenance.workspace_ids(moved)
    assert known[0] == first
    assert _old_formula(tmp_path / "a", "/x/origin.git") in known
    assert _old_formula(moved, "/x/origin") in known
    assert _old_formula(tmp_path / "a", "/x/origin.git") not in provenance.workspace_ids(copy)


def test_two_worktrees_of_one_repository_have_two_ids(tmp_path):
    main = _clone(tmp_path / "main", "/x/origin.git")
    _git(main, "-c", "user.email=t@e", "-c", "user.name=t", "commit", "-q", "--allow-empty", "-m", "init")
    _git(main, "worktree", "add", "-q", str(tmp_path / "wt"), "-b", "wt")
    assert provenance.workspace_id(main) != provenance.workspace_id(tmp_path / "wt")
    assert provenance.workspace_id(main) == provenance.workspace_id(main)


def test_a_git_folder_that_cannot_be_written_falls_back_to_the_normalised_url(tmp_path, monkeypatch):
    a = _clone(tmp_path / "a", "/x/origin.git")
    monkeypatch.setattr(ids, "_id_file", lambda root: None)
    one = provenance.workspace_id(a)
    _git(a, "remote", "set-url", "origin", "file:///x/origin/")
    assert provenance.workspace_id(a) == one


def test_your_latest_sweep_finds_a_sweep_tagged_with_the_old_id(tmp_path, monkeypatch):
    """A sweep logged before (its tag: the old formula) is still this clone's latest sweep, and a teammate's is not."""
    from aumesh.tracking import queries
    from aumesh.tracking import runs as tracking
    from aumesh.tracking.mlflow_store import WORKSPACE_TAG
    from conftest import new_store

    ws = _clone(tmp_path / "ws", "/x/origin.git")
    (tmp_path / "aumesh-test-store").mkdir()
    store = new_store(tmp_path / "aumesh-test-store" / "mlflow.db")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{store}")
    monkeypatch.chdir(ws)
    mine = tracking.start_parent_run({}, "old sweep")
    tracking.set_run_tags(mine, {WORKSPACE_TAG: _old_formula(ws, "/x/origin.git")})
    tracking.end_run(mine)
    theirs = tracking.start_parent_run({}, "a teammate's sweep")
    tracking.set_run_tags(theirs, {WORKSPACE_TAG: "0123456789abcdef"})
    tracking.end_run(theirs)
    me = queries.current_owner(ws)
    assert queries.latest_parent_run({}, workspace=me["workspaces"]) == mine
    assert queries.latest_parent_run({}, workspace=me["workspace"]) is None  # the new id alone would lose it
