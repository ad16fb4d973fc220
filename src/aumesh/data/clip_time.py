"""A clip's frame rate from py-feat's ``approx_time`` (:func:`fps_from_approx_time`; :mod:`aumesh.data.clip`'s "Time").

py-feat writes ``approx_time`` as ``"MM:SS"``, the frame's time truncated to whole seconds
(``feat.data.VideoDataset.calc_approx_frame_time``); each row then bounds the frame rate, and the common rates in the
bounds tell it.
"""

from __future__ import annotations

import logging
import math
import re

import numpy as np

log = logging.getLogger(__name__)

#: The frame rate when ``approx_time`` does not tell one (and ``--fps`` is not given).
DEFAULT_FPS = 25.0
#: Frame rates video files have; ``approx_time`` (whole seconds) usually allows only one of them.
COMMON_FPS = (24000 / 1001, 24.0, 25.0, 30000 / 1001, 30.0, 48.0, 50.0, 60000 / 1001, 60.0, 100.0, 120.0)
_TIME = re.compile(r"^\s*(?:(\d+):)?(\d+):(\d+)(?:\.(\d+))?\s*$")


def _approx_seconds(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``approx_time`` values as ``(ok, lower, upper)``: each row's true time lies in ``[lower, upper)``. py-feat's
    ``"MM:SS"`` truncates to whole seconds (``[t, t + 1)``); ``"[HH:]MM:SS.fff"`` or numbers are taken to the last
    digit (``[t - r, t + r]``). None when a value is neither."""
    n = len(values)
    ok, lower, upper = np.zeros(n, bool), np.zeros(n), np.zeros(n)
    for i, v in enumerate(values):
        if v is None or (isinstance(v, float) and math.isnan(v)):
            continue
        if isinstance(v, (int, float, np.integer, np.floating)):
            t = float(v)
            r = 1.0 if float(t).is_integer() else 1e-3
            lo, hi = (t, t + 1.0) if r == 1.0 else (t - r, t + r)
        else:
            m = _TIME.match(str(v))
            if not m:
                return None
            h, mi, s, frac = m.groups()
            t = int(h or 0) * 3600 + int(mi) * 60 + int(s)
            if frac:
                r = 10.0 ** -len(frac)
                t += int(frac) * r
                lo, hi = t - r, t + r
            else:
                lo, hi = t, t + 1.0
        ok[i], lower[i], upper[i] = True, lo, hi
    return ok, lower, upper


def fps_from_approx_time(frame: np.ndarray, approx: np.ndarray) -> float | None:
    """The frame rate py-feat's ``approx_time`` implies, or None when it does not tell.

    Each row says ``lower <= frame / fps < upper`` (whole seconds for py-feat's ``"MM:SS"``), so ``fps`` lies in
    ``(max frame / upper, min frame / lower]``. Of the common rates (:data:`COMMON_FPS`: 23.976, 24, 25, 29.97, 30,
    48, 50, 59.94, 60, 100, 120) in that interval, the one nearest its middle; no common rate but an interval
    narrower than 1%: its middle, to 3 decimals. A clip shorter than a second bounds the rate only from below: then
    None (25) unless 25 is too slow for it. Contradictory values (another video's times) give None.

    With ``skip_frames`` a clip of a few minutes may not tell a rate from its NTSC neighbour (30 and 29.97 are 0.1%
    apart: 0.06 s in a minute); ``--fps`` settles it.
    """
    parsed = _approx_seconds(np.asarray(approx, dtype=object))
    if parsed is None:
        return None
    ok, lower, upper = parsed
    f = np.asarray(frame, np.float64)
    use = ok & (f > 0)
    if not use.any():
        return None
    lo = float(np.max(f[use] / upper[use]))
    bounded = use & (lower > 0)
    hi = float(np.min(f[bounded] / lower[bounded])) if bounded.any() else math.inf
    tol = 1e-9
    if lo >= hi * (1 + tol):
        log.warning("approx_time contradicts itself (frame rate above %.4g and at most %.4g): using 25 fps", lo, hi)
        return None
    candidates = [c for c in COMMON_FPS if c > lo * (1 + tol) and c <= hi * (1 + tol)]
    if math.isinf(hi):
        if DEFAULT_FPS > lo * (1 + tol):
            return None
        return candidates[0] if candidates else None
    if candidates:
        middle = (lo + hi) / 2
        return min(candidates, key=lambda c: abs(c - middle))
    return round((lo + hi) / 2, 3) if hi - lo <= 0.01 * hi else None


__all__ = ["COMMON_FPS", "DEFAULT_FPS", "fps_from_approx_time"]
