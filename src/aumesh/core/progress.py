"""Progress bars for long work (tqdm on stderr), silent when stderr is not a terminal.

Logs, CI, ``dvc queue`` workers and captured test output get no bar; ``dvc repro`` in a terminal
passes the stage's stderr through, so the bars show there.
"""

from __future__ import annotations

import sys


def bar(total: int | None, desc: str, unit: str = "rows"):
    """A tqdm bar of ``total`` ``unit`` on stderr; disabled (no output at all) when stderr is not a terminal."""
    from tqdm.auto import tqdm

    return tqdm(
        total=total,
        desc=desc,
        unit=unit,
        unit_scale=unit == "rows",
        leave=False,
        dynamic_ncols=True,
        disable=not sys.stderr.isatty(),
    )
