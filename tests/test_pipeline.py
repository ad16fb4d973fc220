"""The recipe end to end on synthetic tables with a known truth, checked against independent references."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.cross_decomposition import PLSRegression as SkPLS
from sklearn.metrics import mean_absolute_error, r2_score
from sklearn.model_selection import GroupKFold

from aumesh.core.errors import ConfigError
from aumesh.core.schema import AU_COLUMNS, N_VERTICES
from aumesh.geometry.align import umeyama_batch
from aumesh.model.features import design_matrix
from aumesh.pipeline import evaluate as ev
from aumesh.pipeline.evaluate.prepared_data import load_prepared
from conftest import default_config


def _arrays(prepared, target="absolute", method="low_au"):
    X = design_matrix(prepared.au, prepared.pose, True, True)
    Y = np.asarray(prepared.meshes, dtype=np.float64)
    if target == "neutral":
        Y = Y - prepared.neutral[method][prepared.frames["video_index"].to_numpy()]
    return X, Y


def _group_kfold(video, n_splits=3):
    """Fold of each frame: the f-th test split of scikit-learn's GroupKFold on the video index (the card's CV)."""
    fold = np.empty(len(video), dtype=np.int64)
    for f, (_, test) in enumerate(GroupKFold(n_splits=n_splits).split(np.zeros(len(video)), groups=video)):
        fold[test] = f
    return fold


def test_fold_r2_and_mae_equal_sklearn_pls_on_the_same_split(recovery_prepared):
    prepared = load_prepared(recovery_prepared / "prepared")
    cfg = default_config(**{"model.n_components": 10})
    cv, _ = ev.cross_validate_and_fit(prepared, cfg)
    X, Y = _arrays(prepared)
    fold = _group_kfold(prepared.frames["video_index"].to_numpy())
    for f in (0, 2):
        train, test = fold != f, fold == f
        ref = SkPLS(n_components=10, scale=True, tol=1e-13, max_iter=10000).fit(X[train], Y[train])
        pred = ref.predict(X[test])
        assert cv.r2_folds[f] == pytest.approx(r2_score(Y[test], pred, multioutput="variance_weighted"), abs=1e-7)
        assert cv.mae_folds[f] == pytest.approx(mean_absolute_error(Y[test], pred), rel=1e-6)
        frame_err = np.sqrt(((Y[test] - pred).reshape(-1, 3, N_VERTICES) ** 2).sum(1)).mean(1)
        assert cv.vertex_error_folds[f] == pytest.approx(frame_err.mean(), rel=1e-6)
        # each frame's error, in its row of the on-disk vector (float32)
        np.testing.assert_allclose(np.asarray(cv.frame_vertex_error)[test], frame_err, rtol=2e-5)


@pytest.mark.parametrize("n_splits", [2, 3, 4, 5])
def test_video_folds_from_frame_counts_equal_group_kfold_on_the_frames(n_splits):
    """Random video sizes with many ties (and videos without frames), frames in any order: the fold of every
    frame equals scikit-learn's GroupKFold on the per-frame video index."""
    rng = np.random.default_rng(n_splits)
    for n_videos, high in ((7, 3), (60, 4), (500, 12), (3000, 40)):
        count = rng.integers(0, high, n_videos)
        count[:n_splits] = np.maximum(count[:n_splits], 1)
        video = rng.permutation(np.repeat(np.arange(n_videos), count))
        video_fold = ev.video_folds(count, n_splits)
        np.testing.assert_array_equal(video_fold[video], _group_kfold(video, n_splits))
        assert (video_fold[count == 0] == -1).all()


def test_video_folds_of_the_prepared_data_equal_group_kfold(recovery_prepared):
    prepared = load_prepared(recovery_prepared / "prepared")
    video = prepared.frames["video_index"].to_numpy()
    np.testing.assert_array_equal(prepared.videos.count, np.bincount(video, minlength=len(prepared.video_ids)))
    for n_splits in (2, 3, 5):
        np.testing.assert_array_equal(
            ev.video_folds(prepared.videos.count, n_splits)[video], _group_kfold(video, n_splits)
        )
    with pytest.raises(ConfigError, match="cv.n_splits=4 but only 3 videos"):
        ev.video_folds(np.array([0, 5, 2, 0, 9]), 4)


def test_full_rank_final_fit_is_ordinary_least_squares(default_evaluation):
    prepared, _, final = default_evaluation
    assert final.n_components == 83
    X, Y = _arrays(prepared)
    beta, *_ = np.linalg.lstsq(np.column_stack([X, np.ones(len(X))]), Y, rcond=None)
    np.testing.assert_allclose(final.coef, beta[:-1].T, rtol=1e-6, atol=1e-6 * np.abs(beta[:-1]).max())
    np.testing.assert_allclose(final.raw_intercept, beta[-1], rtol=1e-9, atol=1e-6)


def _truth_in_reference_frame(truth_npz, prepared):
    """Map the generator's canonical-frame truth into the aligned frame with the anchors' similarity."""
    truth = np.load(truth_npz)
    anchors = truth["template_px"][truth["anchor_indices"]]
    R, s, _ = umeyama_batch(anchors[None], prepared.reference["reference_anchors"].astype(np.float64))
    fields = truth["coef"].reshape(-1, 3, N_VERTICES).transpose(0, 2, 1)  # (83, 478, 3)
    mapped = s[0] * fields @ R[0].T
    return mapped.transpose(0, 2, 1).reshape(len(fields), -1)  # (83, 1434) axis-major


@pytest.fixture(scope="module")
def default_evaluation(recovery_prepared):
    prepared = load_prepared(recovery_prepared / "prepared")
    return prepared, *ev.cross_validate_and_fit(prepared, default_config())


def test_recovered_au_displacement_fields_match_the_truth(recovery_tables, default_evaluation):
    prepared, _, final = default_evaluation
    true_rows = _truth_in_reference_frame(recovery_tables[0] / "truth.npz", prepared)
    cosines = []
    for a, au in enumerate(AU_COLUMNS):
        est, true = final.coef[:, a], true_rows[a]
        cosine = est @ true / (np.linalg.norm(est) * np.linalg.norm(true))
        cosines.append(cosine)
        assert cosine > 0.95, f"{au}: recovered field points elsewhere (cosine {cosine:.3f})"
        assert np.linalg.norm(est) / np.linalg.norm(true) == pytest.approx(1.0, abs=0.15), au
    assert np.median(cosines) > 0.99


def test_cv_r2_is_close_to_what_the_true_model_achieves(recovery_tables, default_evaluation):
    prepared, cv, _ = default_evaluation
    X, Y = _arrays(prepared)
    true_rows = _truth_in_reference_frame(recovery_tables[0] / "truth.npz", prepared)
    pred = X @ true_rows
    pred += (Y - pred).mean(axis=0)  # the truth's intercept in the aligned frame
    true_r2 = r2_score(Y, pred, multioutput="variance_weighted")
    assert 0.3 < true_r2 < 0.99  # the synthetic problem is neither trivial nor hopeless
    assert np.mean(cv.r2_folds) == pytest.approx(true_r2, abs=0.03)


def test_neutral_target_equals_explicit_subtraction(recovery_prepared):
    from aumesh.model.pls import PLSRegression

    prepared = load_prepared(recovery_prepared / "prepared")
    cfg = default_config(**{"preprocess.target": "neutral", "model.n_components": 12})
    cv, final = ev.cross_validate_and_fit(prepared, cfg)
    X, Y = _arrays(prepared, target="neutral")
    fold = _group_kfold(prepared.frames["video_index"].to_numpy())
    model = PLSRegression(n_components=12).fit(X[fold != 1], Y[fold != 1])
    assert cv.r2_folds[1] == pytest.approx(
        r2_score(Y[fold == 1], model.predict(X[fold == 1]), multioutput="variance_weighted"), abs=1e-9
    )
    full = PLSRegression(n_components=12).fit(X, Y)
    np.testing.assert_allclose(final.coef, full.coef_, rtol=1e-9, atol=1e-12)
    # released meshes add the population's mean neutral, so `x @ coef + intercept` is a face, not a displacement
    weights = np.bincount(prepared.frames["video_index"].to_numpy())
    mean_neutral = weights @ prepared.neutral["low_au"] / weights.sum()
    np.testing.assert_allclose(final.mesh_intercept, full.raw_intercept_ + mean_neutral, rtol=1e-6)


def test_n_components_above_feature_count_is_clipped_or_rejected(recovery_prepared):
    cfg = default_config(**{"features.name": "au"})
    assert ev.effective_n_components(cfg) == 20
    # refused when the configuration is loaded, before any work or MLflow run starts
    with pytest.raises(ValueError, match=r"model.n_components=83 exceeds the 20 features"):
        default_config(**{"features.name": "au", "model.clip_n_components": "false"})


def test_same_inputs_give_identical_coefficients_twice(recovery_tables, tmp_path):
    from aumesh.data import tables
    from aumesh.pipeline import prepare

    out = recovery_tables[0]
    cfg = default_config(**{"model.n_components": 20})
    coefs = []
    for run in range(2):
        found = tables.discover(out / "data", cfg.data.tables, cfg.data.mesh_npy)
        prepare.run(found, cfg, tmp_path / f"prepared{run}")
        _, final = ev.cross_validate_and_fit(load_prepared(tmp_path / f"prepared{run}"), cfg)
        coefs.append(final.coef)
    assert np.array_equal(coefs[0], coefs[1])
    assert np.array_equal(
        np.load(tmp_path / "prepared0" / "meshes.npy"), np.load(tmp_path / "prepared1" / "meshes.npy")
    )


@pytest.mark.slow
def test_direction_report_on_a_trained_release_flags_a_deliberately_reversed_au(tmp_path):
    """Synthetic truth with AU12 reversed (corners pulled down): the trained release fails AU12 only."""
    import dataclasses

    from aumesh.card import directions
    from aumesh.data import tables
    from aumesh.model.release import release_arrays
    from aumesh.pipeline import prepare
    from aumesh.synthetic import tables as synth
    from conftest import RECOVERY_SPEC

    spec = dataclasses.replace(RECOVERY_SPEC, n_frames=2000, n_videos=200, reversed_aus=("AU12",))
    synth.write_tables(tmp_path / "data", spec)
    cfg = default_config()
    prepare.run(tables.discover(tmp_path / "data", cfg.data.tables, cfg.data.mesh_npy), cfg, tmp_path / "prepared")
    prepared = load_prepared(tmp_path / "prepared")
    _, final = ev.cross_validate_and_fit(prepared, cfg)
    arrays = release_arrays(
        final.coef, final.mesh_intercept, final.feature_columns, final.n_components, prepared.reference, "", {}
    )
    report = directions.au_direction_report(arrays)
    verdicts = {au: r["verdict"] for au, r in report["aus"].items()}
    assert verdicts["AU12"] == "fail"
    assert [au for au, v in verdicts.items() if v != "pass"] == ["AU12"], verdicts


def _per_video_demeaned(A, video):
    sums = np.zeros((video.max() + 1, A.shape[1]))
    np.add.at(sums, video, A)
    return A - (sums / np.bincount(video)[:, None])[video]


def test_within_target_is_ols_on_per_video_demeaned_data(recovery_prepared):
    """Full rank: the within coefficients are numpy lstsq on demeaned design and mesh; the released intercept
    is the population's (mean mesh - mean design @ slopes); CV demeans each held-out video by its own means."""
    prepared = load_prepared(recovery_prepared / "prepared")
    cv, final = ev.cross_validate_and_fit(prepared, default_config(**{"preprocess.target": "within"}))
    X, Y = _arrays(prepared)
    video = prepared.frames["video_index"].to_numpy()
    Xd, Yd = _per_video_demeaned(X, video), _per_video_demeaned(Y, video)
    beta, *_ = np.linalg.lstsq(Xd, Yd, rcond=None)
    assert final.n_components == 83
    np.testing.assert_allclose(final.coef, beta.T, rtol=1e-6, atol=1e-6 * np.abs(beta).max())
    np.testing.assert_allclose(final.mesh_intercept, Y.mean(0) - X.mean(0) @ beta, rtol=1e-9, atol=1e-5)
    # the card's inference snippet gives a face: x @ coef + intercept at the mean design is the mean mesh
    np.testing.assert_allclose(X.mean(0) @ final.coef.T + final.mesh_intercept, Y.mean(0), atol=1e-5)
    fold = _group_kfold(video)
    for f in (0, 2):
        train, test = fold != f, fold == f
        b, *_ = np.linalg.lstsq(
            _per_video_demeaned(X[train], np.unique(video[train], return_inverse=True)[1]),
            _per_video_demeaned(Y[train], np.unique(video[train], return_inverse=True)[1]),
            rcond=None,
        )
        vt = np.unique(video[test], return_inverse=True)[1]
        Xt, Yt = _per_video_demeaned(X[test], vt), _per_video_demeaned(Y[test], vt)
        pred = Xt @ b
        assert cv.r2_folds[f] == pytest.approx(r2_score(Yt, pred, multioutput="variance_weighted"), abs=1e-7)
        assert cv.mae_folds[f] == pytest.approx(mean_absolute_error(Yt, pred), rel=1e-6)


@pytest.mark.slow
def test_within_neutral_target_is_ols_on_both_sides_minus_the_neutral_frames(recovery_prepared):
    prepared = load_prepared(recovery_prepared / "prepared")
    _, final = ev.cross_validate_and_fit(prepared, default_config(**{"preprocess.target": "within_neutral"}))
    X, Y = _arrays(prepared)
    video = prepared.frames["video_index"].to_numpy()
    low = prepared.frames["low_au"].to_numpy()
    xbar = np.array([X[low & (video == v)].mean(0) for v in range(video.max() + 1)])
    Xn, Yn = X - xbar[video], Y - prepared.neutral["low_au"][video]
    beta, *_ = np.linalg.lstsq(np.column_stack([Xn, np.ones(len(Xn))]), Yn, rcond=None)
    np.testing.assert_allclose(final.coef, beta[:-1].T, rtol=1e-6, atol=1e-6 * np.abs(beta[:-1]).max())
    np.testing.assert_allclose(final.mesh_intercept, Y.mean(0) - X.mean(0) @ beta[:-1], rtol=1e-9, atol=1e-4)


@pytest.mark.slow
def test_au_field_reliability_is_the_cosine_between_fields_fitted_on_each_fold_alone(recovery_prepared):
    prepared = load_prepared(recovery_prepared / "prepared")
    cv, _ = ev.cross_validate_and_fit(prepared, default_config(**{"model.n_components": 30}))
    X, Y = _arrays(prepared)
    fold = _group_kfold(prepared.frames["video_index"].to_numpy())
    fields = [
        SkPLS(n_components=30, scale=True, tol=1e-13, max_iter=10000).fit(X[fold == f], Y[fold == f]).coef_[:, :20]
        for f in range(3)
    ]
    unit = [F / np.linalg.norm(F, axis=0) for F in fields]
    expected = np.mean([(unit[a] * unit[b]).sum(0) for a, b in ((0, 1), (0, 2), (1, 2))], axis=0)
    np.testing.assert_allclose(cv.au_reliability, expected, atol=1e-6)
    metrics = cv.metrics()
    assert metrics["au_reliability_min"] == pytest.approx(expected.min(), abs=1e-6)
    assert metrics["au_reliability_median"] == pytest.approx(np.median(expected), abs=1e-6)
    assert list(metrics["au_reliability"]) == list(AU_COLUMNS)
    assert 0 <= metrics["n_aus_facs_pass"] <= 20 and metrics["n_aus_facs_pass"] >= 18  # clean synthetic truth
    assert cv.scalar_metrics()["au_reliability_AU12"] == pytest.approx(expected[AU_COLUMNS.index("AU12")], abs=1e-6)


@pytest.mark.slow
def test_evaluate_stage_keeps_each_frames_error_and_the_cards_curve_not_the_vector(tmp_path_factory):
    """model/frame_vertex_error.npy: each frame's held-out error in frames.parquet's order (its fold means are the
    metrics'); cv.npz: the 1001-point curve, NumPy's quantiles and the exact ECDF there, so the card's 50 % and
    90 % marks are those of the whole vector; the committed 101-point CSV is the same curve's coarse version."""
    import pandas as pd

    from aumesh import config
    from aumesh.card import render
    from aumesh.pipeline import model_files
    from aumesh.stages import evaluate
    from test_sweep import workspace_with_store

    with workspace_with_store(tmp_path_factory, "frame-error") as ws:
        cfg = config.load_params(ws / "params.yaml")
        metrics = evaluate.main(cfg)
        model = ws / cfg.paths.model_dir
        errors = np.load(model / model_files.FRAME_ERROR_FILE)
        video = pd.read_parquet(ws / cfg.paths.prepared_dir / "frames.parquet", columns=["video_index"])["video_index"]
        curve = pd.read_csv(ws / cfg.paths.error_curve_file)
        with np.load(model / model_files.CV_NPZ) as z:
            assert "vertex_error" not in z.files  # no per-frame vector in cv.npz
            cv = render.load_cv(model / model_files.CV_NPZ)
    assert errors.dtype == np.float32 and errors.shape == (len(video),)
    fold = _group_kfold(video.to_numpy(), cfg.cv.n_splits)
    for f in range(cfg.cv.n_splits):
        assert errors[fold == f].astype(np.float64).mean() == pytest.approx(metrics["vertex_error_folds"][f], rel=1e-6)
    e = np.sort(errors.astype(np.float64))
    q = np.linspace(0, 1, model_files.CARD_ERROR_CURVE_POINTS)
    np.testing.assert_array_equal(cv["cumulative_error_thresholds"], np.quantile(e, q, method="inverted_cdf"))
    np.testing.assert_array_equal(
        cv["cumulative_error_fraction"], np.searchsorted(e, cv["cumulative_error_thresholds"], side="right") / e.size
    )
    thresholds, fraction = render.cumulative_curve(cv)
    for p in (0.5, 0.9):  # the figure's marks: first point at or above p, on the curve and on the whole ECDF
        assert thresholds[np.searchsorted(fraction, p)] == e[np.searchsorted(np.arange(1, e.size + 1) / e.size, p)]
    np.testing.assert_allclose(
        curve["vertex_error"], np.quantile(e, np.linspace(0, 1, 101), method="inverted_cdf"), rtol=1e-5
    )  # the committed CSV: 6 significant digits


@pytest.mark.slow
def test_the_evaluate_stage_never_imports_mlflow_its_run_is_logged_beside(tmp_path_factory):
    """MLflow (its import alone ~4 s of CPU) is imported and the run logged by the tracking helper process while the
    stage computes: the stage process never imports it, and the run is complete (params, metrics, the pyfunc model,
    the stage's pid) and the one ``tracking.json`` names. Nor does it import the prepare stage's data contract
    (pandera: ~0.2 s of every evaluate), only the names of the prepared files."""
    import json
    import os
    import subprocess
    import sys

    from mlflow import MlflowClient

    from aumesh import config
    from aumesh.pipeline import model_files
    from aumesh.tracking import runs as tracking
    from test_sweep import workspace_with_store

    code = (
        "import json, os, sys\n"
        "from aumesh import config\n"
        "from aumesh.stages import evaluate\n"
        "evaluate.main(config.load_params('params.yaml'))\n"
        "print(json.dumps({'pid': os.getpid(), 'mlflow': sorted(m for m in sys.modules if m.split('.')[0] == 'mlflow'),\n"
        "                  'pandera': sorted(m for m in sys.modules if m.split('.')[0] == 'pandera')}))\n"
    )
    with workspace_with_store(tmp_path_factory, "beside") as ws:
        out = subprocess.run([sys.executable, "-c", code], cwd=ws, env=os.environ, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        stage = json.loads(out.stdout.strip().splitlines()[-1])
        cfg = config.load_params(ws / "params.yaml")
        run_info = json.loads((ws / cfg.paths.model_dir / model_files.TRACKING_JSON).read_text())
        client = MlflowClient(os.environ["MLFLOW_TRACKING_URI"])
        run = client.get_run(run_info["run_id"])
        artifacts = {a.path for a in client.list_artifacts(run.info.run_id, "model")}
    assert stage["mlflow"] == [] and stage["pandera"] == []
    assert run.info.status == "FINISHED" and run.data.tags[tracking.PID_TAG] == str(stage["pid"])
    assert run.data.params["model.n_components"] == str(cfg.model.n_components)
    assert {"r2_mean", "mae_mean", "seconds_log_model"} <= set(run.data.metrics)
    assert "model/MLmodel" in artifacts


def test_the_passes_scratch_goes_with_its_result_or_with_the_next_stage_after_a_kill(recovery_prepared, tmp_path):
    """The scratch folders (per-video sums, each frame's error) carry their process: removed with the statistics and
    the result, or, when their process was killed, by the next evaluate stage's start; a live run's stay."""
    import gc
    import os
    import socket
    import subprocess
    import sys

    from aumesh.stages import common

    host = socket.gethostname()
    prepared = load_prepared(recovery_prepared / "prepared")
    before = set(recovery_prepared.glob(".evaluate-scratch*"))  # of results other tests still hold
    cv, _ = ev.cross_validate_and_fit(prepared, default_config(**{"model.n_components": 5}))
    scratch = cv.frame_vertex_error.path.parent
    assert scratch.parent == (recovery_prepared / "prepared").parent
    assert scratch.name.startswith(f".evaluate-scratch.tmp-{os.getpid()}-{host}-")
    del cv
    gc.collect()
    assert not scratch.exists() and set(recovery_prepared.glob(".evaluate-scratch*")) == before  # pass A's went too

    dead_pid = int(
        subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True).stdout
    )
    build = tmp_path / "build"
    killed, live = (
        build / f".evaluate-scratch.tmp-{dead_pid}-{host}-abc",
        build / f".evaluate-scratch.tmp-{os.getpid()}-{host}-d",
    )
    for d in (killed, live):
        d.mkdir(parents=True)
    common.start_stage(
        "evaluate",
        default_config(**{"paths.prepared_dir": str(build / "prepared"), "paths.model_dir": str(build / "model")}),
    )
    assert not killed.exists() and live.exists()


def test_staged_video_codes_and_au_sums_equal_numpy_unique_and_pandas_row_sums():
    """Pass 2 reads the staged metadata as Arrow arrays: its video codes are ``np.unique(..., return_inverse=True)``
    and its AU sums pandas' row sums, bit for bit (the low-AU flags and thresholds rest on them)."""
    import pandas as pd
    import pyarrow as pa

    from aumesh.pipeline.prepare import tasks as prepare_tasks

    rng = np.random.default_rng(7)
    names = np.array(["b", "a", "c10", "c9", "été", "a"], dtype=object)[rng.integers(0, 6, 500)]
    chunked = pa.chunked_array([pa.array(names[:200]), pa.array(names[200:])])  # two chunks, as a table may hold
    videos, code = prepare_tasks._video_codes(chunked)
    expected_videos, expected_code = np.unique(names.astype(str), return_inverse=True)
    np.testing.assert_array_equal(videos, expected_videos)
    np.testing.assert_array_equal(code, expected_code)

    frame = pd.DataFrame({name: rng.random(500) ** rng.integers(1, 8) for name in AU_COLUMNS})
    frame.insert(0, "Pitch", rng.random(500))  # another float column in the same pandas block, as staged
    rows = np.flatnonzero(rng.random(500) < 0.9)
    pandas_sums = frame.loc[frame.index[rows], list(AU_COLUMNS)].to_numpy().sum(axis=1)
    assert np.array_equal(prepare_tasks.au_sums(pa.Table.from_pandas(frame), rows), pandas_sums)
    assert not np.array_equal(np.ascontiguousarray(frame[list(AU_COLUMNS)].to_numpy()[rows]).sum(axis=1), pandas_sums)
