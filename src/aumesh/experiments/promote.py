"""Promotion: a sweep's best run becomes the configuration ``dvc repro`` builds, and the registry's champion.

``aumesh promote [--sweep ID | --latest | --across] [--metric M] [--target T]``: without a sweep named, the caller's
own latest sweep (this clone's: ``aumesh.workspace.id``); ``--across`` ranks every finished run on the workspace's data
version (DVC hash), whoever ran it, and says whose run won.

1. ranks the sweep's FINISHED children (:func:`choose`): by default the highest mean CV R²
   (``r2_mean``) when every candidate has the same ``preprocess.target``; when targets differ
   their ``r2_mean`` are in different spaces (absolute vs neutral-subtracted coordinates) and are
   not compared: the criterion becomes ``r2_displacement_mean``, R² of the AU-driven displacement
   from each test video's neutral, which depends only on the slope and is the same space and the
   same information for every target (see :mod:`aumesh.pipeline.evaluate`). ``--metric`` can also rank by
   AU-field reliability (``au_reliability_median``, ``au_reliability_min``, ``au_reliability_<AU>``: cosine
   between each AU's fields fitted on different folds) or ``n_aus_facs_pass``, which depend only on the
   slopes too. Asking for a target-space metric over mixed targets is an error (restrict with
   ``--target``). Values within
   :data:`TIE_TOLERANCE` tie; ties go to fewer (effective) components, then fewer requested
   components, then the earlier run;
2. writes the winner's configuration to ``conf/experiment/promoted.yaml`` (``# @package
   _global_``; loaded by the ``optional experiment: promoted`` entry of ``conf/config.yaml``'s
   defaults list, after the groups so it overrides them): the model-defining keys
   (:data:`MODEL_KEYS`) always, plus any other key whose value in the run differs from ``conf/``
   without the experiment. Before anything is written, a temporary copy of ``conf/`` with the new
   file is composed and every run parameter (except ``paths.*``, ``tracking.*``, ``compute.*``,
   ``data.chunk_rows``: where a run lived, was logged and computed is not what it is) must compose to the run's value;
3. registers the run's MLflow pyfunc model (artifact ``model/``: the release-format NPZ with a
   signature, :mod:`aumesh.tracking.pyfunc`) as a new version of the
   registered model (default ``aumesh-au-to-mesh``) and points the alias ``champion`` at it;
4. recomposes ``params.yaml`` and writes ``promotion.json`` (``{"promoted": {...}}``, read by the
   release stage into ``model_card.json["promotion"]`` and the card's "Promotion" section).

Then ``dvc repro`` rebuilds exactly that release (evaluate and release re-run on the new params).
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from aumesh.config import flatten as flatten_config
from aumesh.core.errors import UserError
from aumesh.core.io import atomic_write_json, atomic_write_text

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd

DEFAULT_MODEL_NAME = "aumesh-au-to-mesh"
CHAMPION_ALIAS = "champion"
TIE_TOLERANCE = 1e-9
EXPERIMENT_GROUP = "experiment"
EXPERIMENT_NAME = "promoted"
DEFAULTS_ENTRY = f"optional {EXPERIMENT_GROUP}: {EXPERIMENT_NAME}"
MODEL_ARTIFACT_DIR = "model"
# metrics in the same space for every preprocess.target: they depend on the slopes only
CROSS_TARGET_METRICS = ("r2_displacement_mean", "au_reliability_median", "au_reliability_min", "n_aus_facs_pass")
_METRIC_WORDS = {
    "r2_displacement_mean": "R² of the AU-driven displacement from each test video's neutral, which depends only "
    "on the slope and is the same space and the same information for every target",
    "n_aus_facs_pass": "the number of AUs whose field's direction passes the FACS check (slopes only)",
}
_RELIABILITY_WORDS = "the cosine between AU fields fitted on different folds (slopes only, the same for every target)"
# always written to the experiment file: what a sweep typically varies and what defines the model
MODEL_KEYS = (
    "preprocess.target",
    "preprocess.neutral.method",
    "features.name",
    "model.n_components",
    "model.scale",
    "model.clip_n_components",
)
# never promoted: where things live, how runs are logged and where they compute, not what the model is (a sweep on
# a cluster must not write compute.address into conf/ and params.yaml)
NOT_PROMOTED = ("paths.", "tracking.", "compute.", "data.chunk_rows")

_TARGET_SPACE = {
    "absolute": "absolute aligned coordinates",
    "neutral": "neutral-subtracted coordinates (mesh minus the video's neutral)",
    "within": "per-video demeaned coordinates (within-video variation only)",
    "within_neutral": "coordinates relative to the video's neutral frames (design and mesh)",
}


def cross_target(metric: str) -> bool:
    """Whether *metric* means the same for every ``preprocess.target`` (see :data:`CROSS_TARGET_METRICS`)."""
    return metric in CROSS_TARGET_METRICS or metric.startswith("au_reliability_")


def _metric_words(metric: str) -> str:
    return _RELIABILITY_WORDS if metric.startswith("au_reliability_") else _METRIC_WORDS.get(metric, metric)


# ------------------------------------------------------------------ candidates and the criterion
@dataclass(frozen=True)
class Candidate:
    """One child run of a sweep, as promotion sees it."""

    run_id: str
    run_name: str | None
    status: str
    params: Mapping[str, str]
    metrics: Mapping[str, float]
    start_time: float = 0.0
    error: str | None = None
    user: str | None = None  # aumesh.user: whose run
    workspace: str | None = None  # aumesh.workspace.id: which clone
    parent_run_id: str | None = None  # its sweep (None: a pipeline evaluate run)

    @property
    def target(self) -> str | None:
        return self.params.get("preprocess.target")

    @property
    def n_components(self) -> int:
        """Effective components (logged metric); the requested value if the run has none."""
        if "n_components" in self.metrics:
            return int(self.metrics["n_components"])
        return self.requested_components

    @property
    def requested_components(self) -> int:
        try:
            return int(self.params.get("model.n_components", 10**9))
        except ValueError:
            return 10**9


@dataclass(frozen=True)
class Choice:
    """The promotion decision, with the words that go into the model card."""

    run_id: str
    metric: str
    value: float
    criterion: str
    compared: str
    targets: tuple[str, ...]
    n_candidates: int
    n_excluded: int
    ranking: tuple[tuple[str, float], ...]


def candidates_from_frame(children: pd.DataFrame) -> list[Candidate]:
    """Candidates from :func:`aumesh.tracking.queries.list_child_runs` output (``params.*``/``metrics.*`` columns)."""

    def text(row, key):
        value = row.get(key)
        return value if isinstance(value, str) else None

    out = []
    for row in children.to_dict(orient="records"):
        params = {k[len("params.") :]: v for k, v in row.items() if k.startswith("params.") and isinstance(v, str)}
        metrics = {
            k[len("metrics.") :]: float(v)
            for k, v in row.items()
            if k.startswith("metrics.") and v is not None and v == v
        }
        start = row.get("start_time")
        out.append(
            Candidate(
                run_id=row["run_id"],
                run_name=row.get("run_name"),
                status=row["status"],
                params=params,
                metrics=metrics,
                start_time=float(start.timestamp()) if hasattr(start, "timestamp") else 0.0,
                error=text(row, "error"),
                user=text(row, "user"),
                workspace=text(row, "workspace"),
                parent_run_id=text(row, "parent_run_id"),
            )
        )
    return out


def higher_is_better(metric: str) -> bool:
    """R² metrics are maximised; errors (``mae*``, ``vertex_error*``) and ``*_std`` minimised."""
    return not (metric.startswith(("mae", "vertex_error")) or metric.endswith("_std"))


def default_metric(targets: Iterable[str | None]) -> str:
    """``r2_mean`` when the candidates share one target, else ``r2_displacement_mean``."""
    return "r2_mean" if len(set(targets)) <= 1 else "r2_displacement_mean"


def rank(candidates: Sequence[Candidate], metric: str, tie_tolerance: float = TIE_TOLERANCE) -> list[Candidate]:
    """Candidates best first by *metric*; values within *tie_tolerance* of the best remaining tie,
    and ties go to fewer effective components, fewer requested components, then the earlier run."""
    sign = 1.0 if higher_is_better(metric) else -1.0
    pool = [c for c in candidates if metric in c.metrics]
    ranked: list[Candidate] = []
    while pool:
        best = max(sign * c.metrics[metric] for c in pool)
        tied = [c for c in pool if sign * c.metrics[metric] >= best - tie_tolerance]
        pick = min(tied, key=lambda c: (c.n_components, c.requested_components, c.start_time, c.run_id))
        ranked.append(pick)
        pool.remove(pick)
    return ranked


def choose(
    candidates: Sequence[Candidate],
    metric: str | None = None,
    target: str | None = None,
    tie_tolerance: float = TIE_TOLERANCE,
    scope: str = "of the sweep",
) -> Choice:
    """Pick the run to promote (see the module docstring for the criterion).

    Parameters
    ----------
    candidates : sequence of Candidate
        All children of the sweep; only FINISHED ones (with *target*, if given) compete.
    metric : str, optional
        Override the default criterion metric.
    target : {"absolute", "neutral"}, optional
        Only consider runs with this ``preprocess.target``.
    tie_tolerance : float
    scope : str, default "of the sweep"
        Where the candidates come from, in the criterion's words (``--across``: the team's runs on the data).

    Returns
    -------
    Choice

    Raises
    ------
    ValueError
        No finished candidate, a metric no candidate has, or a target-space metric over
        candidates whose targets differ.
    """
    pool = [c for c in candidates if c.status == "FINISHED" and (target is None or c.target == target)]
    if not pool:
        raise ValueError(
            f"no FINISHED run among {len(candidates)} children"
            + (f" with preprocess.target={target}" if target else "")
            + "; nothing to promote (see `aumesh runs` for their errors)."
        )
    targets = tuple(sorted({str(c.target) for c in pool}))
    chosen_metric = metric or default_metric(targets)
    if len(targets) > 1 and not cross_target(chosen_metric):
        raise ValueError(
            f"--metric {chosen_metric}: candidates differ in preprocess.target ({', '.join(targets)}) and "
            f"{chosen_metric} is measured in each run's own target space, so the values are not comparable. "
            f"Fix: use --metric {' or '.join(CROSS_TARGET_METRICS)} (the same for every target) or restrict with "
            f"--target {'|'.join(_TARGET_SPACE)}."
        )
    ranked = rank(pool, chosen_metric, tie_tolerance)
    if not ranked:
        raise ValueError(
            f"metric {chosen_metric!r} is logged by none of the {len(pool)} finished runs; "
            f"available: {', '.join(sorted(set().union(*(c.metrics for c in pool))))}"
        )
    best = ranked[0]
    direction = "highest" if higher_is_better(chosen_metric) else "lowest"
    n_splits = best.params.get("cv.n_splits", "?")
    criterion = (
        f"{direction} {chosen_metric} ({n_splits}-fold GroupKFold CV, mean over folds) among {len(ranked)} "
        f"FINISHED runs {scope}; values within {tie_tolerance:g} tie and ties go to fewer components"
    )
    counts = {t: sum(1 for c in ranked if str(c.target) == t) for t in targets}
    if len(targets) == 1:
        space = _TARGET_SPACE.get(targets[0], targets[0])
        compared = (
            f"all {len(ranked)} candidates have preprocess.target={targets[0]}: {chosen_metric} is in "
            f"{space}, the same space for every candidate"
        )
        if cross_target(chosen_metric):
            compared += f" ({_metric_words(chosen_metric)})"
    else:
        compared = (
            f"candidates differ in preprocess.target ({', '.join(f'{t}: {n}' for t, n in counts.items())}); "
            f"their r2_mean are in different spaces ({' vs '.join(_TARGET_SPACE.get(t, t) for t in targets)}) "
            f"and were not compared. All were scored on {chosen_metric}: {_metric_words(chosen_metric)}"
        )
    if target is not None:
        compared += f"; restricted to preprocess.target={target}"
    excluded = len(candidates) - len(ranked)
    return Choice(
        run_id=best.run_id,
        metric=chosen_metric,
        value=float(best.metrics[chosen_metric]),
        criterion=criterion,
        compared=compared,
        targets=targets,
        n_candidates=len(ranked),
        n_excluded=excluded,
        ranking=tuple((c.run_id, float(c.metrics[chosen_metric])) for c in ranked),
    )


# ------------------------------------------------------------------ configuration
def _param_string(value: Any) -> str:
    """A value as MLflow stores it in params (``aumesh.tracking.values.prepare_params``)."""
    from aumesh.tracking.values import prepare_params

    return prepare_params({"v": value})["v"]


def _typed(text: str, like: Any) -> Any:
    """Parse a logged param string back to the type of the composed value *like*."""
    if isinstance(like, bool):
        if text.lower() not in ("true", "false"):
            raise ValueError(f"not a boolean: {text!r}")
        return text.lower() == "true"
    if isinstance(like, int):
        return int(text)
    if isinstance(like, float):
        return float(text)
    if isinstance(like, (list, tuple)):
        return json.loads(text)
    if like is None:
        return None if text == "None" else yaml.safe_load(text)
    return text


def _promotable(key: str) -> bool:
    return not any(key == p or key.startswith(p) for p in NOT_PROMOTED)


def promoted_values(run_params: Mapping[str, str], base: Mapping[str, Any]) -> dict[str, Any]:
    """The keys and typed values the experiment file must set to reproduce a run.

    Parameters
    ----------
    run_params : Mapping
        The run's flattened params (strings, as logged).
    base : Mapping
        ``conf/`` composed without the promoted experiment (nested, as :func:`aumesh.config.compose`).

    Returns
    -------
    dict
        ``{dotted key: value}``: :data:`MODEL_KEYS`, plus every other promotable key whose run
        value differs from *base*.

    Raises
    ------
    ValueError
        The run used other data (``paths.data_dir``), or has keys ``conf/`` no longer has.
    """
    flat = flatten_config(base)
    if "paths.data_dir" in run_params and run_params["paths.data_dir"] != _param_string(flat.get("paths.data_dir")):
        raise ValueError(
            f"the run used paths.data_dir={run_params['paths.data_dir']} but conf/ has {flat.get('paths.data_dir')}: "
            "promoting it would not rebuild that model from the workspace's data. Fix: promote a sweep run on the "
            "workspace's data."
        )
    unknown = sorted(k for k in run_params if _promotable(k) and k not in flat)
    if unknown:
        raise ValueError(
            f"run params {', '.join(unknown)} are not keys of conf/ (configuration changed since the "
            "sweep?); re-run the sweep with the current conf/."
        )
    values: dict[str, Any] = {}
    for key, text in sorted(run_params.items()):
        if not _promotable(key):
            continue
        if key in MODEL_KEYS or text != _param_string(flat[key]):
            values[key] = _typed(text, flat[key])
    return values


def hydra_override(key: str, value: Any) -> str:
    """``key=value`` in Hydra's override syntax (booleans lower case, lists as JSON)."""
    if isinstance(value, bool):
        return f"{key}={str(value).lower()}"
    if isinstance(value, (list, tuple)):
        return f"{key}={json.dumps(list(value))}"
    return f"{key}={value}"


def experiment_yaml(values: Mapping[str, Any], provenance_lines: Sequence[str] = ()) -> str:
    """Text of ``conf/experiment/promoted.yaml`` for dotted *values*."""
    nested: dict[str, Any] = {}
    for key, value in values.items():
        node = nested
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = list(value) if isinstance(value, tuple) else value
    header = [
        "# @package _global_",
        "# Written by `aumesh promote`: the promoted sweep run's configuration. conf/config.yaml's",
        f"# defaults list loads it (`{DEFAULTS_ENTRY}`) after the groups, so these values win.",
        *[f"# {line}" for line in provenance_lines],
    ]
    return "\n".join(header) + "\n" + yaml.safe_dump(nested, sort_keys=False)


def check_defaults_entry(conf_dir: Path) -> None:
    """Make sure ``conf/config.yaml`` loads the promoted experiment after the config groups.

    Raises
    ------
    ValueError
        The entry is missing or comes before a group it must override (the fix is in the message).
    """
    path = Path(conf_dir) / "config.yaml"
    doc = yaml.safe_load(path.read_text()) or {}
    defaults = doc.get("defaults") or []
    names = [next(iter(d.items())) if isinstance(d, dict) else (d, None) for d in defaults]
    keys = [k for k, _ in names]
    entry = f"optional {EXPERIMENT_GROUP}"
    if (entry, EXPERIMENT_NAME) not in names:
        raise ValueError(
            f"{path}: the defaults list has no `- {DEFAULTS_ENTRY}`. Fix: add it after the config "
            "groups (before `_self_`) so `aumesh promote`'s conf/experiment/promoted.yaml is loaded."
        )
    pos = keys.index(entry)
    late = [k for k in ("paths", "data", "preprocess", "features", "model", "cv", "tracking") if k in keys[pos:]]
    if late:
        raise ValueError(f"{path}: `- {DEFAULTS_ENTRY}` must come after the groups it overrides ({', '.join(late)}).")


def compose_with(conf_dir: Path, experiment_text: str | None, overrides: Sequence[str] = ()) -> dict:
    """Compose a temporary copy of *conf_dir* whose promoted experiment is *experiment_text* (None: absent)."""
    from aumesh.config import compose

    with tempfile.TemporaryDirectory(prefix="aumesh-promote-") as tmp:
        copy = Path(tmp) / "conf"
        shutil.copytree(conf_dir, copy)
        exp = copy / EXPERIMENT_GROUP / f"{EXPERIMENT_NAME}.yaml"
        if exp.exists():
            exp.unlink()
        if experiment_text is not None:
            exp.parent.mkdir(parents=True, exist_ok=True)
            exp.write_text(experiment_text)
        return compose(list(overrides), config_dir=copy)


def verify_composition(composed: Mapping[str, Any], run_params: Mapping[str, str]) -> None:
    """Every promotable run param must compose to the run's value.

    Raises
    ------
    ValueError
        Naming every key whose composed value differs.
    """
    flat = {k: _param_string(v) for k, v in flatten_config(composed).items()}
    wrong = [
        f"{k}: run {v!r}, composed {flat.get(k)!r}"
        for k, v in sorted(run_params.items())
        if _promotable(k) and flat.get(k) != v
    ]
    if wrong:
        raise ValueError("the promoted conf/ does not compose to the run's configuration: " + "; ".join(wrong))


# ------------------------------------------------------------------ the command
class OverruleError(UserError, ValueError):
    """Promotion refused: a newer pipeline run evaluated another configuration than the sweep's best."""


class PromotionError(UserError, ValueError):
    """Promotion refused: an unfinished sweep, or a best run whose model artifacts are gone or outside the workspace."""


def check_finished(parent: Mapping[str, Any], children: pd.DataFrame, partial: bool) -> str | None:
    """Refuse a sweep that did not finish (interrupted, killed, failed or still running) unless ``partial``.

    Parameters
    ----------
    parent : Mapping
        The sweep's parent run (:func:`aumesh.tracking.queries.run_record`).
    children : DataFrame
        Its child runs (:func:`aumesh.tracking.queries.list_child_runs`).
    partial : bool
        Promote from what finished anyway.

    Returns
    -------
    str or None
        With ``partial`` and an unfinished sweep: the sentence naming the runs compared; None for a finished sweep.

    Raises
    ------
    PromotionError
        The sweep did not finish and ``partial`` is false.
    """
    tags = parent.get("tags", {})
    expected = tags.get("aumesh.sweep.n_expected")
    finished = children[children["status"] == "FINISHED"] if len(children) else children
    if parent.get("status") == "FINISHED" and not tags.get("aumesh.sweep.interrupted"):
        return None
    status = str(parent.get("status"))
    state = tags.get("aumesh.sweep.interrupted") or {"RUNNING": "is still running (or its process died)"}.get(
        status, f"ended {status}"
    )
    of = f"{len(finished)} of {expected or '?'} configurations finished"
    if not partial:
        raise PromotionError(
            f"sweep {parent['run_id']} did not finish ({state}; {of}): its best run is the best of a part of the "
            "sweep. Fix: rerun the sweep (`aumesh sweep -m ...`), or pass --partial to promote the best of the runs "
            "that finished."
        )
    names = ", ".join(f"{r.run_name} ({r.run_id})" for r in finished.itertuples()) if len(finished) else "none"
    return f"partial sweep ({state}; {of}): compared only {names}"


def model_artifacts(run_id: str, tracking_cfg: Mapping[str, Any] | None, root: Path) -> tuple[bool, str]:
    """Whether run ``run_id`` still has its model (a non-empty ``model/``), and where it should be (workspace-relative
    when local). A local artifact folder outside the workspace is refused: a record must not point there."""
    from urllib.parse import unquote, urlsplit

    from aumesh.core import provenance
    from aumesh.tracking import mlflow_store

    client = mlflow_store.get_client(tracking_cfg)
    uri = f"{client.get_run(run_id).info.artifact_uri.rstrip('/')}/{MODEL_ARTIFACT_DIR}"
    if urlsplit(uri).scheme in ("", "file"):  # a path on this machine (a server's is mlflow-artifacts:/..., s3://...)
        path = Path(unquote(urlsplit(uri).path) if uri.startswith("file:") else uri)
        store = mlflow_store.sqlite_path(mlflow_store.resolve_tracking_uri(tracking_cfg))
        if store is not None and store.resolve().is_relative_to(root) and not path.resolve().is_relative_to(root):
            raise PromotionError(
                f"run {run_id}: its artifacts lie outside this workspace ({path}), so registering it would register "
                f"another workspace's model. Fix: promote from that workspace, or rerun the sweep here."
            )
        present = path.is_dir() and any(path.iterdir())  # what registry.register_model_version asks of the store
        return present, provenance.shareable_location(uri, [root]) or uri
    return bool(client.list_artifacts(run_id, MODEL_ARTIFACT_DIR)), uri


def check_not_overruled(values: Mapping[str, Any], parent_run_id: str, newer_run: Mapping[str, Any]) -> None:
    """Refuse to promote over a pipeline run that started after the sweep and evaluated another configuration.

    Parameters
    ----------
    values : Mapping
        The dotted keys and values promotion would write (:func:`promoted_values`).
    parent_run_id : str
        The sweep.
    newer_run : Mapping
        A :func:`aumesh.tracking.queries.run_record` of an evaluate run that started after the sweep.

    Raises
    ------
    OverruleError
        Some promoted value differs from the newer run's parameter; the message names them and the ways out.
    """
    params = newer_run.get("params", {})
    differ = [
        f"{key}={params.get(key, '(absent)')} there, {_param_string(value)} in the sweep's best run"
        for key, value in values.items()
        if params.get(key) != _param_string(value)
    ]
    if not differ:
        return
    started = datetime.fromtimestamp(newer_run["start_time"] / 1000, tz=UTC).strftime("%Y-%m-%d %H:%M")
    raise OverruleError(
        f"sweep {parent_run_id} is older than evaluate run {newer_run['run_id']} ({newer_run.get('run_name')}, "
        f"started {started} UTC), which evaluated another configuration ({'; '.join(differ)}): promoting the sweep "
        "would overrule it. Fix: run a new sweep, name the sweep to promote with --sweep ID (`aumesh runs --sweeps` "
        "lists them), or pass --latest to promote your latest sweep anyway."
    )


def promote(
    parent_run_id: str | None,
    root: str | Path,
    tracking_cfg: Mapping[str, Any] | None = None,
    metric: str | None = None,
    target: str | None = None,
    model_name: str | None = None,
    register: bool = True,
    alias: str = CHAMPION_ALIAS,
    newer_run: Mapping[str, Any] | None = None,
    across: bool = False,
    partial: bool = False,
    skip_missing: bool = False,
    say=print,
) -> dict[str, Any]:
    """Promote the best child of sweep *parent_run_id* (or, *across*, the best run on this data) in workspace *root*
    (see the module docstring).

    Parameters
    ----------
    parent_run_id : str or None
        The sweep; None with *across*.
    root : Path
        Workspace root (``conf/``, ``params.yaml``, the promotion file).
    tracking_cfg : Mapping, optional
        The ``tracking`` group (store and experiment of the sweep).
    metric, target : str, optional
        See :func:`choose`.
    model_name : str, optional
        Registered model name; default :data:`DEFAULT_MODEL_NAME`.
    register : bool, default True
        Register the run's NPZ and set *alias*; False leaves the registry alone.
    alias : str, default "champion"
    newer_run : Mapping, optional
        An evaluate run (:func:`aumesh.tracking.queries.run_record`) that started after the sweep; if the
        winner's configuration differs from it, nothing is written (:func:`check_not_overruled`).
    across : bool, default False
        Rank every FINISHED model run (sweep children and pipeline evaluate runs) of the experiment whose data is
        the workspace's (the DVC hash of ``data.dvc``), whoever ran it (:func:`aumesh.tracking.queries.finished_runs_on_data`).
    partial : bool, default False
        Promote from a sweep that did not finish (interrupted, killed); without it that is refused
        (:func:`check_finished`). The record's ``partial`` names the runs compared.
    skip_missing : bool, default False
        When the best run's model artifacts are gone, take the next best whose artifacts exist (and say so, through
        ``say``); without it that is refused, naming the run and the path. Only with ``register``.
    say : callable, default print
        Where the notes on skipped runs and partial sweeps go.

    Returns
    -------
    dict
        The ``promoted`` record written to the promotion file (with ``user`` and ``workspace``: whose run won).
    """
    from aumesh.config import from_dict, write_params
    from aumesh.tracking import queries, registry
    from aumesh.tracking import runs as tracking

    root = Path(root).resolve()
    conf_dir = root / "conf"
    check_defaults_entry(conf_dir)
    partial_note = None
    if across:
        data_md5 = _workspace_data_md5(root)
        candidates = candidates_from_frame(queries.finished_runs_on_data(data_md5, tracking_cfg))
        if not candidates:
            raise UserError(
                f"no FINISHED run on this workspace's data (data.dvc md5 {data_md5}) in the tracking store; "
                "run a sweep first (`aumesh sweep -m ...`)."
            )
        scope = f"on this data (DVC {data_md5}), whoever ran them"
    else:
        if parent_run_id is None:
            raise ValueError("promote: name a sweep (parent_run_id) or pass across=True")
        children = queries.list_child_runs(parent_run_id, tracking_cfg)
        partial_note = check_finished(queries.run_record(parent_run_id, tracking_cfg), children, partial)
        if partial_note:
            say(partial_note)
        candidates = candidates_from_frame(children)
        scope = "of the sweep"
    choice = choose(candidates, metric=metric, target=target, scope=scope)
    skipped: list[dict[str, str]] = []
    while register:  # the model registered must exist: name the run and the path, or (--skip-missing) take the next
        present, where = model_artifacts(choice.run_id, tracking_cfg, root)
        if present:
            break
        if not skip_missing:
            raise PromotionError(
                f"run {choice.run_id}, the best {scope} by {choice.metric}, has lost its model "
                f"artifacts ({where} is missing or empty). Fix: --skip-missing promotes the next best run whose "
                "artifacts exist, or rerun the sweep; --no-register promotes its configuration without the registry."
            )
        skipped.append({"run_id": choice.run_id, "missing": where})
        say(
            f"skipped run {choice.run_id} ({choice.metric} = {choice.value:.6f}): its model artifacts are gone "
            f"({where}); taking the next best"
        )
        rest = [c for c in candidates if c.run_id not in {s["run_id"] for s in skipped}]
        try:
            choice = choose(rest, metric=metric, target=target, scope=scope)
        except ValueError as err:
            raise PromotionError(
                f"no run {scope} with its model artifacts left ({len(skipped)} skipped): {err}"
            ) from err
    if skipped:
        say(f"promoting run {choice.run_id} ({choice.metric} = {choice.value:.6f}), the best run whose artifacts exist")
    winner = next(c for c in candidates if c.run_id == choice.run_id)
    sweep_id = winner.parent_run_id if across else parent_run_id

    base = compose_with(conf_dir, None)
    values = promoted_values(winner.params, base)
    if newer_run is not None:
        check_not_overruled(values, str(sweep_id), newer_run)
    overrides = [hydra_override(k, v) for k, v in values.items()]
    origin = f"run {winner.run_id} of sweep {sweep_id}" if sweep_id else f"evaluate run {winner.run_id}"
    text = experiment_yaml(
        values,
        [
            origin + (f" (by {winner.user}, across the team's runs)" if across else ""),
            f"criterion: {choice.metric} = {choice.value:.6f}",
        ],
    )
    composed = compose_with(conf_dir, text)
    verify_composition(composed, winner.params)
    cfg = from_dict(composed)

    version = None
    name = model_name or DEFAULT_MODEL_NAME
    if register:
        version = registry.register_model_version(
            winner.run_id,
            MODEL_ARTIFACT_DIR,
            name,
            tracking_cfg,
            alias=alias,
            tags={
                "aumesh.parent_run_id": str(sweep_id),
                "aumesh.metric": choice.metric,
                "aumesh.value": f"{choice.value:.6f}",
                "aumesh.config_overrides": " ".join(overrides),
                "aumesh.user": str(winner.user),
            },
            description=f"aumesh promote: {choice.criterion}",
        )

    exp_path = conf_dir / EXPERIMENT_GROUP / f"{EXPERIMENT_NAME}.yaml"
    exp_path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(exp_path, text)
    write_params(composed, root / "params.yaml")
    record = {
        "run_id": winner.run_id,
        "run_name": winner.run_name,
        "parent_run_id": sweep_id,
        "user": winner.user,  # whose run won (git user.email, else the login)
        "workspace": winner.workspace,  # which clone ran it (an id, not a path)
        "across": across,
        "criterion": choice.criterion,
        "metric": choice.metric,
        "value": choice.value,
        "compared": choice.compared,
        "targets": list(choice.targets),
        "n_candidates": choice.n_candidates,
        "n_excluded": choice.n_excluded,
        "runner_up": (
            {"run_id": choice.ranking[1][0], "value": choice.ranking[1][1]} if len(choice.ranking) > 1 else None
        ),
        "config_overrides": overrides,
        "config_file": str(exp_path.relative_to(root)),
        "registered_model": version["name"] if version else None,
        "model_version": version["version"] if version else None,
        "alias": alias if version else None,
        # promotion.json is committed: locations relative to the workspace, never its absolute path, and never a
        # tracking server's address (the run id finds the run on the team's server)
        "model_source": _model_source(version["source"], winner.run_id, root) if version else None,
        "tracking_uri": tracking.store_label(tracking_cfg),
        "promoted_at": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    if skipped:
        record["skipped_missing_artifacts"] = skipped
    if partial_note:
        record["partial"] = partial_note
    atomic_write_json(root / cfg.paths.promotion_file, {"promoted": record})
    return record


def _model_source(source: str, run_id: str, root: Path) -> str:
    """The registered model's source as promotion.json holds it: repo-relative inside the workspace, a server's
    ``mlflow-artifacts:/`` URI as it is; a path elsewhere (another machine's) as ``runs:/<run id>/model``."""
    from aumesh.core import provenance

    shared = provenance.shareable_location(source, [root]) or source
    if shared.startswith("file:") or Path(shared).is_absolute():
        return f"runs:/{run_id}/{MODEL_ARTIFACT_DIR}"
    return shared


def _workspace_data_md5(root: Path) -> str:
    from aumesh.core import provenance

    try:
        md5 = provenance.data_digest(root).get("md5")
    except (FileNotFoundError, ValueError) as err:
        raise UserError(f"--across ranks the runs on this workspace's data: {err}") from None
    if not md5:
        raise UserError(f"{root / 'data.dvc'}: no md5; `dvc add data` first (--across ranks the runs on this data).")
    return str(md5)
