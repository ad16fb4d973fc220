"""What the evaluate passes produce, as objects: the per-fold statistics of a configuration (:class:`FoldStatistics`),
its models (:class:`Fits`), the cross-validation's scores (:class:`CVResult`, with the metrics a run records) and the
final fit as released (:class:`FinalModel`, with the card's NPZ arrays). No pass over the data here: the passes that
fill them are :mod:`aumesh.pipeline.evaluate.statistics_pass` and :mod:`aumesh.pipeline.evaluate`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aumesh.core.io import NpyRows, RowArray
from aumesh.core.schema import AU_COLUMNS
from aumesh.model import reliability
from aumesh.model.cross_products import CrossProducts
from aumesh.model.eiv import EivFit, IdentificationScreen
from aumesh.model.kernel_pls import PLSFit
from aumesh.model.release import release_arrays


def total_of(parts: list[CrossProducts]) -> CrossProducts:
    """The statistics of every fold's rows: ``parts`` added in fold order."""
    out = parts[0].copy()
    for s in parts[1:]:
        out = out + s
    return out


def training_sets(parts: list[CrossProducts]) -> list[CrossProducts]:
    """The ``2 n_splits + 1`` training statistics in :class:`Fits`' order: each fold's complement (total - fold), all
    rows, each fold alone."""
    total = total_of(parts)
    return [total - held_out for held_out in parts] + [total] + list(parts)


@dataclass
class FoldStatistics:
    """Per-fold statistics of one design (features x target) over all prepared frames."""

    target: list[CrossProducts]  # (X, Y in the run's target space) per fold
    displacement: list[CrossProducts]  # (X - x̄_v, Y_abs - n_v) per fold
    video_fold: np.ndarray  # (n_videos,) fold of each video (-1: no frames)
    x_offset: np.ndarray | None = None  # (n_videos, p) per-video design centre of the target (None: none)
    y_offset: RowArray | None = None  # (n_videos, 1434) per-video mesh centre of the target (None: none)
    # within-video statistics of the 20 AUs with the mesh over every frame, whatever the target (the screen's moments)
    au_within: CrossProducts | None = None
    pose_mean: np.ndarray | None = None  # (3,) E[pose] over every frame (radians)
    pose_second: np.ndarray | None = None  # (3, 3) E[pose pose^T]
    # model/eiv=instruments: per fold, within-video statistics of the augmented design [X | Z] (the configuration's
    # columns, then the same columns of the instrument AUs: aumesh.model.pass_design.augmented_index) with Y
    instruments: list[CrossProducts] | None = None

    @property
    def total(self) -> CrossProducts:
        return total_of(self.target)


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
    frame_vertex_error: NpyRows  # (n,) float32 mean per-vertex Euclidean error of each frame (held out), on disk
    vertex_error_per_vertex: np.ndarray  # (478,) mean over held-out frames
    n_frames_folds: list[int]
    n_videos_folds: list[int]
    extra: dict = field(default_factory=dict)
    au_reliability: np.ndarray | None = None  # (20,) mean cosine of each AU's field between folds fitted alone
    n_aus_facs_pass: int | None = None  # AUs of the final model whose direction passes the FACS check
    au_identification: IdentificationScreen | None = None  # the AU identification screen (aumesh.model.eiv)
    eiv: dict | None = None  # model/eiv != none: what the correction used (pipeline.evaluate.eiv_fits.eiv_record)

    def metrics(self) -> dict:
        def ms(values):
            return float(np.mean(values)), float(np.std(values))

        r2m, r2s = ms(self.r2_folds)
        dm, ds = ms(self.r2_displacement_folds)
        maem, maes = ms(self.mae_folds)
        vem, ves = ms(self.vertex_error_folds)
        return {
            "r2_mean": r2m,
            "r2_std": r2s,
            "r2_folds": [float(v) for v in self.r2_folds],
            "r2_displacement_mean": dm,
            "r2_displacement_std": ds,
            "r2_displacement_folds": [float(v) for v in self.r2_displacement_folds],
            "mae_mean": maem,
            "mae_std": maes,
            "mae_folds": [float(v) for v in self.mae_folds],
            "vertex_error_mean": vem,
            "vertex_error_std": ves,
            "vertex_error_folds": [float(v) for v in self.vertex_error_folds],
            "n_components": self.n_components,
            "n_features": len(self.feature_columns),
            "n_frames_folds": self.n_frames_folds,
            "n_videos_folds": self.n_videos_folds,
        } | self.field_metrics()

    def field_metrics(self) -> dict:
        """AU-field reliability (min, median, per AU) and the FACS direction count, when computed."""
        out = {} if self.au_reliability is None else reliability.summarize(self.au_reliability, list(AU_COLUMNS))
        if self.n_aus_facs_pass is not None:
            out["n_aus_facs_pass"] = int(self.n_aus_facs_pass)
        if self.au_identification is not None:
            out["n_aus_unidentified"] = int(self.au_identification.flagged.sum())
            out["au_identification"] = self.au_identification.to_card()
        if self.eiv is not None:
            out["eiv"] = self.eiv
        return out

    def scalar_metrics(self) -> dict[str, float]:
        """What a run logs to MLflow: every scalar of :meth:`metrics`, the per-AU reliability as ``au_reliability_<AU>``."""
        metrics = self.metrics()
        out = {k: v for k, v in metrics.items() if isinstance(v, float)}
        out |= {f"au_reliability_{au}": v for au, v in metrics.get("au_reliability", {}).items()}
        if "n_aus_facs_pass" in metrics:
            out["n_aus_facs_pass"] = float(metrics["n_aus_facs_pass"])
        if "n_aus_unidentified" in metrics:
            out["n_aus_unidentified"] = float(metrics["n_aus_unidentified"])
            # sigma* of the AUs that turn within the screen's grid (the others have none: not logged)
            out |= {
                f"au_sigma_star_{au}": float(v["sigma_star"])
                for au, v in metrics["au_identification"].items()
                if v["sigma_star"] is not None
            }
        return out


@dataclass
class Fits:
    """Every model of one configuration, fitted from its statistics (:func:`aumesh.pipeline.evaluate.fit_models`)."""

    folds: list[Any]  # PLSFit or EivFit: fold f's model, trained on the other folds (cross-validation)
    final: PLSFit | EivFit  # trained on every frame (card: final fit on all kept frames)
    alone: list[Any]  # PLSFit or EivFit: trained on fold f alone (the AU-field reliability)


@dataclass
class FinalModel:
    coef: np.ndarray  # (1434, p) raw-input coefficients (scikit-learn's coef_ layout)
    raw_intercept: np.ndarray  # (1434,) true intercept for raw inputs, in the target space
    mesh_intercept: np.ndarray  # (1434,) intercept that yields a mesh (adds the mean neutral for target=neutral)
    feature_columns: list[str]
    n_components: int
    model: PLSFit | EivFit
    # model/eiv != none: the card's least-squares fit on the same rows, written beside the corrected one (1434, p)
    uncorrected_coef: np.ndarray | None = None
    identification: IdentificationScreen | None = None

    def release_arrays(self, reference: dict[str, np.ndarray], metadata: dict[str, Any]) -> dict[str, np.ndarray]:
        """This fit as the card's NPZ arrays (:func:`aumesh.model.release.release_arrays`; the card's text comes with
        the release stage), in the frame of ``reference`` (prepare's :func:`~aumesh.pipeline.integrity.load_reference`)."""
        return release_arrays(
            self.coef,
            self.mesh_intercept,
            self.feature_columns,
            self.n_components,
            reference,
            card_text="",
            metadata=metadata,
            uncorrected_coef=self.uncorrected_coef,
            identification=None if self.identification is None else self.identification.release_arrays(),
        )
