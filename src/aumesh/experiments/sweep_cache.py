"""The sweep's reuse between configurations: which prepared data serve a configuration, and a per-process cache.

Reuse between configurations (per process; every joblib worker keeps its own, :func:`process_cache`):

* the loaded :class:`aumesh.pipeline.evaluate.Prepared` (memory-mapped meshes), keyed by its directory;
* the fold of every frame, keyed by (prepared data, ``cv.n_splits``);
* the per-fold :class:`aumesh.pipeline.evaluate.FoldStatistics`, keyed by (prepared data,
  ``preprocess.target``, ``preprocess.neutral.method``, ``features``, ``cv.n_splits``): a new ``model.*`` value costs fits from
  statistics and one prediction pass, never a new pass of accumulation;
* the CV result and final fit, keyed by the statistics and the *effective* number of
  components: ``model.n_components`` clipped to the number of features (40 or 83 on the
  23-feature design) is the same model as an earlier configuration and is logged, not refitted.

Prepared data. The prepare-relevant keys are the ``prepare`` stage's params in ``dvc.yaml``
(:data:`PREPARE_KEYS`). When a configuration's values equal those of the workspace's
``params.yaml`` the sweep reads ``paths.prepared_dir`` (the DVC output; ``dvc repro prepare``
first). When they differ, the sweep prepares once into ``build/sweeps/prepared/<key>/`` (or into
``paths.prepared_dir`` if that was overridden too), stamps the directory with the values it was
prepared from and reuses it across sweeps; a stamped directory with other values is an error.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aumesh.config import flatten as flatten_config
from aumesh.core import storage
from aumesh.core.errors import ConfigError
from aumesh.core.io import atomic_write_json
from aumesh.core.schema import instrument_columns
from aumesh.pipeline.prepared_files import PREPARED_FILES, SUMMARY_FILE

if TYPE_CHECKING:  # pragma: no cover
    import numpy as np

    from aumesh.config import Config
    from aumesh.pipeline.evaluate.prepared_data import Prepared
    from aumesh.pipeline.evaluate.results import CVResult, FinalModel, FoldStatistics

log = logging.getLogger(__name__)

PREPARED_CACHE_DIR = "build/sweeps/prepared"
PREPARE_STAMP = "aumesh_sweep_prepare.json"

# The prepare stage's params (dvc.yaml), minus data.chunk_rows (memory, not results).
PREPARE_KEYS = (
    "paths.data_dir",
    "data.tables",
    "data.mesh_npy",
    "data.coerce_numeric",
    "preprocess.pose_filter",
    "preprocess.alignment",
    "preprocess.neutral.low_au_quantile",
    "preprocess.empty_video",
    "preprocess.max_drop_fraction",
    "seed",
)
MAX_CACHED_STATISTICS = 8  # FoldStatistics kept per process (a few MB each: X'X, X'Y, diag(Y'Y) per fold)


# ------------------------------------------------------------------ pure helpers
def prepare_signature(cfg: Config) -> dict[str, Any]:
    """The values of :data:`PREPARE_KEYS` in *cfg*, flattened (what the prepared data depend on).

    Parameters
    ----------
    cfg : aumesh.config.Config

    Returns
    -------
    dict
        ``{dotted key: value}``, sorted by key.
    """
    flat = flatten_config(cfg.to_dict())
    out = {k: v for k, v in sorted(flat.items()) if any(k == p or k.startswith(p + ".") for p in PREPARE_KEYS)}
    if cfg.model.eiv.instrument_aus:  # carried into frames.parquet; only when set, so other runs' keys are unchanged
        out["model.eiv.instrument_aus"] = cfg.model.eiv.instrument_aus
    return dict(sorted(out.items()))


def prepare_key(signature: Mapping[str, Any]) -> str:
    """Short content hash of a :func:`prepare_signature` (names the prepared-data cache dir)."""
    text = json.dumps(signature, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def statistics_key(prepared_id: str, cfg: Config) -> tuple:
    """Cache key of the per-fold statistics: everything :func:`aumesh.pipeline.evaluate.accumulate` depends on."""
    return (
        prepared_id,
        cfg.preprocess.target,
        cfg.preprocess.neutral.method,
        cfg.features.name,
        int(cfg.cv.n_splits),
        cfg.model.eiv.instrument_aus,  # model/eiv=instruments: the augmented design's statistics
    )


@dataclass(frozen=True)
class PreparedSource:
    """Where a configuration's prepared data live and whether the sweep has to prepare them."""

    path: Path
    managed_by_dvc: bool
    signature: dict[str, Any]
    key: str


def resolve_prepared(cfg: Config, workspace: Config | None, root: Path) -> PreparedSource:
    """Decide which prepared directory serves *cfg* (see the module docstring).

    Parameters
    ----------
    cfg : Config
        The configuration of one job.
    workspace : Config or None
        The workspace's ``params.yaml`` (what ``dvc repro`` prepared from), None if absent.
    root : Path
        Workspace root; relative paths are resolved against it.

    Returns
    -------
    PreparedSource
    """
    signature = prepare_signature(cfg)
    key = prepare_key(signature)
    own = (root / cfg.paths.prepared_dir).resolve()
    if (
        workspace is not None
        and signature == prepare_signature(workspace)
        and own == (root / workspace.paths.prepared_dir).resolve()
    ):
        return PreparedSource(own, True, signature, key)
    if workspace is not None and own != (root / workspace.paths.prepared_dir).resolve():
        return PreparedSource(own, False, signature, key)  # the user named the directory
    return PreparedSource((root / PREPARED_CACHE_DIR / key).resolve(), False, signature, key)


# ------------------------------------------------------------------ the cache
@dataclass
class SweepCache:
    """Per-process reuse of prepared data, folds and per-fold statistics across configurations."""

    prepared: dict[str, Prepared] = field(default_factory=dict)
    folds: dict[tuple, np.ndarray] = field(default_factory=dict)
    designs: dict[tuple, Any] = field(default_factory=dict)  # (prepared id, n_splits, instruments) -> DesignStatistics
    feature_sets: dict[tuple, list[str]] = field(default_factory=dict)  # the same key -> the designs' feature sets
    statistics: OrderedDict = field(default_factory=OrderedDict)
    results: OrderedDict = field(default_factory=OrderedDict)
    workspace: dict[str, Any] = field(default_factory=dict)
    hits: int = 0
    misses: int = 0
    passes: int = 0  # statistics passes over the meshes this process made
    pass_reused: bool = False  # the last statistics_for took its columns from an earlier pass

    def workspace_params(self, root: Path) -> Config | None:
        """The workspace's ``params.yaml`` as a Config (cached by mtime), None if absent."""
        from aumesh.config import load_params

        path = root / "params.yaml"
        if not path.exists():
            return None
        stamp = (str(path), path.stat().st_mtime_ns)
        if self.workspace.get("stamp") != stamp:
            self.workspace = {"stamp": stamp, "cfg": load_params(path)}
        return self.workspace["cfg"]

    def load(self, source: PreparedSource, cfg: Config) -> tuple[Prepared, str]:
        """The prepared data for *source* (preparing them first if needed); returns (data, cache id)."""
        from aumesh.pipeline.evaluate.prepared_data import load_prepared

        ensure_prepared(source, cfg)
        summary = source.path / SUMMARY_FILE
        pid = f"{source.path}@{summary.stat().st_mtime_ns}"
        if pid not in self.prepared:
            self.prepared = {pid: load_prepared(source.path)}  # one prepared set at a time
            self.folds.clear()
            self.designs.clear()
            self.feature_sets.clear()
            self.statistics.clear()
            self.results.clear()
        return self.prepared[pid], pid

    def fold_of(self, prepared: Prepared, pid: str, n_splits: int) -> np.ndarray:
        from aumesh.pipeline import evaluate as ev

        key = (pid, n_splits)
        if key not in self.folds:
            self.folds[key] = ev.video_folds(prepared.videos.count, n_splits)
        return self.folds[key]

    def statistics_for(
        self, prepared: Prepared, pid: str, cfg: Config, feature_sets: Sequence[str] = ()
    ) -> tuple[FoldStatistics, bool]:
        """Per-fold statistics of *cfg*'s design and target; (stats, True if reused).

        The one pass over the meshes accumulates the union of the designs of *cfg*'s ``features`` and of
        *feature_sets* (the sweep's ``features`` options: :func:`aumesh.experiments.sweep.swept_feature_sets`), so
        every configuration of the sweep takes its columns from it; a configuration outside that union (not announced)
        costs one more pass, of the union with it.
        """
        from aumesh.model.statistics import FULL_DESIGN, design_union
        from aumesh.pipeline.evaluate import statistics_pass
        from aumesh.pipeline.evaluate.prepared_data import workers_check

        key = statistics_key(pid, cfg)
        if key in self.statistics:
            self.statistics.move_to_end(key)
            self.hits += 1
            return self.statistics[key], True
        fold = self.fold_of(prepared, pid, cfg.cv.n_splits)
        instruments = instrument_columns(cfg.model.eiv.instrument_aus)
        design_key = (pid, cfg.cv.n_splits, instruments)
        have = self.designs.get(design_key)
        self.pass_reused = have is not None and set(cfg.features.columns) <= set(have.columns)
        if not self.pass_reused:
            # the one pass over the meshes; every target/feature set of the union derives from it
            from aumesh.pipeline import compute

            names = [*self.feature_sets.get(design_key, []), cfg.features.name, *feature_sets]
            self.feature_sets[design_key] = list(dict.fromkeys(names))
            columns = design_union(self.feature_sets[design_key])
            with compute.engine(cfg.compute, **workers_check(prepared)):
                self.designs[design_key] = statistics_pass.design_statistics(
                    prepared,
                    fold,
                    cfg.cv.n_splits,
                    cfg.data.chunk_rows,
                    instruments,
                    None if columns == FULL_DESIGN else columns,
                )
            self.passes += 1
        stats = statistics_pass.accumulate(prepared, cfg, fold, design=self.designs[design_key])
        self.statistics[key] = stats
        while len(self.statistics) > MAX_CACHED_STATISTICS:
            self.statistics.popitem(last=False)
        self.misses += 1
        return stats, False

    def evaluation_for(
        self, prepared: Prepared, pid: str, cfg: Config, stats: FoldStatistics
    ) -> tuple[CVResult, FinalModel, bool]:
        """CV result and final fit of *cfg*; reused when only a clipped ``model.n_components`` differs
        (e.g. 40 and 83 on a 23-feature design are the same 23-component model), never across ``model.eiv`` or
        ``model.identification`` settings."""
        from aumesh.pipeline import evaluate as ev

        # the detector-noise correction and the screen's settings make another model/result of the same statistics
        key = statistics_key(pid, cfg) + (
            ev.effective_n_components(cfg),
            bool(cfg.model.scale),
            cfg.model.eiv,
            cfg.model.identification,
        )
        if key in self.results:
            self.results.move_to_end(key)
            return (*self.results[key], True)
        cv, final = evaluate_configuration(prepared, cfg, stats)
        self.results[key] = (cv, final)
        while len(self.results) > MAX_CACHED_STATISTICS:
            self.results.popitem(last=False)
        return cv, final, False


_CACHE: SweepCache | None = None


def process_cache() -> SweepCache:
    """The cache shared by all jobs that run in this process."""
    global _CACHE
    if _CACHE is None:
        _CACHE = SweepCache()
    return _CACHE


def ensure_prepared(source: PreparedSource, cfg: Config) -> Path:
    """Make sure *source* holds prepared data for *cfg*; prepare into it when absent.

    Raises
    ------
    FileNotFoundError
        A DVC-managed directory that does not exist (fix: ``dvc repro prepare``).
    ValueError
        A directory stamped with other prepare values (fix: delete it or override
        ``paths.prepared_dir``).
    """
    from aumesh.data import tables
    from aumesh.pipeline import prepare as prep

    complete = all((source.path / n).exists() for n in PREPARED_FILES)
    if source.managed_by_dvc:
        if not complete:
            raise FileNotFoundError(
                f"{source.path}: prepared data missing. It is the prepare stage's output for the workspace's "
                "params.yaml; run `dvc repro prepare` (or `make demo`) first."
            )
        return source.path
    stamp_path = source.path / PREPARE_STAMP
    from filelock import FileLock

    source.path.parent.mkdir(parents=True, exist_ok=True)
    with FileLock(source.path.with_name(source.path.name + ".lock")):
        if complete and stamp_path.exists():
            stamp = json.loads(stamp_path.read_text())
            if stamp.get("signature") != json.loads(json.dumps(source.signature, default=str)):
                raise ValueError(
                    f"{source.path} was prepared by a sweep with other values of {', '.join(PREPARE_KEYS)}: "
                    f"{stamp.get('signature')}. Fix: delete it, or override paths.prepared_dir with a new directory."
                )
            return source.path
        if complete:
            log.warning(
                "%s: prepared data without a sweep stamp; using them as they are (not verified against %s)",
                source.path,
                ", ".join(PREPARE_KEYS),
            )
            return source.path
        log.info("preparing %s from %s (prepare values differ from params.yaml's)", source.path, cfg.paths.data_dir)
        if storage.is_url(cfg.paths.data_dir):  # tables.discover reads parquet tables in a local folder only
            raise ConfigError(
                f"paths.data_dir={cfg.paths.data_dir}: this sweep re-prepares the data (its values of "
                f"{', '.join(PREPARE_KEYS)} differ from params.yaml's) and reads the tables from a local folder only. "
                "Fix: sweep only evaluate's keys on the prepared data, or `dvc exp run -S` those values (ingest reads "
                "s3://), or copy the tables to a local folder (`aws s3 sync`)."
            )
        found = tables.discover(cfg.paths.data_dir, cfg.data.tables, cfg.data.mesh_npy, cfg.data.coerce_numeric)
        prep.run(found, cfg, source.path)
        atomic_write_json(stamp_path, {"signature": source.signature, "key": source.key})
    return source.path


def evaluate_configuration(prepared: Prepared, cfg: Config, stats: FoldStatistics) -> tuple[CVResult, FinalModel]:
    """Cross-validation and final fit of one configuration from (possibly shared) statistics."""
    from aumesh.pipeline import compute
    from aumesh.pipeline import evaluate as ev
    from aumesh.pipeline.evaluate.prepared_data import workers_check

    with compute.engine(cfg.compute, **workers_check(prepared)):
        return ev.cross_validate_and_fit_from_statistics(prepared, cfg, stats)
