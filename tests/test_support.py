"""What a release's data supports (issue 41, items 4, 5 and 7): the input ranges prepare records, the card's and the
NPZ's record of them, and the warnings beyond them."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from aumesh.core.schema import AU_COLUMNS, INPUT_COLUMNS
from aumesh.model import support
from conftest import default_config


def _expected_ranges(frames: pd.DataFrame) -> dict:
    """The independent reference: np.quantile and a count over the prepared frames, column by column."""
    out = {}
    for name in INPUT_COLUMNS:
        v = frames[name].to_numpy(np.float64)
        out[name] = {
            "min": float(v.min()),
            "p1": float(np.quantile(v, 0.01)),
            "p50": float(np.quantile(v, 0.5)),
            "p99": float(np.quantile(v, 0.99)),
            "max": float(v.max()),
            "active_fraction": float(np.mean(v > 0.1)) if name in AU_COLUMNS else None,
        }
    return out


def test_prepared_input_ranges_are_numpys_quantiles_of_the_fitted_frames(recovery_prepared):
    """summary.json's input_ranges: np.quantile (and the share above 0.1) of each input over frames.parquet, the
    frames the model is fitted on, exactly."""
    prepared = recovery_prepared / "prepared"
    summary = json.loads((prepared / "summary.json").read_text())
    frames = pd.read_parquet(prepared / "frames.parquet")
    assert len(frames) == summary["n_frames"]
    assert summary["input_ranges"] == _expected_ranges(frames)


@pytest.mark.slow
def test_ranges_over_several_partitions_equal_one_quantile_of_the_kept_frames(small_tables, tmp_path):
    """Partitions of 64 rows (many row groups, outliers dropped in each): still np.quantile of the kept frames."""
    import pyarrow.parquet as pq

    from aumesh.data import tables

    for path in small_tables.glob("*.parquet"):  # row groups of 37 rows: partitions are whole row groups
        pq.write_table(pq.read_table(path), path, row_group_size=37)
    from aumesh.pipeline import prepare

    cfg = default_config(**{"paths.data_dir": str(small_tables), "compute.partition_rows": 64})
    found = tables.discover(small_tables, cfg.data.tables, cfg.data.mesh_npy)
    summary = prepare.run(found, cfg, tmp_path / "prepared", detectors={"MPDetector": 2})
    frames = pd.read_parquet(tmp_path / "prepared" / "frames.parquet")
    assert pq.ParquetFile(tmp_path / "prepared" / "frames.parquet").metadata.num_row_groups > 1  # one per partition
    assert summary["counts"]["dropped_alignment_outliers"] > 0  # the ranges are over the kept frames only
    assert summary["input_ranges"] == _expected_ranges(frames)
    assert summary["detector"]["name"] == "MPDetector"
    assert summary["detector"]["au_meaning"] == support.AU_MEANING["MPDetector"]


# ------------------------------------------------------------------------------------------- a single-person set
@pytest.fixture(scope="module")
def single_person(tmp_path_factory):
    """A small set of one person (three clips, no identity differences) whose AU09 never exceeds 0.035 (the issue's
    real clips), prepared; and a release made from its summary as the release stage makes it (card data -> NPZ):
    ``(summary, frames, release arrays)``."""
    import pyarrow.parquet as pq

    from aumesh.data import tables
    from aumesh.geometry import face
    from aumesh.model.release import release_arrays
    from aumesh.pipeline import prepare
    from aumesh.synthetic import tables as synth
    from aumesh.synthetic.truth import synthetic_release_arrays

    d = tmp_path_factory.mktemp("single")
    synth.write_tables(d / "data", synth.SynthSpec(n_frames=240, n_videos=3, seed=5, identity_scale=0.0))
    for path in (d / "data").glob("*.parquet"):
        t = pq.read_table(path)
        j = t.schema.get_field_index("AU09")
        au09 = t.column(j).to_numpy() * 0.035 / max(float(t.column(j).to_numpy().max()), 1e-9)
        pq.write_table(
            t.set_column(j, t.schema.field(j), [au09.astype(t.schema.field(j).type.to_pandas_dtype())]), path
        )
    cfg = default_config(**{"paths.data_dir": str(d / "data")})
    found = tables.discover(d / "data", cfg.data.tables, cfg.data.mesh_npy)
    summary = prepare.run(found, cfg, d / "prepared", detectors={"Detectorv2": 3})
    frames = pd.read_parquet(d / "prepared" / "frames.parquet")
    truth = synthetic_release_arrays(120.0 * face.canonical_template() * np.array([1.0, -1.0, -1.0]))
    reference = {k: truth[k] for k in ("mean_aligned_mesh", "mean_low_au_mesh", "reference_anchors", "anchor_indices")}
    card = {"data": support.data_support(summary), "config": cfg.to_dict()}
    arrays = release_arrays(truth["coef"].T, truth["intercept"], list(INPUT_COLUMNS), 23, reference, "", card)
    return summary, frames, arrays


def test_single_person_set_au09_at_one_warns_in_one_line_and_an_in_range_input_does_not(single_person):
    import warnings

    import aumesh
    from aumesh.model.input_checks import InputRangeWarning

    summary, frames, arrays = single_person
    assert frames["AU09"].max() <= 0.035 + 1e-6
    assert summary["detector"]["name"] == "Detectorv2"
    with pytest.warns(InputRangeWarning) as caught:
        aumesh.predict_mesh(arrays, {"AU09": 1.0})
    assert len(caught) == 1  # once per call
    message = str(caught[0].message)
    assert "\n" not in message
    train = summary["input_ranges"]["AU09"]
    assert f"AU09 up to 1 (training max {train['max']:.3g}, p99 {train['p99']:.3g})" in message
    assert "AU09 was never expressed in the training data" in message
    # within every AU's training range (the medians of the frames): silent
    inside = {a: float(frames[a].median()) for a in AU_COLUMNS}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        aumesh.predict_mesh(arrays, inside)
        # the training frames themselves, but where the unsupported AU09 is at most py-feat's 0.02
        aumesh.predict_mesh(arrays, frames.loc[frames["AU09"] <= 0.02, list(AU_COLUMNS)])
        aumesh.predict_mesh(arrays, {"AU09": 0.02})  # py-feat's threshold for an unsupported input


def test_one_warning_per_call_names_every_problem(single_person):
    """An AU above 1 (as numbers), an AU above its training max and a yaw beyond the pose filter: one line."""
    import aumesh
    from aumesh.model.input_checks import InputRangeWarning

    _, frames, arrays = single_person
    aus = np.zeros((3, 20))
    aus[0, AU_COLUMNS.index("AU12")] = 4.0  # OpenFace's scale
    aus[1, AU_COLUMNS.index("AU26")] = float(frames["AU26"].max()) + 0.2
    with pytest.warns(InputRangeWarning) as caught:
        aumesh.predict_mesh(arrays, aus, pose=[0.0, 1.2, 0.0])
    assert len(caught) == 1
    message = str(caught[0].message)
    for part in ("AU12 = 4 at row 0 is above 1", "AU26 up to", "AU12 up to 4", "pose: Yaw = 1.2 rad"):
        assert part in message, (part, message)


def test_release_npz_records_p99_and_unsupported_and_old_releases_still_load(single_person, tmp_path):
    import warnings

    import aumesh
    from aumesh.core.io import atomic_savez
    from aumesh.model.release_check import ReleaseError

    summary, frames, arrays = single_person
    path = atomic_savez(tmp_path / "release.npz", **arrays)
    loaded = aumesh.load_release(path)
    np.testing.assert_array_equal(
        loaded["feature_p99"],
        np.quantile(frames[list(INPUT_COLUMNS)].to_numpy(np.float64), 0.99, axis=0).astype(np.float32),
    )
    assert loaded["unsupported_features"].tolist() == ["AU09"]
    meta = json.loads(str(loaded["training_metadata"]))
    assert meta["data"]["detector"]["au_meaning"] == support.AU_MEANING["Detectorv2"]
    assert meta["data"]["unsupported_inputs"] == ["AU09"]
    # an old release (no new keys, no ranges in its metadata) loads, predicts and warns only as before
    old = {k: v for k, v in arrays.items() if k not in ("feature_p99", "unsupported_features")}
    old["training_metadata"] = np.array(json.dumps({"config": meta["config"]}))
    atomic_savez(tmp_path / "old.npz", **old)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        aumesh.predict_mesh(aumesh.load_release(tmp_path / "old.npz"), {"AU09": 1.0})
    # py-feat's keys alone (no card ranges): p99 is the bound, unsupported still warns
    bare = dict(old, feature_p99=arrays["feature_p99"], unsupported_features=arrays["unsupported_features"])
    with pytest.warns(aumesh.InputRangeWarning, match=r"AU09 up to 1 \(training p99 .*never expressed"):
        aumesh.predict_mesh(bare, {"AU09": 1.0})
    with pytest.raises(ReleaseError, match="'feature_p99' must be \\(23,\\)"):
        aumesh.load_release(dict(arrays, feature_p99=np.zeros(20, np.float32)))
    with pytest.raises(ReleaseError, match="'unsupported_features' must be"):
        aumesh.load_release(dict(arrays, unsupported_features=np.array(["AU99"])))


# ------------------------------------------------------------------------------------------- the AU space
def test_detector_summary_and_counts_from_a_manifest_with_or_without_detectors():
    assert support.detector_counts({"sources": [{"detector": "MPDetector"}, {"detector": "MPDetector"}]}) == {
        "MPDetector": 2
    }
    assert support.detector_counts({"detectors": {"Detectorv2": 3, "MPDetector": 0}, "sources": []}) == {
        "Detectorv2": 3
    }
    assert support.detector_summary({"Detectorv2": 3})["name"] == "Detectorv2"
    assert support.detector_summary({"Detectorv2": 1, "MPDetector": 1})["name"] == "mixed"
    assert support.detector_summary({"MPDetector": 1, "split": 2})["name"] == "mixed"
    assert support.detector_summary({"split": 2})["name"] == "unknown"
    assert support.detector_summary({})["name"] == "unknown"
    assert "probabilit" in support.AU_MEANING["Detectorv2"] and "blendshape" in support.AU_MEANING["MPDetector"]
    people = support.people_summary({"identity_labels": 1}, 3)
    assert people["identity_labels"] == 1 and "Identity" in people["note"]
    assert support.people_summary({}, 3)["identity_labels"] is None


def test_a_real_pipelines_card_npz_and_rig_record_the_datas_support(good_workspace):
    """The release stage end to end (conftest's good workspace): card JSON, MODEL_CARD.md, NPZ and glb agree with
    prepare's summary."""
    from aumesh.export.gltf import GLB_NAME
    from aumesh.model.release import load_npz

    summary = json.loads((good_workspace / "build" / "prepared" / "summary.json").read_text())
    card = json.loads((good_workspace / "release" / "model_card.json").read_text())
    assert card["data"]["input_ranges"] == summary["input_ranges"]
    expected = [a for a in AU_COLUMNS if summary["input_ranges"][a]["p99"] < support.UNSUPPORTED_P99]
    assert card["data"]["unsupported_inputs"] == expected
    assert card["data"]["detector"] == summary["detector"]
    assert set(card["data"]["people"]) == {"identity_labels", "note"}
    npz = load_npz(good_workspace / "release" / "au_to_mesh_pls.npz")
    np.testing.assert_array_equal(
        npz["feature_p99"], np.array([summary["input_ranges"][c]["p99"] for c in INPUT_COLUMNS], np.float32)
    )
    assert npz["unsupported_features"].tolist() == expected
    assert json.loads(str(npz["training_metadata"]))["data"]["detector"]["name"] == summary["detector"]["name"]
    md = (good_workspace / "release" / "MODEL_CARD.md").read_text()
    training = md.split("## Training data")[1].split("\n## ")[0]
    assert f"- AU space: **{summary['detector']['name']}**" in training
    glb = (good_workspace / "release" / GLB_NAME).read_bytes()
    import struct

    length = struct.unpack("<I", glb[12:16])[0]
    extras = json.loads(glb[20 : 20 + length])["asset"]["extras"]
    assert extras["training_range"]["AU12"]["max"] == summary["input_ranges"]["AU12"]["max"]
    assert extras.get("unsupported_targets", []) == expected  # pygltflib leaves an empty list out


# ------------------------------------------------------------------------------------------- predict, animate, pyfunc
def _release_with_support(tmp_path, detector: str, ranges: dict | None = None):
    """The upright synthetic-truth release, recording training ranges (AU09 never expressed, AU12 at most 0.6) and
    the training tables' detector, as the release stage does."""
    from aumesh.core.io import atomic_savez
    from aumesh.model.release import load_npz
    from conftest import upright_truth_release

    arrays = load_npz(upright_truth_release(tmp_path / "truth.npz"))
    if ranges is None:
        ranges = {c: support.range_record([0.0, 0.0, 0.2, 0.95, 1.0], 0.5) for c in INPUT_COLUMNS}
        ranges["AU09"] = support.range_record([0.0, 0.0, 0.01, 0.03, 0.035], 0.0)
        ranges["AU12"] = support.range_record([0.0, 0.0, 0.1, 0.5, 0.6], 0.3)
    meta = {
        "data": {
            "input_ranges": ranges,
            "unsupported_inputs": support.unsupported_inputs(ranges),
            "detector": support.detector_summary({detector: 1}),
        }
    }
    arrays.update(
        training_metadata=np.array(json.dumps(meta)),
        feature_p99=support.feature_p99(ranges),
        unsupported_features=np.array(support.unsupported_inputs(ranges)),
    )
    return atomic_savez(tmp_path / f"support-{detector}.npz", **arrays)


def test_predict_npz_joins_back_to_the_fex_rows_and_warns_for_another_detector(tmp_path, caplog):
    """``aumesh predict``'s NPZ: input, frame and face beside the meshes; a pandas merge on them gives each row's
    own AUs back (frames with two faces, a no-face row). A Detectorv2 release given an MPDetector table warns once."""
    from aumesh import cli
    from aumesh.synthetic.pyfeat import write_pyfeat_tables
    from aumesh.synthetic.tables import SynthSpec

    written = write_pyfeat_tables(
        tmp_path / "raw", SynthSpec(n_frames=60, n_videos=2, seed=1), detector="mp", extra_face_rate=0.3, seed=2
    )
    table = written["files"][0]
    release = _release_with_support(tmp_path, "Detectorv2")
    out = tmp_path / "meshes.npz"
    with caplog.at_level("WARNING"):
        assert cli.main(["predict", str(table), "--release", str(release), "--out", str(out)]) == 0
    lines = [
        r.getMessage()
        for r in caplog.records
        if "MPDetector's but the release was trained on Detectorv2" in r.getMessage()
    ]
    assert len(lines) == 1 and "\n" not in lines[0]
    fex = pd.read_csv(table)
    with np.load(out, allow_pickle=False) as z:
        got = pd.DataFrame({"input": z["input"], "frame": z["frame"], "face": z["face"]})
        au = z["au"]
    assert len(got) == len(fex)
    # the independent route: py-feat's rows numbered within their (input, frame) in file order
    fex = fex[["input", "frame", *AU_COLUMNS]].assign(face=fex.groupby(["input", "frame"]).cumcount())
    assert (fex.groupby(["input", "frame"]).size() > 1).any()  # several faces in some frames
    assert not got.duplicated().any()
    got[list(AU_COLUMNS)] = au
    joined = got.merge(
        fex[["input", "frame", "face", *AU_COLUMNS]], on=["input", "frame", "face"], suffixes=("", "_fex")
    )
    assert len(joined) == len(fex)
    np.testing.assert_array_equal(
        joined[list(AU_COLUMNS)].to_numpy(), joined[[f"{a}_fex" for a in AU_COLUMNS]].to_numpy()
    )


def test_predict_of_an_input_columns_table_has_no_keys_and_no_detector_warning(tmp_path, caplog):
    from aumesh import cli

    release = _release_with_support(tmp_path, "Detectorv2")
    pd.DataFrame({"AU12": [0.1, 0.9], "AU09": [0.0, 0.0]}).to_csv(tmp_path / "t.csv", index=False)
    with caplog.at_level("WARNING"):
        assert (
            cli.main(["predict", str(tmp_path / "t.csv"), "--release", str(release), "--out", str(tmp_path / "o.npz")])
            == 0
        )
    with np.load(tmp_path / "o.npz") as z:
        assert not {"input", "frame", "face"} & set(z.files)
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 1 and "AU12 up to 0.9 (training max 0.6, p99 0.5)" in messages[0], messages


def test_pyfunc_model_logs_the_range_warning_on_every_call(tmp_path, caplog):
    from aumesh.model.release_check import load_release
    from aumesh.tracking.pyfunc import ReleaseModel

    model = ReleaseModel()
    model.release_ = load_release(_release_with_support(tmp_path, "MPDetector"))
    with caplog.at_level("WARNING", logger="aumesh.tracking.pyfunc"):
        for _ in range(2):
            model.predict(None, pd.DataFrame({"AU09": [0.5], "AU12": [0.3]}))
        model.predict(None, pd.DataFrame({"AU12": [0.3]}))  # within the data: silent
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 2 and all("AU09 up to 0.5" in m and "never expressed" in m for m in lines), lines


def test_animate_warns_once_for_the_clip_and_for_another_detector(tmp_path, caplog):
    from aumesh.cli import main
    from aumesh.synthetic.pyfeat import write_pyfeat_tables
    from aumesh.synthetic.tables import SynthSpec

    written = write_pyfeat_tables(tmp_path / "raw", SynthSpec(n_frames=40, n_videos=1, seed=4), detector="v2", seed=1)
    release = _release_with_support(tmp_path, "MPDetector")
    with caplog.at_level("WARNING"):
        assert main(["animate", written["files"][0], "--out", str(tmp_path / "c.glb"), "--release", str(release)]) == 0
    lines = [r.getMessage() for r in caplog.records if r.name == "aumesh.export.gltf_clip"]
    assert len(lines) == 2, lines
    assert "Detectorv2's but the release was trained on MPDetector" in lines[0]
    assert "AU12 up to" in lines[1] and "training max 0.6" in lines[1] and "never expressed" in lines[1]


def test_the_build_runs_mlflow_model_carries_the_datas_support(good_workspace, monkeypatch):
    """The evaluate stage's logged pyfunc model (what promotion registers and `mlflow models serve` serves) has the
    same feature_p99 and unsupported_features as the release, so serving warns as predict_mesh does."""
    import mlflow

    from aumesh.model.release import load_npz
    from aumesh.tracking.pyfunc import NPZ_ARTIFACT

    monkeypatch.chdir(good_workspace)
    run_id = json.loads((good_workspace / "build" / "model" / "tracking.json").read_text())["run_id"]
    store = f"sqlite:///{good_workspace / 'mlflow.db'}"  # given to the call: MLflow's global URI is not the test's
    logged = load_npz(
        mlflow.artifacts.download_artifacts(run_id=run_id, artifact_path=NPZ_ARTIFACT, tracking_uri=store)
    )
    release = load_npz(good_workspace / "release" / "au_to_mesh_pls.npz")
    np.testing.assert_array_equal(logged["feature_p99"], release["feature_p99"])
    np.testing.assert_array_equal(logged["unsupported_features"], release["unsupported_features"])
    assert (
        json.loads(str(logged["training_metadata"]))["data"]["input_ranges"]
        == json.loads(str(release["training_metadata"]))["data"]["input_ranges"]
    )
