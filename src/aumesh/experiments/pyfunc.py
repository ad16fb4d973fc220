"""Where the pyfunc wrapper used to live: kept importable for the MLflow models logged before it moved.

Every model logged as code carries a copy of its ``pyfunc_entry.py``, which names the module it loads; models logged
before the layout of issue 42 (the registered ``@champion`` included) name ``aumesh.experiments.pyfunc``. The wrapper
itself lives in :mod:`aumesh.tracking.pyfunc`, the one package that imports MLflow.
"""

from aumesh.tracking.pyfunc import ReleaseModel, log_release_model

__all__ = ["ReleaseModel", "log_release_model"]
