"""``viewer.html``: one self-contained, offline page to play with a release (``aumesh view``).

A shaded face (three.js, WebGL) driven by 20 AU sliders and 3 pose sliders, each an
``<input type="range">`` named by its input column (``AU12``, ``Pitch``, ...), a reset button
and the model card's numbers. The page computes the card's prediction itself
(``flat = x @ coef + intercept``; with ``coef_full`` the pose-conditioned full design) from the
release's arrays, embedded exactly (base64 float32), and turns the head at render time with
the card's ``Rotation.from_euler("xyz", [Pitch, Yaw, Roll])``. The camera looks along -z with
y up: the card's canonical frame.

The canvas fills the window beside the panel; three.js's own ``OrbitControls`` (drag turns the
view, the wheel zooms, right-drag pans) move the camera, never the model. The panel has the FACS
names beside the AU codes (:data:`aumesh.core.schema.AU_NAMES`), "Copy as JSON" (the current
values as ``{"AU01": 0, ..., "Pitch": 0, "Yaw": 0, "Roll": 0}``, ready for
``aumesh.predict_mesh(m, json.loads(text))``) and a PNG snapshot of the canvas.

three.js is not downloaded at view time: the locked npm package (``package-lock.json``,
installed into ``node_modules/`` by ``make tools``) is inlined as ES modules in data: URLs
named by the page's import map: ``three.module.js``, ``three.core.js`` (``three.module.js``'s
import of ``./three.core.js``, which a data: URL cannot resolve, is renamed to the bare specifier
``three/core``) and ``examples/jsm/controls/OrbitControls.js`` (it imports only ``three``). No
network, no CDN: the file works from disk, offline.

**Clips** (issue 36): the page plays a video's py-feat table, opened by a file picker or a drop (CSV or
``.csv.gz``, decompressed by the browser's ``DecompressionStream``; parsed by column name with
:func:`aumesh.data.clip.read_clip`'s rules, ported: no-face rows, the largest face (the face track where two are
about the same size: issue 44), videos by their input paths shown by their stems where unique, either detector's mesh,
the frame rate from ``approx_time``, :func:`~aumesh.data.clip.bridge`'s gap rule), or embedded by ``aumesh view
NPZ --clip TABLE`` (:func:`table_clips`: ``read_clip`` + ``bridged_weights``, any table format, compact base64
arrays). Either way the recorded mesh is in frame pixels on every axis, converted by the ingest's rules (issue 41;
docs/conventions.md, "py-feat's mesh units"): ``read_clip`` runs the ingest's own functions, the page's port runs the
numbers :func:`unit_rules` passes it, and both give the ingest's cleaned mesh bit for bit; the status line says what
was converted (:data:`aumesh.data.clip.MESH_UNIT_NOTES`). One code path does the rest for both: the frame's bridged weights drive the sliders (pose 0 unless "follow
pose"); the frame's recorded mesh is turned into the card's frame (``canonical_frame``, ported) and aligned onto the
model's predicted mesh with the card's similarity Procrustes on the 12 anchors (Horn's quaternion method: JavaScript
has no SVD; equal to ``umeyama_batch``); the model's face is coloured by the per-vertex distance (viridis, in
inter-ocular distances of the release's neutral face). ``window.aumeshViewer.clip`` exposes it to scripts and tests.

**Identification** (issue 43): when the release records the AU identification screen
(:func:`aumesh.export.identification.release_identification`; :func:`slider_identification`), a flagged AU's slider is
greyed and disabled (a clip still drives it: a frame's prediction uses every AU the detector gave) with a one-line reason
under it, and a "partner group" slider (``AU09+AU10``) moves both members by the same amount: the field ``B_k + B_j``,
which the data identifies when its members are not. The page's values, "Copy as JSON" and the mesh are the members'
own values plus their groups'; a release without the screen shows no flags and no group slider.

**Support** (issue 41): when the release records its training data's ranges (:func:`slider_support`), each AU
slider's track beyond the largest value training saw is hatched, its value turns orange there, and an AU the data
never expressed (training p99 below 0.05) is labelled "not in training data" (its FACS name in the row's tooltip);
the marks are on the rows (``data-beyond``, ``data-support``) for scripts and tests.

Every string the page embeds (the card's rows: run names and ids, promotion fields, config
values; the source name) travels as JSON inside ``<script type="application/json">`` with ``<``,
``>``, ``&``, U+2028 and U+2029 written as ``\\uXXXX`` escapes (:func:`script_json`), so no text can
close the script element or open a comment in it, and the page puts it in the DOM as text only.
"""

from __future__ import annotations

import base64
import json
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.core.schema import (
    ANCHOR_INDICES,
    AU_COLUMNS,
    AU_NAMES,
    INPUT_COLUMNS,
    N_VERTICES,
    POSE_COLUMNS,
    unflatten_axis_major,
)
from aumesh.geometry import face

VIEWER_NAME = "viewer.html"
THREE_ENV = "AUMESH_NODE_MODULES"
_TEMPLATE = Path(__file__).with_name("viewer.html")
_CORE_IMPORT = "'./three.core.js'"
CORE_SPECIFIER = "three/core"
ORBIT_SPECIFIER = "three/addons/controls/OrbitControls.js"  # three.js's own name for it (its docs' import line)
_ORBIT_FILE = Path("examples", "jsm", "controls", "OrbitControls.js")  # relative to the package folder
_PLACEHOLDER = re.compile(r"__(IMPORT_MAP|AUMESH_DATA)__")
# JSON inside <script>: these characters could end the element ("</script>"), open a comment ("<!--") that
# swallows the rest of the page, start an entity, or end a JavaScript line; JSON's \uXXXX keeps their meaning.
_SCRIPT_ESCAPES = {"<": "\\u003c", ">": "\\u003e", "&": "\\u0026", "\u2028": "\\u2028", "\u2029": "\\u2029"}
DEFAULT_POSE_LIMITS = {"Pitch": 0.5, "Yaw": 0.7, "Roll": 0.5}  # radians, when the card has no pose filter


def find_node_modules(required: list[str], what: str) -> Path:
    """The ``node_modules`` folder holding every file of ``required`` (paths inside it): ``$AUMESH_NODE_MODULES``,
    else ``./node_modules``, else the repository's. Shared by the viewer (three.js) and the DVC plots template (vega).

    Raises
    ------
    FileNotFoundError
        Naming ``what`` was looked for, the places searched and the fix (``make tools``).
    """
    candidates = [
        Path(os.environ[THREE_ENV]) if os.environ.get(THREE_ENV) else None,
        Path.cwd() / "node_modules",
        Path(__file__).resolve().parents[3] / "node_modules",
    ]
    searched = []
    for base in filter(None, candidates):
        searched.append(str(base))
        if all((base / name).is_file() for name in required):
            return base
    raise FileNotFoundError(
        f"{what} not found in "
        + ", ".join(searched)
        + f". Fix: run `make tools` (npm ci) in the aumesh repository, or set {THREE_ENV} to a "
        "node_modules folder holding it."
    )


def find_three() -> Path:
    """three.js's ``build/`` folder (:func:`find_node_modules`)."""
    return (
        find_node_modules(
            ["three/build/three.module.js", "three/build/three.core.js"], "three.js (viewer.html inlines it; no CDN)"
        )
        / "three"
        / "build"
    )


def _data_url(text: str) -> str:
    return "data:text/javascript;base64," + base64.b64encode(text.encode("utf-8")).decode("ascii")


def module_urls(build: Path | None = None) -> dict[str, str]:
    """The page's import map: specifier -> data: URL of three.js's ES modules.

    ``three`` (``three.module.js``, its import of ``./three.core.js`` renamed to the bare specifier
    ``three/core``), ``three/core`` (``three.core.js``) and :data:`ORBIT_SPECIFIER`
    (``examples/jsm/controls/OrbitControls.js``, which imports ``three`` only), all from the same package.
    """
    build = build or find_three()
    module = (build / "three.module.js").read_text(encoding="utf-8")
    if _CORE_IMPORT not in module:
        raise ValueError(
            f"{build / 'three.module.js'}: no import of {_CORE_IMPORT}; this three.js layout is not "
            "supported. Fix: install the version in package-lock.json (`make tools`)."
        )
    core = (build / "three.core.js").read_text(encoding="utf-8")
    if "from './" in core:
        raise ValueError(f"{build / 'three.core.js'} imports other files; not supported. Fix: `make tools`.")
    orbit_path = build.parent / _ORBIT_FILE
    if not orbit_path.is_file():
        raise FileNotFoundError(
            f"{orbit_path} not found (the viewer's orbit and zoom). Fix: `make tools` "
            "(npm ci) installs the whole 'three' package."
        )
    orbit = orbit_path.read_text(encoding="utf-8")
    if re.search(r"""from\s*['"]\.""", orbit):
        raise ValueError(f"{orbit_path} imports relative files; only 'three' can be resolved. Fix: `make tools`.")
    return {
        "three": _data_url(module.replace(_CORE_IMPORT, json.dumps(CORE_SPECIFIER))),
        CORE_SPECIFIER: _data_url(core),
        ORBIT_SPECIFIER: _data_url(orbit),
    }


def script_json(value: Any) -> str:
    """``value`` as JSON safe inside an HTML ``<script>`` element.

    ``<``, ``>``, ``&``, U+2028 and U+2029 become ``\\u003c``, ``\\u003e``, ``\\u0026``, ``\\u2028``,
    ``\\u2029``: the same JSON value (``JSON.parse`` gives the original text back), but no ``</script>``,
    ``<!--`` or ``<script`` can appear in the page's source, whatever the strings hold.
    """
    # ensure_ascii: the page stays ASCII (no encoding question when written); U+2028/9 are escaped by it too
    text = json.dumps(value, allow_nan=False)
    return re.sub("[<>&\u2028\u2029]", lambda m: _SCRIPT_ESCAPES[m.group(0)], text)


def _b64(array: np.ndarray, dtype: str = "<f4") -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).tobytes()).decode("ascii")


def clip_data(clip: Any, weights: np.ndarray | None = None) -> dict:
    """One :class:`aumesh.data.clip.Clip` as the page's JSON (``aumesh view NPZ --clip TABLE``).

    Frame numbers as a list, ``has_face`` as 0/1; the AUs, pose and ``weights`` (the clip's
    :func:`~aumesh.data.clip.bridged_weights`, the default) as base64 float64 (the page's sliders show exactly
    what ``aumesh animate`` writes); the recorded mesh, vertex-major ``(n, 478, 3)``, as base64 float32 with NaN
    rows where no face, like the release's arrays: already in frame pixels (``read_clip`` converts it with the
    ingest's functions; ``mesh_units`` says how, a key of :data:`~aumesh.data.clip.MESH_UNIT_NOTES`), so the
    page converts only the tables dropped on it (:func:`unit_rules`). The page times the frames itself
    (``frame / fps``, the clip's rule) and bridges the pose by the same rule.
    """
    from aumesh.data.clip import bridged_weights

    weights = bridged_weights(clip) if weights is None else np.asarray(weights, dtype=np.float64)
    return {
        "source": str(clip.source),
        "video": str(clip.video),
        "frame": [int(f) for f in clip.frame],
        "fps": float(clip.fps),
        "fps_source": str(clip.fps_source),
        "has_face": [int(bool(v)) for v in clip.has_face],
        "aus": _b64(clip.aus, "<f8"),
        "pose": _b64(clip.pose, "<f8"),
        "weights": _b64(weights, "<f8"),
        "mesh": None if clip.mesh is None else _b64(clip.mesh),
        "frame_size": None if clip.frame_size is None else [float(v) for v in clip.frame_size],
        "mesh_units": str(clip.mesh_units),
    }


def unit_rules() -> dict:
    """The ingest's unit rules as the page's JSON, so a table dropped on the page is converted by the same numbers
    as ``read_clip`` converts an embedded one (docs/conventions.md, "py-feat's mesh units"): the vertices whose
    spans judge the units (:data:`aumesh.data.units.SHAPE_VERTICES`), :data:`~aumesh.data.units.NORMALIZED_MAX_EXTENT`,
    :data:`~aumesh.data.units.NORMALIZED_MAX_RECT_FRACTION`, the detectors' z units (:data:`~aumesh.data.units.Z_CROP`:
    name and divisor), the FaceRect and frame-size columns, and the words for each outcome
    (:data:`~aumesh.data.clip.MESH_UNIT_NOTES`); with them the face track's ambiguity ratio
    (:data:`~aumesh.data.face_track.AMBIGUOUS_AREA_RATIO`) and the columns a header may not repeat
    (:data:`~aumesh.data.pyfeat.READ_COLUMNS`)."""
    from aumesh.data import face_track, pyfeat, units
    from aumesh.data.clip import MESH_UNIT_NOTES

    return {
        "face_box_origin": list(pyfeat.FACE_BOX_ORIGIN),
        "ambiguous_area_ratio": float(face_track.AMBIGUOUS_AREA_RATIO),
        "read_columns": sorted(pyfeat.READ_COLUMNS),
        "shape_vertices": [int(i) for i in units.SHAPE_VERTICES],
        "normalized_max_extent": float(units.NORMALIZED_MAX_EXTENT),
        "normalized_max_rect_fraction": float(units.NORMALIZED_MAX_RECT_FRACTION),
        "z_crop": {det: [unit, float(divisor)] for det, (unit, divisor) in units.Z_CROP.items()},
        "face_box_size": list(pyfeat.FACE_BOX_SIZE),
        "frame_size": list(pyfeat.FRAME_SIZE),
        "notes": dict(MESH_UNIT_NOTES),
    }


def card_rows(metadata: Mapping[str, Any]) -> list[tuple[str, str]]:
    """The card's numbers as (label, text) rows, from ``training_metadata`` (``model_card.json``); absent ones skipped."""

    def get(*keys):
        node: Any = metadata
        for k in keys:
            if not isinstance(node, Mapping) or k not in node:
                return None
            node = node[k]
        return node

    rows = []

    def add(label, value, fmt="{}"):
        if value is not None:
            rows.append((label, fmt.format(*value) if isinstance(value, tuple) else fmt.format(value)))

    cv = get("cv") or {}
    if "r2_mean" in cv:
        add("CV R² (variance-weighted)", (cv["r2_mean"], cv.get("r2_std", float("nan"))), "{:.4f} ± {:.4f}")
    if "r2_displacement_mean" in cv:
        add(
            "CV R² of AU displacement",
            (cv["r2_displacement_mean"], cv.get("r2_displacement_std", float("nan"))),
            "{:.4f} ± {:.4f}",
        )
    add("CV MAE (px)", cv.get("mae_mean"), "{:.4f}")
    add("CV per-vertex error (px)", cv.get("vertex_error_mean"), "{:.4f}")
    add("folds", cv.get("r2_folds") and ", ".join(f"{v:.4f}" for v in cv["r2_folds"]))
    add("n_components", get("model", "n_components"))
    add("features", get("config", "features", "name"))
    add("target", get("config", "preprocess", "target"))
    frames, videos = get("data", "n_frames"), get("data", "n_videos")
    if frames is not None:
        add("training data", (frames, videos), "{:,} frames, {} videos")
    add("CV groups", get("config", "cv", "group"))
    add("git commit", get("provenance", "git_commit"))
    # two runs: the one that built these exact arrays (dvc repro), and the sweep child promoted to choose the config
    add("build run (MLflow)", get("mlflow", "run_id"))
    promotion = get("promotion")
    if isinstance(promotion, Mapping):
        name, run_id = promotion.get("run_name"), promotion.get("run_id")
        add("promoted run (MLflow)", f"{name} ({run_id})" if name and run_id else (name or run_id))
        add("sweep (MLflow)", promotion.get("parent_run_id"))
        add("promotion", promotion.get("criterion"))
        add("compared", promotion.get("compared") or None)
        overrides = promotion.get("config_overrides")
        add("config overrides", " ".join(map(str, overrides)) if isinstance(overrides, list) else overrides)
        model = promotion.get("registered_model")
        if model:
            version, alias = promotion.get("model_version"), promotion.get("alias")
            add("registered model", f"{model}" + (f" v{version}" if version else "") + (f" @{alias}" if alias else ""))
    add("source", get("source"))
    return [(label, str(text)) for label, text in rows]


#: The page's heading and the heading of its input sliders, by family (issue 46).
PAGE_TITLES: dict[str, tuple[str, str]] = {
    "au": ("aumesh: AUs + head pose \u2192 478-vertex face mesh", "Action Units (intensity 0..1)"),
    "blendshapes": (
        "aumesh: blendshapes + head pose \u2192 478-vertex face mesh",
        "MediaPipe blendshapes (score 0..1; ARKit-style names)",
    ),
    "emotions": ("aumesh: emotions + head pose \u2192 478-vertex face mesh", "Emotions (probability 0..1)"),
}


def slider_support(npz: Mapping[str, Any]) -> dict | None:
    """What the page marks on the AU sliders (:func:`aumesh.model.support.release_support`): ``{"bound": "max" |
    "p99", "upper": {AU: the largest value training saw}, "p99": {AU: p99}, "unsupported": [AU, ...]}``, None for a
    release that records no ranges (nothing is marked). A slider's track beyond ``upper`` is hatched; an unsupported
    AU's row says "not in training data"."""
    from aumesh.model import support

    found = support.release_support(npz)
    if found is None:
        return None
    names = [str(c) for c in np.asarray(npz.get("au_columns", AU_COLUMNS)).tolist()]  # a family's au_view: its inputs

    def finite(values: Mapping[str, float]) -> dict[str, float]:
        return {a: float(v) for a, v in values.items() if a in names and np.isfinite(v)}

    return {
        "bound": found.bound,
        "upper": finite(found.upper),
        "p99": finite(found.p99),
        "unsupported": [a for a in names if a in found.unsupported],
    }


def slider_identification(npz: Mapping[str, Any], where: str = "release") -> dict | None:
    """What the page says of the AU identification screen (:func:`aumesh.export.identification.release_identification`):
    ``{"flag_below", "sigma_star": {AU: float | None}, "partner": {AU: AU}, "flagged": {AU: the reason's sentence},
    "short": {AU: the line under its slider}, "groups": [{"name": "AU09+AU10", "members": ["AU09", "AU10"],
    "flagged": ["AU10"]}, ...]}``, None for a release without the screen (nothing greyed, no group slider). A group's
    slider goes under its last flagged member's reason line."""
    from aumesh.export.identification import release_identification

    found = release_identification(npz, where)
    if found is None:
        return None
    return {
        "flag_below": found.flag_below,
        "sigma_star": dict(found.sigma_star),
        "partner": dict(found.partner),
        "flagged": {au: found.reason(au) for au in found.flagged},
        "short": {au: found.short_reason(au) for au in found.flagged},
        "groups": [
            {
                "name": name,
                "members": list(members),
                "flagged": [a for a in found.flagged if found.group_name(a) == name],
            }
            for name, members in found.groups().items()
        ],
    }


def viewer_html(
    npz: Mapping[str, Any],
    source: str = "",
    modules: Mapping[str, str] | None = None,
    clips: list[dict] | None = None,
) -> str:
    """The viewer page for release arrays ``npz`` (the card's keys; ``coef_full`` used when present).

    ``modules`` is the import map (:func:`module_urls`, read from ``node_modules`` when None). ``clips``: videos
    to play, embedded (:func:`clip_data` each; the page opens the first, a selector the others).
    """
    from aumesh.model.family_inference import au_view, release_family

    family = release_family(npz)
    if family != "au":  # a blendshape or emotion release (issue 46): its inputs' sliders, by its own names
        npz = au_view(npz)
    columns = [str(c) for c in np.asarray(npz["input_columns"]).tolist()]
    if family == "au" and columns != list(INPUT_COLUMNS):
        raise ValueError(
            f"{source or 'release'}: 'input_columns' is {columns}, expected the card's {list(INPUT_COLUMNS)}"
        )
    inputs = [str(c) for c in np.asarray(npz["au_columns"]).tolist()]
    intercept = np.asarray(npz["intercept"], dtype=np.float32)
    base = unflatten_axis_major(intercept).astype(np.float64)
    metadata = json.loads(str(npz["training_metadata"])) if "training_metadata" in npz else {}
    pose_filter = (metadata.get("config") or {}).get("preprocess", {}).get("pose_filter", {}) if metadata else {}
    limits = dict(DEFAULT_POSE_LIMITS)
    if pose_filter.get("max_abs_pitch_deg"):
        limits["Pitch"] = round(float(np.radians(pose_filter["max_abs_pitch_deg"])), 2)
    if pose_filter.get("max_abs_yaw_deg"):
        limits["Yaw"] = round(float(np.radians(pose_filter["max_abs_yaw_deg"])), 2)
    data = {
        "n_vertices": N_VERTICES,
        "input_columns": columns,
        "au_columns": inputs,
        "pose_columns": list(POSE_COLUMNS),
        "au_names": dict(AU_NAMES) if family == "au" else {},
        "family": family,
        "title": PAGE_TITLES[family][0],
        "inputs_heading": PAGE_TITLES[family][1],
        "au_max": 1.0,
        "pose_limits": limits,
        "intercept": _b64(intercept),
        "coef": _b64(npz["coef"]),
        "triangles": face.outward_triangles(base, face.triangulate(base)).ravel().tolist(),
        "anchor_indices": list(ANCHOR_INDICES),  # the card's 12 Procrustes anchors (a clip's recorded mesh)
        "clips": list(clips or []),
        "card": card_rows(metadata),
        "source": f"release: {source}" if source else "",
        "support": slider_support(npz),
        "identification": slider_identification(npz, source or "release"),
        "units": unit_rules(),  # a dropped table's mesh converted by the ingest's rules (clip_data's are already)
    }
    if "coef_full" in npz:
        data["coef_full"] = _b64(npz["coef_full"])
        data["input_columns_full"] = [str(c) for c in np.asarray(npz["input_columns_full"]).tolist()]
    fill = {"IMPORT_MAP": script_json({"imports": dict(modules or module_urls())}), "AUMESH_DATA": script_json(data)}
    # one pass: a placeholder's name inside the embedded text is never substituted again
    return _PLACEHOLDER.sub(lambda m: fill[m.group(1)], _TEMPLATE.read_text(encoding="utf-8"))


def write_viewer(npz: Mapping[str, Any], path: str | Path, source: str = "", clips: list[dict] | None = None) -> Path:
    """Write :func:`viewer_html` to ``path`` atomically."""
    from aumesh.core.io import atomic_write_text

    return atomic_write_text(path, viewer_html(npz, source, clips=clips))


def table_clips(
    path: str | Path, video: str | None = None, fps: float | None = None, mesh_units: str = "detector"
) -> list[dict]:
    """The page's clips (:func:`clip_data`) of a py-feat table, read once: ``video`` only, or every video it holds
    (a video without a face is left out while others play). ``mesh_units``: ``detector`` (z converted by the
    detector's crop) or ``pixels`` (z as written), as :func:`~aumesh.data.clip.read_clip`'s."""
    from aumesh.core.errors import TableError
    from aumesh.data.clip import read_clip, read_table

    if video is not None:
        return [clip_data(read_clip(path, video=video, fps=fps, mesh_units=mesh_units))]
    table = read_table(path)
    names = table.videos
    if len(names) == 1:  # its own error (no face, ...), as read_clip gives it
        return [clip_data(table.clip(names[0], fps=fps, mesh_units=mesh_units))]
    clips, failed = [], []
    for name in names:  # every video, for the page's selector
        try:
            clips.append(clip_data(table.clip(name, fps=fps, mesh_units=mesh_units)))
        except TableError as err:
            failed.append(err)
    if not clips:
        raise failed[0]
    return clips
