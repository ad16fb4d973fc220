"""viewer.html in a real browser: Debian's chromium, headless, driven by Playwright (no browser download)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import upright_truth_release
from aumesh.data.schema import INPUT_COLUMNS, flatten_axis_major
from aumesh import cli
from aumesh.export import viewer
from aumesh.model.release import load_npz

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run"]
FOREHEAD = (10, 151, 9, 67, 297, 109, 338, 103, 332)
MOUTH = (61, 291, 0, 17, 13, 14, 78, 308, 39, 269, 181, 405)
SHOTS = Path(__file__).resolve().parents[1] / "build" / "test-screenshots"  # kept for a person to look at


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} not installed (apt-get install chromium; .ci/run does it)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def page_file(tmp_path_factory, node_tools):
    d = tmp_path_factory.mktemp("viewer")
    npz = upright_truth_release(d / "release.npz")
    assert cli.main(["view", str(npz), "--out", str(d / "face.html")]) == 0  # `aumesh view NPZ --out FILE`
    return npz, d / "face.html"


def _open(browser, path):
    context = browser.new_context(viewport={"width": 1100, "height": 700}, offline=True)  # no network at all
    page = context.new_page()
    problems = []
    page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
    page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    requests = []
    page.on("request", lambda r: requests.append(r.url) if not r.url.startswith(("file:", "data:")) else None)
    page.goto(path.as_uri())
    page.wait_for_function("window.aumeshViewer && window.aumeshViewer.ready", timeout=60_000)
    return page, problems, requests


def _shot(page, name):
    from PIL import Image
    import io

    SHOTS.mkdir(parents=True, exist_ok=True)
    png = page.locator("canvas").screenshot()
    (SHOTS / name).write_bytes(png)
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def _box(page, indices, pad=6):
    pts = np.array([page.evaluate(f"window.aumeshViewer.project({i})") for i in indices])
    (x0, y0), (x1, y1) = pts.min(axis=0) - pad, pts.max(axis=0) + pad
    return slice(int(max(y0, 0)), int(y1) + 1), slice(int(max(x0, 0)), int(x1) + 1)


def _changed(a, b, box):
    return float(np.mean(np.abs(a[box] - b[box]).sum(axis=-1) > 30))


def test_sliders_move_the_mouth_not_the_forehead(browser, page_file):
    npz_path, path = page_file
    page, problems, requests = _open(browser, path)
    assert page.locator('input[type="range"]').evaluate_all("els => els.map(e => e.name)") == list(INPUT_COLUMNS)
    forehead, mouth = _box(page, FOREHEAD), _box(page, MOUTH)
    neutral = _shot(page, "viewer_neutral.png")
    assert neutral.std() > 10  # a face, not a blank canvas
    for au in ("AU12", "AU26"):
        page.locator(f'input[name="{au}"]').fill("1")
        moved = _shot(page, f"viewer_{au}.png")
        assert _changed(neutral, moved, mouth) > 0.05, au
        assert _changed(neutral, moved, forehead) < 0.002, au
        # the page's mesh is the card's prediction
        x = np.zeros(23); x[INPUT_COLUMNS.index(au)] = 1.0  # noqa: E702
        m = np.load(npz_path, allow_pickle=False)
        expected = x @ m["coef"].astype(np.float64) + m["intercept"].astype(np.float64)
        got = flatten_axis_major(np.array(page.evaluate("window.aumeshViewer.mesh()")).reshape(478, 3))
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5 * np.abs(expected).max())
        page.click("#reset")
        np.testing.assert_array_equal(_shot(page, "viewer_reset.png"), neutral)
    assert problems == [] and requests == []
    page.close()


def test_pose_sliders_use_coef_full(browser, tmp_path, node_tools):
    """With pose x AU terms the page's mesh is the pose-conditioned prediction (aumesh.predict_mesh)."""
    import aumesh
    from aumesh.data.schema import feature_columns
    from aumesh.model.release import release_arrays

    truth = load_npz(upright_truth_release(tmp_path / "truth.npz"))
    columns = feature_columns(True, True)
    rng = np.random.default_rng(0)
    coef = rng.normal(0.0, 2.0, (1434, len(columns)))
    coef[:, :20] = truth["coef"][:20].T
    reference = {k: truth[k] for k in ("mean_aligned_mesh", "mean_low_au_mesh", "reference_anchors", "anchor_indices")}
    arrays = release_arrays(coef, truth["intercept"], columns, 83, reference, card_text="", metadata={})
    path = viewer.write_viewer(arrays, tmp_path / viewer.VIEWER_NAME)
    page, problems, _ = _open(browser, path)
    page.locator('input[name="AU12"]').fill("0.5")
    page.locator('input[name="Pitch"]').fill("0.3")
    page.locator('input[name="Roll"]').fill("-0.2")
    got = np.array(page.evaluate("window.aumeshViewer.mesh()")).reshape(478, 3)
    expected = aumesh.predict_mesh(arrays, {"AU12": 0.5}, pose=[0.3, 0.0, -0.2])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5 * np.abs(expected).max())
    assert np.abs(expected - aumesh.predict_mesh(arrays, {"AU12": 0.5})).max() > 1.0  # pose terms matter here
    _shot(page, "viewer_pose.png")
    assert problems == []
    page.close()
