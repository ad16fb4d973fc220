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
filter: :func:`aumesh.predict_mesh`'s :class:`aumesh.InputRangeWarning`) and rows without a face are logged, one line
each per call (the server's log; ``model.predict``'s stderr); with ``params={"beyond_training": "refuse"}`` the
range line is an input error instead.

Input errors are aumesh's own (:class:`aumesh.PredictionInputError`: pose in degrees, a partly NaN
row, half a pose; and, served or loaded, an AU outside py-feat's 0..1, :data:`SERVED_AU_RANGE`: AU12 = 5 or 1e308
were answered 200, the latter with ``Infinity`` in the JSON) raised as :class:`ServingInputError`, an
``MlflowException`` with ``INVALID_PARAMETER_VALUE``: ``mlflow models serve`` answers HTTP 400 with aumesh's one-line
message as the response's ``message``, and ``model.predict`` raises it with the same text. So every mesh answered
for a row with a face is finite.

The answer's size: MLflow's scoring server writes the (n, 1434) float64 answer as JSON numbers (~27 KB a row); the
encoding, not the prediction, is what a large batch waits for (10,000 rows: past the server's 60 s
``MLFLOW_SCORING_SERVER_REQUEST_TIMEOUT``, HTTP 504). ``params={"output": "base64"}`` answers each row as one
base64 string of its float32 coordinates (:func:`base64_meshes`) and its ``no_face`` flag; README "Use the model"
gives the batch sizes measured through the server (``benchmarks/bench_serve.py``). Models logged before these params
have no params schema: MLflow ignores the params (with a warning) and answers float64.

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

from aumesh.core.schema import INPUT_COLUMNS, N_TARGETS, POSE_COLUMNS, flatten_axis_major
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


#: ``params={"output": ...}``: the answer's format. ``float64`` (default, and the only one of models logged before the
#: params existed): an (n, 1434) array, one row of axis-major coordinates per input row. ``base64``: a table of two
#: columns, ``mesh`` (the row's 1434 coordinates as little-endian float32 bytes, base64: 7,648 characters instead of
#: ~27,000 of JSON numbers) and ``no_face`` (bool).
OUTPUTS = ("float64", "base64")
#: ``params={"beyond_training": ...}``: inputs beyond the training data (``InputRangeWarning``) are ``warn``: answered,
#: with the warning's line in the server's log (default), or ``refuse``: answered 400 with the line.
BEYOND_TRAINING = ("warn", "refuse")
#: A served AU outside py-feat's 0..1 scale (either detector's) is refused: the model's input is a detector's AU row,
#: and a value like 5 (OpenFace's 0..5) or 1e308 answers a mesh that means nothing, or overflows to Infinity.
SERVED_AU_RANGE = (0.0, 1.0)


class ReleaseModel(PythonModel):
    """MLflow pyfunc wrapper of a release NPZ: DataFrame of input columns (any of the 23) -> (n, 1434) meshes."""

    def load_context(self, context) -> None:
        from aumesh.model.release_check import load_release

        self.release_ = load_release(context.artifacts[NPZ_KEY])

    def predict(self, context, model_input: pd.DataFrame, params: dict[str, Any] | None = None) -> Any:
        """One mesh per row: an (n, 1434) float64 array of axis-major coordinates (``aumesh.predict_mesh``), or with
        ``params={"output": "base64"}`` a DataFrame of ``mesh`` (base64 float32 bytes) and ``no_face``.

        Columns are taken by name; a missing AU is 0 and no pose columns is pose 0 (``predict_mesh``'s rules);
        other columns are ignored. An AU outside 0..1 (:data:`SERVED_AU_RANGE`), aumesh's input errors and, with
        ``params={"beyond_training": "refuse"}``, inputs beyond the training data raise :class:`ServingInputError`
        (HTTP 400 when served, aumesh's one line as the message); otherwise those are logged, one line a request.
        """
        from aumesh.model.input_columns import PredictionInputError

        output, beyond = _params(params)
        frame = pd.DataFrame(model_input)
        present = [c for c in INPUT_COLUMNS if c in frame.columns]
        try:
            values = frame[present].astype(np.float64)
        except (TypeError, ValueError) as err:
            raise ServingInputError(
                f"inputs: not numbers ({err}); send AU01..AU43, Pitch, Yaw, Roll as numbers"
            ) from None
        try:
            _check_served_aus(values)
            meshes = _predict_checked(self.release_, values, refuse=beyond == "refuse")
        except PredictionInputError as err:
            raise ServingInputError(str(err)) from None  # the line is the whole story; no chained traceback
        flat = flatten_axis_major(meshes.reshape(len(frame), -1, 3))
        if output == "float64":
            return flat
        return base64_meshes(flat)


def _params(params: Mapping[str, Any] | None) -> tuple[str, str]:
    """``output`` and ``beyond_training`` of a request's params (defaults for None or absent), checked."""
    params = params or {}
    output, beyond = str(params.get("output", OUTPUTS[0])), str(params.get("beyond_training", BEYOND_TRAINING[0]))
    if output not in OUTPUTS:
        raise ServingInputError(f"params: output {output!r} is not one of {', '.join(OUTPUTS)}")
    if beyond not in BEYOND_TRAINING:
        raise ServingInputError(f"params: beyond_training {beyond!r} is not one of {', '.join(BEYOND_TRAINING)}")
    return output, beyond


def _check_served_aus(values: pd.DataFrame) -> None:
    """Refuse a finite AU outside :data:`SERVED_AU_RANGE` (NaN and infinity are ``predict_mesh``'s to name), naming
    the first (row, column) and the fix."""
    from aumesh.model.input_columns import PredictionInputError

    aus = [c for c in values.columns if c not in POSE_COLUMNS]
    if not aus:
        return
    a = values[aus].to_numpy()
    lo, hi = SERVED_AU_RANGE
    bad = np.isfinite(a) & ((a < lo) | (a > hi + 1e-6))
    if bad.any():
        row, col = (int(i) for i in np.argwhere(bad)[0])
        raise PredictionInputError(
            f"aus: {aus[col]} = {a[row, col]:g} at row {row} ({int(bad.sum())} value(s)) is outside {lo:g}..{hi:g}, "
            f"py-feat's AU scale and the model's; the served model refuses it (0..5 is OpenFace's scale: divide by 5)"
        )


def _predict_checked(release, values: pd.DataFrame, refuse: bool) -> np.ndarray:
    """``predict_mesh`` of ``values``; its warnings (beyond the training data, rows without a face) logged one line
    each, or with ``refuse`` an :class:`InputRangeWarning` raised as the input error it describes."""
    import warnings

    from aumesh.model.inference import predict_mesh
    from aumesh.model.input_checks import InputRangeWarning, NoFaceWarning, logged_range_warnings
    from aumesh.model.input_columns import PredictionInputError

    if not refuse:
        # one logged line per request (a Python warning would show once per process: later requests unwarned)
        with logged_range_warnings(log, "aumesh model"):
            return predict_mesh(release, values)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", InputRangeWarning)
        warnings.simplefilter("always", NoFaceWarning)
        meshes = predict_mesh(release, values)
    ranges = [str(w.message) for w in caught if issubclass(w.category, InputRangeWarning)]
    if ranges:
        raise PredictionInputError(f"{'; '.join(ranges)} (refused: params beyond_training=refuse)")
    for w in caught:
        if issubclass(w.category, NoFaceWarning):
            log.warning("aumesh model: %s", w.message)
    return meshes


def base64_meshes(flat: np.ndarray) -> pd.DataFrame:
    """(n, 1434) axis-major meshes -> DataFrame ``mesh`` (base64 of the row's little-endian float32 bytes, 5,736
    bytes) and ``no_face`` (the row is all NaN). A client decodes a row with
    ``np.frombuffer(base64.b64decode(s), "<f4").reshape(3, 478).T`` -> (478, 3)."""
    import base64

    rows = np.ascontiguousarray(flat, dtype="<f4")
    return pd.DataFrame(
        {
            "mesh": [base64.b64encode(r.tobytes()).decode("ascii") for r in rows],
            "no_face": np.isnan(rows).all(axis=1),
        }
    )


def signature():
    """Inputs: the 23 named float (double) columns, each optional (missing AU = 0, no pose = pose 0, as
    :func:`aumesh.predict_mesh`); output: a (-1, 1434) float64 tensor (the default ``output``); params ``output``
    (:data:`OUTPUTS`) and ``beyond_training`` (:data:`BEYOND_TRAINING`)."""
    from mlflow.models.signature import ModelSignature
    from mlflow.types.schema import ColSpec, ParamSchema, ParamSpec, Schema, TensorSpec

    return ModelSignature(
        inputs=Schema([ColSpec("double", c, required=False) for c in INPUT_COLUMNS]),
        outputs=Schema([TensorSpec(np.dtype(np.float64), (-1, N_TARGETS))]),
        params=ParamSchema(
            [ParamSpec("output", "string", OUTPUTS[0]), ParamSpec("beyond_training", "string", BEYOND_TRAINING[0])]
        ),
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
