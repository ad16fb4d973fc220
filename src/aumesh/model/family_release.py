"""A family release's arrays: the blendshape or emotion fit in py-feat's loader format (issue 46, contract item 3).

py-feat 2.1.5 reads these NPZs with ``feat.plotting._load_pls_feat_to_mesh_from_hub`` (through
``load_blendshape_face_mesh_model`` / ``load_emotion_face_mesh_model``) into a ``PLSFeatMeshModel``:

* ``coef`` (p, 1434): it keeps the array whole and predicts ``x @ coef[:k] + intercept`` with ``k =
  len(feature_columns)`` ("pose channels are implicit-zero, so only the leading feature rows of the deployed coef
  contribute"), so the family's ``k`` inputs must be the first rows; the pose and pose x input rows follow in the
  design's order (:func:`aumesh.core.families.feature_set_columns`), which makes ``coef`` the whole fit;
* ``intercept`` (1434,), axis-major ``[x | y | z]``;
* ``feature_columns`` (k,): must equal ``_FEAT_MESH_SPECS[feature][2]`` exactly (``MP_BLENDSHAPE_NAMES`` /
  ``FEAT_EMOTION_COLUMNS``) or the loader raises "feature_columns drifted";
* ``pose_columns``, ``mean_aligned_mesh`` (478, 3); and, optional to the loader, ``feature_p99`` (k,) (its
  ``feature_max``: ``predict_face_mesh_from_features`` clips inputs to ``[0, feature_p99]``),
  ``unsupported_features`` (inputs "the detector never expresses, whose coefficients are unconstrained": py-feat warns
  when one is given above 0.02) and ``mean_neutral_mesh`` (478, 3).

Every geometric array is in the AU release's canonical frame (:func:`aumesh.model.release.release_arrays`: x the
subject's left, y up, z out of the face, found from the reference's ``mean_aligned_mesh``), the frame py-feat's
``plot_face_mesh`` draws upright (its docstring: "+Y up (forehead at ~+8, chin at ~-8), +Z out of the face"), so the
AU and family releases of one training set render in one frame, as py-feat's own v6 family does.

Pure functions on arrays and dicts; the release stage (:mod:`aumesh.stages.release_family`) does the I/O.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from aumesh.core.families import FAMILIES, PYFEAT_FEATURE
from aumesh.core.schema import N_TARGETS, POSE_COLUMNS
from aumesh.core.schema import feature_columns as design_columns
from aumesh.geometry.frame import canonical_frame, rotate_axis_major, to_canonical
from aumesh.model import support

#: the fix for a family fit whose columns are not its family's design
FAMILY_FIT_FIX = "refit the family (`dvc repro -f evaluate`)"


def npz_name(family: str) -> str:
    """The family release's NPZ file name: py-feat's stem (``_FEAT_MESH_SPECS``; ``bs_to_mesh_pls.npz``,
    ``emotion_to_mesh_pls.npz``). py-feat's hub names add ``_<version>``; a local loader takes any path."""
    return f"{PYFEAT_FEATURE[check_release_family(family)][1]}.npz"


def check_release_family(family: str) -> str:
    """``family`` when it has a py-feat loader (blendshapes, emotions); a one-line error otherwise (the AU family's
    release is the ``release`` stage's ``au_to_mesh_pls.npz``)."""
    if family not in PYFEAT_FEATURE:
        raise ValueError(
            f"family={family!r} has no family release; use one of {', '.join(PYFEAT_FEATURE)} "
            "(the AUs are released by the `release` stage)"
        )
    return family


def input_ranges(
    quantiles: np.ndarray, active: np.ndarray, n_frames: int, columns: Sequence[str]
) -> dict[str, dict[str, float | None]]:
    """Each family input's range record (:func:`aumesh.model.support.range_record`), as prepare records the AUs'.

    Parameters
    ----------
    quantiles : ndarray, shape (k, 5)
        Each input's :data:`aumesh.model.support.RANGE_QUANTILES` over the training frames (``np.quantile``, linear).
    active : ndarray, shape (k,)
        Frames with the input above :data:`aumesh.model.support.ACTIVE_AU`.
    n_frames : int
        Training frames.
    columns : sequence of str, length k
        The inputs, in the family's order.

    Returns
    -------
    dict
        ``{name: {"min", "p1", "p50", "p99", "max", "active_fraction"}}``.
    """
    q = np.asarray(quantiles, dtype=np.float64)
    a = np.asarray(active, dtype=np.float64)
    if q.shape != (len(columns), len(support.RANGE_QUANTILES)) or a.shape != (len(columns),):
        raise ValueError(f"quantiles {q.shape} / active {a.shape} do not match {len(columns)} columns")
    n = max(int(n_frames), 1)
    return {name: support.range_record(q[j], float(a[j] / n)) for j, name in enumerate(columns)}


def ranges_of(values: np.ndarray, columns: Sequence[str]) -> dict[str, dict[str, float | None]]:
    """:func:`input_ranges` of an in-memory (n, k) block of inputs (tests, small tables): ``np.quantile`` directly."""
    v = np.asarray(values, dtype=np.float64)
    q = np.quantile(v, list(support.RANGE_QUANTILES.values()), axis=0).T if len(v) else np.zeros((v.shape[1], 5))
    return input_ranges(q, (v > support.ACTIVE_AU).sum(axis=0), len(v), columns)


def design_rows(coef: np.ndarray, feature_columns: Sequence[str], family: str) -> tuple[np.ndarray, list[str]]:
    """``coef`` (1434, p) as py-feat's rows (p, 1434) in the design's order (:func:`aumesh.core.schema.feature_columns`):
    the family's inputs first in py-feat's order, then Pitch, Yaw, Roll and the pose-major pose x input products, as
    many of them as the fit has; rows are picked by name, never by position.

    Raises
    ------
    ValueError
        One line naming the family input the fit lacks, a column no design of the family has, or a shape that is
        not (1434, p).
    """
    c = np.asarray(coef, dtype=np.float64)
    cols = [str(s) for s in feature_columns]
    if c.shape != (N_TARGETS, len(cols)):
        raise ValueError(f"family fit coef has shape {c.shape}, expected ({N_TARGETS}, {len(cols)}): {FAMILY_FIT_FIX}")
    inputs = list(FAMILIES[family])
    missing = [n for n in inputs if n not in cols]
    if missing:
        raise ValueError(
            f"the {family} fit's feature_columns lack {missing[:3]}{' ...' if len(missing) > 3 else ''}: it is not a "
            f"{family} fit. Fix: {FAMILY_FIT_FIX}"
        )
    universe = design_columns(True, True, inputs)  # [inputs | pose | pose-major pose x input]: the design order
    unknown = [n for n in cols if n not in set(universe)]
    if unknown:
        raise ValueError(
            f"the {family} fit's feature_columns hold {unknown[:3]}, not a column of a {family} design. "
            f"Fix: {FAMILY_FIT_FIX}"
        )
    order = [n for n in universe if n in set(cols)]
    return c[:, [cols.index(n) for n in order]].T, order


def family_release_arrays(
    family: str,
    coef: np.ndarray,
    intercept: np.ndarray,
    feature_columns: Sequence[str],
    n_components: int,
    reference: Mapping[str, np.ndarray],
    ranges: Mapping[str, Mapping[str, Any]],
    card_text: str = "",
    metadata: Mapping[str, Any] | None = None,
) -> dict[str, np.ndarray]:
    """The family NPZ's arrays: py-feat's ``PLSFeatMeshModel`` keys plus aumesh's own (as the AU NPZ has them).

    Parameters
    ----------
    family : {"blendshapes", "emotions"}
    coef : ndarray, shape (1434, p)
        The family fit's raw-input coefficients (``build/families/<family>/model.npz`` ``coef``), aligned frame.
    intercept : ndarray, shape (1434,)
        Its mesh intercept (``mesh_intercept``): the mesh at all inputs 0, aligned frame.
    feature_columns : sequence of str, length p
        The fit's design columns (the family's inputs, then pose and pose x input when the design has them).
    n_components : int
        PLS components of the fit.
    reference : mapping
        prepare's ``reference.npz`` (:func:`aumesh.pipeline.integrity.load_reference`): ``mean_aligned_mesh``,
        ``mean_low_au_mesh``, ``reference_anchors`` (478/12, 3), ``anchor_indices`` (12,), aligned frame.
    ranges : mapping
        Each family input's range record over the training frames (:func:`input_ranges`); an input it lacks gets
        ``feature_p99`` NaN and is not judged unsupported.
    card_text, metadata
        ``MODEL_CARD.md`` and ``model_card.json`` (stored as ``model_card`` / ``training_metadata``, as in the AU NPZ).

    Returns
    -------
    dict of str -> ndarray
        py-feat's keys: ``coef`` (p, 1434) float32, family inputs first (:func:`design_rows`); ``intercept`` (1434,)
        float32; ``feature_columns`` (k,) str, py-feat's list; ``pose_columns`` (the design's pose inputs: (3,) or
        (0,)); ``mean_aligned_mesh`` (478, 3) float32; ``feature_p99`` (k,) float32; ``unsupported_features`` (m,)
        str (training p99 below :data:`aumesh.model.support.UNSUPPORTED_P99`: never expressed);
        ``mean_neutral_mesh`` (478, 3) float32 (the reference's mean of its low-AU frames, prepare's neutral
        population, = ``mean_low_au_mesh``). aumesh's: ``input_columns`` (p,) (``coef``'s rows), ``family``,
        ``pyfeat_feature``, ``n_components``, ``mean_low_au_mesh``, ``reference_anchors``, ``anchor_indices``,
        ``model_card``, ``training_metadata``.
    """
    check_release_family(family)
    rows, design = design_rows(coef, feature_columns, family)
    inputs = list(FAMILIES[family])
    rotation, origin = canonical_frame(reference["mean_aligned_mesh"])

    def mesh(key: str) -> np.ndarray:
        return to_canonical(reference[key], rotation, origin).astype(np.float32)

    return {
        # ---- what PLSFeatMeshModel reads (feat/plotting.py _load_pls_feat_to_mesh_from_hub)
        "coef": rotate_axis_major(rows, rotation).astype(np.float32),
        "intercept": rotate_axis_major(np.asarray(intercept, np.float64), rotation, origin).astype(np.float32),
        "feature_columns": np.array(inputs),
        "pose_columns": np.array([p for p in POSE_COLUMNS if p in design], dtype=str).reshape(-1),
        "mean_aligned_mesh": mesh("mean_aligned_mesh"),
        "feature_p99": support.feature_p99(ranges, inputs),
        "unsupported_features": np.array(support.unsupported_inputs(ranges, inputs), dtype=str).reshape(-1),
        "mean_neutral_mesh": mesh("mean_low_au_mesh"),
        # ---- aumesh's own, as in the AU NPZ (aumesh.model.release.release_arrays)
        "input_columns": np.array(design),
        "family": np.array(family),
        "pyfeat_feature": np.array(PYFEAT_FEATURE[family][0]),
        "n_components": np.array(n_components, dtype=np.int32),
        "mean_low_au_mesh": mesh("mean_low_au_mesh"),
        "reference_anchors": mesh("reference_anchors"),
        "anchor_indices": np.asarray(reference["anchor_indices"], dtype=np.int32),
        "model_card": np.array(card_text),
        "training_metadata": np.array(json.dumps(dict(metadata or {}), sort_keys=True, default=str)),
    }
