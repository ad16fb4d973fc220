"""In-process sweeps with Hydra's syntax, logged to MLflow as one parent run and one child per configuration.

``aumesh sweep -m preprocess.target=absolute,neutral,within features=au,au_pose,au_pose_interactions \\
model.n_components=10,23,40,83`` runs :func:`main`: a Hydra app
on the repo's ``conf/`` (the same configuration ``dvc exp run`` composes into ``params.yaml``)
whose task function evaluates one configuration on the prepared data. Not a DVC stage: a sweep
is exploration; ``aumesh promote`` turns its best run into ``conf/`` so ``dvc repro`` rebuilds it.

The sweep is three modules: this one (the Hydra app, its MLflow callback, the launch and the end of a sweep),
:mod:`aumesh.experiments.sweep_child` (one configuration as a child run) and :mod:`aumesh.experiments.sweep_cache`
(which prepared data serve a configuration; the per-process reuse of data, statistics and fits between
configurations).

MLflow layout. A Hydra callback (:class:`SweepCallback`, configured in ``conf/hydra/default.yaml``)
opens the parent run when the (multi)run starts and writes its id to ``<sweep dir>/mlflow_parent.json``,
where every job (in this process, a joblib worker or a cluster node) finds it. Each job's task function
(:func:`aumesh.experiments.sweep_child.run_configuration`) opens a child run recorded as every evaluation run is
(:mod:`aumesh.pipeline.run_record`: params, provenance tags, per-fold metrics and their means, the
R²-vs-n_components curve and figure, the model as an MLflow pyfunc model under ``model/``: what ``aumesh promote``
registers). A configuration that raises (e.g. a data or config error) is recorded as a FAILED child with the error
and the sweep goes on. When the sweep ends the parent is FINISHED with tags counting its children.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, cast

from aumesh.core.io import atomic_write_json

log = logging.getLogger(__name__)

PARENT_FILE = "mlflow_parent.json"
RESULT_FILE = "result.json"
SWEEPS_DIR = "build/sweeps"
PARENT_ENV = "AUMESH_SWEEP_PARENT_RUN_ID"


def read_feature_sets(directory: str | Path) -> list[str]:
    """The ``features`` options the sweep in ``directory`` runs (its parent file's ``feature_sets``; [] when not
    recorded): every job accumulates the union of their designs in its one statistics pass."""
    path = Path(directory) / PARENT_FILE
    if not path.exists():
        return []
    return [str(name) for name in json.loads(path.read_text()).get("feature_sets") or []]


def swept_feature_sets(overrides: Sequence[str]) -> list[str]:
    """The ``features`` options named by a sweep's ``overrides`` (``features=a,b,c``, ``features=choice(a,b)`` or one
    value), in order; [] when the sweep does not set ``features``."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    out: list[str] = []
    for override in OverridesParser.create().parse_overrides([o for o in overrides if "=" in o]):
        if override.get_key_element().lstrip("+~") != "features":
            continue
        values = (
            list(override.sweep_string_iterator())
            if override.is_sweep_override()
            else [override.get_value_element_as_str()]
        )
        out += [str(v) for v in values if str(v) not in out]
    return out


def read_parent(directory: str | Path) -> str | None:
    """The parent run id the callback wrote into a sweep (or run) directory, else ``$AUMESH_SWEEP_PARENT_RUN_ID``."""
    path = Path(directory) / PARENT_FILE
    if path.exists():
        return json.loads(path.read_text()).get("run_id")
    return os.environ.get(PARENT_ENV) or None


def _plain_config(config) -> dict[str, Any]:
    """A composed Hydra config without its ``hydra`` node, interpolations resolved."""
    from omegaconf import OmegaConf

    data = OmegaConf.to_container(config, resolve=False)
    assert isinstance(data, dict), type(data)  # a composed config is a DictConfig
    data.pop("hydra", None)
    return cast(dict[str, Any], OmegaConf.to_container(OmegaConf.create(data), resolve=True))


class SweepCallback:
    """Hydra callback: one MLflow parent run per sweep (``hydra.callbacks.aumesh_mlflow`` in conf/hydra/).

    Implements Hydra's callback protocol (``hydra.experimental.callback.Callback``) without
    importing Hydra at module import. Hydra turns callback exceptions into warnings; a job that
    finds no parent file warns and logs its run without a parent. The parent's params are the
    sweep's base configuration; the swept values are in its ``aumesh.sweep.overrides`` tag.
    """

    def __init__(self, **_: Any) -> None:
        self._t0: float | None = None
        self._progress = None  # a tqdm bar over the jobs this process launches (quiet when not on a terminal)

    # -- Hydra hooks
    def on_run_start(self, config, **kwargs: Any) -> None:
        self._start(config, Path(str(config.hydra.run.dir)), list(config.hydra.overrides.task), "run")

    def on_run_end(self, config, **kwargs: Any) -> None:
        self._end(config, Path(str(config.hydra.run.dir)))

    def on_multirun_start(self, config, **kwargs: Any) -> None:
        from aumesh.core import progress

        overrides = list(config.hydra.overrides.task)
        self._start(config, Path(str(config.hydra.sweep.dir)), overrides, "multirun")
        self._progress = progress.bar(count_jobs(overrides), "sweep", unit="config")

    def on_multirun_end(self, config, **kwargs: Any) -> None:
        if self._progress is not None:
            self._progress.close()
            self._progress = None
        self._end(config, Path(str(config.hydra.sweep.dir)))

    def on_job_start(self, config, **kwargs: Any) -> None:
        pass

    def on_job_end(self, config, job_return=None, **kwargs: Any) -> None:
        # jobs run in this process (basic launcher) advance the bar; a joblib or cluster
        # worker has its own callback instance and no bar
        if self._progress is not None:
            self._progress.update(1)

    # -- implementation
    def _start(self, config, directory: Path, overrides: list[str], mode: str) -> None:
        from aumesh.config import recorded_overrides
        from aumesh.tracking import runs as tracking

        self._t0 = time.perf_counter()
        plain = _plain_config(config)
        tracking_cfg = dict(plain.get("tracking") or {})
        launcher = str(config.hydra.launcher.get("_target_", "")) if "launcher" in config.hydra else ""
        parent = tracking.start_parent_run(
            tracking_cfg,
            run_name=f"sweep {directory.name}",
            params=plain,
            tags={
                "aumesh.sweep.dir": str(directory.resolve()),
                "aumesh.sweep.overrides": " ".join(recorded_overrides(overrides)),
                "aumesh.sweep.mode": mode,
                "aumesh.sweep.launcher": launcher,
                "aumesh.sweep.n_expected": count_jobs(overrides) if mode == "multirun" else 1,
            },
        )
        directory.mkdir(parents=True, exist_ok=True)
        atomic_write_json(
            directory / PARENT_FILE,
            {
                "run_id": parent,
                "tracking_uri": tracking.tracking_uri(tracking_cfg) if parent else None,
                "overrides": recorded_overrides(overrides),
                # the designs every job's one statistics pass accumulates (the union: sweep_cache.statistics_for)
                "feature_sets": list(
                    dict.fromkeys([str((plain.get("features") or {}).get("name")), *swept_feature_sets(overrides)])
                ),
            },
        )
        if parent:
            os.environ[PARENT_ENV] = parent
            log.info("sweep parent run %s (%s)", parent, directory)

    def _end(self, config, directory: Path) -> None:
        from aumesh.tracking import runs as tracking

        parent = read_parent(directory)
        os.environ.pop(PARENT_ENV, None)
        if not parent:
            return
        tracking_cfg = dict(_plain_config(config).get("tracking") or {})
        wall = time.perf_counter() - self._t0 if self._t0 else None
        children, tags = tracking.finish_sweep(parent, tracking_cfg, wall)
        if children is None:
            return
        print(
            f"\nsweep parent {parent}: {tags['aumesh.sweep.n_children']} configurations, "
            f"{tags['aumesh.sweep.n_failed']} not finished" + (f", {wall:.1f} s" if wall is not None else "")
        )
        if len(children):
            from aumesh.experiments.leaderboard import format_runs_table, runs_table

            print(format_runs_table(runs_table(children)))
        print(f"(`aumesh runs --sweep {parent}`; `aumesh promote --sweep {parent}`)")


def count_jobs(overrides: Sequence[str]) -> int:
    """Number of configurations Hydra's basic sweeper makes of ``overrides`` (the product of the sweeps)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    total = 1
    for override in OverridesParser.create().parse_overrides(list(overrides)):
        if override.is_sweep_override():
            total *= len(list(override.sweep_string_iterator()))
    return total


def _task(config) -> dict[str, Any]:
    """Hydra task function: one configuration."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from aumesh.config import recorded_overrides
    from aumesh.experiments.sweep_child import run_configuration

    hc = HydraConfig.get()
    multirun = hc.mode == RunMode.MULTIRUN
    parent = read_parent(hc.sweep.dir if multirun else hc.run.dir)
    # what the child records (its name, tag): compute.address=... or tracking.* given on the command line are not
    overrides = recorded_overrides(list(hc.overrides.task))
    if parent is None:
        log.warning(
            "no sweep parent run found in %s: is the aumesh SweepCallback configured "
            "(conf/hydra/default.yaml)? Logging this configuration without a parent.",
            hc.sweep.dir if multirun else hc.run.dir,
        )
    feature_sets = read_feature_sets(hc.sweep.dir if multirun else hc.run.dir)
    result = run_configuration(_plain_config(config), overrides, parent, feature_sets=feature_sets)
    atomic_write_json(Path(hc.runtime.output_dir) / RESULT_FILE, result)
    return result


def conf_dir(root: Path | None = None) -> Path:
    """The repo's ``conf/`` (absolute)."""
    from aumesh.core import provenance

    path = (root or provenance.repo_root()) / "conf"
    if not (path / "config.yaml").exists():
        raise FileNotFoundError(f"{path}/config.yaml not found: run `aumesh sweep` inside the aumesh checkout.")
    return path.resolve()


def sweep_overrides(argv: Sequence[str], stamp: str | None = None) -> list[str]:
    """The user's Hydra arguments plus literal ``hydra.sweep.dir``/``hydra.run.dir`` under build/sweeps/.

    A literal directory (not ``${now:...}``) is the same in every process of the sweep, so jobs
    in joblib workers or on cluster nodes find the parent file. User-given values win.
    """
    from aumesh.config import check_overrides

    args = list(argv)
    check_overrides([a for a in args if "=" in a])
    stamp = stamp or datetime.now().strftime("%Y-%m-%d_%H-%M-%S_%f")
    if not any(a.lstrip("+").startswith("hydra.sweep.dir=") for a in args):
        args.append(f"hydra.sweep.dir={SWEEPS_DIR}/{stamp}")
    if not any(a.lstrip("+").startswith("hydra.run.dir=") for a in args):
        args.append(f"hydra.run.dir={SWEEPS_DIR}/{stamp}")
    return args


@dataclass(frozen=True)
class SweepOutcome:
    """What a sweep ran: its folder, parent run, and how many configurations did not finish."""

    directory: Path
    parent_run_id: str | None
    n_jobs: int
    n_failed: int


def outcome(directory: Path, expected_jobs: int) -> SweepOutcome:
    """Count the jobs' ``result.json`` under a sweep folder; a job without one (it died) counts as failed.

    Before any job started (Hydra's ``--help``, ``--cfg``) there is no parent file and nothing counts.
    """
    if not (directory / PARENT_FILE).is_file():
        return SweepOutcome(directory, None, 0, 0)
    results = [json.loads(p.read_text()) for p in sorted(directory.rglob(RESULT_FILE))]
    failed = sum(1 for r in results if r.get("status") != "FINISHED") + max(0, expected_jobs - len(results))
    return SweepOutcome(directory, read_parent(directory), max(expected_jobs, len(results)), failed)


def _hydra_value(args: Sequence[str], key: str) -> str | None:
    return next((a.split("=", 1)[1] for a in args if a.lstrip("+").startswith(f"{key}=")), None)


def run_sweep(argv: Sequence[str]) -> SweepOutcome:
    """``aumesh sweep [-m] key=v1,v2 ...``: run the Hydra app on the repo's conf/ from the repo root.

    The working directory becomes the workspace root (``conf/paths`` are relative to it). A configuration
    that fails is a FAILED child and the sweep goes on; the returned :class:`SweepOutcome` counts them.
    """
    import hydra

    from aumesh.core import provenance

    root = provenance.repo_root()
    conf = conf_dir(root)
    if Path.cwd().resolve() != root.resolve():
        log.info("running from the workspace root %s (conf/paths are relative to it)", root)
        os.chdir(root)
    args = sweep_overrides(argv)
    multirun = "-m" in args or "--multirun" in args
    directory = Path(_hydra_value(args, "hydra.sweep.dir" if multirun else "hydra.run.dir") or ".")
    expected = count_jobs([a for a in args if "=" in a and not a.startswith("-")]) if multirun else 1
    app = hydra.main(config_path=str(conf), config_name="config", version_base=None)(_task)
    saved = sys.argv
    sys.argv = ["aumesh-sweep", *args]
    try:
        app()
    except KeyboardInterrupt as err:  # Ctrl-C or SIGTERM: the running child is KILLED (tracked_run); now the parent
        raise interrupted(directory, expected, err) from err
    finally:
        sys.argv = saved
        from hydra.core.global_hydra import GlobalHydra

        GlobalHydra.instance().clear()  # so config.compose() works again in this process
    return outcome(directory, expected)


def interrupted(directory: Path, expected: int, err: KeyboardInterrupt) -> KeyboardInterrupt:
    """Mark an interrupted sweep's parent, and any child still RUNNING, KILLED (tag ``aumesh.sweep.interrupted``:
    ``aumesh promote`` refuses the sweep without ``--partial``); return the one-line
    :class:`aumesh.core.signals.Interrupted` to raise."""
    import signal

    from aumesh.core.signals import Interrupted, Terminated
    from aumesh.tracking import queries
    from aumesh.tracking import runs as tracking

    signum = signal.SIGTERM if isinstance(err, Terminated) else signal.SIGINT
    how = f"stopped: {err}" if isinstance(err, Terminated) else "Ctrl-C"
    parent = read_parent(directory) if (directory / PARENT_FILE).is_file() else None
    os.environ.pop(PARENT_ENV, None)
    if parent is None:
        return Interrupted(f"interrupted ({how}) before the sweep started; nothing was logged", signum)
    tracking_cfg: dict[str, Any] = {}
    with contextlib.suppress(Exception):
        from aumesh.config import load_params

        tracking_cfg = dict(load_params("params.yaml").tracking.__dict__)
    children = queries.list_child_runs(parent, tracking_cfg)
    done = int(children["status"].isin(["FINISHED", "FAILED"]).sum()) if len(children) else 0
    finished = int((children["status"] == "FINISHED").sum()) if len(children) else 0
    summary = f"interrupted after {done} of {expected} runs"
    killed = []
    client = tracking.get_client(tracking_cfg)
    for row in children.itertuples() if len(children) else ():
        if row.status == "RUNNING":  # a child in another process (joblib) that did not close its run
            client.set_tag(row.run_id, tracking.ERROR_TAG, f"sweep {summary} ({how})")
            client.set_terminated(row.run_id, "KILLED")
        if row.status in ("RUNNING", "KILLED"):
            killed.append(row.run_name)
    tracking.set_run_tags(
        parent,
        {
            "aumesh.sweep.interrupted": f"{summary} ({how})",
            "aumesh.sweep.n_children": len(children),
            "aumesh.sweep.n_finished": finished,
            "aumesh.sweep.n_failed": len(children) - finished,
            tracking.ERROR_TAG: f"sweep {summary} ({how})",
        },
        tracking_cfg,
    )
    tracking.end_run(parent, tracking_cfg, "KILLED")
    return Interrupted(
        f"{summary} ({how}): sweep {parent} and its running configuration "
        f"{', '.join(killed) or '(none)'} marked KILLED; `aumesh promote` refuses it without --partial",
        signum,
    )


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m aumesh.experiments.sweep``: exit 1 when a configuration failed (``aumesh sweep`` adds ``--allow-failures``)."""
    return 1 if run_sweep(sys.argv[1:] if argv is None else argv).n_failed else 0


if __name__ == "__main__":  # python -m aumesh.experiments.sweep -m key=v1,v2
    sys.exit(main())
