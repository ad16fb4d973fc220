"""Runs INSIDE a py-feat environment (see check_pyfeat_client.py): our release through py-feat's own client.

Loads the release NPZ with ``feat.plotting.load_face_mesh_viz_model`` (only ``hf_hub_download`` is
replaced, by a function returning the local path), predicts neutral, AU12, AU26 and AU04 with
``feat.plotting.predict_face_mesh`` and draws them with ``feat.plotting.plot_face_mesh`` (matplotlib,
py-feat's default view). Screen positions are read back from the drawn axes (matplotlib's own 3-D
projection and data-to-pixel transform), so the checks see the face exactly as py-feat draws it:

* upright: forehead 10 above chin 152, eyes above the mouth, the subject's left eye (263) on the
  screen's right (as in a photograph of the subject);
* AU12 (lip corner puller): both mouth corners 61 / 291 go up and outward;
* AU26 (jaw drop): chin 152 and lower lip 17 go down, the upper lip 0 moves less than the chin;
* AU04 (brow lowerer): the inner brows 107 / 336 go down (and not apart).

Writes PNGs and ``pyfeat_check.json`` to ``--out``; exit status 1 if a check fails.
Only numpy, matplotlib and py-feat are needed here (aumesh is not installed in that environment).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

AUS = ("AU12", "AU26", "AU04")


def screen_xy(ax, mesh: np.ndarray) -> np.ndarray:
    """Pixel positions (478, 2) of the mesh as plot_face_mesh drew it on ``ax`` (x right, y up)."""
    from mpl_toolkits.mplot3d import proj3d

    ax.figure.canvas.draw()  # fixes the view (limits, projection) py-feat set
    # plot_face_mesh maps data (x, y, z) to matplotlib (x, z, y)
    px, py, _ = proj3d.proj_transform(mesh[:, 0], mesh[:, 2], mesh[:, 1], ax.get_proj())
    return ax.transData.transform(np.column_stack([px, py]))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--release", required=True, help="release NPZ (card format)")
    parser.add_argument("--out", required=True, help="folder for the PNGs and pyfeat_check.json")
    parser.add_argument("--intensity", type=float, default=1.0, help="AU intensity of the checked predictions")
    args = parser.parse_args(argv)
    release = str(Path(args.release).resolve())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    import matplotlib

    matplotlib.use("Agg")
    import feat
    import feat.plotting as fp
    import matplotlib.pyplot as plt
    from feat.pretrained import AU_LANDMARK_MAP

    fp.hf_hub_download = lambda *a, **k: release  # the one replacement: no hub, our file
    model = fp.load_face_mesh_viz_model()
    names = AU_LANDMARK_MAP["Feat"]

    def au_vector(au: str | None, value: float) -> np.ndarray:
        v = np.zeros(len(names), dtype=np.float32)
        if au:
            v[names.index(au)] = value
        return v

    # ------------------------------------------------------------- draw, read the screen back
    fig = plt.figure(figsize=(16, 5.2))
    panels = [(None, "neutral (AU = 0)")] + [(au, f"{au} = {args.intensity:g}") for au in AUS]
    neutral = fp.predict_face_mesh(au_vector(None, 0.0), model=model)
    screens = {}  # per panel: (neutral, drawn mesh) projected through that panel's own view
    for k, (au, title) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1, projection="3d")
        vec = au_vector(au, args.intensity)
        fp.plot_face_mesh(au=vec, model=model, ax=ax, mode="tesselation", linewidth=0.3)
        fig.text((k + 0.5) / len(panels), 0.04, title, ha="center", fontsize=11)
        screens[au or "neutral"] = (screen_xy(ax, neutral), screen_xy(ax, fp.predict_face_mesh(vec, model=model)))
    fig.suptitle(
        f"aumesh release through py-feat {feat.__version__}'s own loader and plot_face_mesh "
        "(default view, tessellation)",
        fontsize=11,
    )
    fig.subplots_adjust(left=-0.05, right=1.05, bottom=-0.2, top=1.1, wspace=-0.25)
    fig.savefig(out / "pyfeat_tesselation.png", dpi=110)
    plt.close(fig)

    # the same AUs exaggerated x3, contours over the neutral in grey, to see the direction by eye
    fig = plt.figure(figsize=(12, 5.2))
    for k, au in enumerate(AUS):
        ax = fig.add_subplot(1, len(AUS), k + 1, projection="3d")
        fp.plot_face_mesh(au=au_vector(None, 0), model=model, ax=ax, mode="contours", color="0.6")
        fp.plot_face_mesh(au=au_vector(au, 3 * args.intensity), model=model, ax=ax, mode="contours", color="tab:red")
        fig.text(
            (k + 0.5) / len(AUS),
            0.04,
            f"{au} = {3 * args.intensity:g} (red) over neutral (grey)",
            ha="center",
            fontsize=11,
        )
    fig.suptitle("py-feat plot_face_mesh, contours", fontsize=11)
    fig.subplots_adjust(left=-0.05, right=1.05, bottom=-0.2, top=1.1, wspace=-0.25)
    fig.savefig(out / "pyfeat_contours.png", dpi=110)
    plt.close(fig)

    # ------------------------------------------------------------- the checks, in screen pixels (y up)
    n = screens["neutral"][1]
    iod = float(np.linalg.norm(n[263] - n[33]))
    d = {au: screens[au][1] - screens[au][0] for au in AUS}
    eyes_y, mouth_y = n[[33, 263, 133, 362], 1].mean(), n[[61, 291, 0, 17], 1].mean()
    checks = {
        "upright: forehead 10 above chin 152": bool(n[10, 1] > n[152, 1] + iod),
        "upright: eyes above mouth": bool(eyes_y > mouth_y + 0.3 * iod),
        "subject's left eye 263 on the screen's right": bool(n[263, 0] > n[33, 0] + 0.5 * iod),
        "AU12: both mouth corners up": bool(d["AU12"][61, 1] > 0 and d["AU12"][291, 1] > 0),
        "AU12: mouth corners outward": bool(d["AU12"][61, 0] < 0 < d["AU12"][291, 0]),
        "AU26: chin 152 and lower lip 17 down": bool(d["AU26"][152, 1] < 0 and d["AU26"][17, 1] < 0),
        "AU26: upper lip 0 moves less than the chin": bool(abs(d["AU26"][0, 1]) < abs(d["AU26"][152, 1])),
        "AU04: inner brows 107 and 336 down": bool(d["AU04"][107, 1] < 0 and d["AU04"][336, 1] < 0),
        "AU04: inner brows not apart": bool(d["AU04"][336, 0] - d["AU04"][107, 0] <= 0),
    }
    moves = {
        au: {str(v): [round(float(c), 3) for c in d[au][v]] for v in (61, 291, 152, 17, 0, 107, 336)} for au in AUS
    }
    report = {
        "pyfeat_version": feat.__version__,
        "release": release,
        "model": repr(model),
        "intensity": args.intensity,
        "screen_inter_ocular_px": round(iod, 2),
        "neutral_screen_px": {str(v): [round(float(c), 1) for c in n[v]] for v in (10, 152, 33, 263, 1, 61, 291)},
        "displacement_screen_px (x right, y up)": moves,
        "checks": checks,
        "pngs": [str(out / "pyfeat_tesselation.png"), str(out / "pyfeat_contours.png")],
    }
    (out / "pyfeat_check.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    return 0 if all(checks.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
