"""AU detector noise in the synthetic tables (issue 43): off by default (the tables of the generator before it), the AR(1)
and cross-AU correlation the spec asks for, the generator's within-video error covariance against the generated noise,
a second detector's ``{au}_2`` columns in every layout, and noisy py-feat tables through the ingest."""

from __future__ import annotations

import dataclasses
import hashlib
import subprocess
import sys
import types
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from aumesh.core.schema import AU_COLUMNS
from aumesh.data import tables
from aumesh.model.eiv import load_sigma_u
from aumesh.pipeline import ingest, prepare
from aumesh.synthetic import au_noise
from aumesh.synthetic import tables as synth
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from conftest import REPO, default_config

#: The last commit of the generator before detector noise: its tables are the reference for "off by default".
BEFORE_NOISE = "2400a91"
I2 = list(synth.INSTRUMENT_COLUMNS)


def _digests(folder: Path) -> dict[str, str]:
    return {
        str(f.relative_to(folder)): hashlib.sha256(f.read_bytes()).hexdigest()
        for f in sorted(folder.rglob("*"))
        if f.is_file()
    }


def _old_tables_module() -> types.ModuleType:
    """``aumesh.synthetic.tables`` as it was at :data:`BEFORE_NOISE` (skipped without the git history)."""
    try:
        source = subprocess.run(
            ["git", "show", f"{BEFORE_NOISE}:src/aumesh/synthetic/tables.py"],
            cwd=REPO,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip(f"git history with {BEFORE_NOISE} not available")
    module = types.ModuleType("old_synth_tables")
    sys.modules[module.__name__] = module  # dataclasses look their module up
    try:
        exec(compile(source, "old_synth_tables", "exec"), module.__dict__)  # noqa: S102 - our own file, older
    finally:
        del sys.modules[module.__name__]
    return module


@pytest.mark.slow
@pytest.mark.parametrize("layout", ["columns", "pyfeat"])
def test_without_noise_the_tables_and_truth_are_byte_identical_to_the_generator_before_it(tmp_path, layout):
    old = _old_tables_module()
    kwargs = dict(n_frames=360, n_videos=9, seed=4, layout=layout, identity_au_coupling=0.1, frames_per_file=150)
    old.write_tables(tmp_path / "old", old.SynthSpec(**kwargs), tmp_path / "old" / "truth.npz")
    synth.write_tables(tmp_path / "new", synth.SynthSpec(**kwargs), tmp_path / "new" / "truth.npz")
    old_files, new_files = _digests(tmp_path / "old"), _digests(tmp_path / "new")
    assert len(old_files) >= 3 and new_files == old_files


def test_inert_noise_settings_change_nothing(tmp_path):
    """The knobs only act when they are on: other AR, correlation and co-activation pairs with the sds at 0 write
    the same files, and the recorded AUs are the true ones."""
    spec = synth.SynthSpec(n_frames=200, n_videos=6, seed=2)
    inert = replace(spec, au_noise_ar=0.2, au_noise_correlation=(), coactivated_aus=(), au_activity=1.0)
    synth.write_tables(tmp_path / "a", spec, tmp_path / "a" / "truth.npz")
    synth.write_tables(tmp_path / "b", inert, tmp_path / "b" / "truth.npz")
    a, b = _digests(tmp_path / "a"), _digests(tmp_path / "b")
    assert a.pop("truth.npz") != b.pop("truth.npz") and a == b  # the truth's spec record names the settings
    ta, tb = np.load(tmp_path / "a" / "truth.npz"), np.load(tmp_path / "b" / "truth.npz")
    assert ta.files == tb.files and all(np.array_equal(ta[k], tb[k]) for k in ta.files if k != "spec")
    counts, args = synth.frames_per_video(spec), _gen_args(spec)
    g = synth.generate_video(spec, 0, int(counts[0]), *args)
    assert g["au"] is g["au_true"] and "au_error" not in g and "au2" not in g
    assert set(np.load(tmp_path / "a" / "truth.npz").files).isdisjoint({"au_sigma_u_within", "frames_per_video"})


def _gen_args(spec):
    from aumesh.synthetic.pyfeat_faces import synth_setup

    return synth_setup(spec)[1]


def test_the_error_is_the_ar1_and_cross_au_correlation_the_spec_asks_for():
    pairs = (("AU06", "AU12", 0.5), ("AU09", "AU10", -0.3), ("AU25", "AU26", 0.7))
    spec = synth.SynthSpec(n_frames=12_000, n_videos=4, seed=5, au_noise_sd=0.07, au_noise_ar=0.6)
    spec = replace(spec, au_noise_correlation=pairs)
    counts = synth.frames_per_video(spec)
    errors = [synth.detector_readings(spec, v, np.full((int(n), 20), 0.5))["au_error"] for v, n in enumerate(counts)]
    e = np.concatenate(errors)
    n = len(e)
    # sd: Var of a sample variance of an AR(1) ~ 2 s^4 (1 + phi^2) / (1 - phi^2) / n
    se_var = 2 * 0.07**4 * (1 + 0.36) / (1 - 0.36) / n
    np.testing.assert_allclose(e.var(axis=0), 0.07**2, atol=5 * np.sqrt(se_var))
    # lag-1 autocorrelation within each video: phi, se ~ sqrt((1 - phi^2) / n)
    lag1 = sum((x[1:] * x[:-1]).sum(0) for x in errors) / sum((x[:-1] ** 2).sum(0) for x in errors)
    np.testing.assert_allclose(lag1, 0.6, atol=5 * np.sqrt((1 - 0.36) / n))
    # cross-AU correlation at lag 0: the pairs', 0 elsewhere; se ~ (1 - rho^2) sqrt((1 + phi^2) / (1 - phi^2) / n)
    R = np.corrcoef(e.T)
    want = np.eye(20)
    for a, b, rho in pairs:
        want[AU_COLUMNS.index(a), AU_COLUMNS.index(b)] = want[AU_COLUMNS.index(b), AU_COLUMNS.index(a)] = rho
    np.testing.assert_allclose(R, want, atol=5 * np.sqrt((1 + 0.36) / (1 - 0.36) / n))
    # stationary from the first frame: across many short videos, frame 0 has the same variance as frame 20
    starts = np.stack([synth.detector_readings(spec, v, np.zeros((21, 20)))["au_error"] for v in range(400)])
    for t in (0, 20):
        np.testing.assert_allclose(starts[:, t].var(), 0.07**2, rtol=5 * np.sqrt(2 / starts[:, t].size))


def _within_se(counts: np.ndarray, ar: float) -> np.ndarray:
    """Per video ``tr(A^2)``, ``A = M Gamma M`` (``M`` the centring, ``Gamma`` the AR(1) correlation): a Gaussian
    error's within-video sum of squares has variance ``2 s^4 tr(A^2)`` (a cross product ``(1 + rho^2) s^4 tr(A^2)``)."""
    out = []
    for T in counts:
        i = np.arange(T)
        M = np.eye(T) - 1.0 / T
        A = M @ ar ** np.abs(i[:, None] - i[None, :]) @ M
        out.append(np.sum(A * A))
    return np.asarray(out)


def test_the_generators_sigma_u_is_the_within_video_covariance_of_its_noise():
    spec = synth.realistic_noise_spec(n_frames=60_000, n_videos=4000, seed=1, au_noise_sd=0.07)
    counts = synth.frames_per_video(spec)
    e = np.concatenate(
        [synth.detector_readings(spec, v, np.full((n, 20), 0.5))["au_error"] for v, n in enumerate(counts)]
    )
    empirical = au_noise.within_covariance(e, counts)
    analytic = au_noise.au_error_covariance(spec, counts)
    s2, tr = 0.07**2, _within_se(counts, spec.au_noise_ar).sum()
    rho = au_noise.correlation_matrix(spec.au_noise_correlation)
    se = s2 * np.sqrt((1 + rho**2) * tr) / counts.sum()  # diagonal: 2 tr; rho^2 = 1 there
    assert np.all(np.abs(empirical - analytic) < 4 * se)
    # the AR(1) matters at ~15 frames per video: white noise's share (1 - videos / frames) is many errors away
    white = s2 * rho * (1 - len(counts) / counts.sum())
    assert np.all(np.abs(np.diag(white - empirical)) > 10 * np.diag(se))


def test_the_truth_file_holds_sigma_u_and_writes_the_npy_model_eiv_reads(tmp_path):
    spec = synth.SynthSpec(n_frames=300, n_videos=10, seed=6, au_noise_sd=0.05, instrument_noise_sd=0.08)
    synth.write_tables(tmp_path / "data", spec, tmp_path / "truth.npz")
    truth = np.load(tmp_path / "truth.npz")
    counts = synth.frames_per_video(spec)
    np.testing.assert_array_equal(truth["frames_per_video"], counts)
    share = au_noise.within_share(counts, 0.7)
    np.testing.assert_allclose(np.diag(truth["au_sigma_u_within"]), 0.05**2 * share)
    np.testing.assert_allclose(np.diag(truth["au2_sigma_u_within"]), 0.08**2 * share)
    path = synth.write_truth_sigma_u(tmp_path / "truth.npz")
    assert path == tmp_path / "sigma_u.npy"
    np.testing.assert_array_equal(load_sigma_u(path), truth["au_sigma_u_within"])
    # the recorded error (after clipping to [0, 1]) measured from the tables' AUs and the true ones
    au = pd.read_parquet(tmp_path / "data" / "frames_0000.parquet")[list(AU_COLUMNS)].to_numpy()
    gen = _gen_args(spec)
    true = np.concatenate([synth.generate_video(spec, v, int(n), *gen)["au_true"] for v, n in enumerate(counts)])
    np.testing.assert_allclose(truth["au_sigma_u_within_recorded"], au_noise.within_covariance(au - true, counts))


@pytest.mark.slow
def test_the_second_detector_is_its_own_noise_on_the_same_frames(tmp_path):
    spec = synth.SynthSpec(n_frames=3000, n_videos=20, seed=8, au_noise_sd=0.06, instrument_noise_sd=0.06)
    synth.write_tables(tmp_path / "cols", spec)
    synth.write_tables(tmp_path / "split", replace(spec, layout="pyfeat"))
    cols = pd.read_parquet(tmp_path / "cols" / "frames_0000.parquet")
    split = pd.read_parquet(tmp_path / "split" / "frames_0000.parquet")
    assert list(cols.columns[cols.columns.get_loc("AU43") + 1 :][:20]) == I2
    pd.testing.assert_frame_equal(cols[list(AU_COLUMNS) + I2], split[list(AU_COLUMNS) + I2])
    gen = _gen_args(spec)
    true = np.concatenate(
        [synth.generate_video(spec, v, int(n), *gen)["au_true"] for v, n in enumerate(synth.frames_per_video(spec))]
    )
    e1, e2 = cols[list(AU_COLUMNS)].to_numpy() - true, cols[I2].to_numpy() - true
    assert cols[I2].to_numpy().min() >= 0 and cols[I2].to_numpy().max() <= 1
    # independent errors: their correlation is 0 within ~5 se of an AR(1) 0.7 sample correlation
    r = np.array([np.corrcoef(e1[:, k], e2[:, k])[0, 1] for k in range(20)])
    assert np.all(np.abs(r) < 5 * np.sqrt((1 + 0.49) / (1 - 0.49) / len(true)))
    assert np.all(np.abs(e1).mean(0) > 0.02) and np.all(np.abs(e2).mean(0) > 0.02)  # both detectors are noisy


@pytest.mark.slow
@pytest.mark.parametrize("detector,fmt", [("mp", "csv"), ("v2", "csv"), ("mp", "parquet"), ("v2", "parquet")])
def test_pyfeat_tables_carry_both_detectors_aus(tmp_path, detector, fmt):
    spec = synth.SynthSpec(n_frames=240, n_videos=6, seed=3, au_noise_sd=0.05, instrument_noise_sd=0.05)
    write_pyfeat_tables(tmp_path / "d", spec, detector=detector, fmt=fmt, clean_dir=tmp_path / "clean")
    path = tmp_path / "d" / f"clip_0000.{fmt}"
    table = pd.read_csv(path) if fmt == "csv" else pq.read_table(path).to_pandas()
    start = table.columns.get_loc("AU43") + 1
    assert list(table.columns[start : start + 20]) == I2
    clean = pd.read_parquet(tmp_path / "clean" / "clip_0000.parquet")
    main = table[(table["Identity"] == "Person_0")].reset_index(drop=True)
    # the main face's readings of both detectors are the clean tables' (the generator's), frame by frame
    np.testing.assert_allclose(main[I2].to_numpy(), clean[I2].to_numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(main[list(AU_COLUMNS)].to_numpy(), clean[list(AU_COLUMNS)].to_numpy(), atol=1e-12)
    # without the instrument no such column, and the AU columns are where they were
    write_pyfeat_tables(tmp_path / "one", replace(spec, instrument_noise_sd=0.0), detector=detector, fmt=fmt)
    plain = pd.read_csv(tmp_path / "one" / "clip_0000.csv", nrows=2) if fmt == "csv" else None
    names = plain.columns if plain is not None else pq.read_schema(tmp_path / "one" / "clip_0000.parquet").names
    assert not set(I2) & set(names) and list(names) == [c for c in table.columns if c not in I2]


@pytest.mark.slow
def test_noisy_pyfeat_csv_with_a_second_detector_still_ingests_as_its_clean_tables(tmp_path):
    spec = synth.realistic_noise_spec(n_frames=450, n_videos=12, seed=3, instrument_noise_sd=0.07)
    write_pyfeat_tables(tmp_path / "csv", spec, detector="mp", fmt="csv", clean_dir=tmp_path / "clean")
    prepared = {}
    for name in ("csv", "clean"):
        cfg = default_config()
        cfg = dataclasses.replace(cfg, paths=dataclasses.replace(cfg.paths, data_dir=str(tmp_path / name)))
        manifest = ingest.run(cfg, tmp_path / f"{name}_work" / "ingested")
        found = tables.check_tables(manifest["tables"], cfg.data.mesh_npy, cfg.data.coerce_numeric)
        prepare.run(found, cfg, tmp_path / f"{name}_work" / "prepared", ingested=manifest["counts"])
        prepared[name] = pd.read_parquet(tmp_path / f"{name}_work" / "prepared" / "frames.parquet")
    pd.testing.assert_frame_equal(prepared["csv"], prepared["clean"])
    # the AUs trained on are the noisy detector's, not the truth
    clean = pd.read_parquet(tmp_path / "clean" / "clip_0000.parquet")
    assert float(np.abs(clean[list(AU_COLUMNS)].to_numpy() - clean[I2].to_numpy()).mean()) > 0.03


def test_the_realistic_preset_coactivates_and_its_control_has_the_same_frames():
    spec = synth.realistic_noise_spec(n_frames=6000, n_videos=160, seed=2)
    control = synth.realistic_noise_spec(n_frames=6000, n_videos=160, seed=2, au_noise_sd=0.0)
    counts, gen = synth.frames_per_video(spec), _gen_args(spec)
    noisy, clean = [], []
    for v in range(40):
        a = synth.generate_video(spec, v, int(counts[v]), *gen)
        b = synth.generate_video(control, v, int(counts[v]), *gen)
        np.testing.assert_array_equal(a["mesh"], b["mesh"])  # the mesh follows the true AUs in both
        np.testing.assert_array_equal(a["au_true"], b["au"])  # the control records the truth
        noisy.append(a["au"] - a["au"].mean(0))
        clean.append(a["au_true"] - a["au_true"].mean(0))
    r = np.corrcoef(np.concatenate(clean).T)
    for a, b, _ in synth.COACTIVATED_AUS:
        if (a, b) != ("AU25", "AU26"):
            assert r[AU_COLUMNS.index(a), AU_COLUMNS.index(b)] > 0.8, (a, b)
    assert np.std(np.concatenate(noisy) - np.concatenate(clean)) > 0.05


def test_bad_noise_settings_are_one_line_errors(tmp_path):
    with pytest.raises(ValueError, match="AU99"):
        au_noise.correlation_matrix([("AU01", "AU99", 0.5)])
    with pytest.raises(ValueError, match="no valid correlation matrix"):
        au_noise.correlation_matrix([("AU01", "AU02", 0.9), ("AU02", "AU04", 0.9), ("AU01", "AU04", -0.9)])
    with pytest.raises(ValueError, match="au_noise_ar"):
        synth.detector_readings(synth.SynthSpec(au_noise_sd=0.1, au_noise_ar=1.0), 0, np.zeros((5, 20)))
    with pytest.raises(ValueError, match="need 0-1"):
        synth.coactivate(np.zeros((3, 20)), (("AU09", "AU10", 0.8),), 1.5)
    synth.write_tables(tmp_path / "data", synth.SynthSpec(n_frames=40, n_videos=2), tmp_path / "truth.npz")
    with pytest.raises(ValueError, match="no au_sigma_u_within"):
        synth.write_truth_sigma_u(tmp_path / "truth.npz")


def test_aumesh_synth_writes_the_noisy_tables_and_sigma_u_beside_the_truth(tmp_path, capsys):
    from aumesh import cli

    argv = ["synth", "--out", str(tmp_path / "data"), "--frames", "300", "--videos", "10", "--seed", "2"]
    argv += ["--realistic", "--instrument-noise-sd", "0.05", "--truth", str(tmp_path / "truth.npz")]
    assert cli.main(argv) == 0
    capsys.readouterr()
    spec = synth.realistic_noise_spec(300, 10, 2, instrument_noise_sd=0.05)
    want = au_noise.au_error_covariance(spec, synth.frames_per_video(spec))
    np.testing.assert_allclose(load_sigma_u(tmp_path / "sigma_u.npy"), want)
    assert set(I2) <= set(pq.read_schema(tmp_path / "data" / "frames_0000.parquet").names)
    # without noise: no sigma_u.npy, and the tables of the plain spec
    assert cli.main(["synth", "--out", str(tmp_path / "plain"), "--frames", "300", "--videos", "10",
                     "--truth", str(tmp_path / "plain" / "truth.npz")]) == 0  # fmt: skip
    assert not (tmp_path / "plain" / "sigma_u.npy").exists()
