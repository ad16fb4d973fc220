"""The AU identification screen and the detector-noise corrections in the evaluate pipeline, the card and its limits."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from aumesh.card import limits
from aumesh.card.identification import identification_section
from aumesh.card.model_card import model_card_markdown
from aumesh.core.errors import ConfigError
from aumesh.core.schema import AU_COLUMNS
from aumesh.model import eiv
from aumesh.pipeline import evaluate as ev
from aumesh.pipeline.evaluate.prepared_data import load_prepared
from aumesh.pipeline.evaluate.statistics_pass import accumulate
from conftest import default_config
from test_limits import _large_card


@pytest.fixture(scope="module")
def prepared(recovery_prepared):
    return load_prepared(recovery_prepared / "prepared")


def _run(prepared, **overrides):
    return ev.cross_validate_and_fit(prepared, default_config(**overrides))


@pytest.mark.slow
def test_without_a_correction_the_fit_is_todays_and_the_screen_flags_nothing_on_noise_free_data(prepared):
    cfg = default_config()
    cv, final = ev.cross_validate_and_fit(prepared, cfg)
    # today's fit: the PLS of the configuration's statistics, row for row
    stats = accumulate(prepared, cfg, ev.video_folds(prepared.videos.count, cfg.cv.n_splits))
    np.testing.assert_array_equal(final.coef, ev.fit(stats.total, ev.effective_n_components(cfg), True).coef_)
    assert final.uncorrected_coef is None and cv.eiv is None
    screen = cv.au_identification
    assert screen is final.identification and not screen.flagged.any(), screen.to_card()
    metrics = cv.metrics()
    assert metrics["n_aus_unidentified"] == 0 and set(metrics["au_identification"]) == set(AU_COLUMNS)
    logged = cv.scalar_metrics()
    assert logged["n_aus_unidentified"] == 0.0
    assert all(np.isfinite(v) for k, v in logged.items() if k.startswith("au_sigma_star_"))


def test_the_screens_moments_are_the_within_targets_au_block(prepared):
    cfg = default_config(**{"preprocess.target": "within", "features": "au"})
    stats = accumulate(prepared, cfg, ev.video_folds(prepared.videos.count, cfg.cv.n_splits))
    within = stats.total  # the within target's own statistics of the 20 AUs, fold by fold and added
    np.testing.assert_allclose(stats.au_within.cxx, within.cxx, rtol=1e-9, atol=1e-9 * np.abs(within.cxx).max())
    np.testing.assert_allclose(stats.au_within.cxy, within.cxy, rtol=1e-8, atol=1e-9 * np.abs(within.cxy).max())
    # and the screen on them is eiv.identification_screen's
    screen = ev.identification(cfg, stats)
    ref = eiv.identification_screen(within.cxx / within.n, within.cxy / within.n)
    np.testing.assert_allclose(screen.cosines, ref.cosines, atol=1e-9)


@pytest.mark.slow
def test_a_corrected_run_with_zero_noise_is_least_squares_and_writes_the_uncorrected_fit_beside_it(prepared, tmp_path):
    np.save(tmp_path / "zero.npy", np.zeros((20, 20)))
    base = {"preprocess.target": "within"}
    _, plain = _run(prepared, **base)
    cv, final = _run(prepared, **base, **{"model/eiv": "corrected", "model.eiv.sigma_u": str(tmp_path / "zero.npy")})
    # the card's fit (83 components on 83 features: least squares) is written beside, exactly as a plain run gives it
    np.testing.assert_array_equal(final.uncorrected_coef, plain.coef)
    # with no noise the corrected fit is least squares too (another algorithm: equal up to rounding)
    np.testing.assert_allclose(final.coef, plain.coef, rtol=1e-6, atol=1e-6 * np.abs(plain.coef).max())
    assert cv.eiv["method"] == "corrected" and cv.eiv["sigma_u_sha256"] and cv.metrics()["eiv"] == cv.eiv
    arrays = final.release_arrays(prepared.reference, metadata={})
    assert arrays["coef_uncorrected"].shape == (23, 1434) and arrays["coef_full_uncorrected"].shape == (83, 1434)
    assert arrays["au_identification_flagged"].shape == (20,)


@pytest.mark.slow
def test_a_corrected_run_corrects_the_au_fields_and_keeps_the_pose_rows_close(prepared, tmp_path):
    np.save(tmp_path / "s.npy", 0.03**2 * np.eye(20))
    cv, final = _run(
        prepared,
        **{"preprocess.target": "within", "model/eiv": "corrected", "model.eiv.sigma_u": str(tmp_path / "s.npy")},
    )
    au = slice(0, 20)
    # the AU fields grow (attenuation undone) and stay within the floor's bound of 1 / 0.3
    grow = np.linalg.norm(final.coef[:, au], axis=0) / np.linalg.norm(final.uncorrected_coef[:, au], axis=0)
    assert (grow > 1.0).all() and (grow < 1 / 0.3 + 1e-9).all(), grow
    assert np.isfinite(cv.metrics()["r2_mean"])


@pytest.mark.parametrize(
    "overrides,words",
    [
        (
            {"model/eiv": "corrected", "model.eiv.sigma_u": "''"},
            "needs the AU detector's within-video error covariance",
        ),
        ({"model/eiv": "corrected"}, "preprocess.target=within"),
        ({"model/eiv": "instruments", "model.eiv.instrument_aus": "AU_2", "preprocess.target": "within"}, "{au}"),
        ({"model.eiv.sigma_u": "x.npy"}, "is given but model.eiv.method='none': choose model/eiv=corrected"),
        ({"model.identification.sigma_step": "0.5"}, "need 0 < step <= max"),
    ],
)
def test_contradicting_or_missing_eiv_options_are_refused_naming_the_key(overrides, words):
    with pytest.raises(ConfigError, match="model") as err:
        default_config(**overrides)
    assert words in str(err.value)


def test_the_corrected_option_reads_the_validation_folders_covariance_by_default():
    cfg = default_config(**{"model/eiv": "corrected", "preprocess.target": "within"})
    assert cfg.model.eiv.sigma_u == f"{cfg.paths.validation_dir}/sigma_u.npy"
    moved = default_config(**{"model/eiv": "corrected", "preprocess.target": "within", "paths.validation_dir": "v2"})
    assert moved.model.eiv.sigma_u == "v2/sigma_u.npy"  # one source of truth for the folder


def test_a_params_file_edited_by_hand_with_another_methods_key_is_refused():
    from aumesh import config

    data = default_config().to_dict()
    data["model"]["eiv"]["sigma_u"] = "x.npy"
    with pytest.raises(ConfigError, match=r"model.eiv.sigma_u='x.npy' is given but model.eiv.method='none'"):
        config.from_dict(data)


def _screen_card(flag_aus=("AU10",)) -> dict:
    card = copy.deepcopy(_large_card())
    card["config"]["model"] = default_config().to_dict()["model"]
    card["au_identification"] = {
        au: {
            "sigma_star": 0.06 if au in flag_aus else None,
            "flagged": au in flag_aus,
            "partner": "AU09" if au == "AU10" else "AU12",
            "group": "AU09+AU10" if au == "AU10" else "+".join(sorted([au, "AU12"])),
            "group_sigma_star": None,
        }
        for au in AU_COLUMNS
    }
    return card


def test_a_flagged_au_is_a_limit_naming_its_partner_group_and_the_remedy():
    card = _screen_card()
    warnings = limits.release_warnings(card, au_field_iod={au: 0.05 for au in AU_COLUMNS})
    (w,) = [w for w in warnings if w["code"] == "unidentified_au_fields"]
    assert w["aus"] == ["AU10"] and w["partners"] == {"AU10": "AU09"} and w["groups"] == ["AU09+AU10"]
    assert "model/eiv=corrected" in w["message"] and "not a proof" in w["message"]
    text = model_card_markdown(card | {"warnings": warnings}, None, [])
    assert "unidentified" in text[text.index("## Limits") :].split("\n## ")[0]
    section = text[text.index("## AU identification under detector noise") :].split("\n## ")[0]
    assert "| AU10 | 0.060 | **yes** | AU09 | AU09+AU10 | > 0.2 |" in section
    assert "| AU01 | > 0.2 | no |" in section and "a screen, not a proof" in section


def test_no_flag_no_warning_and_old_cards_without_a_screen_have_no_section():
    assert not [w for w in limits.release_warnings(_screen_card(())) if w["code"] == "unidentified_au_fields"]
    assert identification_section(_large_card()) == []
    assert "No AU field flagged" in "\n".join(identification_section(_screen_card(())))


def test_the_covariance_is_checked_before_any_work_and_a_file_outside_the_validation_folder_is_said(
    tmp_path, monkeypatch, caplog
):
    from aumesh.pipeline.evaluate.eiv_fits import check_eiv_inputs

    monkeypatch.chdir(tmp_path)
    (tmp_path / "validation").mkdir()
    np.save(tmp_path / "validation" / "s.npy", 0.01 * np.eye(20))
    np.save(tmp_path / "elsewhere.npy", 0.01 * np.eye(20))
    np.save(tmp_path / "validation" / "bad.npy", np.eye(3))
    within = {"preprocess.target": "within", "model/eiv": "corrected"}
    with caplog.at_level("WARNING"):
        check_eiv_inputs(default_config(**within, **{"model.eiv.sigma_u": "validation/s.npy"}))
        assert "outside paths.validation_dir" not in caplog.text
        check_eiv_inputs(default_config(**within, **{"model.eiv.sigma_u": "elsewhere.npy"}))
        assert "elsewhere.npy is outside paths.validation_dir" in caplog.text
    with pytest.raises(ConfigError, match=r"validation/bad.npy: shape \(3, 3\)"):
        check_eiv_inputs(default_config(**within, **{"model.eiv.sigma_u": "validation/bad.npy"}))
    check_eiv_inputs(default_config())  # nothing to check without a correction


@pytest.mark.slow
def test_on_realistic_noisy_tables_the_screen_flags_the_reversed_field_and_the_correction_undoes_it(tmp_path):
    """Issue 43's "Done when" at the issue's size (30,000 frames, 800 videos, detector error sd 0.07, AR(1) in time,
    correlated across AU pairs; co-activated AUs), through prepare and evaluate, against the generator's truth.
    benchmarks/bench_au_identification.py runs the same on py-feat CSVs and prints every field."""
    import dataclasses

    from aumesh.data import tables
    from aumesh.pipeline import prepare
    from aumesh.synthetic import au_noise, truth
    from aumesh.synthetic import tables as synth

    noisy = synth.realistic_noise_spec()
    control = dataclasses.replace(noisy, au_noise_sd=0.0)
    sigma = au_noise.au_error_covariance(noisy, synth.frames_per_video(noisy))
    np.save(tmp_path / "sigma.npy", sigma)
    np.save(tmp_path / "sigma15.npy", 1.5 * sigma)
    within = {"preprocess.target": "within"}
    cosines, screens = {}, {}
    for name, spec in (("noisy", noisy), ("control", control)):
        synth.write_tables(tmp_path / name / "data", spec, truth_path=tmp_path / name / "truth.npz")
        cfg = default_config()
        found = tables.discover(tmp_path / name / "data", cfg.data.tables, cfg.data.mesh_npy)
        prepare.run(found, cfg, tmp_path / name / "prepared")
        prepared = load_prepared(tmp_path / name / "prepared")
        true = dict(np.load(tmp_path / name / "truth.npz"))
        runs = {"within": within}
        if name == "noisy":
            runs |= {
                "corrected": {**within, "model/eiv": "corrected", "model.eiv.sigma_u": str(tmp_path / "sigma.npy")},
                "corrected15": {**within, "model/eiv": "corrected", "model.eiv.sigma_u": str(tmp_path / "sigma15.npy")},
            }
        for run, overrides in runs.items():
            cv, final = _run(prepared, **overrides)
            key = f"{name} {run}"
            cosines[key] = truth.au_field_cosines(
                final.coef, final.feature_columns, true, prepared.reference["reference_anchors"]
            )
            screens[key] = cv.au_identification
    noisy_cos, screen = cosines["noisy within"], screens["noisy within"]
    assert (noisy_cos < 0).any(), noisy_cos  # the problem: a co-activated AU's field comes out reversed
    assert screen.flagged[noisy_cos < 0].all() and all(screen.partner[i] for i in np.flatnonzero(noisy_cos < 0))
    assert 1 <= screen.flagged.sum() <= 3, screen.flagged_names()
    assert not screens["control within"].flagged.any(), screens["control within"].flagged_names()
    assert np.median(cosines["noisy corrected"]) >= 0.95 and cosines["noisy corrected"].min() >= 0, cosines
    assert cosines["noisy corrected15"].min() >= 0, cosines["noisy corrected15"]


def test_predict_mesh_warns_once_when_a_flagged_au_is_driven_and_not_for_its_group_partner_alone():
    import warnings

    import aumesh
    from aumesh.model.input_checks import InputRangeWarning
    from aumesh.synthetic.truth import synthetic_release_arrays

    arrays = synthetic_release_arrays()
    flagged = np.isin(AU_COLUMNS, ["AU24"])
    arrays |= {
        "au_identification_sigma_star": np.where(flagged, 0.06, np.nan),
        "au_identification_flagged": flagged,
        "au_identification_partner": np.array(["AU26" if a == "AU24" else "AU12" for a in AU_COLUMNS]),
        "au_identification_flag_below": np.array(0.1),
    }
    with pytest.warns(InputRangeWarning, match=r"AU24 \(sigma\* 0.060; drive AU24\+AU26\) given, but not identified"):
        aumesh.predict_mesh(arrays, {"AU24": 0.5})
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputRangeWarning)
        aumesh.predict_mesh(arrays, {"AU26": 0.5, "AU12": 1.0})  # unflagged AUs: no word
        aumesh.predict_mesh({k: v for k, v in arrays.items() if not k.startswith("au_ident")}, {"AU24": 0.5})
