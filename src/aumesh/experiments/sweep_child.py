"""One configuration of a sweep as an MLflow child run: validated, evaluated (from the cache) and recorded.

Each job opens a child run (:func:`aumesh.tracking.runs.tracked_run`) under the sweep's parent and records it as every
evaluation run does (:mod:`aumesh.pipeline.run_record`: flattened params, provenance tags, per-fold metrics and
their means, the R²-vs-n_components curve and figure, the release model as an MLflow pyfunc model under ``model/``),
plus what only a sweep child has: tags ``aumesh.role`` = ``sweep-child``, ``aumesh.sweep.overrides``, where its
prepared data came from and what the cache reused (:mod:`aumesh.experiments.sweep_cache`), and its timings
(``seconds_load``, ``seconds_statistics``, ``seconds_cv_fit``, ``seconds_job``). A configuration that raises (e.g. a
data or config error) is recorded as a FAILED child with the error; :func:`run_configuration` never raises for it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aumesh.experiments.sweep_cache import SweepCache, process_cache, resolve_prepared
from aumesh.pipeline import run_record

if TYPE_CHECKING:  # pragma: no cover
    from aumesh.config import Config

log = logging.getLogger(__name__)

CHILD_ROLE = "sweep-child"
# BLAS threads per job: a sweep parallelises over configurations (hydra/launcher=joblib), not inside
# the small (p x p, p x 1434) products of one fit, where extra threads only contend (10x slower on
# a busy 2-core box). Set AUMESH_SWEEP_BLAS_THREADS=0 to leave the BLAS default.
BLAS_THREADS_ENV = "AUMESH_SWEEP_BLAS_THREADS"


def run_name(overrides: Sequence[str]) -> str:
    """Compact child run name from a job's overrides: ``target=neutral,pose=true,n_components=10`` (never those of
    :data:`aumesh.config.WHERE_GROUPS`: :func:`aumesh.config.recorded_overrides`)."""
    from aumesh.config import recorded_overrides

    parts = []
    for ov in recorded_overrides(overrides):
        key, sep, value = ov.partition("=")
        if not sep or key.startswith("hydra"):
            continue
        parts.append(f"{key.lstrip('+~').rsplit('.', 1)[-1]}={value}")
    return ",".join(parts) or "base"


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


def run_configuration(
    raw: Mapping[str, Any],
    overrides: Sequence[str] = (),
    parent_run_id: str | None = None,
    cache: SweepCache | None = None,
    root: Path | None = None,
    feature_sets: Sequence[str] = (),
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
        Defaults to :func:`aumesh.experiments.sweep_cache.process_cache`.
    root : Path, optional
        Workspace root; defaults to :func:`aumesh.core.provenance.repo_root`.
    feature_sets : sequence of str
        Every ``features`` option of the sweep (:func:`aumesh.experiments.sweep.read_feature_sets`): the statistics
        pass accumulates the union of their designs once, for every configuration.

    Returns
    -------
    dict
        ``run_id``, ``run_name``, ``status`` (``FINISHED``/``FAILED``), ``error`` and summary metrics.
    """
    from aumesh.config import from_dict, recorded_overrides
    from aumesh.core import provenance
    from aumesh.tracking import runs as tracking

    cache = cache or process_cache()
    root = Path(root) if root is not None else provenance.repo_root()
    raw = dict(raw)
    tracking_cfg = dict(raw.get("tracking") or {})
    name = run_name(overrides)
    tags = {
        tracking.ROLE_TAG: CHILD_ROLE,
        **run_record.run_tags("sweep", (raw.get("preprocess") or {}).get("target"), _family(raw)),
        "aumesh.sweep.overrides": " ".join(recorded_overrides(overrides)),
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
                summary, reused = _evaluate_in_run(run, cfg, cache, root, raw, feature_sets)
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


def _family(raw: Mapping[str, Any]) -> str | None:
    """The input family of a composed configuration's ``features.name`` (None when it names no feature set: the
    configuration then fails validation in its run)."""
    from aumesh.core.families import FEATURE_SETS

    spec = FEATURE_SETS.get(str((raw.get("features") or {}).get("name")))
    return spec[0] if spec else None


def _evaluate_in_run(
    run, cfg: Config, cache: SweepCache, root: Path, opened: Mapping[str, Any], feature_sets: Sequence[str] = ()
) -> tuple[dict[str, Any], bool]:
    """Load (or reuse) the data and statistics, evaluate, and record the run as every evaluation run is recorded
    (:mod:`aumesh.pipeline.run_record`; ``opened``: the params the run was opened with); returns (summary metrics,
    statistics reused)."""
    from aumesh.core import provenance

    run_record.log_clipping(cfg, run)  # before any work: more components than features fails here
    source = resolve_prepared(cfg, cache.workspace_params(root), root)
    t0 = time.perf_counter()
    prepared, pid = cache.load(source, cfg)
    t1 = time.perf_counter()
    digest = None
    with contextlib.suppress(FileNotFoundError, ValueError):
        digest = provenance.data_digest(root, "data.dvc")
    run_record.log_inputs(run, cfg, prepared, opened, digest, root)
    t2 = time.perf_counter()
    stats, reused = cache.statistics_for(prepared, pid, cfg, feature_sets)
    t3 = time.perf_counter()
    cv, final, same_model = cache.evaluation_for(prepared, pid, cfg, stats)
    t4 = time.perf_counter()
    tags = {
        "aumesh.prepared_dir": str(source.path),
        "aumesh.prepared.key": source.key,
        "aumesh.cache.statistics": "reused" if reused else "computed",
        # the pass over the meshes (the union of the sweep's designs): computed by the first configuration only
        "aumesh.cache.pass": "reused" if reused or cache.pass_reused else "computed",
    }
    if same_model:
        tags["aumesh.cache.result"] = "reused (clipped n_components: same model as an earlier configuration)"
    timings = {"seconds_load": t1 - t0, "seconds_statistics": t3 - t2, "seconds_cv_fit": t4 - t3}
    record = run_record.results_record(cfg, cv, final, metrics=timings, tags=tags)
    run_record.log_results(run, record)
    # the data's support travels with the model (the promoted sweep child's model is the registered one)
    run_record.log_model(run, run_record.model_arrays(cfg, prepared, cv, final, run.run_id))
    summary = {k: record.metrics[k] for k in ("r2_mean", "r2_std", "r2_displacement_mean", "mae_mean", "n_components")}
    return summary, reused
