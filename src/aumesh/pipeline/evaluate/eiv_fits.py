"""The fits of a configuration corrected for detector noise (``model/eiv``; docs/method.md eqs. 4-7).

Each of the ``2 n_splits + 1`` fits of :func:`aumesh.pipeline.evaluate.fit_models` (every fold's training rows, all
rows, each fold alone) is refitted by the configured correction from the same within-video statistics; the
uncorrected PLS fits stay beside them (the R²-by-components curve and the uncorrected fields come from them).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from aumesh.config import Config
from aumesh.core.blas import one_blas_thread
from aumesh.model import eiv
from aumesh.pipeline.evaluate.results import Fits, FoldStatistics, total_of, training_sets

log = logging.getLogger(__name__)


def check_eiv_inputs(cfg: Config) -> None:
    """Before any work: ``model.eiv.sigma_u`` is readable and valid (one line naming the file and the fix), and a
    warning when it lies outside ``paths.validation_dir`` (the folder dvc.yaml lists as evaluate's dependency: an edit
    elsewhere does not rerun the stage)."""
    if cfg.model.eiv.method != "corrected":
        return
    path = Path(cfg.model.eiv.sigma_u or "")
    eiv.load_sigma_u(path)
    folder = Path(cfg.paths.validation_dir).resolve()
    if folder not in path.resolve().parents:
        log.warning(
            "model.eiv.sigma_u=%s is outside paths.validation_dir (%s): DVC does not rerun evaluate when it changes "
            "(the card records its sha256). Fix: keep it in %s/",
            path,
            cfg.paths.validation_dir,
            cfg.paths.validation_dir,
        )


def design_sigma(cfg: Config, stats: FoldStatistics) -> np.ndarray:
    """``model.eiv.sigma_u`` (20 x 20, the AUs') extended to the configuration's design (docs/method.md eq. 5b)."""
    sigma_au = eiv.load_sigma_u(Path(cfg.model.eiv.sigma_u or ""))
    if stats.pose_mean is None or stats.pose_second is None:
        raise ValueError("design_sigma: the statistics carry no pose moments (aumesh.model.statistics.pose_moments)")
    return eiv.design_error_covariance(sigma_au, cfg.features.columns, stats.pose_mean, stats.pose_second)


def corrected_fits(cfg: Config, stats: FoldStatistics) -> Fits:
    """Floored corrected least squares (``model/eiv=corrected``) for every training set of ``stats``."""
    sigma = design_sigma(cfg, stats)
    with one_blas_thread():
        models = [eiv.corrected_fit(s, sigma, cfg.model.eiv.floor) for s in training_sets(stats.target)]
    k = len(stats.target)
    return Fits(folds=models[:k], final=models[k], alone=models[k + 1 :])


def instrumental_fits(cfg: Config, stats: FoldStatistics) -> Fits:
    """Within two-stage least squares (``model/eiv=instruments``; docs/method.md eq. 7) for every training set of
    ``stats``: each from the within-video statistics of the augmented design ``[X | Z]`` (``stats.instruments``,
    training = total - fold), ``B = (Z'X)^-1 Z'Y`` (:func:`aumesh.model.eiv.instrumental_fit`)."""
    if stats.instruments is None:
        raise ValueError(
            "instrumental_fits: the statistics carry no instruments (accumulate with model/eiv=instruments)"
        )
    p = len(cfg.features.columns)
    with one_blas_thread():
        models = [eiv.instrumental_fit(s, p) for s in training_sets(stats.instruments)]
    k = len(stats.instruments)
    return Fits(folds=models[:k], final=models[k], alone=models[k + 1 :])


def first_stage(cfg: Config, stats: FoldStatistics) -> dict[str, dict[str, float]]:
    """Per AU, the first stage's R² and F over every frame (:func:`aumesh.model.eiv.first_stage_strength`): how much
    of the AU's within-video variance the instruments (all of them, pose and pose x AU included) explain; weak below
    F ~10."""
    if stats.instruments is None:
        raise ValueError("first_stage: the statistics carry no instruments (accumulate with model/eiv=instruments)")
    total = total_of(stats.instruments)
    p = len(cfg.features.columns)
    cxx = total.cxx
    return eiv.first_stage_strength(cxx[p:, p:], cxx[p:, :p], cxx[:p, :p], int(total.n))


def eiv_record(cfg: Config, stats: FoldStatistics | None = None) -> dict | None:
    """What a corrected run's card and metrics record of its correction (None for ``model/eiv=none``): the method,
    and for ``corrected`` the floor, the covariance file (repo-relative as configured) and its sha256; for
    ``instruments`` the column pattern and, given ``stats``, the first stage's strength per AU (:func:`first_stage`)."""
    import hashlib

    eiv_cfg = cfg.model.eiv
    if eiv_cfg.method == "none":
        return None
    record: dict = {"method": eiv_cfg.method, "full": cfg.features.interactions}
    if eiv_cfg.method == "corrected":
        path = Path(eiv_cfg.sigma_u or "")
        record |= {
            "floor": eiv_cfg.floor,
            "sigma_u": eiv_cfg.sigma_u,
            "sigma_u_sha256": hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else None,
        }
    else:
        record["instrument_aus"] = eiv_cfg.instrument_aus
        if stats is not None and stats.instruments is not None:
            record["first_stage"] = first_stage(cfg, stats)
    return record


def eiv_fits(cfg: Config, stats: FoldStatistics) -> Fits | None:
    """The configured correction's fits (None for ``model/eiv=none``: the PLS fits are the model)."""
    method = cfg.model.eiv.method
    if method == "none":
        return None
    if method == "corrected":
        return corrected_fits(cfg, stats)
    if method == "instruments":
        return instrumental_fits(cfg, stats)
    raise NotImplementedError(f"model.eiv.method={method!r}")
