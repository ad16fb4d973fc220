"""Issue 44: ``aumesh predict`` streams its table (chunks in, chunks out). The NPZ equals the one-shot route's (the
whole table read with pandas, checked, predicted and saved with ``np.savez``: the code before the stream) for any
chunk size; the input checks are one warning a run over the whole table, and errors name the table's row."""

from __future__ import annotations

import logging

import numpy as np
import pandas as pd
import pytest

from aumesh.core.schema import AU_COLUMNS, POSE_COLUMNS
from aumesh.model.inference import predict_rows
from aumesh.model.input_checks import input_rows
from aumesh.model.release_check import load_release
from aumesh.pipeline import predict, predict_stream
from test_predict_fex import fex_table, run_predict, write_release, write_table
from test_support import _release_with_support


def one_shot(release, table) -> dict[str, np.ndarray]:
    """The NPZ's arrays by the route before the stream: the whole table in memory (pandas), one check, one
    prediction, the keys by pandas' groupby over the whole table."""
    arrays = load_release(release)
    df, selection = predict.read_table(table, AU_COLUMNS, keys=predict.KEY_COLUMNS)
    au, pose, _ = input_rows(arrays, df, selection=selection)
    return {
        "meshes": predict_rows(arrays, au, pose).astype(np.float32),
        "no_face": np.isnan(au).all(axis=1),
        "au": au,
        "pose": pose,
        "au_columns": np.asarray(arrays["au_columns"]),
        "pose_columns": np.array(POSE_COLUMNS),
        **predict.row_keys(df),
    }


def pyfeat_video_table(rng: np.random.Generator) -> pd.DataFrame:
    """Two videos of py-feat rows: frames with two faces, frames without a face, and the same (video, frame) again
    far later in the file (a table concatenated from two runs): the face index must count across chunks."""
    parts = []
    for video, frames in (("clips/a.mp4", [0, 1, 1, 2, 3]), ("other/a.mp4", [0, 0, 1]), ("clips/a.mp4", [1, 4])):
        df = fex_table("mp", rng, n=len(frames), no_face_row=None, junk=False)
        df["input"], df["frame"] = video, frames
        parts.append(df)
    df = pd.concat(parts, ignore_index=True)
    df.loc[[2, 7], [*AU_COLUMNS, "Pitch", "Yaw", "Roll"]] = np.nan  # py-feat's rows for frames without a face
    df.loc[[2, 7], "FaceScore"] = np.nan
    df.loc[5, "FaceScore"] = 0.0
    return df


@pytest.fixture(scope="module")
def tables(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tables")
    rng = np.random.default_rng(7)
    fex = pyfeat_video_table(rng)
    inputs = pd.DataFrame(rng.uniform(0, 1, (11, 23)), columns=[*AU_COLUMNS, *POSE_COLUMNS])
    inputs[list(POSE_COLUMNS)] *= 0.3
    inputs.loc[4] = np.nan  # every input NaN: a frame without a face
    return {
        "pyfeat.csv": write_table(fex, tmp / "pyfeat.csv"),
        "pyfeat.parquet": write_table(fex, tmp / "pyfeat.parquet"),
        "v2.parquet": write_table(fex_table("v2", rng, n=9), tmp / "v2.parquet"),
        "inputs.csv": write_table(inputs, tmp / "inputs.csv"),
        "release": write_release(tmp),
    }


@pytest.mark.parametrize("chunk_rows", [1, 3])  # one chunk: the CLI tests of test_predict_fex
@pytest.mark.parametrize("name", ["pyfeat.csv", "pyfeat.parquet", "v2.parquet", "inputs.csv"])
def test_the_streamed_npz_equals_the_one_shot_one(tables, tmp_path, monkeypatch, name, chunk_rows):
    monkeypatch.setattr(predict_stream, "CSV_BLOCK_BYTES", 1 << 17)  # a few py-feat rows a CSV block
    monkeypatch.setattr(predict_stream, "COPY_ROWS", 2)  # the scratch files copied a few rows at a time too
    table, release = tables[name], tables["release"]
    out, n = predict.predict_table(release, table, tmp_path / "m.npz", chunk_rows=chunk_rows)
    expected = one_shot(release, table)
    with np.load(out, allow_pickle=False) as got:
        assert list(got.keys()) == list(expected)  # the same entries, in the same order
        for key, want in expected.items():
            assert got[key].dtype == want.dtype and got[key].shape == want.shape, key
            np.testing.assert_array_equal(got[key], want, err_msg=key)
    assert n == len(expected["meshes"])
    if name.startswith("pyfeat"):  # the keys join back: the repeated (video, frame) counted on, across chunks
        with np.load(out) as got:
            assert got["face"].tolist() == [0, 0, 1, 0, 0, 0, 1, 0, 2, 0]
            assert got["no_face"].tolist() == [i in (2, 5, 7) for i in range(10)]


def test_range_warnings_are_one_line_for_the_whole_table(tmp_path, caplog):
    """Rows beyond the training data in several chunks: one line, the table's first such row and the rows counted
    over the whole table (numpy's count of the table), the largest value over every chunk."""
    release = _release_with_support(tmp_path, "MPDetector")  # AU12's training max 0.6, AU09 never expressed
    rng = np.random.default_rng(3)
    df = pd.DataFrame({"AU12": rng.uniform(0, 0.5, 40), "AU09": 0.0, "Pitch": 0.0, "Yaw": 0.0, "Roll": 0.0})
    df.loc[[9, 21, 33], "AU12"] = [0.7, 0.95, 0.8]  # in the 2nd, 4th and 6th chunk of 6 rows
    df.loc[[14, 30], "Yaw"] = [0.9, -1.0]  # beyond the card's |yaw| <= 40 deg
    df.loc[[26], "AU09"] = 0.3
    table = write_table(df, tmp_path / "t.csv")
    with caplog.at_level(logging.WARNING, logger="aumesh.pipeline.predict"):
        predict.predict_table(release, table, tmp_path / "m.npz", chunk_rows=6)
    lines = [r.getMessage() for r in caplog.records if "beyond" in r.getMessage()]
    assert len(lines) == 1, lines
    line = lines[0]
    above = int(((df["AU12"] > 0.6) | (df["AU09"] > 0.035)).sum())  # rows above a training max, any AU
    assert f"AU12 up to {df['AU12'].max():.3g} (training max 0.6, p99 0.5)" in line
    assert f"beyond the training data ({above} row(s))" in line
    beyond_yaw = int((df["Yaw"].abs() > np.deg2rad(40)).sum())
    assert "Yaw = 0.9 rad (51.6 deg) at row 14 is beyond" in line and f"{beyond_yaw} row(s) beyond" in line
    assert "AU09 was never expressed" in line
    # the same table in one chunk: the same line (the chunking does not show)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="aumesh.pipeline.predict"):
        predict.predict_table(release, table, tmp_path / "m1.npz", chunk_rows=4096)
    assert [r.getMessage() for r in caplog.records if "beyond" in r.getMessage()] == lines


def test_an_error_in_a_later_chunk_names_the_tables_row_and_leaves_no_file(tables, tmp_path, capsys):
    df = pd.read_csv(tables["pyfeat.csv"])
    df.loc[8, "AU04"] = np.nan  # row 8: a partly NaN row, in the 3rd chunk of 3 rows
    table = write_table(df, tmp_path / "bad.csv")
    out = tmp_path / "m.npz"
    with pytest.raises(
        predict.PredictionInputError, match=r"bad\.csv: aus: 1 NaN/inf value\(s\), first in 'AU04' at row 8"
    ):
        predict.predict_table(tables["release"], table, out, chunk_rows=3)
    assert not out.exists() and list(tmp_path.iterdir()) == [table]  # no partial NPZ, no scratch folder left


def test_the_cli_marks_no_face_rows_in_one_line(tables, tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="aumesh.pipeline.predict"):
        assert run_predict(tables["pyfeat.csv"], tables["release"], tmp_path / "m.npz") == 0
    lines = [r.getMessage() for r in caplog.records if "without a face" in r.getMessage()]
    assert len(lines) == 1 and "3 of 10 row(s) without a face" in lines[0] and "no_face True in m.npz" in lines[0]
