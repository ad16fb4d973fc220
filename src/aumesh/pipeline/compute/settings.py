"""Where the passes run, as a run reads it: the ``compute`` group with the environment's settings over it.

Where a run executes is not what it computes: the environment's ``AUMESH_COMPUTE_<KEY>`` (``AUMESH_COMPUTE_ADDRESS=
tcp://host:8786`` alone selects the cluster) overrides the ``compute`` group of ``params.yaml`` (:func:`effective`), so
``dvc repro -f`` runs on a cluster without a change to a tracked file. Messages name a key where it was set
(:func:`source_of`, :func:`local_fix`). The engine that runs the passes on it is :mod:`aumesh.pipeline.compute`.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping

from aumesh.config import ComputeConfig
from aumesh.core.errors import ConfigError

#: The environment variables that override the ``compute`` group: ``AUMESH_COMPUTE_<KEY>`` (e.g.
#: ``AUMESH_COMPUTE_ADDRESS``, ``AUMESH_COMPUTE_CONNECT_TIMEOUT``, ``AUMESH_COMPUTE_SCHEDULER``).
ENV_PREFIX = "AUMESH_COMPUTE_"


def _from_environment(environ: Mapping[str, str] | None = None) -> dict[str, str]:
    env = os.environ if environ is None else environ
    given = {}
    for f in dataclasses.fields(ComputeConfig):
        value = env.get(ENV_PREFIX + f.name.upper(), "").strip()
        if value:
            given[f.name] = value
    return given


def effective(cfg: ComputeConfig, environ: Mapping[str, str] | None = None) -> ComputeConfig:
    """``cfg`` with the environment's ``AUMESH_COMPUTE_<KEY>`` over it (the environment wins); an address alone means
    ``scheduler=distributed``.

    Where a computation runs is not what it computes (the scheduler changes no result beyond float64 summation
    order), so a cluster's address belongs to the shell, not to ``params.yaml``: ``AUMESH_COMPUTE_ADDRESS=tcp://h:8786
    dvc repro -f`` leaves every tracked file as it is, and the address never reaches a record (the MLflow run's
    parameters, the model card), which hold the configuration read from ``params.yaml``.

    Raises
    ------
    ConfigError
        A value of the wrong type or outside what the key allows, named by its variable.
    """
    given = _from_environment(environ)
    if not given:
        return cfg
    if "address" in given and "scheduler" not in given:
        given["scheduler"] = "distributed"
    from aumesh import config

    try:
        return config.from_dict({"compute": {**dataclasses.asdict(cfg), **given}}).compute
    except ConfigError as err:
        names = ", ".join(f"{ENV_PREFIX}{k.upper()}={v}" for k, v in given.items())
        raise ConfigError(f"{names} (environment): {err}") from None


def source_of(key: str, environ: Mapping[str, str] | None = None) -> str:
    """Where the ``compute`` key ``key`` is set, for messages: its environment variable if set, else ``compute.<key>``."""
    name = ENV_PREFIX + key.upper()
    env = os.environ if environ is None else environ
    return name if env.get(name, "").strip() else f"compute.{key}"


def local_fix() -> str:
    """How to run without the cluster, in the words of where it was chosen."""
    key = source_of("address")
    return f"unset {key} to run here" if key.startswith(ENV_PREFIX) else "compute=local runs here"
