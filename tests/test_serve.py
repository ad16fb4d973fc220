"""Issue 44: the served model (MLflow pyfunc, ``mlflow models serve``) applies ``predict_mesh``'s checks and answers
a documented batch within the server's timeout. AU12 = 5 and 1e308 were answered 200 (the latter with ``Infinity`` in
the JSON); 10,000 rows timed out (HTTP 504) in MLflow's JSON encoding. Now: an AU outside 0..1 is a 400 with aumesh's
line, ``params={"beyond_training": "refuse"}`` refuses extrapolation, and ``params={"output": "base64"}`` answers each
mesh as one base64 string of float32 bytes."""

from __future__ import annotations

import base64
import json
import logging

import numpy as np
import pandas as pd
import pytest
from mlflow.exceptions import MlflowException

import aumesh
from aumesh.core.schema import AU_COLUMNS, INPUT_COLUMNS, flatten_axis_major
from aumesh.model.release import load_npz
from conftest import upright_truth_release
from test_pyfunc import OLD_ENTRY, _card_snippet, invoke_text, scoring_server

#: README "Use the model": the rows a request may carry with the default float64 answer, and with output=base64,
#: within MLflow's default 60 s request timeout, with room for a loaded machine (benchmarks/bench_serve.py on the
#: shared 2-core machine: float64 2,000 rows 5.9 s, 10,000 rows 53 s; base64 10,000 rows 3.1 s, 20,000 rows 9.5 s).
FLOAT64_BATCH, BASE64_BATCH = 2_000, 20_000


def decode(answer: pd.DataFrame | list) -> np.ndarray:
    """``output=base64`` rows -> (n, 1434) float32, as README "Use the model" decodes them."""
    rows = answer["mesh"] if isinstance(answer, pd.DataFrame) else [r["mesh"] for r in answer]
    return np.stack([np.frombuffer(base64.b64decode(s), "<f4") for s in rows])


def _rows(n: int, seed: int = 0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    df = pd.DataFrame(0.0, index=range(n), columns=list(INPUT_COLUMNS))
    df[list(AU_COLUMNS)] = rng.uniform(0.0, 1.0, (n, len(AU_COLUMNS)))  # py-feat's 0..1 AUs, frontal pose
    return df


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A release saved as the project's MLflow pyfunc model and loaded back by MLflow's loader."""
    import mlflow.pyfunc

    from aumesh.tracking.pyfunc import save_release_model

    tmp = tmp_path_factory.mktemp("served")
    npz = upright_truth_release(tmp / "release.npz")
    model_dir = save_release_model(npz, tmp / "model")
    return npz, model_dir, mlflow.pyfunc.load_model(str(model_dir))


def test_base64_output_is_the_float64_meshes_as_float32_bytes(served):
    npz, _, model = served
    df = _rows(6)
    df.loc[3] = np.nan  # a frame without a face: every input missing
    flat = model.predict(df)
    answer = model.predict(df, params={"output": "base64"})
    assert list(answer.columns) == ["mesh", "no_face"]
    np.testing.assert_array_equal(decode(answer), flat.astype(np.float32))
    assert answer["no_face"].tolist() == [i == 3 for i in range(6)]
    face = ~answer["no_face"].to_numpy()
    np.testing.assert_allclose(decode(answer)[face], _card_snippet(npz, df[face]), rtol=1e-6, atol=1e-3)
    # one row decodes to the (478, 3) mesh of predict_mesh
    one = np.frombuffer(base64.b64decode(answer["mesh"][0]), "<f4").reshape(3, 478).T
    np.testing.assert_allclose(one, aumesh.predict_mesh(load_npz(npz), df.iloc[[0]])[0], rtol=1e-6, atol=1e-3)


@pytest.mark.parametrize("value", [5.0, 1e308, -1e308, -0.5, 1.01])
def test_an_au_outside_0_to_1_is_refused_as_400(served, value):
    _, _, model = served
    df = _rows(3).assign(AU12=[0.2, value, 0.3])
    with pytest.raises(MlflowException) as err:
        model.predict(df)
    assert err.value.get_http_status_code() == 400 and err.value.error_code == "INVALID_PARAMETER_VALUE"
    message = err.value.message
    assert f"aus: AU12 = {value:g} at row 1 (1 value(s)) is outside 0..1" in message and "\n" not in message
    assert "divide by 5" in message
    model.predict(df.assign(AU12=1.0))  # the scale's ends are answered


def test_infinite_or_partly_missing_inputs_are_predict_meshs_errors(served):
    _, _, model = served
    for bad, expected in ((np.inf, "NaN/inf value"), (np.nan, "only partly NaN")):
        df = _rows(2)
        df.loc[1, "AU04"] = bad
        with pytest.raises(MlflowException) as err:
            model.predict(df)
        assert err.value.get_http_status_code() == 400 and expected in err.value.message


def test_beyond_the_training_data_is_logged_or_refused(tmp_path, caplog):
    import mlflow.pyfunc

    from aumesh.tracking.pyfunc import save_release_model
    from test_support import _release_with_support

    model = mlflow.pyfunc.load_model(
        str(save_release_model(_release_with_support(tmp_path, "MPDetector"), tmp_path / "model"))
    )
    df = pd.DataFrame({"AU12": [0.2, 0.9]})  # the training max of AU12 is 0.6
    with caplog.at_level(logging.WARNING, logger="aumesh.tracking.pyfunc"):
        flat = model.predict(df)
    assert np.isfinite(flat).all()
    assert [r.getMessage() for r in caplog.records if "AU12 up to 0.9" in r.getMessage()]
    with pytest.raises(MlflowException) as err:
        model.predict(df, params={"beyond_training": "refuse"})
    assert err.value.get_http_status_code() == 400
    assert "AU12 up to 0.9 (training max 0.6, p99 0.5)" in err.value.message and "refused" in err.value.message
    model.predict(df.assign(AU12=0.5), params={"beyond_training": "refuse"})  # within the data: answered
    with pytest.raises(MlflowException, match="output 'float16' is not one of float64, base64"):
        model.predict(df, params={"output": "float16"})


def test_a_model_logged_without_params_still_loads_and_answers_float64(served, tmp_path, monkeypatch):
    """A model logged before the params (the old entry file, a signature without params): MLflow ignores params it
    has no schema for, and the model answers as it did."""
    import sys

    import mlflow.pyfunc
    from mlflow.models.signature import ModelSignature

    from aumesh.tracking import pyfunc

    npz, _, _ = served
    entry = tmp_path / "old" / "pyfunc_entry.py"
    entry.parent.mkdir()
    entry.write_text(OLD_ENTRY)
    old = pyfunc.signature()
    mlflow.pyfunc.save_model(
        str(tmp_path / "model"),
        python_model=str(entry),
        artifacts={pyfunc.NPZ_KEY: str(npz)},
        signature=ModelSignature(inputs=old.inputs, outputs=old.outputs),  # no params, as logged before
        input_example=pyfunc.input_example(),
        pip_requirements=pyfunc.requirements(),
    )
    monkeypatch.delitem(sys.modules, "aumesh.experiments.pyfunc", raising=False)
    model = mlflow.pyfunc.load_model(str(tmp_path / "model"))
    df = _rows(4)
    expected = flatten_axis_major(aumesh.predict_mesh(load_npz(npz), df))
    np.testing.assert_array_equal(model.predict(df, params={"output": "base64"}), expected)


@pytest.mark.slow
def test_the_real_server_answers_the_documented_batches_and_refuses_absurd_inputs(served, tmp_path):
    """`mlflow models serve` (README's command, default 60 s timeout): the documented batch sizes answer 200 in both
    formats; AU12 = 5 and 1e308 are 400 with aumesh's line; no response carries Infinity."""
    npz, model_dir, _ = served
    answers = []
    with scoring_server(str(model_dir), tmp_path) as url:
        for n, output in ((FLOAT64_BATCH, "float64"), (BASE64_BATCH, "base64")):
            df = _rows(n, seed=n)
            payload = {"dataframe_split": df.to_dict(orient="split") | {"index": None}, "params": {"output": output}}
            status, text = invoke_text(url, payload, timeout_s=120)
            answers.append(text)
            assert status == 200, text[:500]
            predictions = json.loads(text)["predictions"]
            got = np.asarray(predictions) if output == "float64" else decode(predictions)
            assert got.shape == (n, 1434)
            rows = [0, n // 2, n - 1]
            np.testing.assert_allclose(got[rows], _card_snippet(npz, df.iloc[rows]), rtol=1e-6, atol=1e-3)
        for value in (5.0, 1e308):
            status, text = invoke_text(url, {"dataframe_records": [{"AU12": value}]})
            answers.append(text)
            assert status == 400, text[:500]
            message = json.loads(text)["message"]
            assert message.startswith(f"aus: AU12 = {value:g} at row 0") and "outside 0..1" in message
    assert not any("Infinity" in text for text in answers)
