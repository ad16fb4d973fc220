"""model/eiv=instruments: a second detector's AUs on the same frames as instruments (within two-stage least squares).

The data path (ingest and prepare carry the instrument columns into frames.parquet; a missing column or a missing value
is a one-line error; without instruments nothing changes), the streamed statistics of the augmented design against an
explicit numpy computation on the demeaned rows, and recovery of a known truth where least squares is biased.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from aumesh.core.errors import TableError
from aumesh.core.schema import AU_COLUMNS, N_TARGETS, POSE_COLUMNS, feature_columns, instrument_columns
from aumesh.data import tables
from aumesh.model import eiv
from aumesh.model.features import design_matrix
from aumesh.model.pass_design import FULL_DESIGN, augmented_index
from aumesh.model.statistics import accumulate_design, fold_within_statistics
from aumesh.pipeline import compute, ingest, prepare
from aumesh.pipeline.evaluate import video_folds
from aumesh.pipeline.evaluate.eiv_fits import eiv_fits, first_stage, instrumental_fits
from aumesh.pipeline.evaluate.prepared_data import load_prepared
from aumesh.pipeline.evaluate.results import training_sets
from aumesh.pipeline.evaluate.statistics_pass import accumulate
from aumesh.synthetic.pyfeat import write_pyfeat_tables
from aumesh.synthetic.tables import SynthSpec, write_tables
from conftest import default_config

PATTERN = "{au}_2"
INSTRUMENTS = instrument_columns(PATTERN)
#: model/eiv=instruments needs the within target (aumesh.config.validate)
WITH_INSTRUMENTS = {
    "model/eiv": "instruments",
    "model.eiv.instrument_aus": f"'{PATTERN}'",
    "preprocess.target": "within",
}


def _cfg(data_dir: Path, **overrides):
    cfg = default_config(**overrides)
    return dataclasses.replace(cfg, paths=dataclasses.replace(cfg.paths, data_dir=str(data_dir)))


def _add_instruments(folder: Path, sd: float, seed: int = 0) -> None:
    """Every parquet table of ``folder`` gains ``AU01_2 .. AU28_2``: its AUs plus independent noise of sd ``sd`` (a
    second detector's reading of the same frames)."""
    rng = np.random.default_rng(seed)
    for path in sorted(folder.glob("*.parquet")):
        table = pq.read_table(path)
        for au, name in zip(AU_COLUMNS, INSTRUMENTS, strict=True):
            values = table.column(au).to_numpy(zero_copy_only=False).astype(np.float64)
            table = table.append_column(name, pa.array(values + sd * rng.standard_normal(len(values))))
        pq.write_table(table, path)


def _prepare(data_dir: Path, out: Path, **overrides) -> Path:
    cfg = _cfg(data_dir, **overrides)
    manifest = ingest.run(cfg, out / "ingested")
    found = tables.check_tables(
        manifest["tables"], cfg.data.mesh_npy, cfg.data.coerce_numeric, instrument_columns(cfg.model.eiv.instrument_aus)
    )
    prepare.run(found, cfg, out / "prepared", ingested=manifest["counts"])
    return out / "prepared"


@pytest.fixture(scope="module")
def instrumented(tmp_path_factory) -> tuple[Path, Path]:
    """A small columns-layout set (400 frames, 40 videos) with instrument columns, prepared with model/eiv=instruments:
    (data folder, prepared folder). Read-only."""
    root = tmp_path_factory.mktemp("instrumented")
    write_tables(root / "data", SynthSpec(n_frames=400, n_videos=40, seed=3))
    _add_instruments(root / "data", sd=0.05)
    return root / "data", _prepare(root / "data", root, **WITH_INSTRUMENTS)


def _within(rows: np.ndarray, video: np.ndarray) -> np.ndarray:
    """``rows`` minus each video's mean row."""
    out = rows.astype(np.float64).copy()
    for v in np.unique(video):
        at = video == v
        out[at] -= out[at].mean(axis=0)
    return out


# ------------------------------------------------------------------------------------------------------ data path
def test_prepare_carries_instrument_columns(instrumented):
    data_dir, prepared = instrumented
    frames = pd.read_parquet(prepared / "frames.parquet")
    assert list(INSTRUMENTS) == [c for c in frames.columns if c.endswith("_2")]
    source = pd.concat([pd.read_parquet(p) for p in sorted(data_dir.glob("*.parquet"))])
    merged = frames.merge(source, on=["video_id", "frame"], suffixes=("", "_src"))
    assert len(merged) == len(frames) > 0
    for name in INSTRUMENTS:  # the second detector's values of the same frames, as written
        np.testing.assert_array_equal(merged[name].to_numpy(), merged[f"{name}_src"].to_numpy())


def test_without_instruments_prepared_frames_unchanged(small_tables, tmp_path):
    """Tables with instrument columns but model/eiv=none: the same frames.parquet, bit for bit, as without the columns,
    and no column beyond today's."""
    plain = _prepare(small_tables, tmp_path / "plain")
    extra = tmp_path / "extra-data"
    extra.mkdir()
    for path in small_tables.glob("*"):
        (extra / path.name).write_bytes(path.read_bytes())
    _add_instruments(extra, sd=0.05)
    ignored = _prepare(extra, tmp_path / "extra")
    assert (plain / "frames.parquet").read_bytes() == (ignored / "frames.parquet").read_bytes()
    names = pq.read_schema(plain / "frames.parquet").names
    assert not any(n.endswith("_2") for n in names)
    assert set(names) == {"video_id", "frame", *AU_COLUMNS, *POSE_COLUMNS, "video_index", "low_au"}


def test_missing_instrument_column_is_one_line_error(small_tables):
    cfg = _cfg(small_tables, **WITH_INSTRUMENTS)
    with pytest.raises(TableError) as err:
        ingest.find_sources(small_tables, cfg.data.tables, cfg.data.mesh_npy, INSTRUMENTS)
    message = str(err.value)
    assert "\n" not in message
    assert str(sorted(small_tables.glob("*.parquet"))[0]) in message
    assert "'AU01_2'" in message and "Fix:" in message and "model.eiv.instrument_aus" in message
    # prepare's check of the tables the ingest lists says the same
    with pytest.raises(TableError, match=r"column 'AU01_2' is missing.*Fix:"):
        tables.check_tables(sorted(small_tables.glob("*.parquet")), cfg.data.mesh_npy, False, INSTRUMENTS)


def test_missing_instrument_value_is_one_line_error(small_tables):
    """A frame the second detector has no value for is refused (not dropped), naming the file, column and row."""
    _add_instruments(small_tables, sd=0.05)
    path = sorted(small_tables.glob("*.parquet"))[0]
    table = pq.read_table(path)
    values = table.column("AU12_2").to_numpy().copy()
    values[7] = np.nan
    pq.write_table(table.set_column(table.schema.get_field_index("AU12_2"), "AU12_2", pa.array(values)), path)
    [found] = tables.check_tables([path], "{stem}.npy", False, INSTRUMENTS)
    with pytest.raises(TableError) as err:
        tables.read_pieces_metadata(tables.pieces(found), instruments=INSTRUMENTS)
    message = str(err.value)
    assert "\n" not in message
    assert str(path) in message and "'AU12_2'" in message and "row 7 " in message and "Fix:" in message
    # the other instrument columns and the same rows read as they are without model/eiv=instruments
    assert len(tables.read_pieces_metadata(tables.pieces(found))) == found.n_rows


@pytest.mark.slow
@pytest.mark.parametrize(("detector", "fmt"), [("mp", "csv"), ("v2", "csv"), ("mp", "parquet"), ("mp", "split")])
def test_ingest_carries_instruments_from_pyfeat_tables(tmp_path, detector, fmt):
    """py-feat's tables of either detector (CSV, parquet, the split layout): the ingested tables carry the instrument
    columns of the kept face rows, as written; without model/eiv=instruments they have no such column."""
    spec = SynthSpec(n_frames=60, n_videos=3, seed=5)
    write_pyfeat_tables(tmp_path / "data", spec, detector=detector, fmt=fmt)
    if fmt == "csv":
        rng = np.random.default_rng(1)
        [csv] = sorted((tmp_path / "data").glob("*.csv"))
        df = pd.read_csv(csv)
        second = df[list(AU_COLUMNS)].to_numpy() + 0.05 * rng.standard_normal((len(df), len(AU_COLUMNS)))
        df = pd.concat([df, pd.DataFrame(second, columns=list(INSTRUMENTS))], axis=1)
        df.to_csv(csv, index=False)
    else:
        _add_instruments(tmp_path / "data", sd=0.05, seed=1)
        df = pd.concat([pd.read_parquet(p) for p in sorted((tmp_path / "data").glob("*.parquet"))])
    cfg = _cfg(tmp_path / "data", **WITH_INSTRUMENTS)
    manifest = ingest.run(cfg, tmp_path / "ingested")
    out = pd.concat([pd.read_parquet(t) for t in manifest["tables"]])
    assert len(out) == manifest["counts"]["frames_out"] > 0
    assert set(INSTRUMENTS) <= set(out.columns)
    # each kept row's instruments are its source row's (matched on its AUs: distinct per face row)
    source = df.dropna(subset=[AU_COLUMNS[0]]).set_index([*AU_COLUMNS])
    kept = out.set_index([*AU_COLUMNS])
    np.testing.assert_allclose(kept[list(INSTRUMENTS)].to_numpy(), source.loc[kept.index, list(INSTRUMENTS)].to_numpy())
    if any(
        e["read"].startswith("cleaned") for e in manifest["sources"]
    ):  # written by the ingest: AUs, pose, then these
        written = pq.read_schema(manifest["tables"][-1]).names
        assert written[: 2 + 20 + 3 + 20] == ["video_id", "frame", *AU_COLUMNS, *POSE_COLUMNS, *INSTRUMENTS]
    ingest.run(_cfg(tmp_path / "data"), tmp_path / "ingested-plain")  # model/eiv=none: the tables it writes have none
    for table in (tmp_path / "ingested-plain" / ingest.TABLES_DIR).glob("*.parquet"):
        assert not set(INSTRUMENTS) & set(pq.read_schema(table).names)


# ------------------------------------------------------------------------------------------------- the statistics
def test_streamed_2sls_equals_numpy_on_demeaned_rows(instrumented):
    """Each fold's 2SLS coefficients from pass A's streamed statistics (training = total - fold) equal
    ``solve(Z'X, Z'Y)`` on the training rows demeaned per video, computed from the prepared files directly."""
    data_dir, prepared_dir = instrumented
    cfg = _cfg(data_dir, **WITH_INSTRUMENTS)
    prepared = load_prepared(prepared_dir)
    with compute.engine(cfg.compute):
        fold = video_folds(prepared.videos.count, cfg.cv.n_splits)
        stats = accumulate(prepared, cfg, fold)
    assert stats.instruments is not None and len(stats.instruments) == cfg.cv.n_splits
    fits = instrumental_fits(cfg, stats)
    assert eiv_fits(cfg, stats).final.method == "instruments"

    frames = pd.read_parquet(prepared_dir / "frames.parquet")
    video = frames["video_index"].to_numpy()
    columns = cfg.features.columns
    idx = [FULL_DESIGN.index(c) for c in columns]
    pose = frames[list(POSE_COLUMNS)].to_numpy()
    X = design_matrix(frames[list(AU_COLUMNS)].to_numpy(), pose, True, True)[:, idx]
    Z = design_matrix(frames[list(INSTRUMENTS)].to_numpy(), pose, True, True)[:, idx]
    Y = np.load(prepared_dir / "meshes.npy").astype(np.float64)
    frame_fold = fold[video]
    for f in range(cfg.cv.n_splits):
        train = frame_fold != f
        Xw, Zw, Yw = (_within(a[train], video[train]) for a in (X, Z, Y))
        expected = np.linalg.solve(Zw.T @ Xw, Zw.T @ Yw)  # (p, 1434)
        got = fits.folds[f].coef_.T
        scale = np.abs(expected).max()
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-7 * scale)
        # and the uncorrected fit beside it is least squares on the same rows
        ols = np.linalg.lstsq(Xw, Yw, rcond=None)[0]
        np.testing.assert_allclose(fits.folds[f].uncorrected_coef_.T, ols, rtol=0, atol=1e-7 * np.abs(ols).max())
    # the final model: every frame
    Xw, Zw, Yw = (_within(a, video) for a in (X, Z, Y))
    expected = np.linalg.solve(Zw.T @ Xw, Zw.T @ Yw)
    np.testing.assert_allclose(fits.final.coef_.T, expected, rtol=0, atol=1e-7 * np.abs(expected).max())
    # first stage over every frame: partial R² of each AU on the instruments (numpy's own regression)
    strength = first_stage(cfg, stats)
    fitted = Zw @ np.linalg.lstsq(Zw, Xw, rcond=None)[0]
    for k, au in enumerate(AU_COLUMNS):
        r2 = (fitted[:, k] ** 2).sum() / (Xw[:, k] ** 2).sum()
        assert strength[au]["r2"] == pytest.approx(r2, rel=1e-6)


def _truth_problem(seed: int = 0, n_videos: int = 150, per_video: int = 30, noise: float = 0.07):
    """Frames with known fields ``B`` (83, 1434): true AUs with co-activated pairs, observed AUs = truth + classical
    noise, a second detector's AUs = truth + independent noise; per-video offsets in AUs and mesh (identity)."""
    rng = np.random.default_rng(seed)
    n = n_videos * per_video
    video = np.repeat(np.arange(n_videos), per_video)
    base = rng.gamma(1.0, 0.15, (n, 20))
    true = base.copy()
    for k, j in ((9, 8), (1, 0), (5, 15)):  # co-activated pairs (AU12 with AU11, AU02 with AU01, AU07 with AU24)
        true[:, j] = 0.8 * base[:, k] + 0.5 * base[:, j]
    true += rng.uniform(0, 0.2, (n_videos, 20))[video]  # each subject's baseline
    pose = rng.normal(0, 0.15, (n, 3))
    B = rng.normal(0, 1, (83, N_TARGETS)) * np.r_[np.ones(20), 0.3 * np.ones(3), 0.1 * np.ones(60)][:, None]
    B[8] = -3.0 * B[9] + 0.5 * B[8]  # AU11's field small beside its co-activated partner's, and opposed
    Y = design_matrix(true, pose, True, True) @ B + rng.normal(0, 1, (n_videos, N_TARGETS))[video]
    Y += 0.02 * rng.standard_normal(Y.shape)
    observed = true + noise * rng.standard_normal(true.shape)
    second = true + noise * rng.standard_normal(true.shape)
    return observed, second, pose, video, Y, B


def _cosines(coef: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Per AU, the cosine of a fitted field (coef_ (1434, p), AU columns first) to the truth's."""
    fitted = coef[:, :20].T
    return np.einsum("kj,kj->k", fitted, B[:20]) / (np.linalg.norm(fitted, axis=1) * np.linalg.norm(B[:20], axis=1))


def test_2sls_recovers_truth_where_least_squares_is_biased():
    observed, second, pose, video, Y, B = _truth_problem()
    n_splits = 3
    fold = video % n_splits
    design = accumulate_design(
        observed,
        pose,
        video,
        int(video.max()) + 1,
        fold,
        n_splits,
        [(np.arange(len(Y)), Y.copy())],
        second,
        INSTRUMENTS,
    )
    columns = feature_columns(True, True)
    per_fold = [fold_within_statistics(design, f, augmented_index(columns)) for f in range(n_splits)]
    final = eiv.instrumental_fit(training_sets(per_fold)[n_splits], len(columns))
    iv, ols = _cosines(final.coef_, B), _cosines(final.uncorrected_coef_, B)
    assert iv.min() > 0.95, iv
    assert ols.min() < 0.5, ols  # the same moments by least squares: the small field of a pair turned by the noise
    assert iv[np.argmin(ols)] > 0.95


def test_evaluate_fits_the_instrumented_models(instrumented):
    """cross_validate_and_fit with model/eiv=instruments: the released coefficients are the final 2SLS fit, the least-
    squares fit of the same rows beside them, the cross-validation scores the folds' 2SLS fits, and the run's record
    names the instruments and their first-stage strength."""
    from aumesh.pipeline import evaluate as ev

    data_dir, prepared_dir = instrumented
    cfg = _cfg(data_dir, **WITH_INSTRUMENTS)
    prepared = load_prepared(prepared_dir)
    with compute.engine(cfg.compute):
        stats = accumulate(prepared, cfg, video_folds(prepared.videos.count, cfg.cv.n_splits))
    fits = instrumental_fits(cfg, stats)
    cv, final = ev.cross_validate_and_fit(prepared, cfg)
    np.testing.assert_array_equal(final.coef, fits.final.coef_)
    assert final.uncorrected_coef is not None and not np.array_equal(final.uncorrected_coef, final.coef)
    assert cv.eiv is not None and cv.eiv["method"] == "instruments" and cv.eiv["instrument_aus"] == PATTERN
    assert set(cv.eiv["first_stage"]) == set(AU_COLUMNS)
    assert all(0.0 < s["r2"] <= 1.0 and s["f"] > 10 for s in cv.eiv["first_stage"].values())


@pytest.mark.slow
def test_stages_run_with_instruments(tmp_path, monkeypatch):
    """ingest, prepare and evaluate by ``aumesh`` on tables with a second detector's AUs, model/eiv=instruments."""
    from aumesh import cli
    from aumesh.config import write_params
    from conftest import new_store

    write_tables(tmp_path / "data", SynthSpec(n_frames=400, n_videos=40, seed=4))
    _add_instruments(tmp_path / "data", sd=0.05)
    write_params(_cfg(tmp_path / "data", **WITH_INSTRUMENTS).to_dict(), tmp_path / "params.yaml")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{new_store(tmp_path / 'mlflow.db')}")
    for stage in ("ingest", "prepare", "evaluate"):
        assert cli.main([stage]) == 0
    import json

    cfg = _cfg(tmp_path / "data", **WITH_INSTRUMENTS)
    assert set(INSTRUMENTS) <= set(pq.read_schema(Path(cfg.paths.prepared_dir) / "frames.parquet").names)
    model = np.load(Path(cfg.paths.model_dir) / "model.npz")
    assert model["coef"].shape == model["coef_uncorrected"].shape and not np.array_equal(
        model["coef"], model["coef_uncorrected"]
    )
    metrics = json.loads(Path(cfg.paths.metrics_file).read_text())
    assert metrics["eiv"]["method"] == "instruments" and set(metrics["eiv"]["first_stage"]) == set(AU_COLUMNS)


def test_evaluating_instruments_on_data_prepared_without_them_is_one_line_naming_the_fix(recovery_prepared):
    from aumesh.core.errors import ConfigError
    from aumesh.pipeline import evaluate as ev

    prepared = load_prepared(recovery_prepared / "prepared")  # prepared with model/eiv=none: no AU*_2 columns
    with pytest.raises(ConfigError, match=r"frames.parquet: no column AU01_2, AU02_2, AU04_2 \.\.\. for model/eiv"):
        ev.cross_validate_and_fit(prepared, default_config(**WITH_INSTRUMENTS))
