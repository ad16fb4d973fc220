"""The prepare stage's scratch files: what its passes stage per partition for the next ones, and their readers.

Pass 1 stages each partition's validated metadata (with each row's table, ``piece``, and ``wild`` flag) and the anchors
of every row, so the tables are parsed and validated once; pass 2 stages each pose-passing frame's residual, AU sum,
video code and similarity transform (``<i>.pass2.npz``); pass 3 writes each partition's kept metadata in the same
Arrow format (``parts/<i>.arrow``). Files are named by the partition's index inside the run's own scratch folder
(absolute paths: workers elsewhere read and write them). The per-partition values of the stage's exact quantiles
(:func:`aumesh.pipeline.quantiles.exact_quantiles`: residuals, |pose|, kept AU sums) are read here too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather

from aumesh.core.io import load_npz, read_row_set
from aumesh.pipeline.prepare.selection import Candidates, keep_mask


def write_staged(table: pa.Table, path: Path) -> None:
    """A table the stage reads back itself (scratch, the partitions' kept metadata): Arrow IPC, uncompressed
    (written and read at memory speed; parquet's encoding and compression cost seconds a pass at 344k frames)."""
    feather.write_feather(table, path, compression="uncompressed")


def read_staged(path: Path, columns: list[str] | None = None) -> pa.Table:
    """A table :func:`write_staged` wrote (``columns``: only those). Memory-mapped: the uncompressed columns are read
    in place, not copied onto the task's heap. On the calling thread only, as every read of the passes (the partitions
    already run on every core; Arrow's own thread pool would only oversubscribe them, and a process interrupted while
    it works can hang in the pool's teardown at exit, as in apache/arrow#50482)."""
    return feather.read_table(path, columns=columns, memory_map=True, use_threads=False)


def staged_metadata_file(scratch: Path, i: int) -> Path:
    """Partition ``i``'s validated metadata (with the ``piece`` of each row), as pass 1 stages it."""
    return scratch / f"{i:06d}.arrow"


def staged_anchors_file(scratch: Path, i: int) -> Path:
    """Partition ``i``'s float32 anchors of every row, (n_rows, n_anchors, 3), as pass 1 stages them."""
    return scratch / f"{i:06d}.npy"


def staged_table(scratch: Path, i: int, columns: list[str] | None = None) -> pa.Table:
    """Partition ``i``'s validated metadata (with the ``piece`` of each row), as pass 1 staged it (``columns``: only
    those)."""
    return read_staged(staged_metadata_file(scratch, i), columns)


def anchors_in_table_order(scratch: Path, candidates: Candidates) -> np.ndarray:
    """(m, n_anchors, 3) float32 anchors of ``candidates`` in the tables' order
    (:meth:`aumesh.pipeline.prepare.selection.Candidates.in_table_order`: partition by partition), read from the
    partitions' staged anchors."""
    ordered = candidates.in_table_order()
    return np.concatenate(
        [read_row_set(staged_anchors_file(scratch, i), ordered.row[ordered.part == i]) for i in np.unique(ordered.part)]
    )


def pass2_file(scratch: Path, i: int) -> Path:
    """Partition ``i``'s arrays of pass 2 (an ``.npz``)."""
    return scratch / f"{i:06d}.pass2.npz"


def pass2(item: tuple[Path, int], *keys: str) -> list[np.ndarray]:
    """Arrays ``keys`` of partition ``item = (scratch, i)`` as pass 2 staged them
    (:func:`aumesh.pipeline.prepare.tasks.residual_partition`)."""
    return load_npz(pass2_file(*item), keys)


def staged_residuals(item: tuple[Path, int]) -> np.ndarray:
    """(n_pose,) float64: the max anchor residual of each pose-passing frame of partition ``item``."""
    return pass2(item, "residual")[0]


def staged_abs_pose(column: int, item: tuple[Path, int]) -> np.ndarray:
    """(n_rows,) float64: |Pitch|, |Yaw| or |Roll| (``column`` 0, 1, 2) of every row of partition ``item``."""
    return pass2(item, "abs_pose")[0][:, column].astype(np.float64)


def kept_au_sums(threshold: float | None, item: tuple[Path, int]) -> np.ndarray:
    """(n_kept,) float64: the AU sums of partition ``item``'s frames kept by the outlier cut (``threshold``)."""
    residual, au_sum = pass2(item, "residual", "au_sum")
    return au_sum[keep_mask(residual, threshold)]
