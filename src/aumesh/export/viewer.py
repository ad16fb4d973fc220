"""``viewer.html``: one self-contained, offline page to play with a release (``aumesh view``).

A shaded face (three.js, WebGL) driven by 20 AU sliders and 3 pose sliders, each an
``<input type="range">`` named by its input column (``AU12``, ``Pitch``, ...), a reset button
and the model card's numbers. The page computes the card's prediction itself
(``flat = x @ coef + intercept``; with ``coef_full`` the pose-conditioned full design) from the
release's arrays, embedded exactly (base64 float32), and turns the head at render time with
the card's ``Rotation.from_euler("xyz", [Pitch, Yaw, Roll])``. The camera looks along -z with
y up: the card's canonical frame.

three.js is not downloaded at view time: the locked npm package (``package-lock.json``,
installed into ``node_modules/`` by ``make tools``) is inlined as its two ES modules in data: URLs
named by the page's import map (``three.module.js`` imports ``./three.core.js``, which a data: URL
cannot resolve: that one import is renamed to the bare specifier ``three/core``). No network, no CDN: the file works from disk, offline.
"""

from __future__ import annotations

import base64
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.data.schema import AU_COLUMNS, INPUT_COLUMNS, POSE_COLUMNS, N_VERTICES, unflatten_axis_major
from aumesh.geometry import face

VIEWER_NAME = "viewer.html"
THREE_ENV = "AUMESH_NODE_MODULES"
_TEMPLATE = Path(__file__).with_name("viewer.html")
_CORE_IMPORT = "'./three.core.js'"
CORE_SPECIFIER = "three/core"
DEFAULT_POSE_LIMITS = {"Pitch": 0.5, "Yaw": 0.7, "Roll": 0.5}  # radians, when the card has no pose filter


def find_three() -> Path:
    """three.js's ``build/`` folder: ``$AUMESH_NODE_MODULES``, else ``./node_modules``, else the repository's.

    Raises
    ------
    FileNotFoundError
        Naming the places searched and the fix (``make tools``).
    """
    candidates = [Path(os.environ[THREE_ENV]) if os.environ.get(THREE_ENV) else None,
                  Path.cwd() / "node_modules", Path(__file__).resolve().parents[3] / "node_modules"]
    searched = []
    for base in filter(None, candidates):
        build = base / "three" / "build"
        searched.append(str(build))
        if (build / "three.module.js").is_file() and (build / "three.core.js").is_file():
            return build
    raise FileNotFoundError("three.js not found (viewer.html inlines it; no CDN) in " + ", ".join(searched)
                            + f". Fix: run `make tools` (npm ci) in the aumesh repository, or set {THREE_ENV} to a "
                            "node_modules folder holding the 'three' package.")


def _data_url(text: str) -> str:
    return "data:text/javascript;base64," + base64.b64encode(text.encode("utf-8")).decode("ascii")


def three_module_urls(build: Path | None = None) -> tuple[str, str]:
    """three.js's two ES modules as data: URLs: ``three.module.js`` (its import of ``./three.core.js``
    renamed to the bare specifier ``three/core``) and ``three.core.js``; the page's import map maps both."""
    build = build or find_three()
    module = (build / "three.module.js").read_text(encoding="utf-8")
    if _CORE_IMPORT not in module:
        raise ValueError(f"{build / 'three.module.js'}: no import of {_CORE_IMPORT}; this three.js layout is not "
                         "supported. Fix: install the version in package-lock.json (`make tools`).")
    core = (build / "three.core.js").read_text(encoding="utf-8")
    if "from './" in core:
        raise ValueError(f"{build / 'three.core.js'} imports other files; not supported. Fix: `make tools`.")
    return _data_url(module.replace(_CORE_IMPORT, json.dumps(CORE_SPECIFIER))), _data_url(core)


def _b64(array: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype="<f4").tobytes()).decode("ascii")


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
        add("CV R² of AU displacement", (cv["r2_displacement_mean"], cv.get("r2_displacement_std", float("nan"))),
            "{:.4f} ± {:.4f}")
    add("CV MAE (px)", cv.get("mae_mean"), "{:.4f}")
    add("CV per-vertex error (px)", cv.get("vertex_error_mean"), "{:.4f}")
    add("folds", cv.get("r2_folds") and ", ".join(f"{v:.4f}" for v in cv["r2_folds"]))
    add("n_components", get("model", "n_components"))
    add("features", get("config", "features", "name"))
    add("target", get("config", "preprocess", "target"))
    frames, videos = get("data", "n_frames"), get("data", "n_videos")
    if frames is not None:
        add("training data", (frames, videos), "{:,} frames, {} videos")
    add("git commit", get("provenance", "git_commit"))
    add("MLflow run", get("mlflow", "run_id"))
    promotion = get("promotion")
    if isinstance(promotion, Mapping):
        add("promotion", promotion.get("criterion"))
    add("source", get("source"))
    return rows


def viewer_html(npz: Mapping[str, Any], source: str = "", three_urls: tuple[str, str] | None = None) -> str:
    """The viewer page for release arrays ``npz`` (the card's keys; ``coef_full`` used when present)."""
    columns = [str(c) for c in np.asarray(npz["input_columns"]).tolist()]
    if columns != list(INPUT_COLUMNS):
        raise ValueError(f"{source or 'release'}: 'input_columns' is {columns}, expected the card's {list(INPUT_COLUMNS)}")
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
        "input_columns": list(INPUT_COLUMNS), "au_columns": list(AU_COLUMNS), "pose_columns": list(POSE_COLUMNS),
        "au_max": 1.0, "pose_limits": limits,
        "intercept": _b64(intercept), "coef": _b64(npz["coef"]),
        "triangles": face.outward_triangles(base, face.triangulate(base)).ravel().tolist(),
        "card": card_rows(metadata), "source": f"release: {source}" if source else "",
    }
    if "coef_full" in npz:
        data["coef_full"] = _b64(npz["coef_full"])
        data["input_columns_full"] = [str(c) for c in np.asarray(npz["input_columns_full"]).tolist()]
    payload = json.dumps(data).replace("</", "<\\/")
    module_url, core_url = three_urls or three_module_urls()
    imports = json.dumps({"imports": {"three": module_url, CORE_SPECIFIER: core_url}})
    return _TEMPLATE.read_text(encoding="utf-8").replace("__IMPORT_MAP__", imports).replace("__AUMESH_DATA__", payload)


def write_viewer(npz: Mapping[str, Any], path: str | Path, source: str = "") -> Path:
    """Write :func:`viewer_html` to ``path`` atomically."""
    from aumesh.utils.io import atomic_write_text

    return atomic_write_text(path, viewer_html(npz, source))
