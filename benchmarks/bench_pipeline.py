"""End-to-end pipeline benchmark: wall time and peak RSS of each stage on a synthetic CelebV-HQ-scale set.

Generates (or reuses, cached by size under ``--workdir``) a synthetic set of ``--frames``
frames of ``--videos`` videos, composes a params file whose paths all point into the workdir,
then runs ``aumesh prepare``, ``aumesh evaluate`` and ``aumesh release`` as separate
subprocesses, measuring each (see ``benchmarks/_common.py``). With ``--dvc`` it also runs the
same pipeline through ``dvc repro`` in a temporary DVC workspace (``dvc init --no-scm``, this
repo's ``dvc.yaml``; data as an absolute external dependency), timing every stage command with
``/usr/bin/time`` and the whole ``dvc repro`` (hashing, caching of outputs included).

Prints a markdown table; no assertions. Not a timed test.

Examples
--------
    python benchmarks/bench_pipeline.py                         # 344,418 frames / 9,978 videos
    python benchmarks/bench_pipeline.py --frames 20000 --videos 580 --repeats 3
    python benchmarks/bench_pipeline.py --dvc                   # also the `dvc repro` form
    python benchmarks/bench_pipeline.py --src /path/to/other/src  # benchmark another source tree
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (AUMESH, DEFAULT_OUT, REPO, STAGES, compose_params, dir_size, ensure_data,  # noqa: E402
                     environment_note, fmt_table, run_measured, run_stages,
                     write_data_dvc)


def stage_env(src: str | None) -> dict:
    env = dict(os.environ)
    if src:
        env["PYTHONPATH"] = src + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def run_dvc(workdir: Path, data_dir: Path, env: dict) -> dict:
    """``dvc repro`` of this repo's dvc.yaml in a temporary DVC workspace; per-stage /usr/bin/time."""
    ws = workdir / "dvc_ws"
    shutil.rmtree(ws, ignore_errors=True)
    ws.mkdir(parents=True)
    subprocess.run([str(Path(sys.executable).parent / "dvc"), "init", "--no-scm", "-q"], cwd=ws, check=True, env=env)
    (ws / "src").symlink_to(REPO / "src")
    write_data_dvc(ws, data_dir)
    (ws / "promotion.json").write_text(json.dumps({"promoted": None}))
    text = (REPO / "dvc.yaml").read_text()
    for stage in STAGES:
        text = text.replace(f"cmd: aumesh {stage} ", f"cmd: /usr/bin/time -f '%e %M' -o {stage}.time aumesh {stage} ")
    (ws / "dvc.yaml").write_text(text)
    subprocess.run(AUMESH + ["compose-params", "--config-dir", str(REPO / "conf"), "--out", str(ws / "params.yaml"),
                             f"paths.data_dir={data_dir}", f"tracking.tracking_uri=sqlite:///{ws / 'mlflow.db'}"],
                   check=True, stdout=subprocess.DEVNULL, env=env)
    env = dict(env, PATH=str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", ""))
    m = run_measured([str(Path(sys.executable).parent / "dvc"), "repro"], ws, ws / "dvc_repro.log", env, "dvc repro")
    if m.returncode != 0:
        raise RuntimeError(f"dvc repro failed:\n{(ws / 'dvc_repro.log').read_text()[-3000:]}")
    stages = {}
    for stage in STAGES:
        wall, kib = (ws / f"{stage}.time").read_text().split()[-2:]
        stages[stage] = (float(wall), int(kib) / 1024.0)
    return {"total": m, "stages": stages, "workspace": ws}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=344_418)
    ap.add_argument("--videos", type=int, default=9_978)
    ap.add_argument("--workdir", type=Path, default=DEFAULT_OUT, help="cache of synthetic sets and run folders (git-ignored)")
    ap.add_argument("--repeats", type=int, default=1, help="runs of the three stages; medians are printed")
    ap.add_argument("--dvc", action="store_true", help="also run the `dvc repro` form in a temporary DVC workspace")
    ap.add_argument("--src", default=None, help="PYTHONPATH source tree to benchmark instead of the installed aumesh")
    ap.add_argument("--tag", default="", help="suffix of the run folder (keep runs of different sources apart)")
    ap.add_argument("--keep", action="store_true", help="keep the run folder (prepared meshes etc.) afterwards")
    ap.add_argument("--json", type=Path, default=None, help="also write the measurements here")
    args = ap.parse_args(argv)

    env = stage_env(args.src)
    args.workdir.mkdir(parents=True, exist_ok=True)
    data, gen_s = ensure_data(args.workdir, args.frames, args.videos)
    print(environment_note())
    print(f"data: {data} ({dir_size(data) / 2**30:.2f} GiB parquet)" +
          (f", generated in {gen_s:.0f} s" if gen_s is not None else ", reused"))
    run_dir = args.workdir / f"run_{args.frames}{'_' + args.tag if args.tag else ''}"
    params = compose_params(run_dir, data)

    runs = []
    for r in range(args.repeats):
        ms = run_stages(run_dir, params, env)
        runs.append(ms)
        print(f"run {r + 1}: " + ", ".join(f"{m.stage} {m.wall_s:.1f} s / {m.maxrss_mib:,.0f} MiB" for m in ms), flush=True)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    summary = json.loads((run_dir / "prepared" / "summary.json").read_text())
    meshes_gib = (run_dir / "prepared" / "meshes.npy").stat().st_size / 2**30

    rows, record = [], {"frames": args.frames, "videos": args.videos, "env": environment_note(), "stages": {}}
    for i, stage in enumerate(STAGES):
        wall = statistics.median(run[i].wall_s for run in runs)
        rss = statistics.median(run[i].maxrss_mib for run in runs)
        tree = statistics.median(run[i].tree_rss_mib for run in runs)
        rows.append([stage, wall, rss, tree])
        record["stages"][stage] = {"wall_s": wall, "maxrss_mib": rss, "tree_rss_mib": tree,
                                   "wall_all": [run[i].wall_s for run in runs]}
    totals = [sum(m.wall_s for m in run) for run in runs]
    rows.append(["total (3 stages)", statistics.median(totals), max(r[2] for r in rows), max(r[3] for r in rows)])
    print()
    print(f"{args.frames:,} frames, {args.videos:,} videos -> {summary['n_frames']:,} kept frames "
          f"(meshes.npy {meshes_gib:.2f} GiB); median of {args.repeats} run(s)")
    print(fmt_table(["stage", "wall s", "peak RSS MiB (ru_maxrss)", "peak tree RSS MiB (sampled)"], rows))
    print(f"CV R2 = {metrics['r2_mean']:.4f}, MAE = {metrics['mae_mean']:.4f}")
    record["total_wall_s"] = statistics.median(totals)
    record["metrics"] = {k: metrics[k] for k in ("r2_mean", "mae_mean", "vertex_error_mean", "r2_displacement_mean")}

    if args.dvc:
        res = run_dvc(args.workdir, data, env)
        print()
        print("`dvc repro` in a temporary DVC workspace (stage commands under /usr/bin/time):")
        drows = [[s, w, r] for s, (w, r) in res["stages"].items()]
        drows.append(["dvc repro total", res["total"].wall_s, res["total"].maxrss_mib])
        print(fmt_table(["stage", "wall s", "peak RSS MiB"], drows))
        record["dvc"] = {"total_wall_s": res["total"].wall_s, "stages": res["stages"]}
        shutil.rmtree(res["workspace"], ignore_errors=True)
    if args.json:
        args.json.write_text(json.dumps(record, indent=2))
    if not args.keep:
        shutil.rmtree(run_dir, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
