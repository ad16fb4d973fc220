"""Detector noise in the AU intensities (errors in variables): the identification screen and the two corrections.

The AU intensities are measured by an image detector whose errors are correlated across AUs and persist over frames.
With observed ``x = x* + u`` and ``u`` of within-video covariance ``Sigma_u``, the within-video least-squares slope tends
to ``S^-1 (S - Sigma_u) B`` (docs/method.md, eq. 3): attenuated, and where AUs co-activate, rotated; a small AU field
next to a larger, opposed partner can come out reversed. Everything here works on the within-video moments that the
evaluate stage already has (``S = X'X_w / n``, ``S_xy = X'Y_w / n``: docs/method.md eq. 2), never on rows:

* :func:`floored_corrected_coef`: corrected least squares with a given ``Sigma_u`` (method of moments, eq. 4), each
  whitened direction's reliability floored (eq. 5) so no direction is amplified more than ``1 / floor``;
* :func:`identification_screen`: per AU the critical noise sd ``sigma*`` at which an isotropic ``Sigma_u = sigma^2 I``
  turns its field by more than 60 degrees, the AU's dominant partner, and the partner group's field (eq. 6). A screen,
  not a proof: it says which fields a plausible detector noise *could* turn, from the data's own geometry;
* :func:`instrumental_coef` and :func:`first_stage_strength`: within two-stage least squares with a second detector's
  AUs as instruments (eq. 7);
* :func:`design_error_covariance`: ``Sigma_u`` of the AUs extended to the design's pose and pose x AU columns (eq. 5b);
* :class:`EivFit`: a corrected fit with the attributes the engine's PLS fit has (``coef_``, ``raw_intercept_``, ...).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from aumesh.core.errors import ConfigError
from aumesh.core.schema import AU_COLUMNS, POSE_COLUMNS
from aumesh.model.cross_products import CrossProducts

__all__ = [
    "EivFit",
    "IdentificationScreen",
    "corrected_fit",
    "design_error_covariance",
    "dominant_partners",
    "first_stage_strength",
    "floored_corrected_coef",
    "identification_screen",
    "instrumental_coef",
    "instrumental_fit",
    "load_sigma_u",
    "partner_group",
    "screen_grid",
]

#: Eigenvalues of S below this fraction of the largest are a column without variance (a constant input): its
#: coefficient is 0, as the engine gives it (aumesh.pipeline.evaluate.constant_inputs).
_RANK_RTOL = 1e-12


def _sym_eig(S: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigen-decomposition of a symmetric PSD matrix restricted to its range: (eigenvalues > 0, vectors, kept mask)."""
    lam, V = np.linalg.eigh(0.5 * (S + S.T))
    keep = lam > _RANK_RTOL * max(float(lam.max(initial=0.0)), 0.0)
    return lam[keep], V[:, keep], keep


def _corrected_inverse(S: np.ndarray, sigma_u: np.ndarray, floor: float) -> np.ndarray:
    """``S_c^-1`` of docs/method.md eq. 5: the inverse of the corrected moments with each direction's reliability floored.

    Whitened by ``S^-1/2``, the noise is ``M = S^-1/2 Sigma_u S^-1/2 = U diag(kappa) U'``; direction ``i`` keeps a share
    ``rho_i = 1 - kappa_i`` of its variance (its reliability). ``S - Sigma_u = S^1/2 U diag(rho) U' S^1/2``; with
    ``rho_i`` floored at ``floor`` the inverse is ``S^-1/2 U diag(1 / max(rho_i, floor)) U' S^-1/2``: never more than
    ``1 / floor`` times the uncorrected inverse along any whitened direction. On the null space of ``S`` it is 0.
    """
    lam, V, _ = _sym_eig(S)
    root_inv = V / np.sqrt(lam)  # S^-1/2 on the range, as V diag(lam^-1/2) (columns)
    M = root_inv.T @ sigma_u @ root_inv
    kappa, U = np.linalg.eigh(0.5 * (M + M.T))
    rho = np.maximum(1.0 - kappa, floor)
    W = root_inv @ U  # (p, r)
    return (W / rho) @ W.T


def floored_corrected_coef(sxx: np.ndarray, sxy: np.ndarray, sigma_u: np.ndarray, floor: float = 0.3) -> np.ndarray:
    """Corrected least squares with a reliability floor (docs/method.md eqs. 4-5).

    Parameters
    ----------
    sxx : ndarray of shape (p, p)
        Within-video second moments of the observed design, ``X'X_w / n`` (or the sums: ``sxx``, ``sxy`` and
        ``sigma_u`` need only share the scale, so ``X'X_w``, ``X'Y_w`` and ``n Sigma_u`` work as well).
    sxy : ndarray of shape (p, q)
        ``X'Y_w / n``.
    sigma_u : ndarray of shape (p, p)
        The design's within-video error covariance (0 rows and columns for inputs measured without error).
    floor : float, default=0.3
        Smallest reliability a whitened direction may have (``rho >= floor``; 0.3: amplified at most ~3.3x).

    Returns
    -------
    coef : ndarray of shape (p, q)
        ``S_c^-1 S_xy``; with ``sigma_u = 0`` the least-squares slope ``S^-1 S_xy`` (the card's fit with every component).
    """
    sxx, sxy, sigma_u = (np.asarray(a, dtype=np.float64) for a in (sxx, sxy, sigma_u))
    if sxx.shape != sigma_u.shape or sxx.shape[0] != sxy.shape[0]:
        raise ValueError(f"floored_corrected_coef: shapes sxx {sxx.shape}, sxy {sxy.shape}, sigma_u {sigma_u.shape}")
    return _corrected_inverse(sxx, sigma_u, floor) @ sxy


# ----------------------------------------------------------------------------------------------- the screen
@dataclass
class IdentificationScreen:
    """The AU identification screen's result (docs/method.md eq. 6), AU order of ``names``.

    Attributes
    ----------
    names : list of str, length k
    sigma_star : ndarray of shape (k,)
        Smallest grid sd at which the AU's field turns (cosine to the uncorrected field below ``turn_cosine``);
        NaN: it does not turn within the grid.
    flagged : ndarray of bool, shape (k,)
        ``sigma_star < flag_below``.
    partner : list of str, length k
        Each AU's dominant partner ``argmax_j |r_kj| ||B_j|| / ||B_k||``.
    partner_weight : ndarray of shape (k,)
        That maximum: how strongly the partner's field can leak into the AU's.
    group_sigma_star : ndarray of shape (k,)
        ``sigma*`` of the partner group's field ``B_k + B_j`` (NaN: does not turn within the grid).
    grid : ndarray of shape (n_sigma,)
    cosines : ndarray of shape (n_sigma, k)
        Cosine of each AU's corrected field to its uncorrected one at each grid sd.
    flag_below, turn_cosine, floor : float
    """

    names: list[str]
    sigma_star: np.ndarray
    flagged: np.ndarray
    partner: list[str]
    partner_weight: np.ndarray
    group_sigma_star: np.ndarray
    grid: np.ndarray
    cosines: np.ndarray
    flag_below: float
    turn_cosine: float
    floor: float
    field_norm: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def flagged_names(self) -> list[str]:
        return [n for n, f in zip(self.names, self.flagged, strict=True) if f]

    def to_card(self) -> dict[str, dict]:
        """``model_card.json``'s ``au_identification``: ``{AU: {"sigma_star", "flagged", "partner", ...}}``."""
        out = {}
        for i, name in enumerate(self.names):
            s, g = self.sigma_star[i], self.group_sigma_star[i]
            out[name] = {
                "sigma_star": None if np.isnan(s) else round(float(s), 6),
                "flagged": bool(self.flagged[i]),
                "partner": self.partner[i],
                "group": partner_group(name, self.partner[i]),
                "group_sigma_star": None if np.isnan(g) else round(float(g), 6),
            }
        return out

    def release_arrays(self) -> dict[str, np.ndarray]:
        """The release NPZ's ``au_identification_*`` arrays (AU_COLUMNS order)."""
        return {
            "au_identification_sigma_star": self.sigma_star.astype(np.float64),
            "au_identification_flagged": self.flagged.astype(bool),
            "au_identification_partner": np.array(self.partner, dtype=str),
            "au_identification_flag_below": np.array(self.flag_below, dtype=np.float64),
        }


def partner_group(au: str, partner: str) -> str:
    """The name of an AU's partner group, both AUs moved together (``"AU09+AU10"``): sorted, so a pair is one name."""
    return "+".join(sorted((au, partner)))


def screen_grid(sigma_step: float, sigma_max: float) -> np.ndarray:
    """``sigma_step, 2 sigma_step, ..., sigma_max`` (the last step may be shorter so the grid ends at ``sigma_max``)."""
    n = int(np.floor(sigma_max / sigma_step + 1e-9))
    grid = sigma_step * np.arange(1, n + 1)
    return grid if np.isclose(grid[-1], sigma_max) else np.append(grid, sigma_max)


def _cosine_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cosine of (k, q) arrays; 1 where both rows are 0 (nothing to turn)."""
    dot = np.einsum("kq,kq->k", a, b)
    denom = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
    return np.divide(dot, denom, out=np.ones_like(dot), where=denom > 0)


def dominant_partners(sxx: np.ndarray, coef: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each input's dominant partner ``j = argmax_{j != k} |r_kj| ||B_j|| / ||B_k||`` (docs/method.md eq. 6c).

    Under noise, ``k``'s fitted field borrows from ``j``'s in proportion to their correlation and to ``j``'s field size.

    Parameters
    ----------
    sxx : ndarray of shape (k, k)
        Within-video moments of the inputs (their correlations ``r`` follow).
    coef : ndarray of shape (k, q)
        Uncorrected fields, one row per input.

    Returns
    -------
    partner : ndarray of int, shape (k,)
    weight : ndarray of shape (k,)
        The maximised ``|r_kj| ||B_j|| / ||B_k||`` (inf when ``B_k`` is 0 and a correlated ``B_j`` is not).
    """
    sd = np.sqrt(np.clip(np.diagonal(sxx), 0.0, None))
    outer = np.outer(sd, sd)
    r = np.divide(sxx, outer, out=np.zeros_like(sxx), where=outer > 0)
    norm = np.linalg.norm(coef, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        weight = np.abs(r) * norm[None, :] / norm[:, None]
    weight = np.nan_to_num(weight, nan=0.0)
    np.fill_diagonal(weight, -np.inf)
    partner = np.argmax(weight, axis=1)
    return partner, weight[np.arange(len(partner)), partner]


def identification_screen(
    sxx: np.ndarray,
    sxy: np.ndarray,
    names: Sequence[str] = AU_COLUMNS,
    sigma_step: float = 0.005,
    sigma_max: float = 0.20,
    flag_below: float = 0.10,
    turn_cosine: float = 0.5,
    floor: float = 0.3,
) -> IdentificationScreen:
    """Which AU fields an isotropic detector noise could turn (docs/method.md eq. 6).

    For each grid sd ``sigma``, the floored corrected fit with ``Sigma_u = sigma^2 I`` (:func:`floored_corrected_coef`;
    whitening an isotropic noise by ``S`` keeps ``S``'s eigenvectors, so one eigen-decomposition serves every
    ``sigma``); ``sigma*_k`` is the first ``sigma`` at which AU ``k``'s field has a cosine below ``turn_cosine`` with the
    uncorrected one. Cost: one ``(k, k)`` eigen-decomposition and one ``(k, k) @ (k, q)`` product per grid point.

    Parameters
    ----------
    sxx : ndarray of shape (k, k)
        Within-video second moments of the AU block, ``X'X_w / n`` (intensity units: ``sigma`` is in the same units).
    sxy : ndarray of shape (k, q)
        ``X'Y_w / n`` of the AU block with the mesh.
    names : sequence of str, length k
    sigma_step, sigma_max, flag_below, turn_cosine, floor : float
        ``model.identification`` (conf/model/pls.yaml).

    Returns
    -------
    IdentificationScreen
    """
    S = 0.5 * (np.asarray(sxx, dtype=np.float64) + np.asarray(sxx, dtype=np.float64).T)
    Sxy = np.asarray(sxy, dtype=np.float64)
    k = len(names)
    if S.shape != (k, k) or Sxy.shape[0] != k:
        raise ValueError(f"identification_screen: sxx {S.shape}, sxy {Sxy.shape} for {k} inputs")
    lam, V, _ = _sym_eig(S)
    VtSxy = V.T @ Sxy  # (r, q): the moments in S's eigenbasis
    B = V @ (VtSxy / lam[:, None])  # uncorrected least-squares fields (k, q)
    grid = screen_grid(sigma_step, sigma_max)
    partner, weight = dominant_partners(S, B)
    group = B + B[partner]
    cos = np.empty((len(grid), k))
    group_cos = np.empty((len(grid), k))
    for g, sigma in enumerate(grid):
        # eq. 5 with Sigma_u = sigma^2 I: kappa_i = sigma^2 / lambda_i along S's own eigenvectors
        rho = np.maximum(1.0 - sigma**2 / lam, floor)
        Bc = V @ (VtSxy / (lam * rho)[:, None])
        cos[g] = _cosine_rows(Bc, B)
        group_cos[g] = _cosine_rows(Bc + Bc[partner], group)
    return IdentificationScreen(
        names=list(names),
        sigma_star=_first_turn(grid, cos, turn_cosine),
        flagged=_first_turn(grid, cos, turn_cosine) < flag_below,
        partner=[names[j] for j in partner],
        partner_weight=weight,
        group_sigma_star=_first_turn(grid, group_cos, turn_cosine),
        grid=grid,
        cosines=cos,
        flag_below=float(flag_below),
        turn_cosine=float(turn_cosine),
        floor=float(floor),
        field_norm=np.linalg.norm(B, axis=1),
    )


def _first_turn(grid: np.ndarray, cos: np.ndarray, turn_cosine: float) -> np.ndarray:
    """Per column, the first grid value whose cosine is below ``turn_cosine`` (NaN: none)."""
    turned = cos < turn_cosine
    first = np.argmax(turned, axis=0)
    return np.where(turned.any(axis=0), grid[first], np.nan)


# ------------------------------------------------------------------------------------------ error covariances
def load_sigma_u(path: str | Path, names: Sequence[str] = AU_COLUMNS) -> np.ndarray:
    """The AU detector's within-video error covariance from ``model.eiv.sigma_u``.

    A ``.npy`` of shape (20, 20), rows and columns in ``au_columns`` order; or an ``.npz`` with ``sd`` (20,) and
    ``correlation`` (20, 20) (``Sigma_u = diag(sd) R diag(sd)``). It must be finite, symmetric and positive
    semi-definite. Errors name the file and the fix.
    """
    path = Path(path)
    k = len(names)
    fix = (
        f"Fix: model.eiv.sigma_u must be a .npy of shape ({k}, {k}) (rows and columns in au_columns order: "
        f"{', '.join(names)}) or an .npz with sd ({k},) and correlation ({k}, {k}); docs/method.md"
    )
    if not path.is_file():
        raise ConfigError(f"model.eiv.sigma_u={path}: no such file. {fix}")
    try:
        loaded = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise ConfigError(f"model.eiv.sigma_u={path}: not a numpy file ({err}). {fix}") from None
    if isinstance(loaded, np.lib.npyio.NpzFile):
        with loaded:
            if not {"sd", "correlation"} <= set(loaded.files):
                raise ConfigError(f"model.eiv.sigma_u={path}: the .npz has {sorted(loaded.files)}. {fix}")
            sd, corr = np.asarray(loaded["sd"], dtype=np.float64), np.asarray(loaded["correlation"], dtype=np.float64)
        if sd.shape != (k,) or corr.shape != (k, k):
            raise ConfigError(f"model.eiv.sigma_u={path}: sd {sd.shape}, correlation {corr.shape}. {fix}")
        sigma = sd[:, None] * corr * sd[None, :]
    else:
        sigma = np.asarray(loaded, dtype=np.float64)
    if sigma.shape != (k, k):
        raise ConfigError(f"model.eiv.sigma_u={path}: shape {sigma.shape}. {fix}")
    if not np.isfinite(sigma).all():
        raise ConfigError(f"model.eiv.sigma_u={path}: holds NaN or inf. {fix}")
    if not np.allclose(sigma, sigma.T, rtol=1e-8, atol=1e-12):
        raise ConfigError(f"model.eiv.sigma_u={path}: not symmetric (a covariance is). {fix}")
    smallest = float(np.linalg.eigvalsh(sigma).min())
    if smallest < -1e-10 * max(float(np.abs(sigma).max()), 1e-300):
        raise ConfigError(
            f"model.eiv.sigma_u={path}: not positive semi-definite (smallest eigenvalue {smallest:.3g}). {fix}"
        )
    return 0.5 * (sigma + sigma.T)


def design_error_covariance(
    sigma_u: np.ndarray, columns: Sequence[str], pose_mean: np.ndarray, pose_second: np.ndarray
) -> np.ndarray:
    """The design's error covariance from the AUs' (docs/method.md eq. 5b).

    Pose is taken as measured without error (its rows and columns are 0). A pose x AU column ``p * a_k`` carries the
    error ``p u_k``: with the pose independent of the AU error, ``Cov(u_k, p u_l) = E[p] Sigma_kl`` and
    ``Cov(p u_k, p' u_l) = E[p p'] Sigma_kl``, the expectations over the frames (raw pose, radians).

    Parameters
    ----------
    sigma_u : ndarray of shape (20, 20)
        The AUs' within-video error covariance (AU_COLUMNS order).
    columns : sequence of str
        The design's columns (``aumesh.core.schema.feature_columns``: AUs, pose, ``"<pose>*<AU>"``).
    pose_mean : ndarray of shape (3,)
        ``E[p]`` over the frames, POSE_COLUMNS order.
    pose_second : ndarray of shape (3, 3)
        ``E[p p']`` over the frames.

    Returns
    -------
    ndarray of shape (len(columns), len(columns))
    """

    def parts(c: str) -> tuple[str | None, str | None]:  # (pose factor, AU) of a column; (pose, None) for pose
        if "*" in c:
            pose, au = c.split("*")
            return pose, au
        return (None, c) if c in AU_COLUMNS else (c, None)

    decomposed = [parts(c) for c in columns]
    out = np.zeros((len(columns), len(columns)))
    for i, (pi, ai) in enumerate(decomposed):
        for j, (pj, aj) in enumerate(decomposed):
            if ai is None or aj is None:
                continue
            s = sigma_u[AU_COLUMNS.index(ai), AU_COLUMNS.index(aj)]
            if pi is None and pj is None:
                weight = 1.0
            elif pi is None or pj is None:
                weight = pose_mean[POSE_COLUMNS.index(pi or pj)]
            else:
                weight = pose_second[POSE_COLUMNS.index(pi), POSE_COLUMNS.index(pj)]
            out[i, j] = weight * s
    return out


# ----------------------------------------------------------------------------------------------- instruments
def instrumental_coef(szx: np.ndarray, szy: np.ndarray) -> np.ndarray:
    """Just-identified within two-stage least squares: ``B = (Z'X)^-1 Z'Y`` (docs/method.md eq. 7).

    Parameters
    ----------
    szx : ndarray of shape (p, p)
        Within-video cross-moments of the instruments with the design (rows: instruments).
    szy : ndarray of shape (p, q)

    Returns
    -------
    coef : ndarray of shape (p, q)
    """
    return np.linalg.solve(np.asarray(szx, dtype=np.float64), np.asarray(szy, dtype=np.float64))


def first_stage_strength(
    szz: np.ndarray, szx: np.ndarray, sxx: np.ndarray, n: int, names: Sequence[str] = AU_COLUMNS
) -> dict[str, dict[str, float]]:
    """Per instrumented input, the first stage's R² and F: how much of ``x_k``'s within-video variance the
    instruments explain (docs/method.md eq. 7b; weak instruments, F below ~10, leave 2SLS biased toward least squares).

    Parameters
    ----------
    szz : ndarray of shape (m, m)
        Within-video moments of the instruments.
    szx : ndarray of shape (m, p)
        Instruments x design.
    sxx : ndarray of shape (p, p)
        Design.
    n : int
        Frames (the F statistic's denominator degrees of freedom are ``n - m``).
    names : sequence of str
        The first ``len(names)`` design columns' names (the instrumented AUs).

    Returns
    -------
    dict
        ``{name: {"r2": R², "f": F}}``.
    """
    szz, szx, sxx = (np.asarray(a, dtype=np.float64) for a in (szz, szx, sxx))
    m = szz.shape[0]
    explained = np.einsum("ip,ip->p", szx, np.linalg.lstsq(szz, szx, rcond=None)[0])  # diag(X'Z (Z'Z)^-1 Z'X)
    out = {}
    for k, name in enumerate(names):
        total = sxx[k, k]
        r2 = float(explained[k] / total) if total > 0 else 0.0
        r2 = min(max(r2, 0.0), 1.0)
        f = float(r2 / m / ((1.0 - r2) / max(n - m, 1))) if r2 < 1.0 else float("inf")
        out[name] = {"r2": r2, "f": f}
    return out


# ----------------------------------------------------------------------------------------------- fits
@dataclass
class EivFit:
    """A fit corrected for detector noise, with the attributes of the engine's PLS fit that scoring and release read.

    Attributes
    ----------
    coef_ : ndarray of shape (n_targets, n_features)
        ``X @ coef_.T + raw_intercept_`` predicts (scikit-learn's layout).
    raw_intercept_ : ndarray of shape (n_targets,)
    x_mean_ : ndarray of shape (n_features,)
    y_mean_ : ndarray of shape (n_targets,)
    n_samples_ : int
    method : str
        ``"corrected"`` or ``"instruments"``.
    uncorrected_coef_ : ndarray of shape (n_targets, n_features)
        The least-squares fit on the same moments, written beside the corrected one.
    """

    coef_: np.ndarray
    raw_intercept_: np.ndarray
    x_mean_: np.ndarray
    y_mean_: np.ndarray
    n_samples_: int
    method: str
    uncorrected_coef_: np.ndarray


def _least_squares(sxx: np.ndarray, sxy: np.ndarray) -> np.ndarray:
    return floored_corrected_coef(sxx, sxy, np.zeros_like(sxx), 1.0)


def corrected_fit(stats: CrossProducts, sigma_design: np.ndarray, floor: float) -> EivFit:
    """Floored corrected least squares from the within-video statistics of the training rows.

    Parameters
    ----------
    stats : CrossProducts
        Within-video statistics of (design, mesh): ``cxx = X'X_w``, ``cxy = X'Y_w`` over ``n`` frames.
    sigma_design : ndarray of shape (p, p)
        The design's within-video error covariance (:func:`design_error_covariance`); ``n sigma_design`` is subtracted.
    floor : float
        ``model.eiv.floor``.
    """
    cxx, cxy = stats.cxx, stats.cxy
    coef = floored_corrected_coef(cxx, cxy, stats.n * np.asarray(sigma_design, dtype=np.float64), floor).T
    return _fit(stats.x_mean, stats.y_mean, int(stats.n), coef, _least_squares(cxx, cxy).T, "corrected")


def instrumental_fit(stats: CrossProducts, p: int) -> EivFit:
    """Within 2SLS from the statistics of the augmented design ``[X | Z]`` (``p`` design columns, then ``p``
    instrument columns) with the mesh; the design's own statistics are the first ``p`` columns."""
    cxx, cxy = stats.cxx, stats.cxy
    coef = instrumental_coef(cxx[p:, :p], cxy[p:]).T
    uncorrected = _least_squares(cxx[:p, :p], cxy[:p]).T
    return _fit(stats.x_mean[:p], stats.y_mean, int(stats.n), coef, uncorrected, "instruments")


def _fit(
    x_mean: np.ndarray, y_mean: np.ndarray, n: int, coef: np.ndarray, uncorrected: np.ndarray, method: str
) -> EivFit:
    """An :class:`EivFit` of ``coef`` (q, p) with the intercept that makes it predict raw inputs."""
    return EivFit(coef, y_mean - coef @ x_mean, x_mean, y_mean, n, method, uncorrected)
