"""Sufficient statistics of a linear least-squares / PLS problem, accumulated without storing rows.

A PLS2 fit (and every score of a linear model) depends on the data only through the number of
rows ``n``, the column sums of ``X`` (n, p) and ``Y`` (n, q), ``X^T X`` (p, p), ``X^T Y`` (p, q) and
the diagonal of ``Y^T Y`` (q,). :class:`CrossProducts` accumulates them in float64 around a
provisional shift (numerically stable), chunk by chunk; statistics of disjoint row sets add and
subtract exactly (a fold's training statistics are the total minus the fold's).
"""

from __future__ import annotations

import numbers

import numpy as np

__all__ = ["CrossProducts"]

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
                raise ValueError(f"Input {which} contains NaN or infinity (rows {start}..{stop - 1} of this chunk).")
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
