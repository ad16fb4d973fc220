"""Typed view of the configuration.

Under DVC a stage reads the ``params.yaml`` that ``dvc exp run`` composes from ``conf/``
(Hydra enabled in ``.dvc/config``); it never re-composes with ``@hydra.main``, or
``dvc exp run -S`` overrides would be silently ignored. ``compose`` is for the places that
are not DVC stages: ``aumesh compose-params`` (what ``make params`` runs after an edit of
``conf/``), the in-process sweep and the tests.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import yaml

from aumesh.utils.io import atomic_write_text
from aumesh.data.schema import ANCHOR_INDICES, FEATURE_SETS, feature_set_columns
from aumesh.model.statistics import TARGETS


@dataclass(frozen=True)
class PathsConfig:
    data_dir: str = "data"
    prepared_dir: str = "build/prepared"
    model_dir: str = "build/model"
    release_dir: str = "release"
    metrics_file: str = "build/metrics.json"
    promotion_file: str = "promotion.json"


@dataclass(frozen=True)
class DataConfig:
    tables: str = "**/*.parquet"
    mesh_npy: str = "{stem}.npy"
    chunk_rows: int = 8192


@dataclass(frozen=True)
class PoseFilterConfig:
    max_abs_yaw_deg: float = 40.0
    max_abs_pitch_deg: float = 30.0


@dataclass(frozen=True)
class AlignmentConfig:
    anchor_indices: tuple[int, ...] = ANCHOR_INDICES
    outlier_quantile: float = 0.99
    gpa_max_frames: int = 20000
    gpa_max_iter: int = 50
    gpa_tol: float = 1e-10


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


@dataclass(frozen=True)
class FeaturesConfig:
    """The design, one option of the ``features`` group (``conf/features/<name>.yaml``)."""

    name: str = "au_pose_interactions"

    @property
    def pose(self) -> bool:
        """Pose covariates (Pitch, Yaw, Roll) in the design."""
        return FEATURE_SETS[self.name][0]

    @property
    def interactions(self) -> bool:
        """Pose x AU interactions in the design."""
        return FEATURE_SETS[self.name][1]

    @property
    def columns(self) -> list[str]:
        return feature_set_columns(self.name)


# The two switches the features group replaced, and the option each combination now is.
_OLD_FEATURE_KEYS = ("pose", "interactions")


def _old_features_message(data: Mapping[str, Any]) -> str:
    def truthy(v: Any) -> bool:
        return str(v).strip().lower() in ("true", "1", "yes")

    pose, inter = truthy(data.get("pose", True)), truthy(data.get("interactions", True))
    named = {v: k for k, v in FEATURE_SETS.items()}.get((pose, inter))
    hint = f" (pose={pose}, interactions={inter} is `features={named}`)" if named else ""
    return ("features.pose / features.interactions were replaced by the features config group: "
            f"use features=au, features=au_pose or features=au_pose_interactions{hint}; "
            "in params.yaml: `features: {name: au_pose}`")


@dataclass(frozen=True)
class ModelConfig:
    n_components: int = 83
    scale: bool = True
    clip_n_components: bool = True


@dataclass(frozen=True)
class CVConfig:
    n_splits: int = 3
    group: str = "video_id"


@dataclass(frozen=True)
class TrackingConfig:
    enabled: bool = True
    tracking_uri: str | None = None
    experiment: str = "aumesh"


@dataclass(frozen=True)
class Config:
    paths: PathsConfig = field(default_factory=PathsConfig)
    data: DataConfig = field(default_factory=DataConfig)
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    features: FeaturesConfig = field(default_factory=FeaturesConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    cv: CVConfig = field(default_factory=CVConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
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


def _build(cls: type, data: Any, where: str) -> Any:
    """Build dataclass ``cls`` from a mapping, rejecting unknown keys (typos must not pass silently)."""
    if not isinstance(data, dict):
        raise ValueError(f"config section '{where}' must be a mapping, got {type(data).__name__}")
    known = {f.name: f for f in dataclasses.fields(cls)}
    if cls is FeaturesConfig and set(data) & set(_OLD_FEATURE_KEYS):
        raise ValueError(_old_features_message(data))
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ValueError(
            f"unknown config key(s) {', '.join(where + '.' + k if where else k for k in unknown)}; "
            f"known keys of '{where or 'root'}': {', '.join(sorted(known))}"
        )
    kwargs = {}
    for name, value in data.items():
        sub = known[name].default_factory if known[name].default_factory is not dataclasses.MISSING else None
        path = f"{where}.{name}" if where else name
        if sub is not None and dataclasses.is_dataclass(sub):
            kwargs[name] = _build(sub, value, path)
        elif isinstance(value, list):
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = value
    return cls(**kwargs)


def validate(cfg: Config) -> Config:
    """Check values a typo or a bad sweep override could break; errors name the key and the fix."""
    if cfg.preprocess.target not in TARGETS:
        raise ValueError(f"preprocess.target={cfg.preprocess.target!r}: use one of {', '.join(map(repr, TARGETS))}")
    if cfg.preprocess.neutral.method not in ("low_au", "mean"):
        raise ValueError(f"preprocess.neutral.method={cfg.preprocess.neutral.method!r}: use 'low_au' or 'mean'")
    if cfg.preprocess.empty_video not in ("drop", "error"):
        raise ValueError(f"preprocess.empty_video={cfg.preprocess.empty_video!r}: use 'drop' or 'error'")
    q = cfg.preprocess.alignment.outlier_quantile
    if not 0.0 < q <= 1.0:
        raise ValueError(f"preprocess.alignment.outlier_quantile={q}: must be in (0, 1]; 1.0 keeps every frame")
    if len(cfg.preprocess.alignment.anchor_indices) < 3:
        raise ValueError("preprocess.alignment.anchor_indices: need at least 3 anchors for a similarity fit")
    if cfg.model.n_components < 1:
        raise ValueError(f"model.n_components={cfg.model.n_components}: must be >= 1")
    if cfg.cv.n_splits < 2:
        raise ValueError(f"cv.n_splits={cfg.cv.n_splits}: must be >= 2")
    if cfg.data.chunk_rows < 1:
        raise ValueError(f"data.chunk_rows={cfg.data.chunk_rows}: must be >= 1")
    if cfg.features.name not in FEATURE_SETS:
        raise ValueError(f"features={cfg.features.name!r}: use one of {', '.join(FEATURE_SETS)} "
                         "(conf/features/<name>.yaml)")
    return cfg


def from_dict(data: dict[str, Any]) -> Config:
    """Typed, validated config from a plain mapping (a parsed params.yaml or a composed Hydra config)."""
    return validate(_build(Config, dict(data), ""))


def load_params(path: str | Path = "params.yaml") -> Config:
    """Read the DVC-composed ``params.yaml``."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(
            f"{path}: no params file. Run `make params` (or `aumesh compose-params`) to compose it from conf/."
        )
    with open(path) as fh:
        data = yaml.safe_load(fh) or {}
    try:
        return from_dict(data)
    except ValueError as err:
        raise ValueError(f"{path}: {err}") from None


def check_overrides(overrides: Sequence[str]) -> None:
    """Refuse overrides of keys that no longer exist, naming the form that replaced them."""
    for ov in overrides:
        key = ov.lstrip("+~").split("=", 1)[0].strip()
        if key in ("features.pose", "features.interactions"):
            raise ValueError(f"override {ov!r}: " + _old_features_message({}).split(" (")[0])


def compose(overrides: Sequence[str] = (), config_dir: str | Path = "conf", config_name: str = "config") -> dict:
    """Compose ``conf/`` with Hydra overrides into a plain dict (what DVC writes to params.yaml)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from omegaconf import OmegaConf

    check_overrides(overrides)
    with initialize_config_dir(config_dir=str(Path(config_dir).resolve()), version_base=None):
        cfg = hydra_compose(config_name=config_name, overrides=list(overrides))
    return OmegaConf.to_container(cfg, resolve=True)


def write_params(data: dict, path: str | Path = "params.yaml") -> Path:
    """Write a composed config as params.yaml, atomically."""
    header = "# Composed from conf/ by `aumesh compose-params` (dvc exp run rewrites it the same way). Edit conf/, not this file.\n"
    return atomic_write_text(Path(path), header + yaml.safe_dump(data, sort_keys=False))
