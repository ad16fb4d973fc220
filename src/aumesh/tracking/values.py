"""Params cleaning: nested params flattened, and every key and value made one MLflow accepts.

MLflow refuses a param value over 6000 characters, a key with other characters than ``[/\\w.\\- :]`` and batches over
its limits (``mlflow/utils/validation.py`` in 3.17); a sweep's or a stage's config is nested and holds lists. Here
params are flattened (``a.b.c``), lists and mappings become JSON, long values are cut with a visible mark, and metric
values are numbers or a :class:`TypeError`. The run handle (:mod:`aumesh.tracking.handle`), the registry and
``aumesh promote`` (which compares a run's logged params with ``conf/``) all clean values this one way.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from aumesh.core import provenance

# MLflow limits (mlflow/utils/validation.py in 3.17).
MAX_PARAM_VALUE_LENGTH = 6000
MAX_TAG_VALUE_LENGTH = 8000
MAX_KEY_LENGTH = 250
MAX_BATCH = 100  # params/tags per log_batch call
MAX_METRICS_BATCH = 1000
MAX_DATASET_DIGEST_LENGTH = 36
MAX_INPUT_TAG_VALUE_LENGTH = 500
TRUNCATION_MARK = "...[truncated]"


def _truncate(value: str, limit: int) -> str:
    if len(value) <= limit:
        return value
    return value[: limit - len(TRUNCATION_MARK)] + TRUNCATION_MARK


def _clean_key(key: str) -> str:
    """Make *key* a valid MLflow param/metric name (``[/\\w.\\- :]``, <= 250 chars)."""
    out = "".join(c if (c.isalnum() or c in "_-. /:") else "_" for c in str(key))
    return out[:MAX_KEY_LENGTH] or "_"


def _str_value(value: Any, limit: int) -> str:
    if isinstance(value, (dict, list, tuple)):
        value = json.dumps(value, default=str)
    return _truncate(str(value), limit)


def prepare_params(params: Mapping[str, Any]) -> dict[str, str]:
    """Flatten *params* and make every key/value MLflow-safe.

    Parameters
    ----------
    params : Mapping
        Nested config.

    Returns
    -------
    dict
        ``{dotted.key: str}`` with values truncated to 6000 characters (ending in
        ``"...[truncated]"``) and invalid key characters replaced by ``_``.
    """
    return {_clean_key(k): _str_value(v, MAX_PARAM_VALUE_LENGTH) for k, v in provenance.flatten(params).items()}


def run_family(params: Mapping[str, Any], tags: Mapping[str, Any] | None = None) -> str | None:
    """The input family of a model run: its ``aumesh.family`` tag, else the family of its ``features.name``
    (:data:`aumesh.core.families.FEATURE_SETS`: runs logged before the tag existed).

    Parameters
    ----------
    params : Mapping
        The run's params, nested (a composed config) or flattened as logged (``features.name``).
    tags : Mapping, optional
        The run's tags.

    Returns
    -------
    str or None
        ``"au"``, ``"blendshapes"`` or ``"emotions"``; None when neither the tag nor a known ``features.name`` says.
    """
    from aumesh.core.families import FEATURE_SETS
    from aumesh.tracking.mlflow_store import FAMILY_TAG

    tagged = (tags or {}).get(FAMILY_TAG)
    if tagged:
        return str(tagged)
    name = params.get("features.name")
    if name is None and isinstance(params.get("features"), Mapping):
        name = params["features"].get("name")
    spec = FEATURE_SETS.get(str(name)) if name is not None else None
    return spec[0] if spec else None


def _metric_value(value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"metric value {value!r} is not a number") from exc
