"""Calibration of the families' direction check (issue 46, item 4): how often it fails a correct labelling, and how
often it names a permuted one, when the fields are mixed and noisy as a fit's are.

Emotions (:func:`aumesh.card.family_directions.emotion_direction_check`) on the family truth
(:mod:`aumesh.synthetic.family_mixing`: each emotion its EMFACS AU fields summed, canonical template), per mixing
``alpha`` (each row + alpha x |N(0,1)| of every other row) and noise (SNR = truth norm / noise norm), with fresh draws
per case:

* the correct labelling, ``--draws`` times: the rates of fail (a false alarm: the release would be refused), doubtful
  (a warning in the card) and pass;
* every transposition (21), every 3-cycle (70) and py-feat v5's order (Detectorv2's rows under FEAT_EMOTION_COLUMNS
  labels), ``--reps`` draws each: the rate of fail naming exactly the permutation, of fail at all, of doubtful;
* the same cases under the rule before calibration (linear assignment of the centred cosines, any non-identity
  assignment fails), for comparison.

Blendshapes (:func:`aumesh.card.family_directions.blendshape_direction_check`) on the family truth with white noise per
row (SNR 1 and 2 of its own norm; the shapes whose truth is zero get 5 % of the median field): the correct labelling's
fail / doubtful rates, and each of the Left/Right pairs swapped: the rate at which it fails naming that pair.

Prints a table; asserts nothing (tests/test_family_directions.py holds the fast checks).

    .venv/bin/python benchmarks/bench_family_directions.py [--draws 200 --reps 5 --seed 0]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.optimize import linear_sum_assignment

from aumesh.card import family_directions as fd
from aumesh.card.family_expectations import EMOTION_PROTOTYPES
from aumesh.core.families import BLENDSHAPE_COLUMNS, EMOTION_COLUMNS
from aumesh.synthetic import family_mixing as fm

LABELS = list(EMOTION_COLUMNS)


def old_rule(rows: np.ndarray, mesh: np.ndarray) -> tuple[str, tuple[int, ...]]:
    """The rule before calibration: linear assignment on the centred cosines, any non-identity assignment fails."""
    disp, m = fd.family_displacements(rows, LABELS, mesh, list(EMOTION_PROTOTYPES), "bench")
    r, c = linear_sum_assignment(-fd.emotion_score_matrix(disp, m))
    like = tuple(int(x) for x in c[np.argsort(r)])
    return ("pass" if like == tuple(range(7)) else "fail"), like


def new_rule(rows: np.ndarray, mesh: np.ndarray) -> tuple[str, tuple[int, ...]]:
    rep = fd.emotion_direction_check(rows, LABELS, mesh, "bench")
    return rep["verdict"], tuple(LABELS.index(rep["assignment"][n]) for n in LABELS)


def emotions(args: argparse.Namespace, truth: dict[str, np.ndarray]) -> None:
    e, mesh = truth["emotions"], truth["mesh"]
    cases = {
        "transpositions": fm.transpositions(),
        "3-cycles": fm.three_cycles(),
        "v5 order": [fm.V5_PERMUTATION],
    }
    print("Emotions: correct labelling (false alarm = fail) and permuted ones (named = fail naming exactly it)")
    print(
        f"{'alpha':>5} {'snr':>4} {'rule':>4} | {'correct: fail':>13} {'doubtful':>8} | "
        + " | ".join(f"{k}: named / fail / doubtful" for k in cases)
    )
    for alpha, snr in [(0.0, None), (0.0, 1.0), (0.1, 1.0), (0.2, 1.0), (0.3, None), (0.3, 1.0), (0.4, 1.0)]:
        for name, rule in (("new", new_rule), ("old", old_rule)):
            rng = np.random.default_rng(args.seed)
            verdicts = [rule(fm.mixed(e, rng, alpha, snr), mesh)[0] for _ in range(args.draws)]
            row = (
                f"{alpha:5.1f} {snr or '-':>4} {name:>4} | {verdicts.count('fail') / len(verdicts):13.1%} "
                f"{verdicts.count('doubtful') / len(verdicts):8.1%} |"
            )
            for perms in cases.values():
                named = fail = doubt = n = 0
                for perm in perms:
                    for _ in range(args.reps):
                        verdict, like = rule(fm.relabelled(fm.mixed(e, rng, alpha, snr), perm), mesh)
                        n += 1
                        fail += verdict == "fail"
                        named += verdict == "fail" and like == tuple(perm)
                        doubt += verdict == "doubtful"
                row += f" {named / n:6.1%} / {fail / n:6.1%} / {doubt / n:6.1%} |"
            print(row, flush=True)


def blendshapes(args: argparse.Namespace, truth: dict[str, np.ndarray]) -> None:
    b, mesh = truth["blendshapes"], truth["mesh"]
    norms = np.linalg.norm(b, axis=1)
    floor = 0.05 * np.median(norms[norms > 0])
    pairs = [(n, n[: -len("Left")] + "Right") for n in BLENDSHAPE_COLUMNS if n.endswith("Left")]
    cols = list(BLENDSHAPE_COLUMNS)
    print("\nBlendshapes: correct labelling (false alarm = fail) and each Left/Right pair swapped (named = fails it)")
    for snr in (2.0, 1.0):
        rng = np.random.default_rng(args.seed)
        scale = np.where(norms > 0, norms / snr, floor)

        def noisy(rng: np.random.Generator = rng, scale: np.ndarray = scale) -> np.ndarray:
            noise = rng.normal(size=b.shape)
            return b + noise * (scale / np.linalg.norm(noise, axis=1))[:, None]

        verdicts = [fd.blendshape_direction_check(noisy(), cols, mesh)["verdict"] for _ in range(args.draws // 4)]
        named = tried = 0
        for left, right in pairs:
            if norms[cols.index(left)] == 0:
                continue  # gaze shapes: zero truth, nothing to swap
            swapped = cols.copy()
            i, j = cols.index(left), cols.index(right)
            swapped[i], swapped[j] = swapped[j], swapped[i]
            for _ in range(args.reps):
                rep = fd.blendshape_direction_check(noisy(), swapped, mesh)
                tried += 1
                named += rep["pairs"].get(f"{left[:-4]}Left/Right", {}).get("verdict") == "fail"
        print(
            f"  snr {snr}: correct fail {verdicts.count('fail') / len(verdicts):.1%}, doubtful "
            f"{verdicts.count('doubtful') / len(verdicts):.1%} ({len(verdicts)} draws); swapped pairs named "
            f"{named}/{tried}",
            flush=True,
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=200, help="draws of the correct labelling per setting")
    ap.add_argument("--reps", type=int, default=2, help="draws per permutation per setting")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-blendshapes", action="store_true")
    ap.add_argument("--skip-emotions", action="store_true")
    args = ap.parse_args()
    t0 = time.perf_counter()
    truth = fm.truth_fields()
    if not args.skip_emotions:
        emotions(args, truth)
    if not args.skip_blendshapes:
        blendshapes(args, truth)
    print(f"\n{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
