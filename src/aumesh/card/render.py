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
``mediapipe`` package is installed, the project's own triangulation otherwise. This module loads the release and
the CV arrays, chooses what the figures show (the face-frame meshes, the unsupported AUs, the shared exaggeration
factor) and writes the files, atomically (temp file, then ``os.replace``); the figures themselves are the pure
builders of :mod:`aumesh.card.release_figures`, drawn with the primitives of :mod:`aumesh.card.drawing`.

Unsupported AUs: an AU the release's data barely exercised (the NPZ's ``unsupported_features``, py-feat's v6
convention, ``feat/plotting.py`` ``PLSFeatMeshModel``), or whose field is implausibly large
(:func:`aumesh.card.limits.implausible_fields`: more than 5x the median AU), gets an extrapolated field that can
move vertices by more than a face's width. Its panels show the neutral face greyed with the reason
(:func:`unsupported_aus`) instead of an exploded face, and the shared exaggeration factor and the panels' limits
come from the supported AUs only (:func:`display_factor`).

Unidentified AUs (issue 43): the AUs the release's identification screen flags (its ``au_identification_*`` keys,
:func:`aumesh.export.identification.release_identification`; :func:`unidentified_aus`) are drawn as usual, their panels
hatched and titled in orange with "unidentified (sigma* ...): use AU09+AU10"; a release without the keys marks none.

``aumesh render NPZ --out DIR [--cv CVNPZ]`` (:mod:`aumesh.cli.tools`) calls :func:`render_card`: the figures and
the AU-direction report; the release stage calls :func:`render_release` and writes the report itself.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.card.drawing import save_png, supported_mask
from aumesh.card.release_figures import (
    COMPARE_AUS,
    POSES_DEG,
    fig_compare_overlay,
    fig_cumulative_error,
    fig_effect_maps,
    fig_neutral_vs_activated,
    fig_pose_views,
    fig_r2_per_vertex,
    fig_solid_panels,
)
from aumesh.core.io import atomic_write_text
from aumesh.core.schema import AU_COLUMNS, N_VERTICES
from aumesh.geometry import face
from aumesh.model.inference import predict_mesh
from aumesh.model.release_check import load_release

TARGET_VISIBLE = 0.08  # inter-ocular units the largest AU displacement is scaled up to, if smaller
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


def unidentified_aus(arrays: Mapping[str, Any], where: str = "release") -> dict[str, str]:
    """The AUs the release's identification screen flags (issue 43), each with the words its panels show.

    Parameters
    ----------
    arrays : mapping
        The release NPZ's arrays; its ``au_identification_*`` keys are read when present
        (:func:`aumesh.export.identification.release_identification`).
    where : str
        The file's name, for the error a broken set of keys gives.

    Returns
    -------
    dict
        AU -> label (:meth:`~aumesh.export.identification.AuIdentification.label`), e.g.
        ``"unidentified (sigma* 0.060): use AU09+AU10"``, ``AU_COLUMNS`` order; empty for a release without the screen
        or when it flags nothing.
    """
    from aumesh.export.identification import release_identification

    found = release_identification(arrays, where)
    return {} if found is None else {au: found.label(au) for au in found.flagged}


def display_factor(disp: np.ndarray, unsupported: Mapping[str, str] | None) -> float:
    """The figures' shared exaggeration factor (:func:`exaggeration_factor`) from the supported AUs only: an
    exploded AU (drawn greyed) must not set it to 1 and leave every real AU's motion invisible."""
    return exaggeration_factor(np.asarray(disp)[supported_mask(unsupported)])


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
    unidentified = unidentified_aus(arrays, str(npz_path))
    factor = display_factor(disp, unsupported)
    jobs: list[tuple[str, Callable[..., Any], tuple[Any, ...]]] = [
        ("au_solid_panels.png", fig_solid_panels, (neutral, disp, tri, factor, unsupported, unidentified)),
        (
            "au_solid_neutral_vs_activated.png",
            fig_neutral_vs_activated,
            (neutral, disp, tri, factor, COMPARE_AUS, unsupported, unidentified),
        ),
        ("au_compare_overlay.png", fig_compare_overlay, (neutral, disp, tri, factor, unsupported, unidentified)),
        ("au_effect_maps.png", fig_effect_maps, (neutral, disp, tri, scale, unsupported, unidentified)),
        ("pose_views.png", fig_pose_views, (neutral, disp, tri, factor, POSES_DEG, unsupported, unidentified)),
    ]
    if cv is not None and "r2_per_vertex" in cv:
        jobs.append(("r2_per_vertex.png", fig_r2_per_vertex, (neutral, tri, cv["r2_per_vertex"])))
    if cv is not None and ("vertex_error" in cv or "cumulative_error_thresholds" in cv):
        jobs.append(("cumulative_vertex_error.png", fig_cumulative_error, cumulative_curve(cv)))
    return _render_all([(out / name, make, args) for name, make, args in jobs])


def _render(path: Path, make, args) -> Path:
    return save_png(make(*args), path)


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


@dataclass(frozen=True)
class RenderedCard:
    """What :func:`render_card` wrote.

    Attributes
    ----------
    paths : list of Path
        The PNGs (:func:`render_release`), then ``au_directions.json`` and ``au_directions.md``.
    report : dict
        The AU-direction report (:func:`aumesh.card.directions.au_direction_report`); ``report["summary"]`` counts
        the ``pass``, ``doubtful`` and ``fail`` verdicts.
    """

    paths: list[Path]
    report: dict[str, Any]


def render_card(
    npz_path: str | os.PathLike, out_dir: str | os.PathLike, cv_path: str | os.PathLike | None = None
) -> RenderedCard:
    """The visual model card of any release NPZ in the card's format: :func:`render_release`'s figures, plus
    ``au_directions.json`` and ``au_directions.md`` (the FACS direction check), into ``out_dir``.

    Parameters
    ----------
    npz_path : path
        Release NPZ in the card's format (ours or another).
    out_dir : path
        Output folder (created if missing). Files are written atomically.
    cv_path : path, optional
        CV arrays NPZ (``r2_per_vertex``, ``vertex_error`` or the cumulative curve); without it, no R² and error
        figures.

    Returns
    -------
    RenderedCard
        The files written and the AU-direction report.

    Raises
    ------
    FileNotFoundError, KeyError, ValueError
        A missing file, a missing key, an array of the wrong shape (``ReleaseError`` for the release NPZ's).
    """
    from aumesh.card.directions import au_direction_report, report_markdown_table, write_report

    paths = render_release(npz_path, out_dir, cv_path)
    report = au_direction_report(npz_path)
    paths.append(write_report(report, Path(out_dir) / "au_directions.json"))
    paths.append(atomic_write_text(Path(out_dir) / "au_directions.md", report_markdown_table(report)))
    return RenderedCard(paths, report)
