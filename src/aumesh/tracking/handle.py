"""The handle of an open MLflow run: what a run logs (params, tags, metrics, artifacts, its dataset).

:class:`TrackedRun` logs to one run through an explicit client, never MLflow's fluent "active run"; every value is
cleaned first (:mod:`aumesh.tracking.values`). :func:`aumesh.tracking.runs.tracked_run` opens and closes the run and
yields the handle; :class:`aumesh.tracking.beside.RunBeside` queues the same methods to a helper process. With
tracking off, the handle is the no-op :class:`_NullRun`.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aumesh.core import provenance
from aumesh.tracking.values import (
    MAX_BATCH,
    MAX_DATASET_DIGEST_LENGTH,
    MAX_INPUT_TAG_VALUE_LENGTH,
    MAX_KEY_LENGTH,
    MAX_METRICS_BATCH,
    MAX_TAG_VALUE_LENGTH,
    _clean_key,
    _metric_value,
    _str_value,
    _truncate,
    prepare_params,
)

if TYPE_CHECKING:  # pragma: no cover
    from mlflow import MlflowClient


class TrackedRun:
    """Handle for one MLflow run; every method logs to this run explicitly.

    Attributes
    ----------
    run_id : str
    experiment_id : str
    tracking_uri : str
    client : mlflow.MlflowClient
    """

    enabled = True

    def __init__(self, client: MlflowClient, run_id: str, experiment_id: str) -> None:
        self.client = client
        self.run_id = run_id
        self.experiment_id = experiment_id
        self.tracking_uri = client.tracking_uri

    def __repr__(self) -> str:
        return f"TrackedRun(run_id={self.run_id!r}, tracking_uri={self.tracking_uri!r})"

    # -- params / tags / metrics
    def log_params(self, params: Mapping[str, Any]) -> dict[str, str]:
        """Log flattened, truncated params (see :func:`prepare_params`) without the keys of
        :data:`aumesh.config.WHERE_GROUPS` (a scheduler's or a server's address is not what a run computed); returns
        what was logged."""
        from mlflow.entities import Param

        from aumesh.config import without_where

        flat = prepare_params(without_where(params))
        items = [Param(k, v) for k, v in flat.items()]
        for i in range(0, len(items), MAX_BATCH):
            self.client.log_batch(self.run_id, params=items[i : i + MAX_BATCH])
        return flat

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        """Set run tags (values stringified, truncated to 8000 characters)."""
        from mlflow.entities import RunTag

        items = [RunTag(str(k)[:MAX_KEY_LENGTH], _str_value(v, MAX_TAG_VALUE_LENGTH)) for k, v in tags.items()]
        for i in range(0, len(items), MAX_BATCH):
            self.client.log_batch(self.run_id, tags=items[i : i + MAX_BATCH])

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        """Log scalar metrics ``{name: value}`` (numpy scalars accepted) at *step* (default 0)."""
        from mlflow.entities import Metric

        ts = int(time.time() * 1000)
        items = [Metric(_clean_key(k), _metric_value(v), ts, int(step or 0)) for k, v in metrics.items()]
        for i in range(0, len(items), MAX_METRICS_BATCH):
            self.client.log_batch(self.run_id, metrics=items[i : i + MAX_METRICS_BATCH])

    def log_metric_history(self, name: str, values: Any, first_step: int = 0) -> None:
        """Log a whole metric history in one batch: ``values[i]`` at step ``first_step + i``.

        E.g. the R²-vs-n_components curve with ``first_step=1`` (step = number of components);
        one database transaction instead of one per step.
        """
        from mlflow.entities import Metric

        ts = int(time.time() * 1000)
        key = _clean_key(name)
        items = [Metric(key, _metric_value(v), ts, first_step + i) for i, v in enumerate(values)]
        for i in range(0, len(items), MAX_METRICS_BATCH):
            self.client.log_batch(self.run_id, metrics=items[i : i + MAX_METRICS_BATCH])

    def log_fold_metrics(self, name_to_list: Mapping[str, Any], summary: bool = False) -> None:
        """Log per-fold values: ``{"r2": [f0, f1, f2]}`` -> metric ``r2`` at steps 0, 1, 2.

        Parameters
        ----------
        name_to_list : Mapping
            Metric name -> sequence of per-fold values (index = fold = step).
        summary : bool, default False
            Also log ``<name>_mean`` and ``<name>_std`` (population std) at step 0.
        """
        from mlflow.entities import Metric

        ts = int(time.time() * 1000)
        items = []
        means: dict[str, float] = {}
        for name, values in name_to_list.items():
            vals = [_metric_value(v) for v in values]
            key = _clean_key(name)
            items += [Metric(key, v, ts, fold) for fold, v in enumerate(vals)]
            if summary and vals:
                mean = sum(vals) / len(vals)
                means[f"{key}_mean"] = mean
                means[f"{key}_std"] = (sum((v - mean) ** 2 for v in vals) / len(vals)) ** 0.5
        for i in range(0, len(items), MAX_METRICS_BATCH):
            self.client.log_batch(self.run_id, metrics=items[i : i + MAX_METRICS_BATCH])
        if means:
            self.log_metrics(means)

    # -- artifacts
    def log_dict(self, obj: Any, artifact_file: str) -> None:
        """Log a JSON/YAML-serialisable object as *artifact_file* (``.json`` or ``.yaml``)."""
        self.client.log_dict(self.run_id, provenance._plain(obj), artifact_file)

    def log_text(self, text: str, artifact_file: str) -> None:
        """Log a string as *artifact_file*."""
        self.client.log_text(self.run_id, text, artifact_file)

    def log_figure(self, figure: Any, artifact_file: str) -> None:
        """Log a matplotlib (or plotly) figure as *artifact_file* (e.g. ``"plots/cv.png"``)."""
        self.client.log_figure(self.run_id, figure, artifact_file)

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None:
        """Copy a local file or directory into the run's artifacts (under *artifact_path*)."""
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"log_artifact: {path} does not exist")
        if path.is_dir():
            self.client.log_artifacts(self.run_id, str(path), artifact_path)
        else:
            self.client.log_artifact(self.run_id, str(path), artifact_path)

    def log_config(self, resolved_cfg: Any, artifact_file: str = "config.yaml") -> None:
        """Log the resolved config (dict or OmegaConf) as ``config.yaml``."""
        import yaml

        try:  # resolve interpolations if an OmegaConf container was passed
            from omegaconf import DictConfig, ListConfig, OmegaConf

            if isinstance(resolved_cfg, (DictConfig, ListConfig)):
                resolved_cfg = OmegaConf.to_container(resolved_cfg, resolve=True)
        except ImportError:  # pragma: no cover
            pass
        text = yaml.safe_dump(provenance._plain(resolved_cfg), sort_keys=False, default_flow_style=False)
        self.client.log_text(self.run_id, text, artifact_file)

    # -- dataset
    def log_dataset(
        self,
        digest: Mapping[str, Any],
        source: str,
        name: str = "frame_tables",
        context: str = "training",
    ) -> None:
        """Record the DVC-tracked data as an MLflow dataset input of this run.

        An :class:`mlflow.data.meta_dataset.MetaDataset` (metadata only, no data
        copied) whose ``digest`` is the DVC hash (``digest["md5"]``, e.g.
        ``"<32 hex>.dir"``, exactly MLflow's 36-char digest limit; longer values
        are cut and the full value kept in the input tags) and whose source is
        *source*: a local path (stored absolute, source type ``local``) or an
        ``http(s)``/``s3``/... URI. Input tags: ``mlflow.data.context`` and
        ``dvc.md5``/``dvc.size``/``dvc.nfiles``/``dvc.path``/``dvc.file``.

        Parameters
        ----------
        digest : Mapping
            Output of :func:`aumesh.core.provenance.data_digest`.
        source : str
            Where the data lives (e.g. the ``data`` directory).
        name : str, default "frame_tables"
        context : str, default "training"
        """
        from mlflow.data.meta_dataset import MetaDataset
        from mlflow.entities import DatasetInput, InputTag

        if not digest.get("md5"):
            raise ValueError("log_dataset: digest has no 'md5' key; pass aumesh.core.provenance.data_digest(...)")
        md5 = str(digest["md5"])
        # MLflow's stubs declare MetaDataset.profile abstract, but the class is concrete (it returns None) and MLflow's
        # own docs construct it this way
        dataset = MetaDataset(  # type: ignore[abstract]
            _dataset_source(source), name=name, digest=md5[:MAX_DATASET_DIGEST_LENGTH]
        )
        tags = [InputTag("mlflow.data.context", context)]
        for key, tag in (
            ("md5", "dvc.md5"),
            ("size", "dvc.size"),
            ("nfiles", "dvc.nfiles"),
            ("path", "dvc.path"),
            ("dvc_file", "dvc.file"),
        ):
            if digest.get(key) is not None:
                tags.append(InputTag(tag, _truncate(str(digest[key]), MAX_INPUT_TAG_VALUE_LENGTH)))
        log_inputs_once_created(self.client, self.run_id, [DatasetInput(dataset._to_mlflow_entity(), tags=tags)])


#: Attempts at linking a dataset another run is creating at the same moment (see :func:`log_inputs_once_created`).
DATASET_RACE_ATTEMPTS = 4


def log_inputs_once_created(client: MlflowClient, run_id: str, datasets: list, pause_s: float = 0.2) -> None:
    """``client.log_inputs``, again when another run created the same dataset at the same moment.

    MLflow's SQL store inserts a dataset the experiment does not have yet; two runs that log the same data at once
    (two teammates' sweeps starting together on a PostgreSQL server) both insert it, and the second fails on the
    dataset's primary key (``UniqueViolation``; SQLite: ``UNIQUE constraint failed``). The dataset exists by then:
    the next attempt finds it and only links it to this run. Any other error is raised as it comes.
    """
    from mlflow.exceptions import MlflowException

    for attempt in range(DATASET_RACE_ATTEMPTS):
        try:
            client.log_inputs(run_id, datasets=datasets)
            return
        except MlflowException as err:
            text = str(err)
            created_meanwhile = "UniqueViolation" in text or "UNIQUE constraint failed" in text or "dataset_pk" in text
            if not created_meanwhile or attempt == DATASET_RACE_ATTEMPTS - 1:
                raise
            time.sleep(pause_s * (attempt + 1))


class _NullRun(TrackedRun):
    """No-op handle used when ``tracking.enabled`` is false."""

    enabled = False

    def __init__(self) -> None:  # noqa: D107 - nothing to bind
        self.client = None  # type: ignore[assignment]
        self.run_id = None  # type: ignore[assignment]
        self.experiment_id = None  # type: ignore[assignment]
        self.tracking_uri = None

    def __getattribute__(self, item: str) -> Any:
        if item.startswith("log_") or item in ("set_tags", "call", "finish"):
            return lambda *a, **k: None
        return object.__getattribute__(self, item)

    def finish(self) -> None:
        """:meth:`aumesh.tracking.beside.RunBeside.finish` with tracking off: no run to end (declared for the one
        interface, as :meth:`call`)."""

    def call(self, fn, *args, **kwargs) -> None:
        """:meth:`aumesh.tracking.beside.RunBeside.call` with tracking off: nothing to run (``__getattribute__``
        answers first; declared so that the handle :func:`aumesh.tracking.beside.tracked_run_beside` yields has one
        interface)."""


def _dataset_source(source: str):
    """MLflow DatasetSource for a path or URI (paths become absolute, source type ``local``)."""
    import warnings

    from mlflow.data.dataset_source_registry import resolve_dataset_source

    src = str(source)
    if "://" not in src:
        src = Path(src).expanduser().absolute().as_posix()
    if src.startswith(("http://", "https://")):
        from mlflow.data.http_dataset_source import HTTPDatasetSource

        return HTTPDatasetSource(src)
    with warnings.catch_warnings():  # two "local" sources are registered; either is fine
        warnings.simplefilter("ignore")
        try:
            return resolve_dataset_source(src)
        except Exception:
            from mlflow.data.code_dataset_source import CodeDatasetSource

            return CodeDatasetSource({"source": src})
