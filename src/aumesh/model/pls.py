"""Exact PLS regression from sufficient statistics.

A PLS2 fit (scikit-learn's ``PLSRegression``: NIPALS, regression deflation,
mode A) depends on the data only through

* the number of rows ``n``,
* the column sums of ``X`` (n, p) and ``Y`` (n, q),
* the cross-product matrices ``X^T X`` (p, p) and ``X^T Y`` (p, q),
* the diagonal of ``Y^T Y`` (q,) -- needed only for ``scale=True`` and for scores.

:class:`CrossProducts` accumulates these in float64, chunk by chunk, without
ever storing rows. :class:`PLSRegression` fits from them with the improved
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
held-out statistics is :mod:`aumesh.model.scoring`.

Notation: ``n`` rows, ``p`` features, ``q`` targets, ``A`` components.
"""

from __future__ import annotations

import numbers
import warnings
from functools import cached_property

import numpy as np
from scipy.linalg import pinv
from sklearn.base import (
    BaseEstimator,
    ClassNamePrefixFeaturesOutMixin,
    MultiOutputMixin,
    RegressorMixin,
    TransformerMixin,
)
from sklearn.utils.validation import check_array, check_is_fitted, validate_data
from threadpoolctl import threadpool_limits

from aumesh.model.cross_products import CrossProducts

__all__ = ["PLSRegression"]


# --------------------------------------------------------------------------- #
# PLS estimator
# --------------------------------------------------------------------------- #
class PLSRegression(
    ClassNamePrefixFeaturesOutMixin, TransformerMixin, RegressorMixin, MultiOutputMixin, BaseEstimator
):
    """PLS regression (PLS2) fitted exactly from sufficient statistics.

    Drop-in for :class:`sklearn.cross_decomposition.PLSRegression` (NIPALS,
    regression deflation): it returns the converged solution of sklearn's
    power iterations, computed with D&M Algorithm 1 on the (standardized)
    cross-product matrices. A fit with ``n_components=A`` also yields the
    coefficients for every ``k <= A`` (:attr:`coef_path_`).

    Parameters
    ----------
    n_components : int, default=2
        Number of components, ``1 <= n_components <= min(n_samples, n_features)``.
    scale : bool, default=True
        Standardize X and Y columns (std with ``ddof=1``; a zero std is
        replaced by 1, as in sklearn).

    Attributes
    ----------
    coef_ : ndarray of shape (n_targets, n_features)
        Coefficients in raw X units, same meaning as sklearn's:
        ``predict(X) = (X - _x_mean) @ coef_.T + intercept_``.
    intercept_ : ndarray of shape (n_targets,)
        The Y mean (sklearn's meaning; *not* the intercept for raw X).
    raw_intercept_ : ndarray of shape (n_targets,)
        ``y_mean_ - x_mean_ @ coef_.T``: ``X @ coef_.T + raw_intercept_`` predicts.
    coef_path_ : ndarray of shape (n_components, n_targets, n_features)
        ``coef_path_[k - 1]`` is ``coef_`` of a fit with ``k`` components.
    x_weights_ : ndarray of shape (n_features, n_components)
        ``W``: unit weight vectors of the deflated X (sign as sklearn's).
    x_loadings_ : ndarray of shape (n_features, n_components)
        ``P``.
    y_weights_ : ndarray of shape (n_targets, n_components)
        Equal to ``y_loadings_`` (what sklearn's mode-A power iteration converges to).
    y_loadings_ : ndarray of shape (n_targets, n_components)
        ``Q``.
    x_rotations_ : ndarray of shape (n_features, n_components)
        ``R = W (P^T W)^-1``: scores ``T = X_std R``.
    y_rotations_ : ndarray of shape (n_targets, n_components)
        ``y_weights_ pinv(y_loadings_^T y_weights_)``, as sklearn.
    x_mean_, _x_mean : ndarray of shape (n_features,)
    x_std_, _x_std : ndarray of shape (n_features,)
    y_mean_, _y_mean : ndarray of shape (n_targets,)
    y_std_, _y_std : ndarray of shape (n_targets,)
    n_features_in_ : int
    feature_names_in_ : ndarray of shape (n_features_in_,)
        Only when ``fit`` got X with string column names.
    n_components_ : int
        Number of components that carry information (``n_components``
        unless the deflated ``X^T Y`` vanished earlier; later components are zero).
    n_samples_ : int
        Rows the model was fitted on.

    Notes
    -----
    Scores (``x_scores_``) are not available: no rows are kept.
    """

    def __init__(self, n_components=2, scale=True):
        self.n_components = n_components
        self.scale = scale

    # ------------------------------------------------------------------- fit
    def fit(self, X, y):
        """Fit the model to arrays (one pass to build the statistics, then :meth:`fit_stats`).

        Parameters
        ----------
        X : array-like of shape (n_samples, n_features)
        y : array-like of shape (n_samples,) or (n_samples, n_targets)
            Targets (named ``y`` as in sklearn). float32 input stays float32
            until converted block-wise to float64.

        Returns
        -------
        self : PLSRegression
        """
        if y is None:
            raise ValueError(f"{type(self).__name__} requires y to be passed, but the target y is None.")
        X = validate_data(self, X, dtype=[np.float64, np.float32], ensure_min_samples=2)
        Y = check_array(y, input_name="y", dtype=[np.float64, np.float32], ensure_2d=False, ensure_min_samples=2)
        if X.shape[0] != Y.shape[0]:
            raise ValueError(f"X and y have different numbers of rows: {X.shape[0]} != {Y.shape[0]}.")
        predict_1d = Y.ndim == 1
        # Check n_components before the (long) statistics pass.
        _check_n_components(self.n_components, X.shape[0], X.shape[1])
        stats = CrossProducts.from_arrays(X, Y)
        self._fit_stats(stats)
        self._predict_1d = predict_1d
        return self

    def fit_stats(self, stats):
        """Fit the model built from precomputed statistics.

        Parameters
        ----------
        stats : CrossProducts
            Statistics of the training rows (e.g. ``total - held_out``).

        Returns
        -------
        self : PLSRegression
        """
        if not isinstance(stats, CrossProducts):
            raise TypeError(f"stats must be a CrossProducts, got {type(stats).__name__}.")
        self._fit_stats(stats)
        self.n_features_in_ = stats.n_features
        if hasattr(self, "feature_names_in_"):
            del self.feature_names_in_
        self._predict_1d = False
        return self

    def _fit_stats(self, stats):
        if not isinstance(self.scale, (bool, np.bool_)):
            raise ValueError(f"scale must be a bool, got {self.scale!r}.")  # noqa: TRY004 (sklearn raises ValueError)
        n, p, q = stats.n, stats.n_features, stats.n_targets
        if n < 2:
            raise ValueError(f"Found {n} sample(s) while a minimum of 2 is required.")
        A = _check_n_components(self.n_components, n, p)
        for name in ("sum_x", "sum_y", "xtx", "xty", "yty_diag"):
            if not np.isfinite(getattr(stats, name)).all():
                raise ValueError(f"Statistics contain NaN or infinity ({name}).")

        x_mean, y_mean = stats.x_mean, stats.y_mean
        cxx, cxy = stats.cxx, stats.cxy
        if self.scale:
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
        with threadpool_limits(limits=1, user_api="blas"):
            W, P, Q, R, n_informative = _kernel_pls(C, S, A, zero_var_x)

        # Step 8: B = R Q^T in standardized units; back to raw units as sklearn does:
        # coef_ = (B * y_std).T / x_std, shape (q, p): one rank-one term per component, summed in component
        # order, so coef_ is the last of the cumulative sums coef_path_ holds, bit for bit (the path itself,
        # A times the size of coef_, is built when first asked for).
        Rr = R / x_std[:, None]  # (p, A)
        Qr = Q * y_std[:, None]  # (q, A)
        coef = np.zeros((q, p))
        for a in range(A):
            coef += np.multiply.outer(Qr[:, a], Rr[:, a])
        self.__dict__.pop("coef_path_", None)  # a refit's path is its own

        self.x_weights_ = W
        self.x_loadings_ = P
        self.y_loadings_ = Q
        self.y_weights_ = Q.copy()
        self.x_rotations_ = R
        self.y_rotations_ = self.y_weights_ @ pinv(self.y_loadings_.T @ self.y_weights_, check_finite=False)
        self.coef_ = coef
        self.x_mean_ = self._x_mean = x_mean
        self.y_mean_ = self._y_mean = y_mean
        self.x_std_ = self._x_std = x_std
        self.y_std_ = self._y_std = y_std
        self.intercept_ = y_mean.copy()
        self.raw_intercept_ = y_mean - x_mean @ self.coef_.T
        self.n_components_ = n_informative
        self.n_samples_ = n
        self._n_features_out = A
        return self

    # --------------------------------------------------------- path access
    @cached_property
    def coef_path_(self):
        """Coefficients of every ``k <= n_components``, shape (n_components, n_targets, n_features).

        ``coef_path_[k - 1]`` is ``coef_`` of a fit with ``k`` components (B_k = R_{:, :k} Q_{:, :k}^T, in raw
        units): cumulative sums of the components' rank-one terms, built on first use and kept.
        """
        check_is_fitted(self, "x_rotations_")
        path = np.einsum("qa,pa->aqp", self.y_loadings_ * self.y_std_[:, None], self.x_rotations_ / self.x_std_[:, None])
        np.cumsum(path, axis=0, out=path)
        return path

    def _check_k(self, n_components):
        check_is_fitted(self)
        A = self.x_rotations_.shape[1]
        if (
            not isinstance(n_components, numbers.Integral)
            or isinstance(n_components, bool)
            or not 1 <= n_components <= A
        ):
            raise ValueError(f"n_components must be an integer in [1, {A}] for this model, got {n_components!r}.")
        return int(n_components)

    def coef_for(self, n_components):
        """Coefficients of the model with ``n_components`` components.

        Parameters
        ----------
        n_components : int
            ``1 <= n_components <= self.n_components``.

        Returns
        -------
        coef : ndarray of shape (n_targets, n_features)
        """
        return self.coef_path_[self._check_k(n_components) - 1]

    def raw_intercept_for(self, n_components):
        """Intercept for raw X of the model with ``n_components`` components.

        Returns
        -------
        raw_intercept : ndarray of shape (n_targets,)
            ``y_mean_ - x_mean_ @ coef_for(n_components).T``.
        """
        return self.y_mean_ - self.x_mean_ @ self.coef_for(n_components).T

    @property
    def raw_intercept_path_(self):
        """Raw intercepts for every k, shape (n_components, n_targets)."""
        check_is_fitted(self)
        return self.y_mean_[None, :] - np.einsum("aqp,p->aq", self.coef_path_, self.x_mean_)

    # ------------------------------------------------------------- predict
    def predict(self, X, n_components=None):
        """Predict targets.

        Parameters
        ----------
        X : array-like of shape (n_samples, n_features)
        n_components : int, default=None
            Use the first ``n_components`` components (``None``: all).

        Returns
        -------
        Y_pred : ndarray of shape (n_samples, n_targets), or (n_samples,) if
            fitted on 1-D Y.
        """
        check_is_fitted(self)
        coef = self.coef_ if n_components is None else self.coef_for(n_components)
        X = validate_data(self, X, dtype=[np.float64, np.float32], reset=False)
        # As sklearn: centre X (not scaled: coef_ is in raw units), then add the Y mean.
        Y_pred = (np.asarray(X, dtype=np.float64) - self._x_mean) @ coef.T + self.intercept_
        return Y_pred.ravel() if self._predict_1d else Y_pred

    def transform(self, X, y=None):
        """Scores: ``((X - x_mean_) / x_std_) @ x_rotations_`` (and the same for ``y``).

        Parameters
        ----------
        X : array-like of shape (n_samples, n_features)
        y : array-like of shape (n_samples,) or (n_samples, n_targets), default=None

        Returns
        -------
        x_scores : ndarray of shape (n_samples, n_components)
            Or ``(x_scores, y_scores)`` if ``y`` is given, as sklearn.
        """
        check_is_fitted(self)
        X = validate_data(self, X, dtype=[np.float64, np.float32], reset=False)
        x_scores = ((np.asarray(X, dtype=np.float64) - self._x_mean) / self._x_std) @ self.x_rotations_
        if y is None:
            return x_scores
        Y = check_array(y, input_name="y", dtype=[np.float64, np.float32], ensure_2d=False)
        Y = np.asarray(Y, dtype=np.float64).reshape(Y.shape[0], -1)
        y_scores = ((Y - self._y_mean) / self._y_std) @ self.y_rotations_
        return x_scores, y_scores

    def fit_transform(self, X, y=None):
        """Fit, then :meth:`transform` the training data (as sklearn: a tuple when ``y`` is given).

        Returns
        -------
        x_scores : ndarray of shape (n_samples, n_components), or ``(x_scores, y_scores)``
        """
        return self.fit(X, y).transform(X, y)

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.regressor_tags.poor_score = True
        return tags


def _kernel_pls(C, S, A, zero_var_x):
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
                stacklevel=4,
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
                stacklevel=4,
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


def _check_n_components(n_components, n_samples, n_features):
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
