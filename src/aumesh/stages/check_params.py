"""The ``check_params`` stage: ``params.yaml`` sets no scheduler or tracking store other than ``conf/``'s.

``dvc exp run -S compute=distributed -S compute.address=tcp://host:8786`` recomposes ``params.yaml`` with the
address, but ``compute`` and ``tracking`` are not stage params (:data:`aumesh.config.WHERE_GROUPS`: where a run
executes is not what it computes), so DVC reruns nothing, computes nothing on the cluster, and records an
"experiment" whose only change is one machine's address in git. This stage, first in ``dvc.yaml`` and depending on
``params.yaml`` and ``conf/`` (so it reruns, in about a second, whenever either changes), refuses that in one line
before any other stage runs; the way to choose a cluster or a server is the environment (``AUMESH_COMPUTE_ADDRESS``,
``AUMESH_COMPUTE_<KEY>``, ``MLFLOW_TRACKING_URI``) or ``aumesh.local.yaml``, which win over ``params.yaml`` and
leave it, ``dvc.lock`` and the record unchanged.

Why a stage: DVC composes ``params.yaml`` itself (``dvc/utils/hydra.py``) and runs only stale stages; a stage whose
deps are the composed file is the one place that runs every time the composition changes, under ``dvc repro``,
``dvc exp run`` and queued experiments alike. Why refuse rather than warn: DVC shows a stage's output only when it
runs, and a warning from an experiment that succeeds still commits the address.

It is the one stage that composes ``conf/``: it computes nothing from it, it only checks that DVC's ``params.yaml``
(which every other stage reads, never re-composing) was composed from ``conf/`` for these two groups.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from aumesh.config import WHERE_GROUPS, compose, flatten
from aumesh.core.errors import ConfigError

#: what to use instead of a ``params.yaml`` value of each group
FIXES = {
    "compute": "AUMESH_COMPUTE_<KEY> in the environment (`AUMESH_COMPUTE_ADDRESS=tcp://host:8786 dvc exp run ...`)",
    "tracking": "MLFLOW_TRACKING_URI in the environment or aumesh.local.yaml",
}


def where_differences(params: Mapping[str, Any], conf: Mapping[str, Any]) -> dict[str, tuple[Any, Any]]:
    """The keys of :data:`aumesh.config.WHERE_GROUPS` whose value in ``params`` is not the one in ``conf``.

    Parameters
    ----------
    params : Mapping
        ``params.yaml`` as loaded (nested).
    conf : Mapping
        ``conf/`` composed without overrides (nested, :func:`aumesh.config.compose`).

    Returns
    -------
    dict
        ``{dotted key: (params.yaml's value, conf/'s value)}``, sorted by key; an absent key counts as ``None``.
    """
    mine = {k: v for k, v in flatten(params).items() if k.split(".", 1)[0] in WHERE_GROUPS}
    theirs = {k: v for k, v in flatten(conf).items() if k.split(".", 1)[0] in WHERE_GROUPS}
    return {k: (mine.get(k), theirs.get(k)) for k in sorted(set(mine) | set(theirs)) if mine.get(k) != theirs.get(k)}


def main(params_file: str | Path = "params.yaml", config_dir: str | Path = "conf") -> None:
    """Refuse (:class:`aumesh.core.errors.ConfigError`, exit 2) a ``params_file`` whose ``compute`` or ``tracking``
    values differ from ``config_dir``'s composition."""
    import yaml

    params = yaml.safe_load(Path(params_file).read_text()) or {}
    differ = where_differences(params, compose(config_dir=config_dir))
    if not differ:
        return
    listed = ", ".join(f"{k}={a} (conf/: {b})" for k, (a, b) in differ.items())
    groups = sorted({k.split(".", 1)[0] for k in differ})
    raise ConfigError(
        f"{params_file} sets {listed}: where a run executes and is logged is not a stage parameter, so DVC would rerun "
        f"nothing and record the setting in git. Fix: `aumesh compose-params` (params.yaml from conf/), then give it "
        f"as {'; '.join(FIXES[g] for g in groups)}."
    )
