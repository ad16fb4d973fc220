"""The project stands alone: its README and docs point only at files inside the repository."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_docs_name_no_path_outside_the_repository_and_links_resolve(doc):
    text = doc.read_text()
    outside = re.findall(r"(?<![\w.])\.\./[\w./-]+|/work/[\w./-]+|/home/[\w./-]+", text)
    assert not outside, f"{doc.name} points outside the repository: {outside}"
    for target in re.findall(r"\]\(([^)#\s]+)\)", text):
        if not re.match(r"\w+://", target):
            assert (doc.parent / target).exists(), f"{doc.name} links to missing {target}"
