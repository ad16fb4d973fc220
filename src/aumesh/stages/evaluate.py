"""The evaluate stage: cross-validation and the final fit (``paths.model_dir``, metrics, plots), tracked in MLflow; and,
from the same statistics pass, each input family's fit (``families``: ``paths.families_model_dir``/<family>,
``paths.families_metrics_file``), each its own MLflow run (issue 46)."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from aumesh.config import FAMILY_OFF, Config
from aumesh.core.io import atomic_directory, atomic_write_json
from aumesh.pipeline import run_record
from aumesh.pipeline.model_files import (
    CARD_ERROR_CURVE_POINTS,
    CV_NPZ,
    FRAME_ERROR_FILE,
    METRICS_JSON,
    MODEL_NPZ,
    SKIPPED_JSON,
    TRACKING_JSON,
)
from aumesh.pipeline.release import refuse_nonfinite
from aumesh.stages.common import check_columns, data_digest, start_stage

if TYPE_CHECKING:
    from aumesh.pipeline.evaluate.prepared_data import Prepared
    from aumesh.pipeline.evaluate.results import CVResult, FinalModel

log = logging.getLogger(__name__)

#: tag of a family fit whose ``model/eiv`` was set aside (the correction is the AU detector's: the family's is none)
EIV_NOTE_TAG = "aumesh.family.eiv"


def family_configs(cfg: Config) -> list[tuple[str, Config, str | None]]:
    """Each configured input family's configuration (``families.items()``): ``cfg`` with ``features`` :=
    ``families.<f>.features`` and ``model.n_components`` := ``families.<f>.n_components`` (null: ``model.n_components``
    clipped to the design's width), fitted with ``model/eiv=none`` (the corrections are the AU detector's); returns
    ``(family, its config, note)``, the note saying when ``model/eiv`` was set aside (None otherwise). A family set to
    ``none`` is left out."""
    from aumesh.config import EivConfig, FeaturesConfig, validate
    from aumesh.core.families import feature_set_columns

    out = []
    for family, spec in cfg.families.items():
        if spec.features == FAMILY_OFF:
            continue
        width = len(feature_set_columns(spec.features))
        k = spec.n_components if spec.n_components is not None else min(cfg.model.n_components, width)
        note = None
        if cfg.model.eiv.method != "none":
            note = (
                f"model/eiv={cfg.model.eiv.method} corrects the AU detector's noise: the {family} family is fitted "
                "with model/eiv=none"
            )
        model = dataclasses.replace(cfg.model, n_components=k, eiv=EivConfig())
        out.append(
            (family, validate(dataclasses.replace(cfg, features=FeaturesConfig(spec.features), model=model)), note)
        )
    return out


def run_evaluation(
    prepared: Prepared, cfg: Config, handle, params: dict, digest: dict, shared=None
) -> tuple[CVResult, FinalModel]:
    """Evaluate one configuration and log it to an open MLflow run ``handle``
    (:class:`aumesh.tracking.beside.RunBeside`) as every evaluation run records it (:mod:`aumesh.pipeline.run_record`;
    the stage's own: metric ``evaluate_seconds``). ``params``: what the run was opened with; ``digest``:
    ``data.dvc``'s (:func:`aumesh.stages.common.data_digest`); ``shared``: the stage's one statistics pass
    (:class:`aumesh.pipeline.evaluate.SharedPass`), None for a pass of this configuration alone."""
    from aumesh.pipeline import evaluate as ev

    run_record.log_clipping(cfg, handle)
    degenerate = run_record.log_inputs(handle, cfg, prepared, params, digest, Path.cwd())
    t0 = time.perf_counter()
    cv, final = ev.cross_validate_and_fit(prepared, cfg, shared)
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
    from aumesh.core.errors import ConfigError
    from aumesh.model.pass_design import design_union
    from aumesh.pipeline import dvc_metrics
    from aumesh.pipeline import evaluate as ev
    from aumesh.pipeline.evaluate.eiv_fits import check_eiv_inputs
    from aumesh.pipeline.evaluate.prepared_data import load_prepared
    from aumesh.pipeline.evaluate.statistics_pass import check_family_columns
    from aumesh.tracking import mlflow_store
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
    # the model of ``features`` needs its inputs (one line naming the file, the family and the fix, before any pass);
    # a configured family the prepared frames lack is not fitted: one warning line naming the file, family and fix
    check_family_columns(prepared, design_union([cfg.features.name]))
    families = []
    # families not fitted, and why: their folder holds SKIPPED_JSON, so release_family@<family> (whose dvc.yaml dep the
    # folder is) writes a release that says so instead of failing on a missing dependency
    skipped = {f: f"families.{f}.features=none" for f, spec in cfg.families.items() if spec.features == FAMILY_OFF}
    for family, fcfg, note in family_configs(cfg):
        try:
            check_family_columns(prepared, design_union([fcfg.features.name]))
        except ConfigError as err:
            # info, not a warning: tables without a family are an AU-only project; release_family@<family> warns
            log.info("evaluate: families.%s not fitted: %s", family, err)
            skipped[family] = str(err)
            continue
        families.append((family, fcfg, note))
    shared = ev.SharedPass([f.features.name for _, f, _ in families])  # one statistics pass for every fit
    digest = data_digest()
    out, families_out = Path(cfg.paths.model_dir), Path(cfg.paths.families_model_dir)
    family_metrics: dict[str, dict] = {}
    try:
        with contextlib.ExitStack() as stack:
            # MLflow (imported and opened in helper processes) works beside the passes; the logging below is queued to
            # them. Every run is opened now (their imports beside the pass) and ends with the stage: a failure anywhere
            # marks each FAILED and publishes nothing (build/model, build/families and the metrics stay as they were)
            run = stack.enter_context(
                tracked_run_beside(
                    tracking_cfg,
                    run_name=evaluate_run_name(cfg),
                    params=params,
                    tags=run_record.run_tags("evaluate", cfg.preprocess.target),
                )
            )
            family_runs = {
                family: stack.enter_context(
                    tracked_run_beside(
                        tracking_cfg,
                        run_name=evaluate_run_name(fcfg),
                        params=fcfg.to_dict(),
                        tags=run_record.run_tags("evaluate", fcfg.preprocess.target),
                    )
                )
                for family, fcfg, _ in families
            }
            cv, final = run_evaluation(prepared, cfg, run, params, digest, shared)
            metrics = cv.metrics()
            arrays = run_record.model_arrays(cfg, prepared, cv, final, run.run_id)
            refuse_nonfinite(arrays, Path(cfg.paths.prepared_dir))  # before the model is logged or anything written
            run.call(run_record.log_model, arrays)
            family_results = {}
            for family, fcfg, note in families:
                frun = family_runs[family]
                if note is not None:
                    log.warning("evaluate: %s", note)
                    frun.set_tags({EIV_NOTE_TAG: note})
                fcv, ffinal = run_evaluation(prepared, fcfg, frun, fcfg.to_dict(), digest, shared)
                farrays = run_record.model_arrays(fcfg, prepared, fcv, ffinal, frun.run_id)
                refuse_nonfinite(farrays, Path(cfg.paths.prepared_dir))
                frun.call(run_record.log_model, farrays)
                family_metrics[family] = fcv.metrics()
                family_results[family] = (fcv, ffinal, note)
            tmp = stack.enter_context(atomic_directory(out))
            write_model_dir(tmp, cv, final, metrics, _run_info(cfg, run, tracking_cfg) | {"data_digest": digest})
            run.log_artifact(tmp / METRICS_JSON)
            families_tmp = stack.enter_context(atomic_directory(families_out))
            for family, (fcv, ffinal, note) in family_results.items():
                folder = families_tmp / family
                folder.mkdir()
                fcfg = next(f for name, f, _ in families if name == family)
                info = _run_info(fcfg, family_runs[family], tracking_cfg) | {"data_digest": digest, "family": family}
                if note is not None:
                    info["eiv_note"] = note
                write_model_dir(folder, fcv, ffinal, family_metrics[family], info, family=family)
                family_runs[family].log_artifact(folder / METRICS_JSON)
            for family, reason in skipped.items():
                (families_tmp / family).mkdir()
                atomic_write_json(families_tmp / family / SKIPPED_JSON, {"family": family, "reason": reason})
            # every logging call done and every run FINISHED before the folders are swapped in (the ExitStack unwinds:
            # build/families, then build/model): no folder names a run that failed (a lost server ends here, and the
            # previous folders stay)
            for handle in (run, *family_runs.values()):
                handle.finish()
    except TrackingServerError as err:
        raise err.noted(
            f"nothing of this run was published ({out}/, {families_out}/, {cfg.paths.metrics_file} as they were)"
        ) from err
    dvc_metrics.write(cfg.paths, metrics, cv.frame_vertex_error, cv.r2_path_folds)  # committed: `dvc metrics diff`
    atomic_write_json(cfg.paths.families_metrics_file, dvc_metrics.rounded(family_metrics))
    return metrics


def _run_info(cfg: Config, run, tracking_cfg: dict) -> dict:
    """What ``tracking.json`` says of the run that fitted a model folder."""
    from aumesh.tracking import runs as tracking

    return {
        "run_id": run.run_id,
        "run_name": evaluate_run_name(cfg) if cfg.tracking.enabled else None,
        "experiment_id": getattr(run, "experiment_id", None),
        # the card built from this is shared: the workspace's store repo-relative (sqlite:///mlflow.db),
        # never a server's address (the run id finds the run there)
        "tracking_uri": tracking.store_label(tracking_cfg) if cfg.tracking.enabled else None,
    }


def write_model_dir(
    tmp: Path, cv: CVResult, final: FinalModel, metrics: dict, run_info: dict, family: str | None = None
) -> None:
    """The files of ``paths.model_dir`` into the folder ``tmp`` (swapped in by the caller): the model's arrays
    (``model.npz``), the CV's curves (``cv.npz``), the per-frame errors, ``tracking.json`` (``run_info`` and the
    degenerate inputs) and ``metrics.json``. A family's folder (``paths.families_model_dir``/<family>) has the same
    files, and ``model.npz`` a str scalar ``family``."""
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
    if family is not None:
        model_arrays["family"] = np.array(family)
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
