"""DVC's own views of the demo, in a fresh clone after `make demo` and two `dvc exp run -S` experiments:
the README's `dvc exp show` line fits one 120-column screen with every experiment's metrics and swept parameters,
and `dvc plots diff` draws both curves in Chromium with the network blocked (the offline template of .dvc/config).

Slow (two pipeline runs on the demo data): `make test-slow`. Runs in a temporary `git clone` of this checkout's
HEAD (committed code only), never in the working tree.
"""

from __future__ import annotations

import io
import json
import re
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, SCREENSHOTS, clean_env, link_venv

pytestmark = pytest.mark.slow

MAKE = ["make", "-o", ".venv/.installed", "-o", "node_modules/.package-lock.json"]  # linked venv, node tools as given
EXPERIMENTS = {
    "model.n_components=10": ("model", "n_components", 10),
    "features=au_pose": ("features", "name", "au_pose"),
}


def _run(args, cwd: Path, env: dict, timeout: float = 1200.0) -> str:
    proc = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{args} failed ({proc.returncode}):\n{proc.stdout[-4000:]}\n{proc.stderr[-4000:]}"
    return proc.stdout


@pytest.fixture(scope="module")
def demo(tmp_path_factory, node_tools):
    """A fresh clone after `make demo` (pull, repro) with two experiments; (clone, env, head)."""
    import shutil

    if shutil.which("git") is None or not (REPO / ".venv" / "bin" / "dvc").exists():
        pytest.skip("needs git and .venv/bin/dvc")
    ws = tmp_path_factory.mktemp("views") / "clone"
    subprocess.run(["git", "clone", "-q", str(REPO), str(ws)], check=True, capture_output=True)
    link_venv(ws)
    env = clean_env(ws) | {"AUMESH_NODE_MODULES": str(node_tools)}
    env["PATH"] = f"{ws / '.venv' / 'bin'}:{env['PATH']}"  # as a user who activated the venv
    _run([*MAKE, "demo"], ws, env)
    assert (ws / ".dvc" / "plots" / "offline.html").is_file()  # committed: the page .dvc/config names
    assert _run(["git", "status", "--porcelain", "--", ".dvc"], ws, env) == ""
    for override in EXPERIMENTS:
        _run(["dvc", "exp", "run", "-q", "-S", override], ws, env)
    head = _run(["git", "rev-parse", "HEAD"], ws, env).strip()
    return ws, env, head


def _rows(shown: list, head: str) -> dict[str, dict]:
    """``{name: {"params", "metrics"}}`` of the baseline (``"baseline"``) and each experiment of `dvc exp show --json`."""
    rows = {}
    for commit in shown:
        nodes = [("baseline" if commit["rev"] == head else commit["rev"], commit)]
        nodes += [(exp["name"], exp["revs"][0]) for exp in commit.get("experiments") or []]
        for name, node in nodes:
            data = node["data"]
            rows[name] = {
                "params": data["params"]["params.yaml"]["data"],
                "metrics": data["metrics"]["metrics/metrics.json"]["data"],
            }
    return rows


def test_readme_exp_show_fits_one_screen_with_every_experiment(demo):
    ws, env, head = demo
    rows = _rows(json.loads(_run(["dvc", "exp", "show", "--json"], ws, env)), head)
    names = {}
    for override, (group, key, value) in EXPERIMENTS.items():  # each experiment is its -S value, with its own metrics
        (name,) = [
            n for n, r in rows.items() if n not in ("baseline", "workspace") and r["params"][group][key] == value
        ]
        names[override] = name
    assert len(set(names.values())) == 2 and rows["baseline"]["params"]["model"]["n_components"] == 83

    readme = (REPO / "README.md").read_text()
    commands = set(re.findall(r"^(dvc exp show --only-changed .*)$", readme, re.M))
    assert len(commands) == 1, commands  # one command, the same in Quick start and "Comparing experiments"
    (command,) = commands
    table = _run(["bash", "-c", command], ws, env | {"COLUMNS": "120"})  # as typed, shell quoting included
    print(table)
    lines = table.splitlines()
    assert max(map(len, lines)) <= 120, table
    assert "…" not in table, table  # no column or cell cut off
    header = next(line for line in lines if "Experiment" in line).split()
    assert header == [
        "Experiment",
        "r2_mean",
        "r2_displacement_mean",
        "mae_mean",
        "features.name",
        "model.n_components",
    ], header  # the metrics, then exactly the swept parameters
    for override, name in names.items():
        (line,) = [line for line in lines if f"[{name}]" in line]
        r2, r2_displacement, mae = (float(v) for v in line.split("]")[1].split()[:3])
        metrics = rows[name]["metrics"]
        for shown, exact in (
            (r2, metrics["r2_mean"]),
            (r2_displacement, metrics["r2_displacement_mean"]),
            (mae, metrics["mae_mean"]),
        ):
            assert shown == pytest.approx(exact, rel=1e-4), (override, line)
        group, key, value = EXPERIMENTS[override]
        assert line.split()[-2:] == [
            str(rows[name]["params"]["features"]["name"]),
            str(rows[name]["params"]["model"]["n_components"]),
        ], line


def test_plots_diff_draws_both_curves_offline(demo, browser):
    """`dvc plots diff` (the plain command: .dvc/config names the template) in Chromium with every non-file request
    aborted: both plots are drawn, each with the baseline's and the experiment's line, no console error."""
    from PIL import Image

    ws, env, head = demo
    experiment = _run(["dvc", "exp", "list", "--name-only"], ws, env).split()[0]
    _run(["dvc", "plots", "diff", head, experiment], ws, env)
    page_html = (ws / "dvc_plots" / "index.html").read_text()
    assert "cdn.jsdelivr" not in page_html and "vegaEmbed(" in page_html
    # each plot: the baseline's and the experiment's lines, in the first two colours DVC gives revisions
    from dvc_render.vega import OPTIONAL_ANCHOR_RANGES

    colours = [tuple(int(c[i : i + 2], 16) for i in (1, 3, 5)) for c in OPTIONAL_ANCHOR_RANGES["color"][:2]]

    def near(image):  # pixels of each revision's colour in a view (a drawn line; the legend's swatch is ~50)
        return [int((np.abs(image - np.array(colour)).sum(axis=-1) < 60).sum()) for colour in colours]

    problems, blocked = [], []
    context = browser.new_context(viewport={"width": 1280, "height": 1000})
    try:
        context.route(
            "**/*",
            lambda route: (
                route.continue_()
                if route.request.url.startswith(("file:", "data:"))
                else (blocked.append(route.request.url), route.abort())
            ),
        )
        page = context.new_page()
        page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
        page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
        page.goto((ws / "dvc_plots" / "index.html").as_uri())
        views = page.locator(".vega-embed canvas, .vega-embed svg.marks")
        page.wait_for_function(
            "document.querySelectorAll('.vega-embed canvas, .vega-embed svg.marks').length >= 2", timeout=60_000
        )
        # vega draws a view after its element appears: shot again until both lines show in each (the state the
        # checks below assert), not after a settling time; 60 s is a cap for a page that never draws them
        deadline = time.monotonic() + 60
        while True:
            images = [
                np.asarray(Image.open(io.BytesIO(views.nth(i).screenshot())).convert("RGB"), dtype=np.int16)
                for i in range(views.count())
            ]
            if all(min(near(image)) > 150 for image in images) or time.monotonic() > deadline:
                break
            page.wait_for_timeout(250)
        SCREENSHOTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=SCREENSHOTS / "dvc_plots_diff_offline.png", full_page=True)
        text = page.inner_text("body")
    finally:
        context.close()
    assert problems == [] and blocked == [], (problems, blocked)
    assert len(images) == 2, len(images)
    assert "Cumulative vertex error" in text or "Cumulative vertex error" in page_html
    for image in images:  # each plot: the baseline's and the experiment's lines
        assert min(near(image)) > 150, (colours, near(image))
