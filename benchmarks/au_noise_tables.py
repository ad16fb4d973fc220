"""AU fields under detector noise on the realistic preset (issue 43): within-video least squares in the canonical frame.

Generates :func:`aumesh.synthetic.tables.realistic_noise_spec`'s videos (30,000 frames, 800 videos by default) with
``generate_video(..., keep_canonical=True)``, and fits the within-video least squares of the canonical mesh (before
rotation, scale and landmark noise: what alignment recovers at best) on the card's 83-column design (20 AU | 3 pose |
60 pose x AU) built from

* the true AUs (the no-noise control: the same frames, ``au_noise_sd=0``),
* the recorded AUs (detector noise, clipped to [0, 1] as the tables hold them),
* the true AUs + the detector's error unclipped (the classical error model ``au_sigma_u_within`` describes),

and prints each AU field's cosine to the truth (``true_coefficients`` rows), the within-video correlations of the
co-activated pairs, the analytic vs measured ``Sigma_u``, and, when ``aumesh.model.eiv`` is there, the floored
corrected fit with the generator's ``Sigma_u`` (and 1.5x it) and the identification screen. Prints; asserts nothing.

    .venv/bin/python benchmarks/au_noise_tables.py [--frames 30000 --videos 800 --seed 0 --sd 0.07]
"""

from __future__ import annotations

import argparse
import importlib.util
import time

import numpy as np

from aumesh.core.schema import AU_COLUMNS, feature_columns, flatten_axis_major
from aumesh.synthetic import au_noise
from aumesh.synthetic import tables as synth
from aumesh.synthetic.pyfeat_faces import synth_setup


def design(au: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(n, 83) [AU | pose | pose x AU], the generator's (and the card's) column order."""
    return np.column_stack([au, pose, (pose[:, :, None] * au[:, None, :]).reshape(len(au), -1)])


def within(a: np.ndarray) -> np.ndarray:
    return a - a.mean(axis=0)


def cosines(coef: np.ndarray, truth: np.ndarray) -> np.ndarray:
    a, b = coef[: len(AU_COLUMNS)], truth[: len(AU_COLUMNS)]
    return np.einsum("kj,kj->k", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30_000)
    ap.add_argument("--videos", type=int, default=800)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sd", type=float, default=0.07)
    args = ap.parse_args()

    # the second detector (own streams) changes nothing of the first detector's tables: it only adds the 2SLS column
    spec = synth.realistic_noise_spec(
        n_frames=args.frames, n_videos=args.videos, seed=args.seed, au_noise_sd=args.sd, instrument_noise_sd=args.sd
    )
    counts, gen_args = synth_setup(spec)
    coef = gen_args[0]
    names = ("control", "noisy", "unclipped")
    p = coef.shape[0]
    sxx = {k: np.zeros((p, p)) for k in names}
    sxy = {k: np.zeros((p, coef.shape[1])) for k in names}
    szx, szy = np.zeros((p, p)), np.zeros((p, coef.shape[1]))  # the second detector's design as instruments
    true_within, err_within, rec_err_within = [], [], []
    pose_sum, pose_second, clipped, n_total, bias = np.zeros(3), np.zeros((3, 3)), 0, 0, np.zeros(len(AU_COLUMNS))
    t0 = time.perf_counter()
    for v, n in enumerate(counts):
        g = synth.generate_video(spec, v, int(n), *gen_args, keep_canonical=True)
        y = within(flatten_axis_major(g["canonical"]))
        xs = {
            "control": design(g["au_true"], g["pose"]),
            "noisy": design(g["au"], g["pose"]),
            "unclipped": design(g["au_true"] + g["au_error"], g["pose"]),
        }
        for k, x in xs.items():
            xw = within(x)
            sxx[k] += xw.T @ xw
            sxy[k] += xw.T @ y
        zw = within(design(g["au2"], g["pose"]))
        szx += zw.T @ within(xs["noisy"])
        szy += zw.T @ y
        true_within.append(within(g["au_true"]))
        err_within.append(within(g["au_error"]))
        rec_err_within.append(within(g["au"] - g["au_true"]))
        bias += (g["au"] - g["au_true"]).sum(0)
        pose_sum += g["pose"].sum(0)
        pose_second += g["pose"].T @ g["pose"]
        clipped += int(((g["au_true"] + g["au_error"] < 0) | (g["au_true"] + g["au_error"] > 1)).sum())
        n_total += int(n)
    print(f"generated {n_total:,} frames / {len(counts)} videos in {time.perf_counter() - t0:.1f} s")
    print(f"spec: {spec}")
    print(f"recorded AU values clipped to [0, 1]: {clipped / (n_total * len(AU_COLUMNS)):.1%}")

    tw = np.concatenate(true_within)
    corr = np.corrcoef(tw.T)
    print("\nwithin-video correlation of the true AUs:")
    for a, b, _ in synth.COACTIVATED_AUS:
        print(f"  {a}/{b}: {corr[AU_COLUMNS.index(a), AU_COLUMNS.index(b)]:.3f}")

    sigma_u = au_noise.au_error_covariance(spec, counts)
    emp = np.concatenate(err_within).T @ np.concatenate(err_within) / n_total
    rec = np.concatenate(rec_err_within).T @ np.concatenate(rec_err_within) / n_total
    d = np.sqrt(np.diag(sigma_u))
    print(
        f"\nSigma_u diagonal: analytic sd {d.mean():.4f}; measured (unclipped error) {np.sqrt(np.diag(emp)).mean():.4f}; "
        f"recorded - true (clipped) {np.sqrt(np.diag(rec)).mean():.4f} (mean over AUs)"
    )
    print(
        f"  recorded - true: mean {bias.mean() / n_total:+.4f} (clipping cuts the negative errors of AUs near 0; "
        f"largest for an AU {np.max(bias) / n_total:+.4f})"
    )

    fits = {k: np.linalg.solve(sxx[k], sxy[k]) for k in names}
    cos = {k: cosines(fits[k], coef) for k in names}
    extra = {}
    if importlib.util.find_spec("aumesh.model.eiv") is not None:
        from aumesh.model import eiv

        pm, ps = pose_sum / n_total, pose_second / n_total
        cols = feature_columns(True, True)
        for label, scale, s_u in (("corrected", 1.0, sigma_u), ("corr_1.5x", 1.5, sigma_u), ("corr_rec", 1.0, rec)):
            sig = eiv.design_error_covariance(scale * s_u, cols, pm, ps)
            extra[label] = cosines(
                eiv.floored_corrected_coef(sxx["noisy"] / n_total, sxy["noisy"] / n_total, sig), coef
            )
        extra["2sls"] = cosines(eiv.instrumental_coef(szx, szy), coef)
        screens = {
            k: eiv.identification_screen(sxx[k][:20, :20] / n_total, sxy[k][:20] / n_total)
            for k in ("control", "noisy")
        }
    table = {**cos, **extra}
    print("\nAU field cosine to the truth (within-video least squares, canonical frame, 83 columns):")
    print("  AU    " + " ".join(f"{k:>9s}" for k in table))
    for j, au in enumerate(AU_COLUMNS):
        print(f"  {au}  " + " ".join(f"{table[k][j]:9.3f}" for k in table))
    print("  median" + " ".join(f"{np.median(table[k]):9.3f}" for k in table))
    print("  worst " + " ".join(f"{np.min(table[k]):9.3f}" for k in table))
    if extra:
        for k, s in screens.items():
            stars = " ".join(f"{a}={x:.3f}" for a, x in zip(AU_COLUMNS, s.sigma_star, strict=True) if np.isfinite(x))
            print(f"sigma* on {k} (AUs that turn within the grid): {stars or 'none'}")
            flagged = [
                f"{a} (partner {s.partner[j]}, sigma* {s.sigma_star[j]:.3f})"
                for j, a in enumerate(AU_COLUMNS)
                if s.flagged[j]
            ]
            print(f"screen on {k}: {len(flagged)} flagged: {', '.join(flagged) or 'none'}")
    else:
        print("(aumesh.model.eiv not on this branch: corrected fit and screen skipped)")


if __name__ == "__main__":
    main()
