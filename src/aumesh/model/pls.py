"""Exact PLS regression from sufficient statistics, as a scikit-learn estimator.

:class:`PLSRegression` is a drop-in for :class:`sklearn.cross_decomposition.PLSRegression` that fits
from :class:`aumesh.model.cross_products.CrossProducts` (or arrays, through them) with the kernel
algorithm of :mod:`aumesh.model.kernel_pls` (D&M Algorithm 1; the steps are numbered there), and
yields the coefficients of every smaller number of components from the same fit.
"""

from __future__ import annotations

import numbers
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

from aumesh.model.cross_products import CrossProducts
from aumesh.model.kernel_pls import check_n_components, coefficient_path, fit_statistics, intercept_path

__all__ = ["PLSRegression"]


# --------------------------------------------------------------------------- #
# PLS estimator
# --------------------------------------------------------------------------- #
class PLSRegression(ClassNamePrefixFeaturesOutMixin, TransformerMixin, RegressorMixin, MultiOutputMixin, BaseEstimator):
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
        check_n_components(self.n_components, X.shape[0], X.shape[1])
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
        fit = fit_statistics(stats, self.n_components, self.scale)
        self.__dict__.pop("coef_path_", None)  # a refit's path is its own
        vars(self).update(vars(fit))  # the fitted attributes, under their scikit-learn names
        self.y_weights_ = fit.y_loadings_.copy()
        self.y_rotations_ = self.y_weights_ @ pinv(self.y_loadings_.T @ self.y_weights_, check_finite=False)
        self._x_mean, self._y_mean, self._x_std, self._y_std = self.x_mean_, self.y_mean_, self.x_std_, self.y_std_
        self.intercept_ = self.y_mean_.copy()
        self._n_features_out = self.x_rotations_.shape[1]
        return self

    # --------------------------------------------------------- path access
    @cached_property
    def coef_path_(self):
        """Coefficients of every ``k <= n_components``, shape (n_components, n_targets, n_features).

        ``coef_path_[k - 1]`` is ``coef_`` of a fit with ``k`` components (:func:`aumesh.model.kernel_pls.coefficient_path`),
        built on first use and kept.
        """
        check_is_fitted(self, "x_rotations_")
        return coefficient_path(self)

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
        return intercept_path(self)

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
