"""Drawing the card's faces with matplotlib: the primitives every figure of :mod:`aumesh.card.release_figures` is
made of.

A figure is a ``matplotlib.figure.Figure`` on the Agg canvas (:func:`new_figure`: no pyplot, no global backend
change), saved atomically (:func:`save_png`: temp file, then ``os.replace``). Faces are drawn in the face frame of
:func:`aumesh.geometry.face.face_frame` (inter-ocular units, viewed from -z: up at the top, the subject's left on the
image right, as a photograph): Lambert-shaded solid triangles (:func:`draw_solid`, painter's order), the feature
contours (:func:`draw_features`), panel limits and titles; an unsupported AU's panel is the neutral face greyed with
the reason (:func:`mark_unsupported`), and :func:`display_limits` keeps an exploded field from shrinking every face.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import cast

import numpy as np

from aumesh.core.io import atomic_path
from aumesh.core.schema import AU_COLUMNS
from aumesh.geometry import landmarks

DPI = 110
SKIN = np.array([0.93, 0.78, 0.66])
TINT = np.array([0.85, 0.15, 0.10])
LIGHT = np.array([-0.3, -0.35, -1.0]) / np.linalg.norm([-0.3, -0.35, -1.0])  # face frame, toward the light
GREY = np.array([0.78, 0.78, 0.78])  # the neutral face of an unsupported AU's panel
UNIDENTIFIED = "#b05a00"  # a flagged AU's title and hatch (issue 43: not identified under detector noise)
UNIDENTIFIED_NOTE = "hatched, orange title: AU field not identified under detector noise (identification screen)"


def supported_mask(unsupported: Mapping[str, str] | None) -> np.ndarray:
    """(20,) bool: the AUs drawn as moving faces (not in ``unsupported``)."""
    return np.array([au not in (unsupported or {}) for au in AU_COLUMNS])


def new_figure(w: float, h: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def save_png(fig, path: Path) -> Path:
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=DPI, format="png")
    return path


def mesh_limits(mesh: np.ndarray, pad: float = 0.12) -> tuple[tuple[float, float], tuple[float, float]]:
    x, y = mesh[:, 0], -mesh[:, 1]
    return (x.min() - pad, x.max() + pad), (y.min() - pad, y.max() + pad)


def prep_ax(ax, lims, title: str | None = None, fontsize: int = 9) -> None:
    ax.set_xlim(*lims[0])
    ax.set_ylim(*lims[1])
    ax.set_aspect("equal")
    ax.set_axis_off()
    if title:
        # y=1.0 where matplotlib would put it anyway (no tick labels above an axis-off panel), given: matplotlib then
        # skips measuring the hidden axes' ticks to place it at every draw (a quarter of a release's drawing time)
        ax.set_title(title, fontsize=fontsize, y=1.0)


def normal_signs(neutral: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """+1/-1 per triangle so that sign * cross(b-a, c-a) faces the camera (-z) on the frontal neutral."""
    n = np.cross(neutral[tri[:, 1]] - neutral[tri[:, 0]], neutral[tri[:, 2]] - neutral[tri[:, 0]])
    return np.where(n[:, 2] <= 0, 1.0, -1.0)


def draw_solid(
    ax,
    mesh: np.ndarray,
    tri: np.ndarray,
    signs: np.ndarray,
    tint: np.ndarray | None = None,
    cull: bool = False,
    color: np.ndarray = SKIN,
) -> None:
    """Lambert-shaded solid face (face frame, viewed from -z) with optional per-triangle red tint in [0, 1]."""
    from matplotlib.collections import PolyCollection

    n = signs[:, None] * np.cross(mesh[tri[:, 1]] - mesh[tri[:, 0]], mesh[tri[:, 2]] - mesh[tri[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    keep = n[:, 2] < 0.05 if cull else np.ones(len(tri), dtype=bool)
    lam = np.clip(n @ LIGHT, 0.0, 1.0)
    shade = 0.35 + 0.65 * lam
    base = np.broadcast_to(color, (len(tri), 3)).copy()
    if tint is not None:
        t = np.clip(tint, 0.0, 1.0)[:, None] * 0.85
        base = (1 - t) * base + t * TINT
    colors = np.clip(base * shade[:, None], 0, 1)
    order = np.argsort(-mesh[tri, 2].mean(axis=1))  # far first (painter's algorithm)
    order = order[keep[order]]
    verts = np.stack([mesh[tri[order], 0], -mesh[tri[order], 1]], axis=-1)
    # an (n, 3, 2) array, not a list of n arrays: matplotlib closes the triangles in one step instead of one Path
    # construction each (~34,000 per release); its stubs name only the list, its code takes both
    pc = PolyCollection(
        cast("Sequence[np.ndarray]", verts), facecolors=colors[order], edgecolors=colors[order], linewidths=0.2
    )
    ax.add_collection(pc)
    # Irises are not triangulated (they sit in the eye openings): draw them as dots,
    # unless the upper lid has come down past the iris centre (eye closed).
    for c, lid in ((468, 159), (473, 386)):
        if mesh[lid, 1] < mesh[c, 1]:
            ax.plot(mesh[c, 0], -mesh[c, 1], "o", color="0.15", ms=3)


def draw_features(ax, mesh: np.ndarray, color: str = "0.2", lw: float = 0.6) -> None:
    for contour in (
        landmarks.EYE_CONTOUR_RIGHT,
        landmarks.EYE_CONTOUR_LEFT,
        landmarks.LIPS_OUTER,
        landmarks.LIPS_INNER,
        landmarks.BROW_UPPER_RIGHT,
        landmarks.BROW_UPPER_LEFT,
        landmarks.FACE_OVAL,
    ):
        closed = contour not in (landmarks.BROW_UPPER_RIGHT, landmarks.BROW_UPPER_LEFT)
        idx = list(contour) + ([contour[0]] if closed else [])
        ax.plot(mesh[idx, 0], -mesh[idx, 1], color=color, lw=lw)


def au_title(au: str) -> str:
    from aumesh.card.directions import FACS_EXPECTATIONS

    return f"{au} {FACS_EXPECTATIONS[au]['name']}"


def mark_unsupported(ax, neutral: np.ndarray, tri: np.ndarray, signs: np.ndarray | None, label: str) -> None:
    """An unsupported AU's panel: the neutral face greyed (solid, or a wireframe without ``signs``) and ``label``."""
    if signs is None:
        ax.triplot(neutral[:, 0], -neutral[:, 1], tri, color="0.8", lw=0.3)
    else:
        draw_solid(ax, neutral, tri, signs, color=GREY)
    unsupported_label(ax, label)


def unsupported_label(ax, label: str) -> None:
    """``label`` boxed in red across the middle of the panel (the reason an AU is not drawn)."""
    ax.text(
        0.5,
        0.5,
        label.replace(" (", "\n(", 1),
        transform=ax.transAxes,
        ha="center",
        va="center",
        fontsize=8,
        color="0.1",
        bbox={"boxstyle": "round", "facecolor": "white", "edgecolor": "tab:red", "alpha": 0.9},
    )


def mark_unidentified(ax, label: str) -> None:
    """A flagged AU's panel (issue 43, :meth:`aumesh.export.identification.AuIdentification.label`): hatched behind
    the face and its title, set by :func:`prep_ax`, in orange with ``label`` on a line of its own. The field is still
    drawn: it is the release's, only not separable from its partner's by the data."""
    from matplotlib.patches import Rectangle

    ax.add_patch(
        Rectangle(
            (0, 0),
            1,
            1,
            transform=ax.transAxes,
            fill=False,
            hatch="////",
            edgecolor=UNIDENTIFIED,
            alpha=0.3,
            linewidth=0,
            zorder=0,  # behind the face (its collections draw at 1)
        )
    )
    ax.set_title(f"{ax.get_title()}\n{label}", fontsize=8, color=UNIDENTIFIED, y=1.0)


def display_limits(neutral: np.ndarray, disp: np.ndarray, factor: float, supported: np.ndarray, pad: float = 0.12):
    """Panel limits covering the neutral face and the supported AUs' exaggerated faces (an exploded AU, drawn
    greyed, must not shrink every face)."""
    moved = (neutral + factor * disp[supported]).reshape(-1, 3)
    return mesh_limits(np.concatenate([neutral, moved]), pad=pad)
