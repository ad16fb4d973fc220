"""The evaluate stage's one statistics pass for the AU model and the input families (issue 46, contract item 2).

References are independent of the pass: numpy's X'X and X'Y of designs built here column by column, numpy's least
squares and scikit-learn's PLSRegression on the same rows, the AU fit of a pass of the AU design alone, and the number
of times pass A reads meshes.npy.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from aumesh.core.families import BLENDSHAPE_COLUMNS, EMOTION_COLUMNS, feature_set_columns
from aumesh.core.schema import AU_COLUMNS, POSE_COLUMNS
from aumesh.model.pass_design import FULL_DESIGN, design_union
from aumesh.pipeline import evaluate as ev
from aumesh.pipeline import integrity
from aumesh.pipeline.evaluate import statistics_pass
from aumesh.pipeline.evaluate.prepared_data import load_prepared
from aumesh.pipeline.prepared_files import FRAMES_FILE, SUMMARY_FILE
from conftest import default_config

FAMILY_SETS = ["blendshapes_pose_interactions", "emotions_pose"]


def add_family_columns(prepared_dir: Path, out: Path, seed: int = 3) -> Path:
    """A copy of ``prepared_dir`` whose ``frames.parquet`` also carries the 52 blendshape and 7 emotion columns
    (random, float64; the row groups kept), its checksum recorded again in ``summary.json`` as prepare records it."""
    shutil.copytree(prepared_dir, out)
    path = out / FRAMES_FILE
    source = pq.ParquetFile(prepared_dir / FRAMES_FILE)
    rng = np.random.default_rng(seed)
    groups = []
    for g in range(source.num_row_groups):
        t = source.read_row_group(g)
        n = t.num_rows
        bs = rng.uniform(0.0, 1.0, (n, len(BLENDSHAPE_COLUMNS)))
        em = rng.dirichlet(np.ones(len(EMOTION_COLUMNS)), n)
        for j, c in enumerate(BLENDSHAPE_COLUMNS):
            t = t.append_column(c, pa.array(bs[:, j]))
        for j, c in enumerate(EMOTION_COLUMNS):
            t = t.append_column(c, pa.array(em[:, j]))
        groups.append(t)
    with pq.ParquetWriter(path, groups[0].schema) as writer:
        for t in groups:
            writer.write_table(t, row_group_size=t.num_rows)
    summary = json.loads((out / SUMMARY_FILE).read_text())
    summary["checksums"][FRAMES_FILE] = integrity.file_record(path)
    (out / SUMMARY_FILE).write_text(json.dumps(summary))
    return out


@pytest.fixture(scope="module")
def family_prepared(recovery_prepared, tmp_path_factory):
    return add_family_columns(recovery_prepared / "prepared", tmp_path_factory.mktemp("families") / "prepared")


def numpy_design(frames, columns: list[str]) -> np.ndarray:
    """The design ``columns`` built here, one column at a time (the reference of the pass's by-name selection)."""
    out = np.empty((len(frames), len(columns)))
    for j, c in enumerate(columns):
        if "*" in c:
            p, i = c.split("*")
            out[:, j] = frames[p].to_numpy(np.float64) * frames[i].to_numpy(np.float64)
        else:
            out[:, j] = frames[c].to_numpy(np.float64)
    return out


def test_union_is_the_au_design_then_each_other_design_once_pose_shared():
    union = design_union(["au_pose_interactions", *FAMILY_SETS])
    assert union[: len(FULL_DESIGN)] == FULL_DESIGN
    assert len(union) == len(set(union)) == 83 + (52 + 156) + 7  # emotions_pose: its 7 inputs (pose shared)
    for name in FAMILY_SETS:
        assert set(feature_set_columns(name)) <= set(union)
    assert union.count("Pitch") == 1
    # a run without an AU design accumulates the pose and its families' designs only
    assert design_union(["emotions_pose_interactions"]) == [*POSE_COLUMNS, *EMOTION_COLUMNS] + [
        c for c in feature_set_columns("emotions_pose_interactions") if "*" in c
    ]


def test_shared_pass_statistics_of_a_family_equal_numpy_on_the_same_rows(family_prepared):
    prepared = load_prepared(family_prepared)
    cfg = default_config(features="blendshapes_pose_interactions", **{"preprocess.target": "absolute"})
    fold = ev.video_folds(prepared.videos.count, cfg.cv.n_splits)
    union = design_union(["au_pose_interactions", *FAMILY_SETS])
    design = statistics_pass.design_statistics(prepared, fold, cfg.cv.n_splits, 256, columns=union)
    stats = statistics_pass.accumulate(prepared, cfg, fold, design=design)

    frames = prepared.frames
    X = numpy_design(frames, feature_set_columns("blendshapes_pose_interactions"))
    Y = np.asarray(prepared.meshes, dtype=np.float64)
    row_fold = fold[frames["video_index"].to_numpy()]
    for f, s in enumerate(stats.target):
        Xf, Yf = X[row_fold == f], Y[row_fold == f]
        Xc, Yc = Xf - Xf.mean(0), Yf - Yf.mean(0)
        assert s.n == len(Xf)
        np.testing.assert_allclose(s.cxx, Xc.T @ Xc, rtol=1e-9, atol=1e-9 * np.abs(Xc.T @ Xc).max())
        np.testing.assert_allclose(s.cxy, Xc.T @ Yc, rtol=1e-9, atol=1e-9 * np.abs(Xc.T @ Yc).max())


def test_a_family_fit_from_the_shared_pass_equals_lstsq_at_full_rank_and_sklearn_pls(family_prepared):
    from sklearn.cross_decomposition import PLSRegression

    prepared = load_prepared(family_prepared)
    p = len(feature_set_columns("emotions_pose"))
    shared = ev.SharedPass(["blendshapes_pose_interactions", "emotions_pose"])
    frames = prepared.frames
    X = numpy_design(frames, feature_set_columns("emotions_pose"))
    Y = np.asarray(prepared.meshes, dtype=np.float64)
    # full rank: PLS with p components is least squares (the inputs sum to 1 with the intercept: drop neutral's column
    # from the reference and compare predictions, which do not depend on that choice)
    cfg = default_config(features="emotions_pose", **{"preprocess.target": "absolute", "model.n_components": p})
    final = ev.final_fit(
        prepared, cfg, shared.statistics(prepared, cfg), ev.fit_models(cfg, shared.statistics(prepared, cfg)).final
    )
    A = np.hstack([X, np.ones((len(X), 1))])
    beta, *_ = np.linalg.lstsq(A, Y, rcond=None)
    np.testing.assert_allclose(X @ final.coef.T + final.raw_intercept, A @ beta, atol=1e-6 * np.abs(Y).max())
    # fewer components: scikit-learn's PLSRegression(scale=True) on the same rows
    cfg5 = default_config(features="emotions_pose", **{"preprocess.target": "absolute", "model.n_components": 5})
    fit5 = ev.fit_models(cfg5, shared.statistics(prepared, cfg5)).final
    ref = PLSRegression(n_components=5, scale=True, max_iter=10_000, tol=1e-14).fit(X, Y)  # NIPALS converged
    np.testing.assert_allclose(fit5.coef_, ref.coef_, rtol=1e-6, atol=1e-8 * np.abs(ref.coef_).max())
    assert shared.passes == 1


def test_the_au_fit_is_the_same_bits_with_the_families_in_the_pass(family_prepared):
    prepared = load_prepared(family_prepared)
    cfg = default_config()
    cv_alone, final_alone = ev.cross_validate_and_fit(prepared, cfg)
    shared = ev.SharedPass(["blendshapes_pose_interactions", "emotions_pose_interactions"])
    cv_shared, final_shared = ev.cross_validate_and_fit(prepared, cfg, shared)
    assert shared.design is not None and len(shared.design.columns) > len(FULL_DESIGN)
    for key in ("coef", "raw_intercept", "mesh_intercept"):
        assert getattr(final_alone, key).tobytes() == getattr(final_shared, key).tobytes(), key
    assert cv_alone.metrics() == cv_shared.metrics()
    assert np.asarray(cv_alone.frame_vertex_error[:]).tobytes() == np.asarray(cv_shared.frame_vertex_error[:]).tobytes()
    assert cv_alone.r2_path_folds.tobytes() == cv_shared.r2_path_folds.tobytes()


def test_the_stage_reads_the_meshes_once_for_the_au_model_and_every_family(family_prepared, monkeypatch):
    prepared = load_prepared(family_prepared)
    calls = []
    original = statistics_pass.design_partition
    monkeypatch.setattr(
        statistics_pass, "design_partition", lambda group, **kw: calls.append(group) or original(group, **kw)
    )
    shared = ev.SharedPass(["blendshapes_pose_interactions", "emotions_pose_interactions"])
    cfg = default_config()
    ev.cross_validate_and_fit(prepared, cfg, shared)
    for name in shared.feature_sets:
        ev.cross_validate_and_fit(prepared, default_config(features=name, **{"model.n_components": 10}), shared)
    assert shared.passes == 1
    assert sorted(calls) == sorted(prepared.row_groups())  # each row group of meshes.npy read once by pass A


def test_a_sweep_accumulates_the_union_of_its_feature_sets_once(family_prepared, monkeypatch):
    from aumesh.experiments.sweep import swept_feature_sets
    from aumesh.experiments.sweep_cache import SweepCache

    names = swept_feature_sets(["-m", "features=blendshapes_pose_interactions,emotions_pose,au_pose_interactions"][1:])
    assert names == ["blendshapes_pose_interactions", "emotions_pose", "au_pose_interactions"]
    prepared = load_prepared(family_prepared)
    calls = []
    original = statistics_pass.design_partition
    monkeypatch.setattr(
        statistics_pass, "design_partition", lambda group, **kw: calls.append(group) or original(group, **kw)
    )
    cache = SweepCache()
    results = {}
    for name in names:
        cfg = default_config(features=name, **{"model.n_components": 10})
        stats, _ = cache.statistics_for(prepared, "pid", cfg, names)
        results[name] = stats
    assert cache.passes == 1
    assert len(calls) == len(prepared.row_groups())
    # the same statistics as a pass of that design alone would give (the emotion design, by another route)
    alone = statistics_pass.accumulate(
        prepared,
        default_config(features="emotions_pose", **{"model.n_components": 10}),
        cache.fold_of(prepared, "pid", 3),
    )
    for a, b in zip(results["emotions_pose"].target, alone.target, strict=True):
        np.testing.assert_allclose(a.cxy, b.cxy, rtol=1e-9, atol=1e-9 * np.abs(b.cxy).max())


def test_a_family_absent_from_the_prepared_frames_is_one_line_naming_the_file_family_and_fix(recovery_prepared):
    from aumesh.core.errors import ConfigError

    prepared = load_prepared(recovery_prepared / "prepared")  # prepared from tables without the families
    with pytest.raises(ConfigError) as err:
        statistics_pass.check_family_columns(prepared, design_union(["blendshapes_pose"]))
    message = str(err.value)
    assert "\n" not in message
    assert str(prepared.directory / FRAMES_FILE) in message and "blendshapes family" in message and "Fix:" in message
    statistics_pass.check_family_columns(prepared, list(FULL_DESIGN))  # the AUs alone: nothing to refuse
    assert AU_COLUMNS[0] in FULL_DESIGN and POSE_COLUMNS[0] in FULL_DESIGN


# ------------------------------------------------------------------------------ the stage, on family-truth tables
FAMILY_SPEC_KW = dict(n_frames=3000, n_videos=100, seed=5, identity_scale=0.001, unexplained_scale=0.001, noise_px=0.02)


@pytest.fixture(scope="module")
def family_workspace(tmp_path_factory):
    """ingest, prepare and evaluate (``aumesh`` in-process, the fixed configuration: families on by default) on
    synthetic tables whose blendshapes and emotions move the mesh by known fields (``aumesh synth --families``)."""
    from aumesh import cli
    from aumesh.config import write_params
    from aumesh.synthetic import family_truth
    from aumesh.synthetic import tables as synth
    from conftest import new_store

    ws = tmp_path_factory.mktemp("family-ws") / "ws"
    ws.mkdir()
    spec = synth.SynthSpec(**FAMILY_SPEC_KW)
    synth.write_tables(ws / "data", spec, ws / "truth.npz", families=family_truth.family_source(spec))
    write_params(default_config().to_dict(), ws / "params.yaml")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(ws)
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{new_store(ws / 'mlflow.db')}")
        for stage in ("ingest", "prepare", "evaluate"):
            assert cli.main([stage]) == 0
    return ws


def _fields_in_reference_frame(fields: np.ndarray, truth, prepared) -> np.ndarray:
    """Canonical-frame fields (k, 1434) mapped into the aligned frame by the anchors' similarity (as the AU truth)."""
    from aumesh.core.schema import N_VERTICES
    from aumesh.geometry.align import umeyama_batch

    anchors = truth["template_px"][truth["anchor_indices"]]
    R, s, _ = umeyama_batch(anchors[None], prepared.reference["reference_anchors"].astype(np.float64))
    f = fields.reshape(-1, 3, N_VERTICES).transpose(0, 2, 1)
    return (s[0] * f @ R[0].T).transpose(0, 2, 1).reshape(len(fields), -1)


def test_the_stage_writes_each_family_beside_the_au_model(family_workspace):
    ws = family_workspace
    model_files = sorted(p.name for p in (ws / "build/model").iterdir())
    metrics = json.loads((ws / "metrics/families.json").read_text())
    au_metrics = json.loads((ws / "metrics/metrics.json").read_text())
    assert sorted(metrics) == ["blendshapes", "emotions"]
    for family, features in (
        ("blendshapes", "blendshapes_pose_interactions"),
        ("emotions", "emotions_pose_interactions"),
    ):
        folder = ws / "build/families" / family
        assert sorted(p.name for p in folder.iterdir()) == model_files
        with np.load(folder / "model.npz") as npz:
            assert str(npz["family"]) == family
            assert list(npz["feature_columns"]) == feature_set_columns(features)
            assert npz["coef"].shape == (1434, len(feature_set_columns(features)))
        assert set(au_metrics) - set(metrics[family]) <= {
            "au_reliability", "au_reliability_min", "au_reliability_median", "n_aus_facs_pass", "n_aus_unidentified",
            "au_identification",
        }  # fmt: skip
        assert metrics[family]["n_features"] == len(feature_set_columns(features))
        assert json.loads((folder / "metrics.json").read_text())["r2_mean"] == pytest.approx(metrics[family]["r2_mean"])
    with np.load(ws / "build/model/model.npz") as npz:
        assert "family" not in npz.files  # build/model is the AU model, as it always was


def test_each_family_fit_is_its_own_run_tagged_with_its_family(family_workspace, monkeypatch):
    from mlflow.tracking import MlflowClient

    from aumesh.tracking import queries  # noqa: F401 - MLflow through aumesh's store helpers

    ws = family_workspace
    client = MlflowClient(f"sqlite:///{ws / 'mlflow.db'}")
    runs = [r for e in client.search_experiments() for r in client.search_runs([e.experiment_id])]
    by_family = {r.data.tags.get("aumesh.family"): r for r in runs if r.data.tags.get("aumesh.stage") == "evaluate"}
    assert set(by_family) == {"au", "blendshapes", "emotions"}
    assert by_family["blendshapes"].data.params["features.name"] == "blendshapes_pose_interactions"
    assert by_family["emotions"].data.params["features.name"] == "emotions_pose_interactions"
    assert all(r.info.status == "FINISHED" for r in by_family.values())
    for family, run in by_family.items():
        folder = ws / ("build/model" if family == "au" else f"build/families/{family}")
        assert json.loads((folder / "tracking.json").read_text())["run_id"] == run.info.run_id
        assert run.data.metrics["r2_mean"] == pytest.approx(
            json.loads((folder / "metrics.json").read_text())["r2_mean"]
        )


def test_the_fitted_family_fields_recover_the_truth(family_workspace):
    ws = family_workspace
    prepared = load_prepared(ws / "build/prepared")
    truth = np.load(ws / "truth.npz")

    def cos(a, b):
        return np.einsum("kj,kj->k", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))

    with np.load(ws / "build/families/blendshapes/model.npz") as npz:
        est_bs = npz["coef"][:, : len(BLENDSHAPE_COLUMNS)].T  # the fields at pose 0: the inputs' own columns
    true_bs = _fields_in_reference_frame(truth["blendshape_fields"], truth, prepared)
    moving = np.linalg.norm(true_bs, axis=1) > 0
    c_bs = cos(est_bs[moving], true_bs[moving])
    # 3,000 frames for 211 columns fitted with 83 PLS components (model.n_components, the families' default): each
    # moving shape's field comes back pointing its own way, most of them closely
    assert np.median(c_bs) > 0.95 and c_bs.min() > 0.7, np.round(c_bs, 3)
    with np.load(ws / "build/families/emotions/model.npz") as npz:
        est = npz["coef"][:, : len(EMOTION_COLUMNS)].T
    true = _fields_in_reference_frame(truth["emotion_fields"], truth, prepared)
    n = EMOTION_COLUMNS.index("neutral")  # probabilities sum to 1: only differences from neutral are identified
    others = [j for j in range(len(EMOTION_COLUMNS)) if j != n]
    c_emo = cos(est[others] - est[n], true[others] - true[n])
    assert c_emo.min() > 0.9, np.round(c_emo, 3)
    # a permutation of the labels is caught: each estimated field is closest to its own true field
    d_est, d_true = est[others] - est[n], true[others] - true[n]
    unit_est = d_est / np.linalg.norm(d_est, axis=1, keepdims=True)
    unit_true = d_true / np.linalg.norm(d_true, axis=1, keepdims=True)
    assert (np.argmax(unit_est @ unit_true.T, axis=1) == np.arange(len(others))).all()


def test_the_stage_au_model_is_the_au_fit_of_a_pass_without_families(family_workspace):
    ws = family_workspace
    prepared = load_prepared(ws / "build/prepared")
    _, final = ev.cross_validate_and_fit(prepared, default_config())  # the AU design's pass alone
    with np.load(ws / "build/model/model.npz") as npz:
        assert npz["coef"].tobytes() == final.coef.tobytes()
        assert npz["mesh_intercept"].tobytes() == final.mesh_intercept.tobytes()
