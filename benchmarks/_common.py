"""Shared helpers for the pipeline benchmarks: cached synthetic data, params, per-stage measurement.

Each stage runs as its own subprocess (``python -m aumesh prepare|evaluate|release --params FILE``).
Wall time is measured around the subprocess; CPU time and peak RSS are the stage process's own
``ru_utime + ru_stime`` and ``ru_maxrss`` (the kernel's high-water mark of resident memory of that
process, file-backed pages of memory maps included), as ``/usr/bin/time`` reports them, plus a sampled
peak of the RSS summed over the process tree (psutil, every 50 ms) as a cross-check.

Not ``os.wait4`` in this process: Linux starts a child's ``ru_maxrss`` at its parent's high-water mark
(the forked copy of the parent's memory counts until ``exec``), so every stage would report at least
what the benchmark itself once held (~650 MiB after a read floor). ``/usr/bin/time`` is a small process.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# As dvc.yaml runs the stages; and the installed console script imports its entry point from the installed tree,
# which another source tree (--baseline-src, by PYTHONPATH) need not have (aumesh.cli.run is newer than some).
AUMESH = [sys.executable, "-m", "aumesh"]
DEFAULT_OUT = REPO / "benchmarks" / "out"
FRAMES_PER_VIDEO = 344_418 / 9_978  # CelebV-HQ scale: ~34.5 frames per video
#: ``ingest`` first: a source tree without it (before the ingest stage) runs the other three and reports ingest as 0 s.
STAGES = ("ingest", "prepare", "evaluate", "release")
#: What ``dvc repro`` deletes before it runs a stage (its outputs, as :func:`compose_params` names them; ``release/`` is
#: ``persist: true``, kept). A run deletes them too before each timed stage, so the second and later runs do not time
#: the deletion of the previous run's 2 GB of prepared meshes inside ``prepare`` (1.1-1.3 s on a disk mounted with
#: online discard), which neither the first run nor a stage under DVC pays.
DVC_REMOVED_OUTPUTS = {"ingest": ("ingested",), "prepare": ("prepared",), "evaluate": ("model",)}


def has_stage(stage: str, env: dict | None) -> bool:
    """Whether the source tree ``env`` runs (its PYTHONPATH's first entry, else this checkout) has ``stage``."""
    src = (env or {}).get("PYTHONPATH", "").split(os.pathsep)[0] or str(REPO / "src")
    return (Path(src) / "aumesh" / "pipeline" / f"{stage}.py").exists() or stage != "ingest"


def videos_for(n_frames: int) -> int:
    return max(1, round(n_frames / FRAMES_PER_VIDEO))


@dataclass
class Measurement:
    stage: str
    wall_s: float
    maxrss_mib: float  # ru_maxrss of the stage process (/usr/bin/time)
    tree_rss_mib: float  # sampled peak of the summed RSS of the process tree
    returncode: int
    cpu_s: float = 0.0  # user + system CPU seconds of the stage process (and its waited-for children)


def _tree_rss(pid: int) -> int:
    import psutil

    try:
        proc = psutil.Process(pid)
        procs = [proc] + proc.children(recursive=True)
    except psutil.Error:
        return 0
    total = 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            pass
    return total


def run_measured(cmd: list[str], cwd: Path, log_path: Path, env: dict | None = None, stage: str = "") -> Measurement:
    """Run ``cmd``; wall time, its CPU time and ru_maxrss (``/usr/bin/time``) and a sampled tree-RSS peak."""
    with open(log_path, "w") as log, tempfile.NamedTemporaryFile("r", suffix=".time") as usage:
        t0 = time.perf_counter()
        proc = subprocess.Popen(
            ["/usr/bin/time", "-f", "%U %S %M", "-o", usage.name, *cmd],
            cwd=cwd,
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
        )
        peak = [0]
        done = threading.Event()

        def sample():
            while not done.is_set():
                peak[0] = max(peak[0], _tree_rss(proc.pid))
                done.wait(0.05)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        proc.wait()
        wall = time.perf_counter() - t0
        done.set()
        sampler.join()
        user_s, system_s, maxrss_kib = usage.read().split()[-3:]  # after "Command exited with non-zero status N"
    return Measurement(
        stage, wall, int(maxrss_kib) / 1024.0, peak[0] / 2**20, proc.returncode, float(user_s) + float(system_s)
    )


def ensure_data(workdir: Path, n_frames: int, n_videos: int, seed: int = 0) -> tuple[Path, float | None]:
    """Synthetic tables for (n_frames, n_videos), generated once and cached under ``workdir``.

    Returns the data folder and the generation time (None when reused).
    """
    data = workdir / f"data_{n_frames}_{n_videos}"
    if data.exists():
        return data, None
    tmp = data.with_name(data.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    t0 = time.perf_counter()
    subprocess.run(
        AUMESH
        + ["synth", "--out", str(tmp), "--frames", str(n_frames), "--videos", str(n_videos), "--seed", str(seed)],
        check=True,
        stdout=subprocess.DEVNULL,
    )
    tmp.rename(data)
    return data, time.perf_counter() - t0


def source_env(src: str | Path | None) -> dict:
    """The environment that runs the stages of the source tree ``src`` (``PYTHONPATH``; None: the installed aumesh)."""
    env = dict(os.environ)
    if src:
        env["PYTHONPATH"] = str(src) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    if (REPO / "node_modules").is_dir():  # the release's viewer inlines three.js (`make tools`), whichever tree runs
        env.setdefault("AUMESH_NODE_MODULES", str(REPO / "node_modules"))
    return env


def conf_dir(src: str | Path | None) -> Path:
    """The ``conf/`` beside a source tree ``<checkout>/src`` (this repo's for None)."""
    return Path(src).resolve().parent / "conf" if src else REPO / "conf"


def compose_params(
    run_dir: Path, data_dir: Path, overrides: list[str] = (), src: str | Path | None = None, name: str = "params.yaml"
) -> Path:
    """A params file ``run_dir / name`` whose paths all point into ``run_dir`` (tracking: a SQLite store there),
    composed from the ``conf/`` of the source tree ``src`` by that tree's code (None: this checkout)."""
    run_dir.mkdir(parents=True, exist_ok=True)
    write_data_dvc(run_dir, data_dir)
    out = run_dir / name
    paths = {
        "data_dir": data_dir,
        "ingested_dir": run_dir / "ingested",
        "prepared_dir": run_dir / "prepared",
        "model_dir": run_dir / "model",
        "release_dir": run_dir / "release",
        "metrics_file": run_dir / "metrics.json",
        "promotion_file": run_dir / "promotion.json",
        "error_curve_file": run_dir / "cumulative_vertex_error.csv",
        "r2_curve_file": run_dir / "r2_by_n_components.csv",
    }
    # an older tree's conf/ may lack some of today's keys (Hydra refuses to override a missing key)
    known = (
        (conf_dir(src) / "paths" / "default.yaml").read_text()
        if (conf_dir(src) / "paths" / "default.yaml").exists()
        else ""
    )
    path_overrides = [f"paths.{k}={v}" for k, v in paths.items() if not known or f"{k}:" in known]
    subprocess.run(
        AUMESH
        + [
            "compose-params",
            "--config-dir",
            str(conf_dir(src)),
            "--out",
            str(out),
            *path_overrides,
            f"tracking.tracking_uri=sqlite:///{run_dir / 'mlflow.db'}",
            *overrides,
        ],
        check=True,
        stdout=subprocess.DEVNULL,
        env=source_env(src),
    )
    return out


def write_data_dvc(run_dir: Path, data_dir: Path) -> None:
    """A stand-in ``data.dvc`` in the stage's working directory (evaluate logs the data digest to MLflow
    and refuses a digest without md5); the 'md5' names the synthetic set, it is not a real hash."""
    (run_dir / "data.dvc").write_text(
        f"outs:\n- md5: benchmark-{Path(data_dir).name}.dir\n  size: {dir_size(data_dir)}\n"
        f"  nfiles: {sum(1 for _ in Path(data_dir).glob('*.parquet'))}\n  hash: md5\n  path: data\n"
    )


def init_tracking_store(db: Path, env: dict | None = None) -> float:
    """Create the SQLite MLflow store ``db`` (MLflow's schema migrations) as a workspace's first run does;
    returns the wall seconds (a one-time cost per workspace, printed apart from the stages')."""
    t0 = time.perf_counter()
    subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; from mlflow import MlflowClient; MlflowClient(sys.argv[1]).search_experiments()",
            f"sqlite:///{Path(db).resolve()}",
        ],
        check=True,
        capture_output=True,
        env=env,
    )
    return time.perf_counter() - t0


def run_stages(run_dir: Path, params: Path, env: dict | None = None, stages=STAGES) -> list[Measurement]:
    """The pipeline's stages in order, each a measured subprocess (cwd = ``run_dir``).

    The MLflow store is named by ``MLFLOW_TRACKING_URI`` (absolute), so a run folder outside the repository
    works with any source tree (older ones look for the workspace root to resolve a configured URI). It is
    created before the stages (:func:`init_tracking_store`): a user's workspace has it after its first run.
    """
    env = dict(
        env if env is not None else os.environ, MLFLOW_TRACKING_URI=f"sqlite:///{run_dir.resolve() / 'mlflow.db'}"
    )
    if not (run_dir / "mlflow.db").exists():
        init_tracking_store(run_dir / "mlflow.db", env)
    out = []
    for stage in stages:
        if not has_stage(stage, env):
            out.append(Measurement(stage, 0.0, 0.0, 0.0, 0))
            continue
        for name in DVC_REMOVED_OUTPUTS.get(stage, ()):  # untimed, as `dvc repro` removes them before the stage
            shutil.rmtree(run_dir / name, ignore_errors=True)
        if stage == stages[0]:
            # untimed: the writes of earlier runs (another variant's 2 GB of prepared meshes) reach the disk now, not
            # during this run's stages (the kernel's writeback, ~30 s after the writes, slowed the next variant's
            # prepare by ~1-2 s in alternating runs)
            os.sync()
        m = run_measured(AUMESH + [stage, "--params", str(params)], run_dir, run_dir / f"{stage}.log", env, stage)
        out.append(m)
        if m.returncode != 0:
            tail = (run_dir / f"{stage}.log").read_text()[-3000:]
            raise RuntimeError(f"stage {stage} failed (exit {m.returncode}); log tail:\n{tail}")
    return out


def read_floor(data_dir: Path) -> tuple[float, float]:
    """One pyarrow read of every table under ``data_dir`` (all columns; and the mesh ``.npy`` of py-feat's
    layout): ``(wall s, GiB read)``, the least any pipeline over these tables must spend on I/O and decoding."""
    import numpy as np
    import pyarrow.parquet as pq

    t0 = time.perf_counter()
    size = 0
    for f in sorted(Path(data_dir).glob("*.parquet")):
        table = pq.read_table(f)
        size += table.nbytes
        del table
        npy = f.with_suffix(".npy")
        if npy.exists():
            arr = np.load(npy)
            size += arr.nbytes
            del arr
    return time.perf_counter() - t0, size / 2**30


def pyfeat_replicas(workdir: Path, columns_data: Path, copies: int, n_files: int | None = None) -> Path:
    """A py-feat-layout set (AU/pose parquet + float16 ``[N, 478, 3]`` .npy) of ``copies`` copies of the first
    ``n_files`` tables of ``columns_data`` (copy ``c`` renames its videos ``c<c>_...``). The meshes are converted
    once (``<workdir>/pyfeat_base``); copies link to them, so 3M frames cost the disk of the base set only.
    """
    import numpy as np
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    base = workdir / "pyfeat_base"
    files = sorted(Path(columns_data).glob("*.parquet"))
    if not base.exists():
        tmp = base.with_name(base.name + ".tmp")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        for f in files:
            pf = pq.ParquetFile(f)
            names = pf.schema_arrow.names
            mesh = [c for c in names if c[:2] in ("x_", "y_", "z_") and c[2:].isdigit()]
            meta = pq.read_table(f, columns=[c for c in names if c not in set(mesh) and c != "video_id"])
            pq.write_table(meta, tmp / f.name, row_group_size=8192)
            coords = pq.read_table(f, columns=[f"{a}_{i}" for i in range(478) for a in "xyz"])
            arr = np.empty((coords.num_rows, 478 * 3), np.float16)
            for j, col in enumerate(coords.columns):
                arr[:, j] = col.to_numpy()
            np.save(tmp / f.with_suffix(".npy").name, arr.reshape(-1, 478, 3))
            del coords, arr
        tmp.rename(base)
    n_files = n_files or len(files)
    out = workdir / f"pyfeat_{n_files}files_x{copies}"
    if out.exists():
        return out
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for c in range(copies):
        for f in sorted(base.glob("*.parquet"))[:n_files]:
            table = pq.read_table(f)
            if c:
                renamed = pc.replace_substring(table.column("input"), "videos/", f"videos/c{c}_")
                table = table.set_column(table.schema.get_field_index("input"), "input", renamed)
            name = f"c{c}_{f.stem}"
            pq.write_table(table, tmp / f"{name}.parquet", row_group_size=8192)
            os.symlink(f.with_suffix(".npy").resolve(), tmp / f"{name}.npy")
    tmp.rename(out)
    return out


def dir_size(path: Path) -> int:
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file())


def load() -> str:
    """The 1-minute load average (other work on the machine slows wall times)."""
    return f"{os.getloadavg()[0]:.1f}"


def environment_note() -> str:
    import platform

    blas = os.environ.get("OPENBLAS_CORETYPE")
    return (
        f"{platform.node()} | {os.cpu_count()} cores | Python {platform.python_version()} | "
        f"OPENBLAS_CORETYPE={blas if blas is not None else '(unset)'}"
    )


def fmt_table(headers: list[str], rows: list[list]) -> str:
    cells = [[str(h) for h in headers]] + [
        [c if isinstance(c, str) else f"{c:,.1f}" if isinstance(c, float) else f"{c:,}" for c in r] for r in rows
    ]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = ["| " + " | ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)) + " |" for r in cells]
    lines.insert(1, "|" + "|".join("-" * (w + 1) + ":" for w in widths) + "|")
    return "\n".join(lines)
