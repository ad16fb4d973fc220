"""The release NPZ is exactly the card's format; writes are atomic."""

from __future__ import annotations

import json

import numpy as np
import pytest

from aumesh.card.model_card import model_card_markdown
from aumesh.core.io import atomic_directory, atomic_savez
from aumesh.core.schema import AU_COLUMNS, INPUT_COLUMNS, N_TARGETS, feature_columns
from aumesh.model.inference import predict_mesh
from aumesh.model.release import release_arrays
from conftest import face_reference, in_card_frame

CARD_KEYS = {
    "coef": ((23, 1434), np.float32),
    "intercept": ((1434,), np.float32),
    "input_columns": ((23,), None),
    "au_columns": ((20,), None),
    "pose_columns": ((3,), None),
    "mean_aligned_mesh": ((478, 3), np.float32),
    "mean_low_au_mesh": ((478, 3), np.float32),
    "reference_anchors": ((12, 3), np.float32),
    "anchor_indices": ((12,), np.int32),
    "n_components": ((), np.int32),
    "model_card": ((), None),
    "training_metadata": ((), None),
}


def _arrays(columns, rng):
    """Random coefficients, and their release; returned coef and intercept are in the card's frame too."""
    coef = rng.normal(size=(N_TARGETS, len(columns)))
    intercept = rng.normal(size=N_TARGETS) + 300
    reference = face_reference(rng)
    arrays = release_arrays(coef, intercept, columns, len(columns), reference, "card", {"a": 1})
    return *in_card_frame(coef, intercept, reference), arrays


def test_npz_has_the_cards_keys_shapes_dtypes_and_loads_without_pickle(tmp_path):
    rng = np.random.default_rng(0)
    _, _, arrays = _arrays(feature_columns(True, True), rng)
    atomic_savez(tmp_path / "m.npz", **arrays)
    m = np.load(tmp_path / "m.npz", allow_pickle=False)
    for key, (shape, dtype) in CARD_KEYS.items():
        assert m[key].shape == shape, key
        if dtype is not None:
            assert m[key].dtype == dtype, key
        else:
            assert m[key].dtype.kind == "U", key  # fixed-width unicode, no object arrays
    assert m["input_columns"].tolist() == list(INPUT_COLUMNS)
    assert json.loads(str(m["training_metadata"])) == {"a": 1}
    # the card's inference snippet, unchanged
    au = np.zeros(20)
    au[m["au_columns"].tolist().index("AU12")] = 1.0  # noqa: E702
    x = np.concatenate([au, np.zeros(3)])
    flat = x @ m["coef"] + m["intercept"]
    mesh = np.stack([flat[:478], flat[478:956], flat[956:]], axis=1)
    assert mesh.shape == (478, 3)


def test_rows_are_selected_by_name_and_pose_rows_are_zero_without_pose():
    rng = np.random.default_rng(1)
    columns = list(reversed(feature_columns(False, False)))  # a design in another order
    coef, _, arrays = _arrays(columns, rng)
    np.testing.assert_allclose(
        arrays["coef"][AU_COLUMNS.index("AU12")], coef[:, columns.index("AU12")].astype(np.float32)
    )
    assert not arrays["coef"][20:].any()
    assert "coef_full" not in arrays


def test_coef_full_makes_pose_conditioned_prediction_exact():
    rng = np.random.default_rng(2)
    columns = feature_columns(True, True)
    coef, intercept, arrays = _arrays(columns, rng)
    au, pose = rng.random(20), np.array([0.1, -0.3, 0.05])
    x_full = np.concatenate([au, pose, (pose[:, None] * au[None, :]).ravel()])
    expected = (x_full @ coef.T + intercept).reshape(3, 478).T
    np.testing.assert_allclose(predict_mesh(arrays, au, pose), expected, rtol=1e-5, atol=1e-3)
    at_zero = predict_mesh(arrays, au)  # pose 0: the 23-row coef is exact
    np.testing.assert_allclose(
        at_zero, (np.concatenate([au, np.zeros(63)]) @ coef.T + intercept).reshape(3, 478).T, rtol=1e-5, atol=1e-3
    )


def test_wrong_coef_shape_is_rejected():
    with pytest.raises(ValueError, match=r"coef has shape \(1434, 5\), expected \(1434, 23\)"):
        release_arrays(
            np.zeros((1434, 5)),
            np.zeros(1434),
            feature_columns(True, False),
            5,
            face_reference(np.random.default_rng(0)),
            "",
            {},
        )


def test_failed_release_leaves_the_previous_release_untouched(tmp_path):
    release = tmp_path / "release"
    with atomic_directory(release) as tmp:
        (tmp / "model.npz").write_text("v1")
    with pytest.raises(RuntimeError):
        with atomic_directory(release) as tmp:
            (tmp / "model.npz").write_text("half-written v2")
            raise RuntimeError("render failed")
    assert (release / "model.npz").read_text() == "v1"
    assert [p.name for p in tmp_path.iterdir()] == ["release"]  # no temp folder left behind


def _card() -> dict:
    return {
        "name": "x",
        "cv": {
            "r2_mean": 0.2,
            "r2_std": 0.01,
            "r2_folds": [0.2, 0.21, 0.19],
            "r2_displacement_mean": 0.1,
            "r2_displacement_std": 0.0,
            "r2_displacement_folds": [0.1] * 3,
            "mae_mean": 0.2,
            "mae_std": 0.0,
            "mae_folds": [0.2] * 3,
            "vertex_error_mean": 0.4,
            "vertex_error_std": 0.0,
            "vertex_error_folds": [0.4] * 3,
        },
        "data": {
            "n_frames": 10,
            "n_videos": 2,
            "digest": {"md5": "abc.dir"},
            "counts": {
                "frames_in": 12,
                "videos_in": 2,
                "dropped_pose": 1,
                "dropped_alignment_outliers": 1,
                "alignment_residual_threshold": 1.0,
                "videos_dropped_no_frames_left": 0,
            },
        },
        "config": {
            "preprocess": {
                "pose_filter": {"max_abs_yaw_deg": 40, "max_abs_pitch_deg": 30},
                "alignment": {"anchor_indices": [1, 2], "outlier_quantile": 0.99},
                "target": "absolute",
                "neutral": {"method": "low_au"},
            },
            "features": {"name": "au_pose_interactions"},
            "model": {"scale": True},
            "cv": {"n_splits": 3, "group": "video_id"},
        },
        "model": {"n_components": 83, "n_features": 83},
        "provenance": {"git_commit": "deadbeef"},
        "mlflow": {"run_id": "r1"},
        "libraries": {"numpy": "2"},
        "promotion": {"run_id": "child42", "parent_run_id": "sweep7", "criterion": "max r2_mean"},
    }


def test_model_card_markdown_names_the_promoted_run():
    card = _card()
    text = model_card_markdown(card, None, [])
    assert "child42" in text and "sweep7" in text and "0.2000" in text and "abc.dir" in text


def test_card_names_both_runs_the_promoted_and_the_build():
    """One release, two runs: the sweep child that chose the configuration and the `dvc repro` run that built the
    arrays, each with its MLflow id and what it stands for (model_card.json's `runs`, MODEL_CARD.md's "Runs")."""
    from aumesh.pipeline.release import release_runs

    promotion = {
        "run_id": "child42",
        "run_name": "features=au,n_components=10",
        "parent_run_id": "sweep7",
        "criterion": "max r2_mean",
        "compared": "3 runs",
        "registered_model": "aumesh-au-to-mesh",
        "model_version": "2",
        "alias": "champion",
        "tracking_uri": "sqlite:///mlflow.db",
    }
    runs = release_runs(
        {
            "run_id": "build9",
            "run_name": "absolute au k=10",
            "experiment_id": "1",
            "tracking_uri": "sqlite:///mlflow.db",
        },
        promotion,
    )
    assert runs["build"]["run_id"] == "build9" and runs["build"]["role"].startswith("build")
    assert runs["promoted"]["run_id"] == "child42" and runs["promoted"]["parent_run_id"] == "sweep7"
    assert "max r2_mean" in runs["promoted"]["role"]
    card = _card() | {
        "runs": runs,
        "mlflow": {"run_id": "build9", "tracking_uri": "sqlite:///mlflow.db"},
        "promotion": promotion,
    }
    text = model_card_markdown(card, None, [])
    section = text[text.index("## Runs") :].split("\n## ")[0]
    from aumesh.card.markdown import md_text

    # names are text from MLflow: escaped for Markdown (issue 34), read back as typed
    assert f"**Promoted run** `child42` ({md_text('features=au,n_components=10')}) of sweep `sweep7`" in section
    assert "how the configuration was chosen" in section and "`aumesh-au-to-mesh` version 2 (`@champion`)" in section
    assert f"**Build run** `build9` ({md_text('absolute au k=10')}) in `sqlite:///mlflow.db`" in section
    assert "produced these exact arrays" in section
    # without a promotion: the build run alone, and the card says so
    alone = model_card_markdown(
        _card() | {"runs": release_runs({"run_id": "build9"}, None), "promotion": None}, None, []
    )
    section = alone[alone.index("## Runs") :].split("\n## ")[0]
    assert "**Build run** `build9`" in section and "Promoted run" not in section and "no promotion" in section


def test_model_card_markdown_explains_the_target_and_shows_the_au_field_reliability_table():
    import copy

    card = _card()
    card["config"]["preprocess"]["target"] = "within"
    card["cv"] |= {
        "au_reliability_min": 0.41,
        "au_reliability_median": 0.93,
        "n_aus_facs_pass": 19,
        "au_reliability": {au: 0.5 + i / 100 for i, au in enumerate(AU_COLUMNS)},
    }
    text = model_card_markdown(card, None, [])
    assert "Target: **within**: design and mesh demeaned per video" in text
    assert "not comparable across targets" in text
    assert "## AU-field reliability" in text and "median over AUs 0.930, worst 0.410; 19 of 20 AUs pass" in text
    assert "| AU12 | 0.590 |" in text
    plain = copy.deepcopy(card)
    del plain["cv"]["au_reliability"]
    assert "## AU-field reliability" not in model_card_markdown(plain, None, [])
