"""The release stage: the promoted configuration's fit -> ``release/`` (NPZ, cards, figures, rig, viewer), atomically."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from aumesh.card.model_card import model_card_markdown
from aumesh.config import Config
from aumesh.core.io import atomic_directory, atomic_savez, atomic_write_json, atomic_write_text
from aumesh.model.release import CARD_JSON, CARD_MD, NPZ_NAME, release_arrays
from aumesh.pipeline import integrity
from aumesh.pipeline.model_files import CV_NPZ, MODEL_NPZ
from aumesh.pipeline.prepared_files import REFERENCE_FILE
from aumesh.pipeline.release import build_card, load_model, refuse_implausible_face, refuse_nonfinite
from aumesh.stages.common import check_columns, start_stage


def main(cfg: Config) -> Path:
    """Write ``paths.release_dir`` atomically (NPZ, ``model_card.json``, ``MODEL_CARD.md``, figures, AU directions,
    glTF rig, viewer) and return it: a failure leaves the previous release as it was."""
    start_stage("release", cfg)
    from aumesh.card import directions, limits, render
    from aumesh.export import gltf, viewer

    model_dir, prepared_dir = Path(cfg.paths.model_dir), Path(cfg.paths.prepared_dir)
    promotion = None
    if Path(cfg.paths.promotion_file).exists():
        promotion = json.loads(Path(cfg.paths.promotion_file).read_text()).get("promoted") or None
    check_columns(cfg)
    integrity.verify_prepared(prepared_dir, integrity.load_summary(prepared_dir), [REFERENCE_FILE])
    card = build_card(cfg, model_dir, prepared_dir, promotion)
    model = load_model(model_dir)
    reference = integrity.load_reference(prepared_dir)
    refuse_nonfinite({"coef": model["coef"], "intercept": model["mesh_intercept"]}, model_dir / MODEL_NPZ)
    card["data"]["face_shape"] = refuse_implausible_face(
        model["mesh_intercept"], reference["mean_aligned_mesh"], model_dir / MODEL_NPZ, prepared_dir / REFERENCE_FILE
    )
    arrays = release_arrays(
        model["coef"],
        model["mesh_intercept"],
        model["feature_columns"].tolist(),
        int(model["n_components"]),
        reference,
        card_text="",
        metadata=card,
        uncorrected_coef=model.get("coef_uncorrected"),
        identification={k: v for k, v in model.items() if k.startswith("au_identification_")},
    )
    refuse_nonfinite(arrays, model_dir / MODEL_NPZ)  # before anything is written: the previous release stays
    with atomic_directory(cfg.paths.release_dir) as tmp:
        npz_path = tmp / NPZ_NAME
        atomic_savez(npz_path, **arrays)  # figures are rendered from the NPZ alone
        figures = render.render_release(npz_path, tmp / "figures", cv_path=model_dir / CV_NPZ)
        report = directions.au_direction_report(npz_path)
        report["source"] = NPZ_NAME  # not the temp folder it was read from
        directions.write_report(report, tmp / "au_directions.json")
        card["au_directions"] = {au: r["verdict"] for au, r in report["aus"].items()}
        card["warnings"] = limits.release_warnings(card, card["au_directions"], limits.au_field_iod(arrays))
        markdown = model_card_markdown(card, directions.report_markdown_table(report), [str(f) for f in figures])
        arrays["model_card"] = np.array(markdown)
        arrays["training_metadata"] = np.array(json.dumps(card, sort_keys=True, default=str))
        atomic_savez(npz_path, **arrays)
        gltf.write_glb(arrays, tmp / gltf.GLB_NAME, source=NPZ_NAME)
        viewer.write_viewer(arrays, tmp / viewer.VIEWER_NAME, source=NPZ_NAME)
        atomic_write_json(tmp / CARD_JSON, card)
        atomic_write_text(tmp / CARD_MD, markdown)
    return Path(cfg.paths.release_dir)
