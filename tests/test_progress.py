"""Progress bars on a terminal only, one summary line per stage from the CLI, and stages that run outside the
workspace (as the benchmarks' --workdir)."""

from __future__ import annotations

import fcntl
import os
import pty
import struct
import subprocess
import sys
import termios
import threading

import pytest

from aumesh.config import compose, write_params
from aumesh.synthetic.tables import SynthSpec, write_tables


def _stage(stage: str, ws, tty: bool) -> tuple[str, str]:
    """Run ``python -m aumesh <stage>`` in ``ws``; stderr to a pseudo-terminal or a pipe. Returns (stdout, stderr)."""
    return _run([sys.executable, "-m", "aumesh", stage, "--params", "params.yaml"], tty, ws)


def _run(cmd: list[str], tty: bool, ws=None) -> tuple[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    if not tty:
        proc = subprocess.run(cmd, cwd=ws, env=env, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-3000:]
        return proc.stdout, proc.stderr
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))  # a terminal 120 columns wide
    proc = subprocess.Popen(cmd, cwd=ws, env=env, stdout=subprocess.PIPE, stderr=slave, text=True)
    os.close(slave)
    chunks: list[bytes] = []

    def drain():
        while True:
            try:
                data = os.read(master, 4096)
            except OSError:  # EIO: the child closed the terminal
                return
            if not data:
                return
            chunks.append(data)

    reader = threading.Thread(target=drain)
    reader.start()
    out, _ = proc.communicate(timeout=600)
    reader.join(timeout=30)
    os.close(master)
    err = b"".join(chunks).decode(errors="replace")
    assert proc.returncode == 0, err[-3000:]
    return out, err


@pytest.fixture
def stage_ws(tmp_path, fixed_conf):
    """A stage folder outside any workspace (as `benchmarks/*.py --workdir /elsewhere`): params name an absolute store."""
    if any((d / ".git").exists() or (d / "dvc.yaml").exists() for d in tmp_path.parents):
        pytest.skip("the temporary folder is inside a repository")
    write_tables(tmp_path / "data", SynthSpec(n_frames=300, n_videos=30, seed=5))
    write_params(
        compose([f"tracking.tracking_uri=sqlite:///{tmp_path / 'mlflow.db'}"], config_dir=fixed_conf),
        tmp_path / "params.yaml",
    )
    return tmp_path


@pytest.mark.slow
def test_one_summary_line_per_stage_and_no_noise_in_a_pipe(stage_ws):
    out, err = _stage("ingest", stage_ws, tty=False)
    assert out.count("\n") == 1 and out.startswith("ingest: 300 frames from 300 rows of 1 tables"), out
    assert "INFO" not in err and "it/s]" not in err, err
    out, err = _stage("prepare", stage_ws, tty=False)
    assert out.count("\n") == 1 and out.startswith("prepare: kept ") and "of 300 frames" in out, out
    out, err = _stage("evaluate", stage_ws, tty=False)
    assert out.count("\n") == 1 and out.startswith("evaluate: CV R2 = "), out
    assert "INFO" not in err and "it/s]" not in err, err  # no info logs by default, no progress bars in a pipe


def test_a_bar_on_a_terminal_none_in_a_pipe():
    code = "from aumesh.core import progress\nwith progress.bar(1000, 'statistics pass') as b: b.update(1000)"
    _, err = _run([sys.executable, "-c", code], tty=True)
    assert "statistics pass" in err and "/1.00k" in err, err  # rows counted with SI prefixes
    _, err = _run([sys.executable, "-c", code], tty=False)
    assert err == ""


@pytest.mark.slow  # three stage processes on a pseudo-terminal; the pipe case above runs in the fast suite
def test_the_data_passes_show_a_bar_on_a_terminal(stage_ws):
    """Every Dask pass of ingest, prepare and evaluate is named on a terminal (tqdm's Dask callback over its tasks)."""
    _, err = _stage("ingest", stage_ws, tty=True)
    assert "ingest: check parquet" in err, err[-2000:]
    _, err = _stage("prepare", stage_ws, tty=True)
    for name in ("prepare: read + validate", "prepare: residuals", "prepare: align + write"):
        assert name in err, err[-2000:]
    _, err = _stage("evaluate", stage_ws, tty=True)
    for name in ("evaluate: statistics", "evaluate: errors"):
        assert name in err, err[-2000:]
