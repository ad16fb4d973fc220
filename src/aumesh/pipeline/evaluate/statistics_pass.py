"""Pass A of the evaluate stage: one pass over the prepared meshes that accumulates, per fold, the cross-products of
the full design with the absolute coordinates, and per video the sums every target's centres come from
(:func:`design_statistics`); :func:`accumulate` derives a configuration's :class:`FoldStatistics` from them exactly
(``aumesh.model.statistics``), so a sweep needs this pass once. Its tasks also hash the bytes of ``meshes.npy`` they
read; the driver compares the digests with prepare's checksums before any model is fitted
(``aumesh.pipeline.integrity``).
"""

from __future__ import annotations

import shutil
import weakref
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from aumesh.config import Config
from aumesh.core.io import (
    NpyRowFile,
    NpyRows,
    RowArray,
    create_npy,
    read_rows,
    row_runs,
    scratch_directory,
    write_rows,
)
from aumesh.core.schema import AU_COLUMNS, N_TARGETS, POSE_COLUMNS, instrument_columns
from aumesh.model.cross_products import CrossProducts
from aumesh.model.statistics import (
    FULL_DESIGN,
    DesignStatistics,
    DesignSums,
    VideoSumStream,
    design_union,
    extra_inputs,
    fold_configuration_statistics,
    fold_within_statistics,
    head_width,
    pass_design,
    pose_moments,
    target_offsets,
    within_statistics,
)
from aumesh.pipeline import compute, integrity
from aumesh.pipeline.evaluate.prepared_data import (
    BLOCK_ROWS,
    Prepared,
    block_rows,
    fold_grouped_block,
    read_columns,
    read_group,
)
from aumesh.pipeline.evaluate.results import FoldStatistics
from aumesh.pipeline.prepared_files import FRAMES_FILE, MESHES_FILE, scratch_path


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


def video_sums(instruments: Sequence[str] = (), columns: Sequence[str] | None = None) -> dict[str, int]:
    """:data:`VIDEO_SUMS` with the design's width: the union ``columns``' (:func:`aumesh.model.statistics.design_union`;
    default :data:`FULL_DESIGN`), plus :data:`FULL_DESIGN`'s again with instruments (the augmented design
    ``[X | Z | rest]``, :func:`aumesh.model.statistics.pass_design`)."""
    if not instruments and columns is None:
        return VIDEO_SUMS
    width = len(FULL_DESIGN if columns is None else columns) + (len(FULL_DESIGN) if instruments else 0)
    return {name: width if name != "video_sum_y" else w for name, w in VIDEO_SUMS.items()}


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
    instruments: Sequence[str] = (),
    columns: Sequence[str] | None = None,
) -> DesignPart:
    """Pass A on one row group of the prepared data: per-fold sums of the full design with the absolute
    coordinates (shifted by ``a``, ``b``), and the per-video sums; those of videos held whole by this
    partition are written to ``scratch`` as each video finishes, those of videos split across partitions returned.
    The checksummed blocks of ``meshes.npy`` the row group holds (``check``) are hashed from the bytes read, for the
    driver to compare (:meth:`aumesh.pipeline.integrity.StreamedCheck.check`). With ``instruments`` (the second
    detector's AU columns) the design is the augmented ``[X | Z]`` (:func:`aumesh.model.statistics.augmented_design`; ``a`` of its width).
    ``columns``: the union of the designs the pass serves (:func:`aumesh.model.statistics.design_union`; default
    :data:`FULL_DESIGN`); the other families' inputs are read by name."""
    g, start, stop = group
    digests = integrity.RangeDigests(check.ranges(g), check.algorithm) if check is not None else None
    au, pose, video, low = read_group(directory, g)
    instrument_au = read_columns(directory, g, instruments) if instruments else None
    union = list(FULL_DESIGN if columns is None else columns)
    names = extra_inputs(union)
    inputs = read_columns(directory, g, names) if names else None
    fold = video_fold[video]
    widths = video_sums(instruments, columns)
    p, q = widths["video_sum_x"], N_TARGETS
    sums = DesignSums(p, q, n_splits, head_width(union, bool(instruments)))
    split: dict[int, tuple[np.ndarray, ...]] = {}
    finished: dict[str, dict[int, np.ndarray]] = {name: {} for name in widths}  # whole videos, until written

    def done(name: str):
        k = list(widths).index(name)

        def store(v: int, total: np.ndarray, _n_rows: int) -> None:
            if split_video[v]:  # a split video without low-AU rows here adds zeros for them
                values = split.setdefault(v, tuple(np.zeros(width) for width in widths.values()))
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
        files = {name: stack.enter_context(NpyRowFile(scratch / f"{name}.npy", writable=True)) for name in widths}
        for lo in range(start, stop, chunk_rows):
            rows, _, Y = fold_grouped_block(meshes, raw, lo, min(lo + chunk_rows, stop), start, fold, n_splits)
            if digests is not None:
                _hash_block(digests, meshes, rows + start, Y)
            X = pass_design(
                au[rows],
                pose[rows],
                None if instrument_au is None else instrument_au[rows],
                union,
                None if inputs is None else inputs[rows],
                names,
            )
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


def design_statistics(
    prepared: Prepared,
    video_fold: np.ndarray,
    n_splits: int,
    chunk_rows: int,
    instruments: Sequence[str] = (),
    columns: Sequence[str] | None = None,
) -> DesignStatistics:
    """Pass A: per-fold statistics of the full design with absolute coordinates (one pass, every configuration).

    ``video_fold`` (n_videos,) is each video's fold (:func:`aumesh.pipeline.evaluate.video_folds`). The provisional
    shift ``(a, b)`` is the mean of the first :data:`~aumesh.pipeline.evaluate.prepared_data.BLOCK_ROWS` rows (a centre, not a
    statistic: reading ``chunk_rows`` rows for it cost the stage 0.2 s of fresh memory), shared by every fold and
    partition. The per-video sums stay on disk
    (:class:`aumesh.core.io.NpyRows`) in a scratch folder beside the prepared data, removed with the returned
    statistics.

    ``instruments`` (``model/eiv=instruments``: the second detector's AU columns of ``frames.parquet``): the
    statistics are of the augmented design ``[X | Z]`` (:func:`aumesh.model.statistics.augmented_design`), so every fold's within-video
    ``Z'X``, ``Z'Z``, ``Z'Y`` follow exactly (:func:`aumesh.model.statistics.fold_within_statistics`); without them
    nothing changes (the same arrays, the same bits).

    ``columns``: the union of the designs of every configuration the pass serves
    (:func:`aumesh.model.statistics.design_union`: the stage's AU model and its families, or every configuration of a
    sweep; default :data:`FULL_DESIGN`). The AU design's products are the same bits whatever else is accumulated
    (:class:`aumesh.model.statistics.DesignSums`' head); each configuration takes its columns by name.
    """
    n_videos = len(prepared.video_ids)
    videos = prepared.videos
    first = min(BLOCK_ROWS, prepared.n_frames)
    instruments = tuple(instruments)
    union = list(FULL_DESIGN if columns is None else columns)
    names = extra_inputs(union)
    check_instrument_columns(prepared, instruments)
    check_family_columns(prepared, union)
    head = _head(prepared, first, (*instruments, *names))
    a = pass_design(
        head[list(AU_COLUMNS)].to_numpy(np.float64),
        head[list(POSE_COLUMNS)].to_numpy(np.float64),
        head[list(instruments)].to_numpy(np.float64) if instruments else None,
        union,
        head[names].to_numpy(np.float64) if names else None,
        names,
    ).mean(axis=0)
    assert prepared.mesh_path is not None  # load_prepared sets it
    b = read_rows(prepared.mesh_path, 0, first).astype(np.float64).mean(axis=0)
    scratch = scratch_directory(scratch_path(prepared.directory))
    try:
        widths = video_sums(instruments, columns)
        for name, width in widths.items():
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
                instruments=instruments,
                columns=columns,
            ),
            DesignPart.__add__,
            prepared.row_groups(),
            desc="evaluate: statistics",
        )
        if prepared.mesh_check is not None:  # the bytes just read are prepare's, or the stage stops before any fit
            prepared.mesh_check.check(part.digests)
        for v, values in part.split.items():
            for name, row in zip(widths, values, strict=True):
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
        instruments=instruments,
        columns=tuple(union),
    )
    design.neutral_design = {  # mean design row of each video's neutral frames, per neutral method
        "low_au": NeutralDesign(NpyRows(scratch / "video_low_sum_x.npy"), videos.low_count, a),
        "mean": NeutralDesign(design.video_sum_x, design.video_count, a),
    }
    weakref.finalize(design, shutil.rmtree, scratch, True)
    return design


def check_instrument_columns(prepared: Prepared, instruments: Sequence[str]) -> None:
    """The ``model/eiv=instruments`` columns are in ``frames.parquet``, or one line naming the file, the columns and
    the fix (data prepared under another ``model.eiv.instrument_aus``: ingest and prepare carry only the configured
    columns)."""
    if not instruments:
        return
    from aumesh.core.errors import ConfigError

    path = prepared.directory / FRAMES_FILE
    missing = [c for c in instruments if c not in pq.read_schema(path).names]
    if missing:
        raise ConfigError(
            f"{path}: no column {', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''} for model/eiv=instruments "
            f"({len(missing)} of {len(instruments)} missing): the data was prepared without them. Fix: rerun ingest "
            "and prepare with the same model.eiv.instrument_aus (`dvc repro` does, or `aumesh ingest && aumesh prepare`)"
        )


def check_family_columns(prepared: Prepared, columns: Sequence[str]) -> None:
    """The inputs of the union's designs are in ``frames.parquet``, or one line naming the file, the family and the fix
    (contract item 1 of issue 46: a family absent from the source tables is absent from the prepared frames)."""
    names = extra_inputs(columns)
    if not names:
        return
    from aumesh.core.errors import ConfigError
    from aumesh.core.families import FAMILIES

    path = prepared.directory / FRAMES_FILE
    present = set(pq.read_schema(path).names)
    for family, inputs in FAMILIES.items():
        missing = [c for c in inputs if c in names and c not in present]
        if missing:
            raise ConfigError(
                f"{path}: no {family} columns ({', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''}; "
                f"{len(missing)} of {len(inputs)} missing), so the {family} family cannot be fitted. Fix: ingest tables "
                f"that carry them (py-feat's MPDetector or Detectorv2 write all {len(inputs)}) and rerun ingest and "
                f"prepare (`aumesh synth --families` writes synthetic tables with them)"
            )


def pass_columns(cfg: Config, feature_sets: Sequence[str] = ()) -> list[str]:
    """The union of the designs a run needs (:func:`aumesh.model.statistics.design_union`): ``cfg.features``' and each
    of ``feature_sets`` (the stage's ``families.<f>.features``, or a sweep's ``features`` options)."""
    return design_union([cfg.features.name, *feature_sets])


def _head(prepared: Prepared, n: int, instruments: Sequence[str] = ()) -> pd.DataFrame:
    """The first ``n`` rows of ``frames.parquet`` (AU and pose columns, and the ``instruments``)."""
    batches = pq.ParquetFile(prepared.directory / FRAMES_FILE).iter_batches(
        batch_size=n, columns=[*AU_COLUMNS, *POSE_COLUMNS, *instruments]
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
    is each video's fold (:func:`aumesh.pipeline.evaluate.video_folds`).

    ``design`` (from :func:`design_statistics` with the same folds, any union holding ``cfg.features.columns``) is
    reused when given: then no pass over the meshes is needed (aumesh.model.statistics derives every configuration
    from it, its columns taken by name).
    """
    instruments = instrument_columns(cfg.model.eiv.instrument_aus)  # () unless model/eiv=instruments
    if instruments and cfg.features.family != "au":
        from aumesh.core.errors import ConfigError

        raise ConfigError(
            f"model/eiv=instruments corrects the AU detector's noise, but features={cfg.features.name} is the "
            f"{cfg.features.family} family. Fix: model/eiv=none for features={cfg.features.name}"
        )
    if design is None:
        columns = None if cfg.features.family == "au" else pass_columns(cfg)
        design = design_statistics(
            prepared, video_fold, cfg.cv.n_splits, chunk_rows or cfg.data.chunk_rows, instruments, columns
        )
    elif not np.array_equal(design.video_fold, video_fold):
        raise ValueError("accumulate: the design statistics were built with other folds")
    elif instruments and design.instruments != instruments:  # without instruments any pass serves (by name)
        raise ValueError("accumulate: the design statistics were built with other instrument columns")
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
    pose_mean, pose_second = pose_moments(design)
    return FoldStatistics(
        target=target,
        displacement=displacement,
        video_fold=video_fold,
        x_offset=x_offset,
        y_offset=y_offset,
        # the identification screen's moments, every target (a pass without the AU design has none)
        au_within=within_statistics(design, list(AU_COLUMNS)) if set(AU_COLUMNS) <= set(design.columns) else None,
        pose_mean=pose_mean,
        pose_second=pose_second,
        instruments=instrument_statistics(design, cfg.features.columns) if instruments else None,
    )


def instrument_statistics(design: DesignStatistics, columns: list[str]) -> list[CrossProducts]:
    """Per fold, the within-video statistics of the augmented design ``[X | Z]`` of ``columns`` with the mesh
    (:func:`aumesh.model.statistics.augmented_index`: the configuration's columns, then their instruments), the folds
    at once on this machine's cores; training sets are total - fold (docs/method.md eq. 7)."""
    idx = design.augmented_index(columns)
    return compute.local_map(partial(fold_within_statistics, design, idx=idx), range(len(design.folds)))
