"""What a row costs through MLflow's real scoring server (issue 44: 10,000 rows -> HTTP 504 after 60 s).

A release (the synthetic-truth map) saved as the project's MLflow pyfunc model is served by ``mlflow models serve
--env-manager local`` on 127.0.0.1 (README "Use the model"; :func:`aumesh.tracking.server.scoring_command`) with a
long request timeout, so the time of every batch size is measured rather than cut at 60 s. Each batch (random py-feat
AUs in 0..1, frontal pose) is POSTed as ``dataframe_split`` in the default ``float64`` output and in
``params={"output": "base64"}``; the wall time of the request (median of ``--repeats``) and the answer's size are
printed, with the same batch's ``model.predict`` in this process (the prediction alone) beside them. Figures only.

    .venv/bin/python benchmarks/bench_serve.py                       # 100, 1,000, 3,000, 10,000 rows
    .venv/bin/python benchmarks/bench_serve.py --rows 1000 --repeats 5
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pandas as pd


def _model(folder: Path) -> Path:
    from aumesh.geometry import face
    from aumesh.synthetic import truth
    from aumesh.tracking.pyfunc import save_release_model

    npz = folder / "release.npz"
    tpl = 120.0 * face.canonical_template() * np.array([1.0, -1.0, -1.0]) + np.array([320.0, 240.0, 10.0])
    np.savez(npz, **truth.synthetic_release_arrays(tpl))
    return save_release_model(npz, folder / "model")


def _post(url: str, payload: bytes, timeout: float) -> tuple[int, int, float]:
    req = urllib.request.Request(f"{url}/invocations", data=payload, headers={"Content-Type": "application/json"})
    t0 = time.perf_counter()
    try:
        with urllib.request.urlopen(req, timeout=timeout) as resp:
            body = resp.read()
            status = resp.status
    except urllib.error.HTTPError as err:
        body, status = err.read(), err.code
    return status, len(body), time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, nargs="+", default=[100, 1000, 3000, 10000])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--outputs", nargs="+", default=["float64", "base64"], choices=["float64", "base64"])
    parser.add_argument("--timeout", type=int, default=600, help="the server's request timeout for the measurement")
    args = parser.parse_args()

    import mlflow.pyfunc

    from aumesh.core.schema import AU_COLUMNS, INPUT_COLUMNS
    from aumesh.tracking.server import scoring_server

    with tempfile.TemporaryDirectory(prefix="bench-serve-") as tmp:
        model_dir = _model(Path(tmp))
        local = mlflow.pyfunc.load_model(str(model_dir))
        with scoring_server(str(model_dir), Path(tmp) / "serve.log", timeout_s=args.timeout) as url:
            print(f"mlflow models serve (1 worker, timeout {args.timeout} s), medians of {args.repeats}")
            print(f"{'rows':>7} {'output':>8} {'status':>6} {'wall s':>8} {'ms/row':>7} {'MB':>7} {'predict s':>10}")
            rng = np.random.default_rng(0)
            for n in args.rows:
                df = pd.DataFrame(0.0, index=range(n), columns=list(INPUT_COLUMNS))
                df[list(AU_COLUMNS)] = rng.uniform(0.0, 1.0, (n, len(AU_COLUMNS)))
                t0 = time.perf_counter()
                local.predict(df)
                predict_s = time.perf_counter() - t0
                split = df.to_dict(orient="split") | {"index": None}
                for output in args.outputs:
                    payload = json.dumps({"dataframe_split": split, "params": {"output": output}}).encode()
                    runs = [_post(url, payload, args.timeout + 30) for _ in range(args.repeats)]
                    wall = statistics.median(r[2] for r in runs)
                    print(
                        f"{n:>7,} {output:>8} {runs[-1][0]:>6} {wall:>8.2f} {1000 * wall / n:>7.2f} "
                        f"{runs[-1][1] / 1e6:>7.1f} {predict_s:>10.3f}",
                        flush=True,
                    )


if __name__ == "__main__":
    main()
