"""Which face of a frame is the video's person when the largest-face rule cannot tell: the face followed over time.

py-feat writes one row per detected face (the rows of a frame consecutive). ``data.face_selection=largest`` keeps the
largest face box of a frame; with two faces of about the same size (the second's box area at least
:data:`AMBIGUOUS_AREA_RATIO` of the largest's: an *ambiguous* frame) the largest flips between the two people from
frame to frame, and a video's targets would mix them. In an ambiguous frame the face kept is the one that continues
the video's track, the face kept in its previous frame with a face:

1. the face with the track's py-feat ``Identity`` (``Fex.compute_identities``: "Person_<k>" clustered on the face
   embeddings of the whole ``detect`` call, so a label names one person within a video), where py-feat wrote one;
2. else, or when no face has it, the face whose box centre is nearest the track's (distance over the track box's
   side): ``FaceRectX/Y/Width/Height``, else the mesh's x/y extent;
3. a video's first face frame has no track: its largest face (ties: the first row), as without tracking.

A frame the rule can tell (one face, or a clearly largest one) keeps that face, as before, and the track follows it.
The choice in a frame depends only on the frames of its video since the last frame the rule could tell, so a reader
that starts a range at such a frame (:func:`aumesh.data.readers.csv_spans`) gives the same rows as one pass over the
file, however the ranges are packed into tasks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: A frame is ambiguous when its second largest face box has at least this fraction of the largest's area (0.8: the
#: sides within ~11 %, closer than py-feat's boxes of one face vary from frame to frame).
AMBIGUOUS_AREA_RATIO = 0.8


@dataclass(frozen=True)
class Face:
    """The face a video's track last kept: its box centre (x, y), side (sqrt of the area) and py-feat Identity."""

    centre: tuple[float, float]
    side: float
    identity: str | None


#: py-feat's Identity of a face its clustering put in no cluster (``feat.utils.stats.cluster_identities``, method
#: "hdbscan": noise is "Unknown"): not a person, so two "Unknown" faces are not one track.
UNKNOWN_IDENTITY = "Unknown"


def label(value: object) -> str | None:
    """py-feat's Identity of a row as text, None where it has none (NaN, None, "", py-feat's "Unknown")."""
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return None
    text = str(value)
    return text if text and text.lower() != "nan" and text != UNKNOWN_IDENTITY else None


def choose(
    rows: np.ndarray,
    centres: np.ndarray,
    areas: np.ndarray,
    identity: np.ndarray | None,
    track: Face | None,
) -> int:
    """The row of ``rows`` (one frame's ambiguous candidates, in file order) that continues ``track``.

    Parameters
    ----------
    rows : (k,) int, k >= 2, the candidate rows.
    centres : (n, 2) box centres of every row of the block; areas : (n,) box areas.
    identity : (n,) py-feat's Identity of every row, or None without the column.
    track : the face kept in the video's previous face frame; None: the largest (ties: the first row).
    """
    if track is None:
        return int(rows[np.argmax(areas[rows])])
    pool = rows
    if identity is not None and track.identity is not None:
        same = rows[[label(identity[r]) == track.identity for r in rows]]
        pool = same if len(same) else rows
    distance = np.hypot(*(centres[pool] - np.asarray(track.centre)).T) / max(track.side, 1e-9)
    distance = np.where(np.isfinite(distance), distance, np.inf)
    best = np.lexsort((pool, -areas[pool], distance))[0]  # nearest; ties: the larger, then the first row
    return int(pool[best])


def follow(
    video: np.ndarray,
    groups: np.ndarray,
    largest: np.ndarray,
    candidate: np.ndarray,
    areas: np.ndarray,
    centres: np.ndarray,
    identity: np.ndarray | None,
    tracks: dict[str, Face],
) -> tuple[np.ndarray, int]:
    """The row kept in each frame: the largest candidate where the frame is not ambiguous, the track's face where it
    is (module docstring); and the number of ambiguous frames.

    Parameters
    ----------
    video : (n,) each row's video; groups : (g + 1,) starts of the frames' runs of rows, and n.
    largest : (g,) each frame's largest candidate row (the largest-face rule).
    candidate : (n,) bool rows that may be kept (``identity`` selection: the subject's faces only).
    areas, centres, identity : as :func:`choose`.
    tracks : video -> the face its track last kept, carried from the block before (updated in place: the last face
        kept of each video of this block).
    """
    chosen = largest.copy()
    n_frames = len(largest)
    if not n_frames:
        return chosen, 0
    big = np.where(candidate, areas, -np.inf)
    top = big[largest]
    near = candidate & np.isfinite(big) & (big >= AMBIGUOUS_AREA_RATIO * np.repeat(top, np.diff(groups)))
    ambiguous = np.add.reduceat(near.astype(np.int64), groups[:-1]) >= 2
    for g in np.flatnonzero(ambiguous):
        start, stop = groups[g], groups[g + 1]
        v = video[start]
        if g > 0 and video[groups[g - 1]] == v:
            before = chosen[g - 1]
            track = _face(before, centres, areas, identity) if candidate[before] else None
        else:
            track = tracks.get(str(v))
        chosen[g] = choose(np.arange(start, stop)[near[start:stop]], centres, areas, identity, track)
    last = np.r_[video[groups[1:-1]] != video[groups[:-2]], True] if n_frames > 1 else np.ones(1, bool)
    for g in np.flatnonzero(last):  # each video's last frame of the block: the track the next block starts from
        row = chosen[g]
        if candidate[row]:
            tracks[str(video[row])] = _face(row, centres, areas, identity)
    return chosen, int(ambiguous.sum())


def _face(row: int, centres: np.ndarray, areas: np.ndarray, identity: np.ndarray | None) -> Face:
    return Face(
        (float(centres[row, 0]), float(centres[row, 1])),
        float(np.sqrt(max(areas[row], 0.0))),
        None if identity is None else label(identity[row]),
    )
