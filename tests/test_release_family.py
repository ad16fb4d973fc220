"""The family release stage (``release_family@<family>``, issue 46 contract item 3) on a real prepared workspace.

The workspace is the good run's (conftest ``workspace``: 400 synthetic frames, ingest/prepare/evaluate/release run).
Until the evaluate stage fits the families, :func:`make_family_fit` stands in for it: the prepared ``frames.parquet``
gets family columns that are AU columns under blendshape/emotion names (``jawOpen`` = AU26, ``mouthSmileLeft`` =
AU12, ..., ``happiness`` = AU12, ...; the synthetic meshes move by the AUs' true fields, so these columns have known
fields), the other inputs small noise or, for ``ZERO_INPUTS``, 0 in every frame; a PLS fit of ``meshes.npy`` on the
family's configured design is written as ``build/families/<family>/`` with the files of ``build/model/``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from aumesh.core.families import FAMILIES, feature_set_columns
from aumesh.model.family_release import npz_name
from aumesh.synthetic.family_truth import BLENDSHAPE_AU

#: inputs written as 0 in every frame: they must come out as unsupported_features
ZERO_INPUTS = {"blendshapes": ("cheekPuff", "jawForward"), "emotions": ()}
#: emotion -> the AU column standing for it (its prototype's most telling AU, aumesh.synthetic.family_truth.EMOTION_AUS)
EMOTION_AU = {
    "anger": "AU04",
    "disgust": "AU09",
    "fear": "AU20",
    "happiness": "AU12",
    "sadness": "AU15",
    "surprise": "AU02",
    "neutral": None,
}


def family_values(
    frames: pa.Table, family: str, rng: np.random.Generator, softmax: bool = False
) -> dict[str, np.ndarray]:
    """The family's columns for the prepared frames: AU columns under the family's names, small noise elsewhere;
    ``softmax``: each frame's inputs scaled to sum to 1 (as py-feat's emotions do)."""
    n = frames.num_rows
    source = BLENDSHAPE_AU if family == "blendshapes" else EMOTION_AU
    out = {}
    for name in FAMILIES[family]:
        au = source.get(name)
        if name in ZERO_INPUTS[family]:
            out[name] = np.zeros(n)
        elif au is not None:
            out[name] = frames.column(au).to_numpy().astype(np.float64)
        else:
            out[name] = rng.uniform(0.0, 0.2, n)
    if softmax:
        total = sum(out.values()) + 1e-3  # + a floor on neutral's share: no frame sums to 0
        out = {name: (v + (1e-3 if name == "neutral" else 0.0)) / total for name, v in out.items()}
    return out


def _design(values: dict[str, np.ndarray], pose: np.ndarray, columns: list[str]) -> np.ndarray:
    named = dict(values)
    for p, name in enumerate(("Pitch", "Yaw", "Roll")):
        named[name] = pose[:, p]
        for k, v in values.items():
            named[f"{name}*{k}"] = pose[:, p] * v
    return np.column_stack([named[c] for c in columns])


def make_family_fit(ws: Path, family: str, seed: int = 0, softmax: bool = False) -> dict[str, np.ndarray]:
    """Add ``family``'s columns to ``ws``'s prepared frames (checksum updated, as prepare would record it) and write
    ``build/families/<family>/`` as the evaluate stage would (model.npz per the contract, metrics, tracking, cv)."""
    from aumesh.config import load_params
    from aumesh.model.pls import PLSRegression
    from aumesh.pipeline import integrity

    cfg = load_params(ws / "params.yaml")
    prepared = ws / cfg.paths.prepared_dir
    frames_path = prepared / "frames.parquet"
    frames = pq.read_table(frames_path)
    values = family_values(frames, family, np.random.default_rng(seed), softmax)
    for name, v in values.items():
        if name in frames.column_names:
            frames = frames.drop_columns([name])
        frames = frames.append_column(name, pa.array(v))
    pq.write_table(frames, frames_path, row_group_size=150)  # several row groups: the ranges are read a group at a time
    summary = json.loads((prepared / "summary.json").read_text())
    summary["checksums"]["frames.parquet"] = integrity.file_record(frames_path)
    (prepared / "summary.json").write_text(json.dumps(summary))
    meshes = np.load(prepared / "meshes.npy").astype(np.float64)
    pose = np.column_stack([frames.column(c).to_numpy() for c in ("Pitch", "Yaw", "Roll")]).astype(np.float64)
    features = dict(cfg.families.items())[family].features
    columns = feature_set_columns(features)
    x = _design(values, pose, columns)
    pls = PLSRegression(n_components=8, scale=False).fit(x, meshes)
    out = ws / cfg.paths.families_model_dir / family
    out.mkdir(parents=True, exist_ok=True)
    (out / "skipped.json").unlink(missing_ok=True)  # the good workspace's evaluate had no families to fit
    for name in ("metrics.json", "tracking.json", "cv.npz"):
        shutil.copy(ws / cfg.paths.model_dir / name, out / name)
    model = {
        "coef": np.asarray(pls.coef_, np.float64),
        "raw_intercept": pls.raw_intercept_for(8),
        "mesh_intercept": pls.raw_intercept_for(8),
        "feature_columns": np.array(columns),
        "n_components": np.array(8),
        "family": np.array(family),
    }
    np.savez(out / "model.npz", **model)
    return {"x": x, "pls": pls, "columns": np.array(columns), **model}


@pytest.fixture
def family_ws(workspace, monkeypatch):
    monkeypatch.chdir(workspace)
    return workspace


def _release(family: str) -> int:
    from aumesh import cli

    return cli.main(["release_family", family])


@pytest.mark.parametrize("family", ["blendshapes", "emotions"])
def test_release_family_writes_pyfeats_npz_card_and_figures(family_ws, family):
    fit = make_family_fit(family_ws, family)
    assert _release(family) == 0
    out = family_ws / "releases" / family
    names = sorted(p.name for p in out.iterdir())
    assert {npz_name(family), "model_card.json", "MODEL_CARD.md", "figures", f"{family}_directions.json"} <= set(names)
    with np.load(out / npz_name(family), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    k = len(FAMILIES[family])
    assert arrays["feature_columns"].tolist() == list(FAMILIES[family])
    assert arrays["coef"].shape == (len(fit["columns"]), 1434)
    # feature_p99: the p99 of the columns written into frames.parquet, by numpy (another route than the stage's
    # row-group quantiles)
    frames = pq.read_table(family_ws / "build/prepared/frames.parquet", columns=list(FAMILIES[family]))
    expected = np.quantile(np.column_stack([frames.column(c).to_numpy() for c in FAMILIES[family]]), 0.99, axis=0)
    np.testing.assert_allclose(arrays["feature_p99"], expected.astype(np.float32), rtol=1e-6)
    assert arrays["unsupported_features"].tolist() == list(ZERO_INPUTS[family])
    # the card: data it stands on, unsupported inputs, p99 range, provenance, warnings, directions
    card = json.loads((out / "model_card.json").read_text())
    assert card["family"]["name"] == family and card["family"]["npz"] == npz_name(family)
    assert card["data"]["n_frames"] == frames.num_rows
    assert card["data"]["unsupported_inputs"] == list(ZERO_INPUTS[family])
    assert card["data"]["p99_range"]["max"] == pytest.approx(float(expected.max()))
    assert "git_commit" in card["provenance"] and "digest" in card["data"]
    assert card["directions"]["verdict"] in ("pass", "doubtful", "fail")
    codes = {w["code"] for w in card["warnings"]}
    assert "small_data_frames" in codes  # 400 frames for 211 / 28 features
    assert ("unsupported_inputs" in codes) == bool(ZERO_INPUTS[family])
    # a family whose inputs sum to one value in every frame (a softmax) is said to identify only differences; numpy's
    # row sums of the frames decide which case this is
    sums = np.column_stack([frames.column(c).to_numpy() for c in FAMILIES[family]]).sum(axis=1)
    assert ("inputs_sum_constant" in codes) == bool(np.ptp(sums) < 1e-3), (family, np.ptp(sums))
    assert card["data"]["input_sum"] == pytest.approx({"min": sums.min(), "max": sums.max()})
    # the rig (a morph target per input, by name) and the viewer are part of the release
    assert {f"{family}_to_mesh.glb", "viewer.html"} <= set(names)
    md = (out / "MODEL_CARD.md").read_text()
    assert "## Limits of this release" in md and "## What the training data expressed" in md
    for name in ZERO_INPUTS[family]:
        assert f"{name} (never expressed)" in md
    assert str(arrays["model_card"]) == md
    assert json.loads(str(arrays["training_metadata"]))["family"]["name"] == family
    assert (out / "figures" / f"{family}_panels.png").stat().st_size > 10_000
    # py-feat's predict at pose 0 = the fit's at pose 0, in the card frame (the release turns the aligned frame)
    from aumesh.geometry.frame import canonical_frame, rotate_axis_major
    from aumesh.pipeline.integrity import load_reference

    rotation, origin = canonical_frame(load_reference(family_ws / "build/prepared")["mean_aligned_mesh"])
    x0 = fit["x"][:20].copy()
    x0[:, k:] = 0.0  # pose 0: the pose and pose x input columns vanish
    expected_mesh = rotate_axis_major(x0 @ fit["coef"].T + fit["mesh_intercept"], rotation, origin)
    got = fit["x"][:20, :k].astype(np.float32) @ arrays["coef"][:k] + arrays["intercept"]
    assert np.abs(got - expected_mesh).max() < 1e-4 * np.abs(expected_mesh).max()


def test_emotions_that_sum_to_one_are_said_to_identify_differences_only(family_ws):
    """py-feat's emotions are a softmax: the design's intercept is their sum, so the card says one emotion's field
    alone is not identified (the same family's table without the constraint says nothing: the test above)."""
    make_family_fit(family_ws, "emotions", softmax=True)
    assert _release("emotions") == 0
    card = json.loads((family_ws / "releases/emotions/model_card.json").read_text())
    (warning,) = [w for w in card["warnings"] if w["code"] == "inputs_sum_constant"]
    assert warning["sum_min"] == pytest.approx(1.0) and warning["sum_max"] == pytest.approx(1.0)
    assert "only differences" in warning["message"]


def test_family_promotion_is_on_the_card(family_ws):
    make_family_fit(family_ws, "emotions")
    promotion = {"promoted": None, "families": {"emotions": {"run_id": "abc123", "criterion": "best r2_mean"}}}
    (family_ws / "promotion.json").write_text(json.dumps(promotion))
    assert _release("emotions") == 0
    card = json.loads((family_ws / "releases/emotions/model_card.json").read_text())
    assert card["promotion"]["run_id"] == "abc123"
    assert card["runs"]["promoted"]["run_id"] == "abc123"
    assert "abc123" in (family_ws / "releases/emotions/MODEL_CARD.md").read_text()


def test_a_failing_release_leaves_the_previous_one(family_ws, monkeypatch, capsys):
    make_family_fit(family_ws, "emotions")
    assert _release("emotions") == 0
    out = family_ws / "releases/emotions"
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    # the next fit is broken: a NaN in its coefficients must be refused, nothing written
    model = dict(np.load(family_ws / "build/families/emotions/model.npz"))
    model["coef"][3, 0] = np.nan
    np.savez(family_ws / "build/families/emotions/model.npz", **model)
    assert _release("emotions") == 2
    assert "NaN" in capsys.readouterr().err
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before
    # and a failure inside the folder's writing (the figures) leaves it too
    make_family_fit(family_ws, "emotions", seed=1)
    from aumesh.card import family_figures

    def broken(*a, **k):
        raise RuntimeError("render failed")

    monkeypatch.setattr(family_figures, "render_family", broken)
    with pytest.raises(RuntimeError, match="render failed"):
        _release("emotions")
    after = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert after == before
    assert sorted(p.name for p in out.parent.iterdir()) == ["emotions"]  # no temporary left beside it


def test_a_family_missing_from_the_frames_is_one_line(family_ws, capsys):
    fit_dir = family_ws / "build/families/emotions"
    make_family_fit(family_ws, "emotions")
    frames_path = family_ws / "build/prepared/frames.parquet"
    frames = pq.read_table(frames_path).drop_columns(list(FAMILIES["emotions"]))
    pq.write_table(frames, frames_path)
    from aumesh.pipeline import integrity

    summary = json.loads((family_ws / "build/prepared/summary.json").read_text())
    summary["checksums"]["frames.parquet"] = integrity.file_record(frames_path)
    (family_ws / "build/prepared/summary.json").write_text(json.dumps(summary))
    assert fit_dir.exists()
    assert _release("emotions") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert any("frames.parquet: no column 'anger'" in line and "Fix:" in line for line in err), err


def test_a_family_the_tables_lack_is_released_as_not_released(family_ws, caplog):
    """The good workspace's tables carry no families: evaluate leaves a skipped.json saying why (so dvc repro's
    release_family@<family> has its dependency), and the release stage writes a record that says so, with no NPZ."""
    from aumesh import cli

    assert cli.main(["evaluate"]) == 0
    skipped = json.loads((family_ws / "build/families/blendshapes/skipped.json").read_text())
    assert "frames.parquet" in skipped["reason"] and "blendshape" in skipped["reason"]
    assert not (family_ws / "build/families/blendshapes/model.npz").exists()
    with caplog.at_level("WARNING"):
        assert _release("blendshapes") == 0
    out = family_ws / "releases" / "blendshapes"
    assert sorted(p.name for p in out.iterdir()) == ["NOT_RELEASED.md", "model_card.json"]
    card = json.loads((out / "model_card.json").read_text())
    assert card["released"] is False and card["reason"] == skipped["reason"]
    assert "blendshapes not released" in caplog.text


def test_a_family_set_to_none_is_neither_fitted_nor_released(family_ws):
    from aumesh import cli

    make_family_fit(family_ws, "emotions")  # the tables carry emotions: only the setting leaves them out
    text = (family_ws / "params.yaml").read_text()
    (family_ws / "params.yaml").write_text(text.replace("features: emotions_pose_interactions", "features: none", 1))
    assert cli.main(["evaluate"]) == 0
    assert json.loads((family_ws / "build/families/emotions/skipped.json").read_text())["reason"] == (
        "families.emotions.features=none"
    )
    assert "emotions" not in json.loads((family_ws / "metrics/families.json").read_text())
    assert _release("emotions") == 0
    assert json.loads((family_ws / "releases/emotions/model_card.json").read_text())["released"] is False


def test_left_right_pairs_that_move_together_in_the_data_are_found(family_ws):
    """sides_together (the release's input to the direction check) against numpy's correlation of the frames: a pair
    written as one value on both sides moves together; independent sides do not."""
    from aumesh.pipeline.release_family import sides_together

    make_family_fit(family_ws, "blendshapes")
    frames_path = family_ws / "build/prepared/frames.parquet"
    frames = pq.read_table(frames_path)
    copied = frames.column("eyeBlinkLeft").to_numpy() * 0.5 + 0.01  # Right = a linear copy of Left: correlation 1
    frames = frames.drop_columns(["eyeBlinkRight"]).append_column("eyeBlinkRight", pa.array(copied))
    pq.write_table(frames, frames_path, row_group_size=150)
    values = {c: frames.column(c).to_numpy() for c in frames.column_names}
    expected = sorted(
        f"{n[:-4]}Left/Right"
        for n in FAMILIES["blendshapes"]
        if n.endswith("Left")
        and np.ptp(values[n]) > 0
        and np.ptp(values[n[:-4] + "Right"]) > 0
        and np.corrcoef(values[n], values[n[:-4] + "Right"])[0, 1] >= 0.95
        or n.endswith("Left")
        and (np.ptp(values[n]) == 0 or np.ptp(values[n[:-4] + "Right"]) == 0)
    )
    got = sides_together(family_ws / "build/prepared", "blendshapes")
    assert "eyeBlinkLeft/Right" in got
    assert sorted(got) == expected
