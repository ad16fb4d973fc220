"""Promotion: a sweep's best run becomes the configuration ``dvc repro`` builds, and the registry's champion.

``aumesh promote [--sweep ID | --latest | --across] [--metric M] [--target T]``: without a sweep named, the caller's
own latest sweep (this clone's: ``aumesh.workspace.id``); ``--across`` ranks every finished run on the workspace's data
version (DVC hash), whoever ran it, and says whose run won.

1. ranks the sweep's FINISHED children (:func:`aumesh.experiments.ranking.choose`: by default the highest mean CV R²,
   ``r2_displacement_mean`` when targets differ; ``--metric`` and ``--target`` as described there); a sweep that did
   not finish is refused unless ``--partial`` (:func:`check_finished`), and a newer pipeline run on another
   configuration is not overruled (:func:`check_not_overruled`);
2. writes the winner's configuration to ``conf/experiment/promoted.yaml``, checked first to compose to the run's
   (:mod:`aumesh.experiments.promoted_config`);
3. registers the run's MLflow pyfunc model (artifact ``model/``: the release-format NPZ with a
   signature, :mod:`aumesh.tracking.pyfunc`) as a new version of the
   registered model (default ``aumesh-au-to-mesh``) and points the alias ``champion`` at it;
4. recomposes ``params.yaml`` and writes ``promotion.json`` (``{"promoted": {...}}``, read by the
   release stage into ``model_card.json["promotion"]`` and the card's "Promotion" section).

Steps 3 and 4 are one transaction (:mod:`aumesh.experiments.promotion_journal`): a journal written first lists the
old and new state of the alias and every file; killed half-way, the next ``aumesh promote``, ``aumesh runs`` or
evaluate/release stage completes or rolls it back and says which in one line.

Then ``dvc repro`` rebuilds exactly that release (evaluate and release re-run on the new params).

``aumesh promote --family <family> [RUN]`` (issue 46) promotes one input family's model on its own, the same way: the
best run of that family only (a sweep's, ``--across`` the team's, or the run named; a run of another family is
refused in one line), ranked within the family (:func:`aumesh.experiments.ranking.choose`); it writes
``families.<family>: {features: <the run's features.name>, n_components: <its effective components>}`` into
``conf/experiment/promoted.yaml``, registers the run's model as a version of ``aumesh-<family>`` (alias
``champion``) and writes its record to ``promotion.json["families"][<family>]``, which ``release_family@<family>``
records in the family's card. The run's other settings (target, neutral, scaling, ...) are the AU model's in the
pipeline (the evaluate stage fits every family in one pass on one preparation), so a run fitted with others is
refused (:func:`check_shared`). The AU promotion and the other families' are left as they are; the AU promotion
(without ``--family``, or ``--family au``) ranks only AU runs and keeps the families' promotions likewise.
"""

from __future__ import annotations

from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aumesh.core.errors import UserError
from aumesh.core.io import json_text
from aumesh.experiments import promotion_journal
from aumesh.experiments.promoted_config import (
    EXPERIMENT_GROUP,
    EXPERIMENT_NAME,
    FAMILY_OWN_KEYS,
    _param_string,
    check_defaults_entry,
    compose_with,
    experiment_yaml,
    hydra_override,
    promoted_values,
    read_experiment,
    verify_composition,
)
from aumesh.experiments.ranking import candidates_from_frame, choose

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd

DEFAULT_MODEL_NAME = "aumesh-au-to-mesh"
#: a family's registered model (``aumesh-blendshapes``, ``aumesh-emotions``): one version a promoted run, as the AU one
FAMILY_MODEL_NAME = "aumesh-{family}"
CHAMPION_ALIAS = "champion"
MODEL_ARTIFACT_DIR = "model"


class OverruleError(UserError, ValueError):
    """Promotion refused: a newer pipeline run evaluated another configuration than the sweep's best."""


class PromotionError(UserError, ValueError):
    """Promotion refused: an unfinished sweep, or a best run whose model artifacts are gone or outside the workspace."""


class FamilyError(UserError, ValueError):
    """Promotion refused: the run named is of another input family, or was fitted with other shared settings than
    the pipeline fits the families with."""


def check_family(candidate: Any, family: str) -> None:
    """Refuse (one line) promoting *candidate* (:class:`aumesh.experiments.ranking.Candidate`) as a *family* model
    when it is a run of another input family."""
    if candidate.input_family != family:
        name = candidate.params.get("features.name", "?")
        flag = "" if candidate.input_family == "au" else f" --family {candidate.input_family}"
        raise FamilyError(
            f"run {candidate.run_id} is a {candidate.input_family} run (features.name={name}), not a {family} run: "
            f"its R² answers another question. Fix: `aumesh promote{flag} {candidate.run_id}`, or name a {family} run."
        )


def check_shared(run_params: Mapping[str, str], workspace: Mapping[str, Any], family: str, run_id: str) -> None:
    """A family's run must share the settings the pipeline fits every family with (all but its own
    :data:`aumesh.experiments.promoted_config.FAMILY_OWN_KEYS`): the evaluate stage fits the families in the AU
    model's one pass, on one preparation (target, neutral, scaling, CV), so a run fitted otherwise would not be
    rebuilt by ``dvc repro``.

    Parameters
    ----------
    run_params : Mapping
        The run's params as logged.
    workspace : Mapping
        ``conf/`` composed as ``dvc repro`` builds it now (with the promoted experiment).
    family, run_id : str

    Raises
    ------
    FamilyError
        Naming every differing key, both values and the fix.
    ValueError
        The run used other data, or has keys ``conf/`` no longer has (:func:`promoted_values`).
    """
    from aumesh.config import flatten

    flat = flatten(workspace)
    differ = [
        f"{key}={_param_string(value)} (workspace: {_param_string(flat[key])})"
        for key, value in promoted_values(run_params, workspace).items()
        if key not in FAMILY_OWN_KEYS and _param_string(value) != _param_string(flat[key])
    ]
    if differ:
        raise FamilyError(
            f"run {run_id} was fitted with {', '.join(differ)}: the pipeline fits the {family} model with the AU "
            "model's settings, so `dvc repro` would not rebuild it. Fix: sweep the family with the workspace's "
            "settings (or --target to restrict), or promote the AU configuration first."
        )


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
        The dotted keys and values promotion would write (:func:`aumesh.experiments.promoted_config.promoted_values`).
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
    family: str | None = None,
    run_id: str | None = None,
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
        See :func:`aumesh.experiments.ranking.choose`.
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
    family : str, optional
        Promote this input family's model (``blendshapes``, ``emotions``: only its runs compete, into
        ``families.<family>``); None or ``"au"``: the AU model, as ever (only AU runs compete).
    run_id : str, optional
        Promote this run (it must be FINISHED and of *family*) instead of ranking a sweep's.

    Returns
    -------
    dict
        The record written to the promotion file (``promoted``, or ``families.<family>``; with ``user`` and
        ``workspace``: whose run won).
    """
    from filelock import Timeout

    root = Path(root).resolve()
    try:
        with promotion_journal.lock(root):  # one promotion of a workspace at a time
            promotion_journal.recover_locked(root, say)  # an earlier one killed half-way: completed or rolled back
            return _promote_locked(
                parent_run_id,
                root,
                tracking_cfg,
                metric,
                target,
                model_name,
                register,
                alias,
                newer_run,
                across,
                partial,
                skip_missing,
                say,
                family=None if family in (None, "au") else family,
                run_id=run_id,
            )
    except Timeout:
        raise promotion_journal.busy(root) from None


def _promote_locked(
    parent_run_id: str | None,
    root: Path,
    tracking_cfg: Mapping[str, Any] | None,
    metric: str | None,
    target: str | None,
    model_name: str | None,
    register: bool,
    alias: str,
    newer_run: Mapping[str, Any] | None,
    across: bool,
    partial: bool,
    skip_missing: bool,
    say,
    family: str | None = None,
    run_id: str | None = None,
) -> dict[str, Any]:
    from aumesh.config import from_dict, params_text
    from aumesh.tracking import queries, registry
    from aumesh.tracking import runs as tracking

    conf_dir = root / "conf"
    check_defaults_entry(conf_dir)
    partial_note = None
    fam = family or "au"
    if run_id is not None:
        candidates = candidates_from_frame(queries.runs_frame([run_id], tracking_cfg))
        check_family(candidates[0], fam)
        scope = f"named ({run_id})"
    elif across:
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
    choice = choose(candidates, metric=metric, target=target, scope=scope, family=fam)
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
            choice = choose(rest, metric=metric, target=target, scope=scope, family=fam)
        except ValueError as err:
            raise PromotionError(
                f"no run {scope} with its model artifacts left ({len(skipped)} skipped): {err}"
            ) from err
    if skipped:
        say(f"promoting run {choice.run_id} ({choice.metric} = {choice.value:.6f}), the best run whose artifacts exist")
    winner = next(c for c in candidates if c.run_id == choice.run_id)
    sweep_id = winner.parent_run_id if across or run_id is not None else parent_run_id

    exp_path = conf_dir / EXPERIMENT_GROUP / f"{EXPERIMENT_NAME}.yaml"
    # promoted.yaml holds the AU promotion and each family's: this promotion rewrites its own part only
    au_values, au_lines, families, family_lines = read_experiment(exp_path)
    origin = f"run {winner.run_id} of sweep {sweep_id}" if sweep_id else f"evaluate run {winner.run_id}"
    origin += f" (by {winner.user}, across the team's runs)" if across else ""
    if family is None:
        base = compose_with(conf_dir, None)
        values = promoted_values(winner.params, base)
        if newer_run is not None:
            check_not_overruled(values, str(sweep_id), newer_run)
        overrides = [hydra_override(k, v) for k, v in values.items()]
        text = experiment_yaml(
            values, [origin, f"criterion: {choice.metric} = {choice.value:.6f}"], families, family_lines
        )
        composed = compose_with(conf_dir, text)
        verify_composition(composed, winner.params)
        extra: dict[str, Any] = {}
    else:
        workspace = compose_with(conf_dir, exp_path.read_text() if exp_path.exists() else None)
        check_shared(winner.params, workspace, family, winner.run_id)
        spec_values = {"features": winner.params["features.name"], "n_components": winner.n_components}
        if newer_run is not None:
            check_not_overruled({"features.name": spec_values["features"]}, str(sweep_id), newer_run)
        overrides = [hydra_override(f"families.{family}.{k}", v) for k, v in spec_values.items()]
        text = experiment_yaml(
            au_values,
            au_lines,
            {**families, family: spec_values},
            {**family_lines, family: f"{origin}; criterion: {choice.metric} = {choice.value:.6f}"},
        )
        composed = compose_with(conf_dir, text)
        _verify_family(composed, workspace, family, spec_values)
        extra = {"family": family, **spec_values}
    cfg = from_dict(composed)

    name = model_name or (DEFAULT_MODEL_NAME if family is None else FAMILY_MODEL_NAME.format(family=family))
    record: dict[str, Any] = {
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
        # filled in when registered (promotion_journal.with_version); promotion.json is committed: locations
        # relative to the workspace, never its absolute path, and never a tracking server's address (the run id finds
        # the run on the team's server)
        "registered_model": None,
        "model_version": None,
        "alias": None,
        "model_source": None,
        "tracking_uri": tracking.store_label(tracking_cfg),
        "promoted_at": datetime.now(UTC).isoformat(timespec="seconds"),
        **extra,
    }
    if skipped:
        record["skipped_missing_artifacts"] = skipped
    if partial_note:
        record["partial"] = partial_note
    spec = None
    if register:
        spec = {
            "name": name,
            "alias": alias,
            "run_id": winner.run_id,
            "previous_version": (registry.model_version_by_alias(name, alias, tracking_cfg) or {}).get("version"),
            "tags": {
                "aumesh.parent_run_id": str(sweep_id),
                "aumesh.metric": choice.metric,
                "aumesh.value": f"{choice.value:.6f}",
                "aumesh.config_overrides": " ".join(overrides),
                "aumesh.user": str(winner.user),
                **({"aumesh.family": family} if family else {}),
            },
            "description": f"aumesh promote: {choice.criterion}",
        }
    promotion_file = str(cfg.paths.promotion_file)
    # one transaction (aumesh.experiments.promotion_journal): the registry, then the files in this order
    journal = promotion_journal.new_journal(
        root,
        {
            str(exp_path.relative_to(root)): text,
            "params.yaml": params_text(composed),
            promotion_file: None
            if register
            else json_text(
                promotion_journal.promotion_document(
                    promotion_journal.read_promotion(root / promotion_file), record, family
                )
            ),
        },
        record,
        promotion_file,
        spec,
        tracking_cfg,
        family=family,
    )
    return promotion_journal.run(root, journal)


_model_source = promotion_journal.model_source  # kept for callers of the old name


def _verify_family(
    composed: Mapping[str, Any], workspace: Mapping[str, Any], family: str, spec: Mapping[str, Any]
) -> None:
    """The new conf/ composes to the family's promoted design and components, and to everything else as before (the
    AU model and the other families untouched).

    Raises
    ------
    ValueError
        Naming every key that differs.
    """
    from aumesh.config import flatten

    new, old = flatten(composed), flatten(workspace)
    own = {f"families.{family}.{k}": v for k, v in spec.items()}
    wrong = [f"{k}: promoted {v!r}, composed {new.get(k)!r}" for k, v in own.items() if new.get(k) != v]
    wrong += [
        f"{k}: was {old.get(k)!r}, composed {new.get(k)!r}"
        for k in sorted(set(new) | set(old))
        if k not in own and new.get(k) != old.get(k)
    ]
    if wrong:
        raise ValueError(f"the promoted conf/ does not compose to the {family} promotion: " + "; ".join(wrong))


def _workspace_data_md5(root: Path) -> str:
    from aumesh.core import provenance

    try:
        md5 = provenance.data_digest(root).get("md5")
    except (FileNotFoundError, ValueError) as err:
        raise UserError(f"--across ranks the runs on this workspace's data: {err}") from None
    if not md5:
        raise UserError(f"{root / 'data.dvc'}: no md5; `dvc add data` first (--across ranks the runs on this data).")
    return str(md5)
