"""The metrics and plot data DVC compares across commits and experiments.

``dvc exp show``, ``dvc metrics diff`` and ``dvc plots diff`` read these small files from every
revision, so they are committed with git (``cache: false`` in ``dvc.yaml``, outside git-ignored
folders; ``conf/paths`` names them): the evaluate stage's ``metrics.json``, the cumulative
per-frame vertex error curve and the R²-vs-n_components curve (CSV with a header row, one x and
one y column each, drawn by DVC's ``linear`` template).

Floats are rounded to :data:`SIGNIFICANT_DIGITS` significant digits, far below any difference
worth reading and far above last-bit floating-point differences between machines, so a rerun
elsewhere does not show as a changed metric. MLflow and ``build/model/`` keep full precision.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial
from typing import Any

import numpy as np

from aumesh.core.io import NpyRows, atomic_write_json, atomic_write_text, read_rows
from aumesh.pipeline import compute
from aumesh.pipeline.quantiles import NoValuesError, exact_quantiles

#: Significant digits of every float in the committed metrics and plot files.
SIGNIFICANT_DIGITS = 6
#: Points of the cumulative error curve (the empirical CDF at the 0, 1, ..., 100 % quantiles).
ERROR_CURVE_POINTS = 101

#: Values of a per-frame error file one task reads at a time (256 KiB of float32; larger blocks cost the stage
#: ~40 MiB of transients at 1M frames).
BLOCK_ROWS = 1 << 16

ERROR_CURVE_COLUMNS = ("vertex_error", "fraction_of_frames")
R2_CURVE_COLUMNS = ("n_components", "r2")


def rounded(value: Any, digits: int = SIGNIFICANT_DIGITS) -> Any:
    """``value`` with every float (also inside dicts and lists) rounded to ``digits`` significant digits."""
    if isinstance(value, Mapping):
        return {k: rounded(v, digits) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [rounded(v, digits) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(f"{float(value):.{digits}g}")
    return value


def _finite(block) -> np.ndarray:
    """The finite values of one block, float64: an array, or ``(path, start, stop)`` rows of a 1-D ``.npy``."""
    e = np.asarray(block if isinstance(block, np.ndarray) else read_rows(*block), dtype=np.float64).ravel()
    return e[np.isfinite(e)]


def _count_at_most(thresholds: np.ndarray, block) -> np.ndarray:
    """(len(thresholds) + 1,) values of the block ``<=`` each threshold, then the block's finite values."""
    e = np.sort(_finite(block))
    return np.r_[np.searchsorted(e, thresholds, side="right"), e.size]


def _blocks(frame_vertex_error) -> list:
    """Partitions of a per-frame error vector: row ranges of its ``.npy`` on disk, or slices of an array."""
    if isinstance(frame_vertex_error, NpyRows):
        n = len(frame_vertex_error)
        return [(frame_vertex_error.path, lo, min(lo + BLOCK_ROWS, n)) for lo in range(0, n, BLOCK_ROWS)]
    e = np.asarray(frame_vertex_error).ravel()
    return [e[lo : lo + BLOCK_ROWS] for lo in range(0, len(e), BLOCK_ROWS)]


def error_curve(frame_vertex_error, n_points: int = ERROR_CURVE_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """The empirical CDF of the held-out per-frame mean vertex error, at ``n_points`` quantiles.

    The vector is read block by block, never whole: the quantiles are
    :func:`aumesh.pipeline.quantiles.exact_quantiles` (bit-equal to ``np.quantile`` of the whole), the
    fractions a counting pass, on the current Dask scheduler.

    Parameters
    ----------
    frame_vertex_error : ndarray of shape (n_frames,), or :class:`aumesh.core.io.NpyRows` of one on disk
        Mean per-vertex Euclidean error of each held-out frame (``CVResult.frame_vertex_error``); frames
        whose error is not finite are left out.
    n_points : int, default 101
        Quantiles 0, 1/(n_points-1), ..., 1 of the errors (a curve of fixed size, whatever ``n_frames``).

    Returns
    -------
    errors : ndarray of shape (n_points,)
        Error values (frames' own values: the ``inverted_cdf`` quantiles), non-decreasing.
    fraction : ndarray of shape (n_points,)
        Fraction of frames whose error is <= ``errors[i]`` (the exact empirical CDF there).
    """
    blocks = _blocks(frame_vertex_error)
    try:  # its first pass counts the finite values: no pass of our own for that
        if not blocks:
            raise NoValuesError("no frames")
        errors = exact_quantiles(_finite, blocks, np.linspace(0.0, 1.0, n_points), method="inverted_cdf")
    except NoValuesError:
        raise ValueError("frame_vertex_error has no finite value: no held-out frame was scored") from None
    counts = compute.map_reduce(partial(_count_at_most, errors), np.add, blocks)
    return errors, counts[:-1] / counts[-1]


def r2_curve(r2_path_folds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean over folds of the held-out R² for k = 1..n_components.

    Parameters
    ----------
    r2_path_folds : ndarray of shape (n_splits, n_components)
        ``CVResult.r2_path_folds``: row f is fold f's R² of the models with 1..n_components components.

    Returns
    -------
    k : ndarray of shape (n_components,), int
    r2 : ndarray of shape (n_components,)
    """
    path = np.atleast_2d(np.asarray(r2_path_folds, dtype=np.float64))
    return np.arange(1, path.shape[1] + 1), path.mean(axis=0)


def _csv(columns: tuple[str, str], x: np.ndarray, y: np.ndarray) -> str:
    rows = [",".join(columns)]
    rows += [
        f"{rounded(a) if isinstance(a, float) else a},{rounded(b)}" for a, b in zip(x.tolist(), y.tolist(), strict=True)
    ]
    return "\n".join(rows) + "\n"


def write(
    paths, metrics: Mapping[str, Any], frame_vertex_error: NpyRows | np.ndarray, r2_path_folds: np.ndarray
) -> None:
    """Write the metrics JSON and the two plot CSVs where ``paths`` (the ``paths`` config group) says, atomically."""
    atomic_write_json(paths.metrics_file, rounded(dict(metrics)))
    atomic_write_text(paths.error_curve_file, _csv(ERROR_CURVE_COLUMNS, *error_curve(frame_vertex_error)))
    atomic_write_text(paths.r2_curve_file, _csv(R2_CURVE_COLUMNS, *r2_curve(r2_path_folds)))
