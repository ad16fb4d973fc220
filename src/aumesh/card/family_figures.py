"""A family release's figures (issue 46): each input's face at its training p99, and the CV figures of the AU card.

Drawn from the family NPZ alone (:mod:`aumesh.model.family_release`'s keys) with the AU card's primitives
(:mod:`aumesh.card.drawing`) in its face frame (:func:`aumesh.card.family_directions.family_displacements`: x the
subject's left, y down, inter-ocular units; the panels put up at the top and the subject's left on the image right,
as a photograph). Each input is drawn at its training p99 (``feature_p99``), the largest value py-feat gives it
(``predict_face_mesh_from_features`` clips to ``[0, feature_p99]``), so a panel shows the motion the model is used
for; an input the data never expressed (``unsupported_features``) is drawn greyed, labelled, as the AU card draws an
unsupported AU. The R² per vertex and the cumulative error figures are the AU card's
(:func:`aumesh.card.release_figures.fig_r2_per_vertex`, :func:`~aumesh.card.release_figures.fig_cumulative_error`)
on the family fit's ``cv.npz``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.card.drawing import (
    display_limits,
    draw_solid,
    mark_unsupported,
    new_figure,
    normal_signs,
    prep_ax,
)

#: the family figure's file name: ``<family>_panels.png``
PANELS = "{family}_panels.png"


def family_faces(arrays: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray, list[str], np.ndarray]:
    """The family NPZ's zero-input face and each input's displacement at its p99, in the face frame.

    Returns
    -------
    neutral : ndarray, shape (478, 3)
        The mesh at every input 0, pose 0 (``intercept``), face frame, inter-ocular units.
    disp : ndarray, shape (k, 478, 3)
        Each input's displacement at its training p99 (1 where the p99 is not recorded), same frame.
    names : list of str
        ``feature_columns``.
    values : ndarray, shape (k,)
        The value each input is drawn at.
    """
    from aumesh.card.family_directions import family_displacements
    from aumesh.core.schema import unflatten_axis_major
    from aumesh.geometry import face

    names = [str(s) for s in np.asarray(arrays["feature_columns"]).tolist()]
    mean = np.asarray(arrays["mean_aligned_mesh"], dtype=np.float64)
    disp, _ = family_displacements(arrays["coef"], names, mean, names, "<family release>")
    p99 = np.asarray(arrays.get("feature_p99", np.ones(len(names))), dtype=np.float64).reshape(-1)
    values = np.where(np.isfinite(p99) & (p99 > 0), p99, 1.0)
    origin, axes, scale = face.face_frame(mean)
    neutral = (unflatten_axis_major(np.asarray(arrays["intercept"], np.float64)) - origin) @ axes.T / scale
    return neutral, disp * values[:, None, None], names, values


def fig_family_panels(
    neutral: np.ndarray,
    disp: np.ndarray,
    names: list[str],
    values: np.ndarray,
    tri: np.ndarray,
    unsupported: Mapping[str, str],
    family: str,
):
    """Grid of shaded solid faces, one per input at its p99 (pose 0); red tint = displacement; unsupported inputs
    greyed with their label. Displacements are drawn as they are (x1: the values are the data's own)."""
    signs = normal_signs(neutral, tri)
    supported = np.array([n not in unsupported for n in names])
    mags = np.linalg.norm(disp, axis=2)
    vmax = (mags[supported].max() if supported.any() else 0.0) or 1.0
    lims = display_limits(neutral, disp, 1.0, supported)
    cols = min(8, len(names))
    rows = math.ceil(len(names) / cols)
    height = 2.15 * rows + 1.1  # inches: the rows, and a header for the two-line title above the first row's labels
    fig = new_figure(1.9 * cols, height)
    axes = np.atleast_1d(fig.subplots(rows, cols)).ravel()
    for k, ax in enumerate(axes):
        if k >= len(names):
            ax.set_axis_off()
            continue
        if supported[k]:
            draw_solid(ax, neutral + disp[k], tri, signs, tint=mags[k][tri].mean(axis=1) / vmax)
        else:
            mark_unsupported(ax, neutral, tri, signs, unsupported[names[k]])
        prep_ax(ax, lims, f"{names[k]} = {values[k]:.2g}", fontsize=7)
    fig.suptitle(
        f"{family}: each input at its training p99 (the most py-feat gives it), others 0, pose 0\nred tint = "
        "displacement" + ("; grey = never expressed in the training data" if not supported.all() else ""),
        fontsize=10,
        y=1 - 0.08 / height,
        va="top",
    )
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=1 - 0.95 / height, wspace=0.02, hspace=0.2)
    return fig


def render_family(
    arrays: Mapping[str, Any], out_dir: str | os.PathLike, cv_path: str | os.PathLike | None = None
) -> list[Path]:
    """Write the family release's figures into ``out_dir`` (atomically, each): ``<family>_panels.png`` and, with the
    fit's CV arrays, ``r2_per_vertex.png`` / ``cumulative_vertex_error.png``.

    Parameters
    ----------
    arrays : mapping
        The family NPZ's arrays (:func:`aumesh.model.family_release.family_release_arrays`).
    out_dir : path
    cv_path : path, optional
        The family fit's ``cv.npz`` (:func:`aumesh.card.render.load_cv`).
    """
    from aumesh.card.release_figures import fig_cumulative_error, fig_r2_per_vertex
    from aumesh.card.render import _render_all, cumulative_curve, load_cv
    from aumesh.geometry import face

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    family = str(np.asarray(arrays["family"]))
    neutral, disp, names, values = family_faces(arrays)
    tri = face.triangulate(neutral)
    listed = {str(s) for s in np.asarray(arrays.get("unsupported_features", np.array([], str))).ravel()}
    p99 = np.asarray(arrays.get("feature_p99", np.full(len(names), np.nan)), np.float64).reshape(-1)
    unsupported = {n: f"never expressed (p99 {v:.2g})" for n, v in zip(names, p99, strict=True) if n in listed}
    jobs: list[tuple[Path, Any, tuple]] = [
        (
            out / PANELS.format(family=family),
            fig_family_panels,
            (neutral, disp, names, values, tri, unsupported, family),
        )
    ]
    cv = load_cv(cv_path) if cv_path is not None and Path(cv_path).exists() else None
    if cv is not None and "r2_per_vertex" in cv:
        jobs.append((out / "r2_per_vertex.png", fig_r2_per_vertex, (neutral, tri, cv["r2_per_vertex"])))
    if cv is not None and ("vertex_error" in cv or "cumulative_error_thresholds" in cv):
        jobs.append((out / "cumulative_vertex_error.png", fig_cumulative_error, cumulative_curve(cv)))
    return _render_all(jobs)
