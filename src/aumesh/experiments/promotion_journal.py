"""A promotion is one transaction: a journal written before its first effect, completed or rolled back by the next
command that touches promotion.

``aumesh promote`` changes four things, in this order: the model registry (a new version, the alias ``champion`` moved
to it), ``conf/experiment/promoted.yaml``, ``params.yaml`` and ``promotion.json``. Killed between two of them, each was
valid but not together (issue 44: the alias and the experiment file new, ``params.yaml`` and ``promotion.json`` old),
and nothing said so. Now, before the first effect, it writes the journal :data:`JOURNAL` in the workspace atomically:
every file's old text (None: absent) and new text, the alias's previous version, and the version to create, known once
created (its tag :data:`TAG` is the journal's id, so it is found even when the kill came before the journal recorded
it). The steps run in order; deleting the journal is the commit. The whole promotion holds the lock :data:`LOCK`
(``filelock``: released by the kernel when its process dies), so a live promotion's journal is never taken for an
interrupted one.

The next ``aumesh promote``, ``aumesh runs`` and the ``evaluate`` and ``release`` stages (the commands that read what
promotion writes: the runs, ``params.yaml``, ``promotion.json``) find a journal whose lock is free and:

* roll it forward when the whole new state is known (no registry step, or the new version exists): the alias points at
  the new version, every file gets its new text;
* else roll it back: the alias goes back to its previous version (or is removed), every file gets its old text;

and say which in one line (:func:`recover`). A stage that finds ``params.yaml`` or ``promotion.json`` changed by that
stops (exit 2): DVC chose what to run from the old files; ``dvc repro`` again builds the promoted release. A promotion
that fails with an error or Ctrl-C rolls back at once, the same way (:func:`run`).
"""

from __future__ import annotations

import json
import os
import socket
import uuid
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from aumesh.core.errors import CorruptFileError, UserError
from aumesh.core.io import atomic_write_json, atomic_write_text, json_text

JOURNAL = ".aumesh-promotion.journal.json"
LOCK = ".aumesh-promotion.lock"
#: the model version tag naming the promotion (the journal's id) that registered it
TAG = "aumesh.promotion"
MODEL_ARTIFACT_DIR = "model"


class PromotionBusy(UserError):
    """Another ``aumesh promote`` of this workspace is running (it holds :data:`LOCK`)."""


def lock(root: Path, timeout: float = 0):
    """The workspace's promotion lock (``filelock``; ``timeout`` 0: fail at once, -1: wait)."""
    from filelock import FileLock

    return FileLock(str(Path(root) / LOCK), timeout=timeout)


def busy(root: Path) -> PromotionBusy:
    return PromotionBusy(
        f"{Path(root) / LOCK}: another `aumesh promote` of this workspace is running (it holds this lock). "
        "Fix: wait until it has finished, then run this again."
    )


def _read(path: Path) -> str | None:
    return path.read_text() if path.exists() else None


def read_promotion(path: Path) -> dict[str, Any]:
    """``promotion.json`` as it stands (``{}`` when absent): ``{"promoted": <the AU promotion's record or null>,
    "families": {<family>: <its record>}}`` (``families`` once a family was promoted).

    Raises
    ------
    CorruptFileError
        Not a JSON object (the fix is in the message).
    """
    path = Path(path)
    if not path.exists():
        return {}
    try:
        doc = json.loads(path.read_text())
    except ValueError as err:
        doc = err
    if not isinstance(doc, dict):
        raise CorruptFileError(
            f'{path}: not a JSON object ({doc}). Fix: `git checkout {path.name}` (or write {{"promoted": null}} to '
            "it), then promote again."
        )
    return doc


def promotion_document(current: Mapping[str, Any], record: Mapping[str, Any], family: str | None) -> dict[str, Any]:
    """``promotion.json``'s new content: *current* with *record* in its place, the rest as it was: the AU
    promotion's (*family* None) under ``promoted``, a family's under ``families.<family>`` (promoting one never
    touches the others'). With nothing else in *current* the AU promotion's is ``{"promoted": record}``."""
    doc = {"promoted": current.get("promoted"), **{k: v for k, v in current.items() if k != "promoted"}}
    if family is None:
        doc["promoted"] = dict(record)
    else:
        doc["families"] = {**(doc.get("families") or {}), family: dict(record)}
    return doc


def new_journal(
    root: Path,
    files: Mapping[str, str | None],
    record: dict[str, Any],
    promotion_file: str,
    registry: dict[str, Any] | None,
    tracking_cfg: Mapping[str, Any] | None,
    family: str | None = None,
) -> dict[str, Any]:
    """The journal of a promotion about to start: ``files`` (workspace-relative path -> new text, in the order they
    are written; ``promotion_file``'s new text is None until the version is known when ``registry`` is given),
    ``record`` (``promotion.json``'s record, without the version when ``registry``), ``registry`` (``name``,
    ``alias``, ``run_id``, ``tags``, ``description``, ``previous_version``) or None; ``family``: the input family
    promoted (None: the AU model), whose place in ``promotion.json`` the record takes (:func:`promotion_document`,
    on the file as it is now: ``promotion_current``)."""
    return {
        "id": uuid.uuid4().hex,
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "started_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "run_id": record["run_id"],
        "files": {rel: {"old": _read(Path(root) / rel), "new": text} for rel, text in files.items()},
        "promotion_file": promotion_file,
        "record": record,
        "registry": None if registry is None else {**registry, "version": None, "source": None},
        "tracking": dict(tracking_cfg or {}),
        "family": family,
        "promotion_current": read_promotion(Path(root) / promotion_file),
    }


def with_version(record: Mapping[str, Any], version: Mapping[str, Any], root: Path) -> dict[str, Any]:
    """``promotion.json``'s record with the registered version (name, number, alias, repo-relative source)."""
    return {
        **record,
        "registered_model": version["name"],
        "model_version": version["version"],
        "alias": version.get("alias"),
        "model_source": model_source(version["source"], str(record["run_id"]), root),
    }


def model_source(source: str, run_id: str, root: Path) -> str:
    """The registered model's source as promotion.json holds it: repo-relative inside the workspace, a server's
    ``mlflow-artifacts:/`` URI as it is; a path elsewhere (another machine's) as ``runs:/<run id>/model``."""
    from aumesh.core import provenance

    shared = provenance.shareable_location(source, [root]) or source
    if shared.startswith("file:") or Path(shared).is_absolute():
        return f"runs:/{run_id}/{MODEL_ARTIFACT_DIR}"
    return shared


def _known_version(journal: dict[str, Any], root: Path) -> bool:
    """Record in the journal the version this promotion registered, when it exists; False when it does not."""
    from aumesh.tracking import registry

    reg = journal["registry"]
    if reg["version"] is not None:
        return True
    found = registry.find_version(reg["name"], reg["run_id"], TAG, journal["id"], journal["tracking"])
    if found is None:
        return False
    _record_version(journal, {**found, "alias": reg["alias"]}, root)
    return True


def _record_version(journal: dict[str, Any], version: Mapping[str, Any], root: Path) -> None:
    journal["registry"]["version"], journal["registry"]["source"] = version["version"], version["source"]
    journal["record"] = with_version(journal["record"], version, root)
    # journals written before the families have neither key: {"promoted": record}, as then
    current = journal.get("promotion_current") or {}
    journal["files"][journal["promotion_file"]]["new"] = json_text(
        promotion_document(current, journal["record"], journal.get("family"))
    )


def _write_file(root: Path, rel: str, text: str | None) -> None:
    path = root / rel
    if _read(path) == text:  # already so (a step done before the kill, or a write that never happened)
        return
    if text is None:
        path.unlink(missing_ok=True)
    else:
        atomic_write_text(path, text)


def _forward(root: Path, journal: dict[str, Any]) -> None:
    """Every step of the journal from where it stands, the journal's deletion last (idempotent)."""
    from aumesh.tracking import registry

    reg = journal["registry"]
    if reg is not None:
        if reg["version"] is None:
            version = registry.register_model_version(
                reg["run_id"],
                MODEL_ARTIFACT_DIR,
                reg["name"],
                journal["tracking"],
                alias=reg["alias"],
                tags={**reg["tags"], TAG: journal["id"]},
                description=reg["description"],
            )
            _record_version(journal, version, root)
            atomic_write_json(root / JOURNAL, journal)  # from here on, a kill rolls forward
        else:
            registry.set_alias(reg["name"], reg["alias"], reg["version"], journal["tracking"])
    for rel, change in journal["files"].items():
        _write_file(root, rel, change["new"])
    (root / JOURNAL).unlink(missing_ok=True)


def _back(root: Path, journal: dict[str, Any]) -> None:
    from aumesh.tracking import registry

    reg = journal["registry"]
    if reg is not None:
        registry.set_alias(reg["name"], reg["alias"], reg["previous_version"], journal["tracking"])
    for rel, change in reversed(journal["files"].items()):
        _write_file(root, rel, change["old"])
    (root / JOURNAL).unlink(missing_ok=True)


def run(root: Path, journal: dict[str, Any]) -> dict[str, Any]:
    """Carry out a promotion (the caller holds :func:`lock`): the journal first, then each step; an error or Ctrl-C
    on the way rolls it back (the alias to its previous version, the files to their old text; a version registered
    stays, without the alias) and is raised. If the rollback fails too, the journal stays for the next command.
    Returns ``promotion.json``'s record."""
    root = Path(root)
    atomic_write_json(root / JOURNAL, journal)
    try:
        _forward(root, journal)
    except BaseException:
        _back(root, journal)
        raise
    return journal["record"]


def load(root: Path) -> dict[str, Any] | None:
    path = Path(root) / JOURNAL
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except (ValueError, OSError) as err:
        raise CorruptFileError(
            f"{path}: not a readable promotion journal ({err}). Fix: check conf/experiment/promoted.yaml, "
            "params.yaml and promotion.json by hand (or `git checkout` them), then delete it."
        ) from None


def recover_locked(root: Path, say: Callable[[str], Any] = print) -> tuple[str | None, list[str]]:
    """:func:`recover` for a caller that holds :func:`lock`."""
    root = Path(root)
    journal = load(root)
    if journal is None:
        return None, []
    before = {rel: _read(root / rel) for rel in journal["files"]}
    reg = journal["registry"]
    started = f"run {journal['run_id']}, started {journal['started_at']} by pid {journal['pid']}"
    if reg is None or _known_version(journal, root):
        _forward(root, journal)
        changed = [rel for rel in journal["files"] if _read(root / rel) != before[rel]]
        alias = f"alias {reg['alias']} -> version {reg['version']} of {reg['name']}, " if reg else ""
        line = (
            f"completed the interrupted promotion ({started}; journal {JOURNAL}): {alias}"
            f"{'wrote ' + ', '.join(changed) if changed else 'every file was already written'}"
        )
    else:
        _back(root, journal)
        changed = [rel for rel in journal["files"] if _read(root / rel) != before[rel]]
        previous = reg["previous_version"]
        line = (
            f"rolled back the interrupted promotion ({started}; journal {JOURNAL}): it was killed before its model "
            f"version was registered; alias {reg['alias']} -> {'version ' + previous if previous else 'none'}, "
            f"{'restored ' + ', '.join(changed) if changed else 'no file had been written'}. `aumesh promote` again "
            "promotes it"
        )
    say(f"aumesh: {line}")
    return line, changed


def recover(root: Path, say: Callable[[str], Any] = print) -> tuple[str | None, list[str]]:
    """Complete or roll back an interrupted promotion of workspace ``root`` (see the module docstring).

    Returns
    -------
    (str or None, list of str)
        The one line said (None: no journal), and the workspace-relative files the recovery changed.

    Raises
    ------
    PromotionBusy
        A promotion of this workspace is running (its journal is not an interrupted one).
    """
    from filelock import Timeout

    root = Path(root)
    if not (root / JOURNAL).exists():
        return None, []
    try:
        with lock(root):
            return recover_locked(root, say)
    except Timeout:
        raise busy(root) from None
