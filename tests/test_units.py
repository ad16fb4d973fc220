"""py-feat's mesh units (docs/conventions.md "py-feat's mesh units"): z converted by each detector's crop, checked
against an independent route (the same frames written with z in pixels and ingested with ``data.mesh_units=pixels``),
the face-proportion guard, profile faces, and FaceRect missing where a conversion needs it."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from aumesh.card.model_card import _ingest_lines
from aumesh.core.errors import TableError
from aumesh.core.schema import N_VERTICES
from aumesh.data import pyfeat, readers
from aumesh.data import units as data_units
from aumesh.pipeline import evaluate as ev
from aumesh.pipeline import ingest
from aumesh.pipeline.evaluate.prepared_data import load_prepared
from aumesh.pipeline.integrity import load_reference
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from conftest import default_config
from test_ingest import SPEC, Z_ROUND_TRIP, _prepare, _same_prepared

PIXELS = {"data.mesh_units": "pixels"}


@pytest.fixture(scope="module")
def routes(tmp_path_factory):
    """The same synthetic frames as MPDetector and Detectorv2 CSVs, z in the detector's units (ingested by default)
    and z in pixels (ingested with data.mesh_units=pixels): route -> (prepare summary, prepared folder, manifest)."""
    root = tmp_path_factory.mktemp("units")
    out = {}
    for det in ("mp", "v2"):
        for z_pixels in (False, True):
            name = f"{det}-{'pixels' if z_pixels else 'native'}"
            write_pyfeat_tables(root / name, SPEC, detector=det, fmt="csv", z_pixels=z_pixels, videos_per_file=6)
            summary, prepared = _prepare(root / name, root / f"{name}-work", **(PIXELS if z_pixels else {}))
            manifest = json.loads((root / f"{name}-work" / "ingested" / ingest.MANIFEST_FILE).read_text())
            out[name] = (summary, prepared, manifest, root / name)
    return out


def _release(prepared: Path) -> dict[str, np.ndarray]:
    """The release's arrays (AU=0 face, AU fields) of the card's recipe fitted on ``prepared``."""
    cfg = default_config(**{"cv.n_splits": 3})
    data = load_prepared(prepared)
    _, final = ev.cross_validate_and_fit(data, cfg)
    return final.release_arrays(load_reference(prepared), metadata={})


@pytest.mark.slow
def test_native_units_and_pixels_give_the_same_prepared_meshes_and_release(routes):
    reference = routes["v2-pixels"][1]
    for name in ("mp-native", "v2-native", "mp-pixels"):
        _same_prepared(routes[name][1], reference, atol=Z_ROUND_TRIP)
    counts = {name: r[0]["counts"] for name, r in routes.items()}
    assert counts["v2-native"]["rows_z_from_chip"] == counts["v2-native"]["frames_in"] > 0
    assert counts["mp-native"]["rows_z_from_crop256"] == counts["mp-native"]["frames_in"]
    assert counts["v2-pixels"]["rows_z_from_chip"] == counts["mp-pixels"]["rows_z_from_crop256"] == 0
    native, pixels = _release(routes["mp-native"][1]), _release(routes["v2-pixels"][1])
    face = native["intercept"].reshape(3, N_VERTICES)
    width, height, depth = np.ptp(face, axis=1)
    assert 0.3 < depth / width < 0.7  # the template's 0.47: a face, not a cardboard cutout
    scale = np.abs(pixels["intercept"]).max()
    np.testing.assert_allclose(native["intercept"], pixels["intercept"], atol=1e-4 * scale)
    np.testing.assert_allclose(native["coef"], pixels["coef"], atol=1e-4 * np.abs(pixels["coef"]).max())


@pytest.mark.slow
def test_the_manifest_says_what_was_converted_per_source(routes):
    for name, (_, _, manifest, _) in routes.items():
        det = "MPDetector" if name.startswith("mp") else "Detectorv2"
        assert manifest["detectors"] == {det: 2}
        assert manifest["mesh_units"] == ("pixels" if name.endswith("pixels") else "detector")
        for entry in manifest["sources"]:
            units = entry["mesh_units"]
            z = {"mp-native": "crop256", "v2-native": "chip"}.get(name, "pixels")
            assert (units["xy"], units["z"]) == ("pixels", z)
            assert units["rows_converted"] == (units["rows"] if z != "pixels" else 0) and units["rows"] > 0
            assert ("FaceRectWidth" in units["how"]) == (z != "pixels")
            # the face's depth/height as ingested: the template's (0.34 frontal, more with yaw), whichever route
            assert 0.25 < entry["face_depth_over_height"]["ingested"] < 0.6
        # py-feat's Identity among the kept rows: each file's subject (the background person's rows are dropped)
        assert manifest["counts"]["identity_labels"] == 2


@pytest.mark.slow
def test_the_card_names_the_conversion_and_its_rows(routes):
    counts = routes["v2-native"][0]["counts"]
    line = _ingest_lines(counts, {"mesh_units": "detector"})[-1]
    assert line.startswith("- Mesh units: frame pixels; z of ")
    assert f"{counts['rows_z_from_chip']:,} Detectorv2 face rows converted from its 0-1 chip units" in line
    assert "other" not in line  # every row converted
    mixed = counts | {"frames_out": counts["frames_out"] + 7}  # 7 rows of a pixel table beside them
    assert _ingest_lines(mixed, {})[-1].endswith("; the other 7 rows in pixels as recorded")
    line = _ingest_lines(routes["mp-pixels"][0]["counts"], {"mesh_units": "pixels"})[-1]
    assert line == "- Mesh units: frame pixels, as recorded (data.mesh_units=pixels)"


@pytest.fixture(scope="module")
def v2_native(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("v2") / "data"
    spec = dataclasses.replace(SPEC, n_frames=120, n_videos=3)
    write_pyfeat_tables(folder, spec, detector="v2", fmt="csv", extra_face_rate=0.0)
    return folder


@pytest.mark.slow
def test_native_z_ingested_as_pixels_is_refused_with_the_fix(v2_native, tmp_path):
    # Detectorv2's z in 0-1 chip units taken as pixels: the flat face py-feat's real files gave (depth/width 0.001)
    with pytest.raises(TableError, match=r"clip_0000\.csv: the faces do not have a face's proportions") as err:
        ingest.run(_cfg(v2_native, **PIXELS), tmp_path / "ingested")
    message = str(err.value)
    assert "\n" not in message and "set data.mesh_units=detector" in message
    found = re.search(r"median depth/height (\S+) with z taken as pixels .*?; (\S+) with z converted", message)
    assert found, message
    flat, converted = float(found.group(1)), float(found.group(2))
    assert flat < 0.01 and 0.25 < converted < 0.6  # both routes measured and named


@pytest.mark.parametrize(
    "route,fix,slope", [("mp-native", "detector", (-0.3, 0.3)), ("mp-pixels", "pixels", (0.8, 1.3))]
)
@pytest.mark.slow
def test_mpdetector_units_are_told_by_how_z_grows_with_the_face(tmp_path, route, fix, slope):
    """An MPDetector face ~256 px wide has a face's depth/height in either unit: what tells them apart is that a
    face's depth in pixels grows with its size (slope ~1 of log z-extent on log height over near-frontal faces), and
    in the 256-px crop's units it does not (~0)."""
    forced = "pixels" if fix == "detector" else "detector"  # the wrong setting
    # one file of the 12 videos: ~100 near-frontal faces, sizes spread ~11 % (a file of 6 has too few to tell)
    write_pyfeat_tables(tmp_path / "data", SPEC, detector="mp", z_pixels=route.endswith("pixels"))
    with pytest.raises(
        TableError, match=rf"clip_0000\.csv: z as written grows .* Fix: set data\.mesh_units={fix}"
    ) as e:
        ingest.run(_cfg(tmp_path / "data", **{"data.mesh_units": forced}), tmp_path / "ingested")
    found = re.search(r"grows with the face's size as (\S+) ", str(e.value))
    assert found and slope[0] < float(found.group(1)) < slope[1]


def test_pixels_written_under_a_detectors_columns_are_refused_with_the_fix(tmp_path):
    # z already rescaled to pixels but ingested as py-feat's own export: z x FaceRectWidth again, a face ~100x deep
    spec = dataclasses.replace(SPEC, n_frames=120, n_videos=3)
    write_pyfeat_tables(tmp_path / "data", spec, detector="v2", fmt="parquet", z_pixels=True)
    with pytest.raises(TableError, match=r"clip_0000\.parquet: the faces do not have .* set data\.mesh_units=pixels"):
        ingest.run(_cfg(tmp_path / "data"), tmp_path / "ingested")


def _cfg(data_dir: Path, **overrides):
    cfg = default_config(**overrides)
    return dataclasses.replace(cfg, paths=dataclasses.replace(cfg.paths, data_dir=str(data_dir)))


@pytest.mark.slow
def test_profile_faces_ingest_and_the_pose_filter_drops_them(tmp_path):
    # yaw up to 89.5 deg: the 2-D inter-ocular distance of some faces falls below 1 px (the old unit judgement took
    # them for normalized coordinates and refused the set)
    # (faces without identity shape or much noise: in the generator their eyes' depths are then equal)
    spec = dataclasses.replace(
        SPEC, n_frames=200, n_videos=4, identity_scale=0.0, noise_px=0.05, profile_yaw_deg=(85.0, 89.8)
    )
    made = write_pyfeat_tables(tmp_path / "data", spec, detector="mp", fmt="csv", profile_rate=0.1, clean_dir=tmp_path)
    df = pd.read_csv(made["files"][0])
    main = df[df["Identity"] == "Person_0"]
    iod = np.hypot(main["x_33"] - main["x_263"], main["y_33"] - main["y_263"])
    assert (iod < 1.0).any()
    clean = pd.read_parquet(made["clean_files"][0])
    off_pose = int(((np.abs(clean["Yaw"]) > np.deg2rad(40)) | (np.abs(clean["Pitch"]) > np.deg2rad(30))).sum())
    profile = int((np.abs(clean["Yaw"]) >= np.deg2rad(84)).sum())
    assert profile > 0.05 * len(clean)
    summary, _ = _prepare(tmp_path / "data", tmp_path / "work")
    counts = summary["counts"]
    assert counts["rows_converted_from_normalized"] == 0 and counts["rows_z_from_crop256"] == len(clean)
    assert counts["dropped_pose"] == off_pose >= profile


def test_the_unit_judgement_sees_a_profile_face_in_pixels_and_any_face_in_normalized_units():
    from aumesh.synthetic.pyfeat_faces import synth_setup
    from aumesh.synthetic.tables import SynthSpec, generate_video

    spec = SynthSpec(
        n_frames=40,
        n_videos=1,
        seed=3,
        profile_rate=1.0,
        identity_scale=0.0,
        noise_px=0.05,
        profile_yaw_deg=(89.5, 89.9),
    )
    counts, args = synth_setup(spec)
    mesh = generate_video(spec, 0, 40, *args)["mesh"]  # (40, 478, 3) pixels, every frame in profile
    iod = np.linalg.norm(mesh[:, 33, :2] - mesh[:, 263, :2], axis=1)
    assert (iod < 1.0).mean() > 0.5  # what the inter-ocular test took for normalized coordinates
    flat = mesh.transpose(0, 2, 1).reshape(len(mesh), -1)
    assert not data_units.normalized_rows(flat).any()
    normalized = (mesh / [640.0, 480.0, 640.0]).transpose(0, 2, 1).reshape(len(mesh), -1)
    assert data_units.normalized_rows(normalized).all()
    side = np.ptp(mesh[:, :, 1], axis=1) * 1.3  # a FaceRect around the face, in pixels
    assert data_units.normalized_rows(normalized, side).all() and not data_units.normalized_rows(flat, side).any()


def test_a_normalized_parquet_is_cleaned_and_converted(tmp_path):
    spec = dataclasses.replace(SPEC, n_frames=120, n_videos=3)
    write_pyfeat_tables(tmp_path / "data", spec, fmt="parquet", normalized=True, no_face_rate=0, extra_face_rate=0)
    manifest = ingest.run(_cfg(tmp_path / "data", **PIXELS), tmp_path / "ingested")
    (entry,) = manifest["sources"]
    assert entry["read"] == "cleaned (normalized image units)"
    assert (entry["mesh_units"]["xy"], entry["mesh_units"]["z"]) == ("normalized", "normalized")
    assert manifest["counts"]["rows_converted_from_normalized"] == entry["mesh_units"]["rows_converted"] > 0


def test_an_mpdetector_parquet_is_converted_unless_its_z_is_pixels(tmp_path):
    spec = dataclasses.replace(SPEC, n_frames=120, n_videos=3)
    for z_pixels in (False, True):
        data = tmp_path / f"data{z_pixels}"
        write_pyfeat_tables(data, spec, fmt="parquet", z_pixels=z_pixels, no_face_rate=0, extra_face_rate=0)
        manifest = ingest.run(_cfg(data, **(PIXELS if z_pixels else {})), tmp_path / f"ingested{z_pixels}")
        (entry,) = manifest["sources"]
        assert entry["read"] == ("in place" if z_pixels else "cleaned (MPDetector z in its 256-px crop's units)")
        assert entry["mesh_units"]["z"] == ("pixels" if z_pixels else "crop256")
        assert 0.25 < entry["face_depth_over_height"]["ingested"] < 0.6


@pytest.mark.slow
def test_a_face_row_without_face_rect_width_is_named_with_the_fix(v2_native, tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    df = pd.read_csv(v2_native / "clip_0000.csv")
    row = int(np.flatnonzero(df["FaceScore"].notna().to_numpy())[5])
    df.loc[row, "FaceRectWidth"] = np.nan
    df.to_csv(data / "clip_0000.csv", index=False)
    frame, video = int(df.loc[row, "frame"]), re.escape(df.loc[row, "input"])  # the video is its input path
    with pytest.raises(
        TableError,
        match=rf"clip_0000\.csv: column 'FaceRectWidth' is nan on a face row \(frame "
        rf"{frame} of video '{video}'; 1 such rows\).*Fix: .*data\.mesh_units=pixels",
    ):
        ingest.run(_cfg(data), tmp_path / "ingested")
    df.drop(columns=["FaceRectX", "FaceRectY", "FaceRectWidth", "FaceRectHeight"]).to_csv(
        data / "clip_0000.csv", index=False
    )
    with pytest.raises(TableError, match=r"clip_0000\.csv: column 'FaceRectWidth' is missing: Detectorv2's z"):
        ingest.run(_cfg(data), tmp_path / "ingested2")


def test_the_mixed_units_message_names_the_video_as_text():
    mesh = np.ones((2, 3 * N_VERTICES), np.float32)
    mesh[0, :N_VERTICES] = np.linspace(0, 200, N_VERTICES)  # pixels
    mesh[0, N_VERTICES : 2 * N_VERTICES] = np.linspace(0, 300, N_VERTICES)
    mesh[1, : 2 * N_VERTICES] = np.linspace(0, 0.4, 2 * N_VERTICES)  # normalized
    block = readers.Block(video=np.array(["a", "clip7"]), frame=np.array([0, 3]), values={}, identity=None, mesh=mesh)
    layout = pyfeat.Layout("table", "video_id", None, None, None, None, None)
    with pytest.raises(TableError, match=r"^t: mixes .* \(frame 3 of video 'clip7' differs"):
        data_units.convert_units(block, layout, "detector", "t")


def test_the_depth_height_histograms_merge_to_numpys_median():
    rng = np.random.default_rng(4)
    ratios = np.exp(rng.normal(np.log(0.5), 0.4, 5001))
    parts = [data_units.ratio_hist(p) for p in np.array_split(ratios, [1000, 3500])]
    merged = parts[0] + parts[1] + parts[2]
    assert merged.counts.sum() == len(ratios)
    assert merged.median() == pytest.approx(np.median(ratios), rel=0.012)  # half a 0.01-decade bin
    flat = data_units.ratio_hist(np.array([0.0, 1e-3, np.nan, np.inf]))  # non-finite values are not faces
    assert flat.counts.sum() == 2 and flat.median() < 1.1e-3
