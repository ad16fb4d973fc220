"""Fit time and agreement: aumesh.model.pls engine vs sklearn's PLSRegression (NIPALS).

Synthetic data shaped like the real problem: 20 AU-like nonnegative features,
3 pose angles and their 60 pose x AU products (83 features); Y has 1434
targets = X @ B + per-target offsets around 300 px + N(0, 1) noise, with B of
low effective rank (geometrically decaying modes) like a face deformation basis.

The engine's time includes the statistics pass over the rows
(``PLSRegression.fit`` = ``CrossProducts`` accumulation + ``fit_stats``).
Prints a table of median times; no assertions.

Examples
--------
    python benchmarks/bench_engine_vs_sklearn.py --n 20000 --components 10 40 83
    python benchmarks/bench_engine_vs_sklearn.py --n 100000 --components 83 --repeats 1
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numpy as np


def make_data(n, n_targets=1434, seed=0, dtype=np.float64):
    """Face-shaped synthetic regression problem.

    Returns
    -------
    X : ndarray of shape (n, 83)
    Y : ndarray of shape (n, n_targets)
    """
    rng = np.random.default_rng(seed)
    au = np.clip(rng.gamma(0.7, 1.0, size=(n, 20)), 0.0, 5.0)
    pose = rng.normal(size=(n, 3)) * np.array([8.0, 15.0, 5.0])
    inter = (pose[:, :, None] * au[:, None, :]).reshape(n, 60)
    X = np.hstack([au, pose, inter])
    # Mesh deformations are low-dimensional: B = U diag(s) V^T with geometrically decaying
    # singular values over 30 modes (products weighted down), plus a small full-rank part.
    rank = 30
    U = rng.normal(size=(83, rank)) * np.r_[np.ones(23), 0.05 * np.ones(60)][:, None]
    V = rng.normal(size=(rank, n_targets)) / np.sqrt(n_targets)
    B = (U * (20.0 * 0.75 ** np.arange(rank))) @ V + 0.01 * rng.normal(size=(83, n_targets))
    Y = X @ B
    Y += rng.normal(300.0, 50.0, size=n_targets)
    Y += rng.normal(size=Y.shape)
    return X.astype(dtype), Y.astype(dtype)


def timed(fn, repeats):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def blas_info():
    try:
        from threadpoolctl import threadpool_info
    except ImportError:  # pragma: no cover
        return "threadpoolctl not installed"
    parts = [
        f"{d.get('internal_api')} ({d.get('user_api')}) threads={d.get('num_threads')} {d.get('version') or ''}".strip()
        for d in threadpool_info()
    ]
    return "; ".join(parts) or "no threadpools found"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, nargs="+", default=[20000, 100000], help="row counts")
    parser.add_argument("--components", type=int, nargs="+", default=[10, 40, 83], help="n_components values")
    parser.add_argument("--repeats", type=int, default=3, help="repeats per timing (median printed)")
    parser.add_argument("--targets", type=int, default=1434, help="number of targets")
    parser.add_argument(
        "--skip-sklearn-above", type=int, default=None, metavar="N", help="do not run sklearn when n > N"
    )
    parser.add_argument("--sklearn-repeats", type=int, default=None, help="repeats for sklearn (default --repeats)")
    parser.add_argument("--tight", action="store_true", help="also time sklearn at tol=1e-14 (n <= 20000 only)")
    parser.add_argument(
        "--blas-threads", type=int, default=None, help="limit BLAS threads for both engines (default: library default)"
    )
    args = parser.parse_args(argv)
    if args.blas_threads is not None:
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=args.blas_threads, user_api="blas"):
            return run(args)
    return run(args)


def run(args):

    from sklearn import __version__ as sk_version
    from sklearn.cross_decomposition import PLSRegression as SkPLS

    from aumesh.model.pls import PLSRegression

    sk_repeats = args.sklearn_repeats or args.repeats
    print(f"python {platform.python_version()}, numpy {np.__version__}, scikit-learn {sk_version}")
    print(f"BLAS: {blas_info()}")
    print(f"cpus={os.cpu_count()}, load average at start={os.getloadavg()[0]:.2f} (timings are wall-clock)")
    # warm-up (BLAS thread pools, first-call overheads) outside the timings
    Xw, Yw = make_data(500, args.targets, seed=1)
    PLSRegression(n_components=2).fit(Xw, Yw)
    SkPLS(n_components=2).fit(Xw, Yw)
    print(f"targets={args.targets}, features=83, engine repeats={args.repeats}, sklearn repeats={sk_repeats}")
    header = (
        f"{'n':>7} {'comps':>5} {'engine s':>9} {'sklearn s':>10} {'ratio':>7} "
        f"{'max|dcoef|/max|coef|':>21} {'sk tol=1e-14 s':>15} {'rel diff (tight)':>17}"
    )
    print(header)
    print("-" * len(header))
    for n in args.n:
        X, Y = make_data(n, args.targets)
        for k in args.components:
            t_eng, eng = timed(lambda k=k, X=X, Y=Y: PLSRegression(n_components=k, scale=True).fit(X, Y), args.repeats)
            row = f"{n:>7} {k:>5} {t_eng:>9.3f} "
            if args.skip_sklearn_above is not None and n > args.skip_sklearn_above:
                row += f"{'skipped':>10} {'':>7} {'':>21}"
            else:
                t_sk, sk = timed(lambda k=k, X=X, Y=Y: SkPLS(n_components=k, scale=True).fit(X, Y), sk_repeats)
                diff = np.abs(eng.coef_ - sk.coef_).max() / np.abs(sk.coef_).max()
                row += f"{t_sk:>10.2f} {t_sk / t_eng:>7.1f} {diff:>21.2e}"
            if args.tight and n <= 20000:
                t_tight, tight = timed(
                    lambda k=k, X=X, Y=Y: SkPLS(n_components=k, scale=True, tol=1e-14, max_iter=10000).fit(X, Y), 1
                )
                diff_t = np.abs(eng.coef_ - tight.coef_).max() / np.abs(tight.coef_).max()
                row += f" {t_tight:>15.2f} {diff_t:>17.2e}"
            print(row, flush=True)
    print(f"load average at end={os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
