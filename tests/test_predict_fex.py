"""`aumesh predict` and `aumesh.predict_mesh` on py-feat's own output (issue 32): whole Fex tables of either
detector, CSV or parquet, taken as they are: inputs picked by name, no-face rows NaN and flagged, near-miss names,
AU scale, degrees and out-of-range pose. The tables are built here with py-feat 2.1.5's column names."""

from __future__ import annotations

import json
import logging
import re
import warnings

import numpy as np
import pandas as pd
import pytest

import aumesh
from aumesh import cli
from aumesh.core.families import feature_set_columns
from aumesh.core.io import atomic_savez
from aumesh.core.schema import AU_COLUMNS, INPUT_COLUMNS, N_TARGETS
from aumesh.model.input_columns import PredictionInputError
from aumesh.model.release import release_arrays
from aumesh.synthetic.pyfeat_columns import BLENDSHAPE_COLUMNS
from conftest import face_reference

BLENDSHAPES = list(BLENDSHAPE_COLUMNS)
FACE_RECT = ["FaceRectX", "FaceRectY", "FaceRectWidth", "FaceRectHeight"]
POSE_FEX_ORDER = ["Pitch", "Roll", "Yaw"]  # py-feat's order; the model's is Pitch, Yaw, Roll
N_ROWS, NO_FACE_ROW = 6, 4


def fex_table(
    detector: str, rng: np.random.Generator, n: int = N_ROWS, no_face_row: int | None = NO_FACE_ROW, junk: bool = True
) -> pd.DataFrame:
    """A py-feat-shaped detector table (MPDetector: 2,045 columns; Detectorv2: its own layout), random values,
    AUs 0..1, pose in radians within the card's pose filter; ``no_face_row`` is py-feat's row for a frame
    without a face (FaceScore 0 or NaN, every measurement NaN, input/frame/approx_time filled)."""
    cols: dict[str, np.ndarray] = {c: rng.uniform(10, 200, n) for c in FACE_RECT}
    cols["FaceScore"] = rng.uniform(0.5, 1.0, n)
    if detector == "mp":
        cols |= {f"{a}_{i}": rng.uniform(0, 640, n) for i in range(478) for a in "xyz"}
    else:
        cols |= {f"{a}_{i}": rng.uniform(0, 640, n) for a in "xy" for i in range(68)}
    cols |= {"Pitch": rng.uniform(-0.4, 0.4, n), "Roll": rng.uniform(-0.6, 0.6, n), "Yaw": rng.uniform(-0.5, 0.5, n)}
    cols |= {c: rng.normal(size=n) for c in ("X", "Y", "Z")}
    if detector == "mp":
        cols |= {b: rng.random(n) for b in BLENDSHAPES}
    cols |= {a: rng.random(n) for a in AU_COLUMNS}
    if detector == "mp":
        cols |= {e: rng.random(n) for e in ("anger", "disgust", "fear", "happiness", "sadness", "surprise", "neutral")}
    else:
        cols |= {e: rng.random(n) for e in ("Neutral", "Happy", "Sad", "Surprise", "Fear", "Disgust", "Anger")}
        cols |= {"valence": rng.uniform(-1, 1, n), "arousal": rng.uniform(-1, 1, n)}
        cols |= {g: rng.normal(size=n) for g in ("gaze_pitch", "gaze_yaw", "gaze_angle")}
    cols |= {f"Identity_{i}": rng.normal(size=n) for i in range(1, 513)}
    if detector == "mp":
        cols |= {g: rng.normal(size=n) for g in ("gaze_pitch", "gaze_yaw", "gaze_angle")}
    else:
        cols |= {f"mesh_{a}_{i}": rng.uniform(0, 640, n) for a in "xyz" for i in range(478)}
        cols |= {b: rng.random(n) for b in BLENDSHAPES}
    cols |= {
        "FrameHeight": np.full(n, 480.0),
        "FrameWidth": np.full(n, 640.0),
        "input": np.full(n, "clips/video_01.mp4"),
        "frame": np.arange(n),
        "approx_time": np.array([f"00:{i // 30:02d}" for i in range(n)]),
        "Identity": np.full(n, "Person_0"),
    }
    if junk:
        cols |= {"notes": np.full(n, "junk"), "Unnamed: 0": np.arange(n)}
    if no_face_row is not None:  # in the arrays: df.loc over ~2,000 columns took most of a test's time
        kept = ("input", "frame", "approx_time", "FrameHeight", "FrameWidth", "notes", "Unnamed: 0")
        for c in cols:
            if c not in kept:
                cols[c] = cols[c].astype(object if cols[c].dtype.kind == "U" else np.float64)
                cols[c][no_face_row] = np.nan
        cols["FaceScore"][no_face_row] = 0.0 if detector == "mp" else np.nan
    return pd.DataFrame(cols)


def model_inputs(df: pd.DataFrame) -> np.ndarray:
    """(N, 23): the 20 AUs then Pitch, Yaw, Roll, by name (the card's input_columns)."""
    return np.array(df[list(INPUT_COLUMNS)].to_numpy(dtype=np.float64))


def card_snippet(release_path, x: np.ndarray) -> np.ndarray:
    """The card's inference with raw numpy: (N, 23) -> (N, 478, 3) = x @ coef + intercept, axis-major."""
    with np.load(release_path, allow_pickle=False) as m:
        flat = x @ m["coef"].astype(np.float64) + m["intercept"].astype(np.float64)
    return flat.reshape(len(x), 3, -1).transpose(0, 2, 1)


def write_release(tmp_path, features: str = "au_pose", metadata: dict | None = None, seed: int = 0):
    """A release NPZ of a random model (the 23-row ``coef`` is the whole model for ``au_pose``)."""
    rng = np.random.default_rng(seed)
    columns = feature_set_columns(features)
    coef, intercept = rng.normal(size=(N_TARGETS, len(columns))), rng.normal(size=N_TARGETS) + 300.0
    path = tmp_path / f"{features}-{seed}.npz"
    atomic_savez(
        path, **release_arrays(coef, intercept, columns, len(columns), face_reference(rng), "card", metadata or {})
    )
    return path


def write_table(df: pd.DataFrame, path):
    if path.suffix == ".csv":
        df.to_csv(path, index=False)
    else:
        df.to_parquet(path, index=False)
    return path


def run_predict(table, release, out, *extra) -> int:
    return cli.main(["predict", str(table), "--release", str(release), "--out", str(out), *extra])


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    assert err.startswith("aumesh predict: error: ") and err.count("\n") == 1, err
    assert len(err) < 700, f"{len(err)} characters: {err[:300]}"
    return err


class Fex(pd.DataFrame):
    """A DataFrame subclass, as py-feat's Fex is."""

    @property
    def _constructor(self):
        return Fex


# --------------------------------------------------------------------------- whole tables
@pytest.mark.parametrize("detector", ["mp", "v2"])
@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_cli_predicts_a_whole_fex_table_from_its_23_input_columns(tmp_path, capsys, detector, suffix):
    rng = np.random.default_rng(1)
    release = write_release(tmp_path)
    df = fex_table(detector, rng)
    table = write_table(df, tmp_path / f"fex{suffix}")
    out = tmp_path / "meshes.npz"
    assert run_predict(table, release, out) == 0
    assert f"wrote {N_ROWS} mesh(es)" in capsys.readouterr().out
    x = model_inputs(df)
    face = np.arange(N_ROWS) != NO_FACE_ROW
    expected = card_snippet(release, x[face])
    with np.load(out, allow_pickle=False) as z:
        assert z["meshes"].shape == (N_ROWS, 478, 3)
        np.testing.assert_allclose(z["meshes"][face], expected, rtol=1e-5, atol=1e-2)
        np.testing.assert_array_equal(z["no_face"], ~face)
        np.testing.assert_array_equal(z["au"], x[:, :20])  # NaN on the no-face row in both
        np.testing.assert_array_equal(z["pose"], x[:, 20:])  # the model's order, whatever the table's
        assert z["pose_columns"].tolist() == ["Pitch", "Yaw", "Roll"]


@pytest.mark.parametrize("detector", ["mp", "v2"])
def test_predict_mesh_takes_a_whole_fex_dataframe_as_its_23_input_columns(tmp_path, detector):
    df = fex_table(detector, np.random.default_rng(2))
    face = np.arange(N_ROWS) != NO_FACE_ROW
    for features in ("au_pose", "au_pose_interactions"):
        release = write_release(tmp_path, features)
        m = aumesh.load_release(release)
        got = aumesh.predict_mesh(m, df)
        assert got.shape == (N_ROWS, 478, 3)
        # the same as the 23 input columns alone (the path that existed before), no-face row aside
        np.testing.assert_allclose(got[face], aumesh.predict_mesh(m, df.loc[face, list(INPUT_COLUMNS)]), rtol=1e-12)
        np.testing.assert_allclose(aumesh.predict_mesh(m, Fex(df)), got, rtol=0, atol=0)  # py-feat's DataFrame subclass
        if features == "au_pose":  # and the card's snippet, with numpy
            np.testing.assert_allclose(got[face], card_snippet(release, model_inputs(df)[face]), rtol=1e-6, atol=1e-4)


# --------------------------------------------------------------------------- frames without a face
def test_no_face_rows_give_nan_meshes_and_are_flagged(tmp_path, caplog):
    release = write_release(tmp_path)
    m = aumesh.load_release(release)
    df = fex_table("mp", np.random.default_rng(3))
    df.loc[1, "FaceScore"] = 0.0  # FaceScore 0 marks a frame without a face even if values were left in it
    meshes = aumesh.predict_mesh(m, df)
    no_face = np.isin(np.arange(N_ROWS), [1, NO_FACE_ROW])
    assert np.isnan(meshes[no_face]).all() and np.isfinite(meshes[~no_face]).all()
    # an all-NaN row of numbers is a frame without a face too
    x = model_inputs(df)
    x[1] = np.nan
    np.testing.assert_array_equal(np.isnan(aumesh.predict_mesh(m, x[:, :20], x[:, 20:])).all(axis=(1, 2)), no_face)
    # the CLI flags them in the NPZ and says so in one line
    out = tmp_path / "m.npz"
    with caplog.at_level(logging.WARNING, logger="aumesh.pipeline.predict"):
        assert run_predict(write_table(df, tmp_path / "fex.parquet"), release, out) == 0
    with np.load(out, allow_pickle=False) as z:
        np.testing.assert_array_equal(z["no_face"], no_face)
        assert np.isnan(z["meshes"][no_face]).all() and np.isnan(z["au"][no_face]).all()
    assert any("2 of 6 row(s) without a face" in r.getMessage() for r in caplog.records)
    # a one-row mesh file of a frame without a face: nothing to draw
    write_table(df.iloc[[NO_FACE_ROW]], tmp_path / "none.csv")
    assert run_predict(tmp_path / "none.csv", release, tmp_path / "none.obj") == 2


def test_a_partly_nan_row_is_an_error_naming_the_row_and_the_column(tmp_path, capsys):
    release = write_release(tmp_path)
    df = fex_table("v2", np.random.default_rng(4))
    df.loc[2, "AU12"] = np.nan
    with pytest.raises(PredictionInputError, match=r"first in 'AU12' at row 2\. .*only partly NaN\. Fix: fill or drop"):
        aumesh.predict_mesh(release, df)
    assert run_predict(write_table(df, tmp_path / "fex.csv"), release, tmp_path / "m.npz") == 2
    assert re.search(r"fex\.csv: aus: 1 NaN/inf value\(s\), first in 'AU12' at row 2", one_line_error(capsys))


# --------------------------------------------------------------------------- strict, names
def test_strict_refuses_the_other_columns_in_one_line(tmp_path, capsys):
    release = write_release(tmp_path)
    df = fex_table("mp", np.random.default_rng(5))
    table = write_table(df, tmp_path / "fex.csv")
    assert run_predict(table, release, tmp_path / "m.npz", "--strict") == 2
    err = one_line_error(capsys)
    assert re.search(r"fex\.csv: unknown name\(s\) \['FaceRectX', .*\.\.\. \(2024 in all\)\]", err), err
    with pytest.raises(PredictionInputError, match=r"aus \(DataFrame\): unknown name\(s\) \['FaceRectX'"):
        aumesh.predict_mesh(release, df, strict=True)
    # the input columns alone pass strictly; --ignore leaves columns out first
    inputs_only = df[list(INPUT_COLUMNS) + ["frame"]].drop(index=NO_FACE_ROW)
    table = write_table(inputs_only, tmp_path / "inputs.csv")
    assert run_predict(table, release, tmp_path / "m.npz", "--strict", "--ignore", "frame") == 0
    assert aumesh.predict_mesh(release, inputs_only.drop(columns="frame"), strict=True).shape == (N_ROWS - 1, 478, 3)


@pytest.mark.parametrize(
    "column, misspelt", [("AU12", "AU_12"), ("AU12", "au12"), ("AU12", "AU12_r"), ("Yaw", "Yaw "), ("Pitch", "pitch")]
)
def test_a_near_miss_column_gets_a_did_you_mean(tmp_path, capsys, column, misspelt):
    release = write_release(tmp_path)
    df = fex_table("mp", np.random.default_rng(6)).rename(columns={column: misspelt})
    message = f"no column {column!r} (did you mean {misspelt!r}?)"
    with pytest.raises(PredictionInputError, match=re.escape(message)):
        aumesh.predict_mesh(release, df)
    assert run_predict(write_table(df, tmp_path / "fex.csv"), release, tmp_path / "m.npz") == 2
    assert message in one_line_error(capsys)
    # a name given directly (a mapping, a strict table) gets the hint the other way round
    with pytest.raises(PredictionInputError, match=re.escape(f"(did you mean {column!r} for {misspelt!r}?)")):
        aumesh.predict_mesh(release, {misspelt: 0.5})


def test_a_missing_au_without_a_near_miss_is_named_alone(tmp_path):
    df = fex_table("mp", np.random.default_rng(7)).rename(columns={"AU43": "AU45"})  # AU45 is not AU43
    with pytest.raises(
        PredictionInputError,
        match=r"no column 'AU43' \(no column has a name close to it\)\. "
        r"A table with columns besides the model's inputs needs all 20 AUs",
    ):
        aumesh.predict_mesh(write_release(tmp_path), df)


# --------------------------------------------------------------------------- scale and range
def test_aus_on_openfaces_0_to_5_scale_are_refused(tmp_path, capsys):
    from aumesh.model.input_checks import InputRangeWarning

    release = write_release(tmp_path)
    df = fex_table("mp", np.random.default_rng(8))
    df.loc[3, "AU12"] = 4.0
    message = r"AU12 = 4 at row 3 is above 1: .*Fix: divide the AU columns by 5"
    with pytest.raises(PredictionInputError, match=message):
        aumesh.predict_mesh(release, df)
    assert run_predict(write_table(df, tmp_path / "fex.parquet"), release, tmp_path / "m.npz") == 2
    assert re.search(r"fex\.parquet: aus: " + message, one_line_error(capsys))
    # numbers given directly are the caller's to choose: predicted, with a one-line warning naming the column
    with pytest.warns(InputRangeWarning, match=r"aus: AU12 = 4 at row 0 is above 1.*divide by 5"):
        aumesh.predict_mesh(release, {"AU12": 4.0})


def test_pose_in_degrees_is_refused(tmp_path, capsys):
    release = write_release(tmp_path)
    df = fex_table("v2", np.random.default_rng(9))
    df[POSE_FEX_ORDER] = np.rad2deg(df[POSE_FEX_ORDER])
    message = r"pose: \w+ reaches [\d.]+, more than pi/2: pose looks like degrees\. .*Fix: np\.deg2rad\(pose\)"
    with pytest.raises(PredictionInputError, match=message):
        aumesh.predict_mesh(release, df)
    assert run_predict(write_table(df, tmp_path / "fex.csv"), release, tmp_path / "m.npz") == 2
    assert re.search(message, one_line_error(capsys))


def test_pose_beyond_the_training_range_warns_in_one_line(tmp_path, caplog):
    from aumesh.model.input_checks import InputRangeWarning, training_pose_limits

    df = fex_table("mp", np.random.default_rng(10))
    df.loc[1, "Yaw"] = 0.9  # 51.6 deg, beyond the card's |yaw| <= 40 deg
    release = write_release(tmp_path)  # records no pose filter: the card's
    assert training_pose_limits(aumesh.load_release(release))[0] == pytest.approx(
        {"Pitch": np.deg2rad(30.0), "Yaw": np.deg2rad(40.0)}
    )
    with pytest.warns(
        InputRangeWarning,
        match=r"pose: Yaw = 0\.9 rad \(51\.6 deg\) at row 1 is beyond the training "
        r"range \|Yaw\| <= 40 deg \(the card's pose filter",
    ):
        meshes = aumesh.predict_mesh(release, df)
    assert np.isfinite(meshes[1]).all()  # predicted all the same
    # a release that records its pose filter: that range
    narrow = write_release(
        tmp_path,
        metadata={"config": {"preprocess": {"pose_filter": {"max_abs_yaw_deg": 20.0, "max_abs_pitch_deg": 10.0}}}},
        seed=1,
    )
    df[["Pitch", "Yaw"]] = 0.05
    df.loc[2, "Pitch"] = 0.3  # 17.2 deg
    with pytest.warns(InputRangeWarning, match=r"Pitch = 0\.3 rad .* at row 2 .*\|Pitch\| <= 10 deg \(the release's"):
        aumesh.predict_mesh(narrow, df)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # within range, every row with a face: silent (a no-face row says so: NoFaceWarning)
        aumesh.predict_mesh(narrow, df.drop(index=NO_FACE_ROW).assign(Pitch=0.0, Yaw=0.0))
    # the CLI logs it, one line
    with caplog.at_level(logging.WARNING, logger="aumesh.pipeline.predict"):
        assert run_predict(write_table(df, tmp_path / "fex.csv"), narrow, tmp_path / "m.npz") == 0
    lines = [r.getMessage() for r in caplog.records if "beyond the training range" in r.getMessage()]
    assert len(lines) == 1 and "\n" not in lines[0] and lines[0].startswith(str(tmp_path / "fex.csv"))


def test_the_training_metadata_of_a_real_release_names_the_pose_filter(tmp_path):
    """release_stage writes the whole model_card.json as training_metadata; its config holds the pose filter."""
    from aumesh.model.input_checks import training_pose_limits

    card = {"config": {"preprocess": {"pose_filter": {"max_abs_yaw_deg": 40.0, "max_abs_pitch_deg": 30.0}}}}
    release = write_release(tmp_path, metadata=card)
    limits, source = training_pose_limits(dict(np.load(release, allow_pickle=False)))
    assert source == "the release's pose filter" and json.loads(str(np.load(release)["training_metadata"])) == card
    assert limits == pytest.approx({"Pitch": np.deg2rad(30.0), "Yaw": np.deg2rad(40.0)})


# --------------------------------------------------------------------------- reading
def test_a_csv_is_read_for_the_needed_columns_only(tmp_path, monkeypatch):
    import pyarrow.csv as pacsv

    release = write_release(tmp_path)
    table = write_table(fex_table("mp", np.random.default_rng(11)), tmp_path / "fex.csv")
    frames, streams = [], []
    real_pandas, real_arrow = pd.read_csv, pacsv.read_csv

    def spy_pandas(*args, **kwargs):
        frames.append(kwargs)
        return real_pandas(*args, **kwargs)

    def spy_arrow(*args, **kwargs):
        streams.append(list(kwargs["convert_options"].include_columns))
        return real_arrow(*args, **kwargs)

    monkeypatch.setattr(pd, "read_csv", spy_pandas)
    monkeypatch.setattr(pacsv, "read_csv", spy_arrow)
    assert run_predict(table, release, tmp_path / "m.npz") == 0
    assert all(c.get("nrows") == 0 for c in frames)  # pandas reads no rows (the header: readers.csv_header)
    # the rows are streamed (pyarrow): the inputs, FaceScore, and py-feat's input and frame (the keys the NPZ joins
    # back on); the row count reads one of them
    needed = sorted([*INPUT_COLUMNS, "FaceScore", "input", "frame"])
    assert {tuple(sorted(c)) for c in streams if len(c) > 1} == {tuple(needed)}, streams
    assert all(set(c) <= set(needed) for c in streams), streams
