"""``aumesh predict`` against the number of table rows: peak RSS and wall time (issue 44: ~23 KB a row held).

A table of input columns (the 20 AUs, Pitch, Yaw, Roll; py-feat's ``input`` and ``frame`` keys; every 10th row a
frame without a face, all NaN) as CSV (~160 bytes a row, the issue's 162 MB for 1M rows) is predicted to an NPZ
at each size. Each run is ``python -m aumesh predict`` in a child of a small measuring process: the peak RSS is that
process's ``resource.getrusage(RUSAGE_CHILDREN).ru_maxrss`` (a fresh interpreter, so the child's high-water mark does
not start at this script's; see ``_common.py``), the time its wall clock. Flat memory in rows is the claim; the
figures are printed, never asserted.

    .venv/bin/python benchmarks/bench_predict_rows.py                           # 10k, 100k, 300k rows
    .venv/bin/python benchmarks/bench_predict_rows.py --rows 10000 100000 --src /tmp/old-predict/src --tag 4c2936e

``--src`` runs another source tree (``git worktree add /tmp/old-predict 4c2936e``) with this venv's python. Tables are
cached under ``benchmarks/out/predict_rows/`` (written a block at a time by a child process), outputs deleted after
each run.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "benchmarks" / "out" / "predict_rows"

# Runs `aumesh predict` as its child and prints that child's peak RSS (KiB) and wall time as JSON.
MEASURE = r"""
import json, resource, subprocess, sys, time
t0 = time.perf_counter()
rc = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL).returncode
wall = time.perf_counter() - t0
print(json.dumps({"rc": rc, "wall_s": wall, "maxrss_kib": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}))
"""

# Writes the table a block of rows at a time (pyarrow's CSV writer): memory flat while the table grows.
WRITE = r"""
import sys
import numpy as np, pyarrow as pa, pyarrow.csv as pacsv
AUS = ["AU01","AU02","AU04","AU05","AU06","AU07","AU09","AU10","AU11","AU12","AU14","AU15","AU17","AU20","AU23",
       "AU24","AU25","AU26","AU28","AU43"]
path, n = sys.argv[1], int(sys.argv[2])
rng = np.random.default_rng(0)
writer = None
for start in range(0, n, 50_000):
    k = min(50_000, n - start)
    rows = np.arange(start, start + k)
    cols = {a: np.round(rng.uniform(0.0, 0.6, k), 4) for a in AUS}
    cols |= {p: np.round(rng.uniform(-0.2, 0.2, k), 4) for p in ("Pitch", "Yaw", "Roll")}
    blank = rows % 10 == 9  # py-feat's row for a frame without a face
    for v in cols.values():
        v[blank] = np.nan
    cols["input"] = np.array([f"clips/video_{r // 500:05d}.mp4" for r in rows])
    cols["frame"] = rows % 500
    table = pa.table(cols)
    writer = writer or pacsv.CSVWriter(path, table.schema)
    writer.write_table(table)
writer.close()
"""


def table(n_rows: int, out_dir: Path) -> Path:
    path = out_dir / f"inputs_{n_rows}.csv"
    if not path.exists():
        out_dir.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.csv")
        subprocess.run([sys.executable, "-c", WRITE, str(tmp), str(n_rows)], check=True)
        tmp.rename(path)
    return path


def release(out_dir: Path) -> Path:
    """A release NPZ (the synthetic-truth map of ``aumesh.synthetic.truth``, as the tests' releases)."""
    path = out_dir / "release.npz"
    if not path.exists():
        code = (
            "import sys, numpy as np\n"
            "from aumesh.geometry import face\nfrom aumesh.synthetic import truth\n"
            "tpl = 120.0 * face.canonical_template() * np.array([1.0, -1.0, -1.0]) + np.array([320.0, 240.0, 10.0])\n"
            "np.savez(sys.argv[1], **truth.synthetic_release_arrays(tpl))\n"
        )
        subprocess.run([sys.executable, "-c", code, str(path)], check=True, env=_env(REPO / "src"))
    return path


def _env(src: Path) -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(src))


def measure(n_rows: int, src: Path, out_dir: Path, repeats: int) -> dict[str, float]:
    csv = table(n_rows, out_dir)
    npz = out_dir / f"meshes_{n_rows}.npz"
    runs = []
    for _ in range(repeats):
        cmd = [
            sys.executable,
            "-m",
            "aumesh",
            "predict",
            str(csv),
            "--release",
            str(release(out_dir)),
            "--out",
            str(npz),
        ]
        done = subprocess.run([sys.executable, "-c", MEASURE, *cmd], env=_env(src), capture_output=True, text=True)
        result = json.loads(done.stdout.strip().splitlines()[-1])
        if result["rc"] != 0:
            raise SystemExit(f"aumesh predict failed at {n_rows:,} rows (exit {result['rc']})")
        runs.append(result)
        npz.unlink(missing_ok=True)
    return {
        "rows": n_rows,
        "csv_mb": csv.stat().st_size / 1e6,
        "wall_s": statistics.median(r["wall_s"] for r in runs),
        "peak_rss_mib": statistics.median(r["maxrss_kib"] for r in runs) / 1024,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rows", type=int, nargs="+", default=[10_000, 100_000, 300_000])
    parser.add_argument("--src", type=Path, default=REPO / "src", help="the source tree to run (default: this one)")
    parser.add_argument("--tag", default="this tree")
    parser.add_argument("--repeats", type=int, default=1, help="runs per size (medians)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args()
    print(f"aumesh predict, {args.tag} ({args.src}); medians of {args.repeats}")
    print(f"{'rows':>9} {'CSV MB':>8} {'wall s':>8} {'peak RSS MiB':>13} {'KiB/row':>8}")
    for n in args.rows:
        m = measure(n, args.src, args.out, args.repeats)
        per_row = m["peak_rss_mib"] * 1024 / n
        print(
            f"{n:>9,} {m['csv_mb']:>8.1f} {m['wall_s']:>8.2f} {m['peak_rss_mib']:>13,.0f} {per_row:>8.2f}", flush=True
        )


if __name__ == "__main__":
    main()
