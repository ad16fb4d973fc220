"""`aumesh animate`: one video of a py-feat table as an animated glTF whose samples are the model's meshes.

The table is the py-feat-shaped generator's (MPDetector CSV: ~2,045 columns, a background face in some frames),
edited as py-feat writes what the tests need: no-face rows for a short and a long gap, and frames missing as
``skip_frames`` leaves them. Expectations come from the table itself (pandas), the GLB from a parser written from
the spec (tests/test_gltf.py's, not aumesh's writer), the mesh from ``aumesh.predict_mesh``.
"""

from __future__ import annotations

import gzip
import json
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

import aumesh
from aumesh.cli import main
from aumesh.core.schema import AU_COLUMNS, N_VERTICES, POSE_COLUMNS
from aumesh.data.clip import MAX_GAP_S, bridge, fps_from_approx_time, read_clip, smooth
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from aumesh.synthetic.tables import SynthSpec
from conftest import REPO, upright_truth_release
from test_gltf import parse_glb

VIDEO = "vid000000"
SHORT_GAP = (20, 23)  # frames [20, 23) without a face: neighbours 4/25 s apart -> interpolated
LONG_GAP = (50, 70)  # 20 frames: neighbours 21/25 s apart -> held
SKIPPED = (100, 110)  # frames py-feat never wrote (skip_frames)
EPS32 = np.finfo(np.float32).eps


#: py-feat's MPDetector row for a frame without a face: every measurement NaN, FaceScore and the face box 0
KEPT_ON_NO_FACE = ("input", "frame", "approx_time", "FrameHeight", "FrameWidth")
ZERO_ON_NO_FACE = ("FaceScore", "FaceRectX", "FaceRectY", "FaceRectWidth", "FaceRectHeight")


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    """``(csv path, DataFrame)``: two videos; video 0 with the gaps above and frames with two faces."""
    d = tmp_path_factory.mktemp("animate")
    summary = write_pyfeat_tables(
        d / "raw", SynthSpec(n_frames=360, n_videos=2, seed=3), detector="mp", no_face_rate=0.0, extra_face_rate=0.2
    )
    df = pd.read_csv(summary["files"][0])
    mine = df["input"].str.contains(VIDEO)
    assert df.loc[mine, "frame"].max() >= 140
    edited = df[~(mine & df["frame"].between(SKIPPED[0], SKIPPED[1] - 1))]
    mine, frame = edited["input"].str.contains(VIDEO), edited["frame"]
    gap = mine & (frame.between(SHORT_GAP[0], SHORT_GAP[1] - 1) | frame.between(LONG_GAP[0], LONG_GAP[1] - 1))
    edited = edited[~gap | ~edited.duplicated(["input", "frame"])].copy()  # one row for a frame without a face
    gap = gap.reindex(edited.index)
    edited.loc[gap, [c for c in edited.columns if c not in KEPT_ON_NO_FACE]] = np.nan
    edited.loc[gap, list(ZERO_ON_NO_FACE)] = 0.0
    two = edited[edited["input"].str.contains(VIDEO)].groupby("frame").size()
    assert (two == 2).sum() >= 3  # frames where the largest face must be chosen
    path = d / "session.csv"
    # the file: the generator's own lines for the rows kept as they were, to_csv's for the edited ones (to_csv of
    # every row's 2,045 columns took 0.6 s, most of this fixture)
    lines = Path(summary["files"][0]).read_text().splitlines(keepends=True)
    assert len(lines) == len(df) + 1  # one line per row, after the header
    rebuilt = iter(edited.loc[gap].to_csv(index=False, header=False).splitlines(keepends=True))
    path.write_text(lines[0] + "".join(next(rebuilt) if g else lines[i + 1] for i, g in gap.items()))
    return path, edited


def _expected(df: pd.DataFrame) -> dict:
    """From the table, without aumesh: the video's frames, which have a face, and the largest face's values."""
    v = df[df["input"].str.contains(VIDEO)].copy()
    v["area"] = v["FaceRectWidth"].astype(float) * v["FaceRectHeight"].astype(float)
    frames = np.sort(v["frame"].astype(int).unique())
    face = v[v["FaceScore"].astype(float) > 0]
    largest = face.sort_values("area", ascending=False).drop_duplicates("frame").sort_values("frame")
    mesh_cols = [f"{a}_{i}" for i in range(N_VERTICES) for a in "xyz"]  # MPDetector: interleaved
    return {
        "frames": frames,
        "face_frames": largest["frame"].to_numpy(int),
        "aus": largest[list(AU_COLUMNS)].to_numpy(float),
        "pose": largest[list(POSE_COLUMNS)].to_numpy(float),
        "mesh": largest[mesh_cols].to_numpy(float).reshape(-1, N_VERTICES, 3),
    }


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    return upright_truth_release(tmp_path_factory.mktemp("release") / "release.npz")


def _animate(tmp_path, table_path, release, *extra, name="clip.glb"):
    out = tmp_path / name
    code = main(["animate", str(table_path), "--out", str(out), "--release", str(release), *extra])
    assert code == 0
    return out


def sample_linear(times: np.ndarray, values: np.ndarray, t: float) -> np.ndarray:
    """glTF's LINEAR sampler (spec, "Interpolation"): clamped at the ends, lerp between the keyframes around ``t``."""
    if t <= times[0]:
        return values[0]
    if t >= times[-1]:
        return values[-1]
    k = int(np.searchsorted(times, t, side="right"))
    a = (t - times[k - 1]) / (times[k] - times[k - 1])
    return (1 - a) * values[k - 1] + a * values[k]


def _animation(glb):
    """``(doc, times, weights (n, 20), rotations or None, base, targets)`` of an animated GLB, by the spec."""
    doc, accessor = parse_glb(glb)
    anim = doc["animations"][0]
    by_path = {ch["target"]["path"]: (ch, anim["samplers"][ch["sampler"]]) for ch in anim["channels"]}
    ch, s = by_path["weights"]
    assert s.get("interpolation", "LINEAR") == "LINEAR"
    node = doc["nodes"][ch["target"]["node"]]
    prim = doc["meshes"][node["mesh"]]["primitives"][0]
    times = accessor(s["input"]).astype(np.float64)
    weights = accessor(s["output"]).reshape(len(times), -1).astype(np.float64)
    rotations = None
    if "rotation" in by_path:
        rch, rs = by_path["rotation"]
        assert rs["input"] == s["input"] and rs.get("interpolation", "LINEAR") == "LINEAR"
        rotations = accessor(rs["output"]).astype(np.float64)
    base = accessor(prim["attributes"]["POSITION"]).astype(np.float64)
    targets = np.stack([accessor(t["POSITION"]) for t in prim["targets"]]).astype(np.float64)
    return doc, times, weights, rotations, base, targets


# ------------------------------------------------------------------------------------------------ reading the clip


def test_clip_is_the_videos_frames_with_the_largest_face(table):
    path, df = table
    exp = _expected(df)
    clip = read_clip(path, video=VIDEO)
    np.testing.assert_array_equal(clip.frame, exp["frames"])
    assert clip.source == "session.csv" and clip.video == VIDEO and clip.detector == "MPDetector"
    assert (clip.fps, clip.fps_source) == (25.0, "approx_time")
    np.testing.assert_array_equal(clip.time, exp["frames"] / 25.0)
    face = np.isin(clip.frame, exp["face_frames"])
    np.testing.assert_array_equal(clip.has_face, face)
    no_face = clip.frame[~clip.has_face]
    np.testing.assert_array_equal(no_face, np.r_[np.arange(*SHORT_GAP), np.arange(*LONG_GAP)])
    assert not np.isin(np.arange(*SKIPPED), clip.frame).any()
    np.testing.assert_array_equal(clip.aus[face], exp["aus"])
    np.testing.assert_array_equal(clip.pose[face], exp["pose"])
    assert np.isnan(clip.aus[~face]).all() and np.isnan(clip.pose[~face]).all()
    # x, y as py-feat wrote them (frame pixels); z converted from MPDetector's crop units (test_recorded_mesh_*)
    np.testing.assert_array_equal(clip.mesh[face][..., :2], exp["mesh"][..., :2].astype(np.float32))
    assert np.isnan(clip.mesh[~face]).all() and clip.mesh_units == "crop256"
    assert clip.frames_several_faces >= 3


def ingested_meshes(path: Path, mesh_units: str = "detector") -> dict[tuple[str, int], np.ndarray]:
    """(video, frame) -> (478, 3) float32: the ingest's cleaned mesh of a table (aumesh.data.readers and
    aumesh.data.ingest's clean_block, the pipeline's route, not the clip's), frame pixels."""
    from aumesh.data import ingest, readers

    source = readers.open_source(path, "{stem}.npy")
    spans = readers.csv_spans(source) if source.kind == "csv" else [readers.Span(source, 0, source.n_rows or 0)]
    out = {}
    for block, _ in ingest.iter_clean_blocks(spans, "largest", None, mesh_units):
        for video, frame, mesh in zip(block.video, block.frame, block.mesh, strict=True):
            out[(str(video), int(frame))] = mesh.reshape(3, N_VERTICES).T
    return out


def clip_vs_ingest(clip, ingested: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(clip's face frames' meshes, the ingest's of the same frames)``, both (m, 478, 3)."""
    frames = clip.frame[clip.has_face]
    return clip.mesh[clip.has_face], np.stack([ingested[(clip.video_id, int(f))] for f in frames])


@pytest.mark.slow
@pytest.mark.parametrize("detector,unit", [("mp", "crop256"), ("v2", "chip")])
def test_recorded_mesh_is_the_ingests_in_frame_pixels(tmp_path, detector, unit):
    """The clip's recorded mesh of a table in the detector's native units is the ingest's cleaned mesh of the same
    frames (bit for bit), and the same frames written with z in pixels give it too (read with mesh_units=pixels);
    the raw z (crop units) is not what the clip holds. Profile frames (2-D inter-ocular distance below 1 px) are
    not taken for normalized units."""
    spec = SynthSpec(n_frames=80, n_videos=1, seed=11, identity_scale=0.0, noise_px=0.05, profile_yaw_deg=(89.5, 89.9))
    native, pixels = tmp_path / "native", tmp_path / "pixels"
    for out, z_pixels in ((native, False), (pixels, True)):
        write_pyfeat_tables(out, spec, detector=detector, z_pixels=z_pixels, profile_rate=0.6, extra_face_rate=0.2)
    csv = native / "clip_0000.csv"
    clip = read_clip(csv)
    assert clip.mesh_units == unit and clip.detector == ("MPDetector" if detector == "mp" else "Detectorv2")
    got, expected = clip_vs_ingest(clip, ingested_meshes(csv))
    np.testing.assert_array_equal(got, expected)
    # the independent route: z written in pixels, taken as pixels
    twin = read_clip(pixels / "clip_0000.csv", mesh_units="pixels")
    assert twin.mesh_units == "pixels-asked"
    np.testing.assert_array_equal(twin.has_face, clip.has_face)
    np.testing.assert_allclose(got, twin.mesh[twin.has_face], rtol=0, atol=1e-4 * np.abs(got).max())
    # the profile frames are there, and the old inter-ocular judgement would have called them normalized
    iod = np.hypot(*(got[:, 33, :2] - got[:, 263, :2]).T)
    assert np.median(iod) < 1.0, np.median(iod)
    # what read_clip did not do before: z as written is in crop units, a flat face beside pixels
    raw = read_clip(csv, mesh_units="pixels").mesh[clip.has_face]
    assert np.abs(raw[..., 2] - got[..., 2]).max() > 10 * 1e-4 * np.abs(got).max()


def test_normalized_clip_is_converted_and_without_frame_size_kept(tmp_path):
    spec = SynthSpec(n_frames=40, n_videos=1, seed=12)
    write_pyfeat_tables(tmp_path / "a", spec, detector="mp", normalized=True)
    csv = tmp_path / "a" / "clip_0000.csv"
    clip = read_clip(csv)
    assert clip.mesh_units == "normalized"
    got, expected = clip_vs_ingest(clip, ingested_meshes(csv))
    np.testing.assert_array_equal(got, expected)
    write_pyfeat_tables(tmp_path / "b", spec, detector="mp", normalized=True, frame_size=False)
    bare = read_clip(tmp_path / "b" / "clip_0000.csv")
    assert bare.mesh_units == "normalized-raw" and np.nanmax(np.abs(bare.mesh)) < 1.5  # as written


@pytest.mark.slow
def test_csv_gz_parquet_and_a_table_without_mesh_read_alike(table, tmp_path):
    path, df = table
    ref = read_clip(path, video=VIDEO)
    gz = tmp_path / "session.csv.gz"
    gz.write_bytes(gzip.compress(path.read_bytes(), compresslevel=1))
    pq_path = tmp_path / "session.parquet"
    df.to_parquet(pq_path, index=False)
    bare = tmp_path / "bare.parquet"
    df[[c for c in df.columns if c[:2] not in ("x_", "y_", "z_")]].to_parquet(bare, index=False)
    for p in (gz, pq_path, bare):
        clip = read_clip(p, video=VIDEO)
        np.testing.assert_array_equal(clip.frame, ref.frame)
        np.testing.assert_array_equal(clip.has_face, ref.has_face)
        np.testing.assert_array_equal(clip.aus, ref.aus)
        assert (clip.fps, clip.fps_source) == (25.0, "approx_time")
    assert read_clip(bare, video=VIDEO).mesh is None
    np.testing.assert_array_equal(read_clip(pq_path, video=VIDEO).mesh, ref.mesh)


@pytest.mark.parametrize("fps", [24000 / 1001, 24.0, 25.0, 30000 / 1001, 30.0, 50.0, 60.0])
@pytest.mark.parametrize("skip", [1, 5])
def test_frame_rate_from_py_feats_approx_time(fps, skip):
    # feat.data.VideoDataset.calc_approx_frame_time: int(frame / fps) as "MM:SS", frames 0, skip, 2 skip, ...
    frame = np.arange(0, int(fps * 90), skip)
    approx = np.array([f"{int(f / fps) // 60:02d}:{int(f / fps) % 60:02d}" for f in frame], dtype=object)
    found = fps_from_approx_time(frame, approx)
    if skip == 1:
        assert found == pytest.approx(fps, rel=1e-12)
    else:  # whole seconds every 5th frame may not tell 30 from 29.97 (30000/1001): 0.1% apart, both allowed
        assert found == pytest.approx(fps, rel=1.01e-3)


def test_frame_rate_undecided_or_given():
    frame = np.arange(10)  # under a second: every approx_time is 00:00
    assert fps_from_approx_time(frame, np.array(["00:00"] * 10, dtype=object)) is None
    seconds = np.arange(0, 300) / 12.5  # fractional seconds (another tool's export): an uncommon rate
    assert fps_from_approx_time(np.arange(300), seconds) == pytest.approx(12.5, rel=1e-3)
    assert fps_from_approx_time(np.arange(300), np.array(["garbage"] * 300, dtype=object)) is None


def test_fps_option_and_default(table, tmp_path):
    path, df = table
    clip = read_clip(path, video=VIDEO, fps=30)
    assert (clip.fps, clip.fps_source) == (30.0, "--fps")
    np.testing.assert_array_equal(clip.time, clip.frame / 30.0)
    no_time = tmp_path / "no_time.parquet"
    df[[c for c in df.columns if c[:2] not in ("x_", "y_", "z_") and c != "approx_time"]].to_parquet(no_time)
    assert read_clip(no_time, video=VIDEO).fps_source == "default (25)"


def test_bridge_interpolates_short_gaps_and_holds_long_ones():
    t = np.arange(12) / 10.0
    has = np.array([0, 1, 0, 0, 1, 0, 0, 0, 0, 0, 0, 1], bool)  # gaps: start, 0.3 s, 0.7 s, none at the end
    v = np.where(has, np.arange(12.0), np.nan)[:, None]
    out = bridge(v, has, t, max_gap_s=0.5)[:, 0]
    np.testing.assert_allclose(out, [1, 1, 2, 3, 4, 4, 4, 4, 4, 4, 4, 11])
    assert bridge(v, has, t, max_gap_s=0.75)[7, 0] == pytest.approx(7.0)  # 0.7 s apart: interpolated


def test_smooth_is_a_centred_moving_average():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40, 3))
    s = smooth(x, 5)
    np.testing.assert_allclose(s[2:-2], np.stack([np.convolve(x[:, j], np.ones(5) / 5, "valid") for j in range(3)], 1))
    np.testing.assert_allclose(s[0], x[:3].mean(0))
    np.testing.assert_array_equal(smooth(x, 1), x)


# ---------------------------------------------------------------------------------------------------- the GLB


def test_animation_samples_are_predict_mesh(table, release, tmp_path, capsys):
    path, df = table
    glb = _animate(tmp_path, path, release, "--video", VIDEO)
    line = capsys.readouterr().out.strip()
    exp = _expected(df)
    n = len(exp["frames"])
    duration = (exp["frames"][-1] - exp["frames"][0]) / 25
    assert line.startswith(f"wrote {glb} ({n} frames, {duration:.2f} s at 25 fps from approx_time;")
    assert "23 no-face frame(s): 1 gap(s) interpolated, 1 held" in line
    doc, times, weights, rotations, base, targets = _animation(glb)
    assert rotations is None and len(doc["nodes"]) == 1
    np.testing.assert_array_equal(times, ((exp["frames"] - exp["frames"][0]) / 25.0).astype(np.float32))
    assert np.diff(times).max() == pytest.approx((SKIPPED[1] - SKIPPED[0] + 1) / 25, rel=1e-6)  # the skip gap
    meta = doc["asset"]["extras"]
    assert (meta["table"], meta["video"], meta["first_frame"], meta["fps_source"]) == (
        "session.csv",
        VIDEO,
        int(exp["frames"][0]),
        "approx_time",
    )
    # a frame's time as the file holds it (float32: the sampler's keyframe times)
    face_times = ((exp["face_frames"] - exp["frames"][0]) / 25.0).astype(np.float32).astype(np.float64)
    w = np.stack([sample_linear(times, weights, t) for t in face_times])
    sampled = base + np.tensordot(w, targets, 1)
    expected = aumesh.predict_mesh(aumesh.load_release(release), exp["aus"])  # pose 0
    # float32 precision: the file's numbers are float32 roundings of the model's (base, targets, weights), so each
    # coordinate may differ by a few float32 ulps of the terms it sums
    bound = 4 * EPS32 * (np.abs(base) + np.tensordot(np.abs(w), np.abs(targets), 1))
    assert (np.abs(sampled - expected) <= bound).all(), np.abs(sampled - expected).max()


def test_gaps_in_the_animation(table, release, tmp_path):
    path, df = table
    glb = _animate(tmp_path, path, release, "--video", VIDEO)
    _, times, weights, _, _, _ = _animation(glb)
    exp = _expected(df)
    frames = exp["frames"]
    at = {int(f): i for i, f in enumerate(frames)}
    aus = dict(zip(exp["face_frames"].tolist(), exp["aus"], strict=True))
    before, after = SHORT_GAP[0] - 1, SHORT_GAP[1]
    for f in range(*SHORT_GAP):  # linear in time between the face frames around the gap
        a = (f - before) / (after - before)
        np.testing.assert_allclose(weights[at[f]], (1 - a) * aus[before] + a * aus[after], atol=1e-6)
    assert (LONG_GAP[1] - LONG_GAP[0] + 1) / 25 > MAX_GAP_S
    for f in range(*LONG_GAP):  # held: the last face frame's AUs
        np.testing.assert_array_equal(weights[at[f]], aus[LONG_GAP[0] - 1].astype(np.float32))
    np.testing.assert_array_equal(weights[at[LONG_GAP[1]]], aus[LONG_GAP[1]].astype(np.float32))


def test_smooth_option_averages_the_weights(table, release, tmp_path):
    path, _ = table
    glb = _animate(tmp_path, path, release, "--video", VIDEO, "--smooth", "3", name="smooth.glb")
    _, _, smoothed, _, _, _ = _animation(glb)
    _, _, raw, _, _, _ = _animation(_animate(tmp_path, path, release, "--video", VIDEO, name="raw.glb"))
    np.testing.assert_allclose(smoothed[1:-1], (raw[:-2] + raw[1:-1] + raw[2:]) / 3, atol=1e-6)


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate ``v`` by the unit quaternion ``q = (x, y, z, w)``: v + 2w (u x v) + 2 u x (u x v), u = (x, y, z)."""
    u, w = q[:3], q[3]
    return v + 2 * w * np.cross(u, v) + 2 * np.cross(u, np.cross(u, v))


def test_pose_turns_the_head_as_the_card_does(table, release, tmp_path):
    path, df = table
    glb = _animate(tmp_path, path, release, "--video", VIDEO, "--pose", name="pose.glb")
    doc, times, weights, rotations, base, targets = _animation(glb)
    exp = _expected(df)
    at = np.searchsorted(exp["frames"], exp["face_frames"])
    np.testing.assert_allclose(np.linalg.norm(rotations, axis=1), 1, atol=1e-6)
    assert (np.einsum("ij,ij->i", rotations[1:], rotations[:-1]) > 0).all()  # the short way between keyframes
    v = np.array([0.3, -1.2, 2.0])
    for i, pose in zip(at, exp["pose"], strict=True):
        np.testing.assert_allclose(_rotate(rotations[i], v), Rotation.from_euler("xyz", pose).apply(v), atol=1e-6)
    # the head node turns the mesh node about the neutral face's centre: at pose 0 the vertices are the NPZ's
    head = next(n for n in doc["nodes"] if "children" in n)
    mesh_node = doc["nodes"][head["children"][0]]
    centre = base.mean(axis=0)
    np.testing.assert_allclose(head["translation"], centre, rtol=1e-6)
    np.testing.assert_allclose(mesh_node["translation"], -centre, rtol=1e-6)
    i, pose = at[5], exp["pose"][5]
    local = base + np.tensordot(weights[i], targets, 1)
    world = np.array([_rotate(rotations[i], p) for p in local - centre]) + centre
    card = (local - centre) @ Rotation.from_euler("xyz", pose).as_matrix().T + centre  # posed = canonical @ R.T
    np.testing.assert_allclose(world, card, atol=1e-4 * np.abs(card).max())


@pytest.mark.parametrize("pose", [False, True])
def test_animation_passes_the_khronos_gltf_validator(table, release, tmp_path, node_tools, pose):
    path, _ = table
    glb = _animate(tmp_path, path, release, "--video", VIDEO, *(["--pose"] if pose else []))
    proc = subprocess.run(
        ["node", str(REPO / "tests" / "tools" / "validate_gltf.cjs"), str(glb)],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    )
    report = json.loads(proc.stdout)
    assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]
    assert report["issues"]["numWarnings"] == 0, report["issues"]["messages"]
    assert report["info"]["animationCount"] == 1 and report["info"]["totalVertexCount"] == N_VERTICES


def test_trimesh_loads_the_mesh(table, release, tmp_path):
    trimesh = pytest.importorskip("trimesh")
    path, _ = table
    glb = _animate(tmp_path, path, release, "--video", VIDEO, "--pose")
    scene = trimesh.load(glb)
    (mesh,) = scene.geometry.values()
    assert mesh.vertices.shape == (N_VERTICES, 3)
    _, _, _, _, base, _ = _animation(glb)
    np.testing.assert_allclose(scene.to_geometry().vertices, base, atol=1e-4)  # rest pose: the NPZ's


# ------------------------------------------------------------------------------------------------------- errors


def _error(capsys, *argv) -> str:
    assert main(["animate", *map(str, argv)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    return err


def test_errors_are_one_line(table, release, tmp_path, capsys):
    path, df = table
    out = tmp_path / "x.glb"
    err = _error(capsys, path, "--out", out, "--release", release)
    assert "holds 2 videos (vid000000, vid000001)" in err and "--video" in err
    err = _error(capsys, path, "--out", out, "--release", release, "--video", "nope")
    assert "no video 'nope'" in err and "vid000001" in err
    no_aus = tmp_path / "no_aus.parquet"
    df.drop(columns=list(AU_COLUMNS)).to_parquet(no_aus, index=False)
    err = _error(capsys, no_aus, "--out", out, "--release", release)
    assert "no_aus.parquet" in err and "'AU01' is missing" in err
    err = _error(capsys, tmp_path / "missing.csv", "--out", out, "--release", release)
    assert "missing.csv: no such file" in err
    err = _error(capsys, path, "--out", out, "--release", release, "--video", VIDEO, "--smooth", "4")
    assert "--smooth 4" in err
    err = _error(capsys, path, "--out", tmp_path / "x.mp4", "--release", release, "--video", VIDEO)
    assert ".glb" in err
    assert not out.exists() and not list(tmp_path.glob("*.glb"))


# ------------------------------------------------------------------------------------------- three.js in Chromium

THREE_PAGE = """<!doctype html><html><head><script type="importmap">
{"imports": {"three": "/three/build/three.module.js", "three/addons/": "/three/examples/jsm/"}}
</script></head><body><script type="module">
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
const gltf = await new GLTFLoader().loadAsync("/clip.glb");
let mesh = null;
gltf.scene.traverse((o) => { if (o.isMesh) mesh = o; });
const mixer = new THREE.AnimationMixer(gltf.scene);
const action = mixer.clipAction(gltf.animations[0]);
action.setLoop(THREE.LoopOnce);
action.clampWhenFinished = true;
action.play();
// the mesh three.js shows at time t: its morph targets (relative, glTF's) blended by the mixer's influences, placed
// by the node's world matrix (the head's rotation with --pose)
window.sample = (t) => {
  mixer.setTime(t);
  gltf.scene.updateMatrixWorld(true);
  const pos = mesh.geometry.attributes.position, targets = mesh.geometry.morphAttributes.position;
  const w = mesh.morphTargetInfluences, v = new THREE.Vector3(), out = [];
  for (let i = 0; i < pos.count; i++) {
    v.set(pos.getX(i), pos.getY(i), pos.getZ(i));
    for (let k = 0; k < targets.length; k++) {
      v.x += w[k] * targets[k].getX(i); v.y += w[k] * targets[k].getY(i); v.z += w[k] * targets[k].getZ(i);
    }
    v.applyMatrix4(mesh.matrixWorld);
    out.push(v.x, v.y, v.z);
  }
  return { weights: Array.from(w), positions: out };
};
window.info = {
  names: Object.keys(mesh.morphTargetDictionary), relative: mesh.geometry.morphTargetsRelative,
  duration: gltf.animations[0].duration, tracks: gltf.animations[0].tracks.map((t) => t.name),
};
window.ready = true;
</script></body></html>"""


@pytest.mark.slow
def test_three_js_plays_the_clip(table, release, tmp_path, node_tools, browser):
    if not (node_tools / "three" / "examples" / "jsm" / "loaders" / "GLTFLoader.js").exists():
        pytest.skip("three.js's GLTFLoader not installed (make tools)")
    path, df = table
    glb = _animate(tmp_path, path, release, "--video", VIDEO, "--pose", name="three.glb")
    exp = _expected(df)
    files = {"/clip.glb": (glb.read_bytes(), "model/gltf-binary"), "/": (THREE_PAGE.encode(), "text/html")}

    def serve(route):  # every request answered from disk: no server, no network
        url = route.request.url.split("://", 1)[1]
        local = "/" + url.split("/", 1)[1] if "/" in url else "/"
        if local in files:
            body, kind = files[local]
        elif local.startswith("/three/"):
            body, kind = (node_tools / local.lstrip("/")).read_bytes(), "text/javascript"
        else:
            return route.fulfill(status=404, body="")
        route.fulfill(status=200, body=body, content_type=kind)

    page = browser.new_page()
    try:
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.route("http://aumesh.test/**", serve)
        page.goto("http://aumesh.test/")
        page.wait_for_function("window.ready === true", timeout=30000)
        info = page.evaluate("window.info")
        picks = [0, 7, len(exp["face_frames"]) // 2, len(exp["face_frames"]) - 1]
        times = ((exp["face_frames"][picks] - exp["frames"][0]) / 25.0).astype(np.float32)
        got = [page.evaluate("(t) => window.sample(t)", float(t)) for t in times]
    finally:
        page.close()
    assert not errors, errors
    assert info["names"] == list(AU_COLUMNS) and info["relative"] is True
    assert info["duration"] == pytest.approx(float(times[-1]), rel=1e-6)
    assert sorted(name.rsplit(".", 1)[1] for name in info["tracks"]) == ["morphTargetInfluences", "quaternion"]
    m = aumesh.load_release(release)
    centre = aumesh.predict_mesh(m).mean(axis=0)  # the head turns about the neutral face's centre
    for k, sample in zip(picks, got, strict=True):
        np.testing.assert_allclose(sample["weights"], exp["aus"][k], atol=1e-6)
        local = aumesh.predict_mesh(m, exp["aus"][k])  # pose 0
        posed = (local - centre) @ Rotation.from_euler("xyz", exp["pose"][k]).as_matrix().T + centre
        shown = np.asarray(sample["positions"]).reshape(N_VERTICES, 3)
        np.testing.assert_allclose(shown, posed, atol=1e-4 * np.abs(posed).max())
