"""The evaluate stage: cross-validation and the final fit (``paths.model_dir``, metrics, plots), tracked in MLflow."""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from aumesh.config import Config
from aumesh.core.io import atomic_directory, atomic_write_json
from aumesh.pipeline import run_record
from aumesh.pipeline.model_files import (
    CARD_ERROR_CURVE_POINTS,
    CV_NPZ,
    FRAME_ERROR_FILE,
    METRICS_JSON,
    MODEL_NPZ,
    TRACKING_JSON,
)
from aumesh.pipeline.release import refuse_nonfinite
from aumesh.stages.common import check_columns, data_digest, start_stage

if TYPE_CHECKING:
    from aumesh.pipeline.evaluate.prepared_data import Prepared
    from aumesh.pipeline.evaluate.results import CVResult, FinalModel


def run_evaluation(prepared: Prepared, cfg: Config, handle, params: dict, digest: dict) -> tuple[CVResult, FinalModel]:
    """Evaluate one configuration and log it to an open MLflow run ``handle``
    (:class:`aumesh.tracking.beside.RunBeside`) as every evaluation run records it (:mod:`aumesh.pipeline.run_record`;
    the stage's own: metric ``evaluate_seconds``). ``params``: what the run was opened with; ``digest``:
    ``data.dvc``'s (:func:`aumesh.stages.common.data_digest`)."""
    from aumesh.pipeline import evaluate as ev

    run_record.log_clipping(cfg, handle)
    degenerate = run_record.log_inputs(handle, cfg, prepared, params, digest, Path.cwd())
    t0 = time.perf_counter()
    cv, final = ev.cross_validate_and_fit(prepared, cfg)
    cv.extra["degenerate"] = degenerate
    timings = {"evaluate_seconds": time.perf_counter() - t0}
    # drawn and logged by the tracking helper, beside the rest of the stage
    handle.call(run_record.log_results, run_record.results_record(cfg, cv, final, metrics=timings))
    return cv, final


def evaluate_run_name(cfg: Config) -> str:
    """The MLflow run name of a pipeline evaluation: what tells it apart in the run list.

    ``"<target> <features> k=<n_components>"`` (``neutral`` adds its neutral method, ``model/eiv`` its correction:
    ``" eiv=corrected"``), prefixed with the DVC
    experiment's name when DVC runs the stage as an experiment (``DVC_EXP_NAME``, set by ``dvc exp run``
    and queued runs), e.g. ``"bumpy-tods: absolute au_pose_interactions k=40"``.
    """
    target = cfg.preprocess.target
    if target == "neutral":
        target += f"({cfg.preprocess.neutral.method})"
    name = f"{target} {cfg.features.name} k={cfg.model.n_components}"
    if cfg.model.eiv.method != "none":  # a corrected fit is another model of the same rows: say which
        name += f" eiv={cfg.model.eiv.method}"
    exp = os.environ.get("DVC_EXP_NAME")
    return f"{exp}: {name}" if exp else name


def main(cfg: Config) -> dict:
    """Cross-validate and fit the prepared data into ``paths.model_dir`` (and the metrics and plot files DVC
    compares), recorded as one MLflow run; returns the CV metrics (``metrics.json``)."""
    from aumesh.pipeline import dvc_metrics
    from aumesh.pipeline.evaluate.eiv_fits import check_eiv_inputs
    from aumesh.pipeline.evaluate.prepared_data import load_prepared
    from aumesh.tracking import mlflow_store
    from aumesh.tracking import runs as tracking
    from aumesh.tracking.beside import tracked_run_beside
    from aumesh.tracking.connection import TrackingServerError

    start_stage("evaluate", cfg)
    params = cfg.to_dict()
    tracking_cfg = params["tracking"]
    # the tracking store before any work, not after the whole CV: a damaged or locked SQLite store, a server or
    # database that does not answer (one line naming its URI and where that came from)
    mlflow_store.check_tracking(tracking_cfg)
    check_columns(cfg)
    check_eiv_inputs(cfg)  # a bad covariance file stops the stage before any pass
    prepared = load_prepared(cfg.paths.prepared_dir)
    digest = data_digest()
    out = Path(cfg.paths.model_dir)
    try:
        # MLflow (imported and opened in a helper process) works beside the passes; the logging below is queued to it
        with tracked_run_beside(
            tracking_cfg,
            run_name=evaluate_run_name(cfg),
            params=params,
            tags=run_record.run_tags("evaluate", cfg.preprocess.target),
        ) as run:
            cv, final = run_evaluation(prepared, cfg, run, params, digest)
            metrics = cv.metrics()
            arrays = run_record.model_arrays(cfg, prepared, cv, final, run.run_id)
            refuse_nonfinite(arrays, Path(cfg.paths.prepared_dir))  # before the model is logged or anything written
            run.call(run_record.log_model, arrays)
            run_info = {
                "run_id": run.run_id,
                "run_name": evaluate_run_name(cfg) if cfg.tracking.enabled else None,
                "experiment_id": getattr(run, "experiment_id", None),
                # the card built from this is shared: the workspace's store repo-relative (sqlite:///mlflow.db),
                # never a server's address (the run id finds the run there)
                "tracking_uri": tracking.store_label(tracking_cfg) if cfg.tracking.enabled else None,
            }
            with atomic_directory(out) as tmp:
                write_model_dir(tmp, cv, final, metrics, run_info | {"data_digest": digest})
                run.log_artifact(tmp / METRICS_JSON)
                # every logging call done and the run FINISHED before the folder is swapped in: build/model never
                # names a run that failed (a lost server ends here, and the previous build/model stays)
                run.finish()
    except TrackingServerError as err:
        raise err.noted(f"nothing of this run was published ({out}/, {cfg.paths.metrics_file} as they were)") from err
    dvc_metrics.write(cfg.paths, metrics, cv.frame_vertex_error, cv.r2_path_folds)  # committed: `dvc metrics diff`
    return metrics


def write_model_dir(tmp: Path, cv: CVResult, final: FinalModel, metrics: dict, run_info: dict) -> None:
    """The files of ``paths.model_dir`` into the folder ``tmp`` (swapped in by the caller): the model's arrays
    (``model.npz``), the CV's curves (``cv.npz``), the per-frame errors, ``tracking.json`` (``run_info`` and the
    degenerate inputs) and ``metrics.json``."""
    from aumesh.pipeline import dvc_metrics

    model_arrays: dict[str, Any] = {
        "coef": final.coef,
        "raw_intercept": final.raw_intercept,
        "mesh_intercept": final.mesh_intercept,
        "feature_columns": np.array(final.feature_columns),
        "n_components": np.array(final.n_components, dtype=np.int32),
    }
    if final.uncorrected_coef is not None:  # model/eiv: the card's fit of the same rows, beside the corrected
        model_arrays["coef_uncorrected"] = final.uncorrected_coef
    if final.identification is not None:
        model_arrays |= final.identification.release_arrays()
    np.savez(tmp / MODEL_NPZ, **model_arrays)
    thresholds, fraction = dvc_metrics.error_curve(cv.frame_vertex_error, CARD_ERROR_CURVE_POINTS)
    np.savez(
        tmp / CV_NPZ,
        r2_per_vertex=cv.r2_per_vertex,
        r2_per_target=cv.r2_per_target,
        r2_path_folds=cv.r2_path_folds,
        vertex_error_per_vertex=cv.vertex_error_per_vertex,
        cumulative_error_thresholds=thresholds,
        cumulative_error_fraction=fraction,
    )
    shutil.copyfile(cv.frame_vertex_error.path, tmp / FRAME_ERROR_FILE)  # per frame, frames.parquet's order
    atomic_write_json(tmp / TRACKING_JSON, run_info | {"degenerate": cv.extra.get("degenerate", {})})
    atomic_write_json(tmp / METRICS_JSON, metrics)
