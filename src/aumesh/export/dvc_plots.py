"""An HTML template for ``dvc plots show`` / ``dvc plots diff`` that draws offline.

DVC's own page loads vega, vega-lite and vega-embed from a CDN (``dvc_render.vega``: ``<script
src="https://cdn.jsdelivr.net/npm/vega@5...">``); without network it stays white ("vegaEmbed is not
defined"). This template carries the three libraries inlined, from the locked npm packages ``make tools``
installs into ``node_modules/`` (``package-lock.json``: vega 5, vega-lite 5, vega-embed 6, the majors DVC's
Vega-Lite v5 specs are written for), as :mod:`aumesh.export.viewer` inlines three.js.

``.dvc/config`` names it (``[plots] html_template = plots/offline.html``, relative to ``.dvc/``), so the plain
commands use it. It is committed (0.8 MB), as DVC's own custom plot templates in ``.dvc/plots/`` are: a clone
draws offline whatever made its environment (make, conda, ``pip install -e .``), and a missing file would give
DVC's cryptic "HTML template has to contain '{plot_divs}'". ``make tools`` writes it again from the locked
packages with the unlisted command ``aumesh dvc-plots-template [--out FILE]`` (:mod:`aumesh.cli.tools`): the same
bytes while ``package-lock.json`` is unchanged (``tests/test_dvc_plots_template.py`` holds the two together).

The template has DVC's ``{plot_divs}`` and ``{refresh_tag}`` placeholders and deliberately no ``{scripts}``:
that is where DVC would put its CDN ``<script>`` tags.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

#: Where the template is written (from the repository root) and how ``.dvc/config`` names it (from ``.dvc/``).
TEMPLATE_FILE = Path(".dvc") / "plots" / "offline.html"
CONFIG_VALUE = "plots/offline.html"
#: The npm packages inlined, in load order (vega-embed's UMD build finds ``vega`` and ``vegaLite`` as globals).
PACKAGES = (
    ("vega", "build/vega.min.js"),
    ("vega-lite", "build/vega-lite.min.js"),
    ("vega-embed", "build/vega-embed.min.js"),
)
#: DVC's placeholders: a library's text must not contain them, or DVC would fill them in inside the JavaScript.
PLACEHOLDERS = ("{plot_divs}", "{scripts}", "{refresh_tag}")

PAGE = """<!DOCTYPE html>
<html>
<head>
    <meta charset="utf-8">
    {refresh_tag}
    <title>DVC Plot</title>
    <!-- aumesh: {versions} inlined from node_modules (make tools): the page draws offline, no CDN -->
{libraries}
    <style>
        body { font-family: sans-serif; }
        table { border-spacing: 15px; }
    </style>
</head>
<body>
{plot_divs}
</body>
</html>
"""


def find_node_modules() -> Path:
    """The ``node_modules`` folder holding vega, vega-lite and vega-embed
    (:func:`aumesh.export.viewer.find_node_modules`: ``$AUMESH_NODE_MODULES``, ``./node_modules``, the repository's)."""
    from aumesh.export.viewer import find_node_modules as find

    return find(
        [f"{name}/{build}" for name, build in PACKAGES],
        "vega, vega-lite and vega-embed (the DVC plots template inlines them; no CDN)",
    )


def _script(name: str, version: str, text: str) -> str:
    # the HTML parser ends a <script> at the first "</script": escape it (valid JavaScript either way); drop the
    # source-map comment, which names a file that is not beside the page
    text = re.sub(r"\n//# sourceMappingURL=\S+\s*$", "\n", text).replace("</script", "<\\/script")
    clash = [p for p in PLACEHOLDERS if p in text]
    if clash:
        raise ValueError(f"{name} {version} contains DVC's template placeholder(s) {clash}: it cannot be inlined as is")
    return f'    <script data-package="{name}@{version}">\n{text}\n    </script>'


def template_html(node_modules: Path | None = None) -> str:
    """The template's text, with the three libraries of *node_modules* (default :func:`find_node_modules`)."""
    base = node_modules or find_node_modules()
    scripts, versions = [], []
    for name, build in PACKAGES:
        version = json.loads((base / name / "package.json").read_text())["version"]
        versions.append(f"{name} {version}")
        scripts.append(_script(name, version, (base / name / build).read_text(encoding="utf-8")))
    # replacement, not str.format: the page's CSS has braces, and DVC's own placeholders stay for DVC to fill
    return PAGE.replace("{versions}", ", ".join(versions)).replace("{libraries}", "\n".join(scripts))


def write_template(out: str | Path = TEMPLATE_FILE, node_modules: Path | None = None) -> Path:
    """Write the template to *out* atomically (folders created); returns the path."""
    from aumesh.core.io import atomic_write_text

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write_text(out, template_html(node_modules))
