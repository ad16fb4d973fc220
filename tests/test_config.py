"""conf/ composes to the committed params.yaml; bad keys and values fail with the key's name."""

from __future__ import annotations

import pytest
import yaml

from aumesh import config
from conftest import REPO, default_config


def test_committed_params_yaml_is_what_conf_composes_to():
    with open(REPO / "params.yaml") as fh:
        committed = yaml.safe_load(fh)
    assert committed == config.compose(config_dir=REPO / "conf"), "params.yaml is stale: run `make params`"


def test_unknown_key_is_rejected_with_its_path(fixed_conf):
    data = config.compose(config_dir=fixed_conf)
    data["model"]["n_componets"] = 3
    with pytest.raises(ValueError, match=r"unknown config key\(s\) model.n_componets"):
        config.from_dict(data)


@pytest.mark.parametrize(
    "override,message",
    [
        ("preprocess.target=relative", "preprocess.target='relative'"),
        ("features.name=au_pose_inter", "features='au_pose_inter': use one of au, au_pose, au_pose_interactions"),
        ("preprocess.alignment.outlier_quantile=0", "outlier_quantile=0"),
        ("cv.n_splits=1", "cv.n_splits=1"),
    ],
)
def test_bad_values_name_the_key(override, message):
    key, value = override.split("=")
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        default_config(**{key: value})


def test_load_params_reports_the_file(tmp_path):
    (tmp_path / "params.yaml").write_text("model: {n_components: 0}\n")
    with pytest.raises(ValueError, match=r"params.yaml: model.n_components=0"):
        config.load_params(tmp_path / "params.yaml")
    with pytest.raises(config.ConfigError, match="missing.yaml: no params file. Run `make params`"):
        config.load_params(tmp_path / "missing.yaml")


@pytest.mark.parametrize(
    "option,columns",
    [
        ("au", 20),
        ("au_pose", 23),
        ("au_pose_interactions", 83),
        ("blendshapes", 52),
        ("blendshapes_pose_interactions", 52 + 3 + 3 * 52),
        ("emotions_pose", 7 + 3),
    ],
)
def test_feature_sets_are_group_options(option, columns, fixed_conf):
    cfg = config.from_dict(config.compose([f"features={option}"], config_dir=fixed_conf))
    assert cfg.features.name == option and len(cfg.features.columns) == columns


def test_the_replaced_feature_switches_name_the_group(fixed_conf):
    # as a Hydra override (aumesh sweep, compose-params) ...
    with pytest.raises(ValueError, match=r"features=au, features=au_pose or features=au_pose_interactions"):
        config.compose(["features.pose=false"], config_dir=fixed_conf)
    # ... and in an old params.yaml, where the combination names its option
    data = config.compose(config_dir=fixed_conf)
    data["features"] = {"pose": True, "interactions": "false"}
    with pytest.raises(ValueError, match=r"is `features=au_pose`"):
        config.from_dict(data)


def test_each_family_takes_its_own_designs_or_none(fixed_conf):
    cfg = config.from_dict(
        config.compose(
            ["families.emotions.features=none", "families.blendshapes.n_components=5"], config_dir=fixed_conf
        )
    )
    assert dict(cfg.families.items())["emotions"].features == "none"
    assert dict(cfg.families.items())["blendshapes"].n_components == 5
    # another family's design is refused, naming the family's own options
    with pytest.raises(ValueError, match=r"families.emotions.features='blendshapes_pose'.*emotions_pose_interactions"):
        config.from_dict(config.compose(["families.emotions.features=blendshapes_pose"], config_dir=fixed_conf))
    with pytest.raises(ValueError, match=r"families.blendshapes.n_components=0"):
        config.from_dict(config.compose(["families.blendshapes.n_components=0"], config_dir=fixed_conf))
