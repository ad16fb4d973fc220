"""Each video's frames once, across every file of ``data/``, named in the user's files (not the ingested tables).

A video is py-feat's ``input`` path as written (or ``video_id``): the same path in two files, or written twice in one,
with the same frame numbers is the same frames twice (an export copied or appended again). The ingest's tasks each see
a part of the files, so each records, per video and source file, the range of frame numbers it kept
(:data:`FrameRanges`: a few numbers a video, never a frame list); ranges of one video that overlap across files (or
within a file out of order) are then checked frame by frame on those files only (:func:`duplicates`), and a frame
kept twice is one line naming the files, the video and the frame.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from aumesh.core.errors import TableError

#: video -> ``[(source path, first frame, last frame), ...]`` of the frames kept, in the order they were read.
FrameRanges = dict[str, list[tuple[str, int, int]]]


def block_ranges(video: np.ndarray, frame: np.ndarray, where: str) -> FrameRanges:
    """The frame ranges of a block's kept rows (one per frame), after checking that no (video, frame) repeats in it.

    Raises
    ------
    TableError
        A frame of a video kept twice within the block (its rows written again further down the file).
    """
    if not len(frame):
        return {}
    names, code = np.unique(np.asarray(video, dtype=str), return_inverse=True)
    order = np.lexsort((frame, code))
    same = (np.diff(code[order]) == 0) & (np.diff(frame[order]) == 0)
    if same.any():
        row = order[np.flatnonzero(same)[0]]
        raise _repeated(str(video[row]), int(frame[row]), [where], int(same.sum()))
    lo = np.full(len(names), np.iinfo(np.int64).max)
    hi = np.full(len(names), np.iinfo(np.int64).min)
    np.minimum.at(lo, code, frame)
    np.maximum.at(hi, code, frame)
    return {str(v): [(where, int(a), int(b))] for v, a, b in zip(names, lo, hi, strict=True)}


def merge_into(target: FrameRanges, ranges: FrameRanges) -> FrameRanges:
    """``ranges`` added after ``target``'s, in place; a range continuing the last one of its video from the same file
    (its first frame after the last one's last) extends it, so a video read in order is one range per file. The
    lists of ``target`` are its own (``ranges``' are never changed nor shared): adding task after task stays linear."""
    for v, added in ranges.items():
        mine = target.get(v)
        if mine is None:
            mine = target[v] = []
        for where, lo, hi in added:
            if mine and mine[-1][0] == where and lo > mine[-1][2]:
                mine[-1] = (where, mine[-1][1], hi)
            else:
                mine.append((where, lo, hi))
    return target


def overlapping(ranges: FrameRanges) -> dict[str, list[str]]:
    """video -> every file holding its frames (sorted), for the videos whose ranges overlap."""
    out: dict[str, list[str]] = {}
    for v, r in ranges.items():
        if len(r) < 2:
            continue
        r = sorted(r, key=lambda x: (x[1], x[2]))
        reach, clash = r[0][2], False
        for _, lo, hi in r[1:]:
            clash |= lo <= reach
            reach = max(reach, hi)
        if clash:
            out[v] = sorted({w for w, _, _ in r})
    return out


def duplicates(video: str, frames: Mapping[str, Sequence[np.ndarray]]) -> TableError | None:
    """The error for ``video``'s frames kept twice, given each file's kept frames of it (one array per read block), or
    None when no frame repeats (overlapping ranges of interleaved frames)."""
    where = sorted(frames)
    every = [np.concatenate(list(frames[w])) if len(frames[w]) else np.zeros(0, np.int64) for w in where]
    owner = np.repeat(np.arange(len(where)), [len(f) for f in every])
    allf = np.concatenate(every) if every else np.zeros(0, np.int64)
    order = np.argsort(allf, kind="stable")
    same = np.flatnonzero(np.diff(allf[order]) == 0)
    if not len(same):
        return None
    first = int(allf[order[same[0]]])
    files = sorted({where[owner[order[k]]] for k in same} | {where[owner[order[k + 1]]] for k in same})
    return _repeated(video, first, files, len(same))


def _repeated(video: str, frame: int, files: Sequence[str], n: int) -> TableError:
    shown = ", ".join(files[:3]) + (f" and {len(files) - 3} more" if len(files) > 3 else "")
    twice = "in both" if len(files) == 2 else "twice" if len(files) == 1 else "in several"
    return TableError(
        f"{shown}: frame {frame} of video {video!r} is written {twice} ({n} such (video_id, frame) pair(s)): the same "
        f"video's frames "
        f"twice (an export copied or appended again). Fix: remove the repeated rows or file; if they are different "
        f"videos, keep the path each was read from in py-feat's 'input' (or give each its own video_id)."
    )
