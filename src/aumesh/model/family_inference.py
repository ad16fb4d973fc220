"""A family release (blendshapes or emotions -> mesh, issue 46) loaded, checked and predicted by the AU release's code.

A family release NPZ (contract item 3; built by :mod:`aumesh.model.family_release`) holds py-feat's
``PLSFeatMeshModel`` keys: ``coef`` (p, 1434) whose first ``k`` rows are the family's inputs ``feature_columns``
(py-feat's ``MP_BLENDSHAPE_NAMES`` / ``FEAT_EMOTION_COLUMNS``), then pose and pose x input rows named by
``input_columns`` (p,) (``Pitch*jawOpen``: :func:`aumesh.core.schema.interaction_columns`' pose-major names);
``intercept`` (1434,); ``feature_p99`` (k,); ``unsupported_features``; ``mean_aligned_mesh`` and
``mean_neutral_mesh`` (478, 3); aumesh's ``family``, ``training_metadata`` and the rest. The prediction is the AU
release's: ``flat = x_full @ coef + intercept`` with ``x_full = [inputs | pose | pose x input]`` (py-feat's
``PLSFeatMeshModel.predict`` is its pose-0 case, ``x @ coef[:k] + intercept``), in the AU release's canonical frame.

So that one code path serves both (the input checks, their warnings, the streamed ``aumesh predict``, the glTF rig,
the viewer), a family release is seen through :func:`au_view`: the same arrays under the AU release's key names
(``au_columns`` = the family's inputs, ``coef_full`` = the whole design), which
:func:`aumesh.model.inference.predict_rows` and :func:`aumesh.model.input_checks.input_rows` read by name. The family's
own names reach every message and file; Detectorv2's emotion names (``Happy``, ...) are mapped to the family's by
name (:data:`aumesh.core.families.NAME_MAPS`), never by position.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from aumesh.core.families import FAMILIES, NAME_MAPS, PYFEAT_FEATURE, family_columns
from aumesh.core.schema import N_TARGETS, N_VERTICES, POSE_COLUMNS
from aumesh.model.release_check import ReleaseError, _names, load_release, nonfinite_arrays

#: What a family release NPZ must hold (py-feat's loader reads the first six; ``input_columns`` names ``coef``'s rows).
FAMILY_KEYS: tuple[str, ...] = (
    "coef",
    "intercept",
    "feature_columns",
    "pose_columns",
    "mean_aligned_mesh",
    "input_columns",
)

#: The fix for a family release NPZ that cannot be used.
FAMILY_FIX = "`dvc pull --force releases` (the tracked copy) or `dvc repro release_family` (rebuild it)"


def release_family(arrays: Mapping[str, Any]) -> str:
    """``"au"`` for an AU release (the card's NPZ), else the family of a family release: its ``family`` key, or, for a
    py-feat NPZ without it (py-feat's own ``bs_to_mesh_pls_v6.npz``), the family whose names its ``feature_columns``
    are exactly."""
    if "family" in arrays:
        family = str(np.asarray(arrays["family"]))
        if family in PYFEAT_FEATURE:
            return family
    if "au_columns" not in arrays and "feature_columns" in arrays:
        columns = _names(arrays["feature_columns"])
        for family in PYFEAT_FEATURE:
            if columns == list(FAMILIES[family]):
                return family
    return "au"


def check_family_release(arrays: Mapping[str, Any], where: str = "<release arrays>") -> str:
    """The family of release arrays ``arrays``; :class:`ReleaseError` (one line: the key, what it should be, the fix)
    when a key is missing or misshapen, ``feature_columns`` is not py-feat's list, or a coefficient is not finite.

    A py-feat NPZ without ``input_columns`` (py-feat's own releases) is taken as ``feature_columns`` followed by its
    ``pose_columns`` when ``coef`` has exactly those rows; the rest of a design it cannot name is refused.
    """
    family = release_family(arrays)
    if family == "au":
        raise ReleaseError(f"{where}: not a family release (no 'family' key; 'feature_columns' is not a family's list)")
    missing = [k for k in FAMILY_KEYS if k not in arrays and k != "input_columns"]
    if missing:
        raise ReleaseError(f"{where}: missing key {missing[0]!r}; a {family} release NPZ has {list(FAMILY_KEYS)}")
    features = _names(arrays["feature_columns"])
    coef = np.asarray(arrays["coef"])
    rows = _design(arrays)
    if coef.ndim != 2 or coef.shape != (len(rows), N_TARGETS):
        raise ReleaseError(
            f"{where}: 'coef' must be ({len(rows)}, {N_TARGETS}) (rows = input_columns: {len(features)} {family} "
            f"inputs first), got {coef.shape}"
        )
    if rows[: len(features)] != features:
        raise ReleaseError(f"{where}: 'input_columns' must start with 'feature_columns' (py-feat reads coef[:k])")
    if np.asarray(arrays["intercept"]).shape != (N_TARGETS,):
        raise ReleaseError(f"{where}: 'intercept' must be ({N_TARGETS},), got {np.asarray(arrays['intercept']).shape}")
    if np.asarray(arrays["mean_aligned_mesh"]).shape != (N_VERTICES, 3):
        raise ReleaseError(f"{where}: 'mean_aligned_mesh' must be ({N_VERTICES}, 3)")
    if "feature_p99" in arrays and np.asarray(arrays["feature_p99"]).shape != (len(features),):
        raise ReleaseError(
            f"{where}: 'feature_p99' must be ({len(features)},) (each {family} input's training p99), "
            f"got {np.asarray(arrays['feature_p99']).shape}"
        )
    unknown = [u for u in _names(np.asarray(arrays.get("unsupported_features", [])).reshape(-1)) if u not in features]
    if unknown:
        raise ReleaseError(f"{where}: 'unsupported_features' names {unknown[:3]}, not {family} inputs")
    bad = nonfinite_arrays(arrays, ("coef", "intercept"))
    if bad:
        raise ReleaseError(f"{where}: {bad}: a release must be finite. Fix: {FAMILY_FIX}")
    return family


def _design(arrays: Mapping[str, Any]) -> list[str]:
    """``coef``'s row names: ``input_columns``, else (py-feat's own NPZs) ``feature_columns`` + ``pose_columns``."""
    if "input_columns" in arrays:
        return _names(arrays["input_columns"])
    return _names(arrays["feature_columns"]) + _names(np.asarray(arrays.get("pose_columns", [])).reshape(-1))


def is_family_file(path: str | os.PathLike) -> bool:
    """Whether the NPZ at ``path`` is a family release, from its key list and ``family`` entry alone (False for a
    file that is not a readable NPZ: the AU loader then says what is wrong with it)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = set(z.files)
            if "family" in keys:
                return str(z["family"]) in PYFEAT_FEATURE
            if "au_columns" in keys or "feature_columns" not in keys:
                return False
            return release_family({"feature_columns": z["feature_columns"]}) != "au"
    except Exception:  # noqa: BLE001 - any unreadable file: load_release names the problem and the fix
        return False


def load_any_release(source: Any) -> dict[str, np.ndarray]:
    """An AU release (:func:`aumesh.model.release_check.load_release`) or a family release (checked by
    :func:`check_family_release`), from a path or a mapping of arrays."""
    if isinstance(source, Mapping):
        arrays = {k: np.asarray(source[k]) for k in source}
        if release_family(arrays) == "au":
            return load_release(arrays)
        check_family_release(arrays)
        return arrays
    path = Path(source)
    if not path.is_file() or not is_family_file(path):
        return load_release(path)
    from aumesh.core.errors import CorruptFileError
    from aumesh.model.release import load_npz

    try:
        arrays = load_npz(path)
    except CorruptFileError as exc:
        raise ReleaseError(str(exc)) from None
    try:
        check_family_release(arrays, str(path))
    except ReleaseError as exc:
        raise ReleaseError(f"{exc}. Fix: {FAMILY_FIX}") from None
    return arrays


def au_view(arrays: Mapping[str, Any]) -> dict[str, Any]:
    """A family release under the AU release's key names, for the code that reads those (module docstring).

    Returns
    -------
    dict
        ``au_columns`` (k,) the family's inputs; ``input_columns`` (k + 3,) inputs and ``Pitch, Yaw, Roll``;
        ``coef`` (k + 3, 1434) their rows (a pose row the design lacks is zero); with pose x input terms,
        ``coef_full`` (p, 1434) and ``input_columns_full`` (p,), the whole design; ``feature_p99`` (k + 3,) (pose NaN: not checked);
        ``pose_columns``; ``family``; and the release's ``intercept``, ``mean_aligned_mesh``,
        ``unsupported_features``, ``training_metadata`` as they are. An AU release is returned as it is.
    """
    family = release_family(arrays)
    if family == "au":
        return dict(arrays)
    features = _names(arrays["feature_columns"])
    design = _design(arrays)
    coef = np.asarray(arrays["coef"])
    by_name = {c: coef[j] for j, c in enumerate(design)}
    inputs = [*features, *POSE_COLUMNS]
    view: dict[str, Any] = {
        key: arrays[key]
        for key in ("intercept", "mean_aligned_mesh", "mean_neutral_mesh", "unsupported_features", "training_metadata")
        if key in arrays
    }
    view.update(
        family=np.array(family),
        au_columns=np.array(features),
        input_columns=np.array(inputs),
        pose_columns=np.array(POSE_COLUMNS),
        coef=np.stack([by_name.get(c, np.zeros(N_TARGETS, coef.dtype)) for c in inputs]),
    )
    if set(design) - set(inputs):  # pose x input terms: the whole design, as the AU release's coef_full
        view.update(coef_full=coef, input_columns_full=np.array(design))
    if "feature_p99" in arrays:
        p99 = np.asarray(arrays["feature_p99"], dtype=np.float32).reshape(-1)
        view["feature_p99"] = np.concatenate([p99, np.full(len(POSE_COLUMNS), np.nan, np.float32)])
    return view


def renamed(family: str, names: list[str]) -> dict[str, str]:
    """Each name of ``names`` that is one of ``family``'s inputs under a detector's name -> the family's name
    (Detectorv2's ``Happy`` -> ``happiness``); names that are not, or are already the family's, are left out."""
    mapping = NAME_MAPS[family]
    return {n: mapping[n] for n in names if n in mapping and mapping[n] != n}


def family_inputs(family: str, inputs: Any, strict: bool = False) -> Any:
    """``inputs`` as :func:`aumesh.model.input_checks.input_rows` takes them for the family's :func:`au_view`: a
    DataFrame's columns and a mapping's keys renamed to the family's names; a DataFrame with columns besides the
    family's inputs and the pose (a py-feat table) checked first to hold every input (one line naming the missing
    column under either detector's name and the fix: :func:`aumesh.core.families.family_columns`)."""
    from aumesh.model.input_checks import _is_dataframe
    from aumesh.model.input_columns import FACE_SCORE_COLUMN

    if isinstance(inputs, Mapping):
        names = renamed(family, [str(k) for k in inputs])
        return {names.get(str(k), str(k)): v for k, v in inputs.items()}
    if _is_dataframe(inputs):
        columns = [str(c) for c in inputs.columns]
        known = set(NAME_MAPS[family]) | set(POSE_COLUMNS) | {FACE_SCORE_COLUMN}
        if not strict and any(c not in known for c in columns):
            family_columns(columns, family, f"{family} (DataFrame)")
        names = renamed(family, columns)
        return inputs.rename(columns=names) if names else inputs
    return inputs


def _family_words(message: str, family: str) -> str:
    """The AU checks' phrases said of the family's inputs (their numbers and names are already the family's)."""
    return message.replace("aus: ", f"{family}: ").replace("every AU and pose value", f"every {family} and pose value")


def family_input_rows(
    arrays: Mapping[str, Any], inputs: Any = None, pose: Any = None, *, strict: bool = False
) -> tuple[np.ndarray, np.ndarray, bool]:
    """A family release's input rows, checked and warned of as an AU release's
    (:func:`aumesh.model.input_checks.input_rows` on :func:`au_view`): ``(x (N, k), pose (N, 3), single)``.

    Warns
    -----
    InputRangeWarning
        One line: inputs above their training p99 (the release's ``feature_p99``; py-feat clips there), an input of
        ``unsupported_features`` given above 0.02 (py-feat's rule), pose beyond the training range.
    NoFaceWarning
        Rows without a face (their meshes are NaN).
    """
    from aumesh.model.input_checks import InputTally, NoFaceWarning, _warn, input_rows

    family = release_family(arrays)
    view = au_view(arrays)
    tally = InputTally()
    x, pose_rows, single = input_rows(view, family_inputs(family, inputs, strict), pose, strict=strict, tally=tally)
    message = tally.range_message(view)
    if message:
        _warn(_family_words(message, family))
    message = tally.no_face_message()
    if message:
        _warn(_family_words(message, family), NoFaceWarning)
    return x, pose_rows, single


__all__ = [
    "FAMILY_KEYS",
    "au_view",
    "check_family_release",
    "family_input_rows",
    "family_inputs",
    "is_family_file",
    "load_any_release",
    "release_family",
]
