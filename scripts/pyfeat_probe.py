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

The family releases (issue 46; ``--blendshape-release`` / ``--emotion-release``, each optional) are loaded the same
way through ``feat.plotting.load_blendshape_face_mesh_model`` / ``load_emotion_face_mesh_model`` (py-feat's
``_load_pls_feat_to_mesh_from_hub``: its ``feature_columns`` check, ``feature_p99``, ``unsupported_features``), predicted
with ``predict_face_mesh_from_features`` (a dict by name, and a Detectorv2-named DataFrame for emotions) and drawn with
``plot_face_mesh(blendshapes=...)`` / ``plot_face_mesh(emotion=...)``, which clip each input to its ``feature_p99``:

* upright, as for the AUs (blendshapes at 0; emotions at neutral = 1, a probability vector);
* jawOpen: chin 152 and lower lip 17 down, the upper lip 0 moving less than the chin; mouthSmileLeft: the subject's
  left mouth corner 291 up, at least twice as far as the right one 61 (one-sided); browInnerUp: inner brows 107 / 336 up;
* happiness (against neutral): both mouth corners 61 / 291 up; surprise: inner brows up and chin 152 down.

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
#: family -> (py-feat's feature key, loader, plot_face_mesh argument, the baseline input, the checked inputs)
FAMILIES = {
    "blendshapes": (
        "blendshape",
        "load_blendshape_face_mesh_model",
        "blendshapes",
        None,
        ("jawOpen", "mouthSmileLeft", "browInnerUp"),
    ),
    "emotions": ("emotion", "load_emotion_face_mesh_model", "emotion", "neutral", ("happiness", "surprise")),
}


def screen_xy(ax, mesh: np.ndarray) -> np.ndarray:
    """Pixel positions (478, 2) of the mesh as plot_face_mesh drew it on ``ax`` (x right, y up)."""
    from mpl_toolkits.mplot3d import proj3d

    ax.figure.canvas.draw()  # fixes the view (limits, projection) py-feat set
    # plot_face_mesh maps data (x, y, z) to matplotlib (x, z, y)
    px, py, _ = proj3d.proj_transform(mesh[:, 0], mesh[:, 2], mesh[:, 1], ax.get_proj())
    return ax.transData.transform(np.column_stack([px, py]))


def probe_au(fp, feat, plt, release: str, out: Path, intensity: float) -> dict:
    """The AU release through ``load_face_mesh_viz_model`` and ``plot_face_mesh(au=...)``: its report (``checks``)."""
    from feat.pretrained import AU_LANDMARK_MAP

    model = fp.load_face_mesh_viz_model()
    names = AU_LANDMARK_MAP["Feat"]

    def au_vector(au: str | None, value: float) -> np.ndarray:
        v = np.zeros(len(names), dtype=np.float32)
        if au:
            v[names.index(au)] = value
        return v

    # ------------------------------------------------------------- draw, read the screen back
    fig = plt.figure(figsize=(16, 5.2))
    panels = [(None, "neutral (AU = 0)")] + [(au, f"{au} = {intensity:g}") for au in AUS]
    neutral = fp.predict_face_mesh(au_vector(None, 0.0), model=model)
    screens = {}  # per panel: (neutral, drawn mesh) projected through that panel's own view
    for k, (au, title) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1, projection="3d")
        vec = au_vector(au, intensity)
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
        fp.plot_face_mesh(au=au_vector(au, 3 * intensity), model=model, ax=ax, mode="contours", color="tab:red")
        fig.text(
            (k + 0.5) / len(AUS),
            0.04,
            f"{au} = {3 * intensity:g} (red) over neutral (grey)",
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
    return {
        "release": release,
        "model": repr(model),
        "intensity": intensity,
        "screen_inter_ocular_px": round(iod, 2),
        "neutral_screen_px": {str(v): [round(float(c), 1) for c in n[v]] for v in (10, 152, 33, 263, 1, 61, 291)},
        "displacement_screen_px (x right, y up)": moves,
        "checks": checks,
        "pngs": [str(out / "pyfeat_tesselation.png"), str(out / "pyfeat_contours.png")],
    }


def probe_family(fp, plt, family: str, release: str, out: Path) -> dict:
    """A family release through py-feat's own loader, ``predict_face_mesh_from_features`` and ``plot_face_mesh``:
    its report (``checks``). Inputs are given at 1.0 by name; py-feat clips them to the release's ``feature_p99``."""
    import warnings

    import pandas as pd

    feature, loader, argument, base, checked = FAMILIES[family]
    model = getattr(fp, loader)()  # _load_pls_feat_to_mesh_from_hub: feature_columns must equal py-feat's list
    baseline = {base: 1.0} if base else {}
    checks = {
        "loaded as a PLSFeatMeshModel": isinstance(model, fp.PLSFeatMeshModel),
        "feature_p99 read (feature_max)": model.feature_max is not None,
    }

    def mesh_of(feats: dict) -> np.ndarray:
        return fp.predict_face_mesh_from_features(feats, model=model)

    # ------------------------------------------------------------- draw with plot_face_mesh, read the screen back
    panels = [(None, f"{base or 'all inputs'} = {1 if base else 0}")] + [
        (f, f"{f} = 1 (clipped to p99)") for f in checked
    ]
    fig = plt.figure(figsize=(4 * len(panels), 5.2))
    neutral = mesh_of(baseline)
    screens = {}
    for k, (name, title) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1, projection="3d")
        feats = {name: 1.0} if name else baseline
        fp.plot_face_mesh(**{argument: feats}, model=model, ax=ax, mode="tesselation", linewidth=0.3)
        fig.text((k + 0.5) / len(panels), 0.04, title, ha="center", fontsize=11)
        screens[name or "base"] = (screen_xy(ax, neutral), screen_xy(ax, mesh_of(feats)))
    fig.suptitle(
        f"aumesh {family} release through py-feat's {loader} and plot_face_mesh({argument}=...) (default view)",
        fontsize=11,
    )
    fig.subplots_adjust(left=-0.05, right=1.05, bottom=-0.2, top=1.1, wspace=-0.25)
    pngs = [out / f"pyfeat_{family}_tesselation.png", out / f"pyfeat_{family}_contours.png"]
    fig.savefig(pngs[0], dpi=110)
    plt.close(fig)
    # contours, x3 over the baseline in grey (plot_face_mesh(mesh=...): the clip would stop a larger input)
    fig = plt.figure(figsize=(4 * len(checked), 5.2))
    for k, name in enumerate(checked):
        ax = fig.add_subplot(1, len(checked), k + 1, projection="3d")
        fp.plot_face_mesh(mesh=neutral, ax=ax, mode="contours", color="0.6")
        fp.plot_face_mesh(mesh=neutral + 3 * (mesh_of({name: 1.0}) - neutral), ax=ax, mode="contours", color="tab:red")
        fig.text(
            (k + 0.5) / len(checked),
            0.04,
            f"{name}: 3x its p99 motion (red) over {base or 'zero'} (grey)",
            ha="center",
            fontsize=10,
        )
    fig.suptitle(f"py-feat plot_face_mesh, contours ({family})", fontsize=11)
    fig.subplots_adjust(left=-0.05, right=1.05, bottom=-0.2, top=1.1, wspace=-0.25)
    fig.savefig(pngs[1], dpi=110)
    plt.close(fig)

    n = screens["base"][1]
    iod = float(np.linalg.norm(n[263] - n[33]))
    d = {name: screens[name][1] - screens[name][0] for name in checked}
    eyes_y, mouth_y = n[[33, 263, 133, 362], 1].mean(), n[[61, 291, 0, 17], 1].mean()
    checks.update(
        {
            "upright: forehead 10 above chin 152": bool(n[10, 1] > n[152, 1] + iod),
            "upright: eyes above mouth": bool(eyes_y > mouth_y + 0.3 * iod),
            "subject's left eye 263 on the screen's right": bool(n[263, 0] > n[33, 0] + 0.5 * iod),
        }
    )
    if family == "blendshapes":
        checks.update(
            {
                "jawOpen: chin 152 and lower lip 17 down": bool(d["jawOpen"][152, 1] < 0 and d["jawOpen"][17, 1] < 0),
                "jawOpen: upper lip 0 moves less than the chin": bool(
                    abs(d["jawOpen"][0, 1]) < abs(d["jawOpen"][152, 1])
                ),
                # one-sided: the subject's left corner (on the screen's right) rises at least twice the right one
                "mouthSmileLeft: the subject's left corner 291 up, at least twice the right 61": bool(
                    d["mouthSmileLeft"][291, 1] > 0
                    and d["mouthSmileLeft"][291, 1] > 2 * abs(d["mouthSmileLeft"][61, 1])
                ),
                "browInnerUp: inner brows 107 and 336 up": bool(
                    d["browInnerUp"][107, 1] > 0 and d["browInnerUp"][336, 1] > 0
                ),
            }
        )
    else:
        checks.update(
            {
                "happiness: both mouth corners 61 and 291 up": bool(
                    d["happiness"][61, 1] > 0 and d["happiness"][291, 1] > 0
                ),
                "surprise: inner brows 107 and 336 up": bool(d["surprise"][107, 1] > 0 and d["surprise"][336, 1] > 0),
                "surprise: chin 152 down": bool(d["surprise"][152, 1] < 0),
            }
        )
        # Detectorv2's names and order (Neutral, Happy, ...): py-feat matches them by name
        v2 = pd.DataFrame(
            [{"Neutral": 0.0, "Happy": 1.0, "Sad": 0.0, "Surprise": 0.0, "Fear": 0.0, "Disgust": 0.0, "Anger": 0.0}]
        )
        checks["Detectorv2-named DataFrame = the same face by name"] = bool(
            np.allclose(fp.predict_face_mesh_from_features(v2, model=model)[0], mesh_of({"happiness": 1.0}))
        )
    unsupported = list(model.unsupported_features)
    warned = None
    if unsupported:  # py-feat's own warning for an input the data never expressed
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            mesh_of({unsupported[0]: 0.5})
        warned = any("never" in str(w.message) for w in caught)
        checks[f"py-feat warns when {unsupported[0]} (unsupported) is given"] = warned
    moves = {
        f: {str(v): [round(float(c), 3) for c in d[f][v]] for v in (61, 291, 152, 17, 0, 107, 336)} for f in checked
    }
    return {
        "release": release,
        "model": repr(model),
        "feature_columns": list(model.feature_columns),
        "pose_columns": list(model.pose_columns),
        "coef_rows": int(model._coef.shape[0]),
        "feature_max": [round(float(v), 4) for v in model.feature_max] if model.feature_max is not None else None,
        "unsupported_features": unsupported,
        "mean_neutral_mesh": None if model.mean_neutral_mesh is None else list(model.mean_neutral_mesh.shape),
        "screen_inter_ocular_px": round(iod, 2),
        "displacement_screen_px (x right, y up)": moves,
        "checks": checks,
        "pngs": [str(p) for p in pngs],
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--release", default=None, help="AU release NPZ (card format)")
    parser.add_argument("--blendshape-release", default=None, help="blendshape release NPZ (bs_to_mesh_pls.npz)")
    parser.add_argument("--emotion-release", default=None, help="emotion release NPZ (emotion_to_mesh_pls.npz)")
    parser.add_argument("--out", required=True, help="folder for the PNGs and pyfeat_check.json")
    parser.add_argument("--intensity", type=float, default=1.0, help="AU intensity of the checked predictions")
    args = parser.parse_args(argv)
    paths = {
        "au_to_mesh_pls": args.release,
        "bs_to_mesh_pls": args.blendshape_release,
        "emotion_to_mesh_pls": args.emotion_release,
    }
    paths = {stem: str(Path(p).resolve()) for stem, p in paths.items() if p}
    if not paths:
        parser.error("give --release, --blendshape-release and/or --emotion-release")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    import matplotlib

    matplotlib.use("Agg")
    import feat
    import feat.plotting as fp
    import matplotlib.pyplot as plt

    def local_file(*a, filename: str, **k) -> str:
        """The one replacement: no hub, our file for the name py-feat asks for (``<stem>_<version>.npz``)."""
        return paths[filename.rsplit("_", 1)[0]]

    fp.hf_hub_download = local_file
    report: dict = {"pyfeat_version": feat.__version__}
    if "au_to_mesh_pls" in paths:
        report.update(probe_au(fp, feat, plt, paths["au_to_mesh_pls"], out, args.intensity))
    for family, stem in (("blendshapes", "bs_to_mesh_pls"), ("emotions", "emotion_to_mesh_pls")):
        if stem in paths:
            report[family] = probe_family(fp, plt, family, paths[stem], out)
    all_checks = {
        **report.get("checks", {}),
        **{f"{f}: {c}": v for f in ("blendshapes", "emotions") if f in report for c, v in report[f]["checks"].items()},
    }
    (out / "pyfeat_check.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    return 0 if all(all_checks.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
