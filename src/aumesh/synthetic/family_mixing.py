"""Fitted-looking family fields for calibrating the direction check (:mod:`aumesh.card.family_directions`).

A real fit of the emotion family does not return each emotion's own field: the detector confuses emotions (its
softmax outputs are correlated) and the fit leaks one emotion's motion into another's row, and the rows carry
estimation noise. This module makes such rows from the family truth (:func:`aumesh.synthetic.family_truth.family_fields`
on :func:`aumesh.synthetic.truth.facs_displacement_fields`: each emotion the sum of its EMFACS prototype's AU fields,
on the canonical template, face frame, inter-ocular units):

* **mixing** ``alpha``: row i = field_i + sum over j != i of ``alpha * |N(0, 1)|`` x field_j (each row a mix of the
  prototypes, the own one dominant; at alpha 0.3 the mixed rows' cosine to their own truth is ~0.75);
* **noise** ``snr``: white noise per row with norm = (mean norm of the non-zero truth rows) / ``snr``;
* **relabelling** ``perm``: row k holds emotion ``perm[k]`` under the label ``EMOTION_COLUMNS[k]`` (a table whose
  columns were permuted before the fit).

Pure numpy; the benchmark (``benchmarks/bench_family_directions.py``) and the tests draw from here.
"""

from __future__ import annotations

import itertools

import numpy as np

from aumesh.core.families import EMOTION_COLUMNS, EMOTION_COLUMNS_V2, EMOTION_NAME_MAP

#: py-feat's emotion_to_mesh_pls_v5 bug (feat/plotting.py, the note above _FEAT_MESH_SPECS): rows in Detectorv2's
#: order (Neutral, Happy, Sad, Surprise, Fear, Disgust, Anger) labelled in FEAT_EMOTION_COLUMNS order.
V5_PERMUTATION: tuple[int, ...] = tuple(EMOTION_COLUMNS.index(EMOTION_NAME_MAP[n]) for n in EMOTION_COLUMNS_V2)


def truth_fields() -> dict[str, np.ndarray]:
    """The family truth on the canonical template: ``"emotions"`` (7, 1434) and ``"blendshapes"`` (52, 1434),
    axis-major, face frame of the template, inter-ocular units; and ``"mesh"`` (478, 3) the template."""
    from aumesh.core.schema import flatten_axis_major
    from aumesh.geometry.face import canonical_template
    from aumesh.synthetic.family_truth import family_fields
    from aumesh.synthetic.truth import facs_displacement_fields

    mesh = canonical_template()
    out = family_fields(flatten_axis_major(facs_displacement_fields()), mesh)
    return {**out, "mesh": mesh}


def mixed(fields: np.ndarray, rng: np.random.Generator, alpha: float = 0.0, snr: float | None = None) -> np.ndarray:
    """Rows mixed with each other and noised as a fit's are (module docstring).

    Parameters
    ----------
    fields : np.ndarray, shape (k, d)
        The truth rows.
    rng : np.random.Generator
    alpha : float
        Mixing: each other row enters with weight ``alpha * |N(0, 1)|``.
    snr : float, optional
        Field norm over noise norm (None: no noise).

    Returns
    -------
    np.ndarray, shape (k, d)
    """
    f = np.asarray(fields, dtype=np.float64)
    k = len(f)
    m = np.eye(k) + alpha * np.abs(rng.normal(size=(k, k))) * (1.0 - np.eye(k))
    out = m @ f
    if snr:
        norms = np.linalg.norm(f, axis=1)
        noise = rng.normal(size=out.shape)
        noise *= norms[norms > 0].mean() / snr / np.linalg.norm(noise, axis=1, keepdims=True)
        out = out + noise
    return out


def relabelled(rows: np.ndarray, perm) -> np.ndarray:
    """``rows[perm]``: under the family's labels, label k now names the row of emotion ``perm[k]``."""
    return np.asarray(rows)[list(perm)]


def transpositions(n: int = 7) -> list[tuple[int, ...]]:
    """The n(n-1)/2 permutations swapping two labels (21 for the seven emotions)."""
    out = []
    for a, b in itertools.combinations(range(n), 2):
        p = list(range(n))
        p[a], p[b] = b, a
        out.append(tuple(p))
    return out


def three_cycles(n: int = 7) -> list[tuple[int, ...]]:
    """The 2 * C(n, 3) permutations cycling three labels (70 for the seven emotions)."""
    out = []
    for a, b, c in itertools.combinations(range(n), 3):
        for x, y, z in ((a, b, c), (a, c, b)):
            p = list(range(n))
            p[x], p[y], p[z] = y, z, x
            out.append(tuple(p))
    return out
