"""The 344k-frame pipeline reading its tables from a local S3 server (moto) against reading them from disk.

Starts moto's S3-compatible server (``moto_server`` on 127.0.0.1, a process of its own; it keeps the objects in
spooled temporary files), uploads the synthetic tables of ``bench_pipeline.py`` (``_common.ensure_data``: 344,418
frames / 9,978 videos, 14 clean parquet tables; untimed), then runs the four stages, each a measured subprocess
(``_common.run_stages``: wall time and peak RSS), once with ``paths.data_dir`` the local folder and once
``s3://bench/tables``, side by side. From disk the clean tables are read in place; from S3 ingest copies them once
into ``build/ingested`` (prepare's passes then read local disk), which is what the difference measures.

Then the time to the first line on stderr and the exit code of ``aumesh ingest`` for each object-store failure (no
bucket, no such prefix, no credentials, the endpoint down), median of ``--repeats`` runs.

Prints markdown tables; no assertions. Run it alone (other work on the machine slows wall times: the 1-minute load
average is printed before and after).

Examples
--------
    python benchmarks/bench_s3_tables.py                                   # 344k frames
    python benchmarks/bench_s3_tables.py --frames 20000 --videos 580       # quick
    python benchmarks/bench_s3_tables.py --data /path/to/data_344418_9978  # reuse another checkout's tables
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (  # noqa: E402
    AUMESH,
    DEFAULT_OUT,
    compose_params,
    dir_size,
    ensure_data,
    environment_note,
    fmt_table,
    load,
    run_stages,
)

BIN = Path(sys.executable).parent
BUCKET = "bench"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def aws_env(endpoint: str, empty: Path, credentials: bool = True) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("AWS_")}
    env |= {
        "AWS_ENDPOINT_URL": endpoint,
        "AWS_DEFAULT_REGION": "us-east-1",
        "AWS_EC2_METADATA_DISABLED": "true",
        "AWS_SHARED_CREDENTIALS_FILE": str(empty),
        "AWS_CONFIG_FILE": str(empty),
    }
    if credentials:
        env |= {"AWS_ACCESS_KEY_ID": "bench", "AWS_SECRET_ACCESS_KEY": "bench-secret"}
    return env


def start_moto(folder: Path) -> tuple[subprocess.Popen, str]:
    port = _free_port()
    log = open(folder / "moto.log", "ab")
    proc = subprocess.Popen([str(BIN / "moto_server"), "-H", "127.0.0.1", "-p", str(port)], stdout=log, stderr=log)
    deadline = time.monotonic() + 60
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return proc, f"http://127.0.0.1:{port}"
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("moto_server did not start") from None
            time.sleep(0.1)


def upload(endpoint: str, data: Path, prefix: str) -> tuple[str, float]:
    import s3fs

    fs = s3fs.S3FileSystem(key="bench", secret="bench-secret", endpoint_url=endpoint, skip_instance_cache=True)
    if not fs.exists(BUCKET):
        fs.mkdir(BUCKET)
    t0 = time.perf_counter()
    for p in sorted(data.glob("*")):
        if p.is_file():
            fs.put_file(str(p), f"{BUCKET}/{prefix}/{p.name}")
    return f"s3://{BUCKET}/{prefix}", time.perf_counter() - t0


def with_data_dir(params: Path, data_dir: str, out: Path) -> Path:
    doc = yaml.safe_load(params.read_text())
    doc["paths"]["data_dir"] = data_dir
    out.write_text(yaml.safe_dump(doc, sort_keys=False))
    return out


def first_line_seconds(params: Path, cwd: Path, env: dict) -> tuple[float, int, str]:
    """Seconds from the start of ``aumesh ingest`` to its first line on stderr, its exit code and that line."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        AUMESH + ["ingest", "--params", str(params)], cwd=cwd, env=env, stderr=subprocess.PIPE, text=True
    )
    assert proc.stderr is not None
    line = proc.stderr.readline()
    seconds = time.perf_counter() - t0
    rest = proc.stderr.read()
    proc.wait()
    return seconds, proc.returncode, (line or rest).strip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=344_418)
    ap.add_argument("--videos", type=int, default=9_978)
    ap.add_argument("--data", type=Path, default=None, help="an existing tables folder (default: generated, cached)")
    ap.add_argument("--workdir", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--repeats", type=int, default=3, help="runs of each failure case (median)")
    args = ap.parse_args()

    data = args.data or ensure_data(args.workdir, args.frames, args.videos)[0]
    run_root = Path(tempfile.mkdtemp(prefix="bench_s3_", dir=args.workdir if args.workdir.exists() else None))
    empty = run_root / "empty-aws-config"
    empty.touch()
    print(f"# tables on S3 (moto) vs disk: {data} ({dir_size(data) / 2**30:.2f} GiB)\n")
    print(environment_note() + f" | load before: {load()}\n")
    moto, endpoint = start_moto(run_root)
    try:
        url, upload_s = upload(endpoint, data, "tables")
        print(f"upload to moto (untimed in the table): {upload_s:.1f} s\n")
        results = {}
        for name, where in (("disk", str(data.resolve())), ("s3", url)):
            run_dir = run_root / name
            params = compose_params(run_dir, data.resolve())
            with_data_dir(params, where, params)
            results[name] = run_stages(run_dir, params, aws_env(endpoint, empty))
            results[name + "_out"] = {d: dir_size(run_dir / d) for d in ("ingested", "prepared", "model")}
        rows = []
        for i, m in enumerate(results["disk"]):
            s = results["s3"][i]
            rows.append([m.stage, m.wall_s, s.wall_s, m.maxrss_mib, s.maxrss_mib])
        rows.append(
            [
                "total",
                sum(m.wall_s for m in results["disk"]),
                sum(m.wall_s for m in results["s3"]),
                max(m.maxrss_mib for m in results["disk"]),
                max(m.maxrss_mib for m in results["s3"]),
            ]
        )
        print(fmt_table(["stage", "disk wall s", "S3 wall s", "disk peak RSS MiB", "S3 peak RSS MiB"], rows))
        print()
        print(
            fmt_table(
                ["output", "disk MiB", "S3 MiB"],
                [
                    [d, results["disk_out"][d] / 2**20, results["s3_out"][d] / 2**20]
                    for d in ("ingested", "prepared", "model")
                ],
            )
        )
        print()

        # each failure: (data_dir, credentials, endpoint)
        down = f"http://127.0.0.1:{_free_port()}"
        cases = {
            "no bucket": ("s3://no-such-bucket/tables", True, endpoint),
            "no such prefix": (f"s3://{BUCKET}/no-such-prefix", True, endpoint),
            "no credentials": (url, False, endpoint),
            "endpoint down": (url, True, down),
        }
        fail_dir = run_root / "failures"
        fail_dir.mkdir()
        base = compose_params(fail_dir, data.resolve())
        rows = []
        for case, (where, credentials, ep) in cases.items():
            params = with_data_dir(base, where, fail_dir / f"params-{case.replace(' ', '_')}.yaml")
            runs = [first_line_seconds(params, fail_dir, aws_env(ep, empty, credentials)) for _ in range(args.repeats)]
            rows.append([case, statistics.median(r[0] for r in runs), str(runs[-1][1]), runs[-1][2][:150]])
        print(fmt_table(["failure", "s to first line (median)", "exit", "the line"], rows))
        print(f"\nload after: {load()}")
    finally:
        moto.terminate()
        moto.wait(timeout=30)
        shutil.rmtree(run_root, ignore_errors=True)


if __name__ == "__main__":
    main()
