"""viewer.html in a real browser: Debian's chromium, headless, driven by Playwright (no browser download)."""

from __future__ import annotations

import time

import numpy as np
import pytest

from aumesh import cli
from aumesh.core.schema import INPUT_COLUMNS, flatten_axis_major
from aumesh.export import viewer
from aumesh.model.release import load_npz
from conftest import SCREENSHOTS as SHOTS
from conftest import upright_truth_release

FOREHEAD = (10, 151, 9, 67, 297, 109, 338, 103, 332)
MOUTH = (61, 291, 0, 17, 13, 14, 78, 308, 39, 269, 181, 405)


@pytest.fixture(scope="module")
def page_file(tmp_path_factory, node_tools):
    d = tmp_path_factory.mktemp("viewer")
    npz = upright_truth_release(d / "release.npz")
    assert cli.main(["view", str(npz), "--out", str(d / "face.html")]) == 0  # `aumesh view NPZ --out FILE`
    return npz, d / "face.html"


@pytest.fixture(scope="module")
def tab(browser):
    """One offline page (no network) for the module's browser tests, each of which loads its file afresh in it
    (``_open``: a new document, so no page state carries over). Reusing the tab's renderer process, which keeps
    three.js compiled, halves each load of the 3 MB page against a new context per test (~0.3 s of ~0.65 s).
    The page's problems and outside requests go to ``log``, emptied by each ``_open``."""
    context = browser.new_context(offline=True)
    page = context.new_page()
    log: dict[str, list] = {"problems": [], "requests": []}
    page.on("console", lambda m: log["problems"].append(f"console {m.type}: {m.text}") if m.type == "error" else None)
    page.on("pageerror", lambda e: log["problems"].append(f"page error: {e}"))
    # a dialog (alert) means embedded text ran as script; dismissed so the page never blocks
    page.on("dialog", lambda d: (log["problems"].append(f"dialog: {d.message}"), d.dismiss()))
    page.on("request", lambda r: log["requests"].append(r.url) if not r.url.startswith(("file:", "data:")) else None)
    yield page, log
    context.close()


def _open(tab, path, viewport=(1100, 700), wait_ready=True):
    """``tab``'s page showing ``path`` (a fresh document) in a ``viewport`` window: ``(page, problems, requests)``;
    without ``wait_ready``, as soon as the browser has the document (the caller waits for what it needs)."""
    page, log = tab
    page.set_viewport_size({"width": viewport[0], "height": viewport[1]})
    # the previous document unloaded first: an alert or error its timers still raise lands in the old log, not ours
    page.goto("about:blank")
    log["problems"], log["requests"] = problems, requests = [], []
    page.goto(path.as_uri(), wait_until="load" if wait_ready else "commit")
    if wait_ready:
        page.wait_for_function("window.aumeshViewer && window.aumeshViewer.ready", timeout=60_000)
    return page, problems, requests


def _wait_for(page, condition, timeout=60.0):
    """Let ``page`` deliver its events (dialogs, errors) until ``condition()`` holds, or ``timeout`` seconds pass
    (a cap for a page that never gets there, as the pages' ``ready`` wait: not a time the test expects)."""
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        page.wait_for_timeout(10)


def _shot(page, name):
    import io

    from PIL import Image

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


def test_sliders_move_the_mouth_not_the_forehead(tab, page_file):
    npz_path, path = page_file
    page, problems, requests = _open(tab, path)
    assert page.locator('#side input[type="range"]').evaluate_all("els => els.map(e => e.name)") == list(INPUT_COLUMNS)
    forehead, mouth = _box(page, FOREHEAD), _box(page, MOUTH)
    neutral = _shot(page, "viewer_neutral.png")
    assert neutral.std() > 10  # a face, not a blank canvas
    for au in ("AU12", "AU26"):
        page.locator(f'input[name="{au}"]').fill("1")
        moved = _shot(page, f"viewer_{au}.png")
        assert _changed(neutral, moved, mouth) > 0.05, au
        assert _changed(neutral, moved, forehead) < 0.002, au
        # the page's mesh is the card's prediction
        x = np.zeros(23)
        x[INPUT_COLUMNS.index(au)] = 1.0  # noqa: E702
        m = np.load(npz_path, allow_pickle=False)
        expected = x @ m["coef"].astype(np.float64) + m["intercept"].astype(np.float64)
        got = flatten_axis_major(np.array(page.evaluate("window.aumeshViewer.mesh()")).reshape(478, 3))
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5 * np.abs(expected).max())
        page.click("#reset")
        np.testing.assert_array_equal(_shot(page, "viewer_reset.png"), neutral)
    assert problems == [] and requests == []


def _pose_release(tmp_path, metadata=None, card_text=""):
    """Release arrays with pose x AU terms (``coef_full``): the synthetic truth's AU rows, random pose terms."""
    from aumesh.core.schema import feature_columns
    from aumesh.model.release import release_arrays

    truth = load_npz(upright_truth_release(tmp_path / "truth.npz"))
    columns = feature_columns(True, True)
    rng = np.random.default_rng(0)
    coef = rng.normal(0.0, 2.0, (1434, len(columns)))
    coef[:, :20] = truth["coef"][:20].T
    reference = {k: truth[k] for k in ("mean_aligned_mesh", "mean_low_au_mesh", "reference_anchors", "anchor_indices")}
    return release_arrays(
        coef, truth["intercept"], columns, 83, reference, card_text=card_text, metadata=metadata or {}
    )


@pytest.fixture(scope="module")
def pose_page(tmp_path_factory, node_tools):
    """``(arrays, viewer.html)`` of :func:`_pose_release`, built once: the tests only read them."""
    d = tmp_path_factory.mktemp("pose")
    arrays = _pose_release(d)
    return arrays, viewer.write_viewer(arrays, d / viewer.VIEWER_NAME)


def test_pose_sliders_use_coef_full(tab, pose_page):
    """With pose x AU terms the page's mesh is the pose-conditioned prediction (aumesh.predict_mesh)."""
    import aumesh

    arrays, path = pose_page
    page, problems, _ = _open(tab, path)
    page.locator('input[name="AU12"]').fill("0.5")
    page.locator('input[name="Pitch"]').fill("0.3")
    page.locator('input[name="Roll"]').fill("-0.2")
    got = np.array(page.evaluate("window.aumeshViewer.mesh()")).reshape(478, 3)
    expected = aumesh.predict_mesh(arrays, {"AU12": 0.5}, pose=[0.3, 0.0, -0.2])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-5 * np.abs(expected).max())
    assert np.abs(expected - aumesh.predict_mesh(arrays, {"AU12": 0.5})).max() > 1.0  # pose terms matter here
    _shot(page, "viewer_pose.png")
    assert problems == []


# ---------------------------------------------------------------- issue 35: a viewer people can use
VIEW = (1280, 720)


def _ranges_visible(page):
    """Each slider's box, and whether the element at its centre is the slider itself (not covered, not clipped)."""
    return page.evaluate("""() => [...document.querySelectorAll('#side input[type=range]')].map((e) => {
        const r = e.getBoundingClientRect();
        const hit = document.elementFromPoint(r.left + r.width / 2, r.top + r.height / 2);
        return {name: e.name, top: r.top, left: r.left, bottom: r.bottom, right: r.right, hit: hit === e};
    })""")


def test_layout_fills_the_window_and_every_slider_shows_at_1280x720(tab, page_file):
    from aumesh.core.schema import AU_NAMES

    _, path = page_file
    page, problems, requests = _open(tab, path, VIEW)
    boxes = _ranges_visible(page)
    assert [b["name"] for b in boxes] == list(INPUT_COLUMNS)
    for b in boxes:  # inside the window, drawn, nothing scrolled
        assert b["top"] >= 0 and b["left"] >= 0 and b["bottom"] <= VIEW[1] and b["right"] <= VIEW[0], b
        assert b["hit"], f"{b['name']} is covered or clipped"
    scroll = page.evaluate(
        "[document.scrollingElement.scrollHeight, document.scrollingElement.scrollWidth, "
        "document.getElementById('side').scrollTop]"
    )
    assert scroll == [VIEW[1], VIEW[0], 0]  # the page itself never scrolls
    # FACS names beside the codes
    rows = page.locator("#aus .row").evaluate_all("""rows => rows.map((r) => {
        const code = r.querySelector('.code'), name = r.querySelector('.name');
        return [code.textContent, name.textContent, name.scrollWidth <= name.clientWidth];
    })""")
    assert rows == [[au, name, True] for au, name in AU_NAMES.items()]  # each name whole, not cut by an ellipsis
    # the canvas fills what the panel leaves, and follows the window
    side = page.evaluate("document.getElementById('side').getBoundingClientRect().width")
    canvas = page.locator("canvas").bounding_box()
    assert (canvas["x"], canvas["y"]) == (0, 0)
    assert abs(canvas["width"] + side - VIEW[0]) <= 1 and canvas["height"] == VIEW[1]
    page.set_viewport_size({"width": 1000, "height": 600})
    page.wait_for_function("document.querySelector('canvas').getBoundingClientRect().height === 600")
    assert abs(page.locator("canvas").bounding_box()["width"] + side - 1000) <= 1
    assert problems == [] and requests == []


def _support_ranges() -> dict:
    """Training ranges of a small set: AU09 never expressed (p99 0.03, max 0.035), AU12 at most 0.6, the rest 0..1."""
    ranges = {
        c: {"min": 0.0, "p1": 0.0, "p50": 0.2, "p99": 0.95, "max": 1.0, "active_fraction": 0.5} for c in INPUT_COLUMNS
    }
    ranges["AU09"] = {"min": 0.0, "p1": 0.0, "p50": 0.01, "p99": 0.03, "max": 0.035, "active_fraction": 0.0}
    ranges["AU12"] = {"min": 0.0, "p1": 0.0, "p50": 0.1, "p99": 0.5, "max": 0.6, "active_fraction": 0.3}
    return ranges


def test_sliders_mark_the_range_beyond_the_training_data(tab, tmp_path, page_file):
    """A release that records its data's ranges: the track beyond each AU's training max is hatched from that value,
    the value turns orange past it, the AU the data never expressed says so, and every slider still shows at
    1280 x 720 and takes the mouse over the hatch. A release without ranges marks nothing."""
    arrays = _pose_release(tmp_path, metadata={"data": {"input_ranges": _support_ranges()}})
    assert arrays["unsupported_features"].tolist() == ["AU09"]
    path = viewer.write_viewer(arrays, tmp_path / "support.html")
    page, problems, requests = _open(tab, path, VIEW)
    marks = page.evaluate("""() => [...document.querySelectorAll('#aus .row')].map((r) => {
        const input = r.querySelector('input').getBoundingClientRect(), hatch = r.querySelector('.beyond');
        const h = hatch && hatch.getBoundingClientRect();
        return [r.querySelector('.code').textContent, r.dataset.beyond ?? null, r.dataset.support ?? null,
                r.querySelector('.name').textContent, h ? (h.left - input.left) / input.width : null,
                h ? Math.abs(h.right - input.right) : null];
    })""")
    by_au = {m[0]: m[1:] for m in marks}
    assert {au for au, m in by_au.items() if m[0] is not None} == {"AU09", "AU12"}
    assert float(by_au["AU12"][0]) == 0.6 and float(by_au["AU09"][0]) == 0.035
    assert by_au["AU12"][3] == pytest.approx(0.6, abs=0.01) and by_au["AU12"][4] <= 1  # hatched from 0.6 to the end
    assert by_au["AU09"][3] == pytest.approx(0.035, abs=0.01)
    assert by_au["AU09"][1:3] == ["unsupported", "not in training data"]
    assert by_au["AU12"][1:3] == [None, "Lip corner puller"]
    for b in _ranges_visible(page):  # every slider whole in the window and on top of its hatch
        assert b["bottom"] <= VIEW[1] and b["hit"], b
    output = page.locator('#aus .row:has(input[name="AU12"]) output')
    page.locator('input[name="AU12"]').fill("0.5")
    assert "beyond-data" not in (output.get_attribute("class") or "")
    page.locator('input[name="AU12"]').fill("0.8")
    assert "beyond-data" in output.get_attribute("class")
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.locator("#side").screenshot(path=str(SHOTS / "viewer_support_sliders.png"))
    assert problems == [] and requests == []

    _, plain = page_file  # a release that records no ranges: nothing marked
    page, problems, _ = _open(tab, plain, VIEW)
    assert page.evaluate("document.querySelectorAll('#aus .row[data-beyond], #aus .row.unsupported').length") == 0
    assert problems == []


@pytest.mark.slow
def test_drag_orbits_and_wheel_zooms(tab, page_file):
    _, path = page_file
    page, problems, requests = _open(tab, path, VIEW)
    box = page.locator("canvas").bounding_box()
    cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    mesh0, cam0, front = (
        page.evaluate("window.aumeshViewer.mesh()"),
        page.evaluate("window.aumeshViewer.camera()"),
        _shot(page, "viewer_front_1280.png"),
    )
    page.mouse.move(cx, cy)
    page.mouse.down()
    for k in range(1, 11):  # a real drag: pointer events in steps, as a hand would
        page.mouse.move(cx + 22 * k, cy + 4 * k)
    page.mouse.up()
    cam1 = page.evaluate("window.aumeshViewer.camera()")
    turned = _shot(page, "viewer_orbit_canvas.png")
    (SHOTS / "viewer_orbit_1280x720.png").write_bytes(page.screenshot())  # the whole window, for a person
    p0, p1 = np.array(cam0["position"]), np.array(cam1["position"])
    angle = np.degrees(np.arccos(np.clip(p0 @ p1 / np.linalg.norm(p0) / np.linalg.norm(p1), -1, 1)))
    assert angle > 20, angle  # the camera went round the face ...
    assert cam1["distance"] == pytest.approx(cam0["distance"], rel=1e-6)  # ... at the same distance
    assert np.mean(np.abs(front - turned).sum(axis=-1) > 30) > 0.05  # and the picture changed
    assert page.evaluate("window.aumeshViewer.mesh()") == mesh0  # orbit moves the camera, never the model
    # the wheel zooms: the camera comes closer and the face grows on the canvas
    spread0 = np.ptp(np.array([page.evaluate(f"window.aumeshViewer.project({i})") for i in FOREHEAD + MOUTH]), axis=0)
    page.mouse.move(cx, cy)
    page.mouse.wheel(0, -400)
    page.wait_for_function(f"window.aumeshViewer.camera().distance < {cam1['distance'] * 0.95}")
    spread1 = np.ptp(np.array([page.evaluate(f"window.aumeshViewer.project({i})") for i in FOREHEAD + MOUTH]), axis=0)
    assert (spread1 > spread0 * 1.05).all(), (spread0, spread1)
    zoomed = _shot(page, "viewer_zoom_canvas.png")
    assert np.mean(np.abs(turned - zoomed).sum(axis=-1) > 30) > 0.05
    # Reset brings the front view back, pixel for pixel
    page.click("#reset")
    np.testing.assert_array_equal(_shot(page, "viewer_reset_1280.png"), front)
    assert problems == [] and requests == []


@pytest.fixture
def clipboard(tab):
    """The clipboard allowed in ``tab``'s context for one test; withdrawn after it, for the tab's next tests."""
    tab[0].context.grant_permissions(["clipboard-read", "clipboard-write"])
    yield
    tab[0].context.clear_permissions()


def test_copied_json_round_trips_through_predict_mesh(tab, pose_page, clipboard):
    """ "Copy as JSON" puts the current values on the clipboard; predict_mesh(m, json.loads(text)) is the page's mesh."""
    import json

    import aumesh

    arrays, path = pose_page  # pose x AU terms: the pose values in the JSON change the shape
    page, problems, _ = _open(tab, path, VIEW)
    settings = {"AU04": "0.15", "AU12": "0.37", "AU26": "0.8", "Pitch": "0.21", "Yaw": "-0.33", "Roll": "0.12"}
    for name, value in settings.items():
        page.locator(f'input[name="{name}"]').fill(value)
    page.click("#copy-json")
    page.wait_for_function("document.getElementById('copy-json').dataset.json")
    text = page.evaluate("navigator.clipboard.readText()")  # what the user pastes
    assert text == page.get_attribute("#copy-json", "data-json") == page.evaluate("window.aumeshViewer.json()")
    values = json.loads(text)
    assert list(values) == list(INPUT_COLUMNS)
    assert {k: v for k, v in values.items() if v} == {k: float(v) for k, v in settings.items()}
    got = np.array(page.evaluate("window.aumeshViewer.mesh()")).reshape(478, 3)
    expected = aumesh.predict_mesh(arrays, values)
    # the page computes in float64 from the float32 arrays and stores float32 positions: half a float32 ulp apart
    np.testing.assert_allclose(got, expected, rtol=0, atol=2 * np.finfo(np.float32).eps * np.abs(expected).max())
    assert (
        np.abs(expected - aumesh.predict_mesh(arrays, {k: v for k, v in values.items() if k.startswith("AU")})).max()
        > 1.0
    )  # the JSON's pose values matter here
    # no clipboard (blocked): the text is shown selected instead, the same JSON
    page.evaluate("() => { navigator.clipboard.writeText = () => Promise.reject(new Error('blocked')); }")
    page.click("#copy-json")
    page.wait_for_function("document.getElementById('json-text').style.display === 'block'")
    assert page.input_value("#json-text") == text
    assert problems == []


def test_png_snapshot_downloads_the_canvas(tab, page_file, tmp_path):
    import io

    from PIL import Image

    _, path = page_file
    page, problems, _ = _open(tab, path, VIEW)
    page.locator('input[name="AU12"]').fill("1")
    with page.expect_download() as info:
        page.click("#snapshot")
    download = info.value
    assert download.suggested_filename.endswith(".png")
    saved = tmp_path / download.suggested_filename
    download.save_as(saved)
    png = np.asarray(Image.open(saved).convert("RGB"), dtype=np.int16)
    size = page.evaluate("[document.querySelector('canvas').width, document.querySelector('canvas').height]")
    assert (png.shape[1], png.shape[0]) == tuple(size)
    shown = np.asarray(Image.open(io.BytesIO(page.locator("canvas").screenshot())).convert("RGB"), dtype=np.int16)
    assert png.std() > 10 and np.abs(png - shown).mean() < 1.0  # the picture on screen, not a blank buffer
    assert problems == []


# ---------------------------------------------------------------- issue 34: hostile strings stay text
HOSTILE = ("</script><script>alert(1)</script>", "<!--<script>", "<img src=x onerror=alert(1)>")


def _hostile_metadata(text):
    """model_card.json as the release stage writes it, with ``text`` in every string a user, the data or MLflow sets."""
    return {
        "cv": {"r2_mean": 0.5, "r2_std": 0.01, "mae_mean": 1.0, "r2_folds": [0.49, 0.5, 0.51]},
        "model": {"n_components": 83},
        "data": {"n_frames": 1000, "n_videos": 4},
        "config": {"features": {"name": text}, "preprocess": {"target": text}, "cv": {"group": text}},
        "provenance": {"git_commit": text},
        "mlflow": {"run_id": text},
        "promotion": {
            "run_id": text,
            "run_name": text,
            "parent_run_id": text,
            "criterion": text,
            "compared": text,
            "config_overrides": [text, text],
            "registered_model": text,
            "model_version": text,
            "alias": text,
        },
        "source": text,
    }


def test_script_json_escapes_what_could_leave_the_script():
    """Fast, no browser: the embedded JSON has none of < > & U+2028 U+2029 and parses back to the same text."""
    import json

    from aumesh.card.directions import FACS_EXPECTATIONS
    from aumesh.core.schema import AU_COLUMNS, AU_NAMES

    for text in HOSTILE + ("a & b", "line\u2028sep\u2029par", "</SCRIPT >", "]]>"):
        out = viewer.script_json({"k": [text]})
        assert not set(out) & set("<>&\u2028\u2029"), out
        assert json.loads(out) == {"k": [text]}
    assert tuple(AU_NAMES) == AU_COLUMNS and all(FACS_EXPECTATIONS[a]["name"] == AU_NAMES[a] for a in AU_COLUMNS)


def test_page_source_holds_no_hostile_markup(tmp_path):
    """The page's source: exactly the template's three <script> elements, whatever the card's strings hold."""
    modules = {"three": "data:,", viewer.CORE_SPECIFIER: "data:,", viewer.ORBIT_SPECIFIER: "data:,"}
    for text in HOSTILE:
        arrays = _pose_release(tmp_path, _hostile_metadata(text), card_text=text)
        html = viewer.viewer_html(arrays, source=text, modules=modules)
        assert html.lower().count("<script") == 3 and html.lower().count("</script") == 3
        assert "<!--" not in html and "<img" not in html and text not in html
        assert "Lip corner puller" in html and html.isascii()  # no encoding question when the file is written


@pytest.mark.slow
@pytest.mark.parametrize("text", HOSTILE, ids=["close-script", "comment-script", "img-onerror"])
def test_hostile_strings_show_literally(tab, tmp_path, node_tools, text):
    """Issue 34: markup in every embedded field (card, run names, promotion, config, source) stays text."""
    import aumesh

    metadata = _hostile_metadata(text)
    arrays = _pose_release(tmp_path, metadata, card_text=text)
    path = viewer.write_viewer(arrays, tmp_path / viewer.VIEWER_NAME, source=text)
    # a small canvas: 23 renders in software GL; nothing checked here depends on its size
    page, problems, requests = _open(tab, path, (400, 300))
    # the text, literally, in every row that carries it
    cells = page.locator("#card tr").evaluate_all("rows => rows.map(r => [...r.cells].map(c => c.textContent))")
    assert [tuple(c) for c in cells] == viewer.card_rows(metadata)
    assert sum(text in value for _, value in cells) == 12  # 3 config, commit, 2 runs, sweep, 4 promotion, source
    assert page.text_content("#source") == f"release: {text}"
    # no element came from the text
    assert page.evaluate("document.scripts.length") == 3 and page.evaluate("document.images.length") == 0
    # every slider works: each moves the mesh, and the mesh is the model's prediction
    assert page.locator('#side input[type="range"]').count() == len(INPUT_COLUMNS)
    moved = "window.aumeshViewer.mesh().reduce((s, v, i) => s + v * (1 + (i % 7)), 0)"  # a cheap fingerprint
    before = page.evaluate(moved)
    for name in INPUT_COLUMNS:  # each slider's "after" is the next one's "before": nothing else moves the mesh
        page.locator(f'input[name="{name}"]').fill("0.3")
        after = page.evaluate(moved)
        assert after != before, name
        before = after
    got = np.array(page.evaluate("window.aumeshViewer.mesh()")).reshape(478, 3)
    expected = aumesh.predict_mesh(arrays, dict.fromkeys(INPUT_COLUMNS, 0.3))
    np.testing.assert_allclose(got, expected, rtol=0, atol=2 * np.finfo(np.float32).eps * np.abs(expected).max())
    # no element came from the text (checked above), so none can fire later; what the page queued while it loaded
    # (errors, dialogs) is delivered before a task queued after it, and a frame (no wall-clock wait: the page's own
    # queue, however slow the machine)
    page.evaluate("() => new Promise((done) => setTimeout(() => requestAnimationFrame(() => done()), 0))")
    assert problems == [] and requests == []
    # the dialog check can fail: a script that alerts is caught
    with page.expect_event("dialog"):
        page.evaluate("setTimeout(() => alert('control'), 0)")
    _wait_for(page, lambda: problems)
    assert problems == ["dialog: control"]


def test_unescaped_json_would_run_the_text(tab, tmp_path, node_tools, monkeypatch):
    """Control: with plain json.dumps (no escaping) the same text closes the script and runs its own:
    the browser test above can fail."""
    import json

    monkeypatch.setattr(viewer, "script_json", json.dumps)
    text = HOSTILE[0]
    arrays = _pose_release(tmp_path, _hostile_metadata(text))
    path = viewer.write_viewer(arrays, tmp_path / viewer.VIEWER_NAME, source=text)
    page, problems, _ = _open(tab, path, VIEW, wait_ready=False)  # the page may never be ready
    _wait_for(page, lambda: "dialog: 1" in problems)
    assert "dialog: 1" in problems
