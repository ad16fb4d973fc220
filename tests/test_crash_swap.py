"""A folder swapped in by ``atomic_directory`` (release/, build/model, ...) survives a real SIGKILL at any point of the
swap: after the next start it is the previous folder or the new one, never absent, and no temporary is left.

Each case runs the swap in a child process that kills itself (SIGKILL: no handler, no ``finally``) at one point:
right before or right after the atomic exchange (``renameat2(RENAME_EXCHANGE)``), and, with the exchange made to
fail as on a filesystem without it, between the fallback's two renames."""

from __future__ import annotations

import logging
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from aumesh.core import io, swap

CHILD = textwrap.dedent(
    """
    import os, signal, sys
    from pathlib import Path
    from aumesh.core import io, swap

    target, when = Path(sys.argv[1]), sys.argv[2]
    real_exchange, real_replace = swap.exchange, os.replace

    def die():
        os.kill(os.getpid(), signal.SIGKILL)

    def exchange(a, b):
        if when == "before exchange":
            die()
        if when.startswith("fallback"):
            return False  # as EINVAL from a filesystem without RENAME_EXCHANGE
        done = real_exchange(a, b)
        assert done, "this filesystem has no RENAME_EXCHANGE"
        if when == "after exchange":
            die()
        return done

    def replace(src, dst):
        real_replace(src, dst)
        if when == "fallback between renames" and Path(src) == target:  # the previous copy is aside, no target
            die()

    swap.exchange = exchange
    io.os.replace = replace
    with io.atomic_directory(target) as tmp:
        (tmp / "card.md").write_text("new")
    """
)


def _kill_during_swap(target: Path, when: str) -> int:
    proc = subprocess.run([sys.executable, "-c", CHILD, str(target), when], capture_output=True, text=True)
    return proc.returncode


@pytest.fixture
def release(tmp_path) -> Path:
    target = tmp_path / "release"
    target.mkdir()
    (target / "card.md").write_text("previous")
    return target


def _exchange_supported(where: Path) -> bool:
    (where / "a").mkdir()
    (where / "b").mkdir()
    try:
        return swap.exchange(where / "a", where / "b")
    finally:
        (where / "a").rmdir()
        (where / "b").rmdir()


@pytest.mark.parametrize(
    ("when", "expected"),
    [("before exchange", "previous"), ("after exchange", "new"), ("fallback between renames", "previous")],
)
def test_a_kill_during_the_swap_leaves_the_old_or_the_new_folder_after_the_next_start(release, when, expected, caplog):
    if not when.startswith("fallback") and not _exchange_supported(release.parent):
        pytest.skip("no RENAME_EXCHANGE on this filesystem (the fallback case covers it)")
    assert _kill_during_swap(release, when) == -9  # really killed, at that point
    if when == "fallback between renames":  # the window the exchange closes: no release/, the previous copy aside
        assert not release.exists()
        assert sorted(p.name.split("-")[0] for p in release.parent.iterdir()) == [".release.old", ".release.tmp"]
    with caplog.at_level(logging.WARNING, logger="aumesh.core.io"):
        io.remove_stale_temporaries(release)  # what every stage's start does (aumesh.stages.common.start_stage)
    assert (release / "card.md").read_text() == expected
    assert sorted(p.name for p in release.parent.iterdir()) == ["release"]  # no temporary left
    restored = [r.getMessage() for r in caplog.records if "restored the previous copy" in r.getMessage()]
    assert len(restored) == (1 if when == "fallback between renames" else 0), restored
    if restored:
        assert restored[0].startswith(f"{release} was missing")


def test_the_exchange_swaps_in_place_and_the_fallback_renames(release, monkeypatch):
    """Both paths give the same result in-process; the fallback is taken when the exchange is not available."""
    with io.atomic_directory(release) as tmp:
        (tmp / "card.md").write_text("new")
    assert (release / "card.md").read_text() == "new"
    monkeypatch.setattr(swap, "exchange", lambda a, b: False)
    with io.atomic_directory(release) as tmp:
        (tmp / "card.md").write_text("newer")
    assert (release / "card.md").read_text() == "newer"
    assert sorted(p.name for p in release.parent.iterdir()) == ["release"]


def test_exchange_reports_unsupported_and_raises_other_errors(tmp_path):
    (tmp_path / "a").mkdir()
    with pytest.raises(OSError) as err:  # ENOENT is an error, not "unsupported"
        swap.exchange(tmp_path / "a", tmp_path / "missing")
    assert err.value.errno == 2 and "missing" in str(err.value)


def test_a_live_process_s_copy_aside_is_not_restored(tmp_path):
    """A concurrent run between its renames (its process alive) is not raced: nothing is moved."""
    import os
    import socket

    aside = tmp_path / f".release.old-{os.getpid()}-{socket.gethostname()}-x"
    aside.mkdir()
    assert io.restore_previous(tmp_path / "release") is None
    assert aside.exists() and not (tmp_path / "release").exists()
