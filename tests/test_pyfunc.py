"""Every run's model is an MLflow pyfunc model: signature, input example, registry round trip, REST serving."""

from __future__ import annotations

import json
import os
import sys
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import aumesh
from aumesh.core.schema import AU_COLUMNS, INPUT_COLUMNS, flatten_axis_major
from aumesh.model.release import load_npz
from aumesh.tracking import registry
from aumesh.tracking import runs as tracking
from conftest import upright_truth_release

MODEL = "aumesh-au-to-mesh"


def _inputs(n: int = 4) -> pd.DataFrame:
    rng = np.random.default_rng(1)
    df = pd.DataFrame(rng.uniform(0.0, 1.0, (n, 23)), columns=list(INPUT_COLUMNS))  # py-feat's 0..1 AUs
    df[["Pitch", "Yaw", "Roll"]] = 0.0
    return df


def _card_snippet(npz_path: Path, df: pd.DataFrame) -> np.ndarray:
    """The card's inference snippet, with raw numpy: (n, 1434) axis-major."""
    m = np.load(npz_path, allow_pickle=False)
    return df[list(INPUT_COLUMNS)].to_numpy() @ m["coef"].astype(np.float64) + m["intercept"].astype(np.float64)


@pytest.fixture
def champion(tmp_path):
    """A run that logs a synthetic-truth release as its pyfunc model, registered with alias champion."""
    from aumesh.tracking import pyfunc

    npz = upright_truth_release(tmp_path / "release.npz")
    with tracking.tracked_run({}, run_name="pyfunc-test", params=None) as run:
        seconds = pyfunc.log_release_model(run, load_npz(npz))
    version = registry.register_model_version(run.run_id, pyfunc.MODEL_ARTIFACT_DIR, MODEL, {})
    return npz, run.run_id, version, seconds


def test_registered_pyfunc_model_predicts_the_npz_meshes(champion):
    import mlflow.models
    import mlflow.pyfunc

    npz, run_id, version, seconds = champion
    assert version["alias"] == "champion" and seconds > 0
    info = mlflow.models.get_model_info(f"models:/{MODEL}@champion")
    assert registry.model_version_by_alias(MODEL, "champion", {})["run_id"] == run_id
    assert info.signature.inputs.input_names() == list(INPUT_COLUMNS)
    assert [s.type.name for s in info.signature.inputs.inputs] == ["double"] * 23
    assert info.signature.inputs.required_input_names() == []  # every column optional, as in predict_mesh
    assert info.signature.outputs.inputs[0].shape == (-1, 1434)
    assert info.saved_input_example_info["type"] == "dataframe"
    model = mlflow.pyfunc.load_model(f"models:/{MODEL}@champion")
    df = _inputs()
    pred = model.predict(df)
    np.testing.assert_allclose(pred, _card_snippet(npz, df), rtol=0, atol=1e-9 * 400)
    # columns are taken by name: shuffled columns give the same meshes
    np.testing.assert_allclose(model.predict(df[list(reversed(INPUT_COLUMNS))]), pred, rtol=0, atol=1e-12)
    # a missing AU is 0 and no pose columns is pose 0, as in aumesh.predict_mesh (checked against numpy above)
    partial = df.drop(columns=["AU12", "Pitch", "Yaw", "Roll"])
    np.testing.assert_allclose(
        model.predict(partial),
        _card_snippet(npz, partial.reindex(columns=INPUT_COLUMNS, fill_value=0.0)),
        rtol=0,
        atol=1e-9 * 400,
    )
    # aumesh's input errors are MLflow's invalid-parameter errors with aumesh's own line as the message
    from mlflow.exceptions import MlflowException

    from aumesh.model.input_columns import PredictionInputError

    with pytest.raises(PredictionInputError) as lib:
        aumesh.predict_mesh(load_npz(npz), df.assign(Yaw=25.0))
    with pytest.raises(MlflowException) as served:
        model.predict(df.assign(Yaw=25.0))
    assert served.value.error_code == "INVALID_PARAMETER_VALUE" and served.value.get_http_status_code() == 400
    assert served.value.message == str(lib.value) and "degrees" in served.value.message


def test_pyfunc_input_example_is_a_smile(champion):
    import mlflow.models

    npz, run_id, _, _ = champion
    example = mlflow.models.Model.load(f"runs:/{run_id}/model").load_input_example(
        mlflow.artifacts.download_artifacts(f"runs:/{run_id}/model")
    )
    assert list(example.columns) == list(INPUT_COLUMNS)
    assert example.loc[0, "AU12"] == 1.0 and example.drop(columns="AU12").to_numpy().sum() == 0.0
    assert set(AU_COLUMNS) < set(example.columns)


def scoring_server(model_uri: str, tmp_path: Path, timeout_s: int | None = None):
    """`mlflow models serve -m MODEL_URI --env-manager local` on 127.0.0.1 (README "Use the model"), started and
    waited for (:func:`aumesh.tracking.server.scoring_server`); yields its URL, stops its process group after."""
    from aumesh.tracking.server import scoring_server as served

    return served(model_uri, tmp_path / "serve.log", timeout_s=timeout_s)


@pytest.mark.slow
def test_mlflow_models_serve_answers_invocations_over_loopback(champion, tmp_path):
    """`mlflow models serve -m models:/aumesh-au-to-mesh@champion --env-manager local`, a real REST request."""
    npz, _, _, _ = champion
    with scoring_server(f"models:/{MODEL}@champion", tmp_path) as url:
        df = _inputs(3)
        status, answer = _invoke(url, {"dataframe_split": df.to_dict(orient="split") | {"index": None}})
        assert status == 200, answer
        # only AU12, as a client that cares about one AU sends it: the others 0, pose 0 (predict_mesh's rules)
        smile_status, smile = _invoke(url, {"dataframe_records": [{"AU12": 1.0}]})
        # a head turned 25 "radians": aumesh's degrees error, as a 400 whose message is aumesh's line
        bad_status, bad = _invoke(url, {"dataframe_records": [{"AU12": 1.0, "Pitch": 0.0, "Yaw": 25.0, "Roll": 0.0}]})
    pred = np.asarray(answer["predictions"], dtype=np.float64)
    assert pred.shape == (3, 1434)
    np.testing.assert_allclose(pred, _card_snippet(npz, df), rtol=0, atol=1e-9 * 400)
    assert smile_status == 200, smile
    expected = flatten_axis_major(aumesh.predict_mesh(load_npz(npz), {"AU12": 1.0})[None])[0]
    np.testing.assert_allclose(np.asarray(smile["predictions"])[0], expected, rtol=0, atol=1e-9 * 400)
    assert bad_status == 400, bad
    with pytest.raises(aumesh.PredictionInputError) as lib:
        aumesh.predict_mesh(load_npz(npz), {"AU12": 1.0}, pose=[0.0, 25.0, 0.0])
    assert bad["error_code"] == "INVALID_PARAMETER_VALUE"
    assert bad["message"] == str(lib.value) and "degrees" in bad["message"] and "\n" not in bad["message"]


def _invoke(url: str, payload: dict, timeout_s: float = 60) -> tuple[int, dict]:
    """POST *payload* to the scoring server's /invocations: (HTTP status, the JSON answer)."""
    status, text = invoke_text(url, payload, timeout_s)
    return status, json.loads(text)


def invoke_text(url: str, payload: dict, timeout_s: float = 60) -> tuple[int, str]:
    """POST *payload* to the scoring server's /invocations: (HTTP status, the answer's text as sent)."""
    req = urllib.request.Request(
        f"{url}/invocations", data=json.dumps(payload).encode(), headers={"Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as resp:
            return resp.status, resp.read().decode()
    except urllib.error.HTTPError as err:
        return err.code, err.read().decode()


def test_readme_load_model_snippet_works_from_any_folder(champion, tmp_path, monkeypatch):
    """The README's snippet names the workspace's store itself: from another folder it finds the champion and
    leaves no empty mlflow.db behind (without set_tracking_uri MLflow would look in the current folder)."""
    import re

    import mlflow

    npz, _, _, _ = champion
    store = Path(os.environ["MLFLOW_TRACKING_URI"][len("sqlite:///") :])  # the test's workspace store: <dir>/mlflow.db
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = next(
        b for b in re.findall(r"```python\n(.*?)```", readme, re.S) if "models:/aumesh-au-to-mesh@champion" in b
    )
    code = block.replace('Path("~/aumesh").expanduser()', f"Path({str(store.parent)!r})")
    assert code != block, 'the README\'s snippet no longer names the workspace as Path("~/aumesh").expanduser()'
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    namespace = {"df": pd.DataFrame({"AU12": [1.0]})}
    try:
        exec(code, namespace)
    finally:
        mlflow.set_tracking_uri(None)
    expected = flatten_axis_major(aumesh.predict_mesh(load_npz(npz), {"AU12": 1.0})[None])
    np.testing.assert_allclose(namespace["flat"], expected, rtol=0, atol=1e-9 * 400)
    assert list(elsewhere.iterdir()) == []


def test_the_logged_model_keeps_the_datas_support_and_warns_on_each_call(tmp_path, caplog):
    """A release that records its training ranges, logged and loaded back as MLflow loads it: every call beyond the
    data logs one line (as ``aumesh.predict_mesh`` warns); a call within it, none."""
    import mlflow.pyfunc

    from aumesh.tracking import pyfunc
    from test_support import _release_with_support

    npz = _release_with_support(tmp_path, "MPDetector")
    with tracking.tracked_run({}, run_name="pyfunc-support", params=None) as run:
        pyfunc.log_release_model(run, load_npz(npz))
    model = mlflow.pyfunc.load_model(f"runs:/{run.run_id}/{pyfunc.MODEL_ARTIFACT_DIR}")
    with caplog.at_level("WARNING", logger="aumesh.tracking.pyfunc"):
        model.predict(pd.DataFrame({"AU12": [0.9, 0.2]}))
        model.predict(pd.DataFrame({"AU12": [0.9]}))
        model.predict(pd.DataFrame({"AU12": [0.5]}))  # within the training data
    lines = [r.getMessage() for r in caplog.records if r.name == "aumesh.tracking.pyfunc"]
    assert len(lines) == 2 and all("AU12 up to 0.9 (training max 0.6, p99 0.5)" in m for m in lines), lines


#: The "models from code" entry every MLflow model logged before issue 42's layout carries, verbatim (its
#: src/aumesh/experiments/pyfunc_entry.py at commit 0e7b583): the registered @champion imports this path.
OLD_ENTRY = '''"""MLflow "models from code" entry of the pyfunc model (copied into every logged ``model/``; no pickle)."""

import mlflow.models

from aumesh.experiments.pyfunc import ReleaseModel

mlflow.models.set_model(ReleaseModel())
'''


def test_a_model_logged_before_the_move_still_loads_and_predicts(tmp_path, monkeypatch):
    """A model saved as the old code saved it (its entry imports ``aumesh.experiments.pyfunc``) loads with MLflow's
    own loader and predicts what ``aumesh.predict_mesh`` predicts on the same release (and the card's snippet)."""
    import mlflow.pyfunc

    from aumesh.tracking import pyfunc

    npz = upright_truth_release(tmp_path / "release.npz")
    entry = tmp_path / "old" / "pyfunc_entry.py"
    entry.parent.mkdir()
    entry.write_text(OLD_ENTRY)
    model_dir = tmp_path / "model"
    mlflow.pyfunc.save_model(  # the old save_release_model's call, with the old entry file
        str(model_dir),
        python_model=str(entry),
        artifacts={pyfunc.NPZ_KEY: str(npz)},
        signature=pyfunc.signature(),
        input_example=pyfunc.input_example(),
        pip_requirements=pyfunc.requirements(),
    )
    # the model carries the old entry's text, which names the old path
    assert [p.read_text() for p in model_dir.rglob("*.py")] == [OLD_ENTRY]
    # import the kept path afresh from the source tree, as a new process loading the model would
    monkeypatch.delitem(sys.modules, "aumesh.experiments.pyfunc", raising=False)
    model = mlflow.pyfunc.load_model(str(model_dir))
    assert type(model.unwrap_python_model()) is pyfunc.ReleaseModel
    df = _inputs(5)
    df[list(AU_COLUMNS)] *= 0.5  # py-feat's 0..1 scale
    df["Yaw"] = 0.2  # a turned head, within the training range
    pred = model.predict(df)
    assert pred.shape == (5, 1434)
    np.testing.assert_array_equal(pred, flatten_axis_major(aumesh.predict_mesh(load_npz(npz), df)))
    np.testing.assert_allclose(pred, _card_snippet(npz, df), rtol=0, atol=1e-9 * 400)
