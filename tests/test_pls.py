"""Tests of the sufficient-statistics PLS engine (aumesh.model.pls) against sklearn and OLS."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from sklearn.cross_decomposition import PLSRegression as SkPLS
from sklearn.metrics import r2_score
from sklearn.utils.estimator_checks import check_estimator

from aumesh.model.cross_products import CrossProducts
from aumesh.model.pls import PLSRegression
from aumesh.model.scoring import r2_path, r2_per_target, r2_variance_weighted, residual_sums


def max_rel(a, b):
    """max |a - b| relative to max |b|."""
    a, b = np.asarray(a), np.asarray(b)
    return np.abs(a - b).max() / np.abs(b).max()


def make_well_conditioned(n=500, p=12, q=30, seed=0):
    """X with distinct scales and offsets; Y = X B + noise + large offsets.

    B has geometrically decaying singular values so sklearn's power iterations
    converge tightly (the reference is then accurate to ~1e-8).
    """
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(n, p)) * rng.uniform(0.5, 3, p) + rng.uniform(-5, 5, p)
    r = min(p, q)
    U, _ = np.linalg.qr(rng.normal(size=(p, r)))
    V, _ = np.linalg.qr(rng.normal(size=(q, r)))
    B = (U * (10 * 0.5 ** np.arange(r))) @ V.T
    Y = X @ B + 0.5 * rng.normal(size=(n, q)) + rng.uniform(100, 1000, q)
    return X, Y


def make_face_like(n=1000, q=60, seed=1):
    """20 AU-like nonnegative features + 3 pose + 60 pose x AU products (83 features)."""
    rng = np.random.default_rng(seed)
    au = np.clip(rng.gamma(0.7, 1.0, size=(n, 20)), 0, 5)
    pose = rng.normal(size=(n, 3)) * np.array([8.0, 15.0, 5.0])
    inter = (pose[:, :, None] * au[:, None, :]).reshape(n, 60)
    X = np.hstack([au, pose, inter])
    # low-rank deformation basis with well-separated modes, so sklearn's power iterations
    # (the reference) converge to ~1e-8
    U, _ = np.linalg.qr(rng.normal(size=(83, 30)) * np.r_[np.ones(23), 0.05 * np.ones(60)][:, None])
    V, _ = np.linalg.qr(rng.normal(size=(q, 30)))
    B = (U * (20.0 * 0.6 ** np.arange(30))) @ V.T
    Y = X @ B + rng.normal(size=(n, q)) + rng.uniform(100, 1000, q)
    return X, Y


def sk_exact(n_components, scale):
    """sklearn's PLSRegression run with an exact SVD for the weights instead of power iterations."""
    est = SkPLS(n_components=n_components, scale=scale)
    est.algorithm = "svd"  # private switch of sklearn's _PLS base; same algorithm otherwise
    return est


# --------------------------------------------------------------------------- equivalence


def test_full_rank_equals_ols_with_intercept():
    X, Y = make_well_conditioned()
    model = PLSRegression(n_components=X.shape[1]).fit(X, Y)
    A = np.hstack([X, np.ones((X.shape[0], 1))])
    sol, *_ = np.linalg.lstsq(A, Y, rcond=None)
    assert max_rel(model.coef_, sol[:-1].T) < 1e-8
    assert max_rel(model.raw_intercept_, sol[-1]) < 1e-8
    assert max_rel(model.predict(X), A @ sol) < 1e-10


@pytest.mark.parametrize("scale", [True, False])
@pytest.mark.parametrize("k", [1, 2, 4, 7, 11])
def test_below_full_rank_matches_sklearn_nipals(k, scale):
    X, Y = make_well_conditioned()
    ref = SkPLS(n_components=k, scale=scale, tol=1e-14, max_iter=10000).fit(X, Y)
    model = PLSRegression(n_components=k, scale=scale).fit(X, Y)
    assert max_rel(model.coef_, ref.coef_) < 1e-6
    assert max_rel(model.intercept_, ref.intercept_) < 1e-12
    assert max_rel(model.predict(X), ref.predict(X)) < 1e-6
    for name in ("x_weights_", "x_loadings_", "y_loadings_", "y_weights_", "x_rotations_"):
        assert max_rel(getattr(model, name), getattr(ref, name)) < 1e-5, name
    assert max_rel(model.transform(X), ref.transform(X)) < 1e-5


@pytest.mark.parametrize("scale", [True, False])
@pytest.mark.parametrize("k", [1, 3, 8])
def test_matches_sklearn_exact_svd_variant_to_rounding(k, scale):
    # sklearn's own algorithm with exact singular vectors: no power-iteration error in the
    # reference, so agreement must be at rounding level (guards sign flips, scaling, deflation).
    X, Y = make_well_conditioned(seed=3)
    ref = sk_exact(k, scale).fit(X, Y)
    model = PLSRegression(n_components=k, scale=scale).fit(X, Y)
    assert max_rel(model.coef_, ref.coef_) < 1e-10
    assert max_rel(model.x_weights_, ref.x_weights_) < 1e-10
    assert max_rel(model.x_rotations_, ref.x_rotations_) < 1e-10
    assert max_rel(model.y_loadings_, ref.y_loadings_) < 1e-10
    xs, ys = model.transform(X, Y)
    xs_ref, ys_ref = ref.transform(X, Y)
    assert max_rel(xs, xs_ref) < 1e-10 and max_rel(ys, ys_ref) < 1e-10


@pytest.mark.parametrize("k", [5, 20])
def test_face_shaped_83_features_matches_sklearn(k):
    X, Y = make_face_like()
    ref = SkPLS(n_components=k, scale=True, tol=1e-14, max_iter=10000).fit(X, Y)
    model = PLSRegression(n_components=k, scale=True).fit(X, Y)
    assert max_rel(model.coef_, ref.coef_) < 1e-6
    assert max_rel(model.intercept_, ref.intercept_) < 1e-12
    assert max_rel(model.predict(X), ref.predict(X)) < 1e-7
    exact = sk_exact(k, True).fit(X, Y)
    assert max_rel(model.coef_, exact.coef_) < 1e-9


def test_raw_intercept_predicts_from_raw_X():
    X, Y = make_well_conditioned()
    ref = SkPLS(n_components=4, tol=1e-14, max_iter=10000).fit(X, Y)
    model = PLSRegression(n_components=4).fit(X, Y)
    assert max_rel(X @ model.coef_.T + model.raw_intercept_, ref.predict(X)) < 1e-8
    assert np.allclose(model.raw_intercept_for(4), model.raw_intercept_, rtol=0, atol=1e-12)


def test_coef_path_equals_separate_fits():
    X, Y = make_well_conditioned(seed=5)
    big = PLSRegression(n_components=9).fit(X, Y)
    assert big.coef_path_.shape == (9, Y.shape[1], X.shape[1])
    for k in (1, 2, 5, 9):
        small = PLSRegression(n_components=k).fit(X, Y)
        assert max_rel(big.coef_path_[k - 1], small.coef_) < 1e-12
        assert max_rel(big.coef_for(k), small.coef_) < 1e-12
        assert max_rel(big.raw_intercept_for(k), small.raw_intercept_) < 1e-12
        assert max_rel(big.predict(X[:50], n_components=k), small.predict(X[:50])) < 1e-12
    assert np.array_equal(big.coef_path_[-1], big.coef_)
    # the path is built on first use and kept: a refit must not keep the previous fit's
    big.fit(X[:300], Y[:300])
    assert np.array_equal(big.coef_path_[-1], big.coef_)
    assert max_rel(big.coef_path_[0], PLSRegression(n_components=1).fit(X[:300], Y[:300]).coef_) < 1e-12


def test_fit_stats_equals_fit_and_one_dimensional_y_ravel():
    X, Y = make_well_conditioned()
    a = PLSRegression(n_components=3).fit(X, Y)
    b = PLSRegression(n_components=3).fit_stats(CrossProducts.from_arrays(X, Y))
    assert max_rel(b.coef_, a.coef_) < 1e-13
    one = PLSRegression(n_components=3).fit(X, Y[:, 0])
    ref = SkPLS(n_components=3, tol=1e-14, max_iter=10000).fit(X, Y[:, 0])
    assert one.predict(X).shape == (X.shape[0],)
    assert max_rel(one.coef_, ref.coef_) < 1e-8


# --------------------------------------------------------------------------- statistics


def test_chunked_update_equals_one_shot():
    X, Y = make_well_conditioned(n=700)
    chunked = CrossProducts(X.shape[1], Y.shape[1])
    for lo, hi in [(0, 100), (100, 101), (101, 101), (101, 450), (450, 700)]:
        chunked.update(X[lo:hi], Y[lo:hi], block_rows=64)
    # the provisional shift comes from the first block of the first chunk
    np.testing.assert_array_equal(chunked.x_shift, X[:64].mean(0))
    same_shift = CrossProducts.from_arrays(X, Y, x_shift=chunked.x_shift, y_shift=chunked.y_shift)
    default_shift = CrossProducts.from_arrays(X, Y)
    assert chunked.n == same_shift.n == default_shift.n == 700
    for name in ("sum_x", "sum_y", "xtx", "xty", "yty_diag"):
        np.testing.assert_allclose(getattr(chunked, name), getattr(same_shift, name), rtol=1e-10, atol=1e-9)
    for name in ("cxx", "cxy", "cyy_diag", "x_mean", "y_mean"):
        np.testing.assert_allclose(getattr(chunked, name), getattr(default_shift, name), rtol=1e-10, atol=1e-9)


def test_total_minus_fold_equals_complement_statistics():
    X, Y = make_well_conditioned(n=600)
    total = CrossProducts.from_arrays(X, Y)
    fold = total.empty_like().update(X[200:350], Y[200:350])
    rest = np.r_[0:200, 350:600]
    expected = CrossProducts.from_arrays(X[rest], Y[rest], x_shift=total.x_shift, y_shift=total.y_shift)
    train = total - fold
    assert train.n == 450
    for name in ("sum_x", "sum_y", "xtx", "xty", "yty_diag", "cxx", "cxy", "cyy_diag", "x_mean", "y_mean"):
        np.testing.assert_allclose(getattr(train, name), getattr(expected, name), rtol=1e-9, atol=1e-7)
    assert (train + fold).n == total.n
    # model from the difference equals model from the rows
    m1 = PLSRegression(n_components=4).fit_stats(train)
    m2 = PLSRegression(n_components=4).fit(X[rest], Y[rest])
    assert max_rel(m1.coef_, m2.coef_) < 1e-9


def test_combining_statistics_with_different_shifts_raises():
    X, Y = make_well_conditioned(n=100)
    a = CrossProducts.from_arrays(X[:50], Y[:50])
    b = CrossProducts.from_arrays(X[50:], Y[50:])  # own provisional shift
    with pytest.raises(ValueError, match="different shifts"):
        a + b
    with pytest.raises(ValueError, match="negative row count"):
        b.reshifted(a.x_shift, a.y_shift) - CrossProducts.from_arrays(X, Y, a.x_shift, a.y_shift)
    # reshifting makes them combinable, with the same centered sums
    both = a + b.reshifted(a.x_shift, a.y_shift)
    ref = CrossProducts.from_arrays(X, Y)
    np.testing.assert_allclose(both.cxx, ref.cxx, rtol=1e-10, atol=1e-8)
    np.testing.assert_allclose(both.cxy, ref.cxy, rtol=1e-10, atol=1e-8)


def test_copy_is_independent():
    X, Y = make_well_conditioned(n=100)
    a = CrossProducts.from_arrays(X, Y)
    for b in (a.copy(), copy.deepcopy(a)):
        b.update(X[:10], Y[:10])
        assert a.n == 100 and b.n == 110


def test_shifted_accumulation_keeps_precision_far_from_zero():
    # Y ~ 1000 px + N(0, 1), fed as float32 chunks for X: centered sums must keep ~1e-9
    # relative precision (a naive unshifted sum of squares loses ~6 digits here).
    rng = np.random.default_rng(7)
    n, p, q = 20000, 5, 8
    X = (300.0 + rng.normal(size=(n, p))).astype(np.float32)
    Y = 1000.0 + rng.normal(size=(n, q)) + 0.3 * X[:, :1]
    stats = CrossProducts(p, q)
    for lo in range(0, n, 3000):
        stats.update(X[lo : lo + 3000], Y[lo : lo + 3000])
    X64 = X.astype(np.float64)
    Xc, Yc = X64 - X64.mean(0), Y - Y.mean(0)
    np.testing.assert_allclose(stats.cyy_diag, (Yc**2).sum(0), rtol=1e-9)
    np.testing.assert_allclose(stats.cxx, Xc.T @ Xc, rtol=1e-9)
    np.testing.assert_allclose(stats.cxy, Xc.T @ Yc, rtol=1e-9, atol=1e-9 * np.abs(Xc.T @ Yc).max())
    np.testing.assert_allclose(stats.y_mean, Y.mean(0), rtol=1e-14)


# --------------------------------------------------------------------------- degenerate columns


@pytest.mark.parametrize("scale", [True, False])
def test_constant_x_and_y_columns_behave_as_sklearn(scale):
    X, Y = make_well_conditioned(n=300, p=8, q=10)
    X[:, 2] = 0.1
    Y[:, 4] = 123.456
    ref = sk_exact(3, scale).fit(X, Y)
    model = PLSRegression(n_components=3, scale=scale).fit(X, Y)
    assert np.all(model.coef_[:, 2] == 0.0)
    assert np.all(model.coef_[4] == 0.0)
    np.testing.assert_allclose(model.predict(X)[:, 4], 123.456, rtol=1e-15)
    if scale:
        assert model.x_std_[2] == 1.0 and model.y_std_[4] == 1.0
    assert max_rel(model.coef_, ref.coef_) < 1e-10
    assert max_rel(model.predict(X), ref.predict(X)) < 1e-12
    # shifted by something other than their values, constant columns still get zero variance
    stats = CrossProducts.from_arrays(X, Y, x_shift=X.mean(0) + 0.37, y_shift=Y.mean(0) - 11.3)
    assert stats.cxx[2].max() == stats.cxx[:, 2].max() == stats.cyy_diag[4] == 0.0
    shifted = PLSRegression(n_components=3, scale=scale).fit_stats(stats)
    assert np.all(shifted.coef_[:, 2] == 0.0) and np.all(shifted.coef_[4] == 0.0)
    assert max_rel(shifted.coef_, model.coef_) < 1e-10


def test_all_constant_y_warns_and_predicts_the_mean():
    X, _ = make_well_conditioned(n=100, p=5, q=3)
    Y = np.tile([1.0, 2.0, 3.0], (100, 1))
    with pytest.warns(RuntimeWarning, match="vanished after 0"):
        model = PLSRegression(n_components=2).fit(X, Y)
    assert model.n_components_ == 0 and np.all(model.coef_ == 0.0)
    np.testing.assert_array_equal(model.predict(X[:4]), Y[:4])


# --------------------------------------------------------------------------- scoring


def test_scores_from_statistics_equal_r2_score():
    X, Y = make_well_conditioned(n=800, seed=11)
    Y[:, 3] = 5.0  # constant target in the test rows: sklearn's sst == 0 rules apply
    train, test = slice(0, 600), slice(600, 800)
    model = PLSRegression(n_components=5).fit(X[train], Y[train])
    test_stats = CrossProducts.from_arrays(X[test], Y[test])
    pred = model.predict(X[test])
    sse, sst = residual_sums(model.coef_, model.raw_intercept_, test_stats)
    np.testing.assert_allclose(sse, ((Y[test] - pred) ** 2).sum(0), rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(
        r2_per_target(sse, sst), r2_score(Y[test], pred, multioutput="raw_values"), rtol=1e-9, atol=1e-12
    )
    np.testing.assert_allclose(
        r2_variance_weighted(sse, sst), r2_score(Y[test], pred, multioutput="variance_weighted"), rtol=1e-10
    )


def test_r2_path_equals_r2_score_for_each_k():
    X, Y = make_well_conditioned(n=800, seed=12)
    model = PLSRegression(n_components=8).fit(X[:600], Y[:600])
    test_stats = CrossProducts.from_arrays(X[600:], Y[600:])
    path = r2_path(model, test_stats)
    expected = [
        r2_score(Y[600:], model.predict(X[600:], n_components=k), multioutput="variance_weighted") for k in range(1, 9)
    ]
    np.testing.assert_allclose(path, expected, rtol=1e-10)
    assert path.shape == (8,)


@pytest.mark.parametrize("scale", [True, False])
def test_r2_path_equals_scoring_each_model_of_the_coefficient_path(scale):
    """The closed form over pairs of components against residual_sums of every model of ``coef_path_``, with a
    constant target (zero weight), a held-out set whose means differ from the training set's, all components."""
    X, Y = make_well_conditioned(n=900, p=10, q=25, seed=13)
    Y[:, 3] = 7.0  # constant in training and test
    model = PLSRegression(n_components=10, scale=scale).fit(X[:500], Y[:500])
    X_test, Y_test = X[500:] + 0.3, Y[500:] - 2.0  # shifted: the intercept terms count
    test_stats = CrossProducts.from_arrays(X_test, Y_test)
    sse, sst = residual_sums(model.coef_path_, model.raw_intercept_path_, test_stats)
    np.testing.assert_allclose(r2_path(model, test_stats), r2_variance_weighted(sse, sst), rtol=1e-11)
    expected = [
        r2_score(Y_test, model.predict(X_test, n_components=k), multioutput="variance_weighted") for k in range(1, 11)
    ]
    np.testing.assert_allclose(r2_path(model, test_stats), expected, rtol=1e-9)


def test_r2_edge_cases_follow_sklearn_force_finite():
    y = np.array([[1.0, 2.0], [1.0, 3.0], [1.0, 5.0]])
    perfect_const = np.array([[1.0, 2.5], [1.0, 3.0], [1.0, 4.0]])
    wrong_const = np.array([[2.0, 2.5], [1.0, 3.0], [1.0, 4.0]])
    for pred in (perfect_const, wrong_const):
        sse = ((y - pred) ** 2).sum(0)
        sst = ((y - y.mean(0)) ** 2).sum(0)
        np.testing.assert_allclose(r2_per_target(sse, sst), r2_score(y, pred, multioutput="raw_values"))
        assert np.isclose(r2_variance_weighted(sse, sst), r2_score(y, pred, multioutput="variance_weighted"))
    all_const = np.ones((3, 2))
    sse = ((all_const - wrong_const[:, :1].repeat(2, 1)) ** 2).sum(0)
    assert np.isclose(
        r2_variance_weighted(sse, np.zeros(2)),
        r2_score(all_const, wrong_const[:, :1].repeat(2, 1), multioutput="variance_weighted"),
    )


# --------------------------------------------------------------------------- bad input


def test_too_many_components_raises():
    X, Y = make_well_conditioned(n=50, p=6, q=4)
    with pytest.raises(ValueError, match="upper bound is 6"):
        PLSRegression(n_components=7).fit(X, Y)
    with pytest.raises(ValueError, match="upper bound is 5"):
        PLSRegression(n_components=6).fit(X[:5], Y[:5])
    with pytest.raises(ValueError, match=">= 1"):
        PLSRegression(n_components=0).fit(X, Y)
    model = PLSRegression(n_components=3).fit(X, Y)
    with pytest.raises(ValueError, match=r"\[1, 3\]"):
        model.coef_for(4)


def test_nan_input_raises():
    X, Y = make_well_conditioned(n=50, p=6, q=4)
    X[7, 2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        PLSRegression(n_components=2).fit(X, Y)
    stats = CrossProducts(6, 4)
    with pytest.raises(ValueError, match="NaN"):
        stats.update(X, Y)
    X[7, 2] = 0.0
    Y[3, 1] = np.inf
    with pytest.raises(ValueError, match="infinity"):
        stats.update(X, Y)
    assert stats.n == 0


def test_mismatched_rows_and_columns_raise():
    X, Y = make_well_conditioned(n=50, p=6, q=4)
    with pytest.raises(ValueError, match="different numbers of rows"):
        PLSRegression(n_components=2).fit(X, Y[:-1])
    with pytest.raises(ValueError, match="different numbers of rows"):
        CrossProducts(6, 4).update(X, Y[:-1])
    with pytest.raises(ValueError, match="columns"):
        CrossProducts(6, 5).update(X, Y)
    model = PLSRegression(n_components=2).fit(X, Y)
    with pytest.raises(ValueError, match="features"):
        model.predict(X[:, :5])


@pytest.mark.filterwarnings("ignore::sklearn.exceptions.SkipTestWarning")
def test_passes_sklearn_estimator_checks():
    # drop-in guarantee: params-only __init__, validation in fit, clone/get_params, tags
    check_estimator(PLSRegression(n_components=1))


@pytest.mark.slow
def test_the_evaluate_stage_fits_and_scores_without_importing_scikit_learn(tmp_path):
    """The evaluate stage's modules fit from statistics and score on held-out statistics with NumPy alone
    (importing scikit-learn, and SciPy's statistics with it, cost ~1 s of every evaluate); the same numbers as the
    estimator."""
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "from aumesh.tracking import beside, mlflow_store, pyfunc\nfrom aumesh.tracking import runs as tracking\n"
        "from aumesh.pipeline import dvc_metrics, evaluate as ev\nfrom aumesh.stages import evaluate as stage\n"
        "from aumesh.model.cross_products import CrossProducts\n"
        "from aumesh.model.scoring import r2_path\n"
        "rng = np.random.default_rng(0); X = rng.normal(size=(300, 6)); Y = X @ rng.normal(size=(6, 9)) + rng.normal(size=(300, 9))\n"
        "fit = ev.fit(CrossProducts.from_arrays(X[:200], Y[:200]), 4, True)\n"
        "path = r2_path(fit, CrossProducts.from_arrays(X[200:], Y[200:]))\n"
        "print([m for m in sys.modules if m.split('.')[0] == 'sklearn' or m == 'scipy.stats'])\n"
        "np.save(sys.argv[1], np.concatenate([fit.coef_.ravel(), path]))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "out.npy")], capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "[]"
    values = np.load(tmp_path / "out.npy")
    rng = np.random.default_rng(0)
    X = rng.normal(size=(300, 6))
    Y = X @ rng.normal(size=(6, 9)) + rng.normal(size=(300, 9))
    model = PLSRegression(n_components=4).fit(X[:200], Y[:200])
    assert np.array_equal(values[:54], model.coef_.ravel())
    np.testing.assert_allclose(values[54:], r2_path(model, CrossProducts.from_arrays(X[200:], Y[200:])), rtol=1e-13)
