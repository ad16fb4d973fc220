"""The configuration promotion writes: ``conf/experiment/promoted.yaml``, checked to compose to the winning run's.

``aumesh promote`` writes the winner's configuration to ``conf/experiment/promoted.yaml`` (``# @package _global_``;
loaded by the ``optional experiment: promoted`` entry of ``conf/config.yaml``'s defaults list, after the groups so it
overrides them): the model-defining keys (:data:`MODEL_KEYS`) always, plus any other key whose value in the run
differs from ``conf/`` without the experiment. Before anything is written, a temporary copy of ``conf/`` with the new
file is composed and every run parameter (except :data:`NOT_PROMOTED`: where a run lived, was logged and computed is
not what it is) must compose to the run's value (:func:`verify_composition`). Run params are compared as MLflow stores
them (:func:`aumesh.tracking.values.prepare_params`).
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from aumesh.config import WHERE_GROUPS
from aumesh.config import flatten as flatten_config

EXPERIMENT_GROUP = "experiment"
EXPERIMENT_NAME = "promoted"
DEFAULTS_ENTRY = f"optional {EXPERIMENT_GROUP}: {EXPERIMENT_NAME}"
# always written to the experiment file: what a sweep typically varies and what defines the model
MODEL_KEYS = (
    "preprocess.target",
    "preprocess.neutral.method",
    "features.name",
    "model.n_components",
    "model.scale",
    "model.clip_n_components",
)
# never promoted: where things live, how runs are logged and where they compute, not what the model is (a sweep on
# a cluster must not write compute.address into conf/ and params.yaml); nor, by the AU promotion, the families' models
# (`families.`): each family is promoted on its own (`aumesh promote --family`), into the `families` node
NOT_PROMOTED = ("paths.", *(f"{group}." for group in WHERE_GROUPS), "data.chunk_rows", "families.")
FAMILIES_NODE = "families"
# a run's keys its family's promotion writes (as families.<family>.features / .n_components), not the shared ones
FAMILY_OWN_KEYS = ("features.name", "model.n_components", "model.clip_n_components")
_HEADER = (
    "# @package _global_",
    "# Written by `aumesh promote`: the promoted sweep run's configuration. conf/config.yaml's",
    f"# defaults list loads it (`{DEFAULTS_ENTRY}`) after the groups, so these values win.",
)


def _param_string(value: Any) -> str:
    """A value as MLflow stores it in params (``aumesh.tracking.values.prepare_params``)."""
    from aumesh.tracking.values import prepare_params

    return prepare_params({"v": value})["v"]


def _typed(text: str, like: Any) -> Any:
    """Parse a logged param string back to the type of the composed value *like*."""
    if isinstance(like, bool):
        if text.lower() not in ("true", "false"):
            raise ValueError(f"not a boolean: {text!r}")
        return text.lower() == "true"
    if isinstance(like, int):
        return int(text)
    if isinstance(like, float):
        return float(text)
    if isinstance(like, (list, tuple)):
        return json.loads(text)
    if like is None:
        return None if text == "None" else yaml.safe_load(text)
    return text


def _promotable(key: str) -> bool:
    return not any(key == p or key.startswith(p) for p in NOT_PROMOTED)


def promoted_values(run_params: Mapping[str, str], base: Mapping[str, Any]) -> dict[str, Any]:
    """The keys and typed values the experiment file must set to reproduce a run.

    Parameters
    ----------
    run_params : Mapping
        The run's flattened params (strings, as logged).
    base : Mapping
        ``conf/`` composed without the promoted experiment (nested, as :func:`aumesh.config.compose`).

    Returns
    -------
    dict
        ``{dotted key: value}``: :data:`MODEL_KEYS`, plus every other promotable key whose run
        value differs from *base*.

    Raises
    ------
    ValueError
        The run used other data (``paths.data_dir``), or has keys ``conf/`` no longer has.
    """
    flat = flatten_config(base)
    if "paths.data_dir" in run_params and run_params["paths.data_dir"] != _param_string(flat.get("paths.data_dir")):
        raise ValueError(
            f"the run used paths.data_dir={run_params['paths.data_dir']} but conf/ has {flat.get('paths.data_dir')}: "
            "promoting it would not rebuild that model from the workspace's data. Fix: promote a sweep run on the "
            "workspace's data."
        )
    unknown = sorted(k for k in run_params if _promotable(k) and k not in flat)
    if unknown:
        raise ValueError(
            f"run params {', '.join(unknown)} are not keys of conf/ (configuration changed since the "
            "sweep?); re-run the sweep with the current conf/."
        )
    values: dict[str, Any] = {}
    for key, text in sorted(run_params.items()):
        if not _promotable(key):
            continue
        if key in MODEL_KEYS or text != _param_string(flat[key]):
            values[key] = _typed(text, flat[key])
    return values


def hydra_override(key: str, value: Any) -> str:
    """``key=value`` in Hydra's override syntax (booleans lower case, lists as JSON)."""
    if isinstance(value, bool):
        return f"{key}={str(value).lower()}"
    if isinstance(value, (list, tuple)):
        return f"{key}={json.dumps(list(value))}"
    return f"{key}={value}"


def experiment_yaml(
    values: Mapping[str, Any],
    provenance_lines: Sequence[str] = (),
    families: Mapping[str, Any] | None = None,
    family_lines: Mapping[str, str] | None = None,
) -> str:
    """Text of ``conf/experiment/promoted.yaml`` for dotted *values* (the AU promotion's), then the promoted families
    (*families*: ``{family: {"features": ..., "n_components": ...}}``, written under ``families:``; *family_lines*:
    one provenance comment per family). Without families the text is the AU promotion's alone."""
    nested: dict[str, Any] = {}
    for key, value in values.items():
        node = nested
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = list(value) if isinstance(value, tuple) else value
    if families:
        nested[FAMILIES_NODE] = {name: dict(spec) for name, spec in families.items()}
    header = [
        *_HEADER,
        *[f"# {line}" for line in provenance_lines],
        *[
            f"# {FAMILIES_NODE}.{name}: {line}"
            for name, line in (family_lines or {}).items()
            if name in (families or {})
        ],
    ]
    return "\n".join(header) + "\n" + yaml.safe_dump(nested, sort_keys=False)


def read_experiment(path: Path) -> tuple[dict[str, Any], list[str], dict[str, Any], dict[str, str]]:
    """The parts of an existing ``conf/experiment/promoted.yaml`` (:func:`experiment_yaml`'s inverse), so a promotion
    of one part (the AU model, or one family) rewrites it with the others as they were.

    Returns
    -------
    (dict, list of str, dict, dict)
        The AU promotion's values as dotted keys and its provenance lines; the ``families`` node and each family's
        provenance line. All empty when the file does not exist.

    Raises
    ------
    ValueError
        The file is not a YAML mapping (the fix is in the message).
    """
    path = Path(path)
    if not path.exists():
        return {}, [], {}, {}
    text = path.read_text()
    try:
        doc = yaml.safe_load(text) or {}
    except yaml.YAMLError as err:
        doc = err
    if not isinstance(doc, dict):
        raise ValueError(
            f"{path}: not a YAML mapping ({doc}). Fix: `git checkout {path.name}` or delete it, then promote again."
        )
    families = dict(doc.pop(FAMILIES_NODE, None) or {})
    au_lines: list[str] = []
    family_lines: dict[str, str] = {}
    for line in text.splitlines():
        if not line.startswith("#"):
            break
        if line in _HEADER:
            continue
        body = line[2:] if line.startswith("# ") else line[1:]
        name, sep, rest = body.partition(": ")
        if sep and name.startswith(f"{FAMILIES_NODE}.") and name.count(".") == 1:
            family_lines[name.split(".", 1)[1]] = rest
        else:
            au_lines.append(body)
    values = flatten_config(doc) if doc else {}
    return values, au_lines, families, family_lines


def check_defaults_entry(conf_dir: Path) -> None:
    """Make sure ``conf/config.yaml`` loads the promoted experiment after the config groups.

    Raises
    ------
    ValueError
        The entry is missing or comes before a group it must override (the fix is in the message).
    """
    path = Path(conf_dir) / "config.yaml"
    doc = yaml.safe_load(path.read_text()) or {}
    defaults = doc.get("defaults") or []
    names = [next(iter(d.items())) if isinstance(d, dict) else (d, None) for d in defaults]
    keys = [k for k, _ in names]
    entry = f"optional {EXPERIMENT_GROUP}"
    if (entry, EXPERIMENT_NAME) not in names:
        raise ValueError(
            f"{path}: the defaults list has no `- {DEFAULTS_ENTRY}`. Fix: add it after the config "
            "groups (before `_self_`) so `aumesh promote`'s conf/experiment/promoted.yaml is loaded."
        )
    pos = keys.index(entry)
    late = [k for k in ("paths", "data", "preprocess", "features", "model", "cv", "tracking") if k in keys[pos:]]
    if late:
        raise ValueError(f"{path}: `- {DEFAULTS_ENTRY}` must come after the groups it overrides ({', '.join(late)}).")


def compose_with(conf_dir: Path, experiment_text: str | None, overrides: Sequence[str] = ()) -> dict:
    """Compose a temporary copy of *conf_dir* whose promoted experiment is *experiment_text* (None: absent)."""
    from aumesh.config import compose

    with tempfile.TemporaryDirectory(prefix="aumesh-promote-") as tmp:
        copy = Path(tmp) / "conf"
        shutil.copytree(conf_dir, copy)
        exp = copy / EXPERIMENT_GROUP / f"{EXPERIMENT_NAME}.yaml"
        if exp.exists():
            exp.unlink()
        if experiment_text is not None:
            exp.parent.mkdir(parents=True, exist_ok=True)
            exp.write_text(experiment_text)
        return compose(list(overrides), config_dir=copy)


def verify_composition(composed: Mapping[str, Any], run_params: Mapping[str, str]) -> None:
    """Every promotable run param must compose to the run's value.

    Raises
    ------
    ValueError
        Naming every key whose composed value differs.
    """
    flat = {k: _param_string(v) for k, v in flatten_config(composed).items()}
    wrong = [
        f"{k}: run {v!r}, composed {flat.get(k)!r}"
        for k, v in sorted(run_params.items())
        if _promotable(k) and flat.get(k) != v
    ]
    if wrong:
        raise ValueError("the promoted conf/ does not compose to the run's configuration: " + "; ".join(wrong))
