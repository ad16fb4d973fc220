"""Issue 46, the data path of the input families: the 52 blendshapes and 7 emotions py-feat's detectors write are
carried by ingest and prepare into ``frames.parquet`` under the family's names, mapped by name (never by position),
and what is half there is refused in one line. The reference is the same CSVs read by another route: pandas, and the
detectors' names mapped by a dict written here from py-feat 2.1.5's lists (``feat/utils/__init__.py``
``MP_BLENDSHAPE_NAMES``, ``FEAT_EMOTION_COLUMNS``; ``feat/multitask/__init__.py`` ``EMOTION_NAMES_V24``)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from aumesh.core.errors import TableError
from aumesh.pipeline import ingest
from aumesh.stages import ingest as ingest_stage
from aumesh.stages import prepare as prepare_stage
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from aumesh.synthetic.tables import SynthSpec
from conftest import default_config

SPEC = SynthSpec(n_frames=300, n_videos=6, seed=3)  # the pose filter keeps >75 % of its frames

# py-feat 2.1.5's MP_BLENDSHAPE_NAMES, as written there (both detectors write these names)
PYFEAT_BLENDSHAPES = (
    "_neutral browDownLeft browDownRight browInnerUp browOuterUpLeft browOuterUpRight cheekPuff cheekSquintLeft "
    "cheekSquintRight eyeBlinkLeft eyeBlinkRight eyeLookDownLeft eyeLookDownRight eyeLookInLeft eyeLookInRight "
    "eyeLookOutLeft eyeLookOutRight eyeLookUpLeft eyeLookUpRight eyeSquintLeft eyeSquintRight eyeWideLeft "
    "eyeWideRight jawForward jawLeft jawOpen jawRight mouthClose mouthDimpleLeft mouthDimpleRight mouthFrownLeft "
    "mouthFrownRight mouthFunnel mouthLeft mouthLowerDownLeft mouthLowerDownRight mouthPressLeft mouthPressRight "
    "mouthPucker mouthRight mouthRollLower mouthRollUpper mouthShrugLower mouthShrugUpper mouthSmileLeft "
    "mouthSmileRight mouthStretchLeft mouthStretchRight mouthUpperUpLeft mouthUpperUpRight noseSneerLeft "
    "noseSneerRight"
).split()
# FEAT_EMOTION_COLUMNS (MPDetector's names) and Detectorv2's EMOTION_NAMES_V24 -> the FEAT_EMOTION_COLUMNS name
PYFEAT_EMOTIONS = ["anger", "disgust", "fear", "happiness", "sadness", "surprise", "neutral"]
DETECTOR_NAMES = {
    "mp": {**{b: b for b in PYFEAT_BLENDSHAPES}, **{e: e for e in PYFEAT_EMOTIONS}},
    "v2": {
        **{b: b for b in PYFEAT_BLENDSHAPES},
        "Neutral": "neutral",
        "Happy": "happiness",
        "Sad": "sadness",
        "Surprise": "surprise",
        "Fear": "fear",
        "Disgust": "disgust",
        "Anger": "anger",
    },
}


def _cfg(data_dir: Path):
    cfg = default_config()
    return dataclasses.replace(cfg, paths=dataclasses.replace(cfg.paths, data_dir=str(data_dir)))


def _ingest_prepare(data_dir: Path, work: Path) -> tuple[dict, pd.DataFrame]:
    """The ingest and prepare stages (``aumesh ingest``, ``aumesh prepare``): (manifest, frames.parquet)."""
    cfg = _cfg(data_dir)
    paths = dataclasses.replace(cfg.paths, ingested_dir=str(work / "ingested"), prepared_dir=str(work / "prepared"))
    cfg = dataclasses.replace(cfg, paths=paths)
    manifest = ingest_stage.main(cfg)
    prepare_stage.main(cfg)
    return manifest, pd.read_parquet(work / "prepared" / "frames.parquet")


@pytest.fixture(scope="module")
def pyfeat_csvs(tmp_path_factory):
    """``pyfeat_csvs(detector)``: a folder of that detector's CSVs with the family truth, written once per module."""
    made: dict[str, Path] = {}

    def get(detector: str) -> Path:
        if detector not in made:
            folder = tmp_path_factory.mktemp(f"families_{detector}")
            write_pyfeat_tables(folder, SPEC, detector=detector, family_truth=True, videos_per_file=3)
            made[detector] = folder
        return made[detector]

    return get


def _copy(src: Path, dst: Path, edit=None) -> Path:
    """The CSVs of ``src`` in ``dst``, each passed through ``edit(name, DataFrame)`` (None: as they are)."""
    dst.mkdir()
    for f in sorted(src.glob("*.csv")):
        df = pd.read_csv(f)
        (edit(f.name, df) if edit else df).to_csv(dst / f.name, index=False)
    return dst


@pytest.mark.parametrize("detector", ["mp", "v2"])
def test_both_detectors_families_reach_frames_parquet_under_the_family_names(pyfeat_csvs, tmp_path, detector):
    manifest, frames = _ingest_prepare(pyfeat_csvs(detector), tmp_path)
    assert manifest["families"] == {"carried": ["blendshapes", "emotions"], "not_carried": {}}
    names = DETECTOR_NAMES[detector]
    # the independent route: pandas reads the CSVs (its own decimal parser), keeps the main face of each frame and
    # renames the detector's columns by the dict above
    raw = pd.concat([pd.read_csv(f) for f in sorted(pyfeat_csvs(detector).glob("*.csv"))])
    main = raw[raw["Identity"] == "Person_0"].rename(columns={"input": "video_id"})
    as_read = frames[["video_id", "frame"]].merge(main, on=["video_id", "frame"], how="left", validate="one_to_one")
    expected = as_read.rename(columns=names)
    family = PYFEAT_BLENDSHAPES + PYFEAT_EMOTIONS
    assert list(frames.columns[-2 - len(family) : -2]) == family  # the family's order, after the pose
    assert len(frames) > 150 and (frames[family].dtypes == np.float64).all()
    np.testing.assert_array_equal(frames[family].to_numpy(), expected[family].to_numpy())
    # by name, never by position: Detectorv2's 'Happy' (its 2nd emotion column) is the family's 'happiness' (4th)
    happy = "Happy" if detector == "v2" else "happiness"
    np.testing.assert_array_equal(frames["happiness"].to_numpy(), as_read[happy].to_numpy())
    assert np.allclose(frames[PYFEAT_EMOTIONS].sum(axis=1), 1.0)


def test_a_detectorv2_table_in_its_own_emotion_order_lands_under_the_right_names(pyfeat_csvs, tmp_path):
    """Detectorv2's emotion columns in its checkpoint's order (Neutral, Happy, ...) with an eighth 'Contempt' (a v2.3
    checkpoint) and the header shuffled: each lands under its own family name, Contempt ignored."""
    rng = np.random.default_rng(0)

    def shuffled(name, df):
        df = pd.concat([df, pd.DataFrame({"Contempt": rng.uniform(0, 1, len(df))})], axis=1)
        return df[list(rng.permutation(df.columns))]

    data = _copy(pyfeat_csvs("v2"), tmp_path / "data", shuffled)
    _, frames = _ingest_prepare(data, tmp_path / "work")
    raw = pd.concat([pd.read_csv(f) for f in sorted(data.glob("*.csv"))])
    main = raw[raw["Identity"] == "Person_0"].rename(columns={"input": "video_id"})
    got = frames[["video_id", "frame"]].merge(main, on=["video_id", "frame"], how="left", validate="one_to_one")
    for v2, name in DETECTOR_NAMES["v2"].items():
        np.testing.assert_array_equal(frames[name].to_numpy(), got[v2].to_numpy(), err_msg=f"{v2} -> {name}")
    assert "Contempt" not in frames.columns


@pytest.mark.parametrize(("detector", "dropped"), [("mp", "jawOpen"), ("v2", "Happy"), ("mp", "neutral")])
def test_a_half_present_family_is_refused_in_one_line(pyfeat_csvs, tmp_path, detector, dropped):
    data = _copy(pyfeat_csvs(detector), tmp_path / "data", lambda name, df: df.drop(columns=[dropped]))
    with pytest.raises(TableError) as err:
        ingest.run(_cfg(data), tmp_path / "ingested")
    message = str(err.value)
    wanted = DETECTOR_NAMES[detector][dropped]
    family = "emotions" if wanted in PYFEAT_EMOTIONS else "blendshapes"
    assert "\n" not in message and "clip_0000.csv" in message and repr(wanted) in message
    assert family in message and "Fix:" in message


def test_a_family_absent_everywhere_is_simply_not_carried(pyfeat_csvs, tmp_path):
    emotions = [c for c, n in DETECTOR_NAMES["mp"].items() if n in PYFEAT_EMOTIONS]
    data = _copy(pyfeat_csvs("mp"), tmp_path / "data", lambda name, df: df.drop(columns=emotions))
    manifest, frames = _ingest_prepare(data, tmp_path / "work")
    assert manifest["families"] == {"carried": ["blendshapes"], "not_carried": {}}
    assert not set(PYFEAT_EMOTIONS) & set(frames.columns) and set(PYFEAT_BLENDSHAPES) <= set(frames.columns)


def test_a_family_held_by_some_files_only_is_not_carried_and_the_file_is_named(pyfeat_csvs, tmp_path):
    """Not filled in, not refused: the AUs and blendshapes train as before; the manifest and the prepared summary
    name the file without emotions."""
    emotions = [c for c, n in DETECTOR_NAMES["mp"].items() if n in PYFEAT_EMOTIONS]
    data = _copy(
        pyfeat_csvs("mp"), tmp_path / "data", lambda name, df: df.drop(columns=emotions) if "0001" in name else df
    )
    manifest, frames = _ingest_prepare(data, tmp_path / "work")
    assert manifest["families"]["carried"] == ["blendshapes"]
    why = manifest["families"]["not_carried"]["emotions"]
    assert "clip_0001.csv" in why and "clip_0000.csv" not in why and "Fix:" in why and "\n" not in why
    assert not set(PYFEAT_EMOTIONS) & set(frames.columns)
    summary = pd.read_json(tmp_path / "work" / "prepared" / "summary.json", typ="series")
    assert summary["families"] == manifest["families"]


def test_nan_in_a_family_column_of_a_face_row(pyfeat_csvs, tmp_path):
    """As the AUs: some of a row's values NaN is refused (file, column, line); the whole family NaN in every face row
    (MPDetector with ``emotion_model=None``) is the family not measured: not carried, the AUs train; NaN in some face
    rows only is refused."""
    face = None

    def partial(name, df):
        nonlocal face
        if "0001" in name:
            face = int(np.flatnonzero(df["Identity"].eq("Person_0"))[3])
            df.loc[face, "mouthSmileLeft"] = np.nan
        return df

    data = _copy(pyfeat_csvs("mp"), tmp_path / "partial", partial)
    with pytest.raises(TableError, match=r"clip_0001\.csv: blendshapes column 'mouthSmileLeft' is nan at line") as e:
        ingest.run(_cfg(data), tmp_path / "i1")
    assert f"line {face + 2}" in str(e.value) and "\n" not in str(e.value)

    def unmeasured(name, df):
        df[PYFEAT_EMOTIONS] = np.nan  # what MPDetector(emotion_model=None) writes
        return df

    data = _copy(pyfeat_csvs("mp"), tmp_path / "unmeasured", unmeasured)
    manifest, frames = _ingest_prepare(data, tmp_path / "work")
    assert (
        manifest["families"]["carried"] == ["blendshapes"] and "NaN" in manifest["families"]["not_carried"]["emotions"]
    )
    assert not set(PYFEAT_EMOTIONS) & set(frames.columns) and len(frames) > 150

    def some_rows(name, df):
        if "0000" in name:
            df.loc[np.flatnonzero(df["Identity"].eq("Person_0"))[:5], PYFEAT_EMOTIONS] = np.nan
        return df

    data = _copy(pyfeat_csvs("mp"), tmp_path / "some", some_rows)
    with pytest.raises(TableError, match=r"clip_0000\.csv: the emotions columns are NaN in 5 of \d+ face rows"):
        ingest.run(_cfg(data), tmp_path / "i3")
