"""AU detector noise for the synthetic tables (:mod:`aumesh.synthetic.tables`), and the generator's own error covariance.

The AU intensities come from an image detector whose errors are correlated across AUs (py-feat's detectors read
AU06/AU12, AU25/AU26, AU01/AU02, AU09/AU10 from the same image evidence) and last several frames. The generator adds
to the recorded AUs an error ``e`` that is, per video,

* stationary AR(1) in time: ``e_t = phi e_(t-1) + sqrt(1 - phi^2) z_t``, ``e_0`` drawn from the stationary law, so every
  frame has covariance ``Sigma = sd^2 R``;
* correlated across AUs: the innovations ``z_t ~ N(0, sd^2 R)``, ``R`` from pairs of AUs with a correlation
  (:func:`correlation_matrix`);
* independent of the true AUs and of everything else in the video (its own random stream).

The within-video estimators (docs/method.md) see the error after per-video demeaning. With ``T_v`` frames in video
``v``, ``E[sum_t (e_t - ebar)(e_t - ebar)'] = Sigma (T_v - (1/T_v) sum_(s,t) phi^|s-t|)`` (the mean of an AR(1) does
not average away as fast as white noise does), so the within-video error covariance per frame is

    Sigma_u = Sigma * sum_v (T_v - (1/T_v) sum_(s,t) phi^|s-t|) / sum_v T_v        (:func:`au_error_covariance`)

which is what ``model.eiv.sigma_u`` takes (:func:`save_sigma_u`). Pure functions on arrays; nothing at import time.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.signal import lfilter

from aumesh.core.io import atomic_path
from aumesh.core.schema import AU_COLUMNS

#: AU pairs py-feat's detectors read together (one image region, one classifier's shared features), with the
#: correlation of their errors: disjoint pairs at 0.5 keep the correlation matrix positive definite.
DETECTOR_PAIRS: tuple[tuple[str, str, float], ...] = (
    ("AU01", "AU02", 0.5),
    ("AU06", "AU12", 0.5),
    ("AU09", "AU10", 0.5),
    ("AU25", "AU26", 0.5),
)


def correlation_matrix(pairs: Sequence[tuple[str, str, float]], names: Sequence[str] = AU_COLUMNS) -> np.ndarray:
    """The cross-AU correlation of the detector's error from ``(AU, AU, correlation)`` pairs.

    Returns
    -------
    ndarray, shape (20, 20)
        Unit diagonal, ``R[a, b] = R[b, a] = rho`` for each pair, 0 elsewhere; positive definite.

    Raises
    ------
    ValueError
        An unknown AU, a pair of one AU with itself, |rho| >= 1, or pairs that make no valid correlation matrix.
    """
    names = list(names)
    R = np.eye(len(names))
    for a, b, rho in pairs:
        if a not in names or b not in names or a == b:
            raise ValueError(f"au_noise_correlation: pair ({a!r}, {b!r}) needs two different AUs of {', '.join(names)}")
        if not -1.0 < float(rho) < 1.0:
            raise ValueError(f"au_noise_correlation: ({a}, {b}) correlation {rho} must lie strictly between -1 and 1")
        R[names.index(a), names.index(b)] = R[names.index(b), names.index(a)] = float(rho)
    smallest = float(np.linalg.eigvalsh(R).min())
    if smallest <= 0.0:
        raise ValueError(
            f"au_noise_correlation: these pairs make no valid correlation matrix (smallest eigenvalue {smallest:.3g}); "
            f"lower the correlations of pairs that share an AU"
        )
    return R


def ar1_noise(rng: np.random.Generator, n: int, sd: float, ar: float, chol: np.ndarray) -> np.ndarray:
    """A stationary AR(1) error series, correlated across AUs.

    Parameters
    ----------
    rng : the error's own random stream (one ``standard_normal((n, k))`` draw).
    n : frames.
    sd : the error's standard deviation at every frame.
    ar : AR(1) coefficient ``phi`` in (-1, 1) (frame to frame).
    chol : ndarray, shape (k, k)
        Lower Cholesky factor of the cross-AU correlation ``R`` (:func:`correlation_matrix`).

    Returns
    -------
    ndarray, shape (n, k)
        ``e_t = phi e_(t-1) + sqrt(1 - phi^2) z_t``, ``z_t ~ N(0, sd^2 R)``, ``e_0 ~ N(0, sd^2 R)`` (stationary):
        ``Cov(e_t, e_(t+h)) = phi^|h| sd^2 R``.
    """
    if not -1.0 < ar < 1.0:
        raise ValueError(f"au_noise_ar={ar}: the AR(1) coefficient must lie strictly between -1 and 1")
    z = sd * rng.standard_normal((n, chol.shape[0])) @ chol.T
    c = np.sqrt(1.0 - ar * ar)
    z[0] /= c  # e_0 = z_0: drawn from the stationary distribution
    return lfilter([c], [1.0, -ar], z, axis=0)


def ar1_pair_sum(T: np.ndarray, ar: float) -> np.ndarray:
    """``sum_(s,t < T) phi^|s-t|`` for each length in ``T`` (closed form; ``T`` for white noise).

    ``= T + 2 sum_(k=1)^(T-1) (T - k) phi^k = T (1 + phi) / (1 - phi) - 2 phi (1 - phi^T) / (1 - phi)^2``.
    """
    T = np.asarray(T, dtype=np.float64)
    if ar == 0.0:
        return T
    return T * (1.0 + ar) / (1.0 - ar) - 2.0 * ar * (1.0 - ar**T) / (1.0 - ar) ** 2


def within_share(counts: np.ndarray, ar: float) -> float:
    """Share of a stationary AR(1)'s variance that survives per-video demeaning, averaged over all frames:
    ``sum_v (T_v - ar1_pair_sum(T_v) / T_v) / sum_v T_v`` (``1 - n_videos / n_frames`` for white noise)."""
    T = np.asarray(counts, dtype=np.float64)
    return float(np.sum(T - ar1_pair_sum(T, ar) / T) / np.sum(T))


def au_error_covariance(spec, counts: np.ndarray, detector: int = 1) -> np.ndarray:
    """The generator's within-video error covariance of a detector's AUs, ``Sigma_u`` (analytic).

    Parameters
    ----------
    spec : :class:`aumesh.synthetic.tables.SynthSpec`
        Its ``au_noise_sd`` (``instrument_noise_sd`` for ``detector=2``), ``au_noise_ar`` and ``au_noise_correlation``.
    counts : ndarray, shape (n_videos,)
        Frames per video (``write_tables``' summary ``frames_per_video``; ``tables.frames_per_video(spec)``).
    detector : 1 (the AUs as recorded) or 2 (the second detector's ``{au}_2`` columns).

    Returns
    -------
    ndarray, shape (20, 20)
        ``sd^2 R * within_share(counts, phi)``, rows and columns in ``AU_COLUMNS`` order: the expected
        ``sum_v sum_t (e_vt - ebar_v)(e_vt - ebar_v)' / sum_v T_v`` of the error before the recorded AUs are clipped
        to [0, 1] (zeros when the detector is noise-free).
    """
    sd = {1: spec.au_noise_sd, 2: spec.instrument_noise_sd}[detector]
    if sd == 0.0:
        return np.zeros((len(AU_COLUMNS), len(AU_COLUMNS)))
    R = correlation_matrix(spec.au_noise_correlation)
    return sd**2 * R * within_share(counts, spec.au_noise_ar)


def within_covariance(values: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The within-video covariance per frame of ``values`` (n, k), rows grouped by video in runs of ``counts``:
    ``sum_v sum_t (x_vt - xbar_v)(x_vt - xbar_v)' / sum_v T_v`` (what :func:`au_error_covariance` predicts)."""
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    means = np.add.reduceat(values, starts, axis=0) / np.asarray(counts)[:, None]
    w = values - np.repeat(means, counts, axis=0)
    return w.T @ w / len(values)


def save_sigma_u(path: str | Path, sigma_u: np.ndarray) -> Path:
    """Write ``sigma_u`` (20, 20, ``AU_COLUMNS`` order) as the ``.npy`` ``model.eiv.sigma_u`` reads
    (:func:`aumesh.model.eiv.load_sigma_u`)."""
    sigma_u = np.asarray(sigma_u, dtype=np.float64)
    if sigma_u.shape != (len(AU_COLUMNS), len(AU_COLUMNS)):
        raise ValueError(f"save_sigma_u: shape {sigma_u.shape}, need ({len(AU_COLUMNS)}, {len(AU_COLUMNS)})")
    path = Path(path)
    with atomic_path(path, suffix=".npy") as tmp:
        np.save(tmp, sigma_u)
    return path
