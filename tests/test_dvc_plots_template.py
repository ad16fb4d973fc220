"""The committed DVC plots page (.dvc/plots/offline.html) is what the locked vega packages give, and DVC uses it."""

from __future__ import annotations

import os

from aumesh.export import dvc_plots
from conftest import REPO


def test_committed_template_is_the_locked_packages_inlined(node_tools):
    committed = (REPO / dvc_plots.TEMPLATE_FILE).read_text(encoding="utf-8")
    assert committed == dvc_plots.template_html(node_tools), (
        "stale .dvc/plots/offline.html: run `make tools` (python -m aumesh dvc-plots-template) and commit it"
    )
    assert "{plot_divs}" in committed and "{scripts}" not in committed  # where DVC would put its CDN <script> tags
    assert "cdn.jsdelivr" not in committed and "<script src" not in committed
    for name in ("vega", "vega-lite", "vega-embed"):
        assert f'data-package="{name}@' in committed


def test_dvc_config_names_the_template():
    """DVC's own reading of .dvc/config (as `dvc plots show` resolves it: relative to .dvc/)."""
    from dvc.repo import Repo

    with Repo(str(REPO)) as repo:
        value = repo.config["plots"]["html_template"]
        assert value == dvc_plots.CONFIG_VALUE
        assert os.path.samefile(os.path.join(repo.dvc_dir, value), REPO / dvc_plots.TEMPLATE_FILE)
