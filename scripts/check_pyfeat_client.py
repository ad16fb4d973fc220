"""py-feat's own client as a consumer of our release (``make pyfeat-check``; optional and slow).

Creates a throwaway virtual environment, installs py-feat there with pip, and runs
``scripts/pyfeat_probe.py`` in it: the release NPZ is loaded through
``feat.plotting.load_face_mesh_viz_model`` (only ``hf_hub_download`` replaced by a function returning
the local path), AU12, AU26 and AU04 are predicted and drawn with ``feat.plotting.plot_face_mesh``,
and the face is checked upright with each AU moving the right way in screen space, as py-feat draws
it. PNGs and ``pyfeat_check.json`` go to ``--out``. Exit status: the probe's (1 if a check fails).

The family releases (issue 46) are checked the same way when given: ``--blendshape-release``
(``releases/blendshapes/bs_to_mesh_pls.npz``) through ``load_blendshape_face_mesh_model`` and
``plot_face_mesh(blendshapes=...)``, ``--emotion-release`` (``releases/emotions/emotion_to_mesh_pls.npz``) through
``load_emotion_face_mesh_model`` and ``plot_face_mesh(emotion=...)`` (``scripts/pyfeat_probe.py`` says what is checked).

Installing: py-feat needs torch and torchvision. pip (not uv) is used on purpose: on this project's
machines pip finds CPU/local torch wheels on disk where uv would download multi-GB CUDA builds. The
default pins (``--torch``) are torch 2.14.1 + torchvision 0.29.1 (torchvision from PyPI does not
import beside torch 2.13.0); the environment is about 6.5 GB and takes minutes to build. Pass
``--venv DIR`` to build it once at DIR and reuse it on later runs (it is then kept).

    python scripts/check_pyfeat_client.py --release release/au_to_mesh_pls.npz --out build/pyfeat-check \
        --blendshape-release releases/blendshapes/bs_to_mesh_pls.npz --emotion-release releases/emotions/emotion_to_mesh_pls.npz
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
PYFEAT = "py-feat==2.1.5"
TORCH = "torch==2.14.1 torchvision==0.29.1"


def _run(cmd: list[str]) -> None:
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def ensure_environment(venv: Path, torch: str, pyfeat: str) -> Path:
    """A venv at ``venv`` with ``torch`` (space-separated pins) and ``pyfeat`` installed; returns its python."""
    python = venv / "bin" / "python"
    if (
        python.exists()
        and subprocess.run([str(python), "-c", "import feat.plotting"], capture_output=True).returncode == 0
    ):
        print(f"reusing the py-feat environment at {venv}", flush=True)
        return python
    _run([sys.executable, "-m", "venv", str(venv)])
    pip = [str(python), "-m", "pip", "install", "--quiet", "--disable-pip-version-check"]
    _run(pip + torch.split())  # first, so py-feat's own torch requirement is already satisfied
    _run(pip + [pyfeat])
    return python


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    parser.add_argument("--release", default="release/au_to_mesh_pls.npz", help="release NPZ to check")
    parser.add_argument("--blendshape-release", default=None, help="blendshape release NPZ to check too")
    parser.add_argument("--emotion-release", default=None, help="emotion release NPZ to check too")
    parser.add_argument("--out", default="build/pyfeat-check", help="folder for the PNGs and pyfeat_check.json")
    parser.add_argument(
        "--venv",
        default=None,
        help="build (or reuse) the py-feat environment here and keep it; default: a temporary one",
    )
    parser.add_argument("--torch", default=TORCH, help="pip requirement(s) for torch, installed before py-feat")
    parser.add_argument("--pyfeat", default=PYFEAT, help="pip requirement for py-feat")
    parser.add_argument("--intensity", type=float, default=1.0, help="AU intensity of the checked predictions")
    args = parser.parse_args(argv)
    release = Path(args.release)
    given = {
        "--release": release,
        "--blendshape-release": args.blendshape_release,
        "--emotion-release": args.emotion_release,
    }
    for flag, path in given.items():
        if path is not None and not Path(path).is_file():
            print(
                f"check_pyfeat_client: release NPZ not found: {path} (run `make demo` or pass {flag})",
                file=sys.stderr,
            )
            return 2
    families = [
        arg
        for flag, path in given.items()
        if flag != "--release" and path is not None
        for arg in (flag, str(Path(path).resolve()))
    ]
    started = time.perf_counter()
    tmp = None if args.venv else tempfile.mkdtemp(prefix="aumesh-pyfeat-")
    venv = Path(args.venv) if args.venv else Path(tmp) / "venv"
    try:
        python = ensure_environment(venv, args.torch, args.pyfeat)
        built = time.perf_counter()
        status = subprocess.run(
            [
                str(python),
                str(HERE / "pyfeat_probe.py"),
                "--release",
                str(release.resolve()),
                "--out",
                str(Path(args.out).resolve()),
                "--intensity",
                str(args.intensity),
                *families,
            ]
        ).returncode
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    print(
        f"environment {built - started:.0f} s, probe {time.perf_counter() - built:.0f} s; "
        f"{'all checks pass' if status == 0 else 'CHECKS FAILED'}; see {args.out}/pyfeat_check.json and its PNGs"
    )
    return status


if __name__ == "__main__":
    sys.exit(main())
