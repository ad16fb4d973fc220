"""What the prepare stage's ``summary.json`` records besides its counts: the inputs' ranges and the files' checksums.

Pass 4, :func:`input_ranges`: each input's range over the kept frames (the ones the model is fitted on), from pass 3's
per-partition kept metadata, for the release's record of what its data supports (:mod:`aumesh.model.support`);
:func:`checksums`: the prepared files' records that evaluate and release verify (:mod:`aumesh.pipeline.integrity`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from aumesh.core.schema import AU_COLUMNS, INPUT_COLUMNS, N_TARGETS
from aumesh.model import support
from aumesh.pipeline import compute, integrity
from aumesh.pipeline.prepare.staging import read_staged
from aumesh.pipeline.prepared_files import FRAMES_FILE, MESHES_FILE, NEUTRAL_FILES, REFERENCE_FILE, VIDEO_IDS_FILE
from aumesh.pipeline.quantiles import exact_column_quantiles


def _kept_inputs(path: Path) -> np.ndarray:
    """(n_kept, 23) float64 input columns of a partition's kept metadata (pass 3's ``parts/<i>.arrow``)."""
    table = read_staged(path, list(INPUT_COLUMNS))
    return np.column_stack([table.column(c).to_numpy().astype(np.float64) for c in INPUT_COLUMNS]).reshape(
        table.num_rows, len(INPUT_COLUMNS)
    )


def _active_counts(path: Path) -> np.ndarray:
    """(21,) int64: the partition's kept frames with each AU above :data:`aumesh.model.support.ACTIVE_AU`, then its
    kept frames."""
    table = read_staged(path, list(AU_COLUMNS))
    counts = [int((table.column(a).to_numpy() > support.ACTIVE_AU).sum()) for a in AU_COLUMNS]
    return np.array([*counts, table.num_rows], np.int64)


def input_ranges(parts: list[Path]) -> dict[str, dict[str, float | None]]:
    """Each input's range record (:func:`aumesh.model.support.range_record`) over the kept frames of ``parts``
    (pass 3's per-partition metadata files, in order).

    The quantiles are :func:`aumesh.pipeline.quantiles.exact_column_quantiles` of the 23 columns: ``np.quantile`` of
    each column over every kept frame, bit for bit, never gathered, the 23 columns in the same three passes (counts
    and ranges, a histogram, a gather of the needed bins); ``min`` and ``max`` are the 0 and 1 quantiles. The active
    fractions are one more pass of counts.

    Returns
    -------
    dict
        ``{name: {"min", "p1", "p50", "p99", "max", "active_fraction"}}`` for the 23
        :data:`~aumesh.core.schema.INPUT_COLUMNS` (``active_fraction`` None for pose).
    """
    q = np.array(list(support.RANGE_QUANTILES.values()))
    counts = compute.map_reduce(_active_counts, np.add, parts)
    quantiles = exact_column_quantiles(_kept_inputs, parts, q)
    n = max(int(counts[-1]), 1)
    return {
        name: support.range_record(quantiles[j], float(counts[j] / n) if name in AU_COLUMNS else None)
        for j, name in enumerate(INPUT_COLUMNS)
    }


def checksums(directory: Path, mesh_digests: dict[int, tuple[int, int, str]], mesh_offset: int) -> dict[str, dict]:
    """The files' checksums for ``summary.json`` (:mod:`aumesh.pipeline.integrity`): ``meshes.npy`` from the digests
    pass 3 computed while writing its rows (plus its header), the others read back once (small: per video, or the
    frames' metadata)."""
    row_bytes = N_TARGETS * np.dtype(np.float32).itemsize
    blocks = [(0, mesh_offset, integrity.hash_range(directory / MESHES_FILE, 0, mesh_offset))]
    blocks += [
        (mesh_offset + a * row_bytes, mesh_offset + b * row_bytes, h) for a, b, h in mesh_digests.values() if b > a
    ]
    records = {MESHES_FILE: integrity.file_record(directory / MESHES_FILE, blocks)}
    for name in (FRAMES_FILE, VIDEO_IDS_FILE, *NEUTRAL_FILES.values(), REFERENCE_FILE):
        records[name] = integrity.file_record(directory / name)
    return records
