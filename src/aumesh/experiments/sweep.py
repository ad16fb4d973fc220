"""In-process sweeps with Hydra's syntax, logged to MLflow as one parent run and one child per configuration.

``aumesh sweep -m preprocess.target=absolute,neutral,within features=au,au_pose,au_pose_interactions \\
model.n_components=10,23,40,83`` runs :func:`main`: a Hydra app
on the repo's ``conf/`` (the same configuration ``dvc exp run`` composes into ``params.yaml``)
whose task function evaluates one configuration on the prepared data. Not a DVC stage: a sweep
is exploration; ``aumesh promote`` turns its best run into ``conf/`` so ``dvc repro`` rebuilds it.

Reuse between configurations (per process; every joblib worker keeps its own):

* the loaded :class:`aumesh.pipeline.evaluate.Prepared` (memory-mapped meshes), keyed by its directory;
* the fold of every frame, keyed by (prepared data, ``cv.n_splits``);
* the per-fold :class:`aumesh.pipeline.evaluate.FoldStatistics`, keyed by (prepared data,
  ``preprocess.target``, ``preprocess.neutral.method``, ``features``, ``cv.n_splits``): a new ``model.*`` value costs fits from
  statistics and one prediction pass, never a new pass of accumulation;
* the CV result and final fit, keyed by the statistics and the *effective* number of
  components: ``model.n_components`` clipped to the number of features (40 or 83 on the
  23-feature design) is the same model as an earlier configuration and is logged, not refitted.

Prepared data. The prepare-relevant keys are the ``prepare`` stage's params in ``dvc.yaml``
(:data:`PREPARE_KEYS`). When a configuration's values equal those of the workspace's
``params.yaml`` the sweep reads ``paths.prepared_dir`` (the DVC output; ``dvc repro prepare``
first). When they differ, the sweep prepares once into ``build/sweeps/prepared/<key>/`` (or into
``paths.prepared_dir`` if that was overridden too), stamps the directory with the values it was
prepared from and reuses it across sweeps; a stamped directory with other values is an error.

MLflow layout. A Hydra callback (:class:`SweepCallback`, configured in ``conf/hydra/default.yaml``)
opens the parent run when the (multi)run starts and writes its id to ``<sweep dir>/mlflow_parent.json``,
where every job (in this process, a joblib worker or a cluster node) finds it. Each job opens a
child run (``aumesh.tracking.runs.tracked_run``): flattened params, provenance tags (git commit, data
digest), per-fold ``r2``/``mae``/``vertex_error``/``r2_displacement`` (step = fold) and their means,
the R²-vs-n_components curve (metric ``r2_by_n_components``, step = k, and the figure
``plots/r2_vs_n_components.png``) and the model as an MLflow pyfunc model under ``model/`` (the
release-format NPZ, signature and input example: :mod:`aumesh.tracking.pyfunc`; what ``aumesh
promote`` registers; metric ``seconds_log_model``). A configuration that raises (e.g. a data or config error) is recorded as a
FAILED child with the error and the sweep goes on. When the sweep ends the parent is FINISHED with tags counting its children.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import sys
import time
from collections import OrderedDict
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from aumesh.config import flatten as flatten_config
from aumesh.core.io import atomic_write_json
from aumesh.pipeline.prepared_files import PREPARED_FILES, SUMMARY_FILE

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np
    from matplotlib.figure import Figure

    from aumesh.config import Config
    from aumesh.pipeline.evaluation_results import CVResult, FinalModel, FoldStatistics
    from aumesh.pipeline.prepared_data import Prepared

log = logging.getLogger(__name__)

PARENT_FILE = "mlflow_parent.json"
RESULT_FILE = "result.json"
SWEEPS_DIR = "build/sweeps"
PREPARED_CACHE_DIR = "build/sweeps/prepared"
PREPARE_STAMP = "aumesh_sweep_prepare.json"
FIGURE_ARTIFACT = "plots/r2_vs_n_components.png"
CHILD_ROLE = "sweep-child"
PARENT_ENV = "AUMESH_SWEEP_PARENT_RUN_ID"
# BLAS threads per job: a sweep parallelises over configurations (hydra/launcher=joblib), not inside
# the small (p x p, p x 1434) products of one fit, where extra threads only contend (10x slower on
# a busy 2-core box). Set AUMESH_SWEEP_BLAS_THREADS=0 to leave the BLAS default.
BLAS_THREADS_ENV = "AUMESH_SWEEP_BLAS_THREADS"

# The prepare stage's params (dvc.yaml), minus data.chunk_rows (memory, not results).
PREPARE_KEYS = (
    "paths.data_dir",
    "data.tables",
    "data.mesh_npy",
    "data.coerce_numeric",
    "preprocess.pose_filter",
    "preprocess.alignment",
    "preprocess.neutral.low_au_quantile",
    "preprocess.empty_video",
    "preprocess.max_drop_fraction",
    "seed",
)
MAX_CACHED_STATISTICS = 8  # FoldStatistics kept per process (a few MB each: X'X, X'Y, diag(Y'Y) per fold)


# ------------------------------------------------------------------ pure helpers
def prepare_signature(cfg: Config) -> dict[str, Any]:
    """The values of :data:`PREPARE_KEYS` in *cfg*, flattened (what the prepared data depend on).

    Parameters
    ----------
    cfg : aumesh.config.Config

    Returns
    -------
    dict
        ``{dotted key: value}``, sorted by key.
    """
    flat = flatten_config(cfg.to_dict())
    return {k: v for k, v in sorted(flat.items()) if any(k == p or k.startswith(p + ".") for p in PREPARE_KEYS)}


def prepare_key(signature: Mapping[str, Any]) -> str:
    """Short content hash of a :func:`prepare_signature` (names the prepared-data cache dir)."""
    text = json.dumps(signature, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def statistics_key(prepared_id: str, cfg: Config) -> tuple:
    """Cache key of the per-fold statistics: everything :func:`aumesh.pipeline.evaluate.accumulate` depends on."""
    return (prepared_id, cfg.preprocess.target, cfg.preprocess.neutral.method, cfg.features.name, int(cfg.cv.n_splits))


def run_name(overrides: Sequence[str]) -> str:
    """Compact child run name from a job's overrides: ``target=neutral,pose=true,n_components=10``."""
    parts = []
    for ov in overrides:
        key, sep, value = ov.partition("=")
        if not sep or key.startswith("hydra"):
            continue
        parts.append(f"{key.lstrip('+~').rsplit('.', 1)[-1]}={value}")
    return ",".join(parts) or "base"


@dataclass(frozen=True)
class PreparedSource:
    """Where a configuration's prepared data live and whether the sweep has to prepare them."""

    path: Path
    managed_by_dvc: bool
    signature: dict[str, Any]
    key: str


def resolve_prepared(cfg: Config, workspace: Config | None, root: Path) -> PreparedSource:
    """Decide which prepared directory serves *cfg* (see the module docstring).

    Parameters
    ----------
    cfg : Config
        The configuration of one job.
    workspace : Config or None
        The workspace's ``params.yaml`` (what ``dvc repro`` prepared from), None if absent.
    root : Path
        Workspace root; relative paths are resolved against it.

    Returns
    -------
    PreparedSource
    """
    signature = prepare_signature(cfg)
    key = prepare_key(signature)
    own = (root / cfg.paths.prepared_dir).resolve()
    if (
        workspace is not None
        and signature == prepare_signature(workspace)
        and own == (root / workspace.paths.prepared_dir).resolve()
    ):
        return PreparedSource(own, True, signature, key)
    if workspace is not None and own != (root / workspace.paths.prepared_dir).resolve():
        return PreparedSource(own, False, signature, key)  # the user named the directory
    return PreparedSource((root / PREPARED_CACHE_DIR / key).resolve(), False, signature, key)


def r2_curve_figure(r2_path_folds: np.ndarray, title: str) -> Figure:
    """The R²-vs-n_components curve of one configuration: each fold and the mean.

    Parameters
    ----------
    r2_path_folds : ndarray, shape (n_splits, A)
        Held-out R² of the fold's model truncated to k = 1..A components.
    title : str

    Returns
    -------
    matplotlib.figure.Figure
        Agg-backed figure (no pyplot state).
    """
    import numpy as np
    from matplotlib.figure import Figure

    paths = np.atleast_2d(np.asarray(r2_path_folds, dtype=float))
    k = np.arange(1, paths.shape[1] + 1)
    fig = Figure(figsize=(6.0, 3.8), dpi=90)
    ax = fig.add_subplot()
    for f, path in enumerate(paths):
        ax.plot(k, path, lw=0.9, alpha=0.55, label=f"fold {f}")
    mean = paths.mean(axis=0)
    ax.plot(k, mean, color="black", lw=2.0, label="mean")
    best = int(np.argmax(mean))
    ax.scatter([k[best]], [mean[best]], color="crimson", zorder=3, label=f"max mean R² at k={k[best]}")
    ax.set_xlabel("n_components (k)")
    ax.set_ylabel("held-out R² (variance-weighted)")
    ax.set_title(title, fontsize=8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.subplots_adjust(left=0.12, right=0.97, bottom=0.14, top=0.9)
    return fig


# ------------------------------------------------------------------ the cache
@dataclass
class SweepCache:
    """Per-process reuse of prepared data, folds and per-fold statistics across configurations."""

    prepared: dict[str, Prepared] = field(default_factory=dict)
    folds: dict[tuple, np.ndarray] = field(default_factory=dict)
    designs: dict[tuple, Any] = field(default_factory=dict)  # (prepared id, n_splits) -> evaluate.DesignStatistics
    statistics: OrderedDict = field(default_factory=OrderedDict)
    results: OrderedDict = field(default_factory=OrderedDict)
    workspace: dict[str, Any] = field(default_factory=dict)
    hits: int = 0
    misses: int = 0

    def workspace_params(self, root: Path) -> Config | None:
        """The workspace's ``params.yaml`` as a Config (cached by mtime), None if absent."""
        from aumesh.config import load_params

        path = root / "params.yaml"
        if not path.exists():
            return None
        stamp = (str(path), path.stat().st_mtime_ns)
        if self.workspace.get("stamp") != stamp:
            self.workspace = {"stamp": stamp, "cfg": load_params(path)}
        return self.workspace["cfg"]

    def load(self, source: PreparedSource, cfg: Config) -> tuple[Prepared, str]:
        """The prepared data for *source* (preparing them first if needed); returns (data, cache id)."""
        from aumesh.pipeline.prepared_data import load_prepared

        ensure_prepared(source, cfg)
        summary = source.path / SUMMARY_FILE
        pid = f"{source.path}@{summary.stat().st_mtime_ns}"
        if pid not in self.prepared:
            self.prepared = {pid: load_prepared(source.path)}  # one prepared set at a time
            self.folds.clear()
            self.designs.clear()
            self.statistics.clear()
            self.results.clear()
        return self.prepared[pid], pid

    def fold_of(self, prepared: Prepared, pid: str, n_splits: int) -> np.ndarray:
        from aumesh.pipeline import evaluate as ev

        key = (pid, n_splits)
        if key not in self.folds:
            self.folds[key] = ev.video_folds(prepared.videos.count, n_splits)
        return self.folds[key]

    def statistics_for(self, prepared: Prepared, pid: str, cfg: Config) -> tuple[FoldStatistics, bool]:
        """Per-fold statistics of *cfg*'s design and target; (stats, True if reused)."""
        from aumesh.pipeline import statistics_pass
        from aumesh.pipeline.prepared_data import workers_check

        key = statistics_key(pid, cfg)
        if key in self.statistics:
            self.statistics.move_to_end(key)
            self.hits += 1
            return self.statistics[key], True
        fold = self.fold_of(prepared, pid, cfg.cv.n_splits)
        design_key = (pid, cfg.cv.n_splits)
        if design_key not in self.designs:  # the one pass over the meshes; every target/feature set derives from it
            from aumesh.pipeline import compute

            with compute.engine(cfg.compute, **workers_check(prepared)):
                self.designs[design_key] = statistics_pass.design_statistics(
                    prepared, fold, cfg.cv.n_splits, cfg.data.chunk_rows
                )
        stats = statistics_pass.accumulate(prepared, cfg, fold, design=self.designs[design_key])
        self.statistics[key] = stats
        while len(self.statistics) > MAX_CACHED_STATISTICS:
            self.statistics.popitem(last=False)
        self.misses += 1
        return stats, False

    def evaluation_for(
        self, prepared: Prepared, pid: str, cfg: Config, stats: FoldStatistics
    ) -> tuple[CVResult, FinalModel, bool]:
        """CV result and final fit of *cfg*; reused when only a clipped ``model.n_components`` differs
        (e.g. 40 and 83 on a 23-feature design are the same 23-component model)."""
        from aumesh.pipeline import evaluate as ev

        key = statistics_key(pid, cfg) + (ev.effective_n_components(cfg), bool(cfg.model.scale))
        if key in self.results:
            self.results.move_to_end(key)
            return (*self.results[key], True)
        cv, final = evaluate_configuration(prepared, cfg, stats)
        self.results[key] = (cv, final)
        while len(self.results) > MAX_CACHED_STATISTICS:
            self.results.popitem(last=False)
        return cv, final, False


_CACHE: SweepCache | None = None


def process_cache() -> SweepCache:
    """The cache shared by all jobs that run in this process."""
    global _CACHE
    if _CACHE is None:
        _CACHE = SweepCache()
    return _CACHE


def ensure_prepared(source: PreparedSource, cfg: Config) -> Path:
    """Make sure *source* holds prepared data for *cfg*; prepare into it when absent.

    Raises
    ------
    FileNotFoundError
        A DVC-managed directory that does not exist (fix: ``dvc repro prepare``).
    ValueError
        A directory stamped with other prepare values (fix: delete it or override
        ``paths.prepared_dir``).
    """
    from aumesh.data import tables
    from aumesh.pipeline import prepare as prep

    complete = all((source.path / n).exists() for n in PREPARED_FILES)
    if source.managed_by_dvc:
        if not complete:
            raise FileNotFoundError(
                f"{source.path}: prepared data missing. It is the prepare stage's output for the workspace's "
                "params.yaml; run `dvc repro prepare` (or `make demo`) first."
            )
        return source.path
    stamp_path = source.path / PREPARE_STAMP
    from filelock import FileLock

    source.path.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(source.path.with_name(source.path.name + ".lock")):
        if complete and stamp_path.exists():
            stamp = json.loads(stamp_path.read_text())
            if stamp.get("signature") != json.loads(json.dumps(source.signature, default=str)):
                raise ValueError(
                    f"{source.path} was prepared by a sweep with other values of {', '.join(PREPARE_KEYS)}: "
                    f"{stamp.get('signature')}. Fix: delete it, or override paths.prepared_dir with a new directory."
                )
            return source.path
        if complete:
            log.warning(
                "%s: prepared data without a sweep stamp; using them as they are (not verified against %s)",
                source.path,
                ", ".join(PREPARE_KEYS),
            )
            return source.path
        log.info("preparing %s from %s (prepare values differ from params.yaml's)", source.path, cfg.paths.data_dir)
        found = tables.discover(cfg.paths.data_dir, cfg.data.tables, cfg.data.mesh_npy, cfg.data.coerce_numeric)
        prep.run(found, cfg, source.path)
        atomic_write_json(stamp_path, {"signature": source.signature, "key": source.key})
    return source.path


# ------------------------------------------------------------------ one configuration
@contextlib.contextmanager
def blas_threads(default: int = 1) -> Iterator[None]:
    """Limit BLAS/OpenMP threads for the duration of a job (``$AUMESH_SWEEP_BLAS_THREADS``, 0 = no limit)."""
    try:
        n = int(os.environ.get(BLAS_THREADS_ENV, default))
    except ValueError:
        raise ValueError(
            f"{BLAS_THREADS_ENV}={os.environ[BLAS_THREADS_ENV]!r}: use a thread count (0 = BLAS default)"
        ) from None
    if n <= 0:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=n):
        yield


def evaluate_configuration(prepared: Prepared, cfg: Config, stats: FoldStatistics) -> tuple[CVResult, FinalModel]:
    """Cross-validation and final fit of one configuration from (possibly shared) statistics."""
    from aumesh.pipeline import compute
    from aumesh.pipeline import evaluate as ev
    from aumesh.pipeline.prepared_data import workers_check

    with compute.engine(cfg.compute, **workers_check(prepared)):
        return ev.cross_validate_and_fit_from_statistics(prepared, cfg, stats)


def _log_child(
    run,
    cfg: Config,
    prepared: Prepared,
    source: PreparedSource,
    root: Path,
    cv: CVResult,
    final: FinalModel,
    timings: Mapping[str, float],
    reused: bool,
) -> dict[str, Any]:
    """Everything a child run records (metrics, curve, figure, NPZ); returns the summary metrics."""
    from aumesh.core import provenance
    from aumesh.model import support
    from aumesh.tracking.pyfunc import log_release_model

    metrics = cv.metrics()
    run.log_config(cfg.to_dict())
    tags = {
        "aumesh.prepared_dir": str(source.path),
        "aumesh.prepared.key": source.key,
        "aumesh.cache.statistics": "reused" if reused else "computed",
        "aumesh.n_components.effective": final.n_components,
    }
    data_dir = (root / cfg.paths.data_dir).resolve()
    digest = None
    with contextlib.suppress(FileNotFoundError, ValueError):
        digest = provenance.data_digest(root, "data.dvc")
    if digest and digest.get("md5") and data_dir == (root / str(digest.get("path") or "data")).resolve():
        run.log_dataset(digest, source=str(data_dir), name="frame_tables")
    else:
        tags["aumesh.data.note"] = (
            f"paths.data_dir={cfg.paths.data_dir} is not the DVC-tracked data of data.dvc; "
            "aumesh.data.* tags describe data.dvc, not this run's data"
        )
    run.set_tags(tags)
    run.log_fold_metrics(
        {
            "r2": cv.r2_folds,
            "mae": cv.mae_folds,
            "vertex_error": cv.vertex_error_folds,
            "r2_displacement": cv.r2_displacement_folds,
        }
    )
    scalars = cv.scalar_metrics()
    scalars |= {
        "n_components": float(final.n_components),
        "n_features": float(len(final.feature_columns)),
        "n_frames": float(sum(cv.n_frames_folds)),
    } | dict(timings)
    run.log_metrics(scalars)
    # the curve as a metric history, step = n_components (one batch)
    run.log_metric_history("r2_by_n_components", cv.r2_path_folds.mean(axis=0), first_step=1)
    title = (
        f"target={cfg.preprocess.target} neutral={cfg.preprocess.neutral.method} features={cfg.features.name} "
        f"n_components={final.n_components}"
    )
    run.log_figure(r2_curve_figure(cv.r2_path_folds, title), FIGURE_ARTIFACT)
    # the data's support travels with the model (the promoted sweep child's model is the registered one)
    metadata = {
        "mlflow_run_id": run.run_id,
        "config": cfg.to_dict(),
        "cv": {k: v for k, v in metrics.items()},
        "data": support.data_support(prepared.summary),
    }
    arrays = final.release_arrays(prepared.reference, metadata=metadata)
    run.log_metrics({"seconds_log_model": log_release_model(run, arrays)})  # MLflow pyfunc model under model/
    return {k: scalars[k] for k in ("r2_mean", "r2_std", "r2_displacement_mean", "mae_mean", "n_components")}


def run_configuration(
    raw: Mapping[str, Any],
    overrides: Sequence[str] = (),
    parent_run_id: str | None = None,
    cache: SweepCache | None = None,
    root: Path | None = None,
) -> dict[str, Any]:
    """Evaluate and log one configuration as a child run; never raises for a bad configuration.

    Parameters
    ----------
    raw : Mapping
        The composed configuration (plain dict, as Hydra gives it; validated here, inside the run,
        so an invalid configuration becomes a FAILED child).
    overrides : sequence of str
        The job's Hydra overrides (run name and tag).
    parent_run_id : str, optional
        The sweep's parent run.
    cache : SweepCache, optional
        Defaults to :func:`process_cache`.
    root : Path, optional
        Workspace root; defaults to :func:`aumesh.core.provenance.repo_root`.

    Returns
    -------
    dict
        ``run_id``, ``run_name``, ``status`` (``FINISHED``/``FAILED``), ``error`` and summary metrics.
    """
    from aumesh.config import from_dict
    from aumesh.core import provenance
    from aumesh.tracking import runs as tracking

    cache = cache or process_cache()
    root = Path(root) if root is not None else provenance.repo_root()
    raw = dict(raw)
    tracking_cfg = dict(raw.get("tracking") or {})
    name = run_name(overrides)
    tags = {
        tracking.ROLE_TAG: CHILD_ROLE,
        "aumesh.stage": "sweep",
        "aumesh.target": str((raw.get("preprocess") or {}).get("target")),
        "aumesh.sweep.overrides": " ".join(overrides),
    }
    handle = None
    t_start = time.perf_counter()
    try:
        with tracking.tracked_run(
            tracking_cfg, run_name=name, params=raw, tags=tags, parent_run_id=parent_run_id
        ) as run:
            handle = run
            cfg = from_dict(raw)
            with blas_threads():
                summary, reused = _evaluate_in_run(run, cfg, cache, root)
            run.log_metrics({"seconds_job": time.perf_counter() - t_start})
    except Exception as exc:  # recorded as FAILED by tracked_run; the sweep goes on
        log.error("configuration %s failed: %s: %s", name, type(exc).__name__, exc)
        return {
            "run_id": getattr(handle, "run_id", None),
            "run_name": name,
            "status": "FAILED",
            "error": f"{type(exc).__name__}: {exc}",
        }
    log.info(
        "configuration %s: r2_mean=%.4f r2_displacement_mean=%.4f (%s statistics, %.2f s)",
        name,
        summary["r2_mean"],
        summary["r2_displacement_mean"],
        "reused" if reused else "computed",
        time.perf_counter() - t_start,
    )
    return {"run_id": getattr(handle, "run_id", None), "run_name": name, "status": "FINISHED", "error": None} | summary


def _evaluate_in_run(run, cfg: Config, cache: SweepCache, root: Path) -> tuple[dict[str, Any], bool]:
    """Load (or reuse) the data and statistics, evaluate, log; returns (summary metrics, statistics reused)."""
    from aumesh.pipeline import evaluate as ev

    ev.log_clipping(cfg, run)
    source = resolve_prepared(cfg, cache.workspace_params(root), root)
    t0 = time.perf_counter()
    prepared, pid = cache.load(source, cfg)
    t1 = time.perf_counter()
    stats, reused = cache.statistics_for(prepared, pid, cfg)
    t2 = time.perf_counter()
    cv, final, same_model = cache.evaluation_for(prepared, pid, cfg, stats)
    t3 = time.perf_counter()
    if same_model:
        run.set_tags({"aumesh.cache.result": "reused (clipped n_components: same model as an earlier configuration)"})
    summary = _log_child(
        run,
        cfg,
        prepared,
        source,
        root,
        cv,
        final,
        {"seconds_load": t1 - t0, "seconds_statistics": t2 - t1, "seconds_cv_fit": t3 - t2},
        reused,
    )
    return summary, reused


# ------------------------------------------------------------------ Hydra glue
def read_parent(directory: str | Path) -> str | None:
    """The parent run id the callback wrote into a sweep (or run) directory, else ``$AUMESH_SWEEP_PARENT_RUN_ID``."""
    path = Path(directory) / PARENT_FILE
    if path.exists():
        return json.loads(path.read_text()).get("run_id")
    return os.environ.get(PARENT_ENV) or None


def _plain_config(config) -> dict[str, Any]:
    """A composed Hydra config without its ``hydra`` node, interpolations resolved."""
    from omegaconf import OmegaConf

    data = OmegaConf.to_container(config, resolve=False)
    assert isinstance(data, dict), type(data)  # a composed config is a DictConfig
    data.pop("hydra", None)
    return cast(dict[str, Any], OmegaConf.to_container(OmegaConf.create(data), resolve=True))


class SweepCallback:
    """Hydra callback: one MLflow parent run per sweep (``hydra.callbacks.aumesh_mlflow`` in conf/hydra/).

    Implements Hydra's callback protocol (``hydra.experimental.callback.Callback``) without
    importing Hydra at module import. Hydra turns callback exceptions into warnings; a job that
    finds no parent file warns and logs its run without a parent. The parent's params are the
    sweep's base configuration; the swept values are in its ``aumesh.sweep.overrides`` tag.
    """

    def __init__(self, **_: Any) -> None:
        self._t0: float | None = None
        self._progress = None  # a tqdm bar over the jobs this process launches (quiet when not on a terminal)

    # -- Hydra hooks
    def on_run_start(self, config, **kwargs: Any) -> None:
        self._start(config, Path(str(config.hydra.run.dir)), list(config.hydra.overrides.task), "run")

    def on_run_end(self, config, **kwargs: Any) -> None:
        self._end(config, Path(str(config.hydra.run.dir)))

    def on_multirun_start(self, config, **kwargs: Any) -> None:
        from aumesh.core import progress

        overrides = list(config.hydra.overrides.task)
        self._start(config, Path(str(config.hydra.sweep.dir)), overrides, "multirun")
        self._progress = progress.bar(count_jobs(overrides), "sweep", unit="config")

    def on_multirun_end(self, config, **kwargs: Any) -> None:
        if self._progress is not None:
            self._progress.close()
            self._progress = None
        self._end(config, Path(str(config.hydra.sweep.dir)))

    def on_job_start(self, config, **kwargs: Any) -> None:
        pass

    def on_job_end(self, config, job_return=None, **kwargs: Any) -> None:
        # jobs run in this process (basic launcher) advance the bar; a joblib or cluster
        # worker has its own callback instance and no bar
        if self._progress is not None:
            self._progress.update(1)

    # -- implementation
    def _start(self, config, directory: Path, overrides: list[str], mode: str) -> None:
        from aumesh.tracking import runs as tracking

        self._t0 = time.perf_counter()
        plain = _plain_config(config)
        tracking_cfg = dict(plain.get("tracking") or {})
        launcher = str(config.hydra.launcher.get("_target_", "")) if "launcher" in config.hydra else ""
        parent = tracking.start_parent_run(
            tracking_cfg,
            run_name=f"sweep {directory.name}",
            params=plain,
            tags={
                "aumesh.sweep.dir": str(directory.resolve()),
                "aumesh.sweep.overrides": " ".join(overrides),
                "aumesh.sweep.mode": mode,
                "aumesh.sweep.launcher": launcher,
                "aumesh.sweep.n_expected": count_jobs(overrides) if mode == "multirun" else 1,
            },
        )
        directory.mkdir(parents=True, exist_ok=True)
        atomic_write_json(
            directory / PARENT_FILE,
            {
                "run_id": parent,
                "tracking_uri": tracking.tracking_uri(tracking_cfg) if parent else None,
                "overrides": overrides,
            },
        )
        if parent:
            os.environ[PARENT_ENV] = parent
            log.info("sweep parent run %s (%s)", parent, directory)

    def _end(self, config, directory: Path) -> None:
        from aumesh.tracking import runs as tracking

        parent = read_parent(directory)
        os.environ.pop(PARENT_ENV, None)
        if not parent:
            return
        tracking_cfg = dict(_plain_config(config).get("tracking") or {})
        wall = time.perf_counter() - self._t0 if self._t0 else None
        children, tags = tracking.finish_sweep(parent, tracking_cfg, wall)
        if children is None:
            return
        print(
            f"\nsweep parent {parent}: {tags['aumesh.sweep.n_children']} configurations, "
            f"{tags['aumesh.sweep.n_failed']} not finished" + (f", {wall:.1f} s" if wall is not None else "")
        )
        if len(children):
            from aumesh.experiments.leaderboard import format_runs_table, runs_table

            print(format_runs_table(runs_table(children)))
        print(f"(`aumesh runs --sweep {parent}`; `aumesh promote --sweep {parent}`)")


def count_jobs(overrides: Sequence[str]) -> int:
    """Number of configurations Hydra's basic sweeper makes of ``overrides`` (the product of the sweeps)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    total = 1
    for override in OverridesParser.create().parse_overrides(list(overrides)):
        if override.is_sweep_override():
            total *= len(list(override.sweep_string_iterator()))
    return total


def _task(config) -> dict[str, Any]:
    """Hydra task function: one configuration."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    hc = HydraConfig.get()
    multirun = hc.mode == RunMode.MULTIRUN
    parent = read_parent(hc.sweep.dir if multirun else hc.run.dir)
    overrides = list(hc.overrides.task)
    if parent is None:
        log.warning(
            "no sweep parent run found in %s: is the aumesh SweepCallback configured "
            "(conf/hydra/default.yaml)? Logging this configuration without a parent.",
            hc.sweep.dir if multirun else hc.run.dir,
        )
    result = run_configuration(_plain_config(config), overrides, parent)
    atomic_write_json(Path(hc.runtime.output_dir) / RESULT_FILE, result)
    return result


def conf_dir(root: Path | None = None) -> Path:
    """The repo's ``conf/`` (absolute)."""
    from aumesh.core import provenance

    path = (root or provenance.repo_root()) / "conf"
    if not (path / "config.yaml").exists():
        raise FileNotFoundError(f"{path}/config.yaml not found: run `aumesh sweep` inside the aumesh checkout.")
    return path.resolve()


def sweep_overrides(argv: Sequence[str], stamp: str | None = None) -> list[str]:
    """The user's Hydra arguments plus literal ``hydra.sweep.dir``/``hydra.run.dir`` under build/sweeps/.

    A literal directory (not ``${now:...}``) is the same in every process of the sweep, so jobs
    in joblib workers or on cluster nodes find the parent file. User-given values win.
    """
    from aumesh.config import check_overrides

    args = list(argv)
    check_overrides([a for a in args if "=" in a])
    stamp = stamp or datetime.now().strftime("%Y-%m-%d_%H-%M-%S_%f")
    if not any(a.lstrip("+").startswith("hydra.sweep.dir=") for a in args):
        args.append(f"hydra.sweep.dir={SWEEPS_DIR}/{stamp}")
    if not any(a.lstrip("+").startswith("hydra.run.dir=") for a in args):
        args.append(f"hydra.run.dir={SWEEPS_DIR}/{stamp}")
    return args


@dataclass(frozen=True)
class SweepOutcome:
    """What a sweep ran: its folder, parent run, and how many configurations did not finish."""

    directory: Path
    parent_run_id: str | None
    n_jobs: int
    n_failed: int


def outcome(directory: Path, expected_jobs: int) -> SweepOutcome:
    """Count the jobs' ``result.json`` under a sweep folder; a job without one (it died) counts as failed.

    Before any job started (Hydra's ``--help``, ``--cfg``) there is no parent file and nothing counts.
    """
    if not (directory / PARENT_FILE).is_file():
        return SweepOutcome(directory, None, 0, 0)
    results = [json.loads(p.read_text()) for p in sorted(directory.rglob(RESULT_FILE))]
    failed = sum(1 for r in results if r.get("status") != "FINISHED") + max(0, expected_jobs - len(results))
    return SweepOutcome(directory, read_parent(directory), max(expected_jobs, len(results)), failed)


def _hydra_value(args: Sequence[str], key: str) -> str | None:
    return next((a.split("=", 1)[1] for a in args if a.lstrip("+").startswith(f"{key}=")), None)


def run_sweep(argv: Sequence[str]) -> SweepOutcome:
    """``aumesh sweep [-m] key=v1,v2 ...``: run the Hydra app on the repo's conf/ from the repo root.

    The working directory becomes the workspace root (``conf/paths`` are relative to it). A configuration
    that fails is a FAILED child and the sweep goes on; the returned :class:`SweepOutcome` counts them.
    """
    import hydra

    from aumesh.core import provenance

    root = provenance.repo_root()
    conf = conf_dir(root)
    if Path.cwd().resolve() != root.resolve():
        log.info("running from the workspace root %s (conf/paths are relative to it)", root)
        os.chdir(root)
    args = sweep_overrides(argv)
    multirun = "-m" in args or "--multirun" in args
    directory = Path(_hydra_value(args, "hydra.sweep.dir" if multirun else "hydra.run.dir") or ".")
    expected = count_jobs([a for a in args if "=" in a and not a.startswith("-")]) if multirun else 1
    app = hydra.main(config_path=str(conf), config_name="config", version_base=None)(_task)
    saved = sys.argv
    sys.argv = ["aumesh-sweep", *args]
    try:
        app()
    except KeyboardInterrupt as err:  # Ctrl-C or SIGTERM: the running child is KILLED (tracked_run); now the parent
        raise interrupted(directory, expected, err) from err
    finally:
        sys.argv = saved
        from hydra.core.global_hydra import GlobalHydra

        GlobalHydra.instance().clear()  # so config.compose() works again in this process
    return outcome(directory, expected)


def interrupted(directory: Path, expected: int, err: KeyboardInterrupt) -> KeyboardInterrupt:
    """Mark an interrupted sweep's parent, and any child still RUNNING, KILLED (tag ``aumesh.sweep.interrupted``:
    ``aumesh promote`` refuses the sweep without ``--partial``); return the one-line
    :class:`aumesh.core.signals.Interrupted` to raise."""
    import signal

    from aumesh.core.signals import Interrupted, Terminated
    from aumesh.tracking import queries
    from aumesh.tracking import runs as tracking

    signum = signal.SIGTERM if isinstance(err, Terminated) else signal.SIGINT
    how = f"stopped: {err}" if isinstance(err, Terminated) else "Ctrl-C"
    parent = read_parent(directory) if (directory / PARENT_FILE).is_file() else None
    os.environ.pop(PARENT_ENV, None)
    if parent is None:
        return Interrupted(f"interrupted ({how}) before the sweep started; nothing was logged", signum)
    tracking_cfg: dict[str, Any] = {}
    with contextlib.suppress(Exception):
        from aumesh.config import load_params

        tracking_cfg = dict(load_params("params.yaml").tracking.__dict__)
    children = queries.list_child_runs(parent, tracking_cfg)
    done = int(children["status"].isin(["FINISHED", "FAILED"]).sum()) if len(children) else 0
    finished = int((children["status"] == "FINISHED").sum()) if len(children) else 0
    summary = f"interrupted after {done} of {expected} runs"
    killed = []
    client = tracking.get_client(tracking_cfg)
    for row in children.itertuples() if len(children) else ():
        if row.status == "RUNNING":  # a child in another process (joblib) that did not close its run
            client.set_tag(row.run_id, tracking.ERROR_TAG, f"sweep {summary} ({how})")
            client.set_terminated(row.run_id, "KILLED")
        if row.status in ("RUNNING", "KILLED"):
            killed.append(row.run_name)
    tracking.set_run_tags(
        parent,
        {
            "aumesh.sweep.interrupted": f"{summary} ({how})",
            "aumesh.sweep.n_children": len(children),
            "aumesh.sweep.n_finished": finished,
            "aumesh.sweep.n_failed": len(children) - finished,
            tracking.ERROR_TAG: f"sweep {summary} ({how})",
        },
        tracking_cfg,
    )
    tracking.end_run(parent, tracking_cfg, "KILLED")
    return Interrupted(
        f"{summary} ({how}): sweep {parent} and its running configuration "
        f"{', '.join(killed) or '(none)'} marked KILLED; `aumesh promote` refuses it without --partial",
        signum,
    )


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m aumesh.experiments.sweep``: exit 1 when a configuration failed (``aumesh sweep`` adds ``--allow-failures``)."""
    return 1 if run_sweep(sys.argv[1:] if argv is None else argv).n_failed else 0


if __name__ == "__main__":  # python -m aumesh.experiments.sweep -m key=v1,v2
    sys.exit(main())
