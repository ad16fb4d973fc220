"""Copy the cached objects of outputs marked ``push: false`` in ``dvc.yaml`` into a local DVC remote folder.

``build/prepared`` is ``push: false`` (~57 GB at 10M frames: ``dvc push`` leaves it out, README "Data on object
storage"), but the committed demo remote must hold the demo's (26 MB) so that a fresh clone's ``make demo`` finds every
stage up to date. ``dvc push`` has no switch for that, so ``make refresh-demo`` copies those objects itself: the
remote's layout is the cache's (``files/md5/ab/cdef...``; a folder's ``.dir`` listing and each file's object).

Usage: ``python scripts/push_unpushed.py REMOTE_DIR OUT [OUT ...]`` in the workspace (dvc.lock's paths).
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import yaml


def objects(md5: str, cache: Path) -> list[str]:
    """The object ids of an output: its own, and for a folder (``.dir``) every file's."""
    if not md5.endswith(".dir"):
        return [md5]
    listing = json.loads((cache / md5[:2] / md5[2:]).read_text())
    return [md5, *(entry["md5"] for entry in listing)]


def main(remote: str, outs: list[str]) -> int:
    lock = yaml.safe_load(Path("dvc.lock").read_text())
    recorded = {o["path"]: o["md5"] for s in lock["stages"].values() for o in s.get("outs", [])}
    cache, target = Path(".dvc/cache/files/md5"), Path(remote) / "files" / "md5"
    copied = 0
    for out in outs:
        if out not in recorded:
            print(f"{out}: not an output of dvc.lock. Fix: name a path dvc.lock records (e.g. build/prepared).")
            return 2
        for oid in objects(recorded[out], cache):
            dst = target / oid[:2] / oid[2:]
            if not dst.exists():
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(cache / oid[:2] / oid[2:], dst)
                copied += 1
    print(f"{copied} objects of {', '.join(outs)} copied into {remote}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2:]))
