"""Visual model card: every figure renders from a release NPZ alone, is not blank, errors are clear."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aumesh.card import render
from aumesh.data import truth
from aumesh.geometry import face
from aumesh.model.inference import ReleaseError

ALWAYS = (
    "au_solid_panels.png",
    "au_solid_neutral_vs_activated.png",
    "au_compare_overlay.png",
    "au_effect_maps.png",
    "pose_views.png",
)
WITH_CV = ("r2_per_vertex.png", "cumulative_vertex_error.png")


def _pixel_std(path) -> float:
    from matplotlib.image import imread

    img = imread(path)[..., :3]
    return float(img.std())


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    """Synthetic-truth release in py-feat-like pixel space: rotated, scaled, translated, y down."""
    d = tmp_path_factory.mktemp("release")
    R = Rotation.from_euler("xyz", [0.1, -0.2, 0.15]).as_matrix()
    tpl = 120.0 * face.canonical_template() @ R.T + np.array([320.0, 240.0, 0.0])
    npz = d / "release.npz"
    np.savez(npz, **truth.synthetic_release_arrays(tpl))
    rng = np.random.default_rng(0)
    cv = d / "cv.npz"
    np.savez(cv, r2_per_vertex=rng.uniform(0.0, 0.4, 478), vertex_error=rng.gamma(3.0, 0.1, (200, 478)))
    return npz, cv


@pytest.fixture(scope="module")
def rendered(release, tmp_path_factory):
    """Every figure of :func:`release` drawn once for the module by forked worker processes (3 "cores"), as
    ``render_release`` draws them on a multi-core machine: (out folder, paths)."""
    npz, cv = release
    out = tmp_path_factory.mktemp("rendered") / "out"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(render.os, "cpu_count", lambda: 3)
        return out, render.render_release(npz, out, cv_path=cv)


def test_render_release_writes_every_figure_non_blank(rendered):
    out, paths = rendered
    assert sorted(p.name for p in paths) == sorted(ALWAYS + WITH_CV)
    for p in paths:
        assert p.is_file() and p.stat().st_size > 10_000, p.name
        assert _pixel_std(p) > 0.05, f"{p.name} looks uniform"
    assert not list(out.glob(".*"))  # no temp files left behind


def test_figures_drawn_in_worker_processes_equal_those_drawn_in_process(release, rendered, tmp_path, monkeypatch):
    """The figures are drawn on every core (forked workers); the bytes are those of drawing them one by one."""
    npz, cv = release
    _, parallel = rendered
    monkeypatch.setattr(render.os, "cpu_count", lambda: 1)
    serial = render.render_release(npz, tmp_path / "serial", cv_path=cv)
    assert [p.name for p in parallel] == [p.name for p in serial]
    for a, b in zip(parallel, serial, strict=True):
        assert a.read_bytes() == b.read_bytes(), a.name


@pytest.mark.slow  # another full render (~4 s of CPU) for the choice of figures
def test_without_cv_no_cv_figures(release, tmp_path):
    paths = render.render_release(release[0], tmp_path)
    assert sorted(p.name for p in paths) == sorted(ALWAYS)


@pytest.mark.slow  # another full render (~4 s of CPU)
def test_precomputed_cumulative_curve_accepted(release, tmp_path):
    cv = tmp_path / "curve.npz"
    t = np.linspace(0, 1, 50)
    np.savez(cv, cumulative_error_thresholds=t, cumulative_error_fraction=t**0.5)
    paths = render.render_release(release[0], tmp_path / "o", cv_path=cv)
    assert "cumulative_vertex_error.png" in {p.name for p in paths}


def test_frontal_view_has_up_at_top_for_y_down_and_y_up_releases():
    tpl = face.canonical_template()
    for mesh in (tpl, tpl * np.array([1.0, -1.0, -1.0])):
        arrays = truth.synthetic_release_arrays(mesh)
        neutral, disp, _ = render.face_frame_meshes(arrays)
        assert neutral[10, 1] < neutral[152, 1]  # forehead drawn above chin (plotted as -y)
        assert neutral[263, 0] > neutral[33, 0]  # subject's left on image right
        assert neutral[1, 2] == neutral[:, 2].min()
        k = render.AU_COLUMNS.index("AU12")
        assert disp[k, 291, 1] < 0  # smile corners go up on screen


def test_exaggeration_factor_only_for_small_effects():
    assert render.exaggeration_factor(np.full((2, 3, 3), 0.05)) == 1.0
    f = render.exaggeration_factor(np.full((2, 3, 3), 0.002))
    assert f > 1 and f * 0.002 * np.sqrt(3) >= render.TARGET_VISIBLE


@pytest.mark.parametrize("key", ["coef", "intercept", "mean_aligned_mesh", "input_columns"])
def test_missing_key_error_names_key_and_file(tmp_path, key):
    arrays = truth.synthetic_release_arrays()
    del arrays[key]
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    with pytest.raises(ReleaseError, match=key) as exc:
        render.render_release(bad, tmp_path / "out")
    assert "bad.npz" in str(exc.value)


def test_cli_main_writes_figures_and_directions(release, tmp_path, capsys):
    import json

    npz, cv = release
    assert render.main([str(npz), "--out", str(tmp_path), "--cv", str(cv)]) == 0
    report = json.loads((tmp_path / "au_directions.json").read_text())
    assert report["summary"]["pass"] == 20
    assert (tmp_path / "au_directions.md").is_file()
    assert render.main([str(tmp_path / "nope.npz"), "--out", str(tmp_path)]) == 2
    assert "not found" in capsys.readouterr().err
