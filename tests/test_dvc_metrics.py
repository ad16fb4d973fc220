"""The committed metrics and plot data (`dvc metrics diff`, `dvc plots diff`): curves against SciPy's ECDF and NumPy."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from aumesh.pipeline import dvc_metrics


def test_error_curve_is_scipys_empirical_cdf_at_the_frames_own_errors():
    e = np.random.default_rng(0).gamma(2.0, 1.3, size=3751)
    e[[5, 17]] = np.nan  # unscored frames are left out
    x, frac = dvc_metrics.error_curve(e, n_points=101)
    finite = e[np.isfinite(e)]
    assert x.shape == frac.shape == (101,)
    assert x[0] == finite.min() and x[-1] == finite.max() and frac[-1] == 1.0
    assert np.isin(x, finite).all() and np.all(np.diff(x) >= 0)
    np.testing.assert_allclose(frac, stats.ecdf(finite).cdf.evaluate(x), rtol=0, atol=1e-15)
    np.testing.assert_allclose(frac, np.linspace(0, 1, 101), atol=1.0 / finite.size)  # at the quantiles
    with pytest.raises(ValueError, match="no finite value"):
        dvc_metrics.error_curve(np.full(3, np.nan))


@pytest.mark.parametrize("scheduler", ["synchronous", "threads"])
def test_error_curve_of_a_vector_on_disk_read_in_blocks_is_bit_equal_to_numpys(tmp_path, monkeypatch, scheduler):
    """float32 errors on disk (ties: a coarse grid; unscored NaN frames), read 97 values at a time: the curve equals
    np.quantile of the whole vector and the exact fraction <= each value, bit for bit."""
    from aumesh.config import ComputeConfig
    from aumesh.core.io import NpyRows
    from aumesh.pipeline import compute

    rng = np.random.default_rng(5)
    e = np.round(rng.gamma(2.0, 1.3, size=5003) * 20).astype(np.float32) / 20
    e[[0, 900, 4000]] = np.nan
    np.save(tmp_path / "err.npy", e)
    monkeypatch.setattr(dvc_metrics, "BLOCK_ROWS", 97)
    finite = np.sort(e[np.isfinite(e)].astype(np.float64))
    for n_points in (101, 1001):
        expected = np.quantile(finite, np.linspace(0, 1, n_points), method="inverted_cdf")
        with compute.engine(ComputeConfig(scheduler=scheduler, n_workers=2)):
            x, frac = dvc_metrics.error_curve(NpyRows(tmp_path / "err.npy"), n_points)
        np.testing.assert_array_equal(x, expected)
        np.testing.assert_array_equal(frac, np.searchsorted(finite, expected, side="right") / finite.size)


def test_r2_curve_is_the_fold_mean_for_every_k():
    path = np.random.default_rng(1).uniform(0, 1, size=(3, 17))
    k, r2 = dvc_metrics.r2_curve(path)
    np.testing.assert_array_equal(k, np.arange(1, 18))
    np.testing.assert_allclose(r2, path.sum(axis=0) / 3, rtol=1e-15)


def test_rounding_hides_last_bit_differences_and_keeps_six_significant_digits():
    a, b = 0.21495742264526327, np.nextafter(0.21495742264526327, 1.0)
    assert a != b and dvc_metrics.rounded(a) == dvc_metrics.rounded(b) == 0.214957
    assert dvc_metrics.rounded({"x": [1234.56789, 3], "n": 83, "s": "a"}) == {"x": [1234.57, 3], "n": 83, "s": "a"}


def test_write_gives_rounded_json_and_two_csv_plots(tmp_path):
    paths = SimpleNamespace(
        metrics_file=tmp_path / "m" / "metrics.json",
        error_curve_file=tmp_path / "m" / "err.csv",
        r2_curve_file=tmp_path / "m" / "r2.csv",
    )
    rng = np.random.default_rng(2)
    err, path = rng.gamma(2.0, 1.0, size=500), rng.uniform(0, 1, size=(3, 23))
    dvc_metrics.write(paths, {"r2_mean": 0.123456789, "r2_folds": [0.1111111111, 0.2], "n_components": 23}, err, path)
    assert json.loads(paths.metrics_file.read_text()) == {
        "r2_mean": 0.123457,
        "r2_folds": [0.111111, 0.2],
        "n_components": 23,
    }
    curve = pd.read_csv(paths.error_curve_file)
    assert list(curve.columns) == ["vertex_error", "fraction_of_frames"] and len(curve) == 101
    np.testing.assert_allclose(curve["vertex_error"], dvc_metrics.error_curve(err)[0], rtol=1e-5)
    r2 = pd.read_csv(paths.r2_curve_file)
    assert list(r2.columns) == ["n_components", "r2"] and r2["n_components"].tolist() == list(range(1, 24))
    np.testing.assert_allclose(r2["r2"], path.mean(axis=0), rtol=1e-5)
