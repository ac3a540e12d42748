"""`dvc plots show` works offline: a real DVC repository, a real headless chromium, no network.

The repository holds the figures and plot data the render stage writes (from the realistic
fake results) and the plots section `oodrl.report.offline.PLOTS`; `dvc plots show` renders it
into a page with the offline template, which chromium loads with every network path cut.
Each chart must draw its marks as SVG, each figure must load, and the page must log no error
and request nothing from the network. DVC's own page, which loads Vega from a CDN, is the
control: under the same conditions its charts stay empty.
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from pathlib import Path

import pytest
import yaml
from headless_chromium import chromium_path, file_url, load_offline

from oodrl.report.offline import PAGE, PINS, PLOTS, TEMPLATES_DIR, inlined_scripts
from oodrl.report.plots import (
    plot_heatmap,
    plot_severity_curves,
    write_dvc_plot_data,
)
from oodrl.testing.pipeline import run

in_a_browser = [
    pytest.mark.slow,
    pytest.mark.skipif(
        chromium_path() is None,
        reason="Debian's chromium is not installed (apt-get install -y chromium); the offline "
        "`dvc plots show` page can only be checked in a real browser",
    ),
]


def browser_test(test):
    for mark in in_a_browser:
        test = mark(test)
    return test


#: What each chart drew (its marks by type, its axes' descriptions, its line colours), and the
#: page's images; `IDS` is the list of the chart divs' ids, which DVC's page embeds into.
PROBE = """
(() => ({
  charts: IDS.map(id => {
    const svg = document.getElementById(id)?.querySelector('svg');
    const count = kind => svg ? svg.querySelectorAll(`g.mark-${kind}.role-mark > *`).length : 0;
    const strokes = svg ? [...svg.querySelectorAll('g.mark-line.role-mark > path')]
      .map(p => p.getAttribute('stroke')) : [];
    return {
      svg: !!svg,
      width: svg ? svg.getBoundingClientRect().width : 0,
      rect: count('rect'), line: count('line'), symbol: count('symbol'),
      text: count('text'), rule: count('rule'),
      line_colours: [...new Set(strokes)].length,
      axes: svg ? [...svg.querySelectorAll('g.role-axis')].map(a => a.getAttribute('aria-label'))
        : [],
    };
  }),
  images: [...document.images].map(i => ({src: i.getAttribute('src'), width: i.naturalWidth})),
}))()
"""
READY = "IDS.every(id => document.getElementById(id)?.querySelector('svg g.role-mark'))"


def page_report(page: Path, timeout: float = 60.0):
    """Load a `dvc plots show` page offline and probe the charts it embeds."""
    ids = json.dumps(re.findall(r"vegaEmbed\('#([^']+)'", page.read_text(encoding="utf-8")))
    report = load_offline(
        file_url(page), PROBE.replace("IDS", ids), READY.replace("IDS", ids), timeout=timeout
    )
    return json.loads(ids), report


@pytest.fixture
def plots_repo(results, sweep, tmp_path: Path) -> Path:
    """A DVC repository with the render stage's figures and plot data and oodrl's plots."""
    repo = tmp_path / "repo"
    repo.mkdir()
    run(repo, "git", "init", "-q")
    run(repo, "dvc", "init", "-q")
    figures = repo / "reports" / "figures"
    plot_heatmap(results, figures / "matched_auroc_heatmap.png")
    plot_severity_curves(sweep, figures / "severity_curves.png", results)
    write_dvc_plot_data(results, sweep, repo / "reports" / "plots")
    templates = repo / "src" / "oodrl" / "report" / "vega"
    shutil.copytree(TEMPLATES_DIR, templates)
    (repo / "dvc.yaml").write_text(yaml.safe_dump({"plots": list(PLOTS)}, sort_keys=False))
    return repo


def show(repo: Path, *template: str) -> Path:
    run(repo, "dvc", "plots", "show", "-o", "page", *template)
    return repo / "page" / "index.html"


@browser_test
def test_the_offline_page_draws_every_chart_without_a_network(plots_repo):
    ids, report = page_report(show(plots_repo, "--html-template", str(PAGE)))
    assert len(ids) == 3
    assert report.network_requests == []
    assert report.exceptions == []
    assert report.console_errors == []
    bars, heatmap, curves = report.facts["charts"]
    assert all(chart["svg"] and chart["width"] > 100 for chart in (bars, heatmap, curves))
    # One bar per detector, on an axis that starts at zero.
    assert bars["rect"] == 8
    assert any("values from 0" in (axis or "") for axis in bars["axes"]), bars["axes"]
    # One cell and one label per detector × anomaly.
    assert (heatmap["rect"], heatmap["text"]) == (8 * 9, 8 * 9)
    # Per injector panel: one line per detector, each in its own colour, with its points,
    # and two rules (chance and the headline severity).
    assert curves["line"] == 9 * 8
    assert curves["line_colours"] == 8
    assert curves["symbol"] == 9 * 8 * 5
    assert curves["rule"] == 9 * 2
    names = sorted(Path(i["src"]).name for i in report.facts["images"])
    assert len(names) == 2
    assert names[0].endswith("matched_auroc_heatmap.png")
    assert names[1].endswith("severity_curves.png")
    assert all(image["width"] > 0 for image in report.facts["images"])


@browser_test
def test_dvc_default_page_is_blank_offline(plots_repo):
    # The control: DVC's page takes Vega from a CDN, which chromium cannot reach here.
    ids, report = page_report(show(plots_repo), timeout=10)
    assert len(ids) == 3
    assert report.network_requests
    assert not any(chart["svg"] for chart in report.facts["charts"])


def test_the_page_inlines_the_pinned_libraries():
    page = PAGE.read_text(encoding="utf-8")
    scripts = inlined_scripts(page)
    assert [hashlib.sha256(s.encode()).hexdigest() for s in scripts] == [p.sha256 for p in PINS]
    for library in PINS:
        assert f"/*! {library.label} ({library.build})\nCopyright" in page
    assert "{plot_divs}" in page and "{scripts}" not in page
    # Nothing outside the libraries themselves points at the network.
    head = page.split("<script>")[0]
    assert "http://" not in head and "https://" not in head


def test_the_project_uses_the_offline_page_and_plots(repo_root):
    # What the browser test checks is what `dvc plots show` in this project renders.
    plots = yaml.safe_load((repo_root / "dvc.yaml").read_text())["plots"]
    assert plots == list(PLOTS), "dvc.yaml `plots:` must be oodrl.report.offline.PLOTS"
    config = (repo_root / ".dvc" / "config").read_text()
    setting = "html_template = ../" + PAGE.relative_to(repo_root).as_posix()
    assert setting in config, f".dvc/config needs [plots] {setting}"
