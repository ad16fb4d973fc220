"""Stage ``evaluate``: cross-validated PLS and the final fit, from streamed sufficient statistics.

Card, "Method" and "Out-of-sample performance": ``PLSRegression(n_components, scale=True)``;
3-fold GroupKFold by video_id; variance-weighted R² (as ``sklearn.metrics.r2_score(...,
multioutput="variance_weighted")``), MAE; final fit on all kept frames.

Two passes over the prepared meshes:

* pass A (:mod:`aumesh.pipeline.evaluate.statistics_pass`, ``aumesh.model.statistics``) accumulates per-fold cross-products
  of the full design with the absolute coordinates, plus per-video sums; every feature set, target and neutral is
  derived from them exactly, so a sweep needs this pass once. A fold's training statistics are the total minus
  the fold's, so each fold's model, and every smaller ``n_components``, comes from statistics; R² is
  exact from the held-out fold's statistics. Its tasks also hash the bytes of ``meshes.npy`` they read; the driver
  compares the digests with prepare's checksums before any model is fitted (``aumesh.pipeline.integrity``);
* pass B (here) streams the rows once through their fold's model (all folds in one product) for MAE and
  the per-vertex Euclidean error; it runs once per configuration.

This module holds the folds, the fits, pass B and the calls that run a configuration
(:func:`cross_validate_and_fit`); the prepared data and its readers are :mod:`aumesh.pipeline.evaluate.prepared_data`, the
result objects (:class:`~aumesh.pipeline.evaluate.results.CVResult`, ``FinalModel``, ...)
:mod:`aumesh.pipeline.evaluate.results`.

Besides R² in the run's own target space, every run gets ``r2_displacement``: R² of the
AU-driven displacement from each test video's neutral, ``(y - n_v)`` vs ``B (x - x̄_v)``, where
``n_v`` is the video's neutral mesh and ``x̄_v`` the mean design row of the same neutral frames.
It depends only on the slope ``B``, so absolute and neutral-subtracted runs are scored in the
same space and on the same information (see ``aumesh.experiments.promote``).

Every run also gets the AU-field reliability (:func:`au_field_reliability`: per AU, the cosine between
its fields fitted on each fold alone, ``aumesh.model.reliability``) and the number of AUs whose
direction passes the FACS check (:func:`facs_passes`, ``aumesh.card.directions``).
"""

from __future__ import annotations

import heapq
import logging
import shutil
import weakref
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from aumesh.config import Config
from aumesh.core.blas import one_blas_thread
from aumesh.core.errors import ConfigError
from aumesh.core.io import NpyRowFile, NpyRows, create_npy, scratch_directory
from aumesh.core.schema import AU_COLUMNS, N_TARGETS, N_VERTICES, POSE_COLUMNS, instrument_columns
from aumesh.model import eiv, reliability
from aumesh.model.cross_products import CrossProducts
from aumesh.model.eiv import EivFit
from aumesh.model.features import design_matrix
from aumesh.model.kernel_pls import PLSFit, fit_statistics
from aumesh.model.scoring import r2_path, r2_per_target, r2_variance_weighted, residual_sums
from aumesh.model.statistics import FULL_DESIGN, DesignStatistics, design_union, extra_inputs, named_design
from aumesh.pipeline import compute
from aumesh.pipeline.evaluate.eiv_fits import eiv_fits, eiv_record
from aumesh.pipeline.evaluate.prepared_data import (
    Prepared,
    block_rows,
    fold_grouped_block,
    read_columns,
    read_group,
    workers_check,
)
from aumesh.pipeline.evaluate.results import CVResult, FinalModel, Fits, FoldStatistics, training_sets
from aumesh.pipeline.evaluate.statistics_pass import accumulate, design_statistics
from aumesh.pipeline.model_files import FRAME_ERROR_FILE
from aumesh.pipeline.prepared_files import FRAMES_FILE, MESHES_FILE, scratch_path

log = logging.getLogger(__name__)


def effective_n_components(cfg: Config) -> int:
    """``model.n_components``, clipped to the number of features when ``model.clip_n_components``."""
    p = len(cfg.features.columns)
    if cfg.model.n_components > p:
        if not cfg.model.clip_n_components:
            raise ValueError(
                f"model.n_components={cfg.model.n_components} exceeds the {p} features of "
                f"features={cfg.features.name}. Fix: lower it, or set model.clip_n_components=true."
            )
        return p
    return cfg.model.n_components


def video_folds(video_count: np.ndarray, n_splits: int) -> np.ndarray:
    """Fold of every video (fold ``f`` = the f-th test split of scikit-learn's ``GroupKFold(n_splits)`` on the
    frames' video index), from the videos' frame counts alone.

    ``GroupKFold`` (``sklearn/model_selection/_split.py``, no shuffle) takes the groups present in index order,
    sorts their sizes with a stable argsort, reversed (largest first; among equal sizes the highest index first),
    and gives each in turn to the lightest fold so far (the first of equally light ones). A heap of
    ``(frames, fold)`` pops exactly that fold.

    Parameters
    ----------
    video_count : ndarray (n_videos,) int
        Frames of each video (0: the video has none and gets no fold).
    n_splits : int

    Returns
    -------
    ndarray (n_videos,) int64
        Fold of each video, -1 for videos without frames.
    """
    present = np.flatnonzero(np.asarray(video_count) > 0)
    if len(present) < n_splits:
        raise ConfigError(
            f"cv.n_splits={n_splits} but only {len(present)} videos are left after filtering. Fix: lower cv.n_splits."
        )
    sizes = np.asarray(video_count)[present]
    fold = np.full(len(video_count), -1, dtype=np.int64)
    heap = [(0, f) for f in range(n_splits)]
    for i in np.argsort(sizes, kind="stable")[::-1].tolist():
        load, f = heap[0]
        heapq.heapreplace(heap, (load + int(sizes[i]), f))
        fold[present[i]] = f
    return fold


def fit(stats: CrossProducts, n_components: int, scale: bool) -> PLSFit:
    """The engine's PLS fit from statistics (card: PLSRegression(n_components, scale=True); the fitted attributes
    of :class:`aumesh.model.pls.PLSRegression`, without importing scikit-learn in the stage)."""
    with one_blas_thread():
        return fit_statistics(stats, n_components, scale)


def fit_models(cfg: Config, stats: FoldStatistics) -> Fits:
    """The ``2 n_splits + 1`` fits of a configuration: independent, from statistics, so they run at once on this
    machine's cores (:func:`aumesh.pipeline.compute.local_map`; each on one BLAS thread, so each is the same to the
    bit on any number of cores)."""
    A = effective_n_components(cfg)
    training = training_sets(stats.target)
    with one_blas_thread():  # held across the threads: one fit's exit does not lift another's limit
        models = compute.local_map(partial(fit, n_components=A, scale=cfg.model.scale), training)
    k = len(stats.target)
    return Fits(folds=models[:k], final=models[k], alone=models[k + 1 :])


def cross_validate(
    prepared: Prepared,
    cfg: Config,
    stats: FoldStatistics,
    fold_models: Sequence[PLSFit | EivFit],
    chunk_rows: int | None = None,
    path_models: Sequence[PLSFit] | None = None,
) -> CVResult:
    """Score each fold's model (``fold_models[f]``, trained without fold ``f``: :func:`fit_models`) from statistics
    (R²) and one streaming pass (MAE, per-vertex error). The R² of every smaller number of components comes from
    ``path_models`` (the PLS fits; default ``fold_models``): a fit corrected for detector noise has no components."""
    chunk_rows = chunk_rows or cfg.data.chunk_rows
    A = effective_n_components(cfg)
    n_splits = cfg.cv.n_splits
    r2_folds, r2d_folds, paths, sse_sum, sst_sum = [], [], [], np.zeros(N_TARGETS), np.zeros(N_TARGETS)
    models = [(model.coef_, model.raw_intercept_) for model in fold_models]
    with one_blas_thread():
        for f, model in enumerate(fold_models):
            sse, sst = residual_sums(model.coef_, model.raw_intercept_, stats.target[f])
            r2_folds.append(r2_variance_weighted(sse, sst))
            sse_sum += sse
            sst_sum += sst
            sse_d, sst_d = residual_sums(model.coef_, np.zeros(N_TARGETS), stats.displacement[f])
            r2d_folds.append(r2_variance_weighted(sse_d, sst_d))
            paths.append(r2_path((path_models or fold_models)[f], stats.target[f]))

    # pass B: held-out predictions, streamed partition by partition; each frame's error goes to rows of a scratch
    # .npy beside the prepared data (removed with the result), never gathered
    use_pose, inter = cfg.features.pose, cfg.features.interactions
    columns = cfg.features.columns
    video_fold, video_count = stats.video_fold, prepared.videos.count
    has = video_fold >= 0
    count = np.bincount(video_fold[has], weights=video_count[has], minlength=n_splits).astype(np.int64)
    scratch = scratch_directory(scratch_path(prepared.directory))
    frame_error = scratch / FRAME_ERROR_FILE
    try:
        create_npy(frame_error, np.float32, (prepared.n_frames,))
        errors = compute.map_reduce(
            partial(
                error_partition,
                directory=prepared.directory,
                video_fold=video_fold,
                coefs=[np.ascontiguousarray(coef.T) for coef, _ in models],
                intercepts=[intercept for _, intercept in models],
                use_pose=use_pose,
                interactions=inter,
                n_splits=n_splits,
                chunk_rows=block_rows(chunk_rows),
                frame_error=frame_error,
                x_offset=stats.x_offset,
                y_offset=stats.y_offset,
                columns=None if cfg.features.family == "au" else columns,
            ),
            ErrorPart.__add__,
            prepared.row_groups(),
            desc="evaluate: errors",
        )
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        raise
    abs_sum, vertex_sum = errors.abs_sum, errors.vertex_sum
    fold_videos = np.bincount(video_fold[has], minlength=n_splits).tolist()
    sse_v, sst_v = sse_sum.reshape(3, N_VERTICES).sum(0), sst_sum.reshape(3, N_VERTICES).sum(0)
    result = CVResult(
        n_components=A,
        feature_columns=columns,
        r2_folds=[float(r) for r in r2_folds],
        r2_displacement_folds=[float(r) for r in r2d_folds],
        r2_path_folds=np.vstack(paths),
        mae_folds=list(abs_sum / (count * N_TARGETS)),
        vertex_error_folds=list(vertex_sum.sum(axis=1) / (count * N_VERTICES)),
        r2_per_target=r2_per_target(sse_sum, sst_sum),
        r2_per_vertex=r2_per_target(sse_v, sst_v),  # x, y, z pooled per vertex
        frame_vertex_error=NpyRows(frame_error),
        vertex_error_per_vertex=vertex_sum.sum(axis=0) / count.sum(),
        n_frames_folds=[int(c) for c in count],
        n_videos_folds=fold_videos,
    )
    weakref.finalize(result, shutil.rmtree, scratch, True)
    return result


@dataclass
class ErrorPart:
    """Pass B of consecutive partitions: absolute and per-vertex error sums per fold."""

    abs_sum: np.ndarray  # (K,)
    vertex_sum: np.ndarray  # (K, 478)

    def __add__(self, other: ErrorPart) -> ErrorPart:
        return ErrorPart(self.abs_sum + other.abs_sum, self.vertex_sum + other.vertex_sum)


def error_partition(
    group: tuple[int, int, int],
    directory: Path,
    video_fold: np.ndarray,
    coefs: list[np.ndarray],
    intercepts: list[np.ndarray],
    use_pose: bool,
    interactions: bool,
    n_splits: int,
    chunk_rows: int,
    frame_error: Path,
    x_offset=None,
    y_offset=None,
    columns: Sequence[str] | None = None,
) -> ErrorPart:
    """Pass B on one row group: each frame's held-out residual under its fold's model (``coefs[f]`` (p, 1434),
    ``intercepts[f]`` (1434,)), and the error sums per fold; each frame's mean per-vertex error is written to its
    row of the ``.npy`` ``frame_error`` (n_frames,) float32. ``x_offset`` (n_videos, p) and ``y_offset``
    (n_videos, 1434), arrays or :class:`aumesh.core.io.NpyRows`, are the target's per-video centres (None: none);
    only the partition's videos' rows are read. ``columns``: the design of another input family than the AUs (its
    inputs read by name, :func:`aumesh.model.statistics.named_design`); None: the AU design of ``use_pose``,
    ``interactions``."""
    g, start, stop = group
    au, pose, video, _ = read_group(directory, g)
    names = None if columns is None else extra_inputs(columns)
    inputs = None if names is None else read_columns(directory, g, names)
    fold = video_fold[video]
    videos, local = np.unique(video, return_inverse=True)
    x_rows = None if x_offset is None else np.asarray(x_offset[videos], dtype=np.float64)
    y_rows = None if y_offset is None else np.asarray(y_offset[videos])
    abs_sum, vertex_sum = np.zeros(n_splits), np.zeros((n_splits, N_VERTICES))
    # the blocks' arrays, allocated once a task: a fresh set per block left the freed blocks' holes in the heap for the
    # partition's other arrays to fragment
    raw = np.empty((min(chunk_rows, stop - start), N_TARGETS), dtype=np.float32)
    residual = np.empty((len(raw), N_TARGETS))
    vertex_error = np.empty((len(raw), N_VERTICES))
    with NpyRowFile(directory / MESHES_FILE) as meshes, NpyRowFile(frame_error, writable=True) as errors:
        for lo in range(start, stop, chunk_rows):
            rows, bounds, Y = fold_grouped_block(meshes, raw, lo, min(lo + chunk_rows, stop), start, fold, n_splits)
            if inputs is None:
                X = design_matrix(au[rows], pose[rows], use_pose, interactions)
            else:
                X = named_design(pose[rows], inputs[rows], names or [], columns or [])
            if x_rows is not None:  # the target's per-video centres (held-out videos: their own)
                X -= x_rows[local[rows]]
            if y_rows is not None:
                Y = Y - y_rows[local[rows]]
            # minus the residual y - (x @ coef_f.T + raw_intercept_f), rounded as it (-(u - v) is v - u exactly): the
            # prediction's GEMM writes the block, and the float32 rows widen inside the subtraction, not in a copy
            R = residual[: len(Y)]
            for f in range(n_splits):  # one GEMM per fold's rows and model
                lo_f, hi_f = bounds[f], bounds[f + 1]
                np.matmul(X[lo_f:hi_f], coefs[f], out=R[lo_f:hi_f])
                np.subtract(R[lo_f:hi_f], Y[lo_f:hi_f], out=R[lo_f:hi_f])
                R[lo_f:hi_f] += intercepts[f]
            e3 = R.reshape(len(R), 3, N_VERTICES)
            per_vertex = vertex_error[: len(R)]  # (m, 478) Euclidean error per vertex
            np.sqrt(np.einsum("ikj,ikj->ij", e3, e3, out=per_vertex), out=per_vertex)
            error = per_vertex.mean(axis=1)
            errors.write(lo, error[np.argsort(rows)].astype(np.float32))  # back in the file's order
            row_abs = np.abs(R, out=R).sum(axis=1)  # in place: R is not used again (no block-sized temporary)
            for f in range(n_splits):
                lo_f, hi_f = bounds[f], bounds[f + 1]
                abs_sum[f] += row_abs[lo_f:hi_f].sum()
                vertex_sum[f] += per_vertex[lo_f:hi_f].sum(axis=0)
    return ErrorPart(abs_sum, vertex_sum)


def _weighted_mean(rows, weights: np.ndarray, block: int = 4096) -> np.ndarray:
    """``weights @ rows / weights.sum()`` over per-video rows (an array or :class:`aumesh.core.io.NpyRows`),
    a block of videos at a time (the rows are never whole in memory)."""
    total = np.zeros(rows.shape[1:])
    for lo in range(0, len(weights), block):
        total = total + weights[lo : lo + block] @ np.asarray(rows[lo : lo + block], dtype=np.float64)
    return total / weights.sum()


def final_fit(prepared: Prepared, cfg: Config, stats: FoldStatistics, model: PLSFit | EivFit) -> FinalModel:
    """Card: final fit on all kept frames (``model``, fitted on ``stats.total``: :func:`fit_models`), as released."""
    A = effective_n_components(cfg)
    mesh_intercept = model.raw_intercept_.copy()
    # a target relative to per-video centres predicts displacements from them; released meshes add the
    # population's (frame-weighted) mean centre, so `x @ coef + intercept` is a face. For `within` that is
    # the population intercept mean mesh - mean design @ slopes.
    weights = prepared.videos.count.astype(np.float64)
    if stats.y_offset is not None:
        mesh_intercept += _weighted_mean(stats.y_offset, weights)
    if stats.x_offset is not None:
        mesh_intercept -= model.coef_ @ _weighted_mean(stats.x_offset, weights)
    return FinalModel(
        coef=model.coef_.copy(),
        raw_intercept=model.raw_intercept_.copy(),
        mesh_intercept=mesh_intercept,
        feature_columns=cfg.features.columns,
        n_components=A,
        model=model,
    )


def au_field_reliability(alone: Sequence[PLSFit | EivFit]) -> np.ndarray:
    """Per-AU mean cosine between the AU fields of the models fitted on each fold alone (disjoint videos), (20,)."""
    return reliability.field_cosines(np.stack([model.coef_ for model in alone]), np.arange(len(AU_COLUMNS)))


def facs_passes(prepared: Prepared, final: FinalModel) -> int:
    """Number of AUs of the final model whose direction passes the FACS check (``aumesh.card.directions``)."""
    from aumesh.card import directions

    report = directions.au_direction_report(
        {
            "coef": final.coef.T,
            "input_columns": np.array(final.feature_columns),
            "mean_aligned_mesh": prepared.reference["mean_aligned_mesh"],
        }
    )
    return int(report["summary"]["pass"])


def cross_validate_and_fit_from_statistics(
    prepared: Prepared, cfg: Config, stats: FoldStatistics
) -> tuple[CVResult, FinalModel]:
    """Cross-validation, the final fit and the AU-field checks of one configuration from its statistics (``stats``:
    :func:`aumesh.pipeline.evaluate.statistics_pass.accumulate`), on the current scheduler."""
    fits = fit_models(cfg, stats)
    if cfg.features.family != "au":  # the AU-specific pieces (EIV, reliability, FACS, the screen) are the AU model's
        if cfg.model.eiv.method != "none":
            raise ConfigError(
                f"model/eiv={cfg.model.eiv.method} corrects the AU detector's noise, but features={cfg.features.name} "
                f"is the {cfg.features.family} family. Fix: model/eiv=none for features={cfg.features.name}"
            )
        cv = cross_validate(prepared, cfg, stats, fits.folds)
        return cv, final_fit(prepared, cfg, stats, fits.final)
    corrected = eiv_fits(cfg, stats)  # model/eiv: the same statistics refitted for detector noise (None: none)
    used = corrected or fits
    cv = cross_validate(prepared, cfg, stats, used.folds, path_models=fits.folds)
    final = final_fit(prepared, cfg, stats, used.final)
    if corrected is not None:  # written beside the corrected fields: the card's fit of the same rows
        final.uncorrected_coef = fits.final.coef_.copy()
        cv.eiv = eiv_record(cfg, stats)
    cv.au_reliability = au_field_reliability(used.alone)
    cv.n_aus_facs_pass = facs_passes(prepared, final)
    cv.au_identification = final.identification = identification(cfg, stats)
    return cv, final


def identification(cfg: Config, stats: FoldStatistics) -> eiv.IdentificationScreen:
    """The AU identification screen (docs/method.md eq. 6) on the within-video AU moments of every frame."""
    au = stats.au_within
    if au is None:
        raise ValueError("identification: the statistics carry no within-video AU moments")
    ident = cfg.model.identification
    return eiv.identification_screen(
        au.cxx / au.n,
        au.cxy / au.n,
        list(AU_COLUMNS),
        sigma_step=ident.sigma_step,
        sigma_max=ident.sigma_max,
        flag_below=ident.flag_below,
        turn_cosine=ident.turn_cosine,
        floor=ident.floor,
    )


@dataclass
class SharedPass:
    """The evaluate stage's one statistics pass, shared by every configuration it fits (issue 46, contract item 2).

    ``feature_sets``: the designs besides the first configuration's (``families.<f>.features``). The first call of
    :meth:`statistics` runs pass A once over the union of the designs
    (:func:`aumesh.model.statistics.design_union`, with the first configuration's instruments); every call takes its
    configuration's columns from it by name. ``passes`` counts the passes made.
    """

    feature_sets: Sequence[str] = ()
    video_fold: np.ndarray | None = None
    design: DesignStatistics | None = None
    passes: int = 0

    def statistics(self, prepared: Prepared, cfg: Config) -> FoldStatistics:
        """``cfg``'s :class:`FoldStatistics` from the shared pass (run now if it has not been), on the current
        scheduler."""
        if self.design is None or self.video_fold is None:
            self.video_fold = video_folds(prepared.videos.count, cfg.cv.n_splits)
            columns = design_union([cfg.features.name, *self.feature_sets])
            self.design = design_statistics(
                prepared,
                self.video_fold,
                cfg.cv.n_splits,
                cfg.data.chunk_rows,
                instrument_columns(cfg.model.eiv.instrument_aus),
                None if columns == FULL_DESIGN else columns,  # the AU design alone: the pass as it always was
            )
            self.passes += 1
        return accumulate(prepared, cfg, self.video_fold, design=self.design)


def cross_validate_and_fit(
    prepared: Prepared, cfg: Config, shared: SharedPass | None = None
) -> tuple[CVResult, FinalModel]:
    """Cross-validation and the final fit for one configuration (the stage's one typed call): both passes, on
    the ``compute`` group's scheduler. ``shared``: the stage's one statistics pass (:class:`SharedPass`), run by the
    first configuration that needs it and reused by the others."""
    with compute.engine(cfg.compute, **workers_check(prepared)):
        if shared is not None:
            return cross_validate_and_fit_from_statistics(prepared, cfg, shared.statistics(prepared, cfg))
        video_fold = video_folds(prepared.videos.count, cfg.cv.n_splits)
        return cross_validate_and_fit_from_statistics(prepared, cfg, accumulate(prepared, cfg, video_fold))


# ------------------------------------------------------------------------------------------- degenerate inputs
def constant_inputs(prepared: Prepared, inputs: Sequence[str] | None = None) -> dict[str, float]:
    """The input columns ``inputs`` (default: the AU and pose columns) with one value in every prepared frame (column -> that value), from the row groups'
    min/max statistics in ``frames.parquet``'s footer (no pass over the data; a column without statistics is read).

    Such a column carries no information. It stays in the design: its centred values are exactly 0 (the statistics
    shift a column constant in their first block by its value), so the engine, as scikit-learn does, gives it a zero
    standard deviation replaced by 1, no weight in any component and a coefficient of exactly 0 -- the model dropping it
    would fit, with the release's format (23 rows of ``coef``, 83 of ``coef_full``) unchanged. What changes is what
    is said: a console warning, an MLflow tag and the card (:func:`degenerate_inputs`).
    """
    path = prepared.directory / FRAMES_FILE
    md = pq.ParquetFile(path).metadata
    names = md.schema.to_arrow_schema().names
    out = {}
    for name in (*AU_COLUMNS, *POSE_COLUMNS) if inputs is None else inputs:
        j = names.index(name)
        lo, hi = np.inf, -np.inf
        for g in range(md.num_row_groups):
            stats = md.row_group(g).column(j).statistics
            if md.row_group(g).num_rows == 0:
                continue
            if stats is None or not stats.has_min_max:
                values = pq.read_table(path, columns=[name]).column(0).to_numpy()
                lo, hi = (values.min(), values.max()) if len(values) else (np.inf, -np.inf)
                break
            lo, hi = min(lo, stats.min), max(hi, stats.max)
        if lo == hi:
            out[name] = float(lo) + 0.0  # parquet stores a min of 0.0 as -0.0
    return out


def degenerate_inputs(constant: dict[str, float], columns: list[str]) -> dict:
    """What the design's columns ``columns`` lose to the ``constant`` inputs: ``{"constant_inputs": {column: value},
    "constant_features": [design columns without variance], "pose_learned": bool}`` (a pose x AU product has no variance
    when its pose or its AU is 0 in every frame, or both are constant)."""
    dead = []
    for c in columns:
        if "*" in c:
            p, a = c.split("*")
            if (p in constant and a in constant) or constant.get(p) == 0.0 or constant.get(a) == 0.0:
                dead.append(c)
        elif c in constant:
            dead.append(c)
    pose_features = [c for c in columns if c in POSE_COLUMNS or "*" in c]
    return {
        "constant_inputs": dict(constant),
        "constant_features": dead,
        "pose_learned": bool(pose_features) and any(c not in dead for c in pose_features),
    }
