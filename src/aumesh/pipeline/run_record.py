"""What an evaluation run records in MLflow: one definition for the ``evaluate`` stage and every sweep child.

Both callers (:func:`aumesh.stages.evaluate.main`, :func:`aumesh.experiments.sweep_child.run_configuration`) open
the run themselves (the stage in the tracking helper process, :func:`aumesh.tracking.beside.tracked_run_beside`; a sweep
child in its job, :func:`aumesh.tracking.runs.tracked_run`) and then log the same record, in four calls to an open
run handle (the tracking helper's :class:`aumesh.tracking.handle.TrackedRun` API; this module never imports MLflow):

1. :func:`log_clipping` (first: a configuration asking for more components than features fails before any work)
   -- tag ``aumesh.n_components_clipped`` when ``model.n_components`` was clipped;
2. :func:`log_inputs`, once the prepared data are loaded -- the resolved config (artifact ``config.yaml``), the
   config's keys the run was not opened with (params), the tables' DVC digest as the dataset input
   ``frame_tables`` when ``paths.data_dir`` is the data ``data.dvc`` tracks (else tag ``aumesh.data.note``), tags
   ``aumesh.constant_inputs``/``aumesh.constant_features``/``aumesh.pose_learned`` when inputs are constant
   (:func:`log_degenerate`) and metrics ``data.dropped*``/``data.videos_dropped*`` (prepare's filter counts);
3. :func:`log_results` -- tag ``aumesh.n_components.effective``; per-fold ``r2``, ``mae``, ``vertex_error``,
   ``r2_displacement`` (step = fold); every scalar of :meth:`aumesh.pipeline.evaluate.CVResult.scalar_metrics` and
   ``n_components`` (effective), ``n_features``, ``n_frames``; the R²-vs-n_components curve as metric
   ``r2_by_n_components`` (step = k) and figure ``plots/r2_vs_n_components.png``; the caller's timings;
4. :func:`log_model` -- the release arrays (:func:`model_arrays`: training metadata ``mlflow_run_id``, ``config``,
   ``cv``, ``data`` support) as the run's MLflow pyfunc model under ``model/`` and metric ``seconds_log_model``.

Opening tags, the same keys for both (:func:`run_tags`): ``aumesh.stage`` (``evaluate`` or ``sweep``),
``aumesh.target`` and ``aumesh.family`` (the input family: ``au`` for the AU model, ``blendshapes``, ``emotions``). What stays the caller's: the stage's metric ``evaluate_seconds`` and artifact ``metrics.json``
(the file it writes to ``build/``); a sweep child's metrics ``seconds_load``, ``seconds_statistics``,
``seconds_cv_fit``, ``seconds_job``, its tags ``aumesh.role``, ``mlflow.parentRunId``, ``aumesh.sweep.overrides``
and the prepared-cache tags ``aumesh.prepared_dir``, ``aumesh.prepared.key``, ``aumesh.cache.statistics``, ``aumesh.cache.pass``,
``aumesh.cache.result``.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aumesh.config import without_where
from aumesh.core.provenance import flatten

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np

    from aumesh.config import Config
    from aumesh.pipeline.evaluate.prepared_data import Prepared
    from aumesh.pipeline.evaluate.results import CVResult, FinalModel

log = logging.getLogger(__name__)

DATASET_NAME = "frame_tables"
CURVE_METRIC = "r2_by_n_components"
FIGURE_ARTIFACT = "plots/r2_vs_n_components.png"
DATA_NOTE_TAG = "aumesh.data.note"
EFFECTIVE_TAG = "aumesh.n_components.effective"
#: the per-fold metrics (step = fold); their means and standard deviations are scalar metrics
FOLD_METRICS = ("r2", "mae", "vertex_error", "r2_displacement")


#: the input family a run fitted (``au``, ``blendshapes``, ``emotions``: ``features.family``; issue 46)
FAMILY_TAG = "aumesh.family"


def run_tags(stage: str, target: Any, family: str | None = None) -> dict[str, str]:
    """The tags an evaluation run is opened with: ``aumesh.stage`` (``"evaluate"`` for the DVC stage, ``"sweep"`` for
    a sweep child: what :mod:`aumesh.tracking.queries` tells them apart by), ``aumesh.target`` and, given, the input
    ``family`` as ``aumesh.family`` (the AU model's run ``"au"``, each family fit its family, a sweep child its
    ``features``' family: what ``aumesh promote --family`` selects by)."""
    tags = {"aumesh.stage": stage, "aumesh.target": str(target)}
    if family is not None:
        tags[FAMILY_TAG] = str(family)
    return tags


# ------------------------------------------------------------------------------------------- 1. and 2.: inputs
def log_clipping(cfg: Config, handle) -> None:
    """Say a clipped ``model.n_components`` on the console (warning) and in MLflow (tag on the open run ``handle``),
    not only in the card."""
    from aumesh.pipeline.evaluate import effective_n_components

    k = effective_n_components(cfg)
    if k != cfg.model.n_components:
        log.warning(
            "model.n_components=%d clipped to %d, the number of features of features=%s (model.clip_n_components=true)",
            cfg.model.n_components,
            k,
            cfg.features.name,
        )
        handle.set_tags(
            {"aumesh.n_components_clipped": f"{cfg.model.n_components} -> {k} (features={cfg.features.name})"}
        )


def log_degenerate(prepared: Prepared, cfg: Config, handle) -> dict:
    """Say constant inputs aloud: a console warning and MLflow tags on the open run ``handle``; returns
    :func:`aumesh.pipeline.evaluate.degenerate_inputs` (the card's sentence is made from it)."""
    from aumesh.core.families import FAMILIES
    from aumesh.core.schema import POSE_COLUMNS
    from aumesh.pipeline.evaluate import constant_inputs, degenerate_inputs

    family = cfg.features.family
    found = degenerate_inputs(
        constant_inputs(prepared, None if family == "au" else (*FAMILIES[family], *POSE_COLUMNS)),
        cfg.features.columns,
    )
    constant = found["constant_inputs"]
    if not constant:
        return found
    listed = ", ".join(f"{c}={v:g}" for c, v in constant.items())
    log.warning(
        "evaluate: %s constant in every one of the %d prepared frames: %d of the %d features of features=%s carry "
        "no information (kept in the design with coefficients of exactly 0)%s",
        listed,
        prepared.n_frames,
        len(found["constant_features"]),
        len(cfg.features.columns),
        cfg.features.name,
        "" if found["pose_learned"] or not (cfg.features.pose) else "; the model learned nothing from pose",
    )
    handle.set_tags(
        {
            "aumesh.constant_inputs": listed,
            "aumesh.constant_features": str(len(found["constant_features"])),
            "aumesh.pose_learned": str(found["pose_learned"]).lower(),
        }
    )
    return found


def dataset_source(cfg: Config, digest: Mapping[str, Any] | None, root: Path) -> str | None:
    """The data directory to record as the run's dataset input (absolute), or None when ``digest`` (of ``data.dvc``,
    :func:`aumesh.core.provenance.data_digest`) has no hash or describes other data than ``paths.data_dir``."""
    data_dir = (root / cfg.paths.data_dir).resolve()
    if digest and digest.get("md5") and data_dir == (root / str(digest.get("path") or "data")).resolve():
        return str(data_dir)
    return None


def dropped_counts(summary: Mapping[str, Any]) -> dict[str, float]:
    """What prepare's filters dropped, as counts and fractions: metrics ``data.<key>`` of the summary's ``counts``
    whose key starts with ``dropped`` or ``videos_dropped``."""
    counts = summary.get("counts", {})
    return {f"data.{k}": float(v) for k, v in counts.items() if k.startswith(("dropped", "videos_dropped"))}


def log_inputs(
    handle,
    cfg: Config,
    prepared: Prepared,
    opened_params: Mapping[str, Any],
    digest: Mapping[str, Any] | None,
    root: Path,
) -> dict:
    """Log what went into the evaluation (step 2 of the module docstring) to the open run ``handle``.

    Parameters
    ----------
    handle : aumesh.tracking.handle.TrackedRun or aumesh.tracking.beside.RunBeside
    cfg : aumesh.config.Config
    prepared : aumesh.pipeline.evaluate.Prepared
        The loaded prepared data (their ``summary`` and ``frames.parquet``'s statistics).
    opened_params : Mapping
        The (nested) params the run was opened with; the config's other keys are logged here (a sweep child opens
        with the composed config, which lacks the typed config's defaults, e.g. ``compute.connect_timeout``).
    digest : Mapping or None
        :func:`aumesh.core.provenance.data_digest` of ``data.dvc`` (None or without ``md5`` outside DVC).
    root : Path
        The workspace root ``paths.data_dir`` and the digest's ``path`` are relative to.

    Returns
    -------
    dict
        :func:`log_degenerate`'s finding (the stage keeps it for ``tracking.json`` and the card).
    """
    config = without_where(cfg.to_dict())  # where the run executed and was logged is no part of its record
    handle.log_config(config)
    opened = flatten(opened_params)
    missing = {k: v for k, v in flatten(config).items() if k not in opened}
    if missing:
        handle.log_params(missing)
    source = dataset_source(cfg, digest, root)
    if source is not None and digest is not None:
        handle.log_dataset(digest, source=source, name=DATASET_NAME)
    else:
        handle.set_tags(
            {
                DATA_NOTE_TAG: f"paths.data_dir={cfg.paths.data_dir} is not the DVC-tracked data of data.dvc; "
                "aumesh.data.* tags describe data.dvc, not this run's data"
            }
        )
    degenerate = log_degenerate(prepared, cfg, handle)
    dropped = dropped_counts(prepared.summary)
    if dropped:
        handle.log_metrics(dropped)
    return degenerate


# ------------------------------------------------------------------------------------------------ 3.: results
@dataclass(frozen=True)
class ResultsRecord:
    """The results of one evaluation as a run records them (plain values: the stage sends it to its helper process).

    Attributes
    ----------
    tags : dict
        ``aumesh.n_components.effective`` and the caller's extra tags.
    folds : dict of str to list of float
        :data:`FOLD_METRICS` -> per-fold values (index = fold = step).
    metrics : dict of str to float
        Scalar metrics (step 0): the CV's, ``n_components``, ``n_features``, ``n_frames`` and the caller's timings.
    r2_path_folds : ndarray, shape (n_splits, n_components)
        Held-out R² of each fold's model truncated to k = 1..n_components.
    title : str
        The curve figure's title (the configuration).
    """

    tags: dict[str, Any]
    folds: dict[str, list[float]]
    metrics: dict[str, float]
    r2_path_folds: np.ndarray
    title: str = ""


def results_record(
    cfg: Config,
    cv: CVResult,
    final: FinalModel,
    metrics: Mapping[str, float] | None = None,
    tags: Mapping[str, Any] | None = None,
) -> ResultsRecord:
    """The :class:`ResultsRecord` of ``cv`` and ``final``, with the caller's extra ``metrics`` (timings) and
    ``tags``."""
    scalars = cv.scalar_metrics()
    scalars |= {
        "n_components": float(final.n_components),
        "n_features": float(len(final.feature_columns)),
        "n_frames": float(sum(cv.n_frames_folds)),
    } | dict(metrics or {})
    title = (
        f"target={cfg.preprocess.target} neutral={cfg.preprocess.neutral.method} features={cfg.features.name} "
        f"n_components={final.n_components}"
    )
    return ResultsRecord(
        tags={EFFECTIVE_TAG: final.n_components, **(tags or {})},
        folds={name: [float(v) for v in getattr(cv, f"{name}_folds")] for name in FOLD_METRICS},
        metrics=scalars,
        r2_path_folds=cv.r2_path_folds,
        title=title,
    )


def log_results(handle, record: ResultsRecord) -> None:
    """Log ``record`` (step 3 of the module docstring) to the open run ``handle``. A module-level function: the stage
    queues it to its tracking helper (``run.call(log_results, record)``), where the figure is drawn beside the work."""
    if not getattr(handle, "enabled", True):
        return
    from aumesh.card.run_figures import r2_curve_figure

    handle.set_tags(record.tags)
    handle.log_fold_metrics(record.folds)
    handle.log_metrics(record.metrics)
    # the curve as a metric history, step = n_components, in one transaction
    handle.log_metric_history(CURVE_METRIC, record.r2_path_folds.mean(axis=0), first_step=1)
    handle.log_figure(r2_curve_figure(record.r2_path_folds, record.title), FIGURE_ARTIFACT)


# -------------------------------------------------------------------------------------------------- 4.: model
def model_arrays(cfg: Config, prepared: Prepared, cv: CVResult, final: FinalModel, run_id: str | None) -> dict:
    """The release arrays of ``final`` for the run's MLflow model: its training metadata carries the run id, the
    config, the CV metrics and the data's support, so the model warns beyond the data as the release does (and a
    registered model says where it came from)."""
    from aumesh.model import support

    metadata = {
        "mlflow_run_id": run_id,
        "config": without_where(cfg.to_dict()),
        "cv": cv.metrics(),
        "data": support.data_support(prepared.summary),
    }
    return final.release_arrays(prepared.reference, metadata=metadata)


def log_model(handle, arrays: Mapping[str, np.ndarray]) -> None:
    """Log the release ``arrays`` as the open run's MLflow pyfunc model under ``model/``, and the seconds it took
    (``seconds_log_model``); module-level, for ``run.call`` as :func:`log_results`."""
    if not getattr(handle, "enabled", True):  # tracking off: nothing to log, MLflow not imported
        return
    from aumesh.tracking import pyfunc

    handle.log_metrics({"seconds_log_model": pyfunc.log_release_model(handle, arrays)})
