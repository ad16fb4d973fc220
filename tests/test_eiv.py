"""aumesh.model.eiv against independent references: numpy's least squares, a known truth under simulated detector
noise, the explicit corrected fit, and Monte Carlo error covariances."""

from __future__ import annotations

import numpy as np
import pytest

from aumesh.core.errors import ConfigError
from aumesh.core.schema import AU_COLUMNS, POSE_COLUMNS, feature_columns
from aumesh.model import eiv
from aumesh.model.cross_products import CrossProducts


def _cos(a, b):
    return np.einsum("kq,kq->k", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))


def _coactivated(n=60_000, q=40, seed=0, noise=0.0, sigma=None):
    """Two strongly co-activated inputs (r ~ 0.98, their difference's sd 0.03), the second's field small and opposed to
    the first's, and three independent ones (sd 0.2); rows already demeaned (a within-video design).
    Returns (X observed, Y, B true, X true)."""
    rng = np.random.default_rng(seed)
    common = rng.normal(size=n)
    x = (
        np.column_stack(
            [common + 0.15 * rng.normal(size=n), common + 0.15 * rng.normal(size=n), *rng.normal(size=(3, n))]
        )
        * 0.2
    )
    base = rng.normal(size=q)
    B = np.vstack([base, -0.25 * base + 0.1 * rng.normal(size=q), *rng.normal(size=(3, q))])
    Y = x @ B + 0.01 * rng.normal(size=(n, q))
    cov = sigma if sigma is not None else noise**2 * np.eye(5)
    observed = x + rng.multivariate_normal(np.zeros(5), cov, size=n)
    return observed, Y, B, x


def test_without_noise_the_corrected_fit_is_numpy_least_squares():
    X, Y, _, _ = _coactivated(n=5000)
    Xc, Yc = X - X.mean(0), Y - Y.mean(0)
    ref = np.linalg.lstsq(Xc, Yc, rcond=None)[0]
    got = eiv.floored_corrected_coef(Xc.T @ Xc, Xc.T @ Yc, np.zeros((5, 5)), 0.3)
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12)


def test_the_corrected_fit_with_the_true_noise_recovers_the_truth_where_least_squares_reverses_a_field():
    sigma = np.diag([0.03, 0.035, 0.02, 0.04, 0.03]) ** 2
    X, Y, B, _ = _coactivated(sigma=sigma)
    n = len(X)
    ols = eiv.floored_corrected_coef(X.T @ X / n, X.T @ Y / n, np.zeros((5, 5)))
    fixed = eiv.floored_corrected_coef(X.T @ X / n, X.T @ Y / n, sigma, floor=0.3)
    assert _cos(ols, B)[1] < 0  # the small co-activated field comes out reversed: the problem
    assert _cos(fixed, B).min() > 0.95
    # the scale of the moments does not matter: sums with n Sigma_u give the same coefficients
    np.testing.assert_allclose(eiv.floored_corrected_coef(X.T @ X, X.T @ Y, n * sigma, 0.3), fixed, rtol=1e-8)


def test_the_floor_bounds_the_amplification_of_every_whitened_direction():
    X, Y, _, _ = _coactivated(n=4000)
    S = X.T @ X / len(X)
    huge = 10.0 * S  # noise larger than the signal: without the floor the corrected moments are not even PSD
    inv = eiv._corrected_inverse(S, huge, 0.3)
    # along S's whitened directions the corrected inverse is the uncorrected one times 1 / rho, rho floored at 0.3
    lam, V = np.linalg.eigh(S)
    root = V @ np.diag(np.sqrt(lam)) @ V.T
    gains = np.linalg.eigvalsh(root @ inv @ root)
    np.testing.assert_allclose(gains, 1 / 0.3, rtol=1e-8)


def test_the_screen_equals_the_explicit_corrected_fit_with_an_isotropic_noise():
    X, Y, _, _ = _coactivated(n=4000, noise=0.05)
    n = len(X)
    S, Sxy = X.T @ X / n, X.T @ Y / n
    names = [f"A{i}" for i in range(5)]
    screen = eiv.identification_screen(S, Sxy, names, sigma_step=0.01, sigma_max=0.2, floor=0.3)
    B = np.linalg.solve(S, Sxy)
    for g, sigma in enumerate(screen.grid):
        Bc = eiv.floored_corrected_coef(S, Sxy, sigma**2 * np.eye(5), 0.3)
        np.testing.assert_allclose(screen.cosines[g], _cos(Bc, B), rtol=1e-9, atol=1e-12)
    first = [
        next((s for s, c in zip(screen.grid, screen.cosines[:, k], strict=True) if c < 0.5), np.nan) for k in range(5)
    ]
    np.testing.assert_array_equal(screen.sigma_star, first)


def test_the_screen_flags_the_small_coactivated_field_with_its_partner_and_nothing_on_independent_inputs():
    X, Y, B, _ = _coactivated(noise=0.03)
    n = len(X)
    names = ["big", "small", "c", "d", "e"]
    assert _cos(np.linalg.lstsq(X, Y, rcond=None)[0], B)[1] < 0  # reversed by the noise
    screen = eiv.identification_screen(X.T @ X / n, X.T @ Y / n, names, flag_below=0.10)
    assert screen.flagged_names() == ["small"]
    assert screen.partner[1] == "big"
    assert screen.sigma_star[1] < 0.10
    assert np.isnan(screen.sigma_star[2:]).all()  # independent inputs never turn within the grid
    # the group's field (both moved together) is identified: it turns much later than its member, if at all
    assert np.isnan(screen.group_sigma_star[1]) or screen.group_sigma_star[1] > 2 * screen.sigma_star[1]
    card = screen.to_card()
    assert card["small"]["flagged"] and card["small"]["partner"] == "big" and card["small"]["group"] == "big+small"
    arrays = screen.release_arrays()
    assert arrays["au_identification_flagged"].dtype == bool and arrays["au_identification_partner"][1] == "big"
    # the same inputs measured without noise: the small field is right, and correcting only amplifies it (no flag)
    X0, Y0, _, _ = _coactivated(noise=0.0)
    assert not eiv.identification_screen(X0.T @ X0 / n, X0.T @ Y0 / n, names).flagged.any()


def test_the_dominant_partner_maximises_correlation_times_relative_field_size():
    rng = np.random.default_rng(3)
    C = np.cov(rng.normal(size=(4, 500)))
    B = rng.normal(size=(4, 7))
    partner, weight = eiv.dominant_partners(C, B)
    sd = np.sqrt(np.diag(C))
    for k in range(4):
        scores = {
            j: abs(C[k, j] / sd[k] / sd[j]) * np.linalg.norm(B[j]) / np.linalg.norm(B[k]) for j in range(4) if j != k
        }
        assert partner[k] == max(scores, key=scores.get)
        assert weight[k] == pytest.approx(max(scores.values()))


@pytest.mark.slow
def test_the_design_error_covariance_matches_monte_carlo():
    rng = np.random.default_rng(7)
    n = 400_000
    sigma = np.diag(rng.uniform(0.02, 0.08, 20)) ** 2
    sigma[0, 1] = sigma[1, 0] = 0.5 * np.sqrt(sigma[0, 0] * sigma[1, 1])
    pose = rng.normal([0.1, -0.2, 0.05], [0.2, 0.3, 0.1], size=(n, 3))
    u = rng.multivariate_normal(np.zeros(20), sigma, size=n)
    columns = feature_columns(True, True)
    errors = np.column_stack([u, np.zeros((n, 3)), (pose[:, :, None] * u[:, None, :]).reshape(n, -1)])
    empirical = errors.T @ errors / n
    got = eiv.design_error_covariance(sigma, columns, pose.mean(0), pose.T @ pose / n)
    assert columns[20:23] == list(POSE_COLUMNS) and columns[23].split("*")[0] in POSE_COLUMNS
    np.testing.assert_allclose(got, empirical, atol=5 * sigma.max() / np.sqrt(n) * 10)


def test_two_stage_least_squares_with_an_independent_second_measurement_recovers_the_truth():
    sigma = 0.06**2 * np.eye(5)
    X, Y, B, x_true = _coactivated(sigma=sigma, seed=1)
    Z = x_true + np.random.default_rng(9).normal(0, 0.06, size=x_true.shape)
    n = len(X)
    aug = np.column_stack([X, Z])
    stats = CrossProducts.from_arrays(aug, Y)
    fit = eiv.instrumental_fit(stats, 5)
    Xc, Zc, Yc = X - X.mean(0), Z - Z.mean(0), Y - Y.mean(0)
    np.testing.assert_allclose(fit.coef_.T, np.linalg.solve(Zc.T @ Xc, Zc.T @ Yc), rtol=1e-7, atol=1e-10)
    assert _cos(fit.coef_.T, B).min() > 0.95
    assert _cos(fit.uncorrected_coef_.T, B)[1] < _cos(fit.coef_.T, B)[1]
    np.testing.assert_allclose(X @ fit.coef_.T + fit.raw_intercept_, (X - X.mean(0)) @ fit.coef_.T + Y.mean(0))
    strength = eiv.first_stage_strength(Zc.T @ Zc / n, Zc.T @ Xc / n, Xc.T @ Xc / n, n, names=list("abcde"))
    r2_ref = 1 - ((Xc[:, 0] - Zc @ np.linalg.lstsq(Zc, Xc[:, 0], rcond=None)[0]) ** 2).sum() / (Xc[:, 0] ** 2).sum()
    assert strength["a"]["r2"] == pytest.approx(r2_ref, rel=1e-8)
    assert strength["a"]["f"] > 100


def test_a_corrected_fit_from_statistics_predicts_with_its_own_intercept():
    sigma = 0.05**2 * np.eye(5)
    X, Y, _, _ = _coactivated(n=3000, sigma=sigma)
    stats = CrossProducts.from_arrays(X, Y)
    fit = eiv.corrected_fit(stats, sigma, 0.3)
    Xc, Yc = X - X.mean(0), Y - Y.mean(0)
    np.testing.assert_allclose(
        fit.coef_.T, eiv.floored_corrected_coef(Xc.T @ Xc, Xc.T @ Yc, len(X) * sigma, 0.3), rtol=1e-8
    )
    np.testing.assert_allclose(fit.uncorrected_coef_.T, np.linalg.lstsq(Xc, Yc, rcond=None)[0], rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(fit.raw_intercept_, Y.mean(0) - X.mean(0) @ fit.coef_.T)


def test_sigma_u_files_are_read_and_bad_ones_named_with_the_fix(tmp_path):
    rng = np.random.default_rng(0)
    A = rng.normal(size=(20, 20)) * 0.01
    good = A @ A.T
    np.save(tmp_path / "s.npy", good)
    np.testing.assert_allclose(eiv.load_sigma_u(tmp_path / "s.npy"), good)
    sd, corr = np.sqrt(np.diag(good)), good / np.sqrt(np.outer(np.diag(good), np.diag(good)))
    np.savez(tmp_path / "s.npz", sd=sd, correlation=corr)
    np.testing.assert_allclose(eiv.load_sigma_u(tmp_path / "s.npz"), good, rtol=1e-10)
    np.save(tmp_path / "wrong.npy", good[:19, :19])
    np.save(tmp_path / "asym.npy", good + np.triu(np.ones((20, 20))) * 1e-3)
    np.save(tmp_path / "neg.npy", -good)
    for name, words in [
        ("wrong.npy", "shape (19, 19)"),
        ("asym.npy", "not symmetric"),
        ("neg.npy", "semi-definite"),
        ("missing.npy", "no such file"),
    ]:
        with pytest.raises(ConfigError, match="model.eiv.sigma_u") as err:
            eiv.load_sigma_u(tmp_path / name)
        assert words in str(err.value) and "au_columns order" in str(err.value)
        assert AU_COLUMNS[0] in str(err.value)


def test_the_screen_grid_ends_at_sigma_max():
    np.testing.assert_allclose(eiv.screen_grid(0.005, 0.2)[[0, -1]], [0.005, 0.2])
    assert len(eiv.screen_grid(0.005, 0.2)) == 40
    assert eiv.screen_grid(0.03, 0.2)[-1] == 0.2
