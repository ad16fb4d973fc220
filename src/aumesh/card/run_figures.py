"""Figures an MLflow run carries (not the release's card): the R²-vs-n_components curve of one evaluation.

Logged as ``plots/r2_vs_n_components.png`` by every evaluation run (the ``evaluate`` stage's and each sweep child's,
:mod:`aumesh.pipeline.run_record`). Matplotlib through ``matplotlib.figure.Figure`` and its Agg canvas only (no
pyplot state), imported when a figure is made: this package is matplotlib's only home.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np
    from matplotlib.figure import Figure


def r2_curve_figure(r2_path_folds: np.ndarray, title: str) -> Figure:
    """The R²-vs-n_components curve of one configuration: each fold and the mean.

    Parameters
    ----------
    r2_path_folds : ndarray, shape (n_splits, A)
        Held-out R² of the fold's model truncated to k = 1..A components.
    title : str

    Returns
    -------
    matplotlib.figure.Figure
        Agg-backed figure (no pyplot state).
    """
    import numpy as np
    from matplotlib.figure import Figure

    paths = np.atleast_2d(np.asarray(r2_path_folds, dtype=float))
    k = np.arange(1, paths.shape[1] + 1)
    fig = Figure(figsize=(6.0, 3.8), dpi=90)
    ax = fig.add_subplot()
    for f, path in enumerate(paths):
        ax.plot(k, path, lw=0.9, alpha=0.55, label=f"fold {f}")
    mean = paths.mean(axis=0)
    ax.plot(k, mean, color="black", lw=2.0, label="mean")
    best = int(np.argmax(mean))
    ax.scatter([k[best]], [mean[best]], color="crimson", zorder=3, label=f"max mean R² at k={k[best]}")
    ax.set_xlabel("n_components (k)")
    ax.set_ylabel("held-out R² (variance-weighted)")
    ax.set_title(title, fontsize=8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    fig.subplots_adjust(left=0.12, right=0.97, bottom=0.14, top=0.9)
    return fig
