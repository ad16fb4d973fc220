"""The files of the prepared data (``paths.prepared_dir``): what ``prepare`` writes and ``evaluate``, ``release`` and
sweeps read, named in one place.

A module of names only: the stages that read the prepared data import it without the ``prepare`` stage's own
imports (its data contract pulls in pandera and pandas' typing, ~0.2 s of every evaluate).
"""

from __future__ import annotations

from pathlib import Path

#: (n_frames, 1434) float32, axis-major aligned meshes, ``frames.parquet``'s row order.
MESHES_FILE = "meshes.npy"
#: Each kept frame's video_id, frame, AUs, pose, video_index and low_au flag; a row group per partition of the passes.
FRAMES_FILE = "frames.parquet"
#: (n_videos,) the kept videos' ids, sorted (``video_index`` indexes it).
VIDEO_IDS_FILE = "video_ids.npy"
#: Per-video neutral meshes, (n_videos, 1434) float32, by ``preprocess.neutral.method``.
NEUTRAL_FILES = {"mean": "neutral_mean.npy", "low_au": "neutral_low_au.npy"}
#: Reference anchors of the alignment, their indices, the population's mean and low-AU mean meshes.
REFERENCE_FILE = "reference.npz"
#: What the filters kept and dropped (counts, fractions), the frames and videos kept.
SUMMARY_FILE = "summary.json"
PREPARED_FILES = (MESHES_FILE, FRAMES_FILE, VIDEO_IDS_FILE, *NEUTRAL_FILES.values(), REFERENCE_FILE, SUMMARY_FILE)


def scratch_path(prepared_dir: str | Path) -> Path:
    """What the passes' scratch folders (per-video sums, each frame's error) are the temporaries of: a sibling of the
    prepared data (``.evaluate-scratch.tmp-<pid>-<host>-*``, :func:`aumesh.core.io.scratch_directory`), so a killed
    run's are removed when the next evaluate stage starts."""
    return Path(prepared_dir).parent / "evaluate-scratch"
