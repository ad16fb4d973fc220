"""Shared fixtures: small, seeded synthetic frame tables with a known truth, generated offline."""

from __future__ import annotations

import functools
import os
import signal
import socket
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from aumesh import config
from aumesh.data import tables
from aumesh.pipeline import prepare
from aumesh.synthetic import tables as synth

REPO = Path(__file__).resolve().parents[1]

# the BLAS/OpenMP thread pools of numpy, scipy and scikit-learn (the names aumesh.pipeline.compute limits too)
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def pytest_configure(config):
    """With pytest-xdist workers (``make test``: ``-n auto``, one worker per core), each worker's BLAS runs on one
    thread, as aumesh's own Dask workers do (aumesh.pipeline.compute.engine): the workers already use every core,
    and a BLAS pool per worker only oversubscribes them. OpenBLAS threads spin while they wait, so on a 2-core box
    a scikit-learn PLS fit took 36 s of CPU with 2 threads per worker against 6 s with one. Set here, in the
    controller before the workers start, so the workers and the processes the tests start inherit it; a value
    given in the caller's environment wins. Serial runs (``make test-slow``) keep the BLAS default."""
    if getattr(config.option, "numprocesses", None) and "PYTEST_XDIST_WORKER" not in os.environ:
        for name in BLAS_THREAD_VARIABLES:
            os.environ.setdefault(name, "1")


# The modules that take longest on a worker (10-30 s each in `make test`; `--durations=0` tells), run first. With
# `--dist loadfile` (and `--no-loadscope-reorder`, pyproject.toml) xdist hands a worker the next module in this
# order whenever it runs short of work: longest first, the short modules fill in at the end, and no long module
# starts last on one worker while the other sits idle. A stale list costs only balance, never a test.
LONGEST_FIRST = (
    "test_faults.py",
    "test_ingest.py",
    "test_compute.py",
    "test_pipeline.py",
    "test_faults_runs.py",
    "test_viewer_clip.py",
    "test_viewer.py",
    "test_render.py",
    "test_tables.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # a stable sort: the rest keep their order


@pytest.fixture(scope="session", autouse=True)
def _sqlite_stores_without_fsync():
    """The tests' SQLite stores (MLflow's, opened through SQLAlchemy in the test process) skip fsync
    (``PRAGMA synchronous=OFF``): they are thrown away after the run, and MLflow commits a few hundred times to
    create its schema alone (seconds of waiting for the disk per store on a busy machine). Locking, journaling
    and what every other connection reads are unchanged; stores written by other processes (``aumesh`` or
    ``mlflow server`` started by a test) keep SQLite's default."""
    import sqlite3

    from sqlalchemy import event
    from sqlalchemy.engine import Engine

    def no_fsync(dbapi_connection, _record):
        if isinstance(dbapi_connection, sqlite3.Connection):
            dbapi_connection.execute("PRAGMA synchronous=OFF")

    event.listen(Engine, "connect", no_fsync)
    yield
    event.remove(Engine, "connect", no_fsync)


_STORE_TEMPLATE: list[Path] = []  # set once per session by the mlflow_store_template fixture


@pytest.fixture(scope="session", autouse=True)
def mlflow_store_template(tmp_path_factory) -> Path:
    """An empty MLflow SQLite store made by MLflow itself (its schema, every migration, its ``Default``
    experiment), once per test run (:func:`shared_build`), which :func:`new_store` copies.

    MLflow builds a new SQLite store with a few hundred statements and an Alembic migration run: 0.6-1.3 s of
    CPU per store, for about twenty stores a run, against 0.02 s to copy the file. A copy is the same database
    a new store starts as, made by the same MLflow; tests that are about creating a store (the console quiet
    while MLflow creates one, tests/test_progress.py) let aumesh create it."""
    from mlflow import MlflowClient

    def build(folder: Path) -> None:
        with pytest.MonkeyPatch.context() as mp:
            mp.chdir(folder)  # the Default experiment's artifact folder: inside the template's own folder
            MlflowClient(tracking_uri=f"sqlite:///{folder / 'mlflow.db'}").search_experiments()

    template = shared_build(tmp_path_factory, "mlflow-store", build) / "mlflow.db"
    _STORE_TEMPLATE[:] = [template]
    return template


def new_store(db: Path) -> Path:
    """``db`` as a new, empty MLflow store: a copy of :func:`mlflow_store_template` (fast); the folder must exist."""
    import shutil

    shutil.copyfile(_STORE_TEMPLATE[0], db)
    return db


_FAILED = pytest.StashKey[bool]()  # set on a test item whose setup or call failed (pytest_runtest_makereport)


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item, call):
    """Remember on the item that it failed, for fixtures that keep a failed test's files (:func:`remove_unless_failed`)."""
    report = yield
    if report.failed:
        item.stash[_FAILED] = True
    return report


def remove_unless_failed(request: pytest.FixtureRequest, folder: Path, failures_before: int | None = None) -> None:
    """Empty ``folder`` (made by ``tmp_path_factory.mktemp``) at a fixture's teardown, but keep it when the test
    failed, as pytest keeps a failed test's ``tmp_path`` (``tmp_path_retention_policy = "failed"``, pyproject.toml);
    for a module-scoped fixture, pass ``failures_before`` (``request.session.testsfailed`` at its setup): kept when
    a test of the module failed.

    pytest removes ``mktemp`` folders only with the whole run, and only when it passed: a run with two failures kept
    357 per-test stores (920 MB) in /tmp. The empty folder stays until then, so its name is not handed out again
    (``mktemp`` numbers after the highest existing one): a later test must not get the path of a store that a cached
    MLflow client or SQLAlchemy engine of this process may still hold open."""
    import shutil

    if failures_before is None:
        failed = request.node.stash.get(_FAILED, False)
    else:
        failed = request.session.testsfailed > failures_before
    if failed or not folder.is_dir():
        return
    for child in folder.iterdir():
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child, ignore_errors=True)
        else:
            child.unlink(missing_ok=True)


@pytest.fixture(autouse=True)
def _isolated_mlflow(request, tmp_path_factory, monkeypatch):
    """Every test logs to its own throw-away store (:func:`new_store`), never the workspace's mlflow.db; the store's
    folder is emptied when the test ends (kept if it failed: :func:`remove_unless_failed`)."""
    if "MLFLOW_TRACKING_URI" in os.environ and "aumesh-test" in os.environ["MLFLOW_TRACKING_URI"]:
        yield
        return
    folder = tmp_path_factory.mktemp("aumesh-test-mlflow")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{new_store(folder / 'mlflow.db')}")
    yield
    remove_unless_failed(request, folder)


@pytest.fixture(scope="module", autouse=True)
def _module_folders(request, tmp_path_factory):
    """The folders a test module made in the worker's temporary folder (its module fixtures' ``mktemp``: workspaces,
    tables, stores, a server's files), emptied when the module ends (:func:`remove_unless_failed`; all kept when one
    of its tests failed). pytest would remove them only with the whole run, and only when it passed.

    Set up before, so torn down after, the module's own fixtures (an autouse fixture comes first in its scope):
    their servers and browsers are gone by then. Session-scoped fixtures set up before it (:func:`fixed_conf`) and
    ``shared-*`` folders (:func:`shared_build`, the way for a session-scoped fixture to keep a folder) stay."""
    base = tmp_path_factory.getbasetemp()
    before, failures = set(base.iterdir()), request.session.testsfailed
    yield
    for folder in sorted(set(base.iterdir()) - before):
        if folder.is_dir() and not folder.is_symlink() and not folder.name.startswith("shared-"):
            remove_unless_failed(request, folder, failures)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    """After each test (its fixtures' setup included), the root logger as it was before, but for pytest's own handlers.
    Hydra's multirun (``aumesh sweep`` run in-process) configures the root logger for its jobs, a StreamHandler bound
    to the ``sys.stdout`` of that test and a FileHandler in the sweep's folder, and leaves them: a later test on the
    worker wrote its records into the closed stream ("I/O operation on closed file"), and aumesh's own handler, set
    only on a root without handlers (as ``logging.basicConfig``), was never set."""
    import logging

    root = logging.getLogger()
    before, level = set(root.handlers), root.level
    yield
    for handler in [h for h in root.handlers if h not in before and not type(h).__module__.startswith("_pytest")]:
        root.removeHandler(handler)
        handler.close()
    root.setLevel(level)


@pytest.fixture(autouse=True)
def _local_compute(monkeypatch):
    """The passes run where the test's configuration says: a cluster chosen in the caller's shell
    (``AUMESH_COMPUTE_ADDRESS``, aumesh.pipeline.compute.settings.effective) is not the tests' to use."""
    for name in [k for k in os.environ if k.startswith("AUMESH_COMPUTE_")]:
        monkeypatch.delenv(name)


def shared_build(tmp_path_factory, name: str, build) -> Path:
    """A folder built once per test run and shared by every pytest-xdist worker: ``build(folder)`` fills
    ``folder`` the first time any worker asks for ``name``; the others wait for it and get the same folder.

    The pattern of pytest-xdist's documentation ("Making session-scoped fixtures execute only once"): the folder and
    its :class:`filelock.FileLock` live in the run's base temporary folder (the parent of each worker's own, or the
    base folder itself without workers), so nothing is shared between runs. The folder is built where it stays
    (absolute paths recorded inside it, e.g. by MLflow, stay valid) and marked complete last; a build that failed is
    removed and redone by the next worker that asks. Consumers must treat the folder as read-only (copy it to change
    it); wrap the call in a ``scope="session"`` fixture so each worker asks once.

    Parameters
    ----------
    tmp_path_factory : pytest.TempPathFactory
    name : str
        The folder's name, unique in the run.
    build : callable
        ``build(folder: Path) -> None``; ``folder`` exists and is empty.

    Returns
    -------
    Path
        The built folder.
    """
    import shutil

    from filelock import FileLock

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent
    folder, done = root / f"shared-{name}", root / f"shared-{name}.complete"
    with FileLock(str(root / f"shared-{name}.lock")):
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            build(folder)
            done.touch()
    return folder


_SESSION_TMP: list[pytest.TempPathFactory] = []  # set once per session by the _session_tmp fixture


@pytest.fixture(scope="session", autouse=True)
def _session_tmp(tmp_path_factory) -> None:
    _SESSION_TMP[:] = [tmp_path_factory]


def built_once(name: str, build) -> Path:
    """:func:`shared_build` for helpers that are not fixtures (the run's temporary folder found for them)."""
    return shared_build(_SESSION_TMP[0], name, build)


_FIXED_CONF: list[Path] = []  # set once per session by the fixed_conf fixture


@pytest.fixture(scope="session", autouse=True)
def fixed_conf(tmp_path_factory) -> Path:
    """The configuration every test composes: the repo's conf/ groups (the card's defaults) copied to a
    temporary folder without conf/experiment/, where `aumesh promote` writes promoted.yaml. Tests never
    read the user's promotion, params.yaml or mlflow.db (see _isolated_mlflow)."""
    import shutil

    conf = tmp_path_factory.mktemp("fixed") / "conf"
    shutil.copytree(REPO / "conf", conf, ignore=shutil.ignore_patterns("experiment"))
    _FIXED_CONF[:] = [conf]
    return conf


def default_config(**overrides) -> config.Config:
    """The fixed configuration (:func:`fixed_conf`) with Hydra-style overrides (``"model.n_components=10"``)."""
    return _composed(tuple(f"{k}={v}" for k, v in overrides.items()))


@functools.cache
def _composed(items: tuple[str, ...]) -> config.Config:
    """Composed once per worker and set of overrides (a Hydra compose is ~0.1 s): the fixed conf/ does not change
    during a run, and a :class:`aumesh.config.Config` is frozen, so tests can share it."""
    return config.from_dict(config.compose(items, config_dir=_FIXED_CONF[0]))


# a clean, well-identified problem: truth recovery needs signal, not the demo's realism
RECOVERY_SPEC = synth.SynthSpec(
    n_frames=3000,
    n_videos=300,
    seed=7,
    identity_scale=0.001,
    unexplained_scale=0.001,
    noise_px=0.1,
    landmark_failure_rate=0.003,
)


@pytest.fixture(scope="session")
def recovery_tables(tmp_path_factory):
    """:data:`RECOVERY_SPEC`'s tables in ``out/data`` and the generator's truth in ``out/truth.npz``, built once per
    run (:func:`shared_build`): ``(out, summary of synth.write_tables)``. Read-only."""
    import json

    def build(out: Path) -> None:
        summary = synth.write_tables(out / "data", RECOVERY_SPEC, truth_path=out / "truth.npz")
        (out / "summary.json").write_text(json.dumps(summary, default=str))

    out = shared_build(tmp_path_factory, "recovery-tables", build)
    return out, json.loads((out / "summary.json").read_text())


@pytest.fixture(scope="session")
def recovery_prepared(recovery_tables, tmp_path_factory, fixed_conf):
    """:func:`recovery_tables` prepared by the recipe (fixed configuration) into ``out/prepared``, once per run:
    ``out``, the tables' folder. Read-only."""
    out, _ = recovery_tables

    def build(folder: Path) -> None:
        cfg = default_config(**{"paths.data_dir": str(out / "data")})
        found = tables.discover(out / "data", cfg.data.tables, cfg.data.mesh_npy)
        prepare.run(found, cfg, out / "prepared")

    shared_build(tmp_path_factory, "recovery-prepared", build)  # the marker: out/prepared is complete
    return out


@pytest.fixture(scope="session")
def good_workspace(tmp_path_factory, fixed_conf) -> Path:
    """A workspace after a complete good run, built once per test run (:func:`shared_build`): 400 synthetic
    frames of 40 videos in ``data/``, ``params.yaml`` (the fixed test configuration), the ingest, prepare,
    evaluate and release stages run by ``aumesh`` in-process, their MLflow runs in the workspace's own
    ``mlflow.db``. Read-only: tests that change it work on a copy (tests/test_faults.py's ``workspace``)."""
    from aumesh import cli
    from aumesh.config import write_params

    def build(root: Path) -> None:
        ws = root / "ws"
        ws.mkdir()
        synth.write_tables(ws / "data", SMALL_SPEC)
        write_params(default_config().to_dict(), ws / "params.yaml")
        with pytest.MonkeyPatch.context() as mp:
            mp.chdir(ws)
            mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{new_store(ws / 'mlflow.db')}")
            for stage in ("ingest", "prepare", "evaluate", "release"):
                assert cli.main([stage]) == 0

    return shared_build(tmp_path_factory, "good-workspace", build) / "ws"


SMALL_SPEC = synth.SynthSpec(n_frames=400, n_videos=40, seed=3)


@pytest.fixture
def small_tables(tmp_path):
    """A tiny columns-layout set: 400 frames of 40 videos (:data:`SMALL_SPEC`), the test's own copy of the set
    generated once per run (:func:`built_once`): tests change their copy."""
    import shutil

    generated = built_once("small-tables", lambda out: synth.write_tables(out / "data", SMALL_SPEC)) / "data"
    shutil.copytree(generated, tmp_path / "data")
    return tmp_path / "data"


def face_reference(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A prepare-stage reference: the template as a face in image pixels (y down, z into the image), jittered."""
    from aumesh.geometry.face import canonical_template

    face_px = canonical_template() * 60.0 + 300.0
    return {
        "mean_aligned_mesh": face_px + rng.normal(scale=0.1, size=face_px.shape),
        "mean_low_au_mesh": face_px,
        "reference_anchors": face_px[:12],
        "anchor_indices": np.arange(12),
    }


def in_card_frame(coef: np.ndarray, intercept: np.ndarray, reference: dict) -> tuple[np.ndarray, np.ndarray]:
    """Raw coefficients (1434, p) and intercept (1434,) of the aligned frame, turned as ``release_arrays`` turns them."""
    from aumesh.geometry.frame import canonical_frame, rotate_axis_major

    rotation, origin = canonical_frame(reference["mean_aligned_mesh"])
    return rotate_axis_major(coef.T, rotation).T, rotate_axis_major(intercept, rotation, origin)


def identification_keys(flags: dict[str, tuple[float, str]], flag_below: float = 0.10) -> dict[str, np.ndarray]:
    """A release's ``au_identification_*`` keys (issue 43; what ``IdentificationScreen.release_arrays`` writes) with
    ``flags`` (AU -> (sigma*, partner)) flagged; every other AU unflagged with sigma* NaN (did not turn within the
    grid) and the next AU in ``AU_COLUMNS`` as its partner."""
    from aumesh.core.schema import AU_COLUMNS

    n = len(AU_COLUMNS)
    sigma = np.full(n, np.nan)
    partner = [AU_COLUMNS[(k + 1) % n] for k in range(n)]
    for au, (s, p) in flags.items():
        k = AU_COLUMNS.index(au)
        sigma[k], partner[k] = s, p
    return {
        "au_identification_sigma_star": sigma,
        "au_identification_flagged": np.array([au in flags for au in AU_COLUMNS]),
        "au_identification_partner": np.array(partner, dtype=str),
        "au_identification_flag_below": np.array(flag_below),
    }


def seeded_rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


@pytest.fixture(scope="session")
def node_tools():
    """The project's node packages (package-lock.json: three, vega, vega-lite, vega-embed, gltf-validator) in
    REPO/node_modules, or in $AUMESH_NODE_MODULES when that holds them all (the code's own override).

    `make tools` installs them (`npm ci`); if they are missing, this runs the same install once and
    skips, naming the reason, only when npm cannot install them (no npm, no registry access).
    """
    import shutil
    import subprocess

    packages = ("gltf-validator", "three", "vega", "vega-lite", "vega-embed")
    override = os.environ.get("AUMESH_NODE_MODULES")
    if override and all((Path(override) / p / "package.json").exists() for p in packages):
        return Path(override)
    wanted = [REPO / "node_modules" / p / "package.json" for p in packages]
    if all(p.exists() for p in wanted):
        return REPO / "node_modules"
    if shutil.which("npm") is None or shutil.which("node") is None:
        pytest.skip("node/npm not installed: cannot install the node tools (make tools)")
    proc = subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=REPO, capture_output=True, text=True)
    if proc.returncode != 0 or not all(p.exists() for p in wanted):
        pytest.skip(f"npm ci could not install the node tools: {proc.stderr.strip()[-500:]}")
    return REPO / "node_modules"


# Debian's chromium, driven headless by Playwright (no browser download); .ci/run installs it
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


SCREENSHOTS = REPO / "build" / "test-screenshots"  # browser screenshots kept for a person to look at


@pytest.fixture(scope="module")
def browser():
    """A headless :data:`CHROMIUM` (Playwright's ``Browser``), launched once per test module and closed after it
    (``make test`` keeps a module on one worker: ``--dist loadfile``); skipped, naming the fix, without chromium.
    Open pages in a fresh ``browser.new_context(offline=True)`` per test, so tests share the process, not state."""
    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} not installed (apt-get install chromium; .ci/run does it)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


def upright_truth_release(path: Path) -> Path:
    """A synthetic-truth release NPZ in the card's canonical frame (y up, z out of the face), pixel-like units.

    The template's face frame (x to the subject's left, y down, z away) turned half a turn about x,
    then scaled and moved: the AU rows are the known synthetic FACS fields (aumesh.synthetic.truth).
    """
    from aumesh.geometry import face
    from aumesh.synthetic import truth

    tpl = 120.0 * face.canonical_template() * np.array([1.0, -1.0, -1.0]) + np.array([320.0, 240.0, 10.0])
    np.savez(path, **truth.synthetic_release_arrays(tpl))
    return path


# ------------------------------------------------------------------ a fresh `git clone` of this checkout
VENV = REPO / ".venv"


def link_venv(clone: Path) -> None:
    """Give a clone this checkout's environment as its own ``.venv/`` (a directory of links, so git ignores
    it, Python finds ``pyvenv.cfg`` beside ``bin/`` and the Makefile's venv stamp can be declared up to date)."""
    (clone / ".venv").mkdir()
    for name in ("bin", "lib", "lib64", "include", "share", "pyvenv.cfg", ".installed"):
        if (VENV / name).exists():
            (clone / ".venv" / name).symlink_to(VENV / name)


def clean_env(clone: Path) -> dict:
    """The environment of a user who did not activate the venv: the venv's bin is not on PATH; the clone's
    committed code (PYTHONPATH) wins over this checkout's editable install."""
    keep = [
        p for p in os.environ.get("PATH", "").split(os.pathsep) if p and Path(p).resolve() != (VENV / "bin").resolve()
    ]
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("MLFLOW_", "DVC_", "AUMESH_")) and k not in ("PYTHONPATH", "VIRTUAL_ENV")
    }
    env.update(
        PATH=os.pathsep.join(keep),
        PYTHONPATH=str(clone / "src"),
        GIT_AUTHOR_NAME="t",
        GIT_AUTHOR_EMAIL="t@example.com",
        GIT_COMMITTER_NAME="t",
        GIT_COMMITTER_EMAIL="t@example.com",
        MLFLOW_DISABLE_TELEMETRY="true",
        DO_NOT_TRACK="true",
    )
    if os.environ.get("AUMESH_NODE_MODULES"):  # the node tools where this checkout's tests find them
        env["AUMESH_NODE_MODULES"] = os.environ["AUMESH_NODE_MODULES"]
    elif (REPO / "node_modules").is_dir():  # the node tools `make tools` installed here (three.js, vega)
        env["AUMESH_NODE_MODULES"] = str(REPO / "node_modules")
    return env


@pytest.fixture
def fresh_clone(tmp_path) -> tuple[Path, dict]:
    """``git clone`` of this checkout's HEAD with the venv linked in; skipped without git, the venv or demo-remote/."""
    import shutil
    import subprocess

    if shutil.which("git") is None or not (VENV / "bin" / "dvc").exists() or not (REPO / ".git").exists():
        pytest.skip("needs git, .venv/bin/dvc and a git checkout")
    if not (REPO / "demo-remote").is_dir():
        pytest.skip("the committed demo DVC remote (demo-remote/) is missing")
    ws = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", str(REPO), str(ws)], check=True, capture_output=True)
    link_venv(ws)
    return ws, clean_env(ws)


# ------------------------------------------------------------------ a real MLflow tracking server on loopback
STARTUP_TIMEOUT_S = 90.0  # ~20 s on a loaded 2-core box; bounded so a broken server fails the test


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def server_healthy(url: str) -> bool:
    try:
        with urllib.request.urlopen(f"{url}/health", timeout=2) as resp:
            return resp.status == 200
    except (urllib.error.URLError, ConnectionError, OSError):
        return False


def stop_process_group(proc: subprocess.Popen) -> None:
    """Terminate the server's whole process group (uvicorn workers included), then reap."""
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(timeout=10)


@pytest.fixture(scope="module")
def mlflow_server(tmp_path_factory):
    """A real `mlflow server` (SQLite store, artifacts proxied) on a free loopback port for the module: its URL."""
    from aumesh.tracking.server import server_command, server_environment

    tmp = tmp_path_factory.mktemp("mlflow_server")
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    env = server_environment()  # what `aumesh server` runs it with: telemetry and the GenAI job runner off
    env.pop("MLFLOW_TRACKING_URI", None)
    log = open(tmp / "server.log", "w")
    cmd = server_command(f"sqlite:///{tmp / 'mlflow.db'}", str(tmp / "mlartifacts"), port=port, workers=1)
    proc = subprocess.Popen(cmd, cwd=tmp, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + STARTUP_TIMEOUT_S
        while not server_healthy(url):
            if proc.poll() is not None:
                pytest.fail(f"mlflow server exited with {proc.returncode}:\n{(tmp / 'server.log').read_text()[-3000:]}")
            if time.monotonic() > deadline:
                pytest.fail(
                    f"mlflow server not healthy after {STARTUP_TIMEOUT_S}s:\n{(tmp / 'server.log').read_text()[-3000:]}"
                )
            time.sleep(0.25)
        yield url
    finally:
        stop_process_group(proc)
        log.close()


# ------------------------------------------------------------------------------ workspaces the fault tests break
@pytest.fixture
def workspace(good_workspace, tmp_path, monkeypatch):
    """A copy of the good workspace (conftest.good_workspace, built once per run), its own MLflow store included."""
    import shutil

    ws = tmp_path / "ws"
    shutil.copytree(good_workspace, ws)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{ws / 'mlflow.db'}")
    return ws


@pytest.fixture(scope="module")
def dvc_workspace(tmp_path_factory):
    """A git + DVC workspace (the repo's dvc.yaml, conf/, params) after one complete `dvc repro`."""
    import shutil
    import subprocess

    from aumesh.synthetic.tables import SynthSpec, write_tables
    from test_dvc_pipeline import BIN, _run

    ws = tmp_path_factory.mktemp("dvcfaults") / "ws"
    ws.mkdir()
    for name in ("dvc.yaml", "params.yaml", "promotion.json", ".gitignore"):
        shutil.copy(REPO / name, ws / name)
    shutil.copytree(REPO / "conf", ws / "conf")
    shutil.copytree(REPO / "validation", ws / "validation")  # evaluate's dep (paths.validation_dir), as in a clone
    shutil.copytree(REPO / "src", ws / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    for args in (
        ["git", "init", "-q"],
        ["git", "config", "user.email", "t@example.com"],
        ["git", "config", "user.name", "t"],
        [BIN / "dvc", "init", "-q"],
    ):
        _run(args, ws)
    shutil.copy(REPO / ".dvc" / "config", ws / ".dvc" / "config")
    subprocess.run([BIN / "dvc", "remote", "remove", "demo"], cwd=ws, capture_output=True)
    write_tables(ws / "data", SynthSpec(n_frames=600, n_videos=60, seed=11))
    _run([BIN / "dvc", "add", "-q", "data"], ws)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{ws / 'mlflow.db'}")
        _run([BIN / "dvc", "repro"], ws)
    _run(["git", "add", "-A"], ws)
    _run(["git", "commit", "-qm", "good release"], ws)
    return ws


@pytest.fixture
def conf_ws(tmp_path, monkeypatch):
    """A promotion workspace, the current folder: conf/ (without promoted.yaml), dvc.yaml, params.yaml composed from
    that conf/, and an empty promotion.json."""
    import shutil

    ws = tmp_path / "ws"
    ws.mkdir()
    shutil.copytree(REPO / "conf", ws / "conf", ignore=shutil.ignore_patterns("promoted.yaml"))
    shutil.copy(REPO / "dvc.yaml", ws / "dvc.yaml")
    config.write_params(config.compose(config_dir=ws / "conf"), ws / "params.yaml")
    (ws / "promotion.json").write_text('{"promoted": null}\n')
    monkeypatch.chdir(ws)
    return ws
