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


def test_unknown_key_is_rejected_with_its_path():
    data = config.compose(config_dir=REPO / "conf")
    data["model"]["n_componets"] = 3
    with pytest.raises(ValueError, match=r"unknown config key\(s\) model.n_componets"):
        config.from_dict(data)


@pytest.mark.parametrize("override,message", [
    ("preprocess.target=relative", "preprocess.target='relative'"),
    ("features.pose=false", "interactions=true needs features.pose=true"),
    ("preprocess.alignment.outlier_quantile=0", "outlier_quantile=0"),
    ("cv.n_splits=1", "cv.n_splits=1"),
])
def test_bad_values_name_the_key(override, message):
    key, value = override.split("=")
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        default_config(**{key: value})


def test_load_params_reports_the_file(tmp_path):
    (tmp_path / "params.yaml").write_text("model: {n_components: 0}\n")
    with pytest.raises(ValueError, match=r"params.yaml: model.n_components=0"):
        config.load_params(tmp_path / "params.yaml")
    with pytest.raises(FileNotFoundError, match="make params"):
        config.load_params(tmp_path / "missing.yaml")
