"""The py-feat 2.1.5-shaped synthetic tables: columns, no-face rows, background faces, and the clean twin."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from aumesh.core.schema import AU_COLUMNS
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from aumesh.synthetic.pyfeat_columns import pyfeat_columns
from aumesh.synthetic.tables import SynthSpec, write_tables

SPEC = SynthSpec(n_frames=300, n_videos=6)
W, H = 640.0, 480.0
BLENDSHAPES = (
    "_neutral browDownLeft browDownRight browInnerUp browOuterUpLeft browOuterUpRight cheekPuff cheekSquintLeft "
    "cheekSquintRight eyeBlinkLeft eyeBlinkRight eyeLookDownLeft eyeLookDownRight eyeLookInLeft eyeLookInRight "
    "eyeLookOutLeft eyeLookOutRight eyeLookUpLeft eyeLookUpRight eyeSquintLeft eyeSquintRight eyeWideLeft eyeWideRight "
    "jawForward jawLeft jawOpen jawRight mouthClose mouthDimpleLeft mouthDimpleRight mouthFrownLeft mouthFrownRight "
    "mouthFunnel mouthLeft mouthLowerDownLeft mouthLowerDownRight mouthPressLeft mouthPressRight mouthPucker mouthRight "
    "mouthRollLower mouthRollUpper mouthShrugLower mouthShrugUpper mouthSmileLeft mouthSmileRight mouthStretchLeft "
    "mouthStretchRight mouthUpperUpLeft mouthUpperUpRight noseSneerLeft noseSneerRight"
).split()
RECT = ["FaceRectX", "FaceRectY", "FaceRectWidth", "FaceRectHeight"]
IDENT = [f"Identity_{i}" for i in range(1, 513)]
MESH_MP = [f"{a}_{i}" for i in range(478) for a in "xyz"]
MESH_V2 = [f"mesh_{a}_{i}" for a in "xyz" for i in range(478)]
PT68 = [f"{a}_{i}" for a in "xy" for i in range(68)]
EXPECTED = {
    "mp": RECT
    + ["FaceScore"]
    + MESH_MP
    + ["Pitch", "Roll", "Yaw", "X", "Y", "Z"]
    + BLENDSHAPES
    + list(AU_COLUMNS)
    + ["anger", "disgust", "fear", "happiness", "sadness", "surprise", "neutral"]
    + IDENT
    + [
        "gaze_pitch",
        "gaze_yaw",
        "gaze_angle",
        "FrameHeight",
        "FrameWidth",
        "input",
        "frame",
        "approx_time",
        "Identity",
    ],
    "v2": RECT
    + ["FaceScore"]
    + PT68
    + ["Pitch", "Roll", "Yaw", "X", "Y", "Z"]
    + list(AU_COLUMNS)
    + [
        "Neutral",
        "Happy",
        "Sad",
        "Surprise",
        "Fear",
        "Disgust",
        "Anger",
        "valence",
        "arousal",
        "gaze_pitch",
        "gaze_yaw",
        "gaze_angle",
    ]
    + IDENT
    + MESH_V2
    + BLENDSHAPES
    + ["FrameHeight", "FrameWidth", "input", "frame", "approx_time", "Identity"],
}
FILLED = ["input", "frame", "approx_time", "FrameHeight", "FrameWidth"]


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """detector -> (summary, table as pandas reads the CSV, clean table)."""
    out = tmp_path_factory.mktemp("pyfeat")
    result = {}
    for det in ("mp", "v2"):
        s = write_pyfeat_tables(out / det, SPEC, detector=det, clean_dir=out / f"clean_{det}")
        assert len(s["files"]) == 1 and Path(s["files"][0]).name == "clip_0000.csv"
        result[det] = (s, pd.read_csv(s["files"][0]), pd.read_parquet(s["clean_files"][0]))
    return result


def _measurements(df: pd.DataFrame, det: str) -> list[str]:
    keep = set(FILLED) | ({"FaceScore", *RECT} if det == "mp" else set())
    return [c for c in df.columns if c not in keep]


@pytest.mark.parametrize("det", ["mp", "v2"])
def test_columns_in_pyfeat_order(written, det):
    _, df, _ = written[det]
    assert list(df.columns) == EXPECTED[det] == pyfeat_columns(det)
    assert len(BLENDSHAPES) == 52
    assert df.shape[1] == (2045 if det == "mp" else 2183)
    assert list(df.columns).index("x_0") == 5 and (det == "v2" or list(df.columns)[5:8] == ["x_0", "y_0", "z_0"])
    assert pyfeat_columns(det, frame_size=False) == [c for c in EXPECTED[det] if c not in ("FrameHeight", "FrameWidth")]


def test_summary(written):
    s, df, clean = written["mp"]
    assert s["n_videos"] == 6 and s["n_frames"] == 300 and s["n_rows"] == len(df) == 300 + s["n_extra_faces"]
    assert s["n_face_frames"] == 300 - s["n_no_face"] == len(clean)
    assert 0 < s["n_no_face"] <= 20 and 0 < s["n_extra_faces"] <= 30
    assert df[["input", "frame"]].drop_duplicates().shape[0] == 300
    assert written["v2"][0]["n_rows"] == s["n_rows"]  # the extras follow the seed, not the detector
    assert df["input"].str.fullmatch(r"videos/vid\d{6}\.mp4").all() and df["frame"].dtype.kind == "i"
    want = [f"{f // 25 // 60:02d}:{f // 25 % 60:02d}" for f in df["frame"]]
    assert df["approx_time"].tolist() == want and (df["FrameWidth"] == W).all() and (df["FrameHeight"] == H).all()


@pytest.mark.slow
@pytest.mark.parametrize("det", ["mp", "v2"])
def test_no_face_rows(written, det):
    s, df, _ = written[det]
    gone = df["Identity"].isna()
    assert gone.sum() == s["n_no_face"]
    rows = df[gone]
    assert rows[_measurements(df, det)].isna().all().all()  # read_csv reads the empty fields as NaN
    assert rows[FILLED].notna().all().all()
    if det == "mp":
        assert (rows[["FaceScore", *RECT]] == 0).all().all()
    else:
        assert rows[["FaceScore", *RECT]].isna().all().all()
    # one row per no-face frame (replacing the face), and the frames come in runs
    assert not rows.duplicated(["input", "frame"]).any()
    assert not df[df.duplicated(["input", "frame"], keep=False)]["Identity"].isna().any()
    runs = []
    for _, g in rows.groupby("input"):
        f = np.sort(g["frame"].to_numpy())
        runs += [len(r) for r in np.split(f, np.flatnonzero(np.diff(f) != 1) + 1)]
    assert max(runs) > 1 and len(runs) < len(rows)
    face = df[~gone]
    assert face[_measurements(df, det)].drop(columns=IDENT if det == "mp" else []).notna().all().all()
    assert face["FaceScore"].between(0.6, 1.0).all()


@pytest.mark.parametrize("det", ["mp", "v2"])
def test_background_faces(written, det):
    s, df, _ = written[det]
    df = df[["input", "frame", "Identity", "FaceScore", *RECT, *AU_COLUMNS]].assign(row=np.arange(len(df)))
    extra, main = df[df["Identity"] == "Person_1"], df[df["Identity"] == "Person_0"]
    assert len(extra) == s["n_extra_faces"] > 0
    both = extra.merge(main, on=["input", "frame"], suffixes=("_e", "_m"))
    assert len(both) == len(extra)  # every background face shares its frame with the main face
    area = lambda side: both[f"FaceRectWidth_{side}"] * both[f"FaceRectHeight_{side}"]
    assert (area("e") < 0.5 * area("m")).all()
    assert both["FaceScore_e"].between(0.6, 0.9).all() and both["FaceScore_m"].between(0.9, 1.0).all()
    first = both["row_e"] < both["row_m"]
    assert first.any() and (~first).any()  # detection order, not size
    assert ((both["row_e"] - both["row_m"]).abs() == 1).all()
    assert extra[list(AU_COLUMNS)].stack().between(0, 1).all()
    assert not np.allclose(
        both[[f"{a}_e" for a in AU_COLUMNS]].to_numpy(), both[[f"{a}_m" for a in AU_COLUMNS]].to_numpy()
    )
    # the background person appears in runs of consecutive frames
    f = np.sort(extra[extra["input"] == extra["input"].iloc[0]]["frame"].to_numpy())
    assert len(f) == 1 or (np.diff(f) == 1).any()


def _mesh(df: pd.DataFrame, det: str) -> np.ndarray:
    """(n, 478, 3) pixels-or-units, selected by name."""
    if det == "mp":
        return df[MESH_MP].to_numpy().reshape(len(df), 478, 3)
    return df[MESH_V2].to_numpy().reshape(len(df), 3, 478).transpose(0, 2, 1)


#: py-feat's z units (feat/detector_v2.py _mesh_to_original_frame: z unchanged, 0-1 over the chip whose side is
#: FaceRectWidth; feat/MPDetector.py forward: z left in the 256-px crop's scale, FaceRect the crop box)
Z_DIVISOR = {"v2": 1.0, "mp": 256.0}


def _check_clean(df: pd.DataFrame, clean: pd.DataFrame, det: str, units=(1.0, 1.0, 1.0), exact=True, z_crop=False):
    main = df[df["Identity"] == "Person_0"].copy()
    main["video_id"] = main["input"]  # the video's identity: py-feat's input path, in the clean tables too
    main = main.sort_values(["video_id", "frame"]).reset_index(drop=True)
    clean = clean.sort_values(["video_id", "frame"]).reset_index(drop=True)
    assert list(clean.columns) == ["video_id", "frame", *AU_COLUMNS, "Pitch", "Roll", "Yaw", *MESH_MP]
    assert (main["video_id"].to_numpy() == clean["video_id"].to_numpy()).all()
    assert (main["frame"].to_numpy() == clean["frame"].to_numpy()).all()
    cols = [*AU_COLUMNS, "Yaw", "Pitch", "Roll"]  # by name: the tables keep Fex order
    np.testing.assert_array_equal(main[cols].to_numpy(), clean[cols].to_numpy())
    px = _mesh(main, det) * np.asarray(units)
    if z_crop:  # z in the detector's crop units: back to pixels by its FaceRectWidth
        px[:, :, 2] *= main["FaceRectWidth"].to_numpy()[:, None] / Z_DIVISOR[det]
    want = _mesh(clean, "mp")
    assert clean[MESH_MP].dtypes.eq(np.float32).all()
    if exact:
        np.testing.assert_array_equal(px.astype(np.float32), want)
    else:
        np.testing.assert_allclose(px, want, rtol=1e-6, atol=1e-4)
    if det == "v2":  # the 68-point block is 68 of the mesh's vertices' x, y
        pts = main[PT68].to_numpy().reshape(len(main), 2, 68).transpose(0, 2, 1) * np.asarray(units[:2])
        hits = [
            np.flatnonzero(np.isclose(want[0, :, 0], pts[0, k, 0]) & np.isclose(want[0, :, 1], pts[0, k, 1]))
            for k in range(68)
        ]
        assert all(len(h) >= 1 for h in hits)
        idx = np.array([h[0] for h in hits])
        np.testing.assert_allclose(pts, want[:, idx, :2], rtol=1e-6, atol=1e-4)


@pytest.mark.parametrize("det", ["mp", "v2"])
def test_clean_table_is_the_main_face(written, det):
    _, df, clean = written[det]
    _check_clean(df, clean, det, exact=False, z_crop=True)


@pytest.mark.slow
@pytest.mark.parametrize("det", ["mp", "v2"])
def test_z_in_pixels_is_the_clean_mesh_exactly(tmp_path, det):
    spec = SynthSpec(n_frames=60, n_videos=2)
    s = write_pyfeat_tables(tmp_path / "t", spec, detector=det, z_pixels=True, clean_dir=tmp_path / "c")
    _check_clean(pd.read_csv(s["files"][0]), pd.read_parquet(s["clean_files"][0]), det)


def test_face_rect_is_each_detectors_crop_box(written):
    """FaceRect against the face's own extent (the clean mesh): Detectorv2's square chip of side 1.2 x the longer
    side of a box ~8 % beyond the face (extract_face_square_pad_torch), MPDetector's box x 1.25, whole pixels
    (extract_face_from_bbox_torch(face_size=256, expand_bbox=1.25) rounds its corners)."""
    for det in ("mp", "v2"):
        _, df, clean = written[det]
        main = df[df["Identity"] == "Person_0"].sort_values(["input", "frame"])
        mesh = _mesh(clean.sort_values(["video_id", "frame"]), "mp")
        lo, hi = mesh[:, :, :2].min(axis=1), mesh[:, :, :2].max(axis=1)
        box = (hi - lo) * 1.16  # the detector's box: the face's extent and 8 % each side
        x, y, w, h = (main[c].to_numpy() for c in RECT)
        assert (x < lo[:, 0]).all() and (y < lo[:, 1]).all()  # the face lies inside its crop
        assert (x + w > hi[:, 0]).all() and (y + h > hi[:, 1]).all()
        if det == "v2":
            np.testing.assert_array_equal(w, h)
            np.testing.assert_allclose(w, 1.2 * box.max(axis=1), rtol=1e-6)
            np.testing.assert_allclose(x + w / 2, (lo[:, 0] + hi[:, 0]) / 2, atol=1e-6)  # centred
        else:
            assert (np.round(x) == x).all() and (np.round(w) == w).all() and (np.round(h) == h).all()
            np.testing.assert_allclose(w, 1.25 * box[:, 0], atol=1.01)
            np.testing.assert_allclose(h, 1.25 * box[:, 1], atol=1.01)
            assert (np.abs(w - h) > 1).mean() > 0.5  # rectangular, not squared


def test_profile_frames_turn_only_their_runs(tmp_path):
    """``profile_rate``: runs of frames at |yaw| 60-85 deg, generated at that pose (the face's 2-D inter-ocular
    distance shrinks as cos(yaw)); the other frames, the AUs and every other draw as without it."""
    spec = SynthSpec(n_frames=400, n_videos=4, seed=5)
    plain = pd.read_parquet(write_tables(tmp_path / "a", spec)["files"][0])
    turned = pd.read_parquet(write_tables(tmp_path / "b", replace(spec, profile_rate=0.3))["files"][0])
    yaw = np.rad2deg(turned["Yaw"].to_numpy())
    profile = np.abs(yaw) >= 60
    assert 0.15 < profile.mean() < 0.45 and (np.abs(yaw[profile]) <= 85).all()
    assert (np.diff(np.flatnonzero(profile)) == 1).mean() > 0.8  # in runs
    same = [*AU_COLUMNS, "Pitch", "Roll"]
    np.testing.assert_array_equal(plain[same].to_numpy(), turned[same].to_numpy())
    np.testing.assert_array_equal(plain[~profile].to_numpy(), turned[~profile].to_numpy())
    m = turned[MESH_MP].to_numpy().reshape(len(turned), 478, 3)
    iod = np.linalg.norm(m[:, 33, :2] - m[:, 263, :2], axis=1)
    height = m[:, 10, 1] - m[:, 152, 1]
    ratio = np.median(iod[profile] / np.abs(height[profile])) / np.median(iod[~profile] / np.abs(height[~profile]))
    assert ratio < np.cos(np.deg2rad(55))  # the eyes close up, the face keeps its height


def test_clean_frames_are_synths(written, tmp_path):
    _, _, clean = written["mp"]
    s = write_tables(tmp_path, SPEC)
    ref = pd.concat(pd.read_parquet(f) for f in s["files"])
    clean = clean.assign(video_id=clean["video_id"].map(lambda p: Path(p).stem))  # synth's tables name vid000000
    both = clean.merge(ref, on=["video_id", "frame"], suffixes=("", "_ref"))
    assert len(both) == len(clean) and len(ref) == 300
    cols = [*AU_COLUMNS, "Pitch", "Roll", "Yaw", *MESH_MP]
    np.testing.assert_array_equal(both[cols].to_numpy(), both[[f"{c}_ref" for c in cols]].to_numpy())


@pytest.mark.slow
@pytest.mark.parametrize("det", ["mp", "v2"])
def test_normalized_units(tmp_path, det):
    s = write_pyfeat_tables(
        tmp_path / "t",
        SPEC,
        detector=det,
        normalized=True,
        fmt="parquet",
        videos_per_file=2,
        clean_dir=tmp_path / "clean",
    )
    assert [Path(f).name for f in s["files"]] == ["clip_0000.parquet", "clip_0001.parquet", "clip_0002.parquet"]
    df = pd.concat(pd.read_parquet(f) for f in s["files"])
    clean = pd.concat(pd.read_parquet(f) for f in s["clean_files"])
    assert list(df.columns) == EXPECTED[det]
    mesh = _mesh(df[df["Identity"] == "Person_0"], det)
    assert np.nanmax(np.abs(mesh[..., :2])) < 1.5  # normalized image units
    _check_clean(df, clean, det, units=(W, H, W), exact=False)  # normalized: z / FrameWidth, not the crop's
    assert (df.loc[df["Identity"].isna(), "FaceScore"] == 0).all() == (det == "mp")


def test_split_and_frame_size(written, tmp_path):
    s = write_pyfeat_tables(tmp_path / "split", SPEC, fmt="split", frame_size=False, videos_per_file=4)
    assert len(s["files"]) == 2
    csv = written["mp"][1]  # the same rows as one CSV
    n = 0
    for f in s["files"]:
        df = pd.read_parquet(f)
        mesh = np.load(Path(f).with_suffix(".npy"))
        assert mesh.dtype == np.float32 and mesh.shape == (len(df), 478, 3)
        assert list(df.columns) == [c for c in EXPECTED["mp"] if c not in MESH_MP + ["FrameHeight", "FrameWidth"]]
        gone = df["Identity"].isna().to_numpy()
        assert np.isnan(mesh[gone]).all() and np.isfinite(mesh[~gone]).all()
        part = csv.iloc[n : n + len(df)]
        px = part[MESH_MP].to_numpy().reshape(-1, 478, 3)  # the CSV: z in the 256-px crop's units; the .npy pixels
        np.testing.assert_array_equal(px[:, :, :2].astype(np.float32), mesh[:, :, :2])
        z = px[:, :, 2] * part["FaceRectWidth"].to_numpy()[:, None] / 256
        np.testing.assert_allclose(z[~gone], mesh[~gone][:, :, 2], rtol=1e-6, atol=1e-4)
        np.testing.assert_array_equal(part[list(AU_COLUMNS)].to_numpy(), df[list(AU_COLUMNS)].to_numpy())
        n += len(df)
    assert n == len(csv) == s["n_rows"]
    with pytest.raises(ValueError, match="split"):
        write_pyfeat_tables(tmp_path / "x", SPEC, detector="v2", fmt="split")
