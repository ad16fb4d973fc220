"""A damaged object in a DVC remote is refused by ``dvc pull`` (the remotes verify what they download), and a damaged
release NPZ that reaches a reader anyway (copied by hand, cut by a full disk) is one line naming the file and the fix,
not zipfile's traceback."""

from __future__ import annotations

import os
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest

from aumesh import cli
from aumesh.core.errors import CorruptFileError
from aumesh.core.io import load_npz
from aumesh.model.release_check import ReleaseError, load_release
from conftest import upright_truth_release

REPO = Path(__file__).resolve().parents[1]


def _member_offset(path: Path, name: str) -> int:
    """Byte offset of member ``name``'s data in a zip (stored, as ``np.savez`` writes): a byte to damage."""
    with zipfile.ZipFile(path) as z:
        info = z.getinfo(name)
    with open(path, "rb") as fh:
        fh.seek(info.header_offset + 26)
        n, m = int.from_bytes(fh.read(2), "little"), int.from_bytes(fh.read(2), "little")
    return info.header_offset + 30 + n + m + 200


def damage(path: Path, how: str) -> None:
    data = bytearray(path.read_bytes())
    if how == "flipped byte":  # a bit rot in the coefficients: zipfile's CRC-32 no longer matches
        data[_member_offset(path, "coef.npy")] ^= 0xFF
    elif how == "truncated":
        data = data[: len(data) // 2]
    elif how == "not a zip":
        data = bytearray(b"<html>404</html>")
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("how", ["flipped byte", "truncated", "not a zip"])
def test_a_damaged_release_is_one_line_naming_the_file_and_the_fix(tmp_path, how, capsys):
    npz = upright_truth_release(tmp_path / "au_to_mesh_pls.npz")
    load_release(npz)  # whole, it loads
    damage(npz, how)
    with pytest.raises(ReleaseError) as err:
        load_release(npz)
    text = str(err.value)
    assert "\n" not in text and text.startswith(f"{npz}: not a release NPZ: corrupt or truncated"), text
    assert "`dvc pull --force release`" in text and "`dvc repro release`" in text
    # a command that reads a release says it in one line, exit 2 (not zipfile's traceback)
    assert cli.main(["view", str(npz), "--out", str(tmp_path / "v.html")]) == 2
    err_lines = capsys.readouterr().err.strip().splitlines()
    assert len(err_lines) == 1 and "Traceback" not in err_lines[0] and str(npz) in err_lines[0], err_lines


def test_a_release_without_a_key_names_it_and_the_fix(tmp_path):
    npz = upright_truth_release(tmp_path / "au_to_mesh_pls.npz")
    with np.load(npz) as z:
        arrays = {k: z[k] for k in z.files if k != "intercept"}
    np.savez(npz, **arrays)
    with pytest.raises(ReleaseError, match=r"missing key 'intercept'.*Fix: `dvc pull --force release`"):
        load_release(npz)


def test_a_damaged_npz_inside_the_pipeline_names_the_file(tmp_path):
    path = tmp_path / "part.npz"
    np.savez(path, a=np.arange(10_000.0), b=np.zeros(3))
    assert [x.shape for x in load_npz(path, ["a", "b"])] == [(10_000,), (3,)]
    with pytest.raises(CorruptFileError, match=r"part\.npz: no array 'c'"):
        load_npz(path, ["a", "c"])
    data = bytearray(path.read_bytes())
    data[2000] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(CorruptFileError, match=r"part\.npz: not a readable \.npz: corrupt or truncated \(BadZipFile"):
        load_npz(path, ["a"])
    with pytest.raises(FileNotFoundError):
        load_npz(tmp_path / "missing.npz", ["a"])


def test_every_remote_of_the_repository_verifies_what_it_downloads():
    from configobj import ConfigObj

    config = ConfigObj(str(REPO / ".dvc" / "config"))
    remotes = {k: v for k, v in config.items() if k.startswith("remote ")}
    assert remotes, "no DVC remote configured"
    assert all(str(v.get("verify")).lower() == "true" for v in remotes.values()), remotes


@pytest.mark.slow
def test_dvc_pull_refuses_a_damaged_object_of_the_remote(tmp_path):
    """The repository's own remote settings (its .dvc/config, the URL pointed at a test remote): a release whose
    object in the remote was damaged is not pulled; with ``verify`` off (the control) it is pulled, damaged, and
    ``load_release`` names it."""
    from test_dvc_pipeline import BIN

    ws, remote = tmp_path / "ws", tmp_path / "remote"
    ws.mkdir()
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}"}

    def run(*args: str, ok: bool = True) -> subprocess.CompletedProcess:
        proc = subprocess.run(args, cwd=ws, env=env, capture_output=True, text=True)
        assert not ok or proc.returncode == 0, proc.stdout + proc.stderr
        return proc

    run("git", "init", "-q")
    run(str(BIN / "dvc"), "init", "-q")
    (ws / ".dvc" / "config").write_text((REPO / ".dvc" / "config").read_text())
    run(str(BIN / "dvc"), "remote", "modify", "demo", "url", str(remote))
    (ws / "release").mkdir()
    npz = upright_truth_release(ws / "release" / "au_to_mesh_pls.npz")
    run(str(BIN / "dvc"), "add", "-q", "release")
    run(str(BIN / "dvc"), "push", "-q")
    digest = __import__("hashlib").md5(npz.read_bytes()).hexdigest()
    obj = remote / "files" / "md5" / digest[:2] / digest[2:]
    obj.chmod(0o644)
    damage(obj, "flipped byte")

    def fresh_pull() -> subprocess.CompletedProcess:
        import shutil

        shutil.rmtree(ws / ".dvc" / "cache", ignore_errors=True)
        shutil.rmtree(ws / "release", ignore_errors=True)
        return run(str(BIN / "dvc"), "pull", ok=False)

    refused = fresh_pull()
    assert refused.returncode != 0, refused.stdout + refused.stderr
    assert not npz.exists()
    run(str(BIN / "dvc"), "remote", "modify", "demo", "verify", "false")
    pulled = fresh_pull()
    assert pulled.returncode == 0 and npz.exists(), pulled.stdout + pulled.stderr  # silently, without verify
    with pytest.raises(ReleaseError, match="corrupt or truncated.*dvc pull --force release"):
        load_release(npz)
