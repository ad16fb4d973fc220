"""MLflow "models from code" entry of the pyfunc model (copied into every logged ``model/``; no pickle)."""

import mlflow.models

from aumesh.tracking.pyfunc import ReleaseModel

mlflow.models.set_model(ReleaseModel())
