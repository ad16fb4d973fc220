"""A family release's ``MODEL_CARD.md`` (issue 46): the AU card's sections, told about the family's inputs.

Written from the family's ``model_card.json`` (:func:`aumesh.pipeline.release_family.build_family_card`) with the AU
card's pieces (:mod:`aumesh.card.model_card`: the data lines, detector, face shape, runs, frame and pose text;
:func:`aumesh.card.limits.limits_section`); what is AU-only there (the AU-field reliability, the FACS table, the AU
identification screen, the 23-row ``coef``) is replaced by the family's: its inputs, the data's p99 per input and the
inputs it never expressed, the direction check of the family, and py-feat's loader.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from aumesh.card.limits import CHECKED_FAMILY, limits_section
from aumesh.card.markdown import md_code, md_text
from aumesh.card.model_card import (
    FRAME_TEXT,
    POSE_TEXT,
    TARGET_WORDS,
    _face_shape_lines,
    _ingest_lines,
    _runs_lines,
    _url_path,
)
from aumesh.model import support

#: py-feat's loader per family (``feat/plotting.py``) and the argument ``plot_face_mesh`` takes
LOADERS = {
    "blendshapes": ("load_blendshape_face_mesh_model", "blendshapes", "jawOpen"),
    "emotions": ("load_emotion_face_mesh_model", "emotion", "happiness"),
}


def _p99_lines(card: dict[str, Any]) -> list[str]:
    """The section on what the data expressed: each input's p99 (py-feat's ``feature_p99``) and the unsupported."""
    data, fam = card["data"], card["family"]
    ranges = data.get("input_ranges") or {}
    unsupported = list(data.get("unsupported_inputs") or [])
    p = data.get("p99_range") or {}
    lines = [
        "## What the training data expressed",
        "",
        f"Each input's 99th percentile over the {data['n_frames']:,} training frames is the NPZ's `feature_p99`: "
        "py-feat clips inputs to `[0, feature_p99]` before predicting (`predict_face_mesh_from_features`), so the "
        "model is only used within what the data showed. "
        f"p99 over the inputs: {p.get('min', float('nan')):.3g} to {p.get('max', float('nan')):.3g}.",
        "",
    ]
    if unsupported:
        lines += [
            f"**Never expressed** ({len(unsupported)} of {len(fam['inputs'])}; `unsupported_features`, training p99 "
            f"below {support.UNSUPPORTED_P99:g}): {md_text(', '.join(unsupported))}. Their fields are the fit's guess, "
            "not something the data showed; py-feat warns when one is given above 0.02.",
            "",
        ]
    else:
        lines += [f"Every input was expressed (training p99 at least {support.UNSUPPORTED_P99:g}).", ""]
    lines += ["| input | p1 | p50 | p99 | max | share of frames > 0.1 |", "|---|---:|---:|---:|---:|---:|"]
    for name in fam["inputs"]:
        r = ranges.get(name)
        if r is None:
            continue
        active = r.get("active_fraction")
        lines.append(
            f"| {md_text(name)}{' (never expressed)' if name in unsupported else ''} | {r['p1']:.3g} | {r['p50']:.3g} "
            f"| {r['p99']:.3g} | {r['max']:.3g} | {'' if active is None else f'{active:.1%}'} |"
        )
    return lines + [""]


def _detector_lines(data: dict[str, Any], family: str) -> list[str]:
    """The detector of the training tables (``data.detector``, :func:`aumesh.model.support.detector_summary`): the
    family's values mean what that detector's network writes."""
    detector = data.get("detector")
    if not isinstance(detector, dict) or not detector.get("name"):
        return []
    sources = detector.get("sources") or {}
    listed = ", ".join(f"{md_text(k)} {v:,}" for k, v in sources.items())
    return [
        f"- Detector: **{md_text(detector['name'])}**" + (f" (sources: {listed})" if listed else "") + f": the "
        f"{family} are what that detector writes (Detectorv2: its multitask network's; MPDetector: MediaPipe's "
        f"models'). Give the model {family} of the same detector."
    ]


def _directions_lines(card: dict[str, Any]) -> list[str]:
    """The family's direction check, as recorded in the card (``directions``: verdict and message)."""
    d = card.get("directions")
    if not d:
        return []
    return [
        "## Direction check",
        "",
        f"Verdict: **{md_text(d.get('verdict'))}**. {md_text(d.get('message', ''))}",
        f"Details: `{md_text(d.get('file', ''))}`.",
        "",
    ]


def family_card_markdown(card: dict[str, Any], figures: list[str]) -> str:
    """The human-readable card of a family release, generated from its ``model_card.json``."""
    cv, data, cfg, fam = card["cv"], card["data"], card["config"], card["family"]
    pre = cfg["preprocess"]
    family, k = fam["name"], len(fam["inputs"])
    loader, plot_arg, example = LOADERS[family]
    counts = data["counts"]
    folds = ", ".join(f"{v:.4f}" for v in cv.get("r2_folds", []))
    inputs = f"{k} {family}" + (" + 3 pose (Pitch, Yaw, Roll)" if fam["pose"] else "")
    inputs += f" + {3 * k} pose x {family}" if fam["interactions"] else ""
    per = data["n_frames"] / max(card["model"]["n_features"], 1)
    lines = [
        f"# {card['name']}",  # aumesh's own words (pipeline.release_family), as the AU card's title
        "",
        f"Linear PLS regression mapping py-feat's {k} {family} ({md_text(', '.join(fam['inputs'][:4]))}, ...) "
        + ("+ pose " if fam["pose"] else "")
        + f"to 478x3 = 1434 MediaPipe FaceMesh vertex coordinates, in py-feat's `{fam['pyfeat_feature']}` model "
        f"format: `feat.plotting.{loader}` reads `{fam['npz']}` (hub download replaced by the local path) and "
        f"`plot_face_mesh({plot_arg}=...)` draws it. Same frame as this training set's AU release (`release/`).",
        "",
        *(limits_section(card["warnings"], CHECKED_FAMILY) if "warnings" in card else []),
        "## Training data",
        "",
        f"- {data['n_frames']:,} frames from {data['n_videos']:,} videos ({per:,.0f} frames per design column; "
        f"data digest {md_code((data.get('digest') or {}).get('md5'))})",
        *_ingest_lines(counts, cfg.get("data", {})),
        *_detector_lines(data, family),
        f"- Input: {counts['frames_in']:,} frames / {counts['videos_in']:,} videos; pose-filtered to |yaw| <= "
        f"{pre['pose_filter']['max_abs_yaw_deg']} deg, |pitch| <= {pre['pose_filter']['max_abs_pitch_deg']} deg: "
        f"{counts['dropped_pose']:,} frames dropped",
        *_face_shape_lines(data.get("face_shape")),
        f"- Target: **{md_text(pre['target'])}**: " + TARGET_WORDS[pre["target"]].format(method=md_text("low-AU")),
        "",
        *_p99_lines(card),
        "## Method",
        "",
        f"- `PLSRegression(n_components={card['model']['n_components']})` (aumesh's exact kernel-PLS engine), "
        f"design {md_code(fam['features'])}: {inputs} = {card['model']['n_features']} features",
        f"- Released `coef`: ({card['model']['n_features']}, 1434), the {k} {family} rows first (py-feat predicts "
        f"`x @ coef[:{k}] + intercept`, pose implicit 0), then the design's other rows (`input_columns`)",
        "",
        f"## Out-of-sample performance ({cfg['cv']['n_splits']}-fold GroupKFold by {md_text(cfg['cv']['group'])})",
        "",
        "| metric | mean | std | folds |",
        "|---|---|---|---|",
        f"| variance-weighted R² | {cv.get('r2_mean', float('nan')):.4f} | {cv.get('r2_std', float('nan')):.4f} | "
        f"{folds} |",
    ]
    if "vertex_error_mean" in cv:
        lines.append(
            f"| mean per-vertex Euclidean error (px) | {cv['vertex_error_mean']:.4f} | "
            f"{cv.get('vertex_error_std', float('nan')):.4f} | "
            + ", ".join(f"{v:.4f}" for v in cv.get("vertex_error_folds", []))
            + " |"
        )
    lines += ["", *_directions_lines(card), *_runs_lines(card)]
    if figures:
        lines += (
            ["## Figures", ""]
            + [f"![{md_text(Path(f).stem)}](figures/{_url_path(Path(f).name)})" for f in figures]
            + [""]
        )
    lines += [
        "## Inference",
        "",
        "```python",
        "import feat.plotting as fp",
        f'fp.hf_hub_download = lambda *a, **k: "{fam["npz"]}"  # the local file instead of the hub',
        f"model = fp.{loader}()",
        f'fp.plot_face_mesh({plot_arg}={{"{example}": 0.8}}, model=model)  # by name; clipped to feature_p99',
        "```",
        "",
        "Without py-feat:",
        "",
        "```python",
        "import numpy as np",
        f'm = np.load("{fam["npz"]}", allow_pickle=False)',
        f'x = np.zeros({k}); x[m["feature_columns"].tolist().index("{example}")] = 0.8',
        f'flat = x @ m["coef"][:{k}] + m["intercept"]   # (1434,), pose 0',
        "mesh = np.stack([flat[:478], flat[478:956], flat[956:]], axis=1)  # axis-major -> (478, 3)",
        "```",
        "",
        "## Frame",
        "",
        FRAME_TEXT,
        "",
        POSE_TEXT,
        "",
        "## Provenance",
        "",
        f"- code: git {md_code(card['provenance'].get('git_commit'))}"
        + (" (dirty)" if card["provenance"].get("dirty") else ""),
        f"- data: {md_code((data.get('digest') or {}).get('md5'))}",
        f"- config: design {md_code(fam['features'])}, n_components {card['model']['n_components']}"
        + (" (promoted)" if card.get("promotion") else " (conf/'s own)"),
        f"- MLflow build run: {md_code(card['mlflow'].get('run_id'))} ({md_text(card['mlflow'].get('tracking_uri'))})"
        + (f"; promoted run: {md_code(card['promotion'].get('run_id'))}" if card.get("promotion") else ""),
        "- libraries: " + ", ".join(f"{md_text(a)} {md_text(b)}" for a, b in card["libraries"].items() if b),
        "",
    ]
    return "\n".join(lines)
