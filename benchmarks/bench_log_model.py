"""Cost of logging a run's model as an MLflow pyfunc model (every evaluate run and sweep child does it).

Prints, per run, the wall time of ``aumesh.tracking.pyfunc.log_release_model`` (save_model with
signature, input example and its validation, explicit requirements; then the directory logged as
artifacts) against the plain NPZ artifact it replaced (``log_artifact`` of the same NPZ), into a
throw-away SQLite store. The release has the card's 83-column ``coef_full`` (the default feature set).

    .venv/bin/python benchmarks/bench_log_model.py [--runs 10] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10, help="runs per variant (default: %(default)s)")
    ap.add_argument("--workdir", type=Path, default=None, help="where the store goes (default: a temp folder)")
    args = ap.parse_args()

    import os

    from aumesh.core.io import atomic_savez
    from aumesh.core.schema import feature_columns
    from aumesh.model.release import release_arrays
    from aumesh.synthetic.truth import synthetic_release_arrays
    from aumesh.tracking import pyfunc
    from aumesh.tracking import runs as tracking

    work = Path(tempfile.mkdtemp(prefix="aumesh-bench-log-", dir=args.workdir))
    os.environ["MLFLOW_TRACKING_URI"] = f"sqlite:///{work / 'mlflow.db'}"
    truth = synthetic_release_arrays()
    columns = feature_columns(True, True)
    coef = np.random.default_rng(0).normal(size=(1434, len(columns)))
    reference = {k: truth[k] for k in ("mean_aligned_mesh", "mean_low_au_mesh", "reference_anchors", "anchor_indices")}
    arrays = release_arrays(coef, truth["intercept"], columns, 83, reference, card_text="", metadata={})
    npz = atomic_savez(work / "model.npz", **arrays)

    times: dict[str, list[float]] = {"npz artifact only (before)": [], "pyfunc model (now)": []}
    for i in range(args.runs + 1):  # the first round warms imports and the store; not counted
        with tracking.tracked_run({}, run_name=f"bench-{i}", params=None) as run:
            t0 = time.perf_counter()
            run.log_artifact(npz, "model")
            t_npz = time.perf_counter() - t0
        with tracking.tracked_run({}, run_name=f"bench-pyfunc-{i}", params=None) as run:
            t_model = pyfunc.log_release_model(run, arrays)
        if i:
            times["npz artifact only (before)"].append(t_npz)
            times["pyfunc model (now)"].append(t_model)
    print(f"{args.runs} runs per variant, store {work / 'mlflow.db'}")
    for name, values in times.items():
        print(
            f"  {name:28s} median {statistics.median(values):.3f} s   mean {statistics.mean(values):.3f} s   "
            f"max {max(values):.3f} s"
        )
    extra = statistics.median(times["pyfunc model (now)"]) - statistics.median(times["npz artifact only (before)"])
    print(f"  per-run overhead of the pyfunc model: {extra:.3f} s (median)")


if __name__ == "__main__":
    main()
