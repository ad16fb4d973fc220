"""Where the ``aumesh`` command writes besides its results on stdout: one-line messages on stderr that survive a
reader that is gone (:func:`say`), and the library's log records on whatever stderr is at the time
(:func:`configure_logging`). The command's modules print through these; the library below ``cli/`` never prints.
"""

from __future__ import annotations

import logging
import sys


def say(text: str) -> None:
    """Print to stderr; a reader that is gone (DVC killed, its pipe closed) is no reason for a traceback."""
    try:
        print(text, file=sys.stderr, flush=True)
    except (OSError, ValueError):
        pass


class StderrHandler(logging.StreamHandler):
    """A handler on whatever ``sys.stderr`` is when a record is written: a handler bound to the stream of its time
    writes into a closed stream once that is replaced (a second ``main()`` in one process, as in the tests)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler.__init__ assigns it
        pass


def configure_logging(level: int) -> None:
    """``logging.basicConfig`` (the root logger, configured only when nothing configured it), on :class:`StderrHandler`."""
    root = logging.getLogger()
    if root.handlers:
        return
    handler = StderrHandler()
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root.addHandler(handler)
    root.setLevel(level)
