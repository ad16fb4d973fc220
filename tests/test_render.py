"""Visual model card: every figure renders from a release NPZ alone, is not blank, errors are clear."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aumesh.card import release_figures, render
from aumesh.core.schema import AU_COLUMNS
from aumesh.geometry import face
from aumesh.model.release_check import ReleaseError
from aumesh.synthetic import truth

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


@pytest.mark.slow
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
        k = AU_COLUMNS.index("AU12")
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


@pytest.mark.slow
def test_cli_render_writes_figures_and_directions(release, tmp_path, capsys):
    """``aumesh render NPZ --out DIR --cv CV`` (:func:`render.render_card`): every figure and the AU-direction report,
    each file it wrote printed; a missing NPZ is a one-line error with exit 2."""
    import json

    from aumesh import cli

    npz, cv = release
    assert cli.main(["render", str(npz), "--out", str(tmp_path), "--cv", str(cv)]) == 0
    out, err = capsys.readouterr()
    report = json.loads((tmp_path / "au_directions.json").read_text())
    assert report["summary"]["pass"] == 20
    written = sorted(p.name for p in tmp_path.iterdir())
    assert written == sorted([*ALWAYS, *WITH_CV, "au_directions.json", "au_directions.md"])
    assert sorted(Path(line).name for line in out.splitlines()) == written
    assert "AU directions: 20 pass, 0 doubtful, 0 fail" in err
    assert cli.main(["render", str(tmp_path / "nope.npz"), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("aumesh render: error:") and "nope.npz" in err and "not found" in err


# ------------------------------------------------------------------ per-AU scales, unsupported AUs (issue 41)
def _exploded(arrays: dict, au: str = "AU09", times: float = 40.0, listed: bool = True, fields: float = 1.0) -> dict:
    """``arrays`` with every AU field scaled by ``fields`` and ``au``'s by ``times`` more; listed unsupported with
    its training p99 (py-feat's v6 keys) when ``listed``."""
    out = dict(arrays)
    coef = out["coef"].astype(np.float64) * fields
    coef[list(out["input_columns"]).index(au)] *= times
    out["coef"] = coef.astype(np.float32)
    if listed:
        out["unsupported_features"] = np.array([au])
        p99 = np.full(len(out["input_columns"]), 0.8, dtype=np.float32)
        p99[list(out["input_columns"]).index(au)] = 0.035
        out["feature_p99"] = p99
    return out


def _panels(fig) -> list[np.ndarray]:
    """Each AU panel's RGB pixels (the axes' box in the drawn canvas), ``AU_COLUMNS`` order."""
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].astype(np.float64) / 255.0
    height = img.shape[0]
    crops = []
    for ax in fig.axes[:20]:
        (x0, y0), (x1, y1) = ax.get_window_extent().get_points()
        crops.append(img[int(height - y1) + 1 : int(height - y0) - 1, int(x0) + 1 : int(x1) - 1])
    return crops


def _hot(panel: np.ndarray) -> int:
    """How many of a panel's pixels are in magma's top fifth (yellow-white, not the white of the background)."""
    r, g, b = panel[..., 0], panel[..., 1], panel[..., 2]
    return int(np.sum((r > 0.95) & (g > 0.7) & (b < 0.8)))


def test_effect_maps_scale_each_au_to_its_own_maximum():
    tpl = 120.0 * face.canonical_template()
    arrays = _exploded(truth.synthetic_release_arrays(tpl), times=40.0)
    neutral, disp, scale = render.face_frame_meshes(arrays)
    tops = release_figures.effect_map_scales(disp, scale)
    # independent route: the coef rows themselves, in release units (a rotation keeps each vertex's norm)
    rows = arrays["coef"][: len(AU_COLUMNS)].astype(np.float64).reshape(20, 3, 478)
    np.testing.assert_allclose(tops, np.linalg.norm(rows, axis=1).max(axis=1), rtol=1e-5)
    fig = release_figures.fig_effect_maps(neutral, disp, face.triangulate(neutral), scale)
    for k, (ax, panel) in enumerate(zip(fig.axes[:20], _panels(fig), strict=True)):
        assert f"max {tops[k]:.3g}" in ax.get_title()
        assert _hot(panel) >= 5, (AU_COLUMNS[k], _hot(panel))  # no panel left black by AU09's scale


def test_unsupported_aus_come_from_the_npz_and_from_implausible_fields():
    arrays = truth.synthetic_release_arrays(120.0 * face.canonical_template())
    _, disp, _ = render.face_frame_meshes(arrays)
    assert render.unsupported_aus(arrays, disp) == {}
    listed = _exploded(arrays, times=1.0)  # listed, field as it was
    assert render.unsupported_aus(listed, render.face_frame_meshes(listed)[1]) == {
        "AU09": "not in training data (p99 0.035)"
    }
    huge = _exploded(arrays, au="AU26", times=40.0, listed=False)  # not listed, but 40x: AU26 is 3.3x the median
    got = render.unsupported_aus(huge, render.face_frame_meshes(huge)[1])
    sizes = np.linalg.norm(render.face_frame_meshes(huge)[1], axis=2).max(axis=1)
    assert (
        list(got) == ["AU26"]
        and got["AU26"] == f"implausible field ({sizes[17] / np.median(sizes):.0f}x the median AU)"
    )


@pytest.mark.slow
def test_an_exploded_au_is_greyed_and_labelled_and_the_other_panels_are_unchanged():
    """Small fields (x0.1: the figures exaggerate them) and AU09 x400 listed unsupported: the shared factor and every
    other panel are those of the release without AU09's explosion, pixel for pixel."""
    arrays = truth.synthetic_release_arrays(120.0 * face.canonical_template())
    normal, exploded = (
        _exploded(arrays, times=1.0, listed=False, fields=0.1),
        _exploded(arrays, times=400.0, fields=0.1),
    )
    drawn = []
    for a in (normal, exploded):
        neutral, disp, _ = render.face_frame_meshes(a)
        unsupported = render.unsupported_aus(a, disp)
        factor = render.display_factor(disp, unsupported)
        drawn.append(
            (factor, release_figures.fig_solid_panels(neutral, disp, face.triangulate(neutral), factor, unsupported))
        )
    (f_normal, fig_normal), (f_exploded, fig_exploded) = drawn
    assert f_normal == f_exploded == render.exaggeration_factor(render.face_frame_meshes(normal)[1]) > 1
    assert render.exaggeration_factor(render.face_frame_meshes(exploded)[1]) == 1.0  # what all AUs would give
    k = AU_COLUMNS.index("AU09")
    before, after = _panels(fig_normal), _panels(fig_exploded)
    for j in range(20):
        if j != k:
            np.testing.assert_array_equal(before[j], after[j], err_msg=AU_COLUMNS[j])

    def skin(p: np.ndarray) -> float:  # skin tones: red > green > blue (not the grey face, not the red label box)
        r, g, b = p[..., 0], p[..., 1], p[..., 2]
        return float(np.mean((r - b > 0.15) & (g - b > 0.05)))

    assert skin(before[k]) > 0.2 and skin(after[k]) < 0.01  # AU09's face drawn grey, not exploded
    assert any("not in training data" in t.get_text() for t in fig_exploded.axes[k].texts)


@pytest.mark.parametrize("name", ["fig_neutral_vs_activated", "fig_compare_overlay", "fig_pose_views"])
def test_every_au_figure_labels_an_unsupported_au(name):
    arrays = truth.synthetic_release_arrays(120.0 * face.canonical_template())
    exploded = _exploded(arrays, au="AU12", times=40.0)  # AU12: in every one of these figures
    neutral, disp, _ = render.face_frame_meshes(exploded)
    unsupported = render.unsupported_aus(exploded, disp)
    make = getattr(release_figures, name)
    factor = render.display_factor(disp, unsupported)
    extra = {
        "fig_neutral_vs_activated": (release_figures.COMPARE_AUS,),
        "fig_pose_views": (release_figures.POSES_DEG,),
    }.get(name, ())
    fig = make(neutral, disp, face.triangulate(neutral), factor, *extra, unsupported)
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert any("not in training data" in t and "0.035" in t for t in texts), texts
    for ax in fig.axes:  # no panel's limits stretched by the 40x field: every face is drawn at the normal size
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        assert max(x1 - x0, y1 - y0) < 3.0, (name, ax.get_title())


# ------------------------------------------------------------------ issue 43: unidentified AUs marked
FLAGS = {"AU10": (0.06, "AU09"), "AU12": (0.095, "AU06")}  # AU12: in every AU figure, the pose views too


def test_unidentified_aus_come_from_the_npz_keys():
    from conftest import identification_keys

    arrays = truth.synthetic_release_arrays(120.0 * face.canonical_template())
    assert render.unidentified_aus(arrays) == {}  # a release from before the screen
    assert render.unidentified_aus({**arrays, **identification_keys({})}) == {}  # screened, nothing flagged
    assert render.unidentified_aus({**arrays, **identification_keys(FLAGS)}) == {
        "AU10": "unidentified (\u03c3* 0.060): use AU09+AU10",
        "AU12": "unidentified (\u03c3* 0.095): use AU06+AU12",
    }


def test_render_release_marks_the_flagged_aus_in_every_au_figure(tmp_path, monkeypatch):
    """What render_release hands each AU figure: the NPZ's flags (the figures are drawn from these arguments)."""
    from conftest import identification_keys

    npz = tmp_path / "flagged.npz"
    np.savez(npz, **truth.synthetic_release_arrays(120.0 * face.canonical_template()), **identification_keys(FLAGS))
    jobs = []
    monkeypatch.setattr(render, "_render_all", lambda j: jobs.extend(j) or [])
    render.render_release(npz, tmp_path / "out")
    assert sorted(p.name for p, _, _ in jobs) == sorted(ALWAYS)
    for _, _, args in jobs:
        assert args[-1] == render.unidentified_aus(np.load(npz)) and list(args[-1]) == ["AU10", "AU12"]


@pytest.mark.parametrize(
    "name", ["fig_solid_panels", "fig_neutral_vs_activated", "fig_compare_overlay", "fig_effect_maps", "fig_pose_views"]
)
@pytest.mark.slow
def test_every_au_figure_marks_an_unidentified_au(name):
    """A flagged AU's panels: the label under its title in orange and a hatch behind the face; no other panel marked."""
    from matplotlib.colors import to_hex

    from aumesh.card.drawing import UNIDENTIFIED

    arrays = truth.synthetic_release_arrays(120.0 * face.canonical_template())
    neutral, disp, scale = render.face_frame_meshes(arrays)
    unidentified = {"AU10": "unidentified (x): use AU09+AU10", "AU12": "unidentified (y): use AU06+AU12"}
    extra = {
        "fig_neutral_vs_activated": (release_figures.COMPARE_AUS, None),
        "fig_pose_views": (release_figures.POSES_DEG, None),
    }.get(name, (None,))
    fig = getattr(release_figures, name)(
        neutral, disp, face.triangulate(neutral), scale if name == "fig_effect_maps" else 1.0, *extra, unidentified
    )
    marked = []
    for ax in fig.axes:
        title = ax.get_title()
        hatched = any(p.get_hatch() for p in ax.patches)
        labelled = [label for label in unidentified.values() if title.endswith("\n" + label)]
        assert hatched == bool(labelled), title  # hatched exactly when labelled
        if labelled:
            assert to_hex(ax.title.get_color()) == to_hex(UNIDENTIFIED)
            au = title.split()[0]
            assert unidentified[au] == labelled[0], title
            marked.append(au)
    expected = {
        "fig_neutral_vs_activated": ["AU12"],
        "fig_pose_views": ["AU12"] * len(release_figures.POSES_DEG),
    }.get(name, ["AU10", "AU12"])
    assert marked == expected
    # without flags, no panel is marked (the release's figures as before)
    plain = getattr(release_figures, name)(
        neutral, disp, face.triangulate(neutral), scale if name == "fig_effect_maps" else 1.0, *extra
    )
    assert not any(p.get_hatch() for ax in plain.axes for p in ax.patches)
    assert not any("unidentified" in ax.get_title() for ax in plain.axes)
