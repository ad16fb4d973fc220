"""The release's ``MODEL_CARD.md``: the readable card written from ``model_card.json``'s fields."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from aumesh.card.identification import correction_lines, identification_section
from aumesh.card.limits import limits_section
from aumesh.card.markdown import md_code, md_text
from aumesh.core.families import FEATURE_SETS
from aumesh.model.release import NPZ_NAME

CARD_SUMMARY = (
    "Linear PLS regression mapping 20 FACS AU intensities + 3 pose covariates (Pitch, Yaw, Roll) "
    "to 478x3 = 1434 MediaPipe FaceMesh vertex coordinates in a pose-canonical (Procrustes-aligned) "
    "frame. Deploy as 23-d input (AU + pose), pose = 0 for the canonical frontal view. "
    "Layout is axis-major [all x | all y | all z]."
)

FRAME_TEXT = (
    "The mesh is in the card's canonical frame: x toward the subject's left (canthus 263 has larger x than 33), "
    "y up (forehead above chin), z out of the face (the nose tip in front); right-handed. It is a proper rotation "
    "(no reflection) of the Procrustes-aligned frame, found from the anatomy of `mean_aligned_mesh` (the outer "
    "canthi 33 -> 263 give x, chin 152 -> forehead 10 gives y, the nose tip 1 the side z points to), so the release "
    "is the same whatever convention the tables use (image pixels with y down, or y up). Origin: the centroid of "
    "`mean_aligned_mesh`. Scale: unchanged, the Procrustes reference's units (the tables' pixels at the frames' "
    "mean face size)."
)
POSE_TEXT = (
    'Pose at render time: `R = Rotation.from_euler("xyz", [pitch, yaw, roll]).as_matrix(); posed = mesh @ R.T` '
    '(SciPy\'s lowercase "xyz" is extrinsic: R = Rz Ry Rx). In this frame positive yaw turns the nose toward the '
    "subject's left (+x), positive pitch tips the nose down (-y), positive roll raises the subject's left eye "
    "(counter-clockwise as seen from the front)."
)


TARGET_WORDS = {
    "absolute": "absolute aligned coordinates, pooled over all frames (the card's recipe)",
    "neutral": "aligned coordinates minus each video's neutral mesh ({method}); the AUs stay absolute",
    "within": "design and mesh demeaned per video (fixed effects: only how a face moves within its own video); "
    "released with the population intercept, mean mesh - mean design @ coef",
    "within_neutral": "design and mesh minus the mean of each video's neutral ({method}) frames; released with the "
    "population intercept, mean mesh - mean design @ coef",
}

TARGETS_NOTE = (
    "Targets, in short: `absolute` regresses whole faces on AUs, so any link between a person's resting AU readings "
    "and their face shape (detectors read a resting face as some expression) leaks identity into the AU fields. "
    "`neutral` removes each person's neutral face from the mesh only, so their AU baselines are left unexplained. "
    "`within` removes each video's mean from both sides and keeps only how a face moves when its AUs change: use it "
    "when you want what each AU does (sliders, FACS); use `absolute` to reproduce the reference card. R² in each "
    "target's own space measures different variance and is not comparable across targets; "
    "R² of the AU-driven displacement and the AU-field reliability are the same for every target."
)


def reliability_section(cv: dict[str, Any]) -> list[str]:
    """Card section: each AU's field reliability (cosine between fields fitted on different folds)."""
    lines = [
        "## AU-field reliability",
        "",
        "Cosine between each AU's displacement field fitted on each cross-validation fold alone (disjoint videos; "
        "mean over fold pairs; 1 = every subset of videos agrees). No ground truth needed. It measures the field's "
        "stability across video subsets; it does not detect detector-noise bias, which is the same in every subset "
        "(nor an AU the detector confuses with another, or one person in every fold): a field can be reliable and "
        "wrong. The section 'AU identification under detector noise' says which fields such noise could turn.",
        "",
        f"- median over AUs {cv['au_reliability_median']:.3f}, worst {cv['au_reliability_min']:.3f}"
        + (f"; {cv['n_aus_facs_pass']} of 20 AUs pass the FACS direction check" if "n_aus_facs_pass" in cv else ""),
        "",
        "| AU | reliability |",
        "|---|---:|",
    ]
    lines += [f"| {au} | {value:.3f} |" for au, value in cv["au_reliability"].items()]
    return lines + [""]


def _share(counts: dict[str, Any], key: str) -> str:
    """`` (1.2 %)``: the fraction a filter dropped, when the prepared summary records it."""
    return f" ({counts[key + '_fraction']:.1%})" if key + "_fraction" in counts else ""


def _ingest_lines(counts: dict[str, Any], data_cfg: dict[str, Any]) -> list[str]:
    """The card's lines on py-feat's rows (the ingest stage): no-face rows, other faces, units."""
    if "rows_in" not in counts:
        return []
    lines = [
        f"- py-feat rows read: {counts['rows_in']:,} from {counts.get('tables_in', 0):,} table(s); frames without a face "
        f"(py-feat's no-face rows) dropped: {counts['dropped_no_face']:,}{_share(counts, 'dropped_no_face')}"
    ]
    if counts.get("frames_with_several_faces"):
        how = data_cfg.get("face_selection", "largest")
        rule = {"largest": "the largest face box kept", "identity": "py-feat's Identity of the video's subject kept"}
        lines.append(
            f"- Frames with several faces: {counts['frames_with_several_faces']:,} ({md_text(rule.get(how, how))}; "
            f"{counts['dropped_extra_faces']:,} other face rows dropped"
            + (
                f", {counts['dropped_frames_without_subject']:,} frames without the subject dropped"
                if counts.get("dropped_frames_without_subject")
                else ""
            )
            + (
                f"; {counts['frames_ambiguous_faces']:,} of them with two faces of about the same size, where the "
                f"face continuing the video's track was kept"
                if counts.get("frames_ambiguous_faces")
                else ""
            )
            + ")"
        )
    # the ingest stage's conversions (aumesh.data.units; docs/conventions.md "py-feat's mesh units")
    done = []
    if counts.get("rows_z_from_chip"):
        done.append(
            f"z of {counts['rows_z_from_chip']:,} Detectorv2 face rows converted from its 0-1 chip units "
            f"(× FaceRectWidth, the square chip's side)"
        )
    if counts.get("rows_z_from_crop256"):
        done.append(
            f"z of {counts['rows_z_from_crop256']:,} MPDetector face rows converted from its 256-px crop units "
            f"(× FaceRectWidth / 256)"
        )
    if counts.get("rows_converted_from_normalized"):
        done.append(
            f"{counts['rows_converted_from_normalized']:,} face rows converted from normalized image units "
            f"(x, z × FrameWidth, y × FrameHeight)"
        )
    forced = " (data.mesh_units=pixels)" if data_cfg.get("mesh_units") == "pixels" else ""
    converted = sum(
        counts.get(k, 0) for k in ("rows_z_from_chip", "rows_z_from_crop256", "rows_converted_from_normalized")
    )
    others = counts.get("frames_out", converted) - converted
    if done:
        rest = f"; the other {others:,} rows in pixels as recorded{forced}" if others > 0 else ""
        lines.append(f"- Mesh units: frame pixels; {'; '.join(done)}{rest}")
    else:
        lines.append(f"- Mesh units: frame pixels, as recorded{forced}")
    return lines


def _face_shape_lines(shape: dict[str, Any] | None) -> list[str]:
    """The card's line on the AU=0 face's proportions (``data.face_shape``, the release stage's shape guard)."""
    if not shape:
        return []
    low, high = shape.get("accepted_depth_width", (None, None))
    return [
        f"- Face shape (the AU=0 face): depth/width {shape['depth_width']:.3g}, width/height "
        f"{shape['width_height']:.3g} (MediaPipe's canonical face 0.65 and 0.88; a release is refused outside "
        f"depth/width {low:g}-{high:g}, the mark of z in other units than x and y)"
    ]


def _detector_lines(data: dict[str, Any]) -> list[str]:
    """The card's line on the AU space: the detector of the training tables and what its AUs mean
    (``data.detector``, :func:`aumesh.model.support.detector_summary`); none for a card that does not record it."""
    detector = data.get("detector")
    if not isinstance(detector, dict) or not detector.get("name"):
        return []
    sources = detector.get("sources") or {}
    listed = ", ".join(f"{md_text(k)} {v:,}" for k, v in sources.items())
    return [
        f"- AU space: **{md_text(detector['name'])}**" + (f" (sources: {listed})" if listed else "") + ": "
        f"{md_text(detector.get('au_meaning', ''))}. Give the model AUs of the same detector."
    ]


def _runs_lines(card: dict[str, Any]) -> list[str]:
    """The card's "Runs" section: the promoted run (how the configuration was chosen) and the build run (what
    produced these arrays), each with its MLflow id; without a promotion, only the build run."""
    build = (card.get("runs") or {}).get("build") or card.get("mlflow") or {}
    p = card.get("promotion")
    where = f" in {md_code(build['tracking_uri'])}" if build.get("tracking_uri") else ""
    lines = [
        "## Runs",
        "",
        "This release names two MLflow runs: the one that chose its configuration and the one that built its arrays."
        if p
        else "This release was built by one MLflow run; no promotion chose its "
        "configuration (conf/'s own; `aumesh promote` records one).",
        "",
    ]
    if p:
        registered = (
            f"; registered as {md_code(p['registered_model'])} version {md_text(p.get('model_version'))}"
            + (f" ({md_code('@' + str(p['alias']))})" if p.get("alias") else "")
            if p.get("registered_model")
            else ""
        )
        lines += [
            f"- **Promoted run** {md_code(p.get('run_id'))}"
            + (f" ({md_text(p['run_name'])})" if p.get("run_name") else "")
            + f" of sweep {md_code(p.get('parent_run_id'))}: how the configuration was chosen. "
            f"Criterion: {md_text(p.get('criterion'))}" + registered + ".",
            f"  Compared: {md_text(p.get('compared', ''))}",
        ]
    lines += [
        f"- **Build run** {md_code(build.get('run_id'))}"
        + (f" ({md_text(build['run_name'])})" if build.get("run_name") else "")
        + f"{where}: the evaluate run of `dvc repro` that produced these exact arrays and the numbers above.",
        "",
    ]
    return lines


def _url_path(name: str) -> str:
    from urllib.parse import quote

    return quote(name)


def model_card_markdown(card: dict[str, Any], directions_table: str | None, figures: list[str]) -> str:
    """The human-readable card, generated from ``model_card.json``."""
    cv, data, cfg = card["cv"], card["data"], card["config"]
    pre, feats, model = cfg["preprocess"], cfg["features"], cfg["model"]
    folds = ", ".join(f"{v:.4f}" for v in cv["r2_folds"])
    counts = data["counts"]
    _, pose, interactions = FEATURE_SETS[feats["name"]]
    inputs = "20 AU" + (" + 3 pose (Pitch, Yaw, Roll)" if pose else "") + (" + 60 pose x AU" if interactions else "")
    degenerate = data.get("degenerate") or {}
    constant = degenerate.get("constant_inputs") or {}
    dead = degenerate.get("constant_features") or []
    lines = [
        f"# {card['name']}",
        "",
        CARD_SUMMARY,
        "",
        *(limits_section(card["warnings"]) if "warnings" in card else []),
        "## Training data",
        "",
        f"- {data['n_frames']:,} frames from {data['n_videos']:,} videos (data digest {md_code(data['digest'].get('md5'))})",
        *_ingest_lines(counts, cfg.get("data", {})),
        *_detector_lines(data),
        f"- Input: {counts['frames_in']:,} frames / {counts['videos_in']:,} videos",
        # numbers, booleans: typed by the configuration's schema (aumesh.config), printed as they are
        f"- Pose-filtered to |yaw| <= {pre['pose_filter']['max_abs_yaw_deg']} deg, |pitch| <= {pre['pose_filter']['max_abs_pitch_deg']} deg: "
        f"{counts['dropped_pose']:,} frames dropped{_share(counts, 'dropped_pose')}",
        *(
            [
                f"- Wild values (a vertex beyond {pre['alignment']['max_vertex_iod']:g} inter-ocular distances after "
                f"alignment, a corrupt export): {counts['dropped_wild_values']:,} frames dropped"
                f"{_share(counts, 'dropped_wild_values')}"
            ]
            if "dropped_wild_values" in counts
            else []
        ),
        f"- Per-frame Umeyama similarity Procrustes onto a GPA reference of anchors {list(pre['alignment']['anchor_indices'])}; "
        f"frames above the {pre['alignment']['outlier_quantile']:.0%} quantile of max anchor residual dropped: "
        f"{counts['dropped_alignment_outliers']:,}{_share(counts, 'dropped_alignment_outliers')} "
        f"(threshold {counts['alignment_residual_threshold']:.3g})",
        f"- Videos with no frames left (dropped): {counts['videos_dropped_no_frames_left']}"
        f"{_share(counts, 'videos_dropped_no_frames_left')}",
        *_face_shape_lines(data.get("face_shape")),
        *(
            [
                f"- **Constant inputs**: {md_text(', '.join(f'{c} = {v:g}' for c, v in constant.items()))} in every "
                f"training frame: the data cannot say what they do, so the model learned nothing from them "
                f"(their coefficients are exactly 0)"
            ]
            if constant
            else []
        ),
        f"- Target: **{md_text(pre['target'])}**: "
        + TARGET_WORDS[pre["target"]].format(method=md_text(pre["neutral"]["method"])),
        "",
        TARGETS_NOTE,
        "",
        "## Method",
        "",
        ("- Uncorrected fit (released as `coef_uncorrected`): " if correction_lines(card) else "- ")
        + f"`PLSRegression(n_components={card['model']['n_components']}, scale={model['scale']})` (aumesh's exact kernel-PLS engine)",
        *correction_lines(card),
        f"- Inputs for training: {inputs} = {card['model']['n_features']} features"
        + (
            f", of which {len(dead)} have no variance in the training data (constant inputs, or products with an input "
            f"that is 0 in every frame) and carry no information: {card['model']['n_features'] - len(dead)} "
            f"informative"
            if dead
            else ""
        )
        + "; released `coef`: 23 rows (AU + pose)"
        + ("; full design in `coef_full` / `input_columns_full`" if interactions else ""),
        *(
            [
                "- **Pose was not learned**: Pitch, Yaw and Roll were constant in the training data, so every pose and "
                "pose x AU coefficient is 0; a pose given at inference does not change the mesh, and the pose-conditioned "
                "claims above (pose covariates, interactions) do not hold for this release"
            ]
            if pose and dead and not degenerate.get("pose_learned", True)
            else []
        ),
        "",
        f"## Out-of-sample performance ({cfg['cv']['n_splits']}-fold GroupKFold by {md_text(cfg['cv']['group'])})",
        "",
        "| metric | mean | std | folds |",
        "|---|---|---|---|",
        f"| variance-weighted R² ({md_text(pre['target'])} target) | {cv['r2_mean']:.4f} | {cv['r2_std']:.4f} | {folds} |",
        f"| R² of AU-driven displacement from neutral | {cv['r2_displacement_mean']:.4f} | {cv['r2_displacement_std']:.4f} | "
        + ", ".join(f"{v:.4f}" for v in cv["r2_displacement_folds"])
        + " |",
        f"| MAE (px) | {cv['mae_mean']:.4f} | {cv['mae_std']:.4f} | "
        + ", ".join(f"{v:.4f}" for v in cv["mae_folds"])
        + " |",
        f"| mean per-vertex Euclidean error (px) | {cv['vertex_error_mean']:.4f} | {cv['vertex_error_std']:.4f} | "
        + ", ".join(f"{v:.4f}" for v in cv["vertex_error_folds"])
        + " |",
        "",
    ]
    if "au_reliability" in cv:
        lines += reliability_section(cv)
    lines += identification_section(card)
    lines += _runs_lines(card)
    if directions_table:
        lines += ["## AU directions (FACS check)", "", directions_table, ""]
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
        "import numpy as np",
        f'm = np.load("{NPZ_NAME}", allow_pickle=False)',
        'au = np.zeros(20); au[m["au_columns"].tolist().index("AU12")] = 1.0  # smile',
        "x = np.concatenate([au, np.zeros(3)])            # (23,) AU + pose (pitch, yaw, roll)",
        'flat = x @ m["coef"] + m["intercept"]            # (1434,)',
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
        f"- data: {md_code(data['digest'].get('md5'))}",
        f"- MLflow build run: {md_code(card['mlflow'].get('run_id'))} ({md_text(card['mlflow'].get('tracking_uri'))}"
        + (f", experiment {md_text(card['mlflow']['experiment'])}" if card["mlflow"].get("experiment") else "")
        + ")"
        + (f"; promoted run: {md_code(card['promotion'].get('run_id'))}" if card.get("promotion") else ""),
        "- libraries: " + ", ".join(f"{md_text(k)} {md_text(v)}" for k, v in card["libraries"].items() if v),
        "",
    ]
    return "\n".join(lines)
