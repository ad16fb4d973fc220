"""viewer.html of a family release (issue 46 item 5) in a real browser (Debian's chromium, headless, Playwright): its
sliders are the family's inputs by name, and a slider moves the mesh as the NPZ's own arithmetic does (numpy)."""

from __future__ import annotations

import numpy as np
import pytest

from aumesh import cli
from family_release_fixture import family_release, numpy_prediction
from test_viewer import FOREHEAD, MOUTH, _box, _changed, _open, _shot, tab  # noqa: F401 - tab: the module's page

# the input each family's test moves (within its training p99, 0.6) and what it moves: the synthetic truth's field
# (jawOpen follows AU26, happiness is AU06 + AU12: mouth and cheeks, never the forehead)
MOVED = {"blendshapes": "jawOpen", "emotions": "happiness"}


@pytest.fixture(scope="module")
def pages(tmp_path_factory, node_tools):
    d = tmp_path_factory.mktemp("family_viewer")
    out = {}
    for family in MOVED:
        npz = family_release(d / f"{family}.npz", family)
        page = d / f"{family}.html"
        assert cli.main(["view", str(npz), "--out", str(page)]) == 0  # `aumesh view NPZ --out FILE`
        out[family] = (dict(np.load(npz, allow_pickle=False)), page)
    return out


@pytest.mark.parametrize("family", list(MOVED))
def test_family_sliders_move_the_mesh_as_predict_does(tab, pages, family):  # noqa: F811
    npz, path = pages[family]
    names = [str(c) for c in npz["feature_columns"]]
    page, problems, requests = _open(tab, path)
    sliders = page.locator('#side input[type="range"]').evaluate_all("els => els.map(e => e.name)")
    assert sliders == [*names, "Pitch", "Yaw", "Roll"]
    assert family in page.locator("#title").inner_text() and family in page.title()
    forehead, mouth = _box(page, FOREHEAD), _box(page, MOUTH)
    neutral = _shot(page, f"viewer_{family}_neutral.png")
    assert neutral.std() > 10  # a face, not a blank canvas
    moved = MOVED[family]
    page.locator(f'input[name="{moved}"]').fill("0.5")
    shot = _shot(page, f"viewer_{family}_{moved}.png")
    assert _changed(neutral, shot, mouth) > 0.05
    assert _changed(neutral, shot, forehead) < 0.002
    x = np.zeros(len(names))
    x[names.index(moved)] = 0.5
    got = np.array(page.evaluate("window.aumeshViewer.mesh()")).reshape(478, 3)
    expected = numpy_prediction(npz, x)[0]
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5 * np.abs(expected).max())
    # with pose: the full design's pose x input terms (the release's coef rows Pitch*<input>, ...)
    page.locator('input[name="Pitch"]').fill("0.2")
    got = np.array(page.evaluate("window.aumeshViewer.mesh()")).reshape(478, 3)
    posed = numpy_prediction(npz, x, [0.2, 0.0, 0.0])[0]
    assert np.abs(posed - expected).max() > 100 * 1e-5 * np.abs(posed).max()  # the pose terms matter here
    np.testing.assert_allclose(got, posed, rtol=0, atol=1e-5 * np.abs(posed).max())
    _shot(page, f"viewer_{family}_{moved}_pitch.png")
    assert problems == [] and requests == []
