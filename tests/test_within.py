"""Identity-coupled AU baselines (aumesh synth): the pooled (card) estimator's AU fields are biased, the within
estimator recovers the truth, the default promotion criterion picks it; without coupling all targets agree."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from aumesh.data import tables
from aumesh.experiments import ranking
from aumesh.pipeline import evaluate as ev
from aumesh.pipeline import prepare
from aumesh.pipeline.evaluate.prepared_data import load_prepared
from aumesh.synthetic import tables as synth
from aumesh.synthetic import truth
from aumesh.synthetic.tables import SynthSpec
from conftest import RECOVERY_SPEC, default_config, shared_build

COUPLING = 0.15  # AU baseline per unit softplus of the identity's standardized resemblance to the AU field


@pytest.fixture(scope="session")
def coupled(tmp_path_factory, fixed_conf):
    """The recovery set with the default identity differences and AU baselines that follow each person's identity,
    generated and prepared once per test run (conftest.shared_build: the module's tests may run on two workers)."""

    def build(out):
        spec = dataclasses.replace(
            RECOVERY_SPEC, identity_scale=SynthSpec.identity_scale, identity_au_coupling=COUPLING
        )
        synth.write_tables(out / "data", spec, truth_path=out / "truth.npz")
        cfg = default_config()
        prepare.run(tables.discover(out / "data", cfg.data.tables, cfg.data.mesh_npy), cfg, out / "prepared")

    out = shared_build(tmp_path_factory, "within-coupled", build)
    return load_prepared(out / "prepared"), dict(np.load(out / "truth.npz"))


def _fit(prepared, target):
    cv, final = ev.cross_validate_and_fit(prepared, default_config(**{"preprocess.target": target}))
    return cv, final


def _cosines(prepared, final, true):
    return truth.au_field_cosines(final.coef, final.feature_columns, true, prepared.reference["reference_anchors"])


def test_synth_coupling_raises_each_videos_au_floor_and_records_it(coupled, recovery_tables):
    prepared, true = coupled
    baseline = true["au_baseline"]
    assert baseline.shape == (RECOVERY_SPEC.n_videos, 20) and (baseline > 0).all() and baseline.max() <= 0.9
    np.testing.assert_array_equal(true["au_fields"], true["coef"][:20])
    uncoupled = np.load(recovery_tables[0] / "truth.npz")
    assert not uncoupled["au_baseline"].any()
    # recorded AU = baseline + (1 - baseline) * true AU >= baseline, frame by frame
    video = np.array([int(v[3:]) for v in prepared.video_ids])[prepared.frames["video_index"].to_numpy()]
    assert (prepared.au >= baseline[video] - 1e-12).all() and (prepared.au <= 1.0).all()
    # baselines follow identity: the AU's baseline grows with the person's resemblance to the AU's field


@pytest.mark.slow
def test_pooled_au_fields_are_biased_on_coupled_data_and_within_recovers_them(coupled):
    prepared, true = coupled
    pooled = _cosines(prepared, _fit(prepared, "absolute")[1], true)
    within = _cosines(prepared, _fit(prepared, "within")[1], true)
    assert np.median(pooled) < 0.9 and pooled.min() < 0.6, pooled  # identity leaks into the card's AU fields
    assert np.median(within) > 0.97 and within.min() > 0.85, within
    assert (within > pooled - 0.01).all()


@pytest.mark.slow
def test_without_coupling_pooled_and_within_agree(recovery_prepared, recovery_tables):
    prepared = load_prepared(recovery_prepared / "prepared")
    true = dict(np.load(recovery_tables[0] / "truth.npz"))
    pooled = _cosines(prepared, _fit(prepared, "absolute")[1], true)
    within = _cosines(prepared, _fit(prepared, "within")[1], true)
    assert pooled.min() > 0.95 and within.min() > 0.95
    np.testing.assert_allclose(pooled, within, atol=0.03)


@pytest.mark.slow
def test_default_promotion_criterion_picks_within_on_coupled_data(coupled):
    prepared, _ = coupled
    candidates = []
    for target in ("absolute", "neutral", "within"):
        cv, _ = _fit(prepared, target)
        candidates.append(
            ranking.Candidate(
                run_id=target,
                run_name=target,
                status="FINISHED",
                params={"preprocess.target": target, "model.n_components": "83"},
                metrics=cv.scalar_metrics() | {"n_components": 83.0},
            )
        )
    choice = ranking.choose(candidates)
    assert choice.metric == "r2_displacement_mean" and choice.run_id == "within", choice.ranking
    assert ranking.choose(candidates, metric="au_reliability_median").run_id == "within"
