"""The DVC stages' entry points: load params.yaml, call one typed function, write outputs.

``dvc.yaml`` runs ``aumesh prepare``, ``aumesh evaluate`` and ``aumesh release`` from the
repo root; paths come from ``cfg.paths`` (relative to the stage's working directory, so a
DVC queued experiment writes into its own temporary copy). Only MLflow goes to the workspace.
The stages' passes get those paths made absolute (``aumesh.utils.io.absolute``: a cluster's workers run in
directories of their own); the outputs record them as given (``aumesh.utils.io.recorded``), never this machine's
workspace path.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from aumesh.config import Config, PathsConfig
from aumesh.experiments import provenance
from aumesh.model.release import CARD_JSON, CARD_MD, NPZ_NAME, model_card_markdown, release_arrays
from aumesh.pipeline import integrity
from aumesh.pipeline.prepared_files import FRAMES_FILE, REFERENCE_FILE
from aumesh.utils.io import (
    atomic_directory,
    atomic_savez,
    atomic_write_json,
    atomic_write_text,
    remove_stale_temporaries,
)

if TYPE_CHECKING:
    from aumesh.pipeline import evaluate as ev

log = logging.getLogger(__name__)

MODEL_NPZ = "model.npz"
CV_NPZ = "cv.npz"
#: Points of the cumulative vertex error curve ``cv.npz`` keeps for the card's figure (the empirical CDF at the
#: 0, 0.1, ..., 100 % quantiles: finer than the figure's pixels, and a fixed size whatever the frames).
CARD_ERROR_CURVE_POINTS = 1001
TRACKING_JSON = "tracking.json"
METRICS_JSON = "metrics.json"


def data_digest(dvc_file: str = "data.dvc") -> dict[str, Any]:
    """The DVC hash of the frame tables; outside a DVC workspace, a marked placeholder (never silently absent)."""
    try:
        return provenance.data_digest(Path.cwd(), dvc_file)
    except FileNotFoundError as err:
        log.warning("%s", err)
        return {"md5": None, "note": f"{dvc_file} not found: data not tracked by DVC"}


def stage_outputs(stage: str, paths: PathsConfig) -> list[str]:
    """The outputs ``dvc.yaml`` declares for ``stage`` (prepare, evaluate, release)."""
    return {
        "ingest": [paths.ingested_dir],
        "prepare": [paths.prepared_dir],
        "evaluate": [paths.model_dir, paths.metrics_file, paths.error_curve_file, paths.r2_curve_file],
        "release": [paths.release_dir],
    }.get(stage, [])


def start_stage(stage: str, cfg: Config) -> None:
    """Remove what a killed earlier run of ``stage`` left behind (temp folders and files of its outputs, and the
    evaluate passes' scratch folders)."""
    scratch: list[str | Path] = []
    if stage == "evaluate":
        from aumesh.pipeline import evaluate as ev

        scratch.append(ev.scratch_path(cfg.paths.prepared_dir))
    for out in [*stage_outputs(stage, cfg.paths), *scratch]:
        for path in remove_stale_temporaries(out):
            log.info("removed %s, left by a killed run", path)


def removed_by_dvc(stage: str, lock_file: str | Path = "dvc.lock") -> str | None:
    """When DVC runs ``stage`` (``DVC_STAGE``) and removed outputs that ``dvc.lock`` records (a last good version in
    DVC's cache), the one command that brings them back. ``release/`` is ``persist: true``: DVC never removes it."""
    import yaml

    if os.environ.get("DVC_STAGE", "").rsplit(":", 1)[-1] != stage or not Path(lock_file).exists():
        return None
    try:
        locked = yaml.safe_load(Path(lock_file).read_text())["stages"][stage]["outs"]
    except (KeyError, TypeError, yaml.YAMLError):
        return None
    missing = [out["path"] for out in locked if not Path(out["path"]).exists()]
    if not missing:
        return None
    return f"DVC removed {', '.join(missing)} before running {stage}: `dvc checkout {stage}` brings back the last good one."


def check_columns(cfg: Config, columns: list[str] | None = None, where: str | None = None) -> None:
    """Keys of the configuration that name a column, checked against the data before any work (``columns``: the
    data's columns, read from ``where``; default: the prepared frames' ``frames.parquet`` schema).

    ``cv.group``: the cross-validation keeps each group's frames in one fold, and its per-video statistics (the
    neutral meshes, the displacement target) make the video the only grouping it can run; an unknown name was
    ignored before (the same CV ran, and the name was printed in the card as if it had been used).
    """
    from aumesh.data.schema import VIDEO_COLUMN
    from aumesh.utils.errors import ConfigError

    group = cfg.cv.group
    if group == VIDEO_COLUMN:
        return
    if columns is None:
        import pyarrow.parquet as pq

        path = Path(cfg.paths.prepared_dir) / FRAMES_FILE
        where = where or str(path)
        columns = pq.read_schema(path).names if path.exists() else []
    import re

    mesh = [c for c in columns if re.fullmatch(r"[xyz]_\d+", c)]  # 1,434 mesh columns: named as a range
    names = ", ".join(
        [repr(c) for c in columns if c not in set(mesh)] + (["the mesh columns x_0..z_477"] if mesh else [])
    )
    if group not in columns:
        raise ConfigError(
            f"cv.group={group!r} names no column of {where} (its columns: {names}). "
            f"Fix: cv.group={VIDEO_COLUMN} (the video column: the only grouping the CV supports)."
        )
    raise ConfigError(
        f"cv.group={group!r}: the cross-validation groups frames by video only (each video's frames in "
        f"one fold; its per-video neutral meshes need that). Fix: cv.group={VIDEO_COLUMN}."
    )


# Each stage imports only what it runs (a stage is a process of its own: scikit-learn, MLflow, pandera or
# matplotlib imported for nothing cost seconds of every `dvc repro`).


def ingest_stage(cfg: Config) -> dict:
    from aumesh.pipeline import ingest

    start_stage("ingest", cfg)
    return ingest.run(cfg, cfg.paths.ingested_dir)


def prepare_stage(cfg: Config) -> dict:
    from aumesh.data import tables
    from aumesh.pipeline import ingest
    from aumesh.pipeline import prepare as prep

    start_stage("prepare", cfg)
    manifest = ingest.load_manifest(cfg.paths.ingested_dir)
    found = tables.check_tables(manifest["tables"], cfg.data.mesh_npy, cfg.data.coerce_numeric)
    if found:  # keys naming a column, before the passes (the first table's columns: the contract makes them alike)
        import pyarrow.parquet as pq

        check_columns(cfg, pq.read_schema(found[0].path).names, str(found[0].path))
    from aumesh.model import support

    summary = prep.run(
        found, cfg, cfg.paths.prepared_dir, ingested=manifest["counts"], detectors=support.detector_counts(manifest)
    )
    log.info("prepared %d frames of %d videos: %s", summary["n_frames"], summary["n_videos"], summary["counts"])
    return summary


def run_evaluation(prepared: ev.Prepared, cfg: Config, handle) -> tuple[ev.CVResult, ev.FinalModel]:
    """Evaluate one configuration and log it to an open MLflow run ``handle`` (tracking.TrackedRun)."""
    from aumesh.pipeline import evaluate as ev

    timings = {}
    ev.log_clipping(cfg, handle)
    degenerate = ev.log_degenerate(prepared, cfg, handle)
    t0 = time.perf_counter()
    cv, final = ev.evaluate(prepared, cfg)
    cv.extra["degenerate"] = degenerate
    timings["evaluate_seconds"] = time.perf_counter() - t0
    handle.log_fold_metrics(
        {
            "r2": cv.r2_folds,
            "mae": cv.mae_folds,
            "vertex_error": cv.vertex_error_folds,
            "r2_displacement": cv.r2_displacement_folds,
        }
    )
    handle.log_metrics(cv.scalar_metrics() | timings)
    counts = prepared.summary.get("counts", {})  # what the filters dropped, as counts and fractions
    handle.log_metrics(
        {f"data.{k}": float(v) for k, v in counts.items() if k.startswith(("dropped", "videos_dropped"))}
    )
    # the R²-vs-n_components curve, step = n_components, in one transaction
    handle.log_metric_history("r2_by_n_components", cv.r2_path_folds.mean(axis=0), first_step=1)
    return cv, final


def evaluate_run_name(cfg: Config) -> str:
    """The MLflow run name of a pipeline evaluation: what tells it apart in the run list.

    ``"<target> <features> k=<n_components>"`` (``neutral`` adds its neutral method), prefixed with the DVC
    experiment's name when DVC runs the stage as an experiment (``DVC_EXP_NAME``, set by ``dvc exp run``
    and queued runs), e.g. ``"bumpy-tods: absolute au_pose_interactions k=40"``.
    """
    target = cfg.preprocess.target
    if target == "neutral":
        target += f"({cfg.preprocess.neutral.method})"
    name = f"{target} {cfg.features.name} k={cfg.model.n_components}"
    exp = os.environ.get("DVC_EXP_NAME")
    return f"{exp}: {name}" if exp else name


def evaluate_stage(cfg: Config) -> dict:
    from aumesh.experiments import mlflow_store, tracking
    from aumesh.model import support
    from aumesh.pipeline import dvc_metrics
    from aumesh.pipeline import evaluate as ev

    start_stage("evaluate", cfg)
    params = cfg.to_dict()
    tracking_cfg = params["tracking"]
    if cfg.tracking.enabled:  # a damaged or locked store stops the stage before any work, not after the whole CV
        mlflow_store.check_store(
            mlflow_store.resolve_tracking_uri(tracking_cfg), mlflow_store.busy_timeout(tracking_cfg)
        )
    check_columns(cfg)
    prepared = ev.load_prepared(cfg.paths.prepared_dir)
    digest = data_digest()
    out = Path(cfg.paths.model_dir)
    # MLflow (imported and opened in a helper process) works beside the passes; the logging below is queued to it
    with tracking.tracked_run_beside(
        tracking_cfg,
        run_name=evaluate_run_name(cfg),
        params=params,
        tags={"aumesh.stage": "evaluate", "aumesh.target": cfg.preprocess.target},
    ) as run:
        run.log_config(params)
        if digest.get("md5"):  # outside a DVC workspace there is no hash to record (the card says so)
            run.log_dataset(digest, source=str(Path(cfg.paths.data_dir).resolve()), name="frame_tables")
        cv, final = run_evaluation(prepared, cfg, run)
        metrics = cv.metrics()
        # the run's MLflow model warns beyond the data as the release does: it carries the data's support
        arrays = final.release_arrays(
            prepared.reference, metadata={"mlflow_run_id": run.run_id, "data": support.data_support(prepared.summary)}
        )
        refuse_nonfinite(arrays, Path(cfg.paths.prepared_dir))
        run.call(log_release_model, arrays)
        run_info = {
            "run_id": run.run_id,
            "run_name": evaluate_run_name(cfg) if cfg.tracking.enabled else None,
            "experiment_id": getattr(run, "experiment_id", None),
            # the card built from this is shared: the workspace's store repo-relative (sqlite:///mlflow.db),
            # never a server's address (the run id finds the run there)
            "tracking_uri": tracking.store_label(tracking_cfg) if cfg.tracking.enabled else None,
        }
        with atomic_directory(out) as tmp:
            np.savez(
                tmp / MODEL_NPZ,
                coef=final.coef,
                raw_intercept=final.raw_intercept,
                mesh_intercept=final.mesh_intercept,
                feature_columns=np.array(final.feature_columns),
                n_components=np.array(final.n_components, dtype=np.int32),
            )
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
            shutil.copyfile(cv.frame_vertex_error.path, tmp / ev.FRAME_ERROR_FILE)  # per frame, frames.parquet's order
            atomic_write_json(
                tmp / TRACKING_JSON, run_info | {"data_digest": digest, "degenerate": cv.extra.get("degenerate", {})}
            )
            atomic_write_json(tmp / METRICS_JSON, metrics)
        dvc_metrics.write(
            cfg.paths, metrics, cv.frame_vertex_error, cv.r2_path_folds
        )  # committed: `dvc metrics/plots diff`
        run.log_artifact(out / METRICS_JSON)
    return metrics


def log_release_model(handle, arrays: dict) -> None:
    """Log the release arrays as the open run's MLflow pyfunc model, and the seconds it took (``seconds_log_model``);
    ``handle`` is the tracking helper's :class:`aumesh.experiments.tracking.TrackedRun`."""
    from aumesh.experiments import pyfunc

    handle.log_metrics({"seconds_log_model": pyfunc.log_release_model(handle, arrays)})


#: Config groups that say where a run executes and is logged, not what it computes: not stage params in dvc.yaml,
#: never promoted, and not in the shared card (they hold a server's or a scheduler's address).
WHERE_GROUPS = ("tracking", "compute")


def shareable_config(cfg: Config) -> dict:
    """The configuration as the model card records it: what the model is, without :data:`WHERE_GROUPS`."""
    return {k: v for k, v in cfg.to_dict().items() if k not in WHERE_GROUPS}


def build_card(cfg: Config, model_dir: Path, prepared_dir: Path, promotion: dict | None) -> dict:
    """``model_card.json``: CV results, data (counts per filter, digest, what the data supports:
    :func:`aumesh.model.support.data_support`), config, provenance, MLflow run."""
    from aumesh.model import support

    with open(model_dir / METRICS_JSON) as fh:
        metrics = json.load(fh)
    with open(model_dir / TRACKING_JSON) as fh:
        run_info = json.load(fh)
    summary = integrity.load_summary(prepared_dir)  # prepare's counts
    git = provenance.git_commit(Path.cwd())
    return {
        "name": "AU+pose -> MediaPipe mesh PLS (aumesh)",
        "format_version": 2,
        "cv": {k: v for k, v in metrics.items() if k not in ("n_components", "n_features")},
        "model": {
            "n_components": metrics["n_components"],
            "n_features": metrics["n_features"],
            "estimator": "aumesh.model.pls.PLSRegression (exact kernel PLS, = sklearn PLSRegression)",
        },
        "data": {
            "n_frames": summary["n_frames"],
            "n_videos": summary["n_videos"],
            "digest": run_info.get("data_digest"),
            "degenerate": run_info.get("degenerate") or {},
            "counts": summary["counts"],
            "n_low_au_frames": summary["n_low_au_population"],
            **support.data_support(summary),
        },
        "config": shareable_config(cfg),
        "provenance": {"git_commit": git.get("commit"), "dirty": git.get("dirty"), "branch": git.get("branch")},
        "mlflow": {
            **{k: run_info.get(k) for k in ("run_id", "experiment_id", "tracking_uri")},
            "experiment": cfg.tracking.experiment if cfg.tracking.enabled else None,
        },
        "runs": release_runs(run_info, promotion),
        "libraries": provenance.library_versions(),
        "promotion": promotion,
    }


def release_runs(run_info: dict, promotion: dict | None) -> dict:
    """The two MLflow runs a release names: ``build`` made these exact arrays, ``promoted`` chose their configuration.

    Parameters
    ----------
    run_info : dict
        ``build/model/tracking.json``: the evaluate run of ``dvc repro`` (``run_id``, ``run_name``,
        ``experiment_id``, ``tracking_uri``).
    promotion : dict or None
        ``promotion.json``'s ``promoted`` record (:func:`aumesh.experiments.promote.promote`), None when the
        configuration is conf/'s own.

    Returns
    -------
    dict
        ``{"build": {...}, "promoted": {...} or None}``; each names its run id, its store (repo-relative) and, in
        ``role``, what it stands for. The promoted run is a sweep child: the same configuration fitted by the sweep,
        whose metrics decided; the build run refitted it in the pipeline (the card's arrays and numbers are its).
    """
    build = {
        "run_id": run_info.get("run_id"),
        "run_name": run_info.get("run_name"),
        "experiment_id": run_info.get("experiment_id"),
        "tracking_uri": run_info.get("tracking_uri"),
        "role": "build: the evaluate run of `dvc repro` that produced these exact arrays and the card's metrics",
    }
    promoted = None
    if promotion:
        promoted = {
            k: promotion.get(k)
            for k in (
                "run_id",
                "run_name",
                "parent_run_id",
                "tracking_uri",
                "criterion",
                "metric",
                "value",
                "registered_model",
                "model_version",
                "alias",
            )
        }
        promoted["role"] = (
            "promoted: the sweep run whose configuration this release uses, chosen by `aumesh promote` "
            f"({promotion.get('criterion')})"
        )
    return {"build": build, "promoted": promoted}


def load_model(model_dir: Path) -> dict[str, np.ndarray]:
    """The arrays of ``model.npz`` (evaluate's fit); a damaged archive is one line naming it."""
    import zipfile

    from aumesh.utils.errors import CorruptFileError, MissingFileError

    path = Path(model_dir) / MODEL_NPZ
    if not path.exists():
        raise MissingFileError(f"{path}: not found. Fix: run the evaluate stage first (`dvc repro evaluate`).")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, EOFError, OSError) as err:
        raise CorruptFileError(f"{path}: not a readable .npz ({err}). Fix: `dvc repro -f evaluate`.") from None


def refuse_nonfinite(arrays: dict, source: Path) -> None:
    """A :class:`aumesh.model.inference.ReleaseError` naming the first of ``coef``, ``coef_full``, ``intercept`` with a
    NaN/inf value: a release is finite or not written."""
    from aumesh.model.inference import ReleaseError, nonfinite_arrays

    nonfinite = nonfinite_arrays(arrays)
    if nonfinite:
        raise ReleaseError(
            f"{source}: {nonfinite}; nothing written, the previous release is kept. "
            f"Fix: rerun the fit (`dvc repro -f evaluate`) and look for degenerate inputs in its log."
        )


def refuse_implausible_face(
    intercept: np.ndarray, mean_aligned_mesh: np.ndarray, model_path: Path, reference_path: Path
) -> dict[str, Any]:
    """The card's ``data.face_shape``, or a :class:`aumesh.model.inference.ReleaseError` (one line naming the file)
    when the AU=0 face (``intercept``, (1434,) axis-major) or ``mean_aligned_mesh`` (478, 3) has no face's
    depth/width (:func:`aumesh.model.face_shape.face_shape_error`): never a flat face released with exit 0."""
    from aumesh.model.face_shape import au0_face, face_shape_error, face_shape_record
    from aumesh.model.inference import ReleaseError

    try:
        record = face_shape_record(au0_face(intercept), mean_aligned_mesh)
    except ValueError as err:  # no face frame at all (coincident eye corners, chin on the eye line)
        raise ReleaseError(
            f"{model_path}: the AU=0 face (intercept) or {reference_path}'s mean_aligned_mesh is not a face ({err}); "
            f"nothing written, the previous release is kept. Fix: rerun the fit (`dvc repro -f prepare evaluate`)."
        ) from None
    for ratio, what, source in (
        (record["depth_width"], "the AU=0 face (intercept)", model_path),
        (record["mean_aligned_mesh"]["depth_width"], "mean_aligned_mesh", reference_path),
    ):
        error = face_shape_error(ratio, what, str(source))
        if error:
            raise ReleaseError(error)
    return record


def release_stage(cfg: Config) -> Path:
    """Write the release folder atomically: a failure leaves the previous release as it was."""
    start_stage("release", cfg)
    from aumesh.card import directions, limits, render
    from aumesh.export import gltf, viewer

    model_dir, prepared_dir = Path(cfg.paths.model_dir), Path(cfg.paths.prepared_dir)
    promotion = None
    if Path(cfg.paths.promotion_file).exists():
        promotion = json.loads(Path(cfg.paths.promotion_file).read_text()).get("promoted") or None
    check_columns(cfg)
    integrity.verify_prepared(prepared_dir, integrity.load_summary(prepared_dir), [REFERENCE_FILE])
    card = build_card(cfg, model_dir, prepared_dir, promotion)
    model = load_model(model_dir)
    reference = integrity.load_reference(prepared_dir)
    refuse_nonfinite({"coef": model["coef"], "intercept": model["mesh_intercept"]}, model_dir / MODEL_NPZ)
    card["data"]["face_shape"] = refuse_implausible_face(
        model["mesh_intercept"], reference["mean_aligned_mesh"], model_dir / MODEL_NPZ, prepared_dir / REFERENCE_FILE
    )
    arrays = release_arrays(
        model["coef"],
        model["mesh_intercept"],
        model["feature_columns"].tolist(),
        int(model["n_components"]),
        reference,
        card_text="",
        metadata=card,
    )
    refuse_nonfinite(arrays, model_dir / MODEL_NPZ)  # before anything is written: the previous release stays
    with atomic_directory(cfg.paths.release_dir) as tmp:
        npz_path = tmp / NPZ_NAME
        atomic_savez(npz_path, **arrays)  # figures are rendered from the NPZ alone
        figures = render.render_release(npz_path, tmp / "figures", cv_path=model_dir / CV_NPZ)
        report = directions.au_direction_report(npz_path)
        report["source"] = NPZ_NAME  # not the temp folder it was read from
        directions.write_report(report, tmp / "au_directions.json")
        card["au_directions"] = {au: r["verdict"] for au, r in report["aus"].items()}
        card["warnings"] = limits.release_warnings(card, card["au_directions"], limits.au_field_iod(arrays))
        markdown = model_card_markdown(card, directions.report_markdown_table(report), [str(f) for f in figures])
        arrays["model_card"] = np.array(markdown)
        arrays["training_metadata"] = np.array(json.dumps(card, sort_keys=True, default=str))
        atomic_savez(npz_path, **arrays)
        gltf.write_glb(arrays, tmp / gltf.GLB_NAME, source=NPZ_NAME)
        viewer.write_viewer(arrays, tmp / viewer.VIEWER_NAME, source=NPZ_NAME)
        atomic_write_json(tmp / CARD_JSON, card)
        atomic_write_text(tmp / CARD_MD, markdown)
    return Path(cfg.paths.release_dir)
