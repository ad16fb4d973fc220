"""What the AU identification screen adds to the evaluate stage at CelebV-HQ scale (issue 43: "under 1 s").

The screen needs the within-video moments of the 20 AUs with the mesh over every frame
(``aumesh.model.statistics.within_statistics``, from the per-video sums pass A already wrote to disk) and then
``aumesh.model.eiv.identification_screen`` (one 20 x 20 eigen-decomposition, 40 grid points). Neither reads a row of
the meshes: the cost depends on the number of videos, not frames. This builds design statistics of the reference's
shape (344,418 frames, 9,978 videos, 83-column design, 1434 targets; the per-video sums as on-disk ``.npy`` rows, as the
stage keeps them), and times, side by side in one process and in turn:

* ``screen``: within_statistics(AU columns) + identification_screen, what the stage adds;
* ``fold stats``: the configuration statistics evaluate derives per fold (default configuration, 3 folds), an
  existing step of the same stage, for scale.

Prints medians over ``--repeats`` and their ratio. Usage: ``.venv/bin/python benchmarks/bench_identification.py``.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from aumesh.core.io import NpyRows
from aumesh.core.schema import AU_COLUMNS, N_TARGETS, feature_columns
from aumesh.model import eiv
from aumesh.model.cross_products import CrossProducts
from aumesh.model.pass_design import FULL_DESIGN
from aumesh.model.statistics import DesignStatistics, fold_configuration_statistics, within_statistics


def design_of_reference_shape(folder: Path, n_frames: int, n_videos: int, seed: int = 0) -> tuple:
    """Design statistics with the reference's shapes and plausible values (not a real fit: timing only)."""
    rng = np.random.default_rng(seed)
    p, q, k = len(FULL_DESIGN), N_TARGETS, 3
    count = np.full(n_videos, n_frames // n_videos)
    count[: n_frames - count.sum()] += 1
    video_fold = np.arange(n_videos) % k
    sum_x = rng.normal(size=(n_videos, p)) * count[:, None] * 0.1
    sum_y = rng.normal(size=(n_videos, q)) * count[:, None]
    for name, arr in (("sx", sum_x), ("sy", sum_y), ("lx", sum_x * 0.1)):
        np.save(folder / f"{name}.npy", arr)
    folds = []
    for f in range(k):
        cp = CrossProducts(p, q, x_shift=np.zeros(p), y_shift=np.zeros(q))
        m = video_fold == f
        cp.n = int(count[m].sum())
        A = rng.normal(size=(p, p))
        cp.xtx = A @ A.T * cp.n + np.diag(np.full(p, cp.n))
        cp.xty = rng.normal(size=(p, q)) * cp.n
        cp.yty_diag = np.full(q, 10.0 * cp.n)
        cp.sum_x, cp.sum_y = sum_x[m].sum(0), sum_y[m].sum(0)
        folds.append(cp)
    design = DesignStatistics(
        folds=folds,
        video_fold=video_fold,
        video_count=count,
        video_sum_x=NpyRows(folder / "sx.npy"),
        video_sum_y=NpyRows(folder / "sy.npy"),
    )
    neutral = NpyRows(folder / "sy.npy")
    neutral_design = np.load(folder / "lx.npy")
    return design, neutral, neutral_design


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=344_418)
    parser.add_argument("--videos", type=int, default=9_978)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    columns = feature_columns(True, True)
    with tempfile.TemporaryDirectory() as tmp:
        design, neutral, neutral_design = design_of_reference_shape(Path(tmp), args.frames, args.videos)

        def screen() -> None:
            au = within_statistics(design, list(AU_COLUMNS))
            eiv.identification_screen(au.cxx / au.n, au.cxy / au.n)

        def fold_stats() -> None:
            for f in range(3):
                fold_configuration_statistics(design, f, columns, "absolute", neutral, neutral_design)

        times: dict[str, list[float]] = {"screen": [], "fold stats": []}
        for _ in range(args.repeats):  # in turn, so load on the shared machine falls on both alike
            for name, fn in (("screen", screen), ("fold stats", fold_stats)):
                t0 = time.perf_counter()
                fn()
                times[name].append(time.perf_counter() - t0)
    med = {k: statistics.median(v) for k, v in times.items()}
    print(f"{args.frames:,} frames, {args.videos:,} videos, {args.repeats} repeats in turn (seconds)")
    for name, values in times.items():
        print(f"  {name:<11} median {med[name]:.3f}  min {min(values):.3f}  max {max(values):.3f}")
    print(f"  screen / fold stats = {med['screen'] / med['fold stats']:.2f}")


if __name__ == "__main__":
    main()
