"""The family release stage (``release_family@<family>``): a family's fit -> ``releases/<family>/``, atomically.

``releases/<family>/`` holds ``<stem>.npz`` in py-feat's loader format (:mod:`aumesh.model.family_release`),
``model_card.json``, ``MODEL_CARD.md``, ``figures/``, ``<family>_directions.json`` and the rig and viewer; a failure
anywhere leaves the previous release as it was (:func:`aumesh.core.io.atomic_directory`).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from aumesh.config import Config
from aumesh.core.io import (
    atomic_directory,
    atomic_savez,
    atomic_write_json,
    atomic_write_text,
    remove_stale_temporaries,
)
from aumesh.model.family_release import check_release_family, family_release_arrays, npz_name
from aumesh.model.release import CARD_JSON, CARD_MD
from aumesh.pipeline import integrity
from aumesh.pipeline.model_files import CV_NPZ, MODEL_NPZ, SKIPPED_JSON
from aumesh.pipeline.prepared_files import FRAMES_FILE, REFERENCE_FILE
from aumesh.pipeline.release import load_model, refuse_implausible_face, refuse_nonfinite
from aumesh.pipeline.release_family import (
    build_family_card,
    family_fit_dir,
    family_promotion,
    family_release_dir,
    input_sum_range,
    sides_together,
    training_ranges,
)
from aumesh.stages.common import start_stage

log = logging.getLogger(__name__)

#: What ``releases/<family>/`` holds, beside ``model_card.json``, when the family was not fitted
NOT_RELEASED_MD = "NOT_RELEASED.md"


def directions_report(arrays: dict[str, np.ndarray], family: str, source: str, together: list[str]) -> dict:
    """The family's direction check on the release arrays (:mod:`aumesh.card.family_directions`): the report
    (``<family>_directions.json``; ``summary`` is {input: verdict}), and the refusal of a release whose emotion labels
    look permuted or whose blendshapes move the wrong way / side (a one-line
    :class:`aumesh.core.errors.DirectionCheckError`, exit 2, the suspected permutation named). Called inside
    the release's temporary folder, so a refusal leaves the previous release as it was."""
    from aumesh.card import family_directions

    report = family_directions.family_direction_report(
        {**arrays, "family": np.array(family)}, where=source, together=together
    )
    family_directions.check_family_directions(report, source)
    return report


def export_rig_and_viewer(arrays: dict[str, np.ndarray], folder: Path, source: str) -> list[Path]:
    """``<family>_to_mesh.glb`` (a morph target per input, named by the family's own names) and ``viewer.html``
    (a slider per input) of the family release (:mod:`aumesh.export.gltf`, :mod:`aumesh.export.viewer`)."""
    from aumesh.export import gltf, viewer

    return [
        gltf.write_glb(arrays, folder / gltf.glb_name(arrays), source=source),
        viewer.write_viewer(arrays, folder / viewer.VIEWER_NAME, source=source),
    ]


def write_not_released(out: Path, family: str, reason: str) -> Path:
    """``releases/<family>/`` of a family the evaluate stage did not fit: ``model_card.json`` (``released: false``
    and why) and ``NOT_RELEASED.md``, atomically, and one warning line; no NPZ, so no tool mistakes it for a model."""
    log.warning("release_family: %s not released: %s", family, reason)
    text = (
        f"# {family}: not released\n\nThe evaluate stage did not fit the {family} family: {reason}\n\n"
        f"Set `families.{family}.features` to one of the family's designs (conf/families/) on tables that carry it, "
        "then `dvc repro`.\n"
    )
    with atomic_directory(out) as tmp:
        atomic_write_json(tmp / CARD_JSON, {"family": {"name": family}, "released": False, "reason": reason})
        atomic_write_text(tmp / NOT_RELEASED_MD, text)
    return out


def main(cfg: Config, family: str) -> Path:
    """Write ``paths.families_release_dir/<family>`` atomically (NPZ, ``model_card.json``, ``MODEL_CARD.md``, figures,
    directions report, rig, viewer) and return it."""
    from aumesh.card import family_figures, limits
    from aumesh.card.family_card import family_card_markdown
    from aumesh.card.family_directions import family_displacements

    check_release_family(family)
    out = family_release_dir(cfg, family)
    start_stage("release_family", cfg)  # a promotion killed half-way finished first (it writes promotion.json)
    for path in remove_stale_temporaries(out):  # what a killed run of this family's release left
        log.info("removed %s, left by a killed run", path)
    fit_dir, prepared_dir = family_fit_dir(cfg, family), Path(cfg.paths.prepared_dir)
    if (fit_dir / SKIPPED_JSON).exists():  # not fitted (families.<f>.features=none, or tables without the family)
        return write_not_released(out, family, json.loads((fit_dir / SKIPPED_JSON).read_text())["reason"])
    integrity.verify_prepared(prepared_dir, integrity.load_summary(prepared_dir), [REFERENCE_FILE, FRAMES_FILE])
    model = load_model(fit_dir)
    reference = integrity.load_reference(prepared_dir)
    ranges = training_ranges(prepared_dir, family)
    promotion = family_promotion(cfg.paths.promotion_file, family)
    design = [str(c) for c in model["feature_columns"].tolist()]
    card = build_family_card(cfg, family, fit_dir, prepared_dir, promotion, ranges, int(model["n_components"]), design)
    card["data"]["input_sum"] = input_sum_range(prepared_dir, family)  # a softmax family: only differences identified
    refuse_nonfinite({"coef": model["coef"], "intercept": model["mesh_intercept"]}, fit_dir / MODEL_NPZ)
    card["data"]["face_shape"] = refuse_implausible_face(
        model["mesh_intercept"], reference["mean_aligned_mesh"], fit_dir / MODEL_NPZ, prepared_dir / REFERENCE_FILE
    )
    arrays = family_release_arrays(
        family,
        model["coef"],
        model["mesh_intercept"],
        design,
        int(model["n_components"]),
        reference,
        ranges,
        metadata=card,
    )
    refuse_nonfinite(arrays, fit_dir / MODEL_NPZ)  # before anything is written: the previous release stays
    name = npz_name(family)
    inputs = arrays["feature_columns"].tolist()
    disp, _ = family_displacements(arrays["coef"], inputs, arrays["mean_aligned_mesh"], inputs, name)
    field_iod = {n: float(s) for n, s in zip(inputs, limits.au_field_sizes(disp), strict=True)}
    with atomic_directory(out) as tmp:
        report = directions_report(arrays, family, name, sides_together(prepared_dir, family))
        atomic_write_json(tmp / f"{family}_directions.json", report)
        card["directions"] = {
            "verdict": report["verdict"],
            "message": report["message"],
            "file": f"{family}_directions.json",
        }
        card["warnings"] = limits.release_warnings(card, None, field_iod, family=family)
        figures = family_figures.render_family(arrays, tmp / "figures", cv_path=fit_dir / CV_NPZ)
        markdown = family_card_markdown(card, [str(f) for f in figures])
        arrays["model_card"] = np.array(markdown)
        arrays["training_metadata"] = np.array(json.dumps(card, sort_keys=True, default=str))
        atomic_savez(tmp / name, **arrays)
        export_rig_and_viewer(arrays, tmp, name)
        atomic_write_json(tmp / CARD_JSON, card)
        atomic_write_text(tmp / CARD_MD, markdown)
    return out
