"""The release's record and checks: ``model_card.json`` from the evaluate stage's files, the runs it names, and the
refusals that keep a non-finite or flat model out of a release."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.config import WHERE_GROUPS as WHERE_GROUPS  # re-exported: the one list is aumesh.config's
from aumesh.config import Config, without_where
from aumesh.core import provenance
from aumesh.pipeline import integrity
from aumesh.pipeline.model_files import METRICS_JSON, MODEL_NPZ, TRACKING_JSON

_ESTIMATORS = {
    "none": "aumesh.model.pls.PLSRegression (exact kernel PLS, = sklearn PLSRegression)",
    "corrected": "aumesh.model.eiv.corrected_fit (floored corrected least squares, within-video design; "
    "docs/method.md eqs. 4-5)",
    "instruments": "aumesh.model.eiv.instrumental_fit (within two-stage least squares, a second detector's AUs as "
    "instruments; docs/method.md eq. 7)",
}


def shareable_config(cfg: Config) -> dict:
    """The configuration as the model card records it: what the model is, without :data:`WHERE_GROUPS`."""
    return without_where(cfg.to_dict())


def build_card(cfg: Config, model_dir: Path, prepared_dir: Path, promotion: dict | None) -> dict:
    """``model_card.json``: CV results, data (counts per filter, digest, what the data supports:
    :func:`aumesh.model.support.data_support`), config, provenance, MLflow run."""
    from aumesh.model import support

    with open(model_dir / METRICS_JSON) as fh:
        metrics = json.load(fh)
    with open(model_dir / TRACKING_JSON) as fh:
        run_info = json.load(fh)
    summary = integrity.load_summary(prepared_dir)  # prepare's counts
    git = provenance.git_commit(Path.cwd())
    return {
        "name": "AU+pose -> MediaPipe mesh PLS (aumesh)",
        "format_version": 2,
        "cv": {k: v for k, v in metrics.items() if k not in ("n_components", "n_features", "au_identification")},
        "model": {
            "n_components": metrics["n_components"],
            "n_features": metrics["n_features"],
            "estimator": _ESTIMATORS[(metrics.get("eiv") or {}).get("method", "none")],
        },
        # the AU identification screen (aumesh.model.eiv, docs/method.md eq. 6): per AU sigma*, flag, partner, group
        "au_identification": metrics.get("au_identification"),
        "data": {
            "n_frames": summary["n_frames"],
            "n_videos": summary["n_videos"],
            "digest": run_info.get("data_digest"),
            "degenerate": run_info.get("degenerate") or {},
            "counts": summary["counts"],
            "n_low_au_frames": summary["n_low_au_population"],
            **support.data_support(summary),
        },
        "config": shareable_config(cfg),
        "provenance": {"git_commit": git.get("commit"), "dirty": git.get("dirty"), "branch": git.get("branch")},
        "mlflow": {
            **{k: run_info.get(k) for k in ("run_id", "experiment_id", "tracking_uri")},
            "experiment": cfg.tracking.experiment if cfg.tracking.enabled else None,
        },
        "runs": release_runs(run_info, promotion),
        "libraries": provenance.library_versions(),
        "promotion": promotion,
    }


def release_runs(run_info: dict, promotion: dict | None) -> dict:
    """The two MLflow runs a release names: ``build`` made these exact arrays, ``promoted`` chose their configuration.

    Parameters
    ----------
    run_info : dict
        ``build/model/tracking.json``: the evaluate run of ``dvc repro`` (``run_id``, ``run_name``,
        ``experiment_id``, ``tracking_uri``).
    promotion : dict or None
        ``promotion.json``'s ``promoted`` record (:func:`aumesh.experiments.promote.promote`), None when the
        configuration is conf/'s own.

    Returns
    -------
    dict
        ``{"build": {...}, "promoted": {...} or None}``; each names its run id, its store (repo-relative) and, in
        ``role``, what it stands for. The promoted run is a sweep child: the same configuration fitted by the sweep,
        whose metrics decided; the build run refitted it in the pipeline (the card's arrays and numbers are its).
    """
    build = {
        "run_id": run_info.get("run_id"),
        "run_name": run_info.get("run_name"),
        "experiment_id": run_info.get("experiment_id"),
        "tracking_uri": run_info.get("tracking_uri"),
        "role": "build: the evaluate run of `dvc repro` that produced these exact arrays and the card's metrics",
    }
    promoted = None
    if promotion:
        promoted = {
            k: promotion.get(k)
            for k in (
                "run_id",
                "run_name",
                "parent_run_id",
                "tracking_uri",
                "criterion",
                "metric",
                "value",
                "registered_model",
                "model_version",
                "alias",
            )
        }
        promoted["role"] = (
            "promoted: the sweep run whose configuration this release uses, chosen by `aumesh promote` "
            f"({promotion.get('criterion')})"
        )
    return {"build": build, "promoted": promoted}


def load_model(model_dir: Path) -> dict[str, np.ndarray]:
    """The arrays of ``model.npz`` (evaluate's fit); a damaged archive is one line naming it."""
    import zipfile

    from aumesh.core.errors import CorruptFileError, MissingFileError

    path = Path(model_dir) / MODEL_NPZ
    if not path.exists():
        raise MissingFileError(f"{path}: not found. Fix: run the evaluate stage first (`dvc repro evaluate`).")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, EOFError, OSError) as err:
        raise CorruptFileError(f"{path}: not a readable .npz ({err}). Fix: `dvc repro -f evaluate`.") from None


def refuse_nonfinite(arrays: dict, source: Path) -> None:
    """A :class:`aumesh.model.release_check.ReleaseError` naming the first of ``coef``, ``coef_full``, ``intercept`` with a
    NaN/inf value: a release is finite or not written."""
    from aumesh.model.release_check import ReleaseError, nonfinite_arrays

    nonfinite = nonfinite_arrays(arrays)
    if nonfinite:
        raise ReleaseError(
            f"{source}: {nonfinite}; nothing written, the previous release is kept. "
            f"Fix: rerun the fit (`dvc repro -f evaluate`) and look for degenerate inputs in its log."
        )


def refuse_implausible_face(
    intercept: np.ndarray, mean_aligned_mesh: np.ndarray, model_path: Path, reference_path: Path
) -> dict[str, Any]:
    """The card's ``data.face_shape``, or a :class:`aumesh.model.release_check.ReleaseError` (one line naming the file)
    when the AU=0 face (``intercept``, (1434,) axis-major) or ``mean_aligned_mesh`` (478, 3) has no face's
    depth/width (:func:`aumesh.model.face_shape.face_shape_error`): never a flat face released with exit 0."""
    from aumesh.model.face_shape import au0_face, face_shape_error, face_shape_record
    from aumesh.model.release_check import ReleaseError

    try:
        record = face_shape_record(au0_face(intercept), mean_aligned_mesh)
    except ValueError as err:  # no face frame at all (coincident eye corners, chin on the eye line)
        raise ReleaseError(
            f"{model_path}: the AU=0 face (intercept) or {reference_path}'s mean_aligned_mesh is not a face ({err}); "
            f"nothing written, the previous release is kept. Fix: rerun the fit (`dvc repro -f prepare evaluate`)."
        ) from None
    for ratio, what, source in (
        (record["depth_width"], "the AU=0 face (intercept)", model_path),
        (record["mean_aligned_mesh"]["depth_width"], "mean_aligned_mesh", reference_path),
    ):
        error = face_shape_error(ratio, what, str(source))
        if error:
            raise ReleaseError(error)
    return record
