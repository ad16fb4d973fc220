"""Stage ``evaluate``: cross-validated PLS and the final fit, from streamed sufficient statistics.

Card, "Method" and "Out-of-sample performance": ``PLSRegression(n_components, scale=True)``;
3-fold GroupKFold by video_id; variance-weighted R² (as ``sklearn.metrics.r2_score(...,
multioutput="variance_weighted")``), MAE; final fit on all kept frames.

Two passes over the prepared meshes:

* pass A (``aumesh.model.statistics``) accumulates per-fold cross-products of the full design with the
  absolute coordinates, plus per-video sums; every feature set, target and neutral is derived from
  them exactly, so a sweep needs this pass once. A fold's training statistics are the total minus
  the fold's, so each fold's model, and every smaller ``n_components``, comes from statistics; R² is
  exact from the held-out fold's statistics. Its tasks also hash the bytes of ``meshes.npy`` they read; the driver
  compares the digests with prepare's checksums before any model is fitted (``aumesh.pipeline.integrity``);
* pass B streams the rows once through their fold's model (all folds in one product) for MAE and
  the per-vertex Euclidean error; it runs once per configuration.

Besides R² in the run's own target space, every run gets ``r2_displacement``: R² of the
AU-driven displacement from each test video's neutral, ``(y - n_v)`` vs ``B (x - x̄_v)``, where
``n_v`` is the video's neutral mesh and ``x̄_v`` the mean design row of the same neutral frames.
It depends only on the slope ``B``, so absolute and neutral-subtracted runs are scored in the
same space and on the same information (see ``aumesh.experiments.promote``).

Every run also gets the AU-field reliability (:func:`au_field_reliability`: per AU, the cosine between
its fields fitted on each fold alone, ``aumesh.model.reliability``) and the number of AUs whose
direction passes the FACS check (:func:`facs_passes`, ``aumesh.card.directions``).
"""

from __future__ import annotations

import heapq
import logging
import shutil
import weakref
from collections.abc import Mapping
from contextlib import ExitStack
from dataclasses import dataclass, field
from functools import cached_property, partial
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from aumesh.config import Config
from aumesh.core.blas import one_blas_thread
from aumesh.core.errors import ConfigError, UserError
from aumesh.core.io import (
    NpyRowFile,
    NpyRows,
    RowArray,
    absolute,
    check_npy,
    create_npy,
    read_rows,
    row_runs,
    scratch_directory,
    write_rows,
)
from aumesh.core.schema import AU_COLUMNS, N_TARGETS, N_VERTICES, POSE_COLUMNS, feature_columns
from aumesh.model import reliability
from aumesh.model.cross_products import CrossProducts
from aumesh.model.features import design_matrix
from aumesh.model.kernel_pls import PLSFit, fit_statistics
from aumesh.model.release import release_arrays
from aumesh.model.scoring import r2_path, r2_per_target, r2_variance_weighted, residual_sums
from aumesh.model.statistics import (
    FULL_DESIGN,
    DesignStatistics,
    DesignSums,
    VideoSumStream,
    fold_configuration_statistics,
    fold_order,
    target_offsets,
)
from aumesh.pipeline import compute, integrity
from aumesh.pipeline.prepared_files import (
    FRAMES_FILE,
    MESHES_FILE,
    NEUTRAL_FILES,
    PREPARED_FILES,
    VIDEO_IDS_FILE,
    scratch_path,
)

log = logging.getLogger(__name__)


@dataclass
class Prepared:
    """The ``prepare`` stage's outputs. Nothing per frame or per video is loaded until asked for: the passes
    read their own rows (``frames.parquet`` row group by row group, ``meshes.npy`` with file I/O)."""

    directory: Path
    meshes: np.ndarray  # (n, 1434) float32 memmap, axis-major
    video_ids: np.ndarray
    neutral: Mapping[str, NpyRows]  # method -> (n_videos, 1434) float32 rows, read on demand
    reference: dict[str, np.ndarray]
    summary: dict
    mesh_path: Path | None = None  # meshes.npy: the passes read it with plain file I/O
    # meshes.npy's checksummed blocks that pass A verifies as it reads them (row group -> blocks; None: not recorded)
    mesh_check: integrity.StreamedCheck | None = None

    @cached_property
    def frames(self) -> pd.DataFrame:
        """Every prepared frame's metadata (whole: for tests and small data; the passes read row groups)."""
        return pd.read_parquet(self.directory / FRAMES_FILE)

    @cached_property
    def videos(self) -> VideoFrames:
        """Per-video frame counts and row groups (one pass over two columns of ``frames.parquet``)."""
        return video_frames(self.directory, self.row_groups(), len(self.video_ids))

    @property
    def n_frames(self) -> int:
        groups = self.row_groups()
        return groups[-1][2] if groups else 0

    def row_groups(self) -> list[tuple[int, int, int]]:
        """``(row_group, first_row, stop_row)`` of ``frames.parquet``: the partitions of the evaluate passes."""
        return row_groups(self.directory)

    @cached_property
    def au(self) -> np.ndarray:
        """(n, 20) AU intensities, float64 (whole)."""
        return self.frames[list(AU_COLUMNS)].to_numpy(np.float64)

    @cached_property
    def pose(self) -> np.ndarray:
        """(n, 3) Pitch, Yaw, Roll in radians, float64 (whole)."""
        return self.frames[list(POSE_COLUMNS)].to_numpy(np.float64)


def row_groups(directory: Path) -> list[tuple[int, int, int]]:
    """``(row_group, first_row, stop_row)`` of ``frames.parquet`` in ``directory``: the partitions of the passes."""
    md = pq.ParquetFile(directory / FRAMES_FILE).metadata
    bounds = np.r_[0, np.cumsum([md.row_group(g).num_rows for g in range(md.num_row_groups)])]
    return [(g, int(bounds[g]), int(bounds[g + 1])) for g in range(md.num_row_groups) if bounds[g + 1] > bounds[g]]


def workers_check(prepared: Prepared) -> dict[str, Path]:
    """What a cluster's workers must reach (:func:`aumesh.pipeline.compute.engine`): read the prepared frames, write
    the scratch folders beside the prepared data (:func:`scratch_path`)."""
    return {"read": prepared.directory / FRAMES_FILE, "write": scratch_path(prepared.directory).parent}


def _read_group(directory: Path, group: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """AU (m, 20), pose (m, 3), video index (m,) and low-AU flag (m,) of one row group of ``frames.parquet``.

    A column at a time, straight into the stacked arrays: the row group's decoded columns and their compressed pages,
    read at once and then copied twice, were the largest step of a task that grew with the partition (the error pass's
    task at 3.1M frames: 35 -> 21 MiB above the trimmed heap with this and its reused block buffers)."""
    with pq.ParquetFile(directory / FRAMES_FILE) as parquet:

        def column(name: str) -> np.ndarray:
            # one thread: the partitions already run on every core (as aumesh.data.tables reads the tables)
            return (
                parquet.read_row_group(group, columns=[name], use_threads=False)
                .column(0)
                .to_numpy(zero_copy_only=False)
            )

        n_rows = parquet.metadata.row_group(group).num_rows
        au, pose = np.empty((n_rows, len(AU_COLUMNS))), np.empty((n_rows, len(POSE_COLUMNS)))
        for k, name in enumerate(AU_COLUMNS):
            au[:, k] = column(name)
        for k, name in enumerate(POSE_COLUMNS):
            pose[:, k] = column(name)
        return au, pose, column("video_index"), column("low_au")


@dataclass(frozen=True)
class VideoFrames:
    """Where each video's frames are in ``frames.parquet``: per-video arrays (n_videos,), nothing per frame."""

    count: np.ndarray  # frames of each video
    low_count: np.ndarray  # low-AU frames of each video
    first_group: np.ndarray  # first row group holding the video (the number of row groups: none)
    last_group: np.ndarray  # last row group holding the video (-1: none)

    @property
    def split(self) -> np.ndarray:
        """(n_videos,) bool: the video's frames are not all in one row group (or it has none)."""
        return self.first_group != self.last_group


def _video_frames_partition(
    group: tuple[int, int, int], directory: Path
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """``(row group, videos, frames, low-AU frames)`` of one row group of ``frames.parquet``."""
    g = group[0]
    t = pq.ParquetFile(directory / FRAMES_FILE).read_row_group(g, columns=["video_index", "low_au"], use_threads=False)
    video = t.column("video_index").to_numpy()
    low = t.column("low_au").to_numpy(zero_copy_only=False)
    videos, local, count = np.unique(video, return_inverse=True, return_counts=True)
    return g, videos, count, np.bincount(local[low], minlength=len(videos))


def video_frames(directory: Path, groups: list[tuple[int, int, int]], n_videos: int) -> VideoFrames:
    """Per-video frame and low-AU frame counts and first/last row group, from one pass over the ``video_index``
    and ``low_au`` columns of ``frames.parquet`` (row group by row group, on the current Dask scheduler)."""
    count, low_count = np.zeros(n_videos, dtype=np.int64), np.zeros(n_videos, dtype=np.int64)
    first, last = np.full(n_videos, len(groups), dtype=np.int64), np.full(n_videos, -1, dtype=np.int64)
    for g, videos, c, low in compute.map_gather(partial(_video_frames_partition, directory=directory), groups):
        count[videos] += c
        low_count[videos] += low
        first[videos] = np.minimum(first[videos], g)
        last[videos] = np.maximum(last[videos], g)
    return VideoFrames(count=count, low_count=low_count, first_group=first, last_group=last)


class _LazyArrays(Mapping):
    """Read-only mapping onto per-video ``.npy`` arrays, rows read on demand (:class:`aumesh.core.io.NpyRows`)."""

    def __init__(self, paths: dict[str, Path]):
        self._paths = paths

    def __getitem__(self, key: str) -> NpyRows:
        return NpyRows(self._paths[key])

    def __iter__(self):
        return iter(self._paths)

    def __len__(self) -> int:
        return len(self._paths)


def load_prepared(prepared_dir: str | Path) -> Prepared:

    d = Path(prepared_dir)
    missing = [n for n in PREPARED_FILES if not (d / n).exists()]
    if missing:
        raise UserError(f"{d}: missing {', '.join(missing)}. Fix: run the prepare stage first (`dvc repro prepare`).")
    summary = integrity.load_summary(d)
    # before any file is used, truncated, damaged or edited files are refused: the small ones here, whole (their
    # readers pick rows anywhere); meshes.npy here but for the blocks pass A reads whole, one row group each, which
    # are hashed as it reads them (reading the ~2 GB once more here cost the stage 14 % at 344k frames)
    integrity.verify_prepared(d, summary, [n for n in PREPARED_FILES if n != MESHES_FILE])
    offset, _, shape = check_npy(d / MESHES_FILE, integrity.prepared_fix(d / MESHES_FILE) + ".")
    row_bytes = int(np.prod(shape[1:], dtype=np.int64)) * np.dtype(np.float32).itemsize
    partitions = {g: (offset + start * row_bytes, offset + stop * row_bytes) for g, start, stop in row_groups(d)}
    streamed = integrity.verify_prepared(d, summary, [MESHES_FILE], streamed={MESHES_FILE: partitions})
    d = absolute(d)  # what the partition tasks read, and the scratch folders' place: a cluster's workers run elsewhere
    return Prepared(
        directory=d,
        meshes=np.load(d / MESHES_FILE, mmap_mode="r"),
        mesh_path=d / MESHES_FILE,
        video_ids=np.load(d / VIDEO_IDS_FILE, mmap_mode="r"),  # the stage needs their number; 4 MiB at 88k videos
        neutral=_LazyArrays({method: d / name for method, name in NEUTRAL_FILES.items()}),
        reference=integrity.load_reference(d),
        summary=summary,
        mesh_check=streamed.get(MESHES_FILE),
    )


@dataclass
class FoldStatistics:
    """Per-fold statistics of one design (features x target) over all prepared frames."""

    target: list[CrossProducts]  # (X, Y in the run's target space) per fold
    displacement: list[CrossProducts]  # (X - x̄_v, Y_abs - n_v) per fold
    video_fold: np.ndarray  # (n_videos,) fold of each video (-1: no frames)
    x_offset: np.ndarray | None = None  # (n_videos, p) per-video design centre of the target (None: none)
    y_offset: RowArray | None = None  # (n_videos, 1434) per-video mesh centre of the target (None: none)

    @property
    def total(self) -> CrossProducts:
        out = self.target[0].copy()
        for s in self.target[1:]:
            out = out + s
        return out


@dataclass
class CVResult:
    n_components: int
    feature_columns: list[str]
    r2_folds: list[float]
    r2_displacement_folds: list[float]
    r2_path_folds: np.ndarray  # (n_splits, n_components): R² for k = 1..n_components
    mae_folds: list[float]
    vertex_error_folds: list[float]
    r2_per_target: np.ndarray  # (1434,) pooled over folds
    r2_per_vertex: np.ndarray  # (478,) pooled over folds and axes
    frame_vertex_error: NpyRows  # (n,) float32 mean per-vertex Euclidean error of each frame (held out), on disk
    vertex_error_per_vertex: np.ndarray  # (478,) mean over held-out frames
    n_frames_folds: list[int]
    n_videos_folds: list[int]
    extra: dict = field(default_factory=dict)
    au_reliability: np.ndarray | None = None  # (20,) mean cosine of each AU's field between folds fitted alone
    n_aus_facs_pass: int | None = None  # AUs of the final model whose direction passes the FACS check

    def metrics(self) -> dict:
        def ms(values):
            return float(np.mean(values)), float(np.std(values))

        r2m, r2s = ms(self.r2_folds)
        dm, ds = ms(self.r2_displacement_folds)
        maem, maes = ms(self.mae_folds)
        vem, ves = ms(self.vertex_error_folds)
        return {
            "r2_mean": r2m,
            "r2_std": r2s,
            "r2_folds": [float(v) for v in self.r2_folds],
            "r2_displacement_mean": dm,
            "r2_displacement_std": ds,
            "r2_displacement_folds": [float(v) for v in self.r2_displacement_folds],
            "mae_mean": maem,
            "mae_std": maes,
            "mae_folds": [float(v) for v in self.mae_folds],
            "vertex_error_mean": vem,
            "vertex_error_std": ves,
            "vertex_error_folds": [float(v) for v in self.vertex_error_folds],
            "n_components": self.n_components,
            "n_features": len(self.feature_columns),
            "n_frames_folds": self.n_frames_folds,
            "n_videos_folds": self.n_videos_folds,
        } | self.field_metrics()

    def field_metrics(self) -> dict:
        """AU-field reliability (min, median, per AU) and the FACS direction count, when computed."""
        out = {} if self.au_reliability is None else reliability.summarize(self.au_reliability, list(AU_COLUMNS))
        if self.n_aus_facs_pass is not None:
            out["n_aus_facs_pass"] = int(self.n_aus_facs_pass)
        return out

    def scalar_metrics(self) -> dict[str, float]:
        """What a run logs to MLflow: every scalar of :meth:`metrics`, the per-AU reliability as ``au_reliability_<AU>``."""
        metrics = self.metrics()
        out = {k: v for k, v in metrics.items() if isinstance(v, float)}
        out |= {f"au_reliability_{au}": v for au, v in metrics.get("au_reliability", {}).items()}
        if "n_aus_facs_pass" in metrics:
            out["n_aus_facs_pass"] = float(metrics["n_aus_facs_pass"])
        return out


def effective_n_components(cfg: Config) -> int:
    """``model.n_components``, clipped to the number of features when ``model.clip_n_components``."""
    p = len(cfg.features.columns)
    if cfg.model.n_components > p:
        if not cfg.model.clip_n_components:
            raise ValueError(
                f"model.n_components={cfg.model.n_components} exceeds the {p} features of "
                f"features={cfg.features.name}. Fix: lower it, or set model.clip_n_components=true."
            )
        return p
    return cfg.model.n_components


def video_folds(video_count: np.ndarray, n_splits: int) -> np.ndarray:
    """Fold of every video (fold ``f`` = the f-th test split of scikit-learn's ``GroupKFold(n_splits)`` on the
    frames' video index), from the videos' frame counts alone.

    ``GroupKFold`` (``sklearn/model_selection/_split.py``, no shuffle) takes the groups present in index order,
    sorts their sizes with a stable argsort, reversed (largest first; among equal sizes the highest index first),
    and gives each in turn to the lightest fold so far (the first of equally light ones). A heap of
    ``(frames, fold)`` pops exactly that fold.

    Parameters
    ----------
    video_count : ndarray (n_videos,) int
        Frames of each video (0: the video has none and gets no fold).
    n_splits : int

    Returns
    -------
    ndarray (n_videos,) int64
        Fold of each video, -1 for videos without frames.
    """
    present = np.flatnonzero(np.asarray(video_count) > 0)
    if len(present) < n_splits:
        raise ConfigError(
            f"cv.n_splits={n_splits} but only {len(present)} videos are left after filtering. Fix: lower cv.n_splits."
        )
    sizes = np.asarray(video_count)[present]
    fold = np.full(len(video_count), -1, dtype=np.int64)
    heap = [(0, f) for f in range(n_splits)]
    for i in np.argsort(sizes, kind="stable")[::-1].tolist():
        load, f = heap[0]
        heapq.heapreplace(heap, (load + int(sizes[i]), f))
        fold[present[i]] = f
    return fold


@dataclass
class DesignPart:
    """Pass A of consecutive partitions: per-fold sums, and per-video sums of videos split across partitions."""

    sums: DesignSums
    split: dict[int, tuple[np.ndarray, ...]]  # video -> VIDEO_SUMS' rows: (sum x - a, sum y - b, low-AU sum x - a)
    # (start, stop) -> digest of those bytes of meshes.npy as the partitions read them (Prepared.mesh_check)
    digests: dict[tuple[int, int], str] = field(default_factory=dict)

    def __add__(self, other: DesignPart) -> DesignPart:
        split = dict(self.split)
        for v, parts in other.split.items():
            split[v] = tuple(a + b for a, b in zip(split[v], parts, strict=True)) if v in split else parts
        return DesignPart(self.sums + other.sums, split, {**self.digests, **other.digests})


#: Per-video sums pass A writes (rows = video index), in a scratch folder beside the prepared data.
VIDEO_SUMS = {"video_sum_x": len(FULL_DESIGN), "video_sum_y": N_TARGETS, "video_low_sum_x": len(FULL_DESIGN)}


#: Most rows a pass multiplies at a time: a (512, 1434) float64 block and its products stay in the CPU's cache
#: (measured on a 4,096-row chunk of pass A: 511 -> 340 ms single-threaded), and 1 or 2 workers, or the
#: synchronous scheduler, then cut the rows the same way (the same float64 sums).
BLOCK_ROWS = 512


def block_rows(chunk_rows: int) -> int:
    """Rows a task of the evaluate passes reads and multiplies at a time (``data.chunk_rows`` bounds it too)."""
    return min(BLOCK_ROWS, compute.task_rows(chunk_rows))


def _fold_grouped_block(
    meshes: NpyRowFile, raw: np.ndarray, lo: int, hi: int, start: int, fold: np.ndarray, n_splits: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mesh rows ``lo:hi`` grouped by fold (a stable order: rows of a fold, and of a video, keep their order), read
    run by run in that order so the block is never copied to reorder it.

    Returns
    -------
    rows : ndarray of int, shape (m,)
        The partition's rows (``lo - start`` ... ) in the grouped order.
    bounds : ndarray, shape (n_splits + 1,)
        Fold ``f``'s rows are ``[bounds[f], bounds[f + 1])`` of the block.
    Y : ndarray of float32, shape (m, 1434)
        The rows as stored (the first rows of ``raw``): the passes widen them to float64 in their first arithmetic step
        instead of in a copy of their own.
    """
    order, bounds = fold_order(fold[lo - start : hi - start], n_splits)
    if order is None:
        return np.arange(lo - start, hi - start), bounds, meshes.read(lo, hi, raw)
    return order + (lo - start), bounds, meshes.take(order + lo, raw)


def _hash_block(digests: integrity.RangeDigests, meshes: NpyRowFile, file_rows: np.ndarray, Y: np.ndarray) -> None:
    """Feed the block's rows ``Y`` (file rows ``file_rows``, in the block's order) to ``digests`` in the file's order:
    a run of consecutive rows at a time, where the read put it (no copy to reorder the block)."""
    for j, (lo, hi) in sorted(row_runs(file_rows), key=lambda run: run[1][0]):
        digests.update(meshes.offset + lo * meshes.row_bytes, memoryview(Y[j : j + hi - lo].data).cast("B"))


def design_partition(
    group: tuple[int, int, int],
    directory: Path,
    video_fold: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    n_splits: int,
    chunk_rows: int,
    scratch: Path,
    split_video: np.ndarray,
    check: integrity.StreamedCheck | None = None,
) -> DesignPart:
    """Pass A on one row group of the prepared data: per-fold sums of the full design with the absolute
    coordinates (shifted by ``a``, ``b``), and the per-video sums; those of videos held whole by this
    partition are written to ``scratch`` as each video finishes, those of videos split across partitions returned.
    The checksummed blocks of ``meshes.npy`` the row group holds (``check``) are hashed from the bytes read, for the
    driver to compare (:meth:`aumesh.pipeline.integrity.StreamedCheck.check`)."""
    g, start, stop = group
    digests = integrity.RangeDigests(check.ranges(g), check.algorithm) if check is not None else None
    au, pose, video, low = _read_group(directory, g)
    fold = video_fold[video]
    p, q = len(FULL_DESIGN), N_TARGETS
    sums = DesignSums(p, q, n_splits)
    split: dict[int, tuple[np.ndarray, ...]] = {}
    finished: dict[str, dict[int, np.ndarray]] = {name: {} for name in VIDEO_SUMS}  # whole videos, until written

    def done(name: str):
        k = list(VIDEO_SUMS).index(name)

        def store(v: int, total: np.ndarray, _n_rows: int) -> None:
            if split_video[v]:  # a split video without low-AU rows here adds zeros for them
                values = split.setdefault(v, tuple(np.zeros(width) for width in VIDEO_SUMS.values()))
                values[k][:] = total
            else:
                finished[name][v] = total

        return store

    # per-video sums while a video has rows to come in this partition (not a row per video of the partition: ~12 MiB
    # a task at 3.1M frames), the same float64 additions as a dense array's
    streams = {
        "video_sum_x": VideoSumStream(video, done("video_sum_x")),
        "video_sum_y": VideoSumStream(video, done("video_sum_y")),
        "video_low_sum_x": VideoSumStream(video[low], done("video_low_sum_x")),
    }
    raw = np.empty((min(chunk_rows, stop - start), q), dtype=np.float32)
    centred = np.empty(raw.shape)  # the block's rows minus b, float64 (allocated once a task, as raw)
    with ExitStack() as stack:
        meshes = stack.enter_context(NpyRowFile(directory / MESHES_FILE))
        files = {name: stack.enter_context(NpyRowFile(scratch / f"{name}.npy", writable=True)) for name in VIDEO_SUMS}
        for lo in range(start, stop, chunk_rows):
            rows, _, Y = _fold_grouped_block(meshes, raw, lo, min(lo + chunk_rows, stop), start, fold, n_splits)
            if digests is not None:
                _hash_block(digests, meshes, rows + start, Y)
            X = design_matrix(au[rows], pose[rows], True, True)
            X -= a
            Y = np.subtract(Y, b, out=centred[: len(Y)])  # float64 (the float32 rows widen exactly)
            # a video's rows stay consecutive in the fold-grouped block (a video is in one fold): summed in place
            block_video, neutral = video[rows], low[rows]
            streams["video_sum_x"].add(block_video, X)
            streams["video_sum_y"].add(block_video, Y)
            streams["video_low_sum_x"].add(block_video[neutral], X[neutral])
            sums.add(X, Y, fold[rows])
            for name, rows_of in finished.items():
                files[name].write_row_map(rows_of)
                rows_of.clear()
    return DesignPart(sums, split, digests.digests if digests is not None else {})


class NeutralDesign:
    """Mean full-design row of each video's neutral frames, ``(n_videos, 83)``, rows computed on demand from
    the per-video sums pass A wrote (``sum / count + a``)."""

    def __init__(self, sums: RowArray, count: np.ndarray, shift: np.ndarray):
        self.sums, self.count, self.shift = sums, count, shift
        self.shape = (len(count), len(shift))

    def __getitem__(self, key):
        rest = ()
        if isinstance(key, tuple):
            key, rest = key[0], key[1:]
        v = np.arange(self.shape[0])[key]
        out = self.sums[v] / np.maximum(self.count[v], 1).astype(np.float64)[..., None] + self.shift
        return out[(slice(None), *rest)] if rest else out

    def __array__(self, dtype=None, copy=None):
        out = self[:]
        return out if dtype is None else out.astype(dtype)


def design_statistics(prepared: Prepared, video_fold: np.ndarray, n_splits: int, chunk_rows: int) -> DesignStatistics:
    """Pass A: per-fold statistics of the full design with absolute coordinates (one pass, every configuration).

    ``video_fold`` (n_videos,) is each video's fold (:func:`video_folds`). The provisional shift ``(a, b)`` is the
    mean of the first :data:`BLOCK_ROWS` rows (a centre, not a statistic: reading ``chunk_rows`` rows for it cost the
    stage 0.2 s of fresh memory), shared by every fold and partition. The per-video sums stay on disk
    (:class:`aumesh.core.io.NpyRows`) in a scratch folder beside the prepared data, removed with the returned
    statistics.
    """
    n_videos = len(prepared.video_ids)
    videos = prepared.videos
    first = min(BLOCK_ROWS, prepared.n_frames)
    head = _head(prepared, first)
    a = design_matrix(
        head[list(AU_COLUMNS)].to_numpy(np.float64), head[list(POSE_COLUMNS)].to_numpy(np.float64), True, True
    ).mean(axis=0)
    assert prepared.mesh_path is not None  # load_prepared sets it
    b = read_rows(prepared.mesh_path, 0, first).astype(np.float64).mean(axis=0)
    scratch = scratch_directory(scratch_path(prepared.directory))
    try:
        for name, width in VIDEO_SUMS.items():
            create_npy(scratch / f"{name}.npy", np.float64, (n_videos, width))
        part = compute.map_reduce(
            partial(
                design_partition,
                directory=prepared.directory,
                video_fold=video_fold,
                a=a,
                b=b,
                n_splits=n_splits,
                chunk_rows=block_rows(chunk_rows),
                scratch=scratch,
                split_video=videos.split,
                check=prepared.mesh_check,
            ),
            DesignPart.__add__,
            prepared.row_groups(),
            desc="evaluate: statistics",
        )
        if prepared.mesh_check is not None:  # the bytes just read are prepare's, or the stage stops before any fit
            prepared.mesh_check.check(part.digests)
        for v, values in part.split.items():
            for name, row in zip(VIDEO_SUMS, values, strict=True):
                write_rows(scratch / f"{name}.npy", v, row[None])
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        raise
    design = DesignStatistics(
        folds=part.sums.folds(a, b),
        video_fold=video_fold,
        video_count=videos.count,
        video_sum_x=NpyRows(scratch / "video_sum_x.npy"),
        video_sum_y=NpyRows(scratch / "video_sum_y.npy"),
    )
    design.neutral_design = {  # mean design row of each video's neutral frames, per neutral method
        "low_au": NeutralDesign(NpyRows(scratch / "video_low_sum_x.npy"), videos.low_count, a),
        "mean": NeutralDesign(design.video_sum_x, design.video_count, a),
    }
    weakref.finalize(design, shutil.rmtree, scratch, True)
    return design


def _head(prepared: Prepared, n: int) -> pd.DataFrame:
    """The first ``n`` rows of ``frames.parquet`` (AU and pose columns)."""
    batches = pq.ParquetFile(prepared.directory / FRAMES_FILE).iter_batches(
        batch_size=n, columns=[*AU_COLUMNS, *POSE_COLUMNS]
    )
    return next(batches).to_pandas().iloc[:n]


def accumulate(
    prepared: Prepared,
    cfg: Config,
    video_fold: np.ndarray,
    chunk_rows: int | None = None,
    design: DesignStatistics | None = None,
) -> FoldStatistics:
    """Per-fold (target, displacement) statistics of ``cfg``'s features and target; ``video_fold`` (n_videos,)
    is each video's fold (:func:`video_folds`).

    ``design`` (from :func:`design_statistics` with the same folds) is reused when given: then no
    pass over the meshes is needed (aumesh.model.statistics derives every configuration from it).
    """
    if design is None:
        design = design_statistics(prepared, video_fold, cfg.cv.n_splits, chunk_rows or cfg.data.chunk_rows)
    elif not np.array_equal(design.video_fold, video_fold):
        raise ValueError("accumulate: the design statistics were built with other folds")
    method = cfg.preprocess.neutral.method
    # the folds' statistics are independent: at once on this machine's cores (single-threaded BLAS each: the same bits)
    per_fold = compute.local_map(
        partial(
            fold_configuration_statistics,
            design,
            columns=cfg.features.columns,
            target=cfg.preprocess.target,
            neutral=prepared.neutral[method],
            neutral_design_full=design.neutral_design[method],
        ),
        range(cfg.cv.n_splits),
    )
    target, displacement = [t for t, _ in per_fold], [d for _, d in per_fold]
    x_offset, y_offset = target_offsets(
        design, cfg.features.columns, cfg.preprocess.target, prepared.neutral[method], design.neutral_design[method]
    )
    return FoldStatistics(
        target=target, displacement=displacement, video_fold=video_fold, x_offset=x_offset, y_offset=y_offset
    )


def fit(stats: CrossProducts, n_components: int, scale: bool) -> PLSFit:
    """The engine's PLS fit from statistics (card: PLSRegression(n_components, scale=True); the fitted attributes
    of :class:`aumesh.model.pls.PLSRegression`, without importing scikit-learn in the stage)."""
    with one_blas_thread():
        return fit_statistics(stats, n_components, scale)


@dataclass
class Fits:
    """Every model of one configuration, fitted from its statistics (:func:`fit_models`)."""

    folds: list[PLSFit]  # fold f's model: trained on the other folds (cross-validation)
    final: PLSFit  # trained on every frame (card: final fit on all kept frames)
    alone: list[PLSFit]  # trained on fold f alone (the AU-field reliability)


def fit_models(cfg: Config, stats: FoldStatistics) -> Fits:
    """The ``2 n_splits + 1`` fits of a configuration: independent, from statistics, so they run at once on this
    machine's cores (:func:`aumesh.pipeline.compute.local_map`; each on one BLAS thread, so each is the same to the
    bit on any number of cores)."""
    A = effective_n_components(cfg)
    total = stats.total
    training = [total - held_out for held_out in stats.target] + [total] + list(stats.target)
    with one_blas_thread():  # held across the threads: one fit's exit does not lift another's limit
        models = compute.local_map(partial(fit, n_components=A, scale=cfg.model.scale), training)
    k = len(stats.target)
    return Fits(folds=models[:k], final=models[k], alone=models[k + 1 :])


def cross_validate(
    prepared: Prepared, cfg: Config, stats: FoldStatistics, fold_models: list[PLSFit], chunk_rows: int | None = None
) -> CVResult:
    """Score each fold's model (``fold_models[f]``, trained without fold ``f``: :func:`fit_models`) from statistics
    (R²) and one streaming pass (MAE, per-vertex error)."""
    chunk_rows = chunk_rows or cfg.data.chunk_rows
    A = effective_n_components(cfg)
    n_splits = cfg.cv.n_splits
    r2_folds, r2d_folds, paths, sse_sum, sst_sum = [], [], [], np.zeros(N_TARGETS), np.zeros(N_TARGETS)
    models = [(model.coef_, model.raw_intercept_) for model in fold_models]
    with one_blas_thread():
        for f, model in enumerate(fold_models):
            sse, sst = residual_sums(model.coef_, model.raw_intercept_, stats.target[f])
            r2_folds.append(r2_variance_weighted(sse, sst))
            sse_sum += sse
            sst_sum += sst
            sse_d, sst_d = residual_sums(model.coef_, np.zeros(N_TARGETS), stats.displacement[f])
            r2d_folds.append(r2_variance_weighted(sse_d, sst_d))
            paths.append(r2_path(model, stats.target[f]))

    # pass B: held-out predictions, streamed partition by partition; each frame's error goes to rows of a scratch
    # .npy beside the prepared data (removed with the result), never gathered
    use_pose, inter = cfg.features.pose, cfg.features.interactions
    video_fold, video_count = stats.video_fold, prepared.videos.count
    has = video_fold >= 0
    count = np.bincount(video_fold[has], weights=video_count[has], minlength=n_splits).astype(np.int64)
    scratch = scratch_directory(scratch_path(prepared.directory))
    frame_error = scratch / FRAME_ERROR_FILE
    try:
        create_npy(frame_error, np.float32, (prepared.n_frames,))
        errors = compute.map_reduce(
            partial(
                error_partition,
                directory=prepared.directory,
                video_fold=video_fold,
                coefs=[np.ascontiguousarray(coef.T) for coef, _ in models],
                intercepts=[intercept for _, intercept in models],
                use_pose=use_pose,
                interactions=inter,
                n_splits=n_splits,
                chunk_rows=block_rows(chunk_rows),
                frame_error=frame_error,
                x_offset=stats.x_offset,
                y_offset=stats.y_offset,
            ),
            ErrorPart.__add__,
            prepared.row_groups(),
            desc="evaluate: errors",
        )
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        raise
    abs_sum, vertex_sum = errors.abs_sum, errors.vertex_sum
    fold_videos = np.bincount(video_fold[has], minlength=n_splits).tolist()
    sse_v, sst_v = sse_sum.reshape(3, N_VERTICES).sum(0), sst_sum.reshape(3, N_VERTICES).sum(0)
    result = CVResult(
        n_components=A,
        feature_columns=feature_columns(use_pose, inter),
        r2_folds=[float(r) for r in r2_folds],
        r2_displacement_folds=[float(r) for r in r2d_folds],
        r2_path_folds=np.vstack(paths),
        mae_folds=list(abs_sum / (count * N_TARGETS)),
        vertex_error_folds=list(vertex_sum.sum(axis=1) / (count * N_VERTICES)),
        r2_per_target=r2_per_target(sse_sum, sst_sum),
        r2_per_vertex=r2_per_target(sse_v, sst_v),  # x, y, z pooled per vertex
        frame_vertex_error=NpyRows(frame_error),
        vertex_error_per_vertex=vertex_sum.sum(axis=0) / count.sum(),
        n_frames_folds=[int(c) for c in count],
        n_videos_folds=fold_videos,
    )
    weakref.finalize(result, shutil.rmtree, scratch, True)
    return result


#: Each frame's held-out mean per-vertex error, (n_frames,) float32 in ``frames.parquet``'s row order.
FRAME_ERROR_FILE = "frame_vertex_error.npy"


@dataclass
class ErrorPart:
    """Pass B of consecutive partitions: absolute and per-vertex error sums per fold."""

    abs_sum: np.ndarray  # (K,)
    vertex_sum: np.ndarray  # (K, 478)

    def __add__(self, other: ErrorPart) -> ErrorPart:
        return ErrorPart(self.abs_sum + other.abs_sum, self.vertex_sum + other.vertex_sum)


def error_partition(
    group: tuple[int, int, int],
    directory: Path,
    video_fold: np.ndarray,
    coefs: list[np.ndarray],
    intercepts: list[np.ndarray],
    use_pose: bool,
    interactions: bool,
    n_splits: int,
    chunk_rows: int,
    frame_error: Path,
    x_offset=None,
    y_offset=None,
) -> ErrorPart:
    """Pass B on one row group: each frame's held-out residual under its fold's model (``coefs[f]`` (p, 1434),
    ``intercepts[f]`` (1434,)), and the error sums per fold; each frame's mean per-vertex error is written to its
    row of the ``.npy`` ``frame_error`` (n_frames,) float32. ``x_offset`` (n_videos, p) and ``y_offset``
    (n_videos, 1434), arrays or :class:`aumesh.core.io.NpyRows`, are the target's per-video centres (None: none);
    only the partition's videos' rows are read."""
    g, start, stop = group
    au, pose, video, _ = _read_group(directory, g)
    fold = video_fold[video]
    videos, local = np.unique(video, return_inverse=True)
    x_rows = None if x_offset is None else np.asarray(x_offset[videos], dtype=np.float64)
    y_rows = None if y_offset is None else np.asarray(y_offset[videos])
    abs_sum, vertex_sum = np.zeros(n_splits), np.zeros((n_splits, N_VERTICES))
    # the blocks' arrays, allocated once a task: a fresh set per block left the freed blocks' holes in the heap for the
    # partition's other arrays to fragment
    raw = np.empty((min(chunk_rows, stop - start), N_TARGETS), dtype=np.float32)
    residual = np.empty((len(raw), N_TARGETS))
    vertex_error = np.empty((len(raw), N_VERTICES))
    with NpyRowFile(directory / MESHES_FILE) as meshes, NpyRowFile(frame_error, writable=True) as errors:
        for lo in range(start, stop, chunk_rows):
            rows, bounds, Y = _fold_grouped_block(meshes, raw, lo, min(lo + chunk_rows, stop), start, fold, n_splits)
            X = design_matrix(au[rows], pose[rows], use_pose, interactions)
            if x_rows is not None:  # the target's per-video centres (held-out videos: their own)
                X -= x_rows[local[rows]]
            if y_rows is not None:
                Y = Y - y_rows[local[rows]]
            # minus the residual y - (x @ coef_f.T + raw_intercept_f), rounded as it (-(u - v) is v - u exactly): the
            # prediction's GEMM writes the block, and the float32 rows widen inside the subtraction, not in a copy
            R = residual[: len(Y)]
            for f in range(n_splits):  # one GEMM per fold's rows and model
                lo_f, hi_f = bounds[f], bounds[f + 1]
                np.matmul(X[lo_f:hi_f], coefs[f], out=R[lo_f:hi_f])
                np.subtract(R[lo_f:hi_f], Y[lo_f:hi_f], out=R[lo_f:hi_f])
                R[lo_f:hi_f] += intercepts[f]
            e3 = R.reshape(len(R), 3, N_VERTICES)
            per_vertex = vertex_error[: len(R)]  # (m, 478) Euclidean error per vertex
            np.sqrt(np.einsum("ikj,ikj->ij", e3, e3, out=per_vertex), out=per_vertex)
            error = per_vertex.mean(axis=1)
            errors.write(lo, error[np.argsort(rows)].astype(np.float32))  # back in the file's order
            row_abs = np.abs(R, out=R).sum(axis=1)  # in place: R is not used again (no block-sized temporary)
            for f in range(n_splits):
                lo_f, hi_f = bounds[f], bounds[f + 1]
                abs_sum[f] += row_abs[lo_f:hi_f].sum()
                vertex_sum[f] += per_vertex[lo_f:hi_f].sum(axis=0)
    return ErrorPart(abs_sum, vertex_sum)


def _weighted_mean(rows, weights: np.ndarray, block: int = 4096) -> np.ndarray:
    """``weights @ rows / weights.sum()`` over per-video rows (an array or :class:`aumesh.core.io.NpyRows`),
    a block of videos at a time (the rows are never whole in memory)."""
    total = np.zeros(rows.shape[1:])
    for lo in range(0, len(weights), block):
        total = total + weights[lo : lo + block] @ np.asarray(rows[lo : lo + block], dtype=np.float64)
    return total / weights.sum()


@dataclass
class FinalModel:
    coef: np.ndarray  # (1434, p) raw-input coefficients (scikit-learn's coef_ layout)
    raw_intercept: np.ndarray  # (1434,) true intercept for raw inputs, in the target space
    mesh_intercept: np.ndarray  # (1434,) intercept that yields a mesh (adds the mean neutral for target=neutral)
    feature_columns: list[str]
    n_components: int
    model: PLSFit

    def release_arrays(self, reference: dict[str, np.ndarray], metadata: dict[str, Any]) -> dict[str, np.ndarray]:
        """This fit as the card's NPZ arrays (:func:`aumesh.model.release.release_arrays`; the card's text comes with
        the release stage), in the frame of ``reference`` (prepare's :func:`~aumesh.pipeline.integrity.load_reference`)."""
        return release_arrays(
            self.coef,
            self.mesh_intercept,
            self.feature_columns,
            self.n_components,
            reference,
            card_text="",
            metadata=metadata,
        )


def final_fit(prepared: Prepared, cfg: Config, stats: FoldStatistics, model: PLSFit) -> FinalModel:
    """Card: final fit on all kept frames (``model``, fitted on ``stats.total``: :func:`fit_models`), as released."""
    A = effective_n_components(cfg)
    mesh_intercept = model.raw_intercept_.copy()
    # a target relative to per-video centres predicts displacements from them; released meshes add the
    # population's (frame-weighted) mean centre, so `x @ coef + intercept` is a face. For `within` that is
    # the population intercept mean mesh - mean design @ slopes.
    weights = prepared.videos.count.astype(np.float64)
    if stats.y_offset is not None:
        mesh_intercept += _weighted_mean(stats.y_offset, weights)
    if stats.x_offset is not None:
        mesh_intercept -= model.coef_ @ _weighted_mean(stats.x_offset, weights)
    return FinalModel(
        coef=model.coef_.copy(),
        raw_intercept=model.raw_intercept_.copy(),
        mesh_intercept=mesh_intercept,
        feature_columns=feature_columns(cfg.features.pose, cfg.features.interactions),
        n_components=A,
        model=model,
    )


def au_field_reliability(alone: list[PLSFit]) -> np.ndarray:
    """Per-AU mean cosine between the AU fields of the models fitted on each fold alone (disjoint videos), (20,)."""
    return reliability.field_cosines(np.stack([model.coef_ for model in alone]), np.arange(len(AU_COLUMNS)))


def facs_passes(prepared: Prepared, final: FinalModel) -> int:
    """Number of AUs of the final model whose direction passes the FACS check (``aumesh.card.directions``)."""
    from aumesh.card import directions

    report = directions.au_direction_report(
        {
            "coef": final.coef.T,
            "input_columns": np.array(final.feature_columns),
            "mean_aligned_mesh": prepared.reference["mean_aligned_mesh"],
        }
    )
    return int(report["summary"]["pass"])


def evaluate_statistics(prepared: Prepared, cfg: Config, stats: FoldStatistics) -> tuple[CVResult, FinalModel]:
    """Cross-validation, the final fit and the AU-field checks of one configuration from its statistics."""
    fits = fit_models(cfg, stats)
    cv = cross_validate(prepared, cfg, stats, fits.folds)
    final = final_fit(prepared, cfg, stats, fits.final)
    cv.au_reliability = au_field_reliability(fits.alone)
    cv.n_aus_facs_pass = facs_passes(prepared, final)
    return cv, final


def evaluate(prepared: Prepared, cfg: Config) -> tuple[CVResult, FinalModel]:
    """Cross-validation and the final fit for one configuration (the stage's one typed call), the passes on
    the ``compute`` group's scheduler."""
    with compute.engine(cfg.compute, **workers_check(prepared)):
        video_fold = video_folds(prepared.videos.count, cfg.cv.n_splits)
        return evaluate_statistics(prepared, cfg, accumulate(prepared, cfg, video_fold))


# ------------------------------------------------------------------------------------------- degenerate inputs
def constant_inputs(prepared: Prepared) -> dict[str, float]:
    """The AU and pose columns with one value in every prepared frame (column -> that value), from the row groups'
    min/max statistics in ``frames.parquet``'s footer (no pass over the data; a column without statistics is read).

    Such a column carries no information. It stays in the design: its centred values are exactly 0 (the statistics
    shift a column constant in their first block by its value), so the engine, as scikit-learn does, gives it a zero
    standard deviation replaced by 1, no weight in any component and a coefficient of exactly 0 -- the model dropping it
    would fit, with the release's format (23 rows of ``coef``, 83 of ``coef_full``) unchanged. What changes is what
    is said: a console warning, an MLflow tag and the card (:func:`degenerate_inputs`).
    """
    path = prepared.directory / FRAMES_FILE
    md = pq.ParquetFile(path).metadata
    names = md.schema.to_arrow_schema().names
    out = {}
    for name in (*AU_COLUMNS, *POSE_COLUMNS):
        j = names.index(name)
        lo, hi = np.inf, -np.inf
        for g in range(md.num_row_groups):
            stats = md.row_group(g).column(j).statistics
            if md.row_group(g).num_rows == 0:
                continue
            if stats is None or not stats.has_min_max:
                values = pq.read_table(path, columns=[name]).column(0).to_numpy()
                lo, hi = (values.min(), values.max()) if len(values) else (np.inf, -np.inf)
                break
            lo, hi = min(lo, stats.min), max(hi, stats.max)
        if lo == hi:
            out[name] = float(lo) + 0.0  # parquet stores a min of 0.0 as -0.0
    return out


def degenerate_inputs(constant: dict[str, float], columns: list[str]) -> dict:
    """What the design's columns ``columns`` lose to the ``constant`` inputs: ``{"constant_inputs": {column: value},
    "constant_features": [design columns without variance], "pose_learned": bool}`` (a pose x AU product has no variance
    when its pose or its AU is 0 in every frame, or both are constant)."""
    dead = []
    for c in columns:
        if "*" in c:
            p, a = c.split("*")
            if (p in constant and a in constant) or constant.get(p) == 0.0 or constant.get(a) == 0.0:
                dead.append(c)
        elif c in constant:
            dead.append(c)
    pose_features = [c for c in columns if c in POSE_COLUMNS or "*" in c]
    return {
        "constant_inputs": dict(constant),
        "constant_features": dead,
        "pose_learned": bool(pose_features) and any(c not in dead for c in pose_features),
    }
