"""Exact scores of a linear model on held-out sufficient statistics (no pass over rows).

:func:`residual_sums` gives the residual and total sums of squares of ``Y ~ X @ coef.T + a`` on
the rows a :class:`~aumesh.model.cross_products.CrossProducts` summarizes; :func:`r2_per_target`
and :func:`r2_variance_weighted` follow scikit-learn's ``r2_score`` conventions exactly;
:func:`r2_path` scores every number of components of a PLS fit (:mod:`aumesh.model.kernel_pls`).
"""

from __future__ import annotations

import numpy as np

from aumesh.model.cross_products import CrossProducts

__all__ = ["r2_path", "r2_per_target", "r2_variance_weighted", "residual_sums"]


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

    The model with ``k`` components has ``coef = sum_{a<=k} qr_a rr_a^T`` (``rr = x_rotations_ / x_std_``,
    ``qr = y_loadings_ * y_std_``; ``coef_path_[k - 1]``), so each term of :func:`residual_sums`, summed over the
    targets, is a sum over pairs of components ``a, c <= k``:

        sum_j sse_j(k) = sum_j cyy_j + n |dy|^2 - 2 sum_{a<=k} (u_a + n e_a r_a)
                         + sum_{a,c<=k} G_ac (T_ac + n r_a r_c)

    with ``G = qr^T qr``, ``T = rr^T cxx rr``, ``u_a = qr_a^T (cxy^T rr_a)``, ``r = rr^T dx``, ``e = qr^T dy``
    (sums over the targets of nonzero variance; ``dx, dy``: test means minus training means). Every ``k`` costs
    ``O(A^2)`` once the ``(A, A)`` products are formed, instead of scoring the ``(A, q, p)`` coefficient path
    (0.25 s a fold at 83 features and 1434 targets). As :func:`residual_sums`, up to rounding; the sum of squares
    is clipped at 0 as a whole, not per target.

    Parameters
    ----------
    model : PLSRegression or PLSFit
        Fitted engine model (:mod:`aumesh.model.pls`, :mod:`aumesh.model.kernel_pls`); uses ``x_rotations_``,
        ``y_loadings_``, ``x_std_``, ``y_std_``, ``x_mean_``, ``y_mean_``.
    test_stats : CrossProducts
        Statistics of the evaluation rows.

    Returns
    -------
    r2 : ndarray of shape (model.n_components,)
        ``r2[k - 1]`` is the score of the model with ``k`` components.
    """
    if not hasattr(model, "x_rotations_"):  # scikit-learn's check, without importing it for every fitted model
        from sklearn.exceptions import NotFittedError

        raise NotFittedError(f"This {type(model).__name__} instance is not fitted yet. Call 'fit' first.")
    if not isinstance(test_stats, CrossProducts):
        raise TypeError(f"test_stats must be a CrossProducts, got {type(test_stats).__name__}.")
    sst = test_stats.cyy_diag
    varying = sst != 0  # sklearn's variance weighting: constant targets get zero weight
    if not varying.any():  # every target constant: the uniform mean of per-target scores (sklearn), per k
        sse, sst = residual_sums(model.coef_path_, model.raw_intercept_path_, test_stats)
        return r2_variance_weighted(sse, sst)
    n = test_stats.n
    rr = model.x_rotations_ / model.x_std_[:, None]  # (p, A)
    qr = (model.y_loadings_ * model.y_std_[:, None])[varying]  # (q', A)
    dx = test_stats.x_mean - model.x_mean_
    dy = (test_stats.y_mean - model.y_mean_)[varying]
    gram = qr.T @ qr  # G
    r = rr.T @ dx
    u = np.einsum("aj,ja->a", (rr.T @ test_stats.cxy)[:, varying], qr)
    pairs = gram * (rr.T @ test_stats.cxx @ rr + n * np.outer(r, r))
    quad = np.cumsum(np.cumsum(pairs, axis=0), axis=1).diagonal()  # sum over the leading k x k block
    linear = np.cumsum(2.0 * (u + n * (qr.T @ dy) * r))
    sse = np.maximum(sst[varying].sum() + n * (dy @ dy) - linear + quad, 0.0)
    return 1.0 - sse / sst.sum()
