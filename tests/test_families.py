"""The input families (aumesh.core.families): names, order, and the mapping of each detector's header by name.

The independent reference for the emotion mapping is the meaning of the values, not the name lists: in the synthetic
py-feat tables each emotion's probability is driven by its prototypical AUs (happiness by AU12, disgust by AU09,
sadness by AU15), so a column mapped to the wrong emotion (a mapping by position, as emotion_to_mesh_pls_v5's labels
were) does not follow its AU.
"""

from __future__ import annotations

import random

import numpy as np
import pandas as pd
import pytest

from aumesh.core import families
from aumesh.core.errors import TableError
from aumesh.synthetic import tables as synth
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from aumesh.synthetic.pyfeat_columns import pyfeat_columns


@pytest.fixture(scope="module")
def detector_tables(tmp_path_factory) -> dict[str, pd.DataFrame]:
    """The same synthetic videos as MPDetector and as Detectorv2 write them (CSV, read back)."""
    spec = synth.SynthSpec(n_frames=600, n_videos=4, seed=5)
    out = {}
    for det in ("mp", "v2"):
        folder = tmp_path_factory.mktemp(f"fam-{det}")
        files = write_pyfeat_tables(folder, spec, detector=det, no_face_rate=0.0, extra_face_rate=0.0)["files"]
        out[det] = pd.concat([pd.read_csv(f) for f in files], ignore_index=True)
    return out


def test_family_lists_are_well_formed():
    bs = families.BLENDSHAPE_COLUMNS
    assert len(bs) == 52 and len(set(bs)) == 52 and bs[0] == "_neutral"
    # every lateral shape has its mirror (MediaPipe names the subject's side)
    for name in bs:
        if name.endswith("Left"):
            assert name[: -len("Left")] + "Right" in bs
    assert len(families.EMOTION_COLUMNS) == 7
    # Detectorv2's seven names map one to one onto the family
    assert sorted(families.EMOTION_NAME_MAP[c] for c in families.EMOTION_COLUMNS_V2) == sorted(families.EMOTION_COLUMNS)
    assert families.EMOTION_COLUMNS_V2 != families.EMOTION_COLUMNS  # the orders differ: position is not meaning


@pytest.mark.parametrize("det", ["mp", "v2"])
def test_both_detectors_headers_map_to_every_family(det):
    header = pyfeat_columns(det)
    for family, columns in families.FAMILIES.items():
        got = families.family_columns(header, family, source=f"{det}.csv")
        assert list(got) == list(columns)
        assert all(col in header for col in got.values())
    # the blendshapes are written under the family's own names, in its order, by both detectors
    bs = [c for c in header if c in families.BLENDSHAPE_COLUMNS]
    assert bs == list(families.BLENDSHAPE_COLUMNS)


@pytest.mark.parametrize("det", ["mp", "v2"])
def test_emotions_mapped_by_name_follow_their_prototype_aus(detector_tables, det):
    """Each mapped emotion column follows its own AU more than any other emotion column does (happiness ~ AU12,
    disgust ~ AU09, sadness ~ AU15): the values under each name are that emotion's."""
    df = detector_tables[det]
    cols = families.family_columns(df.columns, "emotions", source=f"{det}.csv")
    emo = df[list(cols.values())].to_numpy()
    assert np.allclose(emo.sum(axis=1), 1.0, atol=1e-6)  # a softmax, as both detectors write
    assert emo.min() >= 0.0 and emo.max() <= 1.0
    for emotion, au in (("happiness", "AU12"), ("disgust", "AU09"), ("sadness", "AU15")):
        r = [np.corrcoef(emo[:, k], df[au].to_numpy())[0, 1] for k in range(7)]
        assert int(np.argmax(r)) == list(cols).index(emotion), (det, emotion, au, np.round(r, 2))


def test_blendshapes_in_unit_range(detector_tables):
    for df in detector_tables.values():
        bs = df[list(families.BLENDSHAPE_COLUMNS)].to_numpy()
        assert np.nanmin(bs) >= 0.0 and np.nanmax(bs) <= 1.0


def test_permuted_header_still_maps_by_name():
    header = pyfeat_columns("v2")
    shuffled = header[:]
    random.Random(0).shuffle(shuffled)
    assert families.family_columns(shuffled, "emotions") == families.family_columns(header, "emotions")
    assert families.family_columns(shuffled, "emotions")["happiness"] == "Happy"
    # a v2.3 checkpoint's eighth class has no place in the family and is ignored
    assert families.family_columns([*header, "Contempt"], "emotions")["anger"] == "Anger"


@pytest.mark.parametrize("det,dropped", [("mp", "fear"), ("v2", "Fear")])
def test_missing_emotion_column_is_one_line(det, dropped):
    header = [c for c in pyfeat_columns(det) if c != dropped]
    with pytest.raises(TableError) as err:
        families.family_columns(header, "emotions", source="clips/a.csv")
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith("clips/a.csv: ") and "'fear'" in msg and "'Fear'" in msg and "Fix:" in msg


def test_two_columns_for_one_emotion_are_refused():
    header = [*pyfeat_columns("mp"), "Happy"]
    with pytest.raises(TableError, match=r"^t.csv: columns 'happiness' and 'Happy' both hold") as err:
        families.family_columns(header, "emotions", source="t.csv")
    assert "\n" not in str(err.value)


def test_unknown_family():
    with pytest.raises(ValueError, match="family='visemes'"):
        families.family_columns([], "visemes")
