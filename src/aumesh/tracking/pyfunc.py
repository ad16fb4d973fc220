"""Every run's model as an MLflow Model (``python_function`` flavor), so MLflow's own clients use it.

A run's artifact ``model/`` is an MLflow pyfunc model directory: ``MLmodel`` (signature and
input example), the release-format NPZ (``model/artifacts/au_to_mesh_pls.npz``) and the
:class:`ReleaseModel` wrapper. Promotion registers that directory, so::

    mlflow.pyfunc.load_model("models:/aumesh-au-to-mesh@champion").predict(df)

returns ``aumesh.predict_mesh(npz, df)`` flattened axis-major, and ``mlflow models serve -m
models:/aumesh-au-to-mesh@champion --env-manager local`` serves it over REST.

Signature: inputs are the card's 23 named float columns ``AU01 .. AU43, Pitch, Yaw, Roll``, every
one optional, as in :func:`aumesh.predict_mesh`: a missing AU is 0, no pose columns is pose 0, and
``Pitch, Yaw, Roll`` come all or none (pose in radians; with ``coef_full`` the prediction is
pose-conditioned); the output is one row of 1434 axis-major coordinates
``[x_0..x_477 | y_0.. | z_0..]`` per input row.

Inputs beyond the training data (AUs above the training max, AUs the data never expressed, pose beyond the pose
filter: :func:`aumesh.predict_mesh`'s :class:`aumesh.InputRangeWarning`) are logged, one line per call (the server's
log; ``model.predict``'s stderr), since the REST answer has no place for them.

Input errors are aumesh's own (:class:`aumesh.PredictionInputError`: pose in degrees, a partly NaN
row, half a pose) raised as :class:`ServingInputError`, an ``MlflowException`` with
``INVALID_PARAMETER_VALUE``: ``mlflow models serve`` answers HTTP 400 with aumesh's one-line
message as the response's ``message``, and ``model.predict`` raises it with the same text.

The wrapper is logged as code (MLflow's "models from code": ``pyfunc_entry.py``, no pickle) that
imports :class:`ReleaseModel`, so loading needs ``aumesh`` importable (``--env-manager local`` in
the project's venv). Requirements are
given explicitly (no dependency inference), which keeps logging cheap for every sweep child.
"""

from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import mlflow.pyfunc
import numpy as np
import pandas as pd
from mlflow.exceptions import MlflowException
from mlflow.protos.databricks_pb2 import INVALID_PARAMETER_VALUE
from mlflow.pyfunc import PythonModel

from aumesh.core.schema import INPUT_COLUMNS, N_TARGETS, flatten_axis_major
from aumesh.model.release import NPZ_NAME

log = logging.getLogger(__name__)

MODEL_ARTIFACT_DIR = "model"
NPZ_KEY = "release_npz"
NPZ_ARTIFACT = f"{MODEL_ARTIFACT_DIR}/artifacts/{NPZ_NAME}"  # the NPZ inside a run's model/


class ServingInputError(MlflowException):
    """An input error of aumesh's (:class:`aumesh.PredictionInputError`) as MLflow's invalid-parameter error (HTTP 400).

    Its ``message`` stays aumesh's one line: MLflow's scoring server (3.17, ``invocations``) rewrites the ``message``
    of an ``MlflowException`` from ``predict`` to ``"Failed to predict data '<the whole request DataFrame>'.
    \nError: ..."``, which buries the line a client needs under a printout of its own request. So only the first
    assignment (``MlflowException.__init__``'s) sets it.
    """

    def __init__(self, message: str) -> None:
        super().__init__(message, error_code=INVALID_PARAMETER_VALUE)

    @property
    def message(self) -> str:
        return self._aumesh_message

    @message.setter
    def message(self, value: str) -> None:
        if "_aumesh_message" not in self.__dict__:
            self._aumesh_message = value


class ReleaseModel(PythonModel):
    """MLflow pyfunc wrapper of a release NPZ: DataFrame of input columns (any of the 23) -> (n, 1434) meshes."""

    def load_context(self, context) -> None:
        from aumesh.model.release_check import load_release

        self.release_ = load_release(context.artifacts[NPZ_KEY])

    def predict(self, context, model_input: pd.DataFrame, params: dict[str, Any] | None = None) -> np.ndarray:
        """One mesh per row, flattened axis-major: shape (n, 1434), float64 (``aumesh.predict_mesh``).

        Columns are taken by name; a missing AU is 0 and no pose columns is pose 0 (``predict_mesh``'s rules);
        other columns are ignored. aumesh's input errors raise :class:`ServingInputError` (HTTP 400 when served).
        """
        from aumesh.model.inference import predict_mesh
        from aumesh.model.input_checks import logged_range_warnings
        from aumesh.model.input_columns import PredictionInputError

        frame = pd.DataFrame(model_input)
        present = [c for c in INPUT_COLUMNS if c in frame.columns]
        # predict_mesh's checks beyond the training data, one logged line per request (a Python warning would show
        # once per process: a server's later requests would go unwarned)
        try:
            with logged_range_warnings(log, "aumesh model"):
                meshes = predict_mesh(self.release_, frame[present].astype(np.float64))
        except PredictionInputError as err:
            raise ServingInputError(str(err)) from None  # the line is the whole story; no chained traceback
        return flatten_axis_major(meshes.reshape(len(frame), -1, 3))


def signature():
    """Inputs: the 23 named float (double) columns, each optional (missing AU = 0, no pose = pose 0, as
    :func:`aumesh.predict_mesh`); output: a (-1, 1434) float64 tensor."""
    from mlflow.models.signature import ModelSignature
    from mlflow.types.schema import ColSpec, Schema, TensorSpec

    return ModelSignature(
        inputs=Schema([ColSpec("double", c, required=False) for c in INPUT_COLUMNS]),
        outputs=Schema([TensorSpec(np.dtype(np.float64), (-1, N_TARGETS))]),
    )


def input_example() -> pd.DataFrame:
    """One row: a smile (AU12 = 1), other AUs 0, frontal pose."""
    row = dict.fromkeys(INPUT_COLUMNS, 0.0) | {"AU12": 1.0}
    return pd.DataFrame([row], columns=list(INPUT_COLUMNS))


def requirements() -> list[str]:
    """What the wrapper imports, pinned to this environment (aumesh itself: this repository, installed)."""
    from importlib.metadata import version

    return [f"{p}=={version(p)}" for p in ("mlflow", "numpy", "pandas", "scipy")]


def save_release_model(npz_path: str | Path, path: str | Path) -> Path:
    """Write the MLflow pyfunc model directory of release NPZ *npz_path* to *path* (must not exist)."""
    mlflow.pyfunc.save_model(
        str(path),
        python_model=str(Path(__file__).with_name("pyfunc_entry.py")),
        artifacts={NPZ_KEY: str(npz_path)},
        signature=signature(),
        input_example=input_example(),
        pip_requirements=requirements(),
    )
    return Path(path)


def log_release_model(run, arrays: Mapping[str, np.ndarray]) -> float:
    """Log release arrays as the run's pyfunc model under ``model/``; returns the seconds it took.

    Parameters
    ----------
    run : aumesh.tracking.handle.TrackedRun
        An open run (a disabled run logs nothing).
    arrays : mapping
        The release NPZ's arrays (:func:`aumesh.model.release.release_arrays`).
    """
    from aumesh.core.io import atomic_savez

    if not getattr(run, "enabled", True):
        return 0.0
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="aumesh-model-") as tmp:
        npz = atomic_savez(Path(tmp) / NPZ_NAME, **arrays)
        model_dir = save_release_model(npz, Path(tmp) / MODEL_ARTIFACT_DIR)
        run.log_artifact(model_dir, MODEL_ARTIFACT_DIR)
    return time.perf_counter() - t0
