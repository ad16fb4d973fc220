"""py-feat's own output trains as it is: CSV or parquet from either detector, the split layout, no-face rows, several
faces, normalized units and wild values. The reference is the same frames cleaned by hand (the generator's clean
tables: the main face of every frame with a face, in pixels), prepared by the same recipe."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from aumesh.core.errors import TableError
from aumesh.data import ingest as ingest_data
from aumesh.data import readers, tables
from aumesh.pipeline import ingest, prepare
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from aumesh.synthetic.tables import SynthSpec
from conftest import default_config

SPEC = SynthSpec(n_frames=450, n_videos=12, seed=3)  # 12 videos of ~38 frames: every layout, detector and fault
#: z written in the detector's crop units as float32 and converted back (x FaceRectWidth [/ 256]): a few float32 ulps
#: of coordinates of ~300 px (the prepared meshes of a table in pixels are bit for bit the clean tables')
Z_ROUND_TRIP = 1e-4


def _cfg(data_dir: Path, **overrides):
    cfg = default_config(**overrides)  # composed once per worker and overrides (conftest)
    return dataclasses.replace(cfg, paths=dataclasses.replace(cfg.paths, data_dir=str(data_dir)))


def _prepare(data_dir: Path, work: Path, **overrides) -> tuple[dict, Path]:
    """The ingest stage, then prepare on what it lists: (summary, prepared folder)."""
    cfg = _cfg(data_dir, **overrides)
    manifest = ingest.run(cfg, work / "ingested")
    found = tables.check_tables(manifest["tables"], cfg.data.mesh_npy, cfg.data.coerce_numeric)
    summary = prepare.run(found, cfg, work / "prepared", ingested=manifest["counts"])
    return summary, work / "prepared"


def _same_prepared(a: Path, b: Path, atol: float = 0.0) -> None:
    ma, mb = np.load(a / "meshes.npy"), np.load(b / "meshes.npy")
    assert ma.shape == mb.shape
    np.testing.assert_allclose(ma, mb, rtol=0, atol=atol)
    fa, fb = pd.read_parquet(a / "frames.parquet"), pd.read_parquet(b / "frames.parquet")
    pd.testing.assert_frame_equal(fa, fb)


@pytest.fixture(scope="module")
def pyfeat_data(tmp_path_factory):
    """``pyfeat_data(**kwargs)``: the folder of ``write_pyfeat_tables(folder, SPEC, **kwargs)``, written once per
    module for each set of arguments. Read-only: the ingest reads the tables in place (parquet) or converts them
    into its own folder (CSV); tests that corrupt a table do it on a copy."""
    root = tmp_path_factory.mktemp("pyfeat_data")
    made: dict[tuple, Path] = {}

    def get(**kwargs) -> Path:
        key = tuple(sorted(kwargs.items()))
        if key not in made:
            folder = root / f"data{len(made)}"
            write_pyfeat_tables(folder, SPEC, **kwargs)
            made[key] = folder
        return made[key]

    return get


@pytest.fixture(scope="module")
def clean_reference(tmp_path_factory):
    """The hand-cleaned tables (one per generated file) prepared by the recipe."""
    root = tmp_path_factory.mktemp("pyfeat")
    summary = write_pyfeat_tables(
        root / "mp_csv", SPEC, detector="mp", fmt="csv", clean_dir=root / "clean", videos_per_file=5
    )
    prepared_summary, prepared = _prepare(root / "clean", root / "clean_work")
    return root, summary, prepared_summary, prepared


def test_mpdetector_csv_trains_exactly_as_the_hand_cleaned_tables(clean_reference):
    root, made, clean_summary, clean_prepared = clean_reference
    summary, prepared = _prepare(root / "mp_csv", root / "mp_work")
    c = summary["counts"]
    assert c["rows_in"] == made["n_rows"]
    assert c["dropped_no_face"] == made["n_no_face"] > 0
    assert c["dropped_extra_faces"] == made["n_extra_faces"] > 0
    assert c["frames_with_several_faces"] == made["n_extra_faces"]
    assert c["frames_in"] == made["n_face_frames"] == clean_summary["counts"]["frames_in"]
    assert c["dropped_no_face_fraction"] == pytest.approx(made["n_no_face"] / made["n_rows"])
    assert c["rows_z_from_crop256"] == c["frames_in"] and c["rows_z_from_chip"] == 0
    _same_prepared(prepared, clean_prepared, atol=Z_ROUND_TRIP)


@pytest.mark.slow
@pytest.mark.parametrize("detector,fmt", [("v2", "csv"), ("mp", "parquet"), ("v2", "parquet"), ("mp", "split")])
def test_either_detector_in_any_format_matches_the_hand_cleaned_tables(
    clean_reference, pyfeat_data, detector, fmt, tmp_path
):
    root, made, _, clean_prepared = clean_reference
    data = pyfeat_data(detector=detector, fmt=fmt, videos_per_file=5)
    summary, prepared = _prepare(data, tmp_path / "work")
    assert summary["counts"]["dropped_no_face"] == made["n_no_face"]
    assert summary["counts"]["dropped_extra_faces"] == made["n_extra_faces"]
    _same_prepared(prepared, clean_prepared, atol=0.0 if fmt == "split" else Z_ROUND_TRIP)


def test_normalized_mesh_is_converted_to_pixels_with_the_frame_size(clean_reference, tmp_path):
    root, _, _, clean_prepared = clean_reference
    write_pyfeat_tables(tmp_path / "data", SPEC, detector="mp", fmt="csv", normalized=True, videos_per_file=5)
    summary, prepared = _prepare(tmp_path / "data", tmp_path / "work")
    assert summary["counts"]["rows_converted_from_normalized"] == summary["counts"]["frames_in"]
    # float32 division and multiplication by the frame size: a few ulps of coordinates of ~300 px
    _same_prepared(prepared, clean_prepared, atol=2e-3)
    ref = np.load(prepared / "reference.npz")["mean_aligned_mesh"]
    assert np.ptp(ref[:, 1]) > 50  # pixels, not 0-1 units


def test_normalized_mesh_without_frame_size_is_refused_with_the_fix(tmp_path):
    # 2 videos, not 12: the refusal follows from the table's columns and units, whatever its rows
    spec = dataclasses.replace(SPEC, n_frames=80, n_videos=2)
    write_pyfeat_tables(tmp_path / "data", spec, detector="mp", fmt="csv", normalized=True, frame_size=False)
    with pytest.raises(TableError, match=r"clip_0000\.csv: the mesh is in normalized image units.*FrameWidth"):
        _prepare(tmp_path / "data", tmp_path / "work")


def test_clean_parquet_is_read_in_place_not_copied(clean_reference, tmp_path):
    root, *_ = clean_reference
    cfg = _cfg(root / "clean")
    manifest = ingest.run(cfg, tmp_path / "ingested")
    assert all(e["read"] == "in place" for e in manifest["sources"])
    assert manifest["tables"] == [str(p) for p in sorted((root / "clean").glob("*.parquet"))]
    assert not list((tmp_path / "ingested" / "tables").iterdir())


def test_face_selection_error_refuses_frames_with_several_faces(clean_reference, tmp_path):
    root, *_ = clean_reference  # the MPDetector CSVs: frames with a background face in every file
    with pytest.raises(TableError, match=r"faces in frame .* data\.face_selection=largest"):
        _prepare(root / "mp_csv", tmp_path / "work", **{"data.face_selection": "error"})


def test_face_selection_identity_keeps_the_videos_subject(clean_reference, pyfeat_data, tmp_path):
    root, made, _, clean_prepared = clean_reference
    data = pyfeat_data(detector="mp", fmt="parquet", videos_per_file=5)
    summary, prepared = _prepare(data, tmp_path / "work", **{"data.face_selection": "identity"})
    assert summary["counts"]["dropped_frames_without_subject"] == 0
    _same_prepared(prepared, clean_prepared, atol=Z_ROUND_TRIP)


def test_identity_selection_picks_the_person_seen_most_not_the_largest_face():
    block = readers.Block(
        video=np.array(["v", "v", "v", "v"]),
        frame=np.array([0, 0, 1, 2]),
        values={"FaceRectWidth": np.array([10.0, 50, 10, 10]), "FaceRectHeight": np.array([10.0, 50, 10, 10])},
        identity=np.array(["Person_0", "Person_1", "Person_0", "Person_0"], dtype=object),
        mesh=np.zeros((4, 1434)),
    )
    layout = ingest_data.pyfeat.Layout(
        "MPDetector", "input", None, None, ("FaceRectWidth", "FaceRectHeight"), "Identity", None
    )
    subjects = ingest_data.main_identities({"v": {"Person_0": 3, "Person_1": 1}})
    keep, counts = ingest_data.select_faces(block, layout, "identity", subjects, "t")
    assert keep.tolist() == [0, 2, 3] and counts.extra_faces == 1
    keep, _ = ingest_data.select_faces(block, layout, "largest", None, "t")
    assert keep.tolist() == [1, 2, 3]


def test_csv_ranges_never_split_a_frame_and_give_the_same_tables(clean_reference, tmp_path, monkeypatch):
    root, *_ = clean_reference
    source = readers.open_source(sorted((root / "mp_csv").glob("*.csv"))[0], "{stem}.npy")
    spans = readers.csv_spans(source, range_bytes=200_000)  # ~12 rows a range
    assert len(spans) > 10
    assert spans[0].start > 0 and spans[-1].stop == source.path.stat().st_size
    assert all(a.stop == b.start for a, b in zip(spans[:-1], spans[1:], strict=True))
    whole = readers.read_span(readers.Span(source, spans[0].start, spans[-1].stop))
    parts = [readers.read_span(s) for s in spans]
    keys = [
        (
            str(p.column("input")[0]),
            p.column("frame")[0].as_py(),
            str(p.column("input")[-1]),
            p.column("frame")[-1].as_py(),
        )
        for p in parts
    ]
    for (_, _, last_video, last_frame), (first_video, first_frame, _, _) in zip(keys[:-1], keys[1:], strict=True):
        assert (last_video, last_frame) != (first_video, first_frame)  # a frame's faces stay in one range
    assert sum(p.num_rows for p in parts) == whole.num_rows
    monkeypatch.setattr(readers, "CSV_RANGE_BYTES", 200_000)
    out_small = tmp_path / "small.parquet"
    out_whole = tmp_path / "whole.parquet"
    ingest_data.write_clean(spans, out_small, "largest", None)
    ingest_data.write_clean([readers.Span(source, spans[0].start, spans[-1].stop)], out_whole, "largest", None)
    assert pq.read_table(out_small).equals(pq.read_table(out_whole))


def _corrupt(path: Path, cells: list[tuple[int, str]], value: float) -> None:
    df = pd.read_parquet(path)
    for row, column in cells:
        df.loc[row, column] = np.float32(value)
    df.to_parquet(path)


def test_wild_values_are_dropped_and_the_result_is_the_table_without_them(clean_reference, tmp_path):
    root, *_ = clean_reference
    data, without = tmp_path / "data", tmp_path / "without"
    data.mkdir(), without.mkdir()
    files = sorted((root / "clean").glob("*.parquet"))
    for f in files:
        (data / f.name).write_bytes(f.read_bytes())
        (without / f.name).write_bytes(f.read_bytes())
    # a corrupt export: 1e30 in three cells of non-anchor vertices (chin 152, mouth corner 61, cheek 234)
    cells = [(5, "y_152"), (40, "x_61"), (77, "z_234")]
    _corrupt(data / files[0].name, cells, 1e30)
    df = pd.read_parquet(without / files[0].name)
    df.drop(index=[r for r, _ in cells]).reset_index(drop=True).to_parquet(without / files[0].name)
    summary, prepared = _prepare(data, tmp_path / "w1")
    reference_summary, reference = _prepare(without, tmp_path / "w2")
    assert summary["counts"]["dropped_wild_values"] == 3 - _pose_dropped(df, [r for r, _ in cells])
    _same_prepared(prepared, reference)
    assert np.abs(np.load(prepared / "meshes.npy")).max() < 1e4


def _pose_dropped(df: pd.DataFrame, rows: list[int]) -> int:
    """Rows the pose filter drops before any alignment (never counted as wild)."""
    sub = df.loc[rows]
    return int(((np.abs(sub["Yaw"]) > np.deg2rad(40)) | (np.abs(sub["Pitch"]) > np.deg2rad(30))).sum())


def test_a_wild_anchor_cannot_bend_the_reference(clean_reference, tmp_path):
    root, _, _, clean_prepared = clean_reference
    data = tmp_path / "data"
    data.mkdir()
    for f in sorted((root / "clean").glob("*.parquet")):
        (data / f.name).write_bytes(f.read_bytes())
    first = sorted(data.glob("*.parquet"))[0]
    _corrupt(first, [(3, "x_33"), (9, "y_10")], 1e30)  # two anchors (outer canthus, forehead)
    summary, prepared = _prepare(data, tmp_path / "w")
    assert summary["counts"]["dropped_wild_values"] >= 1
    ref = np.load(prepared / "reference.npz")["reference_anchors"]
    np.testing.assert_allclose(ref, np.load(clean_prepared / "reference.npz")["reference_anchors"], atol=0.5)


def test_too_many_wild_frames_stop_the_run(clean_reference, tmp_path):
    root, *_ = clean_reference
    data = tmp_path / "data"
    data.mkdir()
    f = sorted((root / "clean").glob("*.parquet"))[0]
    df = pd.read_parquet(f)
    df.loc[: len(df) // 2, "y_152"] = np.float32(1e6)  # half the frames' chins far off
    df.to_parquet(data / f.name)
    with pytest.raises(TableError, match=r"wild values drops .*max_vertex_iod"):
        _prepare(data, tmp_path / "w")


def test_no_face_share_beyond_max_drop_fraction_stops_the_run(tmp_path):
    write_pyfeat_tables(tmp_path / "data", SPEC, detector="mp", fmt="csv", no_face_rate=0.4)
    with pytest.raises(TableError, match=r"no-face rows drops .*max_drop_fraction"):
        _prepare(tmp_path / "data", tmp_path / "work")


def test_a_face_row_with_some_values_missing_stays_an_error(tmp_path):
    write_pyfeat_tables(tmp_path / "data", SPEC, detector="mp", fmt="parquet", no_face_rate=0.0, extra_face_rate=0.0)
    path = sorted((tmp_path / "data").glob("*.parquet"))[0]
    df = pd.read_parquet(path)
    df.loc[7, "AU12"] = np.nan  # corruption, not a missing face
    df.to_parquet(path)
    with pytest.raises(TableError, match=r"column 'AU12' has 1 NaN"):
        _prepare(tmp_path / "data", tmp_path / "work")


def test_a_table_with_only_the_68_point_block_is_named(pyfeat_data, tmp_path):
    first = sorted(pyfeat_data(detector="v2", fmt="parquet", videos_per_file=5).glob("*.parquet"))[0]
    (tmp_path / "data").mkdir()
    df = pd.read_parquet(first)
    df.drop(columns=[c for c in df.columns if c.startswith("mesh_")]).to_parquet(tmp_path / "data" / first.name)
    with pytest.raises(TableError, match=r"68-point 2-D block.*not the 478-vertex mesh"):
        _prepare(tmp_path / "data", tmp_path / "work")


@pytest.mark.slow
def test_a_parquet_table_is_streamed_in_batches_without_splitting_a_frames_faces(tmp_path, monkeypatch):
    # 150 frames (~190 rows, ~40 with a second face) in batches of 7 rows: ~30 batches, many frames straddling a
    # batch boundary; the check is per batch, so more rows add time, not coverage (write_clean is ~50 ms a batch)
    spec = SynthSpec(n_frames=150, n_videos=3, seed=3)
    write_pyfeat_tables(tmp_path / "data", spec, detector="mp", fmt="parquet", extra_face_rate=0.3)
    path = sorted((tmp_path / "data").glob("*.parquet"))[0]
    if pq.read_metadata(path).num_row_groups != 1:  # one row group, as pandas writes (the generator's already is)
        pq.write_table(pq.read_table(path), path, row_group_size=1 << 20)
    source = readers.open_source(path, "{stem}.npy")
    whole = readers.Span(source, 0, source.n_rows)
    ingest_data.write_clean([whole], tmp_path / "one.parquet", "largest", None)
    monkeypatch.setattr(readers, "PARQUET_RANGE_ROWS", 7)  # batches of 7 rows: frames with 2 faces straddle them
    batches = list(readers.iter_span_tables(whole))
    assert len(batches) > 20 and sum(t.num_rows for _, t in batches) == source.n_rows
    assert any(t.num_rows != 7 for _, t in batches[:-1])  # a frame's faces were carried into the next batch
    assert all(a.stop == b.start for (a, _), (b, _) in zip(batches[:-1], batches[1:], strict=True))
    counts = ingest_data.write_clean([whole], tmp_path / "many.parquet", "largest", None)
    assert counts.extra_faces > 0
    assert pq.read_table(tmp_path / "many.parquet").equals(pq.read_table(tmp_path / "one.parquet"))
