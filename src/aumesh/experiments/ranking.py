"""Ranking: a sweep's runs (or the team's runs on this data) best first by the promotion criterion.

The criterion (:func:`choose`): by default the highest mean CV R² (``r2_mean``) when every candidate has the same
``preprocess.target``; when targets differ their ``r2_mean`` are in different spaces (absolute vs neutral-subtracted
coordinates) and are not compared: the criterion becomes ``r2_displacement_mean``, R² of the AU-driven displacement
from each test video's neutral, which depends only on the slope and is the same space and the same information for
every target (see :mod:`aumesh.pipeline.evaluate`). A metric can also be AU-field reliability
(``au_reliability_median``, ``au_reliability_min``, ``au_reliability_<AU>``: cosine between each AU's fields fitted on
different folds) or ``n_aus_facs_pass``, which depend only on the slopes too. Asking for a target-space metric over
mixed targets is an error (restrict with a target). Values within :data:`TIE_TOLERANCE` tie; ties go to fewer
(effective) components, then fewer requested components, then the earlier run. Runs of different input families
(``au``, ``blendshapes``, ``emotions``: :attr:`Candidate.input_family`) answer different questions (how AUs, how
blendshapes, how emotions move the face) on different inputs, so their R² are never ranked against each other: the
ranking is within one family (``family``; :data:`FAMILY_ORDER`). ``aumesh promote``
(:mod:`aumesh.experiments.promote`) promotes the winner; ``aumesh runs`` (:mod:`aumesh.experiments.leaderboard`)
shows the ranking.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd

TIE_TOLERANCE = 1e-9
#: the input families in the order tables list them (aumesh.core.families.FAMILIES)
FAMILY_ORDER = ("au", "blendshapes", "emotions")
# metrics in the same space for every preprocess.target: they depend on the slopes only
CROSS_TARGET_METRICS = ("r2_displacement_mean", "au_reliability_median", "au_reliability_min", "n_aus_facs_pass")
_METRIC_WORDS = {
    "r2_displacement_mean": "R² of the AU-driven displacement from each test video's neutral, which depends only "
    "on the slope and is the same space and the same information for every target",
    "n_aus_facs_pass": "the number of AUs whose field's direction passes the FACS check (slopes only)",
}
_RELIABILITY_WORDS = "the cosine between AU fields fitted on different folds (slopes only, the same for every target)"

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
    family: str | None = None  # tag aumesh.family (None: not known from the tags; see input_family)

    @property
    def input_family(self) -> str:
        """The run's input family: its tag, else its ``features.name``'s family, else ``au`` (runs from before the
        families: :func:`aumesh.tracking.values.run_family`)."""
        from aumesh.tracking.values import run_family

        return self.family or run_family(self.params) or "au"

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
                family=text(row, "family"),
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


def eiv_method(candidate: Candidate) -> str:
    """The run's ``model.eiv.method`` (runs from before the option: ``none``)."""
    return candidate.params.get("model.eiv.method") or "none"


def _one_correction(pool: list[Candidate]) -> tuple[list[Candidate], str]:
    """The candidates that compete when their detector-noise corrections differ, and the words that say why.

    A corrected fit has a lower in-sample fit than least squares by design (it undoes least squares' bias toward the
    noisy AUs), so no R² compares a corrected run with an uncorrected one: when the candidates mix ``model/eiv=none``
    with one correction, only the corrected runs compete (the user brought what the correction needs: a validation
    study's error covariance, or a second detector). Two different corrections are not ranked against each other.
    """
    methods = sorted({eiv_method(c) for c in pool})
    if len(methods) <= 1:
        return pool, ""
    corrections = [m for m in methods if m != "none"]
    if len(corrections) > 1:
        raise ValueError(
            f"candidates use different detector-noise corrections ({', '.join(corrections)}): their R² do not "
            "compare (each correction undoes least squares' bias differently). Fix: promote from a sweep with one "
            "model/eiv option, or compare the runs in `aumesh runs` and choose by hand."
        )
    keep = [c for c in pool if eiv_method(c) == corrections[0]]
    counts = ", ".join(f"{m}: {sum(1 for c in pool if eiv_method(c) == m)}" for m in methods)
    note = (
        f"; candidates differ in model.eiv ({counts}): a fit corrected for detector noise has a lower in-sample fit "
        "by design, so R² does not compare corrected and uncorrected runs; only the "
        f"{len(keep)} model.eiv={corrections[0]} runs competed (the correction the data was given evidence for), "
        f"the {len(pool) - len(keep)} uncorrected ones were not ranked"
    )
    return keep, note


def by_family(candidates: Iterable[Candidate]) -> dict[str, list[Candidate]]:
    """Candidates grouped by input family, in :data:`FAMILY_ORDER` (then any other name), each group in order."""
    groups: dict[str, list[Candidate]] = {}
    for c in candidates:
        groups.setdefault(c.input_family, []).append(c)
    order = [f for f in FAMILY_ORDER if f in groups] + sorted(f for f in groups if f not in FAMILY_ORDER)
    return {f: groups[f] for f in order}


def choose(
    candidates: Sequence[Candidate],
    metric: str | None = None,
    target: str | None = None,
    tie_tolerance: float = TIE_TOLERANCE,
    scope: str = "of the sweep",
    family: str | None = None,
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
    family : str, optional
        Only runs of this input family compete (:attr:`Candidate.input_family`). Without it the finished candidates
        must all be of one family.

    Returns
    -------
    Choice

    Raises
    ------
    ValueError
        No finished candidate, a metric no candidate has, a target-space metric over
        candidates whose targets differ, or (without *family*) candidates of several families.
    """
    pool = [
        c
        for c in candidates
        if c.status == "FINISHED"
        and (target is None or c.target == target)
        and (family is None or c.input_family == family)
    ]
    if not pool:
        raise ValueError(
            f"no FINISHED run among {len(candidates)} children"
            + (f" with preprocess.target={target}" if target else "")
            + (f" of the {family} family" if family else "")
            + "; nothing to promote (see `aumesh runs` for their errors)."
        )
    families = by_family(pool)
    if len(families) > 1:
        raise ValueError(
            f"candidates span input families ({', '.join(f'{f}: {len(g)}' for f, g in families.items())}): their R² "
            "answer different questions and are not ranked against each other. Fix: rank within one family "
            "(--family NAME)."
        )
    other_families = sum(1 for c in candidates if family is not None and c.input_family != family)
    pool, eiv_note = _one_correction(pool)
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
    compared += eiv_note
    if other_families:
        compared += (
            f"; only runs of the {family} family competed (the {other_families} runs of other families answer other "
            "questions and were not ranked against them)"
        )
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
