"""A family release NPZ (issue 46, contract item 3) with known coefficients, for the rig, viewer, predict and animate
tests: the synthetic family truth's fields (:func:`aumesh.synthetic.family_truth.family_fields` of the AU truth the
card's synthetic release carries) as the family's input rows, seeded random pose and pose x input rows."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from aumesh.core.families import FAMILIES, feature_set_columns
from aumesh.core.schema import ANCHOR_INDICES, flatten_axis_major
from aumesh.model import support

#: the inputs whose synthetic field is zero get a training p99 below support.UNSUPPORTED_P99 (never expressed)
SUPPORTED_P99, UNSUPPORTED_P99 = 0.6, 0.01
POSE_FILTER = {"max_abs_pitch_deg": 30.0, "max_abs_yaw_deg": 40.0}


def upright_template() -> np.ndarray:
    """conftest.upright_truth_release's face: the canonical template y up, z out of the face, pixel-like units."""
    from aumesh.geometry import face

    return 120.0 * face.canonical_template() * np.array([1.0, -1.0, -1.0]) + np.array([320.0, 240.0, 10.0])


def family_fit(family: str, *, pose_scale: float = 0.5, seed: int = 0, design: str = "_pose_interactions") -> dict:
    """A family fit in the aligned frame as ``build/families/<family>/model.npz`` holds it: ``coef`` (1434, p),
    ``intercept`` (1434,), ``feature_columns`` (p,) (``<family>_pose_interactions``), ``fields`` (k, 1434) the
    family's truth, ``ranges`` (each input's range record: p99 0.6, or 0.01 where the field is zero)."""
    from aumesh.synthetic.family_truth import family_fields
    from aumesh.synthetic.truth import facs_displacement_fields

    tpl = upright_template()
    au_fields = flatten_axis_major(facs_displacement_fields(tpl))  # (20, 1434)
    fields = family_fields(au_fields, tpl)[family]
    columns = feature_set_columns(f"{family}{design}")
    k = len(FAMILIES[family])
    rng = np.random.default_rng(seed)
    coef = rng.normal(0.0, pose_scale, (1434, len(columns)))
    coef[:, :k] = fields.T
    zero = ~np.abs(fields).any(axis=1)
    ranges = {}
    for j, name in enumerate(FAMILIES[family]):
        p99 = UNSUPPORTED_P99 if zero[j] else SUPPORTED_P99
        ranges[name] = support.range_record([0.0, 0.0, p99 / 3, p99, min(1.0, 1.2 * p99)], 0.2)
    return {
        "coef": coef,
        "intercept": flatten_axis_major(tpl),
        "feature_columns": columns,
        "fields": fields,
        "ranges": ranges,
        "template": tpl,
    }


def family_release_arrays_for(
    family: str, *, seed: int = 0, pose_scale: float = 0.5, design: str = "_pose_interactions"
) -> dict:
    """The family release arrays of :func:`family_fit`, made by the release's own writer
    (:func:`aumesh.model.family_release.family_release_arrays`, contract item 3)."""
    from aumesh.model.family_release import family_release_arrays

    fit = family_fit(family, seed=seed, pose_scale=pose_scale, design=design)
    tpl = fit["template"]
    anchors = np.asarray(ANCHOR_INDICES, dtype=np.int32)
    reference = {
        "mean_aligned_mesh": tpl,
        "mean_low_au_mesh": tpl,
        "reference_anchors": tpl[anchors],
        "anchor_indices": anchors,
    }
    metadata = {"config": {"preprocess": {"pose_filter": POSE_FILTER}, "features": {"family": family}}}
    return family_release_arrays(
        family,
        fit["coef"],
        fit["intercept"],
        fit["feature_columns"],
        12,
        reference,
        fit["ranges"],
        card_text=f"aumesh synthetic {family} release (tests/family_release_fixture.py)",
        metadata=metadata,
    )


def family_release(path: Path, family: str, **kw) -> Path:
    """:func:`family_release_arrays_for` written to ``path`` (``np.savez``)."""
    np.savez(path, **family_release_arrays_for(family, **kw))
    return path


def numpy_prediction(npz: dict, x: np.ndarray, pose: np.ndarray | None = None) -> np.ndarray:
    """The NPZ's own arithmetic, written from contract item 3 without aumesh: ``x_full @ coef + intercept`` with
    ``x_full = [inputs | pose | pose x input]`` (pose-major products named ``Pose*input``), as (N, 478, 3)."""
    x = np.atleast_2d(np.asarray(x, np.float64))
    pose = np.zeros((len(x), 3)) if pose is None else np.atleast_2d(np.asarray(pose, np.float64))
    values = dict(zip([str(c) for c in npz["feature_columns"]], x.T, strict=True))
    values |= dict(zip(["Pitch", "Yaw", "Roll"], pose.T, strict=True))
    cols = []
    for name in [str(c) for c in npz["input_columns"]]:
        left, _, right = name.partition("*")
        cols.append(values[name] if not right else values[left] * values[right])
    flat = np.stack(cols, axis=1) @ npz["coef"].astype(np.float64) + npz["intercept"].astype(np.float64)
    return np.stack([flat[:, :478], flat[:, 478:956], flat[:, 956:]], axis=-1)
