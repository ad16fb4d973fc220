"""Stage ``evaluate``: cross-validated PLS and the final fit, from streamed sufficient statistics.

Card, "Method" and "Out-of-sample performance": ``PLSRegression(n_components, scale=True)``;
3-fold GroupKFold by video_id; variance-weighted R² (as ``sklearn.metrics.r2_score(...,
multioutput="variance_weighted")``), MAE; final fit on all kept frames.

Two passes over the prepared meshes:

* pass A (``aumesh.model.statistics``) accumulates per-fold cross-products of the full design with the
  absolute coordinates, plus per-video sums; every feature set, target and neutral is derived from
  them exactly, so a sweep needs this pass once. A fold's training statistics are the total minus
  the fold's, so each fold's model, and every smaller ``n_components``, comes from statistics; R² is
  exact from the held-out fold's statistics;
* pass B streams the rows once through their fold's model (all folds in one product) for MAE and
  the per-vertex Euclidean error; it runs once per configuration.

Besides R² in the run's own target space, every run gets ``r2_displacement``: R² of the
AU-driven displacement from each test video's neutral, ``(y - n_v)`` vs ``B (x - x̄_v)``, where
``n_v`` is the video's neutral mesh and ``x̄_v`` the mean design row of the same neutral frames.
It depends only on the slope ``B``, so absolute and neutral-subtracted runs are scored in the
same space and on the same information (see ``aumesh.experiments.promote``).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import pandas as pd
from sklearn.model_selection import GroupKFold
from threadpoolctl import threadpool_limits

from aumesh.config import Config
from aumesh.utils.errors import ConfigError, UserError
from aumesh.model.features import design_matrix
from aumesh.model.cross_products import CrossProducts
from aumesh.model import reliability
from aumesh.model.pls import PLSRegression
from aumesh.model.scoring import r2_path, r2_per_target, r2_variance_weighted, residual_sums
from aumesh.model.statistics import (DesignStatistics, accumulate_design, configuration_statistics, fold_stacked,
                                     target_offsets)
from aumesh.data.schema import AU_COLUMNS, N_TARGETS, N_VERTICES, POSE_COLUMNS, feature_columns

log = logging.getLogger(__name__)


@dataclass
class Prepared:
    """The ``prepare`` stage's outputs, meshes memory-mapped (never loaded whole)."""

    frames: pd.DataFrame
    meshes: np.ndarray  # (n, 1434) float32 memmap, axis-major
    video_ids: np.ndarray
    neutral: Mapping[str, np.ndarray]  # method -> (n_videos, 1434) float32, loaded on first use
    reference: dict[str, np.ndarray]
    summary: dict
    mesh_path: Path | None = None  # meshes.npy: the streaming passes read it with plain file I/O

    def iter_meshes(self, chunk_rows: int):
        """``(rows, Y)`` over consecutive row slices, ``Y`` float64 of shape (len(rows), 1434).

        Reads ``meshes.npy`` chunk by chunk into two reused buffers (float32 file rows, float64 copy), so
        memory stays bounded: a memory map would leave every page read resident in this process.
        ``Y`` is overwritten by the next chunk: use it (or copy it) before advancing.
        """
        n = self.meshes.shape[0]
        if self.mesh_path is None or n == 0:
            for rows in _chunks(n, chunk_rows):
                yield rows, np.asarray(self.meshes[rows], dtype=np.float64)
            return
        raw = np.empty((min(chunk_rows, n), N_TARGETS), dtype=np.float32)
        out = np.empty(raw.shape, dtype=np.float64)
        with open(self.mesh_path, "rb", buffering=0) as fh:
            fh.seek(self.meshes.offset)
            for rows in _chunks(n, chunk_rows):
                m = rows.stop - rows.start
                view = memoryview(raw[:m]).cast("B")
                got = 0
                while got < len(view):
                    k = fh.readinto(view[got:])
                    if not k:
                        raise EOFError(f"{self.mesh_path}: truncated at row {rows.start + got // (4 * N_TARGETS)}")
                    got += k
                np.copyto(out[:m], raw[:m])
                yield rows, out[:m]

    @cached_property
    def au(self) -> np.ndarray:
        """(n, 20) AU intensities, float64 (one copy, reused by every pass)."""
        return self.frames[list(AU_COLUMNS)].to_numpy(np.float64)

    @cached_property
    def pose(self) -> np.ndarray:
        """(n, 3) Pitch, Yaw, Roll in radians, float64."""
        return self.frames[list(POSE_COLUMNS)].to_numpy(np.float64)


class _LazyArrays(Mapping):
    """Read-only mapping onto NPZ members, each loaded on first access (only the neutral method in use
    is ever in memory: (n_videos, 1434) float32 each)."""

    def __init__(self, npz, names: dict[str, str]):
        self._npz, self._names, self._loaded = npz, names, {}

    def __getitem__(self, key: str) -> np.ndarray:
        if key not in self._loaded:
            self._loaded[key] = self._npz[self._names[key]]
        return self._loaded[key]

    def __iter__(self):
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)


def load_prepared(prepared_dir: str | Path) -> Prepared:
    import json

    d = Path(prepared_dir)
    missing = [n for n in ("meshes.npy", "frames.parquet", "neutrals.npz", "reference.npz", "summary.json") if not (d / n).exists()]
    if missing:
        raise UserError(f"{d}: missing {', '.join(missing)}. Fix: run the prepare stage first (`dvc repro prepare`).")
    neutrals = np.load(d / "neutrals.npz")
    with open(d / "summary.json") as fh:
        summary = json.load(fh)
    return Prepared(
        frames=pd.read_parquet(d / "frames.parquet"),
        meshes=np.load(d / "meshes.npy", mmap_mode="r"),
        mesh_path=d / "meshes.npy",
        video_ids=neutrals["video_ids"],
        neutral=_LazyArrays(neutrals, {"mean": "neutral_mean", "low_au": "neutral_low_au"}),
        reference=dict(np.load(d / "reference.npz")),
        summary=summary,
    )


@dataclass
class FoldStatistics:
    """Per-fold statistics of one design (features x target) over all prepared frames."""

    target: list[CrossProducts]  # (X, Y in the run's target space) per fold
    displacement: list[CrossProducts]  # (X - x̄_v, Y_abs - n_v) per fold
    fold: np.ndarray  # (n,) fold of each frame
    x_offset: np.ndarray | None = None  # (n_videos, p) per-video design centre of the target (None: none)
    y_offset: np.ndarray | None = None  # (n_videos, 1434) per-video mesh centre of the target (None: none)

    @property
    def total(self) -> CrossProducts:
        out = self.target[0].copy()
        for s in self.target[1:]:
            out = out + s
        return out


@dataclass
class CVResult:
    n_components: int
    feature_columns: list[str]
    r2_folds: list[float]
    r2_displacement_folds: list[float]
    r2_path_folds: np.ndarray  # (n_splits, n_components): R² for k = 1..n_components
    mae_folds: list[float]
    vertex_error_folds: list[float]
    r2_per_target: np.ndarray  # (1434,) pooled over folds
    r2_per_vertex: np.ndarray  # (478,) pooled over folds and axes
    frame_vertex_error: np.ndarray  # (n,) mean per-vertex Euclidean error of each frame (held out)
    vertex_error_per_vertex: np.ndarray  # (478,) mean over held-out frames
    n_frames_folds: list[int]
    n_videos_folds: list[int]
    extra: dict = field(default_factory=dict)
    au_reliability: np.ndarray | None = None  # (20,) mean cosine of each AU's field between folds fitted alone
    n_aus_facs_pass: int | None = None  # AUs of the final model whose direction passes the FACS check

    def metrics(self) -> dict:
        def ms(values):
            return float(np.mean(values)), float(np.std(values))

        r2m, r2s = ms(self.r2_folds)
        dm, ds = ms(self.r2_displacement_folds)
        maem, maes = ms(self.mae_folds)
        vem, ves = ms(self.vertex_error_folds)
        return {
            "r2_mean": r2m, "r2_std": r2s, "r2_folds": [float(v) for v in self.r2_folds],
            "r2_displacement_mean": dm, "r2_displacement_std": ds,
            "r2_displacement_folds": [float(v) for v in self.r2_displacement_folds],
            "mae_mean": maem, "mae_std": maes, "mae_folds": [float(v) for v in self.mae_folds],
            "vertex_error_mean": vem, "vertex_error_std": ves, "vertex_error_folds": [float(v) for v in self.vertex_error_folds],
            "n_components": self.n_components,
            "n_features": len(self.feature_columns),
            "n_frames_folds": self.n_frames_folds, "n_videos_folds": self.n_videos_folds,
        } | self.field_metrics()

    def field_metrics(self) -> dict:
        """AU-field reliability (min, median, per AU) and the FACS direction count, when computed."""
        out = {} if self.au_reliability is None else reliability.summarize(self.au_reliability, list(AU_COLUMNS))
        if self.n_aus_facs_pass is not None:
            out["n_aus_facs_pass"] = int(self.n_aus_facs_pass)
        return out

    def scalar_metrics(self) -> dict[str, float]:
        """What a run logs to MLflow: every scalar of :meth:`metrics`, the per-AU reliability as ``au_reliability_<AU>``."""
        metrics = self.metrics()
        out = {k: v for k, v in metrics.items() if isinstance(v, float)}
        out |= {f"au_reliability_{au}": v for au, v in metrics.get("au_reliability", {}).items()}
        if "n_aus_facs_pass" in metrics:
            out["n_aus_facs_pass"] = float(metrics["n_aus_facs_pass"])
        return out


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


def log_clipping(cfg: Config, handle) -> None:
    """Say a clipped ``model.n_components`` on the console (warning) and in MLflow (tag on the open run ``handle``),
    not only in the card."""
    k = effective_n_components(cfg)
    if k != cfg.model.n_components:
        log.warning("model.n_components=%d clipped to %d, the number of features of features=%s "
                    "(model.clip_n_components=true)", cfg.model.n_components, k, cfg.features.name)
        handle.set_tags({"aumesh.n_components_clipped": f"{cfg.model.n_components} -> {k} (features={cfg.features.name})"})


def assign_folds(video_index: np.ndarray, n_splits: int) -> np.ndarray:
    """Fold of every frame, from scikit-learn's ``GroupKFold`` on the video index (fold ``f`` = f-th test split)."""
    n_groups = len(np.unique(video_index))
    if n_groups < n_splits:
        raise ConfigError(f"cv.n_splits={n_splits} but only {n_groups} videos are left after filtering. Fix: lower cv.n_splits.")
    fold = np.empty(len(video_index), dtype=np.int8)
    for f, (_, test) in enumerate(GroupKFold(n_splits=n_splits).split(np.zeros(len(video_index)), groups=video_index)):
        fold[test] = f
    return fold


def neutral_design(X_au: np.ndarray, pose: np.ndarray, video_index: np.ndarray, neutral_rows: np.ndarray,
                   n_videos: int, use_pose: bool, interactions: bool) -> np.ndarray:
    """Mean design row of each video's neutral frames, shape (n_videos, n_features)."""
    X = design_matrix(X_au[neutral_rows], pose[neutral_rows], use_pose, interactions)
    v = video_index[neutral_rows]
    counts = np.bincount(v, minlength=n_videos).astype(np.float64)
    # per-video sums column by column (bincount adds in row order, as np.add.at did, ~100x faster)
    sums = np.column_stack([np.bincount(v, weights=X[:, j], minlength=n_videos) for j in range(X.shape[1])]) \
        if X.shape[1] else np.zeros((n_videos, 0))
    return sums / np.maximum(counts, 1.0)[:, None]


def _chunks(n: int, chunk_rows: int):
    for start in range(0, n, chunk_rows):
        yield slice(start, min(start + chunk_rows, n))


def design_statistics(prepared: Prepared, fold: np.ndarray, n_splits: int, chunk_rows: int) -> DesignStatistics:
    """Pass A: per-fold statistics of the full design with absolute coordinates (one pass, every configuration)."""
    with _one_blas_thread():
        return accumulate_design(prepared.au, prepared.pose, prepared.frames["video_index"].to_numpy(),
                                 len(prepared.video_ids), fold, n_splits, prepared.iter_meshes(chunk_rows))


def accumulate(prepared: Prepared, cfg: Config, fold: np.ndarray, chunk_rows: int | None = None,
               design: DesignStatistics | None = None) -> FoldStatistics:
    """Per-fold (target, displacement) statistics of ``cfg``'s features and target.

    ``design`` (from :func:`design_statistics` with the same folds) is reused when given: then no
    pass over the meshes is needed (aumesh.model.statistics derives every configuration from it).
    """
    if design is None:
        design = design_statistics(prepared, fold, cfg.cv.n_splits, chunk_rows or cfg.data.chunk_rows)
    elif not np.array_equal(design.fold, fold):
        raise ValueError("accumulate: the design statistics were built with other folds")
    video_index = prepared.frames["video_index"].to_numpy()
    method = cfg.preprocess.neutral.method
    neutral_rows = prepared.frames["low_au"].to_numpy() if method == "low_au" else np.ones(len(video_index), bool)
    xbar_neutral = neutral_design(prepared.au, prepared.pose, video_index, neutral_rows, len(prepared.video_ids), True, True)
    target, displacement = configuration_statistics(design, cfg.features.columns, cfg.preprocess.target,
                                                    prepared.neutral[method], xbar_neutral)
    x_offset, y_offset = target_offsets(design, cfg.features.columns, cfg.preprocess.target, prepared.neutral[method],
                                        xbar_neutral)
    return FoldStatistics(target=target, displacement=displacement, fold=fold, x_offset=x_offset, y_offset=y_offset)


def _one_blas_thread():
    """Single-threaded BLAS/LAPACK for the statistics passes and the fits.

    On 2 cores shared with other work, threaded OpenBLAS spends its time waking and spinning
    threads: measured on this machine under load, 83 x 83 products and 83 x 83 eigh per component
    ran 5-60x slower with 2 threads than with 1 (fits: 14-21 s vs 3 s; a pass's X'X blocks: 6.6 s vs
    0.1 s), while the wide GEMMs gain at most 2x on an idle machine. One thread is the robust choice.
    """
    return threadpool_limits(limits=1, user_api="blas")


def _single_threaded(chunks):
    """Iterate ``chunks`` with single-threaded BLAS for the loop body (see :func:`_one_blas_thread`)."""
    with _one_blas_thread():
        yield from chunks


def fit(stats: CrossProducts, n_components: int, scale: bool) -> PLSRegression:
    """The engine's PLS fit from statistics (card: PLSRegression(n_components, scale=True))."""
    with _one_blas_thread():
        return PLSRegression(n_components=n_components, scale=scale).fit_stats(stats)


def cross_validate(prepared: Prepared, cfg: Config, stats: FoldStatistics, chunk_rows: int | None = None) -> CVResult:
    """Score each fold's model from statistics (R²) and one streaming pass (MAE, per-vertex error)."""
    chunk_rows = chunk_rows or cfg.data.chunk_rows
    A = effective_n_components(cfg)
    n_splits = cfg.cv.n_splits
    total = stats.total
    models, r2_folds, r2d_folds, paths, sse_sum, sst_sum = [], [], [], [], np.zeros(N_TARGETS), np.zeros(N_TARGETS)
    with _one_blas_thread():
        for f in range(n_splits):
            model = fit(total - stats.target[f], A, cfg.model.scale)
            models.append((model.coef_.copy(), model.raw_intercept_.copy()))  # not the model: its coef path is 80 MB
            sse, sst = residual_sums(model.coef_, model.raw_intercept_, stats.target[f])
            r2_folds.append(r2_variance_weighted(sse, sst))
            sse_sum += sse
            sst_sum += sst
            sse_d, sst_d = residual_sums(model.coef_, np.zeros(N_TARGETS), stats.displacement[f])
            r2d_folds.append(r2_variance_weighted(sse_d, sst_d))
            paths.append(r2_path(model, stats.target[f]))

    # pass B: held-out predictions, streamed
    use_pose, inter = cfg.features.pose, cfg.features.interactions
    au, pose = prepared.au, prepared.pose
    video_index = prepared.frames["video_index"].to_numpy()
    n = len(stats.fold)
    abs_sum = np.zeros(n_splits)
    vertex_sum = np.zeros((n_splits, N_VERTICES))
    count = np.bincount(stats.fold, minlength=n_splits)
    frame_error = np.empty(n, dtype=np.float32)
    # every fold's model in one matrix: rows [coef_0.T | ... | coef_K-1.T | raw_intercept_0 .. K-1]
    stacked_models = np.vstack([coef.T for coef, _ in models] + [intercept[None] for _, intercept in models])
    for rows, Y in _single_threaded(prepared.iter_meshes(chunk_rows)):
        X = design_matrix(au[rows], pose[rows], use_pose, inter)
        if stats.x_offset is not None:  # the target's per-video centres (held-out videos: their own)
            X -= stats.x_offset[video_index[rows]]
        stacked = fold_stacked(X, stats.fold[rows], n_splits)
        if stats.y_offset is not None:
            Y -= stats.y_offset[video_index[rows]]
        Y -= stacked @ stacked_models  # residual: y - (x @ coef_f.T + raw_intercept_f), f the row's fold
        e3 = Y.reshape(len(Y), 3, N_VERTICES)
        per_vertex = np.sqrt(np.einsum("ikj,ikj->ij", e3, e3))  # (m, 478) Euclidean error per vertex
        frame_error[rows] = per_vertex.mean(axis=1)
        onehot = stacked[:, n_splits * X.shape[1]:]
        abs_sum += np.abs(Y).sum(axis=1) @ onehot
        vertex_sum += onehot.T @ per_vertex
    fold_videos = [int(len(np.unique(video_index[stats.fold == f]))) for f in range(n_splits)]
    sse_v, sst_v = sse_sum.reshape(3, N_VERTICES).sum(0), sst_sum.reshape(3, N_VERTICES).sum(0)
    result = CVResult(
        n_components=A,
        feature_columns=feature_columns(use_pose, inter),
        r2_folds=[float(r) for r in r2_folds],
        r2_displacement_folds=[float(r) for r in r2d_folds],
        r2_path_folds=np.vstack(paths),
        mae_folds=list(abs_sum / (count * N_TARGETS)),
        vertex_error_folds=list(vertex_sum.sum(axis=1) / (count * N_VERTICES)),
        r2_per_target=r2_per_target(sse_sum, sst_sum),
        r2_per_vertex=r2_per_target(sse_v, sst_v),  # x, y, z pooled per vertex
        frame_vertex_error=frame_error,
        vertex_error_per_vertex=vertex_sum.sum(axis=0) / count.sum(),
        n_frames_folds=[int(c) for c in count],
        n_videos_folds=fold_videos,
    )
    return result


@dataclass
class FinalModel:
    coef: np.ndarray  # (1434, p) raw-input coefficients (scikit-learn's coef_ layout)
    raw_intercept: np.ndarray  # (1434,) true intercept for raw inputs, in the target space
    mesh_intercept: np.ndarray  # (1434,) intercept that yields a mesh (adds the mean neutral for target=neutral)
    feature_columns: list[str]
    n_components: int
    model: PLSRegression


def final_fit(prepared: Prepared, cfg: Config, stats: FoldStatistics) -> FinalModel:
    """Card: final fit on all kept frames."""
    A = effective_n_components(cfg)
    model = fit(stats.total, A, cfg.model.scale)
    mesh_intercept = model.raw_intercept_.copy()
    # a target relative to per-video centres predicts displacements from them; released meshes add the
    # population's (frame-weighted) mean centre, so `x @ coef + intercept` is a face. For `within` that is
    # the population intercept mean mesh - mean design @ slopes.
    weights = np.bincount(prepared.frames["video_index"].to_numpy(), minlength=len(prepared.video_ids)).astype(np.float64)
    if stats.y_offset is not None:
        mesh_intercept += weights @ stats.y_offset.astype(np.float64) / weights.sum()
    if stats.x_offset is not None:
        mesh_intercept -= model.coef_ @ (weights @ stats.x_offset / weights.sum())
    return FinalModel(coef=model.coef_.copy(), raw_intercept=model.raw_intercept_.copy(), mesh_intercept=mesh_intercept,
                      feature_columns=feature_columns(cfg.features.pose, cfg.features.interactions), n_components=A, model=model)


def au_field_reliability(cfg: Config, stats: FoldStatistics) -> np.ndarray:
    """Per-AU mean cosine between the AU fields of models fitted on each fold alone (disjoint videos), (20,)."""
    A = effective_n_components(cfg)
    coefs = np.stack([fit(s, A, cfg.model.scale).coef_ for s in stats.target])
    return reliability.field_cosines(coefs, np.arange(len(AU_COLUMNS)))


def facs_passes(prepared: Prepared, final: FinalModel) -> int:
    """Number of AUs of the final model whose direction passes the FACS check (``aumesh.card.directions``)."""
    from aumesh.card import directions

    report = directions.au_direction_report({"coef": final.coef.T, "input_columns": np.array(final.feature_columns),
                                              "mean_aligned_mesh": prepared.reference["mean_aligned_mesh"]})
    return int(report["summary"]["pass"])


def evaluate_statistics(prepared: Prepared, cfg: Config, stats: FoldStatistics) -> tuple[CVResult, FinalModel]:
    """Cross-validation, the final fit and the AU-field checks of one configuration from its statistics."""
    cv = cross_validate(prepared, cfg, stats)
    final = final_fit(prepared, cfg, stats)
    cv.au_reliability = au_field_reliability(cfg, stats)
    cv.n_aus_facs_pass = facs_passes(prepared, final)
    return cv, final


def evaluate(prepared: Prepared, cfg: Config) -> tuple[CVResult, FinalModel]:
    """Cross-validation and the final fit for one configuration (the stage's one typed call)."""
    fold = assign_folds(prepared.frames["video_index"].to_numpy(), cfg.cv.n_splits)
    return evaluate_statistics(prepared, cfg, accumulate(prepared, cfg, fold))
