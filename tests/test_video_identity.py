"""A video is py-feat's ``input`` path, not its stem: two people's ``a/clip01.mp4`` and ``b/clip01.mp4`` stay two
videos through the ingest, prepare and the CV folds; the same path's frames twice name the files; a stem still picks a
video where it is unique. Duplicated column names in a header are refused. The reference is the generator's own
videos (their count and frames) and numpy."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from aumesh.core.errors import TableError
from aumesh.core.schema import AU_COLUMNS, POSE_COLUMNS
from aumesh.data import pyfeat, readers, tables
from aumesh.data.clip import read_clip, read_table
from aumesh.pipeline import ingest, prepare
from aumesh.pipeline.evaluate import video_folds
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from aumesh.synthetic.tables import SynthSpec
from conftest import default_config

SPEC = SynthSpec(n_frames=80, n_videos=4, seed=5)
OTHER = SynthSpec(n_frames=80, n_videos=4, seed=6)  # other people (seeds: faces and AUs), the same video names


def _cfg(data_dir: Path):
    cfg = default_config()
    return dataclasses.replace(cfg, paths=dataclasses.replace(cfg.paths, data_dir=str(data_dir)))


def _as_folder(csv: Path, out: Path, folder: str, frame_shift: int = 0) -> None:
    """``csv`` with py-feat's ``input`` ``videos/vid000000.mp4`` as ``<folder>/vid000000.mp4`` (what detect writes for
    videos of that folder), frames shifted by ``frame_shift``."""
    df = pd.read_csv(csv)
    df["input"] = df["input"].str.replace("videos/", f"{folder}/", regex=False)
    df["frame"] += frame_shift
    out.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(out, index=False)


@pytest.fixture(scope="module")
def two_folders(tmp_path_factory):
    """Two people's exports whose videos have the same file names in two folders: ``(made, data dir)``."""
    root = tmp_path_factory.mktemp("two_folders")
    a = write_pyfeat_tables(root / "raw_a", SPEC, extra_face_rate=0.0)
    b = write_pyfeat_tables(root / "raw_b", OTHER, extra_face_rate=0.0)
    return root, a, b


@pytest.mark.parametrize(
    "frame_shift", [10_000, pytest.param(0, marks=pytest.mark.slow)], ids=["frames-apart", "frames-collide"]
)
def test_same_named_videos_in_two_folders_are_two_videos(two_folders, frame_shift, tmp_path):
    root, a, b = two_folders
    data = tmp_path / "data"
    _as_folder(Path(a["files"][0]), data / "a.csv", "a")
    _as_folder(Path(b["files"][0]), data / "b.csv", "b", frame_shift)
    cfg = _cfg(data)
    manifest = ingest.run(cfg, tmp_path / "ingested")
    found = tables.check_tables(manifest["tables"], cfg.data.mesh_npy)
    summary = prepare.run(found, cfg, tmp_path / "prepared", ingested=manifest["counts"])
    assert summary["counts"]["videos_in"] == SPEC.n_videos + OTHER.n_videos  # 6 + 6, not 6
    frames = pd.read_parquet(tmp_path / "prepared" / "frames.parquet")
    ids = np.load(tmp_path / "prepared" / "video_ids.npy")
    every = {f"{f}/vid{v:06d}.mp4" for f in "ab" for v in range(SPEC.n_videos)}
    assert set(ids.tolist()) <= every and len(ids) == 8 - summary["counts"]["videos_dropped_no_frames_left"]
    assert {v.split("/")[0] for v in ids} == {"a", "b"}  # each video is its path
    # the rows of a/vid000000.mp4 and b/vid000000.mp4 are two videos of the CV: each its own index and frame count
    count = np.bincount(frames["video_index"].to_numpy(), minlength=len(ids))
    both = [v for v in range(SPEC.n_videos) if {f"{f}/vid{v:06d}.mp4" for f in "ab"} <= set(ids.tolist())]
    assert len(both) >= 2
    for v in both:
        ia, ib = (int(np.flatnonzero(ids == f"{f}/vid{v:06d}.mp4")[0]) for f in "ab")
        assert (frames["video_id"].to_numpy()[frames["video_index"].to_numpy() == ia] == ids[ia]).all()
        assert count[ia] > 0 and count[ib] > 0
    folds = video_folds(count, cfg.cv.n_splits)
    assert len(folds) == len(ids) and set(folds.tolist()) == set(range(cfg.cv.n_splits))


def test_one_videos_frames_twice_name_the_files_and_the_video(two_folders, tmp_path):
    root, a, _ = two_folders
    data = tmp_path / "data"
    data.mkdir()
    shutil.copy(a["files"][0], data / "clips.csv")
    shutil.copy(a["files"][0], data / "clips_copy.csv")  # the same export twice
    with pytest.raises(TableError) as err:
        ingest.run(_cfg(data), tmp_path / "ingested")
    message = str(err.value)
    assert "clips.csv" in message and "clips_copy.csv" in message and "'videos/vid000000.mp4'" in message
    assert "\n" not in message and "Fix:" in message


def test_a_frame_written_again_in_one_file_names_it(two_folders, tmp_path):
    root, a, _ = two_folders
    data = tmp_path / "data"
    data.mkdir()
    df = pd.read_csv(a["files"][0])
    again = df[df["input"] == "videos/vid000002.mp4"].head(5)
    pd.concat([df, again]).to_csv(data / "clips.csv", index=False)  # appended again at the end
    with pytest.raises(TableError, match=r"clips\.csv: frame \d+ of video 'videos/vid000002\.mp4' is written twice"):
        ingest.run(_cfg(data), tmp_path / "ingested")


def test_interleaved_exports_of_one_video_are_not_duplicates(two_folders, tmp_path):
    """Overlapping frame ranges are only a reason to look: the even and odd frames of a video in two files are one
    video, kept whole."""
    root, a, _ = two_folders
    data = tmp_path / "data"
    data.mkdir()
    df = pd.read_csv(a["files"][0])
    df[df["frame"] % 2 == 0].to_csv(data / "even.csv", index=False)
    df[df["frame"] % 2 == 1].to_csv(data / "odd.csv", index=False)
    manifest = ingest.run(_cfg(data), tmp_path / "ingested")
    assert manifest["counts"]["frames_out"] == a["n_face_frames"]


def test_a_stem_picks_a_video_where_unique_and_lists_the_candidates_where_not(two_folders, tmp_path):
    root, a, b = two_folders
    df = pd.concat(
        [
            pd.read_csv(a["files"][0]).assign(input=lambda d: d["input"].str.replace("videos/", "a/")),
            pd.read_csv(b["files"][0])
            .query("input != 'videos/vid000001.mp4'")
            .assign(input=lambda d: d["input"].str.replace("videos/", "b/")),
        ]
    )
    path = tmp_path / "both.csv"
    df.to_csv(path, index=False)
    table = read_table(path)
    assert len(table.videos) == 7
    assert table.names["a/vid000001.mp4"] == "vid000001"  # unique stem: shown and picked by it
    assert table.names["a/vid000000.mp4"] == "a/vid000000" and table.names["b/vid000000.mp4"] == "b/vid000000"
    picked = read_clip(path, video="vid000001", mesh_units=None)
    assert picked.video == "vid000001" and picked.video_id == "a/vid000001.mp4"
    whole = read_clip(path, video="b/vid000000.mp4", mesh_units=None)
    expect = df[(df["input"] == "b/vid000000.mp4") & (df["FaceScore"] > 0)]["AU12"].to_numpy()
    np.testing.assert_array_equal(np.sort(whole.aus[whole.has_face, AU_COLUMNS.index("AU12")]), np.sort(expect))
    with pytest.raises(TableError) as err:
        read_clip(path, video="vid000000", mesh_units=None)
    message = str(err.value)
    assert "2 videos are named 'vid000000'" in message and "a/vid000000.mp4" in message and "b/vid000000.mp4" in message
    assert "\n" not in message


@pytest.mark.parametrize(
    "videos",
    [
        ["a/clip01.mp4", "b/clip01.mp4", "c/clip02.mp4"],
        ["x/a/c.mp4", "y/a/c.mp4", "c"],
        ["a/clip01.mp4", "a/clip01.avi", "clip01"],
        ["/data/p1/s1/v.mp4", "/data/p2/s1/v.mp4", "/data/p2/s2/v.mp4"],
    ],
)
def test_video_names_are_unique_and_end_each_path(videos):
    names = pyfeat.video_names(videos)
    assert sorted(names) == sorted(videos) and len(set(names.values())) == len(videos)
    for v, name in names.items():
        stem = str(Path(v).with_suffix("")) if name != v else v
        assert stem.endswith(name), (v, name)  # a trailing part of the path (its extension dropped)
        unique_stem = sum(Path(w).stem == Path(v).stem for w in videos) == 1
        assert (name == Path(v).stem) == unique_stem or name == v


def _parquet_with_names(path: Path, names: list[str], n: int = 3) -> None:
    arrays = [pa.array(np.zeros(n)) if c not in ("input",) else pa.array(["v.mp4"] * n) for c in names]
    pq.write_table(pa.Table.from_arrays(arrays, names=names), path)


def test_a_duplicated_column_name_is_refused_naming_the_file_and_column(tmp_path):
    header = ["input", "frame", *AU_COLUMNS, *POSE_COLUMNS, "FaceRectWidth", "FaceRectHeight"]
    header += [f"{a}_{i}" for i in range(478) for a in "xyz"]
    csv = tmp_path / "dup.csv"
    csv.write_text(",".join([*header, "AU12"]) + "\n")  # AU12 twice
    with pytest.raises(TableError) as err:
        readers.open_source(csv, "{stem}.npy")
    assert str(err.value).startswith(f"{csv}: duplicated column name 'AU12' (2 times)") and "Fix:" in str(err.value)
    pq_path = tmp_path / "dup.parquet"
    _parquet_with_names(pq_path, [*header[: 2 + 20 + 3], "Pitch"])  # pyarrow writes duplicate names
    with pytest.raises(TableError, match=r"dup\.parquet: duplicated column name 'Pitch'"):
        readers.open_source(pq_path, "{stem}.npy")
    with pytest.raises(TableError, match=r"duplicated column name 'Pitch'"):
        tables.check_tables([pq_path], "{stem}.npy")
    from aumesh.pipeline.predict import table_header

    with pytest.raises(TableError, match=r"dup\.csv: duplicated column name 'AU12'"):
        table_header(csv)  # aumesh predict: pandas alone would read the first AU12 and rename the second AU12.1
    # names nothing reads may repeat (py-feat's ~2,000 other columns are never read)
    csv.write_text(",".join([*header, "notes", "notes"]) + "\n")
    assert readers.open_source(csv, "{stem}.npy").layout.detector == "MPDetector"
