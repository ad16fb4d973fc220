"""``aumesh ingest`` against the number of input files: the same py-feat rows as one CSV and as one CSV per video.

py-feat's ``detect(video, save=...)`` writes one CSV per video; CelebV-HQ so exported is ~35,000 files. For each
``--files`` N the benchmark generates (cached under ``--workdir``) N videos of ``--frames-per-video`` frames with
MPDetector's full column set (~2,045 columns, ``aumesh.synthetic.pyfeat``; no-face runs and background faces as py-feat
writes them) as N CSVs (``videos_per_file=1``) and the same rows as one CSV (their bodies joined), then runs
``python -m aumesh ingest --params FILE`` on each in a child process and prints its wall time and peak RSS
(``ru_maxrss`` of the child as ``/usr/bin/time`` reports it, :func:`_common.run_measured`), and the ratios of the
per-video run to the one-file run. Memory should be flat in N and the time close to the one-file read.

``--src`` runs another source tree (e.g. ``git worktree add /tmp/old 4c2936e`` then ``--src /tmp/old/src``): the
same data and the same params keys, that tree's code. No assertions.

Files of fewer than ``aumesh.pipeline.ingest.UNIT_CHECK_ROWS`` faces are judged by the unit guard together, by
detector and units (a one-frame file's depth/height is a single draw), so every generated video is kept.

Examples
--------
    python benchmarks/bench_ingest_files.py                              # N = 100, 1000, 4000
    python benchmarks/bench_ingest_files.py --files 100 1000 --src /tmp/old/src
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    AUMESH,
    DEFAULT_OUT,
    compose_params,
    dir_size,
    environment_note,
    fmt_table,
    load,
    run_measured,
    source_env,
)


def ensure_files(workdir: Path, n_videos: int, frames_per_video: int) -> tuple[Path, Path, dict]:
    """(one-CSV folder, per-video folder, generation summary) of ``n_videos`` videos, generated once and cached.

    The per-video CSVs are written first; the one CSV is their header once and their rows, byte for byte, in
    order."""
    from aumesh.synthetic.pyfeat import write_pyfeat_tables
    from aumesh.synthetic.tables import SynthSpec

    root = workdir / f"files_{n_videos}x{frames_per_video}"
    summary_file = root / "summary.json"
    if not summary_file.exists():
        shutil.rmtree(root, ignore_errors=True)
        spec = SynthSpec(n_frames=n_videos * frames_per_video, n_videos=n_videos)
        t0 = time.perf_counter()
        write_pyfeat_tables(root / "per_video", spec, videos_per_file=1)
        files = sorted((root / "per_video").glob("*.csv"))
        (root / "one").mkdir()
        with open(root / "one" / "clip_0000.csv", "wb") as out:
            for k, path in enumerate(files):
                with open(path, "rb") as fh:
                    header = fh.readline()
                    if k == 0:
                        out.write(header)
                    shutil.copyfileobj(fh, out)
        made = {
            "n_rows": sum(1 for _ in open(root / "one" / "clip_0000.csv", "rb")) - 1,
            "n_files": len(files),
            "generated_s": time.perf_counter() - t0,
        }
        summary_file.write_text(json.dumps(made))
    return root / "one", root / "per_video", json.loads(summary_file.read_text())


def ingest(run_dir: Path, data: Path, src: str | None):
    """One measured ``aumesh ingest`` of ``data`` in ``run_dir``, and its manifest's counts."""
    shutil.rmtree(run_dir, ignore_errors=True)
    params = compose_params(run_dir, data, src=src)
    m = run_measured(
        AUMESH + ["ingest", "--params", str(params)], run_dir, run_dir / "ingest.log", source_env(src), "ingest"
    )
    if m.returncode:
        raise RuntimeError(
            f"ingest of {data} failed (exit {m.returncode}):\n{(run_dir / 'ingest.log').read_text()[-2000:]}"
        )
    counts = json.loads((run_dir / "ingested" / "manifest.json").read_text())["counts"]
    return m, counts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--files", type=int, nargs="+", default=[100, 1000, 4000], help="videos (= per-video CSVs)")
    ap.add_argument("--frames-per-video", type=int, default=2)
    ap.add_argument("--workdir", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--src", default=None, help="another source tree's src/ to run (PYTHONPATH)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    args.workdir.mkdir(parents=True, exist_ok=True)
    print(environment_note())
    print(f"source tree: {args.src or 'this checkout'}", flush=True)
    rows, record = [], []
    for n in args.files:
        one, many, made = ensure_files(args.workdir, n, args.frames_per_video)
        results = {}
        for name, data in (("1 CSV", one), (f"{n} CSVs", many)):
            m, counts = ingest(args.workdir / "files_run", data, args.src)
            results[name] = (m, counts)
            print(
                f"N={n} {name}: {m.wall_s:.1f} s, peak RSS {m.maxrss_mib:,.0f} MiB ({dir_size(data) / 2**20:.0f} MiB of "
                f"CSV, {made['n_rows']:,} rows) | load {load()}",
                flush=True,
            )
        (m1, c1), (mn, cn) = results.values()
        per_source = ("tables_in", "identity_labels")  # by source: N files have N times the one file's
        same = {k: v for k, v in c1.items() if k not in per_source} == {
            k: v for k, v in cn.items() if k not in per_source
        }
        rows.append(
            [
                made.get("n_files", n),
                made["n_rows"],
                m1.wall_s,
                mn.wall_s,
                f"{mn.wall_s / m1.wall_s:.2f}",
                m1.maxrss_mib,
                mn.maxrss_mib,
                f"{mn.maxrss_mib / m1.maxrss_mib:.2f}",
                "yes" if same else "NO",
            ]
        )
        record.append(
            {
                "files": made.get("n_files", n),
                "rows": made["n_rows"],
                "one": m1.__dict__,
                "per_video": mn.__dict__,
                "same": same,
            }
        )
    shutil.rmtree(args.workdir / "files_run", ignore_errors=True)
    print()
    print(
        fmt_table(
            [
                "N files",
                "rows",
                "1 CSV s",
                "N CSVs s",
                "time ratio",
                "1 CSV MiB",
                "N CSVs MiB",
                "RSS ratio",
                "same counts",
            ],
            rows,
        )
    )
    if args.json:
        args.json.write_text(json.dumps(record, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
