"""The visual model card: figures rendered from a release NPZ alone.

Input: a release NPZ in the card's format (``coef`` (23, 1434) axis-major rows in
``input_columns`` order, ``intercept`` (1434,), ``au_columns``,
``mean_aligned_mesh`` (478, 3), ...) and optionally a CV arrays NPZ with
``r2_per_vertex`` (478,) and ``vertex_error`` (per-frame mean per-vertex
Euclidean error, (n_frames,) or (n_frames, 478)), or a precomputed curve
``cumulative_error_thresholds`` + ``cumulative_error_fraction`` (what the evaluate stage's
``build/model/cv.npz`` holds: points of the empirical CDF, so no per-frame vector is loaded).

Prediction follows the card exactly: ``flat = x @ coef + intercept`` with
``x = [AU one-hot | pose 0]``, unflattened from ``[x_0..x_477 | y_.. | z_..]``.

Orientation: the release mesh may be in any convention (py-feat pixel space with
y down, MediaPipe canonical with y up, rotated...). Every figure is drawn in the
face frame of :func:`aumesh.geometry.face.face_frame` computed from ``mean_aligned_mesh``
(up = forehead 10 - chin 152, subject's left = 33 -> 263, toward the camera = the
side of the nose tip 1), in inter-ocular units, frontal view with up at the top
and the subject's left on the image right (as a photograph).

The triangles are :func:`aumesh.geometry.face.triangulate`'s: MediaPipe's tessellation where the
``mediapipe`` package is installed, the project's own triangulation otherwise. Matplotlib is used through
``matplotlib.figure.Figure`` + the Agg canvas only (no pyplot, no global backend
change); every file is written atomically (temp file, then ``os.replace``).

Pose views use the card's render-time rotation
``scipy.spatial.transform.Rotation.from_euler("xyz", [pitch, yaw, roll])`` applied
in MediaPipe-canonical axes (x subject's left, y up, z out of the face) about the
mesh centroid. Note: in SciPy, lowercase ``"xyz"`` is **extrinsic** (R = Rz Ry Rx),
not intrinsic as the card states.

Figure builders ``fig_*`` are pure: they take ``neutral`` (478, 3) and ``disp``
(20, 478, 3, ``AU_COLUMNS`` order) in the face frame (inter-ocular units), ``tri``
(T, 3) from :func:`aumesh.geometry.face.triangulate`, ``factor`` (display exaggeration,
stated in the figure title) and return a ``matplotlib.figure.Figure``;
:func:`render_release` does the I/O.

Unsupported AUs: an AU the release's data barely exercised (the NPZ's ``unsupported_features``, py-feat's v6
convention, ``feat/plotting.py`` ``PLSFeatMeshModel``), or whose field is implausibly large
(:func:`aumesh.card.limits.implausible_fields`: more than 5x the median AU), gets an extrapolated field that can
move vertices by more than a face's width. Its panels show the neutral face greyed with the reason
(:func:`unsupported_aus`) instead of an exploded face, and the shared exaggeration factor and the panels' limits
come from the supported AUs only. The effect maps scale their colours per AU (:func:`effect_map_scales`), each
panel's maximum printed in its title, so one huge AU does not leave the others black.

Command line: ``main(["NPZ", "--out", "DIR", "--cv", "CVNPZ"])`` (``aumesh render``).
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, cast

import numpy as np

from aumesh.core.io import atomic_path, atomic_write_text
from aumesh.core.schema import AU_COLUMNS, N_VERTICES
from aumesh.geometry import face, landmarks
from aumesh.model.inference import load_release, predict_mesh

COMPARE_AUS: tuple[str, ...] = ("AU12", "AU26", "AU04", "AU01")
POSES_DEG: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.0, 0.0),
    (0.0, 30.0, 0.0),
    (0.0, -30.0, 0.0),
    (20.0, 0.0, 0.0),
    (-20.0, 0.0, 0.0),
    (0.0, 0.0, 20.0),
)
DPI = 110
SKIN = np.array([0.93, 0.78, 0.66])
TINT = np.array([0.85, 0.15, 0.10])
LIGHT = np.array([-0.3, -0.35, -1.0]) / np.linalg.norm([-0.3, -0.35, -1.0])  # face frame, toward the light
TARGET_VISIBLE = 0.08  # inter-ocular units the largest AU displacement is scaled up to, if smaller
GREY = np.array([0.78, 0.78, 0.78])  # the neutral face of an unsupported AU's panel
FIGURE_NAMES: tuple[str, ...] = (
    "au_solid_panels.png",
    "au_solid_neutral_vs_activated.png",
    "au_compare_overlay.png",
    "au_effect_maps.png",
    "pose_views.png",
    "r2_per_vertex.png",
    "cumulative_vertex_error.png",
)


# --------------------------------------------------------------------------- loading
def load_cv(cv_path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Load CV arrays: ``r2_per_vertex`` and/or ``vertex_error`` or the cumulative curve."""
    path = Path(cv_path)
    if not path.is_file():
        raise FileNotFoundError(f"CV arrays file not found: {path}")
    with np.load(path, allow_pickle=False) as z:
        cv = {k: z[k] for k in z.files}
    known = {"r2_per_vertex", "vertex_error", "cumulative_error_thresholds"}
    if not known & set(cv):
        raise KeyError(
            f"{path}: no CV key found; expected 'r2_per_vertex', 'vertex_error' or "
            f"'cumulative_error_thresholds' + 'cumulative_error_fraction'; has {sorted(cv)}"
        )
    if "r2_per_vertex" in cv and np.asarray(cv["r2_per_vertex"]).shape != (N_VERTICES,):
        raise ValueError(f"{path}: 'r2_per_vertex' must be ({N_VERTICES},), got {cv['r2_per_vertex'].shape}")
    if "cumulative_error_thresholds" in cv and "cumulative_error_fraction" not in cv:
        raise KeyError(f"{path}: 'cumulative_error_thresholds' given without 'cumulative_error_fraction'")
    return cv


def face_frame_meshes(arrays: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray, float]:
    """Neutral (AU=0, pose=0) mesh and per-AU displacements in the face frame.

    Returns
    -------
    neutral : np.ndarray, shape (478, 3)
        Prediction at x = 0, face frame of ``mean_aligned_mesh``, IOD units.
    disp : np.ndarray, shape (20, 478, 3)
        AU displacements at intensity 1 (``AU_COLUMNS`` order), same frame/units.
    scale : float
        Inter-ocular distance of ``mean_aligned_mesh`` in the release's units.
    """
    from aumesh.card.directions import au_displacements

    disp, _, _ = au_displacements(arrays)
    origin, axes, scale = face.face_frame(np.asarray(arrays["mean_aligned_mesh"], dtype=np.float64))
    neutral = (predict_mesh(arrays) - origin) @ axes.T / scale
    return neutral, disp, float(scale)


def exaggeration_factor(disp: np.ndarray, target: float = TARGET_VISIBLE) -> float:
    """1, or the smallest of 2, 5, 10, 20, 50, ... making the largest displacement >= ``target``."""
    m = float(np.linalg.norm(disp, axis=-1).max()) if disp.size else 0.0
    if m <= 0 or m >= 0.5 * target:
        return 1.0
    for f in (2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000, 10000):
        if f * m >= target:
            return float(f)
    return 10000.0


def unsupported_aus(arrays: Mapping[str, Any], disp: np.ndarray) -> dict[str, str]:
    """The AUs whose panels are not drawn as a moving face, each with the words its panel shows.

    Parameters
    ----------
    arrays : mapping
        The release NPZ's arrays; ``unsupported_features`` (k,) str and ``feature_p99`` (23,) in
        ``input_columns`` order are read when present (py-feat's v6 names, ``feat/plotting.py``).
    disp : ndarray, shape (20, 478, 3)
        AU displacements at intensity 1 (``AU_COLUMNS`` order), :func:`face_frame_meshes`.

    Returns
    -------
    dict
        AU -> label, e.g. ``"not in training data (p99 0.035)"`` or ``"implausible field (26x the median AU)"``,
        in ``AU_COLUMNS`` order; empty when every AU is supported.
    """
    from aumesh.card.limits import au_field_sizes, implausible_fields, moving_median

    listed = {str(a) for a in np.asarray(arrays.get("unsupported_features", np.array([], dtype=str))).ravel()}
    p99: dict[str, float] = {}
    if "feature_p99" in arrays and "input_columns" in arrays:
        names = [str(c) for c in np.asarray(arrays["input_columns"]).tolist()]
        values = np.asarray(arrays["feature_p99"], dtype=np.float64).ravel()
        if len(values) == len(names):
            p99 = dict(zip(names, values.tolist(), strict=True))
    sizes = au_field_sizes(disp)
    implausible = implausible_fields(sizes)
    median = moving_median(sizes)
    out: dict[str, str] = {}
    for k, au in enumerate(AU_COLUMNS):
        if au in listed:
            out[au] = "not in training data" + (f" (p99 {p99[au]:.2g})" if au in p99 else "")
        elif implausible[k]:
            out[au] = f"implausible field ({sizes[k] / median:.0f}x the median AU)"
    return out


def effect_map_scales(disp: np.ndarray, scale: float) -> np.ndarray:
    """Each AU's colour-scale maximum for the effect maps: its own largest vertex displacement, release units.

    Parameters
    ----------
    disp : ndarray, shape (20, 478, 3)
        AU displacements in inter-ocular units.
    scale : float
        Inter-ocular distance in release units (:func:`face_frame_meshes`).

    Returns
    -------
    ndarray, shape (20,)
        Per-AU maximum (release units; px for real data); 1 where an AU does not move (an all-black panel).
    """
    from aumesh.card.limits import au_field_sizes

    top = au_field_sizes(disp) * scale
    return np.where(top > 0, top, 1.0)


def supported_mask(unsupported: Mapping[str, str] | None) -> np.ndarray:
    """(20,) bool: the AUs drawn as moving faces (not in ``unsupported``)."""
    return np.array([au not in (unsupported or {}) for au in AU_COLUMNS])


def display_factor(disp: np.ndarray, unsupported: Mapping[str, str] | None) -> float:
    """The figures' shared exaggeration factor (:func:`exaggeration_factor`) from the supported AUs only: an
    exploded AU (drawn greyed) must not set it to 1 and leave every real AU's motion invisible."""
    return exaggeration_factor(np.asarray(disp)[supported_mask(unsupported)])


# --------------------------------------------------------------------------- drawing
def _figure(w: float, h: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: Path) -> Path:
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=DPI, format="png")
    return path


def _write_text(text: str, path: Path) -> Path:
    return atomic_write_text(path, text)


def _limits(mesh: np.ndarray, pad: float = 0.12) -> tuple[tuple[float, float], tuple[float, float]]:
    x, y = mesh[:, 0], -mesh[:, 1]
    return (x.min() - pad, x.max() + pad), (y.min() - pad, y.max() + pad)


def _prep_ax(ax, lims, title: str | None = None, fontsize: int = 9) -> None:
    ax.set_xlim(*lims[0])
    ax.set_ylim(*lims[1])
    ax.set_aspect("equal")
    ax.set_axis_off()
    if title:
        # y=1.0 where matplotlib would put it anyway (no tick labels above an axis-off panel), given: matplotlib then
        # skips measuring the hidden axes' ticks to place it at every draw (a quarter of a release's drawing time)
        ax.set_title(title, fontsize=fontsize, y=1.0)


def _normal_signs(neutral: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """+1/-1 per triangle so that sign * cross(b-a, c-a) faces the camera (-z) on the frontal neutral."""
    n = np.cross(neutral[tri[:, 1]] - neutral[tri[:, 0]], neutral[tri[:, 2]] - neutral[tri[:, 0]])
    return np.where(n[:, 2] <= 0, 1.0, -1.0)


def _draw_solid(
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


def _draw_features(ax, mesh: np.ndarray, color: str = "0.2", lw: float = 0.6) -> None:
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


def _au_title(au: str) -> str:
    from aumesh.card.directions import FACS_EXPECTATIONS

    return f"{au} {FACS_EXPECTATIONS[au]['name']}"


def _mark_unsupported(ax, neutral: np.ndarray, tri: np.ndarray, signs: np.ndarray | None, label: str) -> None:
    """An unsupported AU's panel: the neutral face greyed (solid, or a wireframe without ``signs``) and ``label``."""
    if signs is None:
        ax.triplot(neutral[:, 0], -neutral[:, 1], tri, color="0.8", lw=0.3)
    else:
        _draw_solid(ax, neutral, tri, signs, color=GREY)
    _unsupported_label(ax, label)


def _unsupported_label(ax, label: str) -> None:
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


def _display_limits(neutral: np.ndarray, disp: np.ndarray, factor: float, supported: np.ndarray, pad: float = 0.12):
    """Panel limits covering the neutral face and the supported AUs' exaggerated faces (an exploded AU, drawn
    greyed, must not shrink every face)."""
    moved = (neutral + factor * disp[supported]).reshape(-1, 3)
    return _limits(np.concatenate([neutral, moved]), pad=pad)


def fig_solid_panels(neutral, disp, tri, factor, unsupported: Mapping[str, str] | None = None):
    """Grid of shaded solid faces, one per AU at intensity 1 (pose 0); red tint = displacement.

    ``unsupported`` (AU -> label, :func:`unsupported_aus`): those panels show the neutral face greyed and the label;
    the tint's scale and the limits come from the other AUs."""
    signs = _normal_signs(neutral, tri)
    supported = supported_mask(unsupported)
    mags = np.linalg.norm(disp, axis=2)
    vmax = (mags[supported].max() if supported.any() else 0.0) or 1.0
    lims = _display_limits(neutral, disp, factor, supported)
    fig = _figure(13, 12.5)
    axes = fig.subplots(4, 5)
    for k, (au, ax) in enumerate(zip(AU_COLUMNS, axes.flat, strict=True)):
        if supported[k]:
            _draw_solid(ax, neutral + factor * disp[k], tri, signs, tint=mags[k][tri].mean(axis=1) / vmax)
        else:
            _mark_unsupported(ax, neutral, tri, signs, (unsupported or {})[au])
        _prep_ax(ax, lims, _au_title(au))
    fig.suptitle(
        f"AU at intensity 1, pose 0 (frontal); red tint = displacement magnitude; displacements x{factor:g}"
        + ("; grey = AU not drawn (unsupported by the data)" if not supported.all() else ""),
        fontsize=12,
    )
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.94, wspace=0.02, hspace=0.12)
    return fig


def fig_neutral_vs_activated(neutral, disp, tri, factor, aus=COMPARE_AUS, unsupported: Mapping[str, str] | None = None):
    """Neutral (top row) vs activated (bottom row) solid faces for a few AUs (unsupported ones greyed, labelled)."""
    signs = _normal_signs(neutral, tri)
    supported = supported_mask(unsupported)
    lims = _display_limits(neutral, disp, factor, supported)
    fig = _figure(3.0 * len(aus), 6.6)
    axes = fig.subplots(2, len(aus), squeeze=False)
    for j, au in enumerate(aus):
        k = AU_COLUMNS.index(au)
        _draw_solid(axes[0, j], neutral, tri, signs)
        _prep_ax(axes[0, j], lims, "neutral (AU=0)")
        if supported[k]:
            _draw_solid(axes[1, j], neutral + factor * disp[k], tri, signs)
        else:
            _mark_unsupported(axes[1, j], neutral, tri, signs, (unsupported or {})[au])
        _prep_ax(axes[1, j], lims, f"{_au_title(au)} = 1")
    how = "true scale (x1)" if factor == 1 else f"displacements exaggerated x{factor:g} for visibility"
    fig.suptitle(f"Neutral vs activated (intensity 1, pose 0); {how}", fontsize=12)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.88, wspace=0.02, hspace=0.1)
    return fig


def fig_compare_overlay(neutral, disp, tri, factor, unsupported: Mapping[str, str] | None = None):
    """Neutral (grey) and activated (blue) wireframes with displacement arrows, per AU (unsupported: labelled)."""
    supported = supported_mask(unsupported)
    lims = _display_limits(neutral, disp, factor, supported)
    fig = _figure(13, 12.5)
    axes = fig.subplots(4, 5)
    for k, (au, ax) in enumerate(zip(AU_COLUMNS, axes.flat, strict=True)):
        if not supported[k]:
            _mark_unsupported(ax, neutral, tri, None, (unsupported or {})[au])
            _prep_ax(ax, lims, _au_title(au))
            continue
        act = neutral + factor * disp[k]
        ax.triplot(neutral[:, 0], -neutral[:, 1], tri, color="0.75", lw=0.3)
        ax.triplot(act[:, 0], -act[:, 1], tri, color="tab:blue", lw=0.3, alpha=0.7)
        mag = np.linalg.norm(disp[k], axis=1)
        sel = np.flatnonzero(mag >= 0.25 * mag.max()) if mag.max() > 0 else np.array([], dtype=int)
        d = factor * disp[k][sel]
        ax.quiver(
            neutral[sel, 0],
            -neutral[sel, 1],
            d[:, 0],
            -d[:, 1],
            angles="xy",
            scale_units="xy",
            scale=1.0,
            color="tab:red",
            width=0.006,
            headwidth=3.5,
            headlength=4,
        )
        _prep_ax(ax, lims, _au_title(au))
    fig.suptitle(
        f"Neutral (grey) vs activated (blue), arrows = displacement (>= 25% of the AU's max); x{factor:g}", fontsize=12
    )
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.94, wspace=0.02, hspace=0.12)
    return fig


def fig_effect_maps(neutral, disp, tri, scale, unsupported: Mapping[str, str] | None = None):
    """Per-AU displacement magnitude as a colour map on the neutral mesh, each panel on its own colour scale
    (:func:`effect_map_scales`, its maximum in the panel's title, release units and inter-ocular distances): one
    huge AU leaves the others readable. Unsupported AUs keep their map, their title says why."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    mags = np.linalg.norm(disp, axis=2) * scale
    tops = effect_map_scales(disp, scale)
    lims = _limits(neutral, pad=0.1)
    fig = _figure(13, 12.5)
    axes = fig.subplots(4, 5)
    for k, (au, ax) in enumerate(zip(AU_COLUMNS, axes.flat, strict=True)):
        ax.tripcolor(
            neutral[:, 0], -neutral[:, 1], tri, mags[k] / tops[k], shading="gouraud", cmap="magma", vmin=0.0, vmax=1.0
        )
        _draw_features(ax, neutral, color="0.6", lw=0.4)
        note = f"\n{(unsupported or {})[au]}" if au in (unsupported or {}) else ""
        top = float(mags[k].max())
        _prep_ax(ax, lims, f"{_au_title(au)}\nmax {top:.3g} ({top / scale:.3f} IOD){note}", fontsize=8)
    fig.subplots_adjust(left=0.01, right=0.9, bottom=0.01, top=0.92, wspace=0.02, hspace=0.28)
    cax = fig.add_axes((0.92, 0.1, 0.015, 0.8))
    fig.colorbar(
        ScalarMappable(norm=Normalize(0.0, 1.0), cmap="magma"),
        cax=cax,
        label="|displacement| at intensity 1 / the panel's max (in its title: release units, px for real data)",
    )
    fig.suptitle("AU effect maps: displacement magnitude per vertex (each AU on its own colour scale)", fontsize=12)
    return fig


def fig_pose_views(neutral, disp, tri, factor, poses_deg=POSES_DEG, unsupported: Mapping[str, str] | None = None):
    """Neutral and AU12-activated face at a few render-time head poses (AU12 unsupported: its row greyed)."""
    from scipy.spatial.transform import Rotation

    signs = _normal_signs(neutral, tri)
    flip = np.diag([1.0, -1.0, -1.0])  # face frame <-> MediaPipe canonical (x left, y up, z out of face)
    au12 = (unsupported or {}).get("AU12")
    rows = (("neutral", neutral, None), ("AU12 = 1", neutral + factor * disp[AU_COLUMNS.index("AU12")], au12))
    r = float(np.abs(neutral).max()) + 0.15
    lims = ((-r, r), (-r, r))
    fig = _figure(2.4 * len(poses_deg), 5.6)
    axes = fig.subplots(2, len(poses_deg), squeeze=False)
    for i, (label, mesh, why) in enumerate(rows):
        mesh = neutral if why else mesh
        centre = mesh.mean(axis=0)
        for j, (p, y, rl) in enumerate(poses_deg):
            R = Rotation.from_euler("xyz", np.radians([p, y, rl])).as_matrix()
            posed = ((mesh - centre) @ flip @ R.T) @ flip + centre
            _draw_solid(axes[i, j], posed, tri, signs, cull=True, color=GREY if why else SKIN)
            _prep_ax(axes[i, j], lims, f"{label}\npitch {p:g} yaw {y:g} roll {rl:g} deg", fontsize=8)
            if why:
                _unsupported_label(axes[i, j], f"AU12 {why}")
    fig.suptitle(
        "Render-time pose: Rotation.from_euler('xyz', [pitch, yaw, roll]) in MP-canonical axes "
        "(x subject's left, y up, z out of face)",
        fontsize=10,
    )
    fig.text(
        0.5,
        0.01,
        "SciPy lowercase 'xyz' is EXTRINSIC (R = Rz Ry Rx), whatever the card claims; "
        f"pose inputs of the model kept at 0; AU12 x{factor:g}",
        ha="center",
        fontsize=8,
    )
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.06, top=0.82, wspace=0.02, hspace=0.3)
    return fig


def fig_r2_per_vertex(neutral, tri, r2):
    """Per-vertex out-of-sample R^2 on the neutral mesh plus its histogram."""
    fig = _figure(10, 5.5)
    ax, axh = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.2, 1]})
    r2 = np.asarray(r2, dtype=np.float64)
    im = ax.tripcolor(
        neutral[:, 0],
        -neutral[:, 1],
        tri,
        r2,
        shading="gouraud",
        cmap="viridis",
        vmin=min(0.0, float(np.nanmin(r2))),
        vmax=max(float(np.nanmax(r2)), 1e-6),
    )
    _draw_features(ax, neutral, color="w", lw=0.4)
    _prep_ax(ax, _limits(neutral, pad=0.1), "R² per vertex (x, y, z pooled; CV held-out folds)")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
    axh.hist(r2[np.isfinite(r2)], bins=40, color="tab:green")
    axh.axvline(float(np.nanmean(r2)), color="k", ls="--", label=f"mean {np.nanmean(r2):.3f}")
    axh.set_xlabel("R² per vertex")
    axh.set_ylabel("vertices")
    axh.legend()
    fig.suptitle("Out-of-sample R² per vertex", fontsize=12)
    fig.subplots_adjust(left=0.02, right=0.97, bottom=0.1, top=0.88, wspace=0.35)
    return fig


def cumulative_curve(cv: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(thresholds, fraction of frames with mean per-vertex error <= threshold)."""
    if "cumulative_error_thresholds" in cv:
        t = np.asarray(cv["cumulative_error_thresholds"], dtype=np.float64)
        f = np.asarray(cv["cumulative_error_fraction"], dtype=np.float64)
        if t.shape != f.shape or t.ndim != 1:
            raise ValueError("cumulative_error_thresholds and cumulative_error_fraction must be equal-length 1-D")
        return t, f
    e = np.asarray(cv["vertex_error"], dtype=np.float64)
    if e.ndim == 2:
        e = e.mean(axis=1)
    e = np.sort(e[np.isfinite(e)])
    if e.size == 0:
        raise ValueError("vertex_error has no finite values")
    return e, np.arange(1, e.size + 1) / e.size


def fig_cumulative_error(thresholds, fraction):
    """Cumulative distribution of the per-frame mean per-vertex error."""
    fig = _figure(7, 5)
    ax = fig.subplots()
    ax.plot(thresholds, fraction, color="tab:blue", lw=2)
    for q in (0.5, 0.9):
        i = int(np.searchsorted(fraction, q))
        if i < len(thresholds):
            ax.axvline(thresholds[i], color="0.5", ls="--", lw=1)
            ax.text(thresholds[i], q, f" {int(q * 100)}%: {thresholds[i]:.3g}", va="bottom", fontsize=9)
    ax.set_xlabel("mean per-vertex Euclidean error (release units; px for real data)")
    ax.set_ylabel("fraction of frames with error <= x")
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    ax.set_title("Cumulative vertex error (out of sample)")
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------- orchestration
def render_release(
    npz_path: str | os.PathLike, out_dir: str | os.PathLike, cv_path: str | os.PathLike | None = None
) -> list[Path]:
    """Render the visual model card from a release NPZ (and optional CV arrays).

    Parameters
    ----------
    npz_path : path
        Release NPZ in the card's format.
    out_dir : path
        Output folder (created if missing). Files are written atomically.
    cv_path : path, optional
        CV arrays NPZ (``r2_per_vertex``, ``vertex_error`` or the cumulative curve).

    Returns
    -------
    list of Path
        The PNGs written: ``au_solid_panels``, ``au_solid_neutral_vs_activated``,
        ``au_compare_overlay``, ``au_effect_maps``, ``pose_views`` and, with CV
        data, ``r2_per_vertex`` / ``cumulative_vertex_error``.
    """
    arrays = load_release(npz_path)
    cv = load_cv(cv_path) if cv_path is not None else None
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    neutral, disp, scale = face_frame_meshes(arrays)
    tri = face.triangulate(neutral)
    unsupported = unsupported_aus(arrays, disp)
    factor = display_factor(disp, unsupported)
    jobs: list[tuple[str, Callable[..., Any], tuple[Any, ...]]] = [
        ("au_solid_panels.png", fig_solid_panels, (neutral, disp, tri, factor, unsupported)),
        (
            "au_solid_neutral_vs_activated.png",
            fig_neutral_vs_activated,
            (neutral, disp, tri, factor, COMPARE_AUS, unsupported),
        ),
        ("au_compare_overlay.png", fig_compare_overlay, (neutral, disp, tri, factor, unsupported)),
        ("au_effect_maps.png", fig_effect_maps, (neutral, disp, tri, scale, unsupported)),
        ("pose_views.png", fig_pose_views, (neutral, disp, tri, factor, POSES_DEG, unsupported)),
    ]
    if cv is not None and "r2_per_vertex" in cv:
        jobs.append(("r2_per_vertex.png", fig_r2_per_vertex, (neutral, tri, cv["r2_per_vertex"])))
    if cv is not None and ("vertex_error" in cv or "cumulative_error_thresholds" in cv):
        jobs.append(("cumulative_vertex_error.png", fig_cumulative_error, cumulative_curve(cv)))
    return _render_all([(out / name, make, args) for name, make, args in jobs])


def _render(path: Path, make, args) -> Path:
    return _save(make(*args), path)


def _render_all(jobs: list[tuple[Path, Any, tuple]]) -> list[Path]:
    """Draw and save each ``(path, figure function, args)``, on every core: Agg drawing is Python-bound (one
    core per process), and the figures are independent. Worker processes are forked (they inherit the imported
    matplotlib); where fork is unavailable or there is one core, they are drawn one by one here."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    from matplotlib.figure import Figure  # noqa: F401  imported once, before the fork

    workers = min(len(jobs), os.cpu_count() or 1)
    if workers < 2 or "fork" not in multiprocessing.get_all_start_methods():
        return [_render(*job) for job in jobs]
    with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
        return list(pool.map(_render, *zip(*jobs, strict=True)))


def main(argv: Sequence[str] | None = None) -> int:
    """``render NPZ --out DIR [--cv CVNPZ]``: figures + ``au_directions.json`` (+ ``.md``) into DIR."""
    from aumesh.card.directions import au_direction_report, report_markdown_table, write_report

    parser = argparse.ArgumentParser(prog="aumesh render", description="Render the visual model card of a release NPZ.")
    parser.add_argument("npz", help="release NPZ (card format)")
    parser.add_argument("--out", required=True, help="output folder for the PNGs and au_directions.json")
    parser.add_argument(
        "--cv", default=None, help="CV arrays NPZ (r2_per_vertex, vertex_error or the cumulative curve)"
    )
    args = parser.parse_args(argv)
    try:
        paths = render_release(args.npz, args.out, args.cv)
        report = au_direction_report(args.npz)
        paths.append(write_report(report, Path(args.out) / "au_directions.json"))
        paths.append(_write_text(report_markdown_table(report), Path(args.out) / "au_directions.md"))
    except (FileNotFoundError, KeyError, ValueError) as exc:
        print(f"aumesh render: error: {exc}", file=sys.stderr)
        return 2
    for p in paths:
        print(p)
    s = report["summary"]
    print(f"AU directions: {s['pass']} pass, {s['doubtful']} doubtful, {s['fail']} fail", file=sys.stderr)
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
