"""Text from outside the code (the user's configuration, the data, MLflow, ``promotion.json``) made safe for
``MODEL_CARD.md``: shown literally by every Markdown renderer, HTML enabled or not.

A card is read on GitHub, in MLflow's UI and in editors' previews; some of them pass raw HTML through, so a run name
like ``<img src=x onerror=alert(1)>`` or a ``<!--`` that hides the rest of the card must arrive as text.
"""

from __future__ import annotations

import html
import re
from typing import Any

# CommonMark lets a backslash escape any ASCII punctuation; these open or close inline Markdown (emphasis, code, links,
# table cells, GFM strikethrough) inside a line; block markers (#, -, 1.) only act at a line's start, where no value is
_MARKDOWN_PUNCTUATION = re.compile(r"([\\`*_\[\]|~])")
# values shown in a code span as they are: ids, hashes, versions, URIs without spaces or Markdown/HTML characters
_PLAIN = re.compile(r"[A-Za-z0-9._:/@+=%-]*")


def md_text(value: Any) -> str:
    """``value`` as literal Markdown text: Markdown punctuation backslash-escaped, then ``&``, ``<``, ``>`` and quotes
    as HTML entities (in that order: an entity's own ``#`` is not escaped), line breaks as spaces (a value never
    starts a new block)."""
    text = re.sub(r"[\r\n\u2028\u2029]+", " ", str(value))
    return html.escape(_MARKDOWN_PUNCTUATION.sub(r"\\\1", text), quote=True)


def md_code(value: Any) -> str:
    """``value`` in a code span when it is a plain token (an id, a hash, a version, a URI), else as :func:`md_text`
    (a code span shows entities and backslashes as typed, so text that needs them is not put in one)."""
    text = str(value)
    return f"`{text}`" if _PLAIN.fullmatch(text) and text else md_text(text)
