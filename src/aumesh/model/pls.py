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

:func:`residual_sums`, :func:`r2_variance_weighted`, :func:`r2_per_target`
and :func:`r2_path` score a model on held-out *statistics*, exactly and
without a pass over rows.

Notation: ``n`` rows, ``p`` features, ``q`` targets, ``A`` components.
"""

from __future__ import annotations

import numbers
import warnings

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

__all__ = [
    "CrossProducts",
    "PLSRegression",
    "r2_path",
    "r2_per_target",
    "r2_variance_weighted",
    "residual_sums",
]

#: Rows converted to float64 at a time inside :meth:`CrossProducts.update`
#: (bounds the temporary shifted copy of a Y block to 8192 * q * 8 bytes, ~94 MB for q=1434).
DEFAULT_BLOCK_ROWS = 8192


# --------------------------------------------------------------------------- #
# Sufficient statistics
# --------------------------------------------------------------------------- #
class CrossProducts:
    """Shifted sufficient statistics of ``(X, Y)`` for linear least squares / PLS.

    All sums are of the *shifted* data ``Xs = X - x_shift`` and
    ``Ys = Y - y_shift`` and are accumulated in float64. Shifting by a
    provisional mean (by default the mean of the first ``block_rows`` rows of
    the first non-empty chunk; a column constant there is shifted by its value) keeps
    the centered sums precise when the data sit far from zero (mesh
    coordinates of 100-1000 px with a spread of ~1 px): the centered sums are
    recovered as ``Xs^T Xs - sum(Xs) sum(Xs)^T / n`` with little cancellation.

    Parameters
    ----------
    n_features : int
        Number of columns ``p`` of ``X``.
    n_targets : int
        Number of columns ``q`` of ``Y``.
    x_shift : array-like of shape (n_features,), default=None
        Value subtracted from every row of ``X`` before accumulation. ``None``:
        taken from the first non-empty chunk passed to :meth:`update` (the
        mean of its first ``block_rows`` rows).
    y_shift : array-like of shape (n_targets,), default=None
        Same for ``Y``.

    Attributes
    ----------
    n : int
        Number of rows accumulated.
    sum_x : ndarray of shape (n_features,)
        ``sum_i (x_i - x_shift)``.
    sum_y : ndarray of shape (n_targets,)
        ``sum_i (y_i - y_shift)``.
    xtx : ndarray of shape (n_features, n_features)
        ``Xs^T Xs``.
    xty : ndarray of shape (n_features, n_targets)
        ``Xs^T Ys``.
    yty_diag : ndarray of shape (n_targets,)
        ``diag(Ys^T Ys)``, i.e. ``sum_i (y_ij - y_shift_j)^2``.
    x_shift : ndarray of shape (n_features,) or None
    y_shift : ndarray of shape (n_targets,) or None

    Notes
    -----
    Statistics with identical shifts can be added and subtracted, e.g. the
    training statistics of a cross-validation fold are ``total - held_out``.
    Build the per-fold statistics with :meth:`empty_like` (or pass
    ``x_shift=total.x_shift, y_shift=total.y_shift``) so the shifts match;
    :meth:`reshifted` re-expresses statistics at another shift exactly (in
    exact arithmetic) when they do not.
    """

    def __init__(self, n_features, n_targets, x_shift=None, y_shift=None):
        self.n_features = _check_positive_int(n_features, "n_features")
        self.n_targets = _check_positive_int(n_targets, "n_targets")
        self.x_shift = _check_shift(x_shift, self.n_features, "x_shift")
        self.y_shift = _check_shift(y_shift, self.n_targets, "y_shift")
        self.n = 0
        self.sum_x = np.zeros(self.n_features)
        self.sum_y = np.zeros(self.n_targets)
        self.xtx = np.zeros((self.n_features, self.n_features))
        self.xty = np.zeros((self.n_features, self.n_targets))
        self.yty_diag = np.zeros(self.n_targets)

    # ----------------------------------------------------------------- build
    @classmethod
    def from_arrays(cls, X, Y, x_shift=None, y_shift=None, block_rows=DEFAULT_BLOCK_ROWS):
        """Statistics of whole arrays (processed in blocks of ``block_rows`` rows).

        Parameters
        ----------
        X : array-like of shape (n_samples, n_features)
        Y : array-like of shape (n_samples, n_targets) or (n_samples,)
        x_shift, y_shift : see :class:`CrossProducts`.
        block_rows : int
            Rows converted to float64 at a time.

        Returns
        -------
        CrossProducts
        """
        X, Y = _as_2d_pair(X, Y)
        return cls(X.shape[1], Y.shape[1], x_shift, y_shift).update(X, Y, block_rows=block_rows)

    def empty_like(self):
        """Empty statistics with the same shape and shifts (for ``total - part``).

        Returns
        -------
        CrossProducts
        """
        return CrossProducts(self.n_features, self.n_targets, self.x_shift, self.y_shift)

    def copy(self):
        """Deep copy.

        Returns
        -------
        CrossProducts
        """
        out = self.empty_like()
        out.n = self.n
        out.sum_x = self.sum_x.copy()
        out.sum_y = self.sum_y.copy()
        out.xtx = self.xtx.copy()
        out.xty = self.xty.copy()
        out.yty_diag = self.yty_diag.copy()
        return out

    __copy__ = copy

    def __deepcopy__(self, memo):
        return self.copy()

    def update(self, X, Y, block_rows=DEFAULT_BLOCK_ROWS):
        """Accumulate a chunk of rows.

        Parameters
        ----------
        X : array-like of shape (n_chunk, n_features)
            Any float (or integer) dtype; converted block-wise to float64.
        Y : array-like of shape (n_chunk, n_targets) or (n_chunk,)
        block_rows : int
            Rows converted to float64 at a time.

        Returns
        -------
        self : CrossProducts

        Raises
        ------
        ValueError
            On shape mismatch or non-finite values. The statistics are left
            unchanged by a block that contains NaN or inf (earlier blocks of
            the same call stay accumulated: check inputs first if that
            matters).
        """
        X, Y = _as_2d_pair(X, Y)
        if X.shape[1] != self.n_features:
            raise ValueError(f"X has {X.shape[1]} columns, these statistics expect {self.n_features}.")
        if Y.shape[1] != self.n_targets:
            raise ValueError(f"Y has {Y.shape[1]} columns, these statistics expect {self.n_targets}.")
        n_rows = X.shape[0]
        if n_rows == 0:
            return self
        block_rows = _check_positive_int(block_rows, "block_rows")
        x_shift = _provisional_shift(X[:block_rows]) if self.x_shift is None else self.x_shift
        y_shift = _provisional_shift(Y[:block_rows]) if self.y_shift is None else self.y_shift
        self.x_shift, self.y_shift = x_shift, y_shift
        for start in range(0, n_rows, block_rows):
            stop = min(start + block_rows, n_rows)
            # one float64 temporary per block, whatever the input dtype
            xs = np.subtract(X[start:stop], x_shift, dtype=np.float64)
            ys = np.subtract(Y[start:stop], y_shift, dtype=np.float64)
            sum_x = xs.sum(axis=0)
            sum_y = ys.sum(axis=0)
            xtx = xs.T @ xs
            yty = np.einsum("ij,ij->j", ys, ys)
            # diag(Xs^T Xs) and diag(Ys^T Ys) are sums of squares: NaN/inf anywhere in
            # the block makes them non-finite, so this checks every entry for free.
            if not (np.isfinite(np.diagonal(xtx)).all() and np.isfinite(yty).all()):
                which = "X" if not np.isfinite(np.diagonal(xtx)).all() else "Y"
                raise ValueError(
                    f"Input {which} contains NaN or infinity (rows {start}..{stop - 1} of this chunk)."
                )
            self.xtx += xtx
            self.xty += xs.T @ ys
            self.sum_x += sum_x
            self.sum_y += sum_y
            self.yty_diag += yty
            self.n += stop - start
        return self

    def reshifted(self, x_shift, y_shift):
        """The same statistics expressed with other shifts.

        Uses ``sum(x - s') = sum(x - s) + n (s - s')`` and the matching
        identities for the cross products (exact in exact arithmetic; in
        floating point exact to rounding when the shifts are close).

        Parameters
        ----------
        x_shift : array-like of shape (n_features,)
        y_shift : array-like of shape (n_targets,)

        Returns
        -------
        CrossProducts
        """
        x_new = _check_shift(x_shift, self.n_features, "x_shift")
        y_new = _check_shift(y_shift, self.n_targets, "y_shift")
        out = CrossProducts(self.n_features, self.n_targets, x_new, y_new)
        if self.n == 0:
            return out
        dx = self.x_shift - x_new
        dy = self.y_shift - y_new
        n = self.n
        out.n = n
        out.sum_x = self.sum_x + n * dx
        out.sum_y = self.sum_y + n * dy
        out.xtx = self.xtx + np.outer(dx, self.sum_x) + np.outer(self.sum_x, dx) + n * np.outer(dx, dx)
        out.xty = self.xty + np.outer(dx, self.sum_y) + np.outer(self.sum_x, dy) + n * np.outer(dx, dy)
        out.yty_diag = self.yty_diag + 2.0 * dy * self.sum_y + n * dy * dy
        return out

    # ------------------------------------------------------------ arithmetic
    def _combine(self, other, sign):
        if not isinstance(other, CrossProducts):
            return NotImplemented
        if (other.n_features, other.n_targets) != (self.n_features, self.n_targets):
            raise ValueError(
                f"Cannot combine statistics of shape (p={self.n_features}, q={self.n_targets}) "
                f"with (p={other.n_features}, q={other.n_targets})."
            )
        # Empty statistics with no shift yet are neutral elements.
        if other.n == 0 and (other.x_shift is None or other.y_shift is None):
            return self.copy()
        if self.n == 0 and (self.x_shift is None or self.y_shift is None):
            if sign < 0:
                _raise_negative(-other.n)
            return other.copy()
        if not (np.array_equal(self.x_shift, other.x_shift) and np.array_equal(self.y_shift, other.y_shift)):
            raise ValueError(
                "Cannot combine CrossProducts with different shifts. Accumulate the parts with the "
                "same shift (CrossProducts(p, q, x_shift=total.x_shift, y_shift=total.y_shift) or "
                "total.empty_like()), or convert one of them with .reshifted(x_shift, y_shift)."
            )
        n = self.n + sign * other.n
        _raise_negative(n)
        out = self.empty_like()
        out.n = n
        out.sum_x = self.sum_x + sign * other.sum_x
        out.sum_y = self.sum_y + sign * other.sum_y
        out.xtx = self.xtx + sign * other.xtx
        out.xty = self.xty + sign * other.xty
        out.yty_diag = self.yty_diag + sign * other.yty_diag
        return out

    def __add__(self, other):
        return self._combine(other, +1)

    def __sub__(self, other):
        return self._combine(other, -1)

    def __repr__(self):
        return f"CrossProducts(n={self.n}, n_features={self.n_features}, n_targets={self.n_targets})"

    # ----------------------------------------------------- centered quantities
    def _require_rows(self):
        if self.n <= 0:
            raise ValueError("CrossProducts holds no rows.")

    @property
    def x_mean(self):
        """Column means of X, shape (n_features,)."""
        self._require_rows()
        return self.x_shift + self.sum_x / self.n

    @property
    def y_mean(self):
        """Column means of Y, shape (n_targets,)."""
        self._require_rows()
        return self.y_shift + self.sum_y / self.n

    # A centered sum of squares below this fraction of the shifted one is rounding noise
    # (the column is constant, but was shifted by something other than its value).
    _CONSTANT_RTOL = 1e-12

    def _constant_x(self):
        css = np.diagonal(self.xtx) - self.sum_x * self.sum_x / self.n
        return css <= self._CONSTANT_RTOL * np.diagonal(self.xtx)

    def _constant_y(self):
        css = self.yty_diag - self.sum_y * self.sum_y / self.n
        return css <= self._CONSTANT_RTOL * self.yty_diag

    @property
    def cxx(self):
        """Centered sums ``(X - x̄)^T (X - x̄)``, shape (n_features, n_features).

        Rows/columns of numerically constant X columns are exactly zero.
        """
        self._require_rows()
        c = self.xtx - np.outer(self.sum_x, self.sum_x) / self.n
        c = 0.5 * (c + c.T)
        const = self._constant_x()
        c[const, :] = 0.0
        c[:, const] = 0.0
        return c

    @property
    def cxy(self):
        """Centered sums ``(X - x̄)^T (Y - ȳ)``, shape (n_features, n_targets).

        Rows of constant X columns and columns of constant Y columns are exactly zero.
        """
        self._require_rows()
        c = self.xty - np.outer(self.sum_x, self.sum_y) / self.n
        c[self._constant_x(), :] = 0.0
        c[:, self._constant_y()] = 0.0
        return c

    @property
    def cyy_diag(self):
        """Centered sums of squares ``sum_i (y_ij - ȳ_j)^2``, shape (n_targets,).

        Exactly zero for numerically constant Y columns.
        """
        self._require_rows()
        c = self.yty_diag - self.sum_y * self.sum_y / self.n
        c[self._constant_y()] = 0.0
        return c


def _raise_negative(n):
    if n < 0:
        raise ValueError(f"Subtraction gives a negative row count ({n}): subtract a subset of the rows only.")


def _check_positive_int(value, name):
    if not isinstance(value, numbers.Integral) or isinstance(value, bool) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}.")
    return int(value)


def _check_shift(shift, size, name):
    if shift is None:
        return None
    arr = np.array(shift, dtype=np.float64).reshape(-1)
    if arr.shape != (size,):
        raise ValueError(f"{name} must have shape ({size},), got {np.shape(shift)}.")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or infinity.")
    return arr


def _provisional_shift(block):
    """Mean of a block as a shift; a column constant in the block is shifted by its value.

    Using the value itself (not its floating-point mean) makes the shifted
    column exactly zero, so a constant column gets exactly zero variance, as in
    sklearn's ``_center_scale_xy``.
    """
    block = np.asarray(block, dtype=np.float64)
    shift = block.mean(axis=0)
    first = block[0]
    constant = (block == first).all(axis=0)
    shift[constant] = first[constant]
    if not np.isfinite(shift).all():
        raise ValueError("Input contains NaN or infinity (first chunk).")
    return shift


def _as_2d_pair(X, Y):
    X = np.asarray(X)
    Y = np.asarray(Y)
    if Y.ndim == 1:
        Y = Y.reshape(-1, 1)
    if X.ndim != 2 or Y.ndim != 2:
        raise ValueError(f"X and Y must be 2-D (Y may be 1-D); got X.ndim={X.ndim}, Y.ndim={Y.ndim}.")
    if X.shape[0] != Y.shape[0]:
        raise ValueError(f"X and Y have different numbers of rows: {X.shape[0]} != {Y.shape[0]}.")
    return X, Y


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
        # coef_ = (B * y_std).T / x_std, shape (q, p). Cumulative sums over components give
        # the coefficient of every k <= A (B_k = R_{:, :k} Q_{:, :k}^T).
        Rr = R / x_std[:, None]  # (p, A)
        Qr = Q * y_std[:, None]  # (q, A)
        path = np.einsum("qa,pa->aqp", Qr, Rr)
        np.cumsum(path, axis=0, out=path)

        self.x_weights_ = W
        self.x_loadings_ = P
        self.y_loadings_ = Q
        self.y_weights_ = Q.copy()
        self.x_rotations_ = R
        self.y_rotations_ = self.y_weights_ @ pinv(self.y_loadings_.T @ self.y_weights_, check_finite=False)
        self.coef_path_ = path
        self.coef_ = path[-1].copy()
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
    def _check_k(self, n_components):
        check_is_fitted(self)
        A = self.coef_path_.shape[0]
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


# --------------------------------------------------------------------------- #
# Scoring from statistics
# --------------------------------------------------------------------------- #
def residual_sums(coef, raw_intercept, stats):
    """Residual and total sums of squares of a linear model on held-out statistics.

    For ``Ŷ = X @ coef.T + raw_intercept`` and the rows summarized by ``stats``,
    with centered sums ``cxx, cxy, cyy`` and means ``x̄, ȳ`` of those rows::

        sse_j = cyy_j - 2 b_j^T cxy[:, j] + b_j^T cxx b_j + n (ȳ_j - a_j - b_j^T x̄)^2
        sst_j = cyy_j

    (``b_j = coef[j]``, ``a_j = raw_intercept[j]``): exact, no pass over rows.

    Parameters
    ----------
    coef : ndarray of shape (n_targets, n_features) or (n_models, n_targets, n_features)
    raw_intercept : ndarray of shape (n_targets,) or (n_models, n_targets)
    stats : CrossProducts
        Statistics of the evaluation rows.

    Returns
    -------
    sse : ndarray of shape (n_targets,) or (n_models, n_targets)
        ``sum_i (y_ij - ŷ_ij)^2`` (clipped at 0 against rounding).
    sst : ndarray of shape (n_targets,)
        ``sum_i (y_ij - ȳ_j)^2``.
    """
    if not isinstance(stats, CrossProducts):
        raise TypeError(f"stats must be a CrossProducts, got {type(stats).__name__}.")
    coef = np.asarray(coef, dtype=np.float64)
    raw_intercept = np.asarray(raw_intercept, dtype=np.float64)
    p, q = stats.n_features, stats.n_targets
    if coef.ndim not in (2, 3) or coef.shape[-2:] != (q, p):
        raise ValueError(f"coef must have shape (n_targets={q}, n_features={p}) or (k, {q}, {p}); got {coef.shape}.")
    if raw_intercept.shape != coef.shape[:-1]:
        raise ValueError(f"raw_intercept must have shape {coef.shape[:-1]}, got {raw_intercept.shape}.")
    cxx, cxy, cyy = stats.cxx, stats.cxy, stats.cyy_diag
    x_mean, y_mean = stats.x_mean, stats.y_mean
    cross = np.einsum("...qp,pq->...q", coef, cxy)  # b_j^T cxy[:, j]
    quad = np.einsum("...qp,...qp->...q", coef @ cxx, coef)  # b_j^T cxx b_j
    bias = y_mean - raw_intercept - coef @ x_mean  # ȳ_j - a_j - b_j^T x̄
    sse = cyy - 2.0 * cross + quad + stats.n * bias * bias
    return np.maximum(sse, 0.0), cyy.copy()


def r2_per_target(sse, sst):
    """Per-target R², as ``sklearn.metrics.r2_score(..., multioutput="raw_values")``.

    ``1 - sse/sst``; where ``sst == 0``: 1.0 if ``sse == 0`` else 0.0 (sklearn's
    ``force_finite=True``).

    Parameters
    ----------
    sse : ndarray of shape (..., n_targets)
    sst : ndarray of shape (n_targets,) or broadcastable to ``sse``

    Returns
    -------
    r2 : ndarray of shape (..., n_targets)
    """
    sse = np.asarray(sse, dtype=np.float64)
    sst = np.broadcast_to(np.asarray(sst, dtype=np.float64), sse.shape)
    out = np.ones(sse.shape)
    valid = (sst != 0) & (sse != 0)
    out[valid] = 1.0 - sse[valid] / sst[valid]
    out[(sse != 0) & (sst == 0)] = 0.0
    return out


def r2_variance_weighted(sse, sst):
    """Variance-weighted R², as ``r2_score(..., multioutput="variance_weighted")``.

    ``1 - sum_j sse_j / sum_j sst_j`` over targets with ``sst_j != 0`` (sklearn
    gives constant targets zero weight); if every target is constant, the
    uniform mean of :func:`r2_per_target`.

    Parameters
    ----------
    sse : ndarray of shape (..., n_targets)
    sst : ndarray of shape (n_targets,) or broadcastable to ``sse``

    Returns
    -------
    r2 : float or ndarray of shape (...)
    """
    sse = np.asarray(sse, dtype=np.float64)
    sst = np.broadcast_to(np.asarray(sst, dtype=np.float64), sse.shape)
    nonzero = sst != 0
    total = sst.sum(axis=-1)
    if not nonzero.any():
        out = r2_per_target(sse, sst).mean(axis=-1)
    else:
        out = 1.0 - np.where(nonzero, sse, 0.0).sum(axis=-1) / np.where(total == 0, 1.0, total)
        if np.ndim(out) and (total == 0).any():  # a row of models with all-constant targets
            out = np.where(total == 0, r2_per_target(sse, sst).mean(axis=-1), out)
    return float(out) if np.ndim(out) == 0 else out


def r2_path(model, test_stats):
    """Variance-weighted R² on held-out statistics for every number of components.

    Parameters
    ----------
    model : PLSRegression
        Fitted engine model (uses ``coef_path_``).
    test_stats : CrossProducts
        Statistics of the evaluation rows.

    Returns
    -------
    r2 : ndarray of shape (model.n_components,)
        ``r2[k - 1]`` is the score of the model with ``k`` components.
    """
    check_is_fitted(model, "coef_path_")
    sse, sst = residual_sums(model.coef_path_, model.raw_intercept_path_, test_stats)
    return r2_variance_weighted(sse, sst)
