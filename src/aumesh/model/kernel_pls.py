"""Exact PLS2 fit from sufficient statistics, on NumPy alone (the computation behind :class:`aumesh.model.pls.PLSRegression`).

A PLS2 fit (scikit-learn's ``PLSRegression``: NIPALS, regression deflation,
mode A) depends on the data only through

* the number of rows ``n``,
* the column sums of ``X`` (n, p) and ``Y`` (n, q),
* the cross-product matrices ``X^T X`` (p, p) and ``X^T Y`` (p, q),
* the diagonal of ``Y^T Y`` (q,) -- needed only for ``scale=True`` and for scores.

:class:`CrossProducts` accumulates these in float64, chunk by chunk, without
ever storing rows. :func:`fit_statistics` fits from them with the improved
kernel algorithm of

    B. S. Dayal and J. F. MacGregor, "Improved PLS algorithms",
    Journal of Chemometrics 11 (1997) 73-85 -- "modified kernel algorithm #1"
    (referred to below as "D&M Algorithm 1"),

which, at convergence of sklearn's power iterations, gives the same weights,
loadings, rotations and coefficients as sklearn's NIPALS, and in the same
pass the coefficients for every smaller number of components. The steps, as
numbered in the code comments (C = Xs^T Xs, S = Xs^T Ys of the centered,
optionally standardized data)::

    1. C, S from the statistics (no rows needed)
    for a = 1..A:
    2. w_a = dominant eigenvector of S S^T           (left singular vector of S)
    3. r_a = w_a - sum_{j<a} (p_j^T w_a) r_j         (so X r_a = deflated X w_a)
    4. tt_a = r_a^T C r_a                            (t_a^T t_a)
    5. p_a = C r_a / tt_a                            (X loading)
    6. q_a = S^T r_a / tt_a                          (Y loading)
    7. S <- S - tt_a p_a q_a^T                       (deflation of X^T Y only)
    8. B = R Q^T; B_k = R[:, :k] Q[:, :k]^T for every k <= A

The statistics are :class:`aumesh.model.cross_products.CrossProducts`; scoring a model on
held-out statistics is :mod:`aumesh.model.scoring`. :class:`aumesh.model.pls.PLSRegression` is the
scikit-learn estimator on top; the pipeline's passes and fits use this module directly, so a stage that
only fits from statistics does not import scikit-learn (and SciPy's statistics with it: ~1 s a process).

Notation: ``n`` rows, ``p`` features, ``q`` targets, ``A`` components.
"""

from __future__ import annotations

import numbers
import warnings
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from aumesh.core.blas import one_blas_thread
from aumesh.model.cross_products import CrossProducts

__all__ = ["PLSFit", "check_n_components", "coefficient_path", "fit_statistics", "intercept_path", "kernel_pls"]


@dataclass(eq=False, repr=False)  # arrays: compared by identity, never printed whole
class PLSFit:
    """A PLS2 fit from statistics: the fitted attributes of :class:`aumesh.model.pls.PLSRegression`, under the same
    names, on a plain object (no scikit-learn).

    Attributes
    ----------
    coef_ : ndarray of shape (n_targets, n_features)
        Coefficients in raw X units: ``X @ coef_.T + raw_intercept_`` predicts.
    raw_intercept_ : ndarray of shape (n_targets,)
        ``y_mean_ - x_mean_ @ coef_.T``.
    x_weights_, x_loadings_, x_rotations_ : ndarray of shape (n_features, n_components)
        ``W``, ``P``, ``R`` (steps 2, 5, 3).
    y_loadings_ : ndarray of shape (n_targets, n_components)
        ``Q`` (step 6).
    x_mean_, x_std_ : ndarray of shape (n_features,)
    y_mean_, y_std_ : ndarray of shape (n_targets,)
    n_components_ : int
        Components that carry information (the rest are zero).
    n_samples_ : int
    """

    x_weights_: np.ndarray
    x_loadings_: np.ndarray
    y_loadings_: np.ndarray
    x_rotations_: np.ndarray
    coef_: np.ndarray
    x_mean_: np.ndarray
    y_mean_: np.ndarray
    x_std_: np.ndarray
    y_std_: np.ndarray
    raw_intercept_: np.ndarray
    n_components_: int
    n_samples_: int

    @cached_property
    def coef_path_(self) -> np.ndarray:
        """(n_components, n_targets, n_features): :func:`coefficient_path`, built on first use."""
        return coefficient_path(self)

    @property
    def raw_intercept_path_(self) -> np.ndarray:
        """(n_components, n_targets): :func:`intercept_path`."""
        return intercept_path(self)


def fit_statistics(stats: CrossProducts, n_components: int, scale: bool) -> PLSFit:
    """PLS2 fit (scikit-learn's ``PLSRegression(n_components, scale)``) from the statistics of the training rows.

    Parameters
    ----------
    stats : CrossProducts
        Statistics of the training rows (e.g. ``total - held_out``).
    n_components : int
        ``1 <= n_components <= min(n_samples, n_features)``.
    scale : bool
        Standardize X and Y columns (std with ``ddof=1``; a zero std is replaced by 1, as in sklearn).

    Returns
    -------
    PLSFit

    Raises
    ------
    ValueError
        Fewer than 2 rows, a bad ``n_components``, NaN or infinity in the statistics (sklearn's messages).
    """
    if not isinstance(stats, CrossProducts):
        raise TypeError(f"stats must be a CrossProducts, got {type(stats).__name__}.")
    n, p, q = stats.n, stats.n_features, stats.n_targets
    if n < 2:
        raise ValueError(f"Found {n} sample(s) while a minimum of 2 is required.")
    A = check_n_components(n_components, n, p)
    for name in ("sum_x", "sum_y", "xtx", "xty", "yty_diag"):
        if not np.isfinite(getattr(stats, name)).all():
            raise ValueError(f"Statistics contain NaN or infinity ({name}).")

    x_mean, y_mean = stats.x_mean, stats.y_mean
    cxx, cxy = stats.cxx, stats.cxy
    if scale:
        # sklearn's _center_scale_xy: std with ddof=1, exactly-zero std -> 1.
        x_std = np.sqrt(np.diagonal(cxx) / (n - 1))
        x_std[x_std == 0.0] = 1.0
        y_std = np.sqrt(stats.cyy_diag / (n - 1))
        y_std[y_std == 0.0] = 1.0
    else:
        x_std = np.ones(p)
        y_std = np.ones(q)
    # Step 1: cross products of the standardized data Xs = (X - x̄)/x_std, Ys = (Y - ȳ)/y_std.
    zero_var_x = np.diagonal(cxx) == 0.0
    C = cxx / np.outer(x_std, x_std)  # Xs^T Xs, (p, p)
    S = cxy / np.outer(x_std, y_std)  # Xs^T Ys, (p, q); deflated in place below

    # The per-component work is small (p x q) matrices: multi-threaded BLAS only adds
    # synchronisation (10x slower on a busy machine), so run it on one thread.
    with one_blas_thread():
        W, P, Q, R, n_informative = kernel_pls(C, S, A, zero_var_x)

    # Step 8: B = R Q^T in standardized units; back to raw units as sklearn does:
    # coef_ = (B * y_std).T / x_std, shape (q, p): one rank-one term per component, summed in component
    # order, so coef_ is the last of the cumulative sums of coefficient_path, bit for bit (the path itself,
    # A times the size of coef_, is built only when asked for).
    Rr = R / x_std[:, None]  # (p, A)
    Qr = Q * y_std[:, None]  # (q, A)
    coef = np.zeros((q, p))
    for a in range(A):
        coef += np.multiply.outer(Qr[:, a], Rr[:, a])
    return PLSFit(
        x_weights_=W,
        x_loadings_=P,
        y_loadings_=Q,
        x_rotations_=R,
        coef_=coef,
        x_mean_=x_mean,
        y_mean_=y_mean,
        x_std_=x_std,
        y_std_=y_std,
        raw_intercept_=y_mean - x_mean @ coef.T,
        n_components_=n_informative,
        n_samples_=n,
    )


def coefficient_path(fit) -> np.ndarray:
    """Coefficients of every ``k <= A`` of a fit (a :class:`PLSFit` or a fitted ``PLSRegression``), shape
    (A, n_targets, n_features): ``B_k = R[:, :k] Q[:, :k]^T`` in raw units, the cumulative sums of the components'
    rank-one terms (step 8); the last is the fit's ``coef_``, bit for bit."""
    path = np.einsum("qa,pa->aqp", fit.y_loadings_ * fit.y_std_[:, None], fit.x_rotations_ / fit.x_std_[:, None])
    np.cumsum(path, axis=0, out=path)
    return path


def intercept_path(fit) -> np.ndarray:
    """Raw intercepts of every ``k <= A`` of a fit (a :class:`PLSFit` or a fitted ``PLSRegression``), shape
    (A, n_targets): ``y_mean_ - x_mean_ @ B_k^T`` for the ``B_k`` of ``fit.coef_path_``."""
    return fit.y_mean_[None, :] - np.einsum("aqp,p->aq", fit.coef_path_, fit.x_mean_)


def kernel_pls(C, S, A, zero_var_x):
    """D&M Algorithm 1, steps 2-7 (see the module docstring).

    Parameters
    ----------
    C : ndarray of shape (p, p)
        ``Xs^T Xs`` of the centered (optionally standardized) data.
    S : ndarray of shape (p, q)
        ``Xs^T Ys``; deflated in place.
    A : int
        Number of components.
    zero_var_x : ndarray of shape (p,), bool
        Zero-variance X columns (get exactly zero weight).

    Returns
    -------
    W, P, R : ndarray of shape (p, A)
    Q : ndarray of shape (q, A)
    n_informative : int
        Components computed before the deflated ``S`` vanished (the rest are zero).
    """
    p, q = S.shape
    W = np.zeros((p, A))
    P = np.zeros((p, A))
    Q = np.zeros((q, A))
    R = np.zeros((p, A))
    s0 = np.linalg.norm(S)
    # Deflated X^T Y below this is rounding noise of the initial one: stop there.
    s_tol = 64 * np.finfo(np.float64).eps * max(p, q) * s0
    n_informative = 0
    for a in range(A):
        s_norm = np.linalg.norm(S)
        if s0 == 0.0 or s_norm <= s_tol:
            warnings.warn(
                f"Deflated X^T Y vanished after {a} component(s) (Y residual is orthogonal to X); "
                f"components {a + 1}..{A} are set to zero.",
                RuntimeWarning,
                stacklevel=3,  # the caller of fit_statistics
            )
            break
        # Step 2: w = dominant left singular vector of the current
        # X^T Y, i.e. the eigenvector of (X^T Y)(X^T Y)^T with the largest eigenvalue
        # (for q = 1 it is X^T y normalized).
        if q == 1:
            w = S[:, 0] / s_norm
        else:
            _, vecs = np.linalg.eigh(S @ S.T)
            w = vecs[:, -1].copy()
        # A zero-variance column has an exactly zero row in X^T Y and X^T X; eigh leaves
        # rounding noise there: zero it so the column gets an exactly zero coefficient.
        if zero_var_x.any():
            w[zero_var_x] = 0.0
            w /= np.linalg.norm(w)
        # sklearn's _svd_flip_1d: the largest |w_i| is positive.
        w *= np.sign(w[np.argmax(np.abs(w))])
        # Step 3: r_a = w_a - sum_{j<a} (p_j^T w_a) r_j, so that t_a = X r_a = X_a w_a
        # (X_a the deflated X) without deflating X.
        r = w - R[:, :a] @ (P[:, :a].T @ w)
        # Step 4: t_a^T t_a = r_a^T X^T X r_a.
        Cr = C @ r
        tt = float(r @ Cr)
        if not tt > 0.0:
            warnings.warn(
                f"Score of component {a + 1} has zero norm; components {a + 1}..{A} are set to zero.",
                RuntimeWarning,
                stacklevel=3,  # the caller of fit_statistics
            )
            break
        # Step 5: p_a = X^T X r_a / (t^T t).   Step 6: q_a = (r_a^T X^T Y)^T / (t^T t).
        p_a = Cr / tt
        q_a = (r @ S) / tt
        # Step 7: (X^T Y)_{a+1} = (X^T Y)_a - (t^T t) p_a q_a^T.
        S -= tt * np.outer(p_a, q_a)
        W[:, a], P[:, a], Q[:, a], R[:, a] = w, p_a, q_a, r
        n_informative = a + 1
    return W, P, Q, R, n_informative


def check_n_components(n_components, n_samples, n_features):
    if not isinstance(n_components, numbers.Integral) or isinstance(n_components, bool):
        raise ValueError(f"n_components must be an integer, got {n_components!r}.")  # noqa: TRY004 (as sklearn)
    if n_components < 1:
        raise ValueError(f"n_components must be >= 1, got {n_components}.")
    # As sklearn's PLSRegression: bounded by the rank of X^T X (Wegelin p. 25).
    upper = min(n_samples, n_features)
    if n_components > upper:
        raise ValueError(
            f"`n_components` upper bound is {upper} (min(n_samples={n_samples}, n_features={n_features})). "
            f"Got {n_components} instead. Reduce `n_components`."
        )
    return int(n_components)
