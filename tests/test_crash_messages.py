"""Write and read failures that used to point nowhere, each one line naming the path and the fix: a read-only
workspace or output folder, a Fortran-ordered ``.npy``, a full disk inside a pass (the OS names no file), and the
``df`` hint naming the mount of the folder that failed (``build/`` on another device than the workspace)."""

from __future__ import annotations

import errno
import os
import subprocess

import numpy as np
import pytest

from aumesh.core import io as aio
from aumesh.core.errors import NotWritableError
from aumesh.core.paths import mount_of
from test_faults import PREPARED, _Tmpfs, run_cli


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


class _ReadOnly(_Tmpfs):
    """``where`` on its own tmpfs (its files copied in), remounted read-only: EROFS, which root gets too."""

    def __enter__(self):
        super().__enter__()
        subprocess.run(["mount", "-o", "remount,ro", self.where], check=True)
        return self

    def __exit__(self, *exc):
        subprocess.run(["mount", "-o", "remount,rw", self.where], check=True)
        super().__exit__(*exc)


class _LazyTmpfs(_Tmpfs):
    """:class:`_Tmpfs` unmounted lazily: this process keeps memory maps of ``build/prepared`` (the prepared arrays'
    cache) past the failed run."""

    def __exit__(self, *exc):
        import shutil

        kept = self.where.with_name(self.where.name + ".kept")
        shutil.copytree(self.where, kept, copy_function=shutil.copy2)
        subprocess.run(["umount", "-l", self.where], check=True)
        self.where.rmdir()
        kept.rename(self.where)


def test_a_read_only_output_folder_is_one_line_naming_it(workspace, capsys):
    before = sorted(p.name for p in (workspace / "release").iterdir())
    with _ReadOnly(workspace / "release", slack=0):
        # --force: past the guard against writing into release/ (tests/test_release_guard.py), to the write itself
        code, err = run_cli(
            ["view", "release/au_to_mesh_pls.npz", "--out", "release/v.html", "--force"], workspace, capsys
        )
    assert code == 2
    line = _one_line(err)
    assert line.startswith("aumesh view: error: release/: cannot write release/v.html there"), line
    assert "read-only filesystem" in line and "Fix: make release/ writable" in line
    assert sorted(p.name for p in (workspace / "release").iterdir()) == before


def test_a_read_only_workspace_stops_the_stage_with_one_line(workspace, capsys):
    with _ReadOnly(workspace / "build", slack=0):
        code, err = run_cli(["prepare"], workspace, capsys)
    assert code == 2
    line = _one_line(err)
    assert line.startswith("aumesh prepare: error: build/: cannot write build/prepared there"), line


def test_not_writable_names_the_folder_without_root(tmp_path, monkeypatch):
    """The same line where a mount is not possible: EACCES from the temporary file's creation."""

    def denied(*args, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "x"))

    monkeypatch.setattr(aio.tempfile, "mkstemp", denied)
    with pytest.raises(NotWritableError, match=r"cannot write .*params\.yaml there \(permission denied"):
        aio.atomic_write_text(tmp_path / "params.yaml", "x")
    assert isinstance(NotWritableError(errno.EACCES, "m"), PermissionError)


def test_a_fortran_ordered_prepared_array_is_one_line_with_the_fix(workspace, capsys):
    meshes = workspace / PREPARED / "meshes.npy"
    a = np.load(meshes)
    np.save(meshes, np.asfortranarray(a))
    with open(meshes, "rb") as fh:
        np.lib.format.read_magic(fh)
        assert np.lib.format.read_array_header_1_0(fh)[1]  # fortran_order: True
    code, err = run_cli(["evaluate"], workspace, capsys)
    assert code == 2
    line = _one_line(err)
    assert (
        f"{PREPARED}/meshes.npy: saved in Fortran order" in line and "np.save(path, np.ascontiguousarray(a))" in line
    ), line
    np.save(meshes, np.ascontiguousarray(np.load(meshes)))  # the fix, as the line says it
    assert aio.check_npy(meshes, "")[2] == a.shape


def test_a_full_disk_inside_a_pass_names_the_file_and_the_mount_of_build(workspace, capsys, monkeypatch):
    """build/ on its own device (a tmpfs), the OS call that fails names no file (pwrite): the line names the file,
    its folder and ``df`` of that folder's mount, not of the workspace's."""

    def full(fd, data, offset):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with _LazyTmpfs(workspace / "build", slack=10_000_000):
        monkeypatch.setattr(aio.os, "pwrite", full)
        code, err = run_cli(["evaluate"], workspace, capsys)
        monkeypatch.undo()
        mount = mount_of(workspace / "build")

    assert code == 2
    line = _one_line(err)
    assert mount == str(workspace / "build") != mount_of(workspace)
    assert "no space left on the device while writing build/" in line, line
    assert f"the filesystem mounted at {mount}" in line and "`df -h build/" in line, line


def test_an_unnamed_full_disk_names_the_mounts_to_look_at(workspace, capsys, monkeypatch):
    """An ENOSPC that reaches the command with no file name (outside aumesh's writers): the workspace's and the
    temporary folder's mounts, not just ``df -h .``."""
    from aumesh.cli import stages

    def fails(args):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(stages, "_cmd_release", fails)
    code, err = run_cli(["release"], workspace, capsys)
    assert code == 2
    line = _one_line(err)
    assert f"the workspace is on {mount_of(workspace)}" in line and "the temporary folder" in line, line
