"""Typed view of the configuration.

Under DVC a stage reads the ``params.yaml`` that ``dvc exp run`` composes from ``conf/``
(Hydra enabled in ``.dvc/config``); it never re-composes with ``@hydra.main``, or
``dvc exp run -S`` overrides would be silently ignored. ``compose`` is for the places that
are not DVC stages: ``aumesh compose-params`` (what ``make params`` runs after an edit of
``conf/``), the in-process sweep and the tests.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import yaml

from aumesh.core.errors import ConfigError
from aumesh.core.families import FEATURE_SETS, feature_set_columns
from aumesh.core.io import atomic_write_text
from aumesh.core.schema import (
    ANCHOR_INDICES,
    MAX_ABS_PITCH_DEG,
    MAX_ABS_YAW_DEG,
    N_VERTICES,
    TARGETS,
)

#: ``data.face_selection``: which face of a frame with several is the video's subject (aumesh.data.ingest).
FACE_SELECTIONS = ("largest", "identity", "error")
#: ``data.mesh_units``: how the mesh's z is read (aumesh.data.units; docs/conventions.md "py-feat's mesh units").
MESH_UNITS = ("detector", "pixels")


@dataclass(frozen=True)
class PathsConfig:
    data_dir: str = "data"
    ingested_dir: str = "build/ingested"
    prepared_dir: str = "build/prepared"
    model_dir: str = "build/model"
    release_dir: str = "release"
    metrics_file: str = "metrics/metrics.json"
    error_curve_file: str = "metrics/cumulative_vertex_error.csv"
    r2_curve_file: str = "metrics/r2_by_n_components.csv"
    promotion_file: str = "promotion.json"
    validation_dir: str = "validation"
    # issue 46: the evaluate stage's fit of each input family (``families``), a folder per family, its metrics, and
    # the release of each (``release_family@<family>``; beside ``release_dir``, which stays the AU release)
    families_model_dir: str = "build/families"
    families_metrics_file: str = "metrics/families.json"
    families_release_dir: str = "releases"


@dataclass(frozen=True)
class DataConfig:
    tables: str = "**/*"
    mesh_npy: str = "{stem}.npy"
    face_selection: str = "largest"
    mesh_units: str = "detector"
    chunk_rows: int = 8192
    coerce_numeric: bool = False


@dataclass(frozen=True)
class PoseFilterConfig:
    max_abs_yaw_deg: float = MAX_ABS_YAW_DEG
    max_abs_pitch_deg: float = MAX_ABS_PITCH_DEG


@dataclass(frozen=True)
class AlignmentConfig:
    anchor_indices: tuple[int, ...] = ANCHOR_INDICES
    outlier_quantile: float = 0.99
    gpa_max_frames: int = 20000
    gpa_max_iter: int = 50
    gpa_tol: float = 1e-10
    max_vertex_iod: float = 4.0


@dataclass(frozen=True)
class NeutralConfig:
    low_au_quantile: float = 0.1
    method: str = "low_au"


@dataclass(frozen=True)
class PreprocessConfig:
    pose_filter: PoseFilterConfig = field(default_factory=PoseFilterConfig)
    alignment: AlignmentConfig = field(default_factory=AlignmentConfig)
    neutral: NeutralConfig = field(default_factory=NeutralConfig)
    target: str = "absolute"
    empty_video: str = "drop"
    max_drop_fraction: float = 0.25


@dataclass(frozen=True)
class FeaturesConfig:
    """The design, one option of the ``features`` group (``conf/features/<name>.yaml``)."""

    name: str = "au_pose_interactions"

    @property
    def family(self) -> str:
        """The input family: ``au``, ``blendshapes`` or ``emotions`` (``aumesh.core.families``)."""
        return FEATURE_SETS[self.name][0]

    @property
    def pose(self) -> bool:
        """Pose covariates (Pitch, Yaw, Roll) in the design."""
        return FEATURE_SETS[self.name][1]

    @property
    def interactions(self) -> bool:
        """Pose x input interactions in the design."""
        return FEATURE_SETS[self.name][2]

    @property
    def columns(self) -> list[str]:
        return feature_set_columns(self.name)


# The two switches the features group replaced, and the option each combination now is.
_OLD_FEATURE_KEYS = ("pose", "interactions")


def _old_features_message(data: Mapping[str, Any]) -> str:
    def truthy(v: Any) -> bool:
        return str(v).strip().lower() in ("true", "1", "yes")

    pose, inter = truthy(data.get("pose", True)), truthy(data.get("interactions", True))
    named = {v: k for k, v in FEATURE_SETS.items()}.get(("au", pose, inter))
    hint = f" (pose={pose}, interactions={inter} is `features={named}`)" if named else ""
    return (
        "features.pose / features.interactions were replaced by the features config group: "
        f"use features=au, features=au_pose or features=au_pose_interactions{hint}; "
        "in params.yaml: `features: {name: au_pose}`"
    )


FAMILY_OFF = "none"  # families.<family>.features of a family neither fitted nor released (its release says so)


@dataclass(frozen=True)
class FamilyConfig:
    """One input family's model beside the AU model (``families.<family>``; ``conf/families/<name>.yaml``)."""

    # the family's design (a ``features`` option of the family, e.g. blendshapes_pose_interactions), or none
    features: str = ""
    n_components: int | None = None  # None: model.n_components, clipped to the design's width


@dataclass(frozen=True)
class BlendshapesFamilyConfig(FamilyConfig):
    features: str = "blendshapes_pose_interactions"  # py-feat's bs_to_mesh_pls design


@dataclass(frozen=True)
class EmotionsFamilyConfig(FamilyConfig):
    features: str = "emotions_pose_interactions"  # py-feat's emotion_to_mesh_pls design


@dataclass(frozen=True)
class FamiliesConfig:
    """The input families (``aumesh.core.families``) ``dvc repro`` fits and releases beside the AU model."""

    blendshapes: BlendshapesFamilyConfig = field(default_factory=BlendshapesFamilyConfig)
    emotions: EmotionsFamilyConfig = field(default_factory=EmotionsFamilyConfig)

    def items(self) -> list[tuple[str, FamilyConfig]]:  # (family, its config), in a fixed order
        return [(f.name, getattr(self, f.name)) for f in dataclasses.fields(self)]


#: ``model.eiv.method``: the errors-in-variables correction, one option of the ``model/eiv`` group
#: (``conf/model/eiv/<name>.yaml``; docs/method.md "Detector noise").
EIV_METHODS = ("none", "corrected", "instruments")


@dataclass(frozen=True)
class EivConfig:
    """What the fit does about noise in the AU detector (``conf/model/eiv/<method>.yaml``; docs/method.md).

    ``none`` is the card's fit. ``corrected`` is corrected least squares on the within-video design with the detector's
    within-video error covariance ``sigma_u`` (a ``.npy`` of 20 x 20, rows and columns in ``au_columns`` order, from a
    validation study: never estimated from the tables), each direction's reliability floored at ``floor``.
    ``instruments`` is within-video two-stage least squares with a second detector's AUs on the same frames, the
    columns ``instrument_aus`` names (``{au}`` is replaced by each AU name, e.g. ``{au}_mp``).
    """

    method: str = "none"
    sigma_u: str | None = None
    floor: float = 0.3
    instrument_aus: str | None = None


@dataclass(frozen=True)
class IdentificationConfig:
    """The AU identification screen (``aumesh.model.eiv.identification_screen``; docs/method.md "The screen").

    Per AU, sigma* = the smallest sd in ``sigma_step``, 2 ``sigma_step``, ... ``sigma_max`` at which the floored
    corrected fit with an isotropic error covariance sigma^2 I turns the AU's field to a cosine below ``turn_cosine``
    with the uncorrected one; the AU is flagged when sigma* < ``flag_below``.
    """

    sigma_max: float = 0.20
    sigma_step: float = 0.005
    flag_below: float = 0.10
    turn_cosine: float = 0.5
    floor: float = 0.3


@dataclass(frozen=True)
class ModelConfig:
    n_components: int = 83
    scale: bool = True
    clip_n_components: bool = True
    eiv: EivConfig = field(default_factory=EivConfig)
    identification: IdentificationConfig = field(default_factory=IdentificationConfig)


@dataclass(frozen=True)
class CVConfig:
    n_splits: int = 3
    group: str = "video_id"


@dataclass(frozen=True)
class TrackingConfig:
    enabled: bool = True
    tracking_uri: str | None = None
    experiment: str = "aumesh"
    # how long a store locked by another process is retried, with backoff, before one line says so
    busy_timeout_s: float = 60.0
    # a tracking server or database: seconds the check before any work waits for it (aumesh.tracking.connection)
    check_timeout_s: float = 5.0
    # MLflow's HTTP requests (MLFLOW_HTTP_REQUEST_TIMEOUT / _MAX_RETRIES / _BACKOFF_FACTOR, unless set): a server lost
    # mid-run ends the command in one line within about (max_retries + 1) x request_timeout_s, not MLflow's 25 min
    request_timeout_s: float = 20.0
    max_retries: int = 2
    backoff_factor: float = 1.0


@dataclass(frozen=True)
class ComputeConfig:
    """Where the data passes run (Dask), one option of the ``compute`` group (``conf/compute/<name>.yaml``).

    Never changes results beyond float64 summation order, so it is not a DVC stage parameter.
    """

    scheduler: str = "threads"  # synchronous | threads | processes | distributed
    n_workers: int | None = None  # threads/processes; None: every core
    address: str | None = None  # distributed: the scheduler's address
    # rows in flight are about n_workers x partition_rows, and the passes' per-partition arrays (metadata, transforms,
    # per-video sums) scale with them: 65,536 put 130k rows in flight from ~130k frames up but 100k at 100k frames
    # (2 x 50k), so the peak grew with the data; 32,768 halves that step (benchmarks/README, issue 12's sixth round)
    partition_rows: int = 32768
    # distributed: seconds to wait for the scheduler (and for a first worker) before the stage stops with one line
    # (Dask's own default waits 30 s and then prints a 75-line traceback)
    connect_timeout: float = 10.0


@dataclass(frozen=True)
class Config:
    paths: PathsConfig = field(default_factory=PathsConfig)
    data: DataConfig = field(default_factory=DataConfig)
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    features: FeaturesConfig = field(default_factory=FeaturesConfig)
    families: FamiliesConfig = field(default_factory=FamiliesConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    cv: CVConfig = field(default_factory=CVConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    compute: ComputeConfig = field(default_factory=ComputeConfig)
    seed: int = 0

    def to_dict(self) -> dict[str, Any]:
        return _plain(dataclasses.asdict(self))


def flatten(data: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (tuples as lists): config keys as Hydra overrides name them."""
    out: dict[str, Any] = {}
    for key, value in data.items():
        path = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, path + "."))
        else:
            out[path] = list(value) if isinstance(value, tuple) else value
    return out


def _plain(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj


def _check_keys(cls: type, data: Any, where: str) -> None:
    """Unknown keys (typos must not pass silently) and replaced keys, named with what replaced them."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"config section '{where}' must be a mapping, got {type(data).__name__} {data!r}")
    known = {f.name: f for f in dataclasses.fields(cls)}
    if cls is FeaturesConfig and set(data) & set(_OLD_FEATURE_KEYS):
        raise ConfigError(_old_features_message(data))
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ConfigError(
            f"unknown config key(s) {', '.join(where + '.' + k if where else k for k in unknown)}; "
            f"known keys of '{where or 'root'}': {', '.join(sorted(known))}"
        )
    for name, value in data.items():
        sub = known[name].default_factory
        if sub is not dataclasses.MISSING and dataclasses.is_dataclass(sub):
            _check_keys(sub, value, f"{where}.{name}" if where else name)


def _schema():
    """The dataclasses as an OmegaConf structured config (Hydra's structured-config machinery), writable."""
    from omegaconf import DictConfig, ListConfig, OmegaConf

    def unlock(node) -> None:  # frozen dataclasses make read-only nodes; the schema must accept a merge
        node._set_flag("readonly", None)
        if isinstance(node, DictConfig):
            for key in node.keys():
                unlock(node._get_node(key))
        elif isinstance(node, ListConfig):
            for i in range(len(node)):
                unlock(node._get_node(i))

    schema = OmegaConf.structured(Config)
    unlock(schema)
    return schema


# OmegaConf's reason -> what the key allows
_ALLOWED = {
    "to Integer": "an integer, e.g. 10",
    "valid bool": "true or false",
    "to Float": "a number, e.g. 0.5",
    "Incompatible value 'None'": "a value (not null)",
}


def _typed(data: Mapping[str, Any]) -> dict[str, Any]:
    """Values converted to the dataclasses' types by OmegaConf (``"10"`` -> 10, ``"false"`` -> False);
    a value that does not convert (``"ten"``, ``10.5`` for an int, ``"nope"`` for a bool) is a ConfigError."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        merged = OmegaConf.merge(_schema(), dict(data))
    except OmegaConfBaseException as err:
        value = getattr(err, "value", None)
        reason = str(getattr(err, "msg", err)).splitlines()[0]
        allowed = next((a for k, a in _ALLOWED.items() if k in reason), None)
        raise ConfigError(f"{err.full_key}={value!r}: " + (f"must be {allowed}" if allowed else reason)) from None
    return cast(dict[str, Any], OmegaConf.to_container(merged))  # a structured config's container is a dict


def _build(cls: type, data: Mapping[str, Any]) -> Any:
    """Build dataclass ``cls`` from checked, typed values (lists become tuples: the config is hashable)."""
    kwargs = {}
    for f in dataclasses.fields(cls):
        value = data[f.name]
        if f.default_factory is not dataclasses.MISSING and dataclasses.is_dataclass(f.default_factory):
            kwargs[f.name] = _build(f.default_factory, value)
        else:
            kwargs[f.name] = tuple(value) if isinstance(value, list) else value
    return cls(**kwargs)


def validate(cfg: Config) -> Config:
    """Check values a typo or a bad sweep override could break; errors name the key, the value and what is allowed."""
    if cfg.preprocess.target not in TARGETS:
        raise ConfigError(f"preprocess.target={cfg.preprocess.target!r}: use one of {', '.join(map(repr, TARGETS))}")
    if cfg.preprocess.neutral.method not in ("low_au", "mean"):
        raise ConfigError(f"preprocess.neutral.method={cfg.preprocess.neutral.method!r}: use 'low_au' or 'mean'")
    if cfg.preprocess.empty_video not in ("drop", "error"):
        raise ConfigError(f"preprocess.empty_video={cfg.preprocess.empty_video!r}: use 'drop' or 'error'")
    q = cfg.preprocess.alignment.outlier_quantile
    if not 0.0 < q <= 1.0:
        raise ConfigError(f"preprocess.alignment.outlier_quantile={q}: must be in (0, 1]; 1.0 keeps every frame")
    if not 0.0 <= cfg.preprocess.max_drop_fraction <= 1.0:
        raise ConfigError(
            f"preprocess.max_drop_fraction={cfg.preprocess.max_drop_fraction}: must be in [0, 1]; 1.0 never stops a run"
        )
    if len(cfg.preprocess.alignment.anchor_indices) < 3:
        raise ConfigError("preprocess.alignment.anchor_indices: need at least 3 anchors for a similarity fit")
    anchors = cfg.preprocess.alignment.anchor_indices
    outside = [i for i in anchors if not 0 <= i < N_VERTICES]
    if outside:  # they name mesh columns x_i, y_i, z_i: there are 478 vertices
        raise ConfigError(
            f"preprocess.alignment.anchor_indices: {outside} name no vertex (MediaPipe's mesh has vertices "
            f"0..{N_VERTICES - 1}: columns x_0..z_{N_VERTICES - 1}). Fix: use vertex numbers in that range "
            f"(the card's anchors: {list(ANCHOR_INDICES)})."
        )
    if len(set(anchors)) != len(anchors):
        raise ConfigError(
            f"preprocess.alignment.anchor_indices: {sorted({i for i in anchors if anchors.count(i) > 1})} "
            f"named twice. Fix: list each anchor vertex once."
        )
    if cfg.model.n_components < 1:
        raise ConfigError(f"model.n_components={cfg.model.n_components}: must be >= 1")
    p = len(cfg.features.columns) if cfg.features.name in FEATURE_SETS else 0
    if p and cfg.model.n_components > p and not cfg.model.clip_n_components:
        raise ConfigError(
            f"model.n_components={cfg.model.n_components} exceeds the {p} features of "
            f"features={cfg.features.name}. Fix: lower it, or set model.clip_n_components=true."
        )
    _validate_eiv(cfg)
    if cfg.cv.n_splits < 2:
        raise ConfigError(f"cv.n_splits={cfg.cv.n_splits}: must be >= 2")
    if cfg.data.face_selection not in FACE_SELECTIONS:
        raise ConfigError(
            f"data.face_selection={cfg.data.face_selection!r}: use one of {', '.join(FACE_SELECTIONS)} "
            "(largest: the largest face box of a frame; identity: py-feat's Identity of the video's subject; "
            "error: refuse frames with several faces)"
        )
    if cfg.data.mesh_units not in MESH_UNITS:
        raise ConfigError(
            f"data.mesh_units={cfg.data.mesh_units!r}: use one of {', '.join(MESH_UNITS)} "
            "(detector: z converted from the units of the py-feat detector the columns name; pixels: every table's "
            "x, y, z already in pixels)"
        )
    if not cfg.preprocess.alignment.max_vertex_iod > 0:
        raise ConfigError(
            f"preprocess.alignment.max_vertex_iod={cfg.preprocess.alignment.max_vertex_iod}: must be > 0 "
            "(inter-ocular distances; a large value such as 1e9 keeps every frame)"
        )
    if cfg.data.chunk_rows < 1:
        raise ConfigError(f"data.chunk_rows={cfg.data.chunk_rows}: must be >= 1")
    if cfg.compute.scheduler not in ("synchronous", "threads", "processes", "distributed"):
        raise ConfigError(
            f"compute.scheduler={cfg.compute.scheduler!r}: use compute=local (threads), synchronous, "
            "processes or distributed (conf/compute/<name>.yaml)"
        )
    if cfg.compute.scheduler == "distributed" and not cfg.compute.address:
        raise ConfigError("compute=distributed needs the scheduler's address: compute.address=tcp://host:8786")
    if cfg.compute.partition_rows < 1:
        raise ConfigError(f"compute.partition_rows={cfg.compute.partition_rows}: must be >= 1")
    if not cfg.compute.connect_timeout > 0:
        raise ConfigError(f"compute.connect_timeout={cfg.compute.connect_timeout}: must be > 0 (seconds)")
    if cfg.features.name not in FEATURE_SETS:
        raise ConfigError(
            f"features={cfg.features.name!r}: use one of {', '.join(FEATURE_SETS)} (conf/features/<name>.yaml)"
        )
    _validate_families(cfg)
    return cfg


def _validate_families(cfg: Config) -> None:
    """Each ``families.<family>.features`` is a design of that family; ``n_components`` >= 1 when set."""
    for family, spec in cfg.families.items():
        options = [name for name, (fam, _, _) in FEATURE_SETS.items() if fam == family] + [FAMILY_OFF]
        if spec.features not in options:
            raise ConfigError(
                f"families.{family}.features={spec.features!r}: use one of {', '.join(options)} "
                f"(the family's designs, or {FAMILY_OFF}: not fitted, not released; conf/families/<name>.yaml)"
            )
        if spec.n_components is not None and spec.n_components < 1:
            raise ConfigError(f"families.{family}.n_components={spec.n_components}: must be >= 1, or null")


def _validate_eiv(cfg: Config) -> None:
    """``model.eiv`` and ``model.identification``: the method's own keys set, no other method's."""
    eiv, ident = cfg.model.eiv, cfg.model.identification
    if eiv.method not in EIV_METHODS:
        raise ConfigError(
            f"model.eiv.method={eiv.method!r}: use model/eiv=none, corrected or instruments (conf/model/eiv/<name>.yaml)"
        )
    if eiv.method == "corrected" and eiv.sigma_u in (None, "", "???"):
        raise ConfigError(
            "model/eiv=corrected needs the AU detector's within-video error covariance: model.eiv.sigma_u=<file.npy> "
            "(20 x 20, rows and columns in au_columns order; docs/method.md)"
        )
    if eiv.method == "instruments" and not (eiv.instrument_aus and "{au}" in eiv.instrument_aus):
        raise ConfigError(
            f"model.eiv.instrument_aus={eiv.instrument_aus!r}: model/eiv=instruments needs the second detector's AU "
            "columns as a pattern with {au}, e.g. model.eiv.instrument_aus='{au}_mp'"
        )
    if eiv.method != "corrected" and eiv.sigma_u:
        raise ConfigError(
            f"model.eiv.sigma_u={eiv.sigma_u!r} is given but model.eiv.method={eiv.method!r}: choose model/eiv=corrected"
        )
    if eiv.method != "instruments" and eiv.instrument_aus:
        raise ConfigError(
            f"model.eiv.instrument_aus={eiv.instrument_aus!r} is given but model.eiv.method={eiv.method!r}: "
            "choose model/eiv=instruments"
        )
    for key, value in (("model.eiv.floor", eiv.floor), ("model.identification.floor", ident.floor)):
        if not 0.0 < value <= 1.0:
            raise ConfigError(f"{key}={value}: must be in (0, 1] (the smallest reliability a direction may have)")
    if eiv.method != "none" and cfg.preprocess.target != "within":
        raise ConfigError(
            f"model/eiv={eiv.method} corrects the within-video design, but preprocess.target={cfg.preprocess.target!r}. "
            "Fix: preprocess.target=within"
        )
    if not 0.0 < ident.sigma_step <= ident.sigma_max:
        raise ConfigError(
            f"model.identification.sigma_step={ident.sigma_step}, sigma_max={ident.sigma_max}: need 0 < step <= max"
        )
    if not -1.0 < ident.turn_cosine < 1.0:
        raise ConfigError(f"model.identification.turn_cosine={ident.turn_cosine}: must be in (-1, 1)")


def from_dict(data: dict[str, Any]) -> Config:
    """Typed, validated config from a plain mapping (a parsed params.yaml or a composed Hydra config).

    Raises
    ------
    ConfigError
        An unknown or replaced key, a value of the wrong type, or a value outside what the key allows;
        the message names the key, the value and what is allowed.
    """
    _check_keys(Config, data, "")
    return validate(_build(Config, _typed(data)))


def load_params(path: str | Path = "params.yaml") -> Config:
    """Read the DVC-composed ``params.yaml``."""
    path = Path(path)
    if not path.exists():
        raise ConfigError(
            f"{path}: no params file. Run `make params` (or `aumesh compose-params`) to compose it from conf/."
        )
    try:
        with open(path) as fh:
            data = yaml.safe_load(fh) or {}
    except yaml.YAMLError as err:
        raise ConfigError(
            f"{path}: not valid YAML ({str(err).splitlines()[0]}). Fix: `make params` recomposes it from conf/."
        ) from None
    try:
        return from_dict(data)
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None


#: Config groups that say where a run executes (``compute``: the Dask scheduler, its address) and where it is logged
#: (``tracking``: the MLflow store), not what it computes. A laptop and a cluster compute the same model, and a
#: scheduler's or a server's address is one machine's: these groups are never a run's name, MLflow params, recorded
#: overrides, promoted config or card (:func:`without_where`, :func:`recorded_overrides`), nor a DVC stage's params.
WHERE_GROUPS = ("compute", "tracking")


def is_where(key: str) -> bool:
    """Whether a dotted config key (``compute.address``) or a Hydra override (``compute=distributed``,
    ``+tracking.experiment=x``, ``~compute.address``) names one of :data:`WHERE_GROUPS`."""
    name = key.lstrip("+~").split("=", 1)[0].strip()
    return name.split(".", 1)[0].split("@", 1)[0].split("/", 1)[0] in WHERE_GROUPS


def without_where(config: Mapping[str, Any]) -> dict[str, Any]:
    """``config`` (nested, or flattened with dotted keys) without the keys of :data:`WHERE_GROUPS`: what a run
    records of its configuration."""
    return {k: v for k, v in config.items() if not is_where(str(k))}


def recorded_overrides(overrides: Sequence[str]) -> list[str]:
    """The Hydra overrides a run records (its name, ``aumesh.sweep.overrides``): ``overrides`` without those of
    :data:`WHERE_GROUPS` (``compute.address=tcp://...`` stays on the command line that gave it)."""
    return [ov for ov in overrides if not is_where(ov)]


def check_overrides(overrides: Sequence[str]) -> None:
    """Refuse overrides of keys that no longer exist, naming the form that replaced them."""
    for ov in overrides:
        key = ov.lstrip("+~").split("=", 1)[0].strip()
        if key in ("features.pose", "features.interactions"):
            raise ConfigError(f"override {ov!r}: " + _old_features_message({}).split(" (")[0])


def compose(overrides: Sequence[str] = (), config_dir: str | Path = "conf", config_name: str = "config") -> dict:
    """Compose ``conf/`` with Hydra overrides into a plain dict (what DVC writes to params.yaml)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    check_overrides(overrides)
    try:
        with initialize_config_dir(config_dir=str(Path(config_dir).resolve()), version_base=None):
            cfg = hydra_compose(config_name=config_name, overrides=list(overrides))
    except (HydraException, OmegaConfBaseException) as err:  # an unknown key or group option in an override
        raise ConfigError(f"{config_dir}/ {' '.join(overrides)}: {str(err).splitlines()[0]}") from None
    return cast(dict[str, Any], OmegaConf.to_container(cfg, resolve=True))  # compose returns a DictConfig


def write_params(data: dict, path: str | Path = "params.yaml") -> Path:
    """Write a composed config as params.yaml, atomically."""
    return atomic_write_text(Path(path), params_text(data))


def params_text(data: dict) -> str:
    """The text of ``params.yaml`` for a composed config (what :func:`write_params` writes)."""
    header = "# Composed from conf/ by `aumesh compose-params` (dvc exp run rewrites it the same way). Edit conf/, not this file.\n"
    return header + yaml.safe_dump(data, sort_keys=False)
