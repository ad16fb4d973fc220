"""Two people of about the same size in every frame: the face kept follows one person through each video (py-feat's
Identity, else box continuity), whatever the CSV ranges and tasks; the ambiguous frames are counted in the ingest
manifest and the card. The reference is the generator's ground truth: which person each written row is."""

from __future__ import annotations

import dataclasses
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from aumesh.card.limits import release_warnings
from aumesh.card.model_card import _ingest_lines
from aumesh.core.schema import AU_COLUMNS
from aumesh.data import face_track, readers
from aumesh.data import ingest as ingest_data
from aumesh.pipeline import ingest
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from aumesh.synthetic.tables import SynthSpec
from conftest import default_config

SPEC = SynthSpec(n_frames=90, n_videos=3, seed=7)  # ~30 frames a video, ~2 rows a frame, ~18 KB a row


def _cfg(data_dir: Path):
    cfg = default_config()
    return dataclasses.replace(cfg, paths=dataclasses.replace(cfg.paths, data_dir=str(data_dir)))


@pytest.fixture(scope="module")
def twins(tmp_path_factory):
    """``(made, {"identity": folder, "boxes": folder}, truth)``: the twin-face export as written, and without py-feat's
    Identity column; ``truth`` is every written face row's person (the generator's Identity) and AUs."""
    root = tmp_path_factory.mktemp("twins")
    made = write_pyfeat_tables(root / "identity", SPEC, twin_face=True)
    df = pd.read_csv(made["files"][0])
    (root / "boxes").mkdir()
    df.drop(columns=["Identity"]).to_csv(root / "boxes" / "clip_0000.csv", index=False)
    truth = df[df["FaceScore"] > 0][["input", "frame", "Identity", "FaceRectWidth", "FaceRectHeight", *AU_COLUMNS]]
    return made, {"identity": root / "identity", "boxes": root / "boxes"}, truth


def _people(rows: pd.DataFrame, truth: pd.DataFrame) -> pd.Series:
    """Each kept row's person: the written face row of the same video and frame with the same AUs."""
    both = rows.merge(truth, left_on=["video_id", "frame"], right_on=["input", "frame"], suffixes=("", "_w"))
    gap = np.abs(both[list(AU_COLUMNS)].to_numpy() - both[[f"{c}_w" for c in AU_COLUMNS]].to_numpy()).max(axis=1)
    same = both[gap < 1e-9]
    assert len(same) == len(rows), "every kept row is one written face row"
    return same.set_index(["video_id", "frame"])["Identity"]


def _ingested(manifest: dict) -> pd.DataFrame:
    return pd.concat(pd.read_parquet(t, columns=["video_id", "frame", *AU_COLUMNS]) for t in manifest["tables"])


@pytest.mark.parametrize("by", ["identity", "boxes"])
def test_two_faces_of_a_size_keep_one_person_per_video(twins, by, tmp_path):
    made, folders, truth = twins
    manifest = ingest.run(_cfg(folders[by]), tmp_path / "ingested")
    people = _people(_ingested(manifest), truth)
    per_video = people.groupby(level="video_id").nunique()
    assert len(per_video) == SPEC.n_videos and (per_video == 1).all(), per_video
    # every face frame has the twin, of a size the largest-face rule cannot tell apart; the background faces are small
    assert manifest["counts"]["frames_ambiguous_faces"] == made["n_twin_faces"] == made["n_face_frames"]
    # the data exercise the mechanism: the largest face alone switches people within a video
    area = truth.assign(area=truth["FaceRectWidth"] * truth["FaceRectHeight"])
    largest = area.loc[area.groupby(["input", "frame"])["area"].idxmax()] if area.index.is_unique else None
    assert largest is not None and (largest.groupby("input")["Identity"].nunique() > 1).any()


def _clean(spans, seeds, task_spans: int, out: Path) -> pa.Table:
    """The spans cleaned as the stage does: packed ``task_spans`` a task, each task its own file, read back in order."""
    parts = []
    for i in range(0, len(spans), task_spans):
        path = out / f"{i:06d}.parquet"
        ingest_data.write_clean(spans[i : i + task_spans], path, "largest", None, "detector", seeds)
        parts.append(pq.read_table(path))
    return pa.concat_tables(parts)


@pytest.mark.parametrize("by", [pytest.param("identity", marks=pytest.mark.slow), "boxes"])
def test_the_rows_kept_do_not_depend_on_ranges_or_tasks(twins, by, tmp_path):
    _, folders, _ = twins
    source = readers.open_source(folders[by] / "clip_0000.csv", "{stem}.npy")
    whole = _clean(readers.csv_spans(source), {}, 1, tmp_path)
    cut_any = False
    for range_bytes, task_spans in ((400_000, 1), (250_000, 2)):
        spans = readers.csv_spans(source, range_bytes=range_bytes)
        cut_any |= any(s.carried for s in spans)
        seeds: ingest_data.Seeds = {}
        for chain in ingest_data.track_chains(spans):
            seeds |= ingest_data.carried_tracks(chain, "largest", None)
        (tmp_path / str(range_bytes)).mkdir(exist_ok=True)
        got = _clean(spans, seeds, task_spans, tmp_path / str(range_bytes))
        assert got.equals(whole), (range_bytes, task_spans)
    assert cut_any  # ranges cut inside a run of two-face frames: the carried tracks were needed


def test_the_stage_gives_the_same_tables_with_small_ranges_and_tasks(twins, tmp_path, monkeypatch):
    _, folders, _ = twins
    one = ingest.run(_cfg(folders["boxes"]), tmp_path / "one")
    monkeypatch.setattr(readers, "csv_spans", partial(readers.csv_spans, range_bytes=300_000))
    monkeypatch.setattr(ingest, "pack", partial(ingest.pack, task_rows=30))
    many = ingest.run(_cfg(folders["boxes"]), tmp_path / "many")
    assert len(many["tables"]) >= 3 > len(one["tables"])
    assert _ingested(many).reset_index(drop=True).equals(_ingested(one).reset_index(drop=True))
    assert many["counts"] == one["counts"]


def test_without_a_track_the_largest_face_is_kept_and_a_clear_largest_always_wins():
    centres = np.array([[0.0, 0.0], [100.0, 0.0], [0.0, 0.0], [100.0, 0.0]])
    areas = np.array([100.0, 95.0, 100.0, 130.0])
    assert face_track.choose(np.array([0, 1]), centres, areas, None, None) == 0
    track = face_track.Face((98.0, 1.0), 10.0, None)
    assert face_track.choose(np.array([0, 1]), centres, areas, None, track) == 1  # nearest the track
    ident = np.array(["P0", "P1", "P0", "P1"], dtype=object)
    assert face_track.choose(np.array([0, 1]), centres, areas, ident, face_track.Face((98.0, 1.0), 10.0, "P0")) == 0
    # frame 2 of a video: face 3 is clearly larger (130 vs 100 < 0.8 x 130): kept whatever the track
    video = np.array(["v", "v", "v", "v"])
    groups = np.array([0, 2, 4])
    largest = np.array([0, 3])
    chosen, n = face_track.follow(video, groups, largest, np.ones(4, bool), areas, centres, None, {"v": track})
    assert chosen.tolist() == [1, 3] and n == 1


def test_pyfeats_unknown_identity_is_no_person():
    """py-feat's hdbscan clustering labels faces it puts in no cluster "Unknown" (feat/utils/stats.py
    cluster_identities): two such faces are not one person, so a track so labelled follows the nearest box."""
    assert face_track.label("Unknown") is None and face_track.label("Person_0") == "Person_0"
    centres = np.array([[0.0, 0.0], [100.0, 0.0]])
    ident = np.array(["Unknown", "Person_1"], dtype=object)
    track = face_track.Face((98.0, 1.0), 10.0, face_track.label("Unknown"))
    assert face_track.choose(np.array([0, 1]), centres, np.array([100.0, 95.0]), ident, track) == 1


def test_the_card_says_how_many_frames_were_ambiguous():
    counts = {"frames_ambiguous_faces": 37, "frames_out": 370, "rows_in": 800, "dropped_no_face": 3}
    counts |= {"frames_with_several_faces": 40, "dropped_extra_faces": 41}
    (w,) = [w for w in release_warnings({"data": {"counts": counts}}) if w["code"] == "ambiguous_faces"]
    assert w["frames_ambiguous_faces"] == 37 and "37 frames (10.0% of the frames)" in w["message"]
    assert not [
        w
        for w in release_warnings({"data": {"counts": {**counts, "frames_ambiguous_faces": 0}}})
        if w["code"] == "ambiguous_faces"
    ]
    lines = "\n".join(_ingest_lines(counts, {"face_selection": "largest"}))
    assert "37 of them with two faces of about the same size" in lines
