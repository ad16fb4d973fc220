"""AU-field reliability: how consistently independent subsets of the videos give each AU's displacement field.

An AU's field is its coefficient column (1434 values, axis-major; at pose 0 with pose x AU
interactions). Fitting the same configuration on each cross-validation fold alone (disjoint sets
of videos) gives one field per fold; the AU's reliability is the mean cosine between the fields of
every pair of folds. 1 means every subset of videos says the same thing about the AU; values near 0
mean its field is noise. No ground truth is needed, and the cosine does not depend on the
coordinate frame (a rotation or scale of the mesh leaves it unchanged). Each field comes from a
fraction of the data, so the full-data field is at least as stable as this says.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np

__all__ = ["field_cosines", "summarize"]


def field_cosines(coefs: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Mean pairwise cosine between the folds' fields of each selected input.

    Parameters
    ----------
    coefs : ndarray of shape (n_folds, n_targets, n_features)
        One model per fold, scikit-learn's ``coef_`` layout.
    rows : ndarray of shape (n_selected,) int
        Feature indices whose fields are compared (the 20 AUs).

    Returns
    -------
    ndarray of shape (n_selected,)
        Mean over fold pairs of ``cos(coef_f[:, j], coef_g[:, j])``; 0 where a field is zero.
    """
    coefs = np.asarray(coefs, dtype=np.float64)
    if coefs.ndim != 3 or len(coefs) < 2:
        raise ValueError(f"field_cosines: need (n_folds >= 2, n_targets, n_features) coefficients, got {coefs.shape}")
    fields = coefs[:, :, rows]  # (K, q, k)
    norms = np.linalg.norm(fields, axis=1)  # (K, k)
    cosines = []
    for f, g in combinations(range(len(coefs)), 2):
        dot = np.einsum("qk,qk->k", fields[f], fields[g])
        denom = norms[f] * norms[g]
        cosines.append(np.divide(dot, denom, out=np.zeros_like(dot), where=denom > 0))
    return np.mean(cosines, axis=0)


def summarize(cosines: np.ndarray, names: list[str]) -> dict:
    """``au_reliability_min``, ``au_reliability_median`` and the per-AU table ``au_reliability`` {name: cosine}."""
    cosines = np.asarray(cosines, dtype=np.float64)
    return {
        "au_reliability_min": float(cosines.min()),
        "au_reliability_median": float(np.median(cosines)),
        "au_reliability": {n: float(c) for n, c in zip(names, cosines, strict=True)},
    }
