"""The release's figures: pure builders, one ``matplotlib.figure.Figure`` each, drawn with :mod:`aumesh.card.drawing`.

Each ``fig_*`` takes ``neutral`` (478, 3) and ``disp`` (20, 478, 3, ``AU_COLUMNS`` order) in the face frame
(inter-ocular units, :func:`aumesh.card.render.face_frame_meshes`), ``tri`` (T, 3) from
:func:`aumesh.geometry.face.triangulate`, ``factor`` (display exaggeration, stated in the figure title) and
``unsupported`` (AU -> label, :func:`aumesh.card.render.unsupported_aus`: those panels show the neutral face greyed
with the reason) and ``unidentified`` (AU -> label, :func:`aumesh.card.render.unidentified_aus`: the AUs the
identification screen flags, issue 43; their panels are hatched, the label under an orange title); the CV figures take the per-vertex R² and the cumulative error curve. :func:`aumesh.card.render.
render_release` chooses their inputs and does the I/O. The effect maps scale their colours per AU
(:func:`effect_map_scales`), each panel's maximum printed in its title, so one huge AU does not leave the others black.

Pose views use the card's render-time rotation
``scipy.spatial.transform.Rotation.from_euler("xyz", [pitch, yaw, roll])`` applied
in MediaPipe-canonical axes (x subject's left, y up, z out of the face) about the
mesh centroid. Note: in SciPy, lowercase ``"xyz"`` is **extrinsic** (R = Rz Ry Rx),
not intrinsic as the card states.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from aumesh.card.drawing import (
    GREY,
    SKIN,
    UNIDENTIFIED_NOTE,
    au_title,
    display_limits,
    draw_features,
    draw_solid,
    mark_unidentified,
    mark_unsupported,
    mesh_limits,
    new_figure,
    normal_signs,
    prep_ax,
    supported_mask,
    unsupported_label,
)
from aumesh.core.schema import AU_COLUMNS

COMPARE_AUS: tuple[str, ...] = ("AU12", "AU26", "AU04", "AU01")
POSES_DEG: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.0, 0.0),
    (0.0, 30.0, 0.0),
    (0.0, -30.0, 0.0),
    (20.0, 0.0, 0.0),
    (-20.0, 0.0, 0.0),
    (0.0, 0.0, 20.0),
)


def _mark(ax, au: str, unidentified: Mapping[str, str] | None) -> None:
    """``au``'s panel marked when the identification screen flags it (:func:`mark_unidentified`)."""
    if au in (unidentified or {}):
        mark_unidentified(ax, (unidentified or {})[au])


def _note(unidentified: Mapping[str, str] | None) -> str:
    """The suptitle's second line when an AU is flagged (empty otherwise)."""
    return f"\n{UNIDENTIFIED_NOTE}" if unidentified else ""


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


def fig_solid_panels(
    neutral,
    disp,
    tri,
    factor,
    unsupported: Mapping[str, str] | None = None,
    unidentified: Mapping[str, str] | None = None,
):
    """Grid of shaded solid faces, one per AU at intensity 1 (pose 0); red tint = displacement.

    ``unsupported`` (AU -> label, :func:`unsupported_aus`): those panels show the neutral face greyed and the label;
    the tint's scale and the limits come from the other AUs."""
    signs = normal_signs(neutral, tri)
    supported = supported_mask(unsupported)
    mags = np.linalg.norm(disp, axis=2)
    vmax = (mags[supported].max() if supported.any() else 0.0) or 1.0
    lims = display_limits(neutral, disp, factor, supported)
    fig = new_figure(13, 12.5)
    axes = fig.subplots(4, 5)
    for k, (au, ax) in enumerate(zip(AU_COLUMNS, axes.flat, strict=True)):
        if supported[k]:
            draw_solid(ax, neutral + factor * disp[k], tri, signs, tint=mags[k][tri].mean(axis=1) / vmax)
        else:
            mark_unsupported(ax, neutral, tri, signs, (unsupported or {})[au])
        prep_ax(ax, lims, au_title(au))
        _mark(ax, au, unidentified)
    fig.suptitle(
        f"AU at intensity 1, pose 0 (frontal); red tint = displacement magnitude; displacements x{factor:g}"
        + ("; grey = AU not drawn (unsupported by the data)" if not supported.all() else "")
        + _note(unidentified),
        fontsize=12,
    )
    fig.subplots_adjust(
        left=0.01, right=0.99, bottom=0.01, top=0.92 if unidentified else 0.94, wspace=0.02, hspace=0.12
    )
    return fig


def fig_neutral_vs_activated(
    neutral,
    disp,
    tri,
    factor,
    aus=COMPARE_AUS,
    unsupported: Mapping[str, str] | None = None,
    unidentified: Mapping[str, str] | None = None,
):
    """Neutral (top row) vs activated (bottom row) solid faces for a few AUs (unsupported ones greyed, labelled)."""
    signs = normal_signs(neutral, tri)
    supported = supported_mask(unsupported)
    lims = display_limits(neutral, disp, factor, supported)
    fig = new_figure(3.0 * len(aus), 6.6)
    axes = fig.subplots(2, len(aus), squeeze=False)
    for j, au in enumerate(aus):
        k = AU_COLUMNS.index(au)
        draw_solid(axes[0, j], neutral, tri, signs)
        prep_ax(axes[0, j], lims, "neutral (AU=0)")
        if supported[k]:
            draw_solid(axes[1, j], neutral + factor * disp[k], tri, signs)
        else:
            mark_unsupported(axes[1, j], neutral, tri, signs, (unsupported or {})[au])
        prep_ax(axes[1, j], lims, f"{au_title(au)} = 1")
        _mark(axes[1, j], au, unidentified)
    how = "true scale (x1)" if factor == 1 else f"displacements exaggerated x{factor:g} for visibility"
    shown = {au: v for au, v in (unidentified or {}).items() if au in aus}
    fig.suptitle(f"Neutral vs activated (intensity 1, pose 0); {how}" + _note(shown), fontsize=12)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.88, wspace=0.02, hspace=0.1)
    return fig


def fig_compare_overlay(
    neutral,
    disp,
    tri,
    factor,
    unsupported: Mapping[str, str] | None = None,
    unidentified: Mapping[str, str] | None = None,
):
    """Neutral (grey) and activated (blue) wireframes with displacement arrows, per AU (unsupported: labelled)."""
    supported = supported_mask(unsupported)
    lims = display_limits(neutral, disp, factor, supported)
    fig = new_figure(13, 12.5)
    axes = fig.subplots(4, 5)
    for k, (au, ax) in enumerate(zip(AU_COLUMNS, axes.flat, strict=True)):
        if not supported[k]:
            mark_unsupported(ax, neutral, tri, None, (unsupported or {})[au])
            prep_ax(ax, lims, au_title(au))
            _mark(ax, au, unidentified)
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
        prep_ax(ax, lims, au_title(au))
        _mark(ax, au, unidentified)
    fig.suptitle(
        f"Neutral (grey) vs activated (blue), arrows = displacement (>= 25% of the AU's max); x{factor:g}"
        + _note(unidentified),
        fontsize=12,
    )
    fig.subplots_adjust(
        left=0.01, right=0.99, bottom=0.01, top=0.92 if unidentified else 0.94, wspace=0.02, hspace=0.12
    )
    return fig


def fig_effect_maps(
    neutral,
    disp,
    tri,
    scale,
    unsupported: Mapping[str, str] | None = None,
    unidentified: Mapping[str, str] | None = None,
):
    """Per-AU displacement magnitude as a colour map on the neutral mesh, each panel on its own colour scale
    (:func:`effect_map_scales`, its maximum in the panel's title, release units and inter-ocular distances): one
    huge AU leaves the others readable. Unsupported AUs keep their map, their title says why."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    mags = np.linalg.norm(disp, axis=2) * scale
    tops = effect_map_scales(disp, scale)
    lims = mesh_limits(neutral, pad=0.1)
    fig = new_figure(13, 12.5)
    axes = fig.subplots(4, 5)
    for k, (au, ax) in enumerate(zip(AU_COLUMNS, axes.flat, strict=True)):
        ax.tripcolor(
            neutral[:, 0], -neutral[:, 1], tri, mags[k] / tops[k], shading="gouraud", cmap="magma", vmin=0.0, vmax=1.0
        )
        draw_features(ax, neutral, color="0.6", lw=0.4)
        note = f"\n{(unsupported or {})[au]}" if au in (unsupported or {}) else ""
        top = float(mags[k].max())
        prep_ax(ax, lims, f"{au_title(au)}\nmax {top:.3g} ({top / scale:.3f} IOD){note}", fontsize=8)
        _mark(ax, au, unidentified)
    fig.subplots_adjust(left=0.01, right=0.9, bottom=0.01, top=0.9 if unidentified else 0.92, wspace=0.02, hspace=0.28)
    cax = fig.add_axes((0.92, 0.1, 0.015, 0.8))
    fig.colorbar(
        ScalarMappable(norm=Normalize(0.0, 1.0), cmap="magma"),
        cax=cax,
        label="|displacement| at intensity 1 / the panel's max (in its title: release units, px for real data)",
    )
    fig.suptitle(
        "AU effect maps: displacement magnitude per vertex (each AU on its own colour scale)" + _note(unidentified),
        fontsize=12,
    )
    return fig


def fig_pose_views(
    neutral,
    disp,
    tri,
    factor,
    poses_deg=POSES_DEG,
    unsupported: Mapping[str, str] | None = None,
    unidentified: Mapping[str, str] | None = None,
):
    """Neutral and AU12-activated face at a few render-time head poses (AU12 unsupported: its row greyed)."""
    from scipy.spatial.transform import Rotation

    signs = normal_signs(neutral, tri)
    flip = np.diag([1.0, -1.0, -1.0])  # face frame <-> MediaPipe canonical (x left, y up, z out of face)
    au12 = (unsupported or {}).get("AU12")
    rows = (("neutral", neutral, None), ("AU12 = 1", neutral + factor * disp[AU_COLUMNS.index("AU12")], au12))
    r = float(np.abs(neutral).max()) + 0.15
    lims = ((-r, r), (-r, r))
    fig = new_figure(2.4 * len(poses_deg), 5.6)
    axes = fig.subplots(2, len(poses_deg), squeeze=False)
    for i, (label, mesh, why) in enumerate(rows):
        mesh = neutral if why else mesh
        centre = mesh.mean(axis=0)
        for j, (p, y, rl) in enumerate(poses_deg):
            R = Rotation.from_euler("xyz", np.radians([p, y, rl])).as_matrix()
            posed = ((mesh - centre) @ flip @ R.T) @ flip + centre
            draw_solid(axes[i, j], posed, tri, signs, cull=True, color=GREY if why else SKIN)
            prep_ax(axes[i, j], lims, f"{label}\npitch {p:g} yaw {y:g} roll {rl:g} deg", fontsize=8)
            if why:
                unsupported_label(axes[i, j], f"AU12 {why}")
            if i == 1:
                _mark(axes[i, j], "AU12", unidentified)
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
    fig = new_figure(10, 5.5)
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
    draw_features(ax, neutral, color="w", lw=0.4)
    prep_ax(ax, mesh_limits(neutral, pad=0.1), "R² per vertex (x, y, z pooled; CV held-out folds)")
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
    axh.hist(r2[np.isfinite(r2)], bins=40, color="tab:green")
    axh.axvline(float(np.nanmean(r2)), color="k", ls="--", label=f"mean {np.nanmean(r2):.3f}")
    axh.set_xlabel("R² per vertex")
    axh.set_ylabel("vertices")
    axh.legend()
    fig.suptitle("Out-of-sample R² per vertex", fontsize=12)
    fig.subplots_adjust(left=0.02, right=0.97, bottom=0.1, top=0.88, wspace=0.35)
    return fig


def fig_cumulative_error(thresholds, fraction):
    """Cumulative distribution of the per-frame mean per-vertex error."""
    fig = new_figure(7, 5)
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
