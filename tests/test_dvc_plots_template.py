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


def test_the_command_make_tools_runs_writes_the_committed_template(node_tools, tmp_path, monkeypatch, capsys):
    """`make tools` runs `python -m aumesh dvc-plots-template --out FILE` (unlisted in `aumesh --help`): the file it
    writes is the committed one, byte for byte; without the vega packages it is a one-line error, exit 2."""
    from aumesh import cli

    monkeypatch.setenv("AUMESH_NODE_MODULES", str(node_tools))
    out = tmp_path / "plots" / "offline.html"
    assert cli.main(["dvc-plots-template", "--out", str(out)]) == 0
    assert out.read_bytes() == (REPO / dvc_plots.TEMPLATE_FILE).read_bytes()
    assert capsys.readouterr().out.startswith(f"wrote {out} (")
    assert "dvc-plots-template" not in cli.build_parser().format_help()

    monkeypatch.setattr(dvc_plots, "find_node_modules", lambda: (_ for _ in ()).throw(FileNotFoundError("no vega")))
    assert cli.main(["dvc-plots-template", "--out", str(tmp_path / "x.html")]) == 2
    assert capsys.readouterr().err == "aumesh dvc-plots-template: error: no vega\n"
