"""The leaderboard page (SPEC §21, §25) on synthetic results of three runs: its bytes, its data,
and what it does in a real headless chromium with every network path cut: the first screen (the
ranking with its CIs), sort, filter, the view in the URL, colours that follow each metric's
direction, the evidence; and the committed suite's page.

Each browser test saves a screenshot (PNG) in its pytest tmp dir; to keep them, set
OODRL_TEST_ARTIFACTS=<folder> (each is copied there) or pass `--basetemp=<folder>`."""

from __future__ import annotations

import colorsys
import json
import os
import re
import shutil
from pathlib import Path
from urllib.parse import quote

import numpy as np
import pytest
from headless_chromium import chromium_path, file_url, load_offline

from oodrl.io import yamlio
from oodrl.metrics.leaderboard import build_board
from oodrl.metrics.operating import OperatingPoint
from oodrl.metrics.tier_results import load_tier_results, tier_results_text
from oodrl.report.leaderboard import read_inputs
from oodrl.report.leaderboard_page import curve_steps, page_data, page_html
from oodrl.stages.leaderboard import run_leaderboard

DETECTORS = ("cusum", "kde_density", "pedm")
FAULTS = ("gaussian_state_noise", "stuck_actuator", "gradual_drift")
RUNS = (("CartPole-v1", "0"), ("CartPole-v1", "1"), ("Hopper-v5", "0"))
TIERS = {
    "mild": (0.95, 0.2),
    "moderate": (0.90, 0.4),
    "severe": (0.75, 0.7),
    "benign": (0.99, 0.05),
}
#: The detector that alarms most on harmless (benign) shifts: the worst there.
LOUD = "cusum"
#: Hopper's stuck actuator never costs a quarter of the return: its severe tier is unreachable.
UNREACHABLE = ("Hopper-v5", "0", "stuck_actuator", "severe")
#: The one tier whose verification the synthetic tier results carry.
VERIFIED = ("CartPole-v1", "0", "gradual_drift", "mild")
#: A detector that runs on CartPole's runs only (as the policy view runs on discrete actions).
ONLY_CARTPOLE = "kde_density"
STAMP = {"protocol_version": 2}
N_FAULTY, N_CLEAN, K = 20, 40, 100


def operating_point(detected: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    delays = tuple(sorted(int(d) for d in rng.integers(1, 90, size=detected)))
    curve = {k: sum(d <= k for d in delays) / N_FAULTY for k in range(0, 151, 10)}
    return OperatingPoint(
        alpha=0.05, threshold=1.0, k=K, n_faulty=N_FAULTY, detected=detected,
        early_false_alarms=1, delays=delays, curve=curve, n_clean=N_CLEAN,
        clean_false_alarms=int(rng.integers(0, 5)), confidence=0.95,
    ).as_dict()  # fmt: skip


def impact(fault: str, run: tuple[str, str]) -> dict:
    grid = [round(0.1 * i, 1) for i in range(1, 11)]
    curve = [
        {"severity": s, "mean_return": 400 * (1 - 0.4 * s), "normalised": round(1 - 0.38 * s, 6),
         "ci": [round(1 - 0.38 * s - 0.03, 6), round(1 - 0.38 * s + 0.03, 6)],
         "monotone": round(1 - 0.38 * s, 6)}
        for s in grid
    ]  # fmt: skip
    tiers = {
        tier: {"level": level, "severity": severity, "ci": [severity - 0.05, severity + 0.05]}
        for tier, (level, severity) in TIERS.items()
    }
    if (*run, fault) == UNREACHABLE[:3]:
        tiers["severe"] = {"level": 0.75, "severity": "unreachable", "ci": ["unreachable"] * 2}
    if (*run, fault) == VERIFIED[:3]:
        tiers["mild"]["verification"] = {
            "ci": [0.931, 0.962],
            "n_episodes": 100,
            "normalised": 0.947,
        }
    return {"clean_return": 400.0, "random_return": 20.0, "tiers": tiers, "curve": curve}


def write_run(directory: Path, run: tuple[str, str], seed: int) -> list[Path]:
    """A run's results.yaml (headline: matched AUROC alone) and tier_results.json."""
    rng = np.random.default_rng(seed)
    headline, tiered = [], []
    detectors = [d for d in DETECTORS if run[0] == "CartPole-v1" or d != ONLY_CARTPOLE]
    for fault in FAULTS:
        for detector in detectors:
            episodes = [round(float(v), 6) for v in rng.uniform(0.5, 1.0, size=6)]
            headline.append({
                "kind": "anomaly", "detector": detector, "injector": fault, "mode": "online",
                "severity": 0.5, "episodes": {"matched_auroc": episodes},
                "metrics": {"matched_auroc": {"mean": float(np.mean(episodes)), "ci_low": 0.5,
                                              "ci_high": 1.0}},
            })  # fmt: skip
            for tier, (_, severity) in TIERS.items():
                if (*run, fault, tier) == UNREACHABLE:
                    continue
                if tier == "benign":  # LOUD alarms on most harmless shifts, the others rarely
                    detected = int(rng.integers(14, 21) if detector == LOUD else rng.integers(1, 4))
                else:
                    detected = int(rng.integers(2, N_FAULTY + 1))
                auroc = [round(float(v), 6) for v in rng.uniform(0.5, 1.0, size=N_FAULTY)]
                tiered.append({
                    "kind": "anomaly", "detector": detector, "injector": fault, "tier": tier,
                    "severity": severity, "mode": "online", "latency": 0,
                    "metrics": {"matched_auroc": {"mean": float(np.mean(auroc)),
                                                  "ci_low": 0.6, "ci_high": 0.9}},
                    "episodes": {
                        "matched_auroc": auroc,
                        f"detection_rate@{K}": [1.0] * detected + [0.0] * (N_FAULTY - detected),
                    },
                    "operating_point": operating_point(detected, seed * 1000 + len(tiered)),
                })  # fmt: skip
    stamp = STAMP | {"params_hash": f"sha256:{seed:064x}"}
    paths = [directory / "results.yaml", directory / "tier_results.json"]
    directory.mkdir(parents=True, exist_ok=True)
    paths[0].write_text(yamlio.dump(stamp | {"records": headline}))
    tier_impact = {fault: impact(fault, run) for fault in FAULTS}
    paths[1].write_text(tier_results_text(stamp | {"records": tiered, "impact": tier_impact}))
    return paths


def write_results(directory: Path) -> dict[tuple[str, str], list[Path]]:
    return {run: write_run(directory / f"{i}", run, i) for i, run in enumerate(RUNS)}


@pytest.fixture
def results(tmp_path: Path) -> dict[tuple[str, str], list[Path]]:
    return write_results(tmp_path / "runs")


@pytest.fixture
def page(results, tmp_path: Path) -> Path:
    run_leaderboard(results, tmp_path / "out", n_boot=50, ci=0.95, seed=0)
    return tmp_path / "out" / "leaderboard.html"


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[Path, dict]:
    """One page for the browser tests (they only read it), and its data."""
    out = tmp_path_factory.mktemp("leaderboard")
    run_leaderboard(write_results(out / "runs"), out, n_boot=50, ci=0.95, seed=0)
    return out / "leaderboard.html", embedded(out / "leaderboard.html")


def embedded(page: Path) -> dict:
    text = page.read_text(encoding="utf-8")
    block = re.search(r'<script type="application/json" id="leaderboard-data">(.*?)</script>',
                      text, re.S)  # fmt: skip
    return json.loads(block.group(1))


def test_the_page_is_the_same_bytes_for_the_same_inputs_and_needs_no_network(
    results, page: Path, tmp_path: Path
):
    run_leaderboard(results, tmp_path / "again", n_boot=50, ci=0.95, seed=0)
    for name in ("leaderboard.html", "leaderboard.json"):
        assert (tmp_path / "out" / name).read_bytes() == (tmp_path / "again" / name).read_bytes()
    text = page.read_text(encoding="utf-8")
    assert "http://" not in text and "https://" not in text
    assert not re.search(r"<(script|link|img|iframe)[^>]+(src|href)=", text)
    assert str(tmp_path) not in text  # no host path
    data = json.loads((tmp_path / "out" / "leaderboard.json").read_text(encoding="utf-8"))
    assert embedded(page) == data  # the page carries leaderboard.json, no fetch
    assert data["protocol_version"] == 2 and data["params_hash"].startswith("sha256:")
    assert '<span id="protocol-version">2</span>' in text
    assert f'<code id="params-hash">{data["params_hash"]}</code>' in text
    assert [r["params_hashes"] for r in data["runs"]] == [[f"sha256:{i:064x}"] for i in range(3)]
    # The leaderboard's own params give another hash; so do a run's.
    run_leaderboard(results, tmp_path / "seed", n_boot=50, ci=0.95, seed=1)
    headline = results[RUNS[0]][0]
    headline.write_text(headline.read_text().replace(f"sha256:{0:064x}", f"sha256:{9:064x}"))
    run_leaderboard(results, tmp_path / "run", n_boot=50, ci=0.95, seed=0)
    hashes = {
        json.loads((tmp_path / out / "leaderboard.json").read_text())["params_hash"]
        for out in ("out", "seed", "run")
    }
    assert len(hashes) == 3
    # Every (environment, policy, fault) × (4 tiers + headline), less the unreachable tier.
    assert len(data["cells"]) == len(RUNS) * len(FAULTS) * 5 - 1
    assert data["tiers"] == ["mild", "moderate", "severe", "benign", "headline"]
    assert data["families"] == ["observation", "action", "dynamics"]


def test_the_page_data_carries_what_the_ranking_shows(page: Path, tmp_path: Path):
    """Mean and IQM with their CIs and the cell counts, as the leaderboard computed them; each
    metric's direction and colour scale; the detection rate that tells harm from harmless."""
    data = embedded(page)
    boards = yamlio.load((tmp_path / "out" / "leaderboard.yaml").read_text())["boards"]
    rate = f"detection_rate@{K}"
    for metric, tiers in boards.items():
        for tier, board in tiers.items():
            assert data["iqm"][metric][tier] == board["iqm"]
            assert data["mean"][metric][tier] == board["mean"]
            assert data["n_cells"][metric][tier] == board["n_cells"]
            scopes = data["iqm_where_more_detectors_run"][metric].get(tier, [])
            expected = board.get("where_more_detectors_run", [])
            assert [s["mean"] for s in scopes] == [e["mean"] for e in expected]
            assert [s["iqm"] for s in scopes] == [e["iqm"] for e in expected]
    assert set(boards[rate]) == {"mild", "moderate", "severe", "benign"}  # no headline rate
    assert data["lower_is_better"] == {rate: ["benign"], "matched_auroc": []}
    assert data["colour_scale"] == {rate: [0.0, 1.0], "matched_auroc": [0.5, 1.0]}
    assert data["harm"] == {"metric": rate, "harmful": "mild", "harmless": "benign"}
    # Timings are the machine's (SPEC §14): the pipeline's page has no µs per step.
    assert "us_per_step" not in data


def test_the_detection_curve_keeps_its_steps_only():
    curve = {0: 0.0, 10: 0.0, 20: 0.25, 30: 0.25, 40: 0.5, 50: 0.5, 60: 0.5}
    assert curve_steps(curve) == [[0, 0.0], [20, 0.25], [40, 0.5], [60, 0.5]]
    # Lossless on the grid: each K takes the rate of the last step at or before it.
    steps = curve_steps(curve)
    assert {k: [r for s, r in steps if s <= k][-1] for k in curve} == curve


needs_chromium = pytest.mark.skipif(
    chromium_path() is None,
    reason="Debian's chromium is not installed (apt-get install -y chromium); the leaderboard "
    "page can only be checked in a real browser",
)

#: The first screen the issue asks for (SPEC §25).
FIRST_SCREEN = (1400, 1000)
RATE = f"detection_rate@{K}"
COMMITTED = Path(__file__).resolve().parents[2] / "pipeline/suite/reports/leaderboard.html"

#: What the page shows: helpers every probe starts with, and `view()`, the state of the DOM.
PRELUDE = """
const $ = id => document.getElementById(id);
const choose = (key, value) => {
  $(`filter-${key}`).value = value;
  $(`filter-${key}`).dispatchEvent(new Event('change'));
};
const header = (table, key) => document.querySelector(`#${table} thead th[data-sort="${key}"]`);
const click = (table, key) => header(table, key).click();
const aria = table => [...document.querySelectorAll(`#${table} thead th[aria-sort]`)]
  .map(th => [th.dataset.sort, th.getAttribute('aria-sort')]);
const box = el => {
  const r = el.getBoundingClientRect();
  return [r.left, r.top, r.right, r.bottom];
};
const background = el => getComputedStyle(el).backgroundColor;
const rankingRows = () => [...document.querySelectorAll('#ranking tbody tr[data-detector]')];
const cell = (row, cls) => row.querySelector(`td.${cls}`);
const view = () => ({
  tier: $('filter-tier').value, metric: $('filter-metric').value,
  family: $('filter-family').value, environment: $('filter-environment').value,
  policy: $('filter-policy').value, hash: location.hash,
  direction: $('direction').textContent, title: $('ranking-title').textContent,
  empty: $('ranking-empty').hidden ? null : $('ranking-empty').textContent,
  ranking: rankingRows().map(r => r.dataset.detector),
  ranks: rankingRows().map(r => cell(r, 'rank').textContent),
  ranking_aria: aria('ranking'),
  cells: [...document.querySelectorAll('#board tbody tr')].map(r => +r.dataset.cell),
  columns: [...document.querySelectorAll('#board thead th.detector')]
    .map(th => th.dataset.sort.slice(9)),
  cells_aria: aria('board'),
  count: $('row-count').textContent,
});
"""


def browse(url: str, probe: str, screenshot: Path, ready: str = "true") -> dict:
    """Load `url` at the first screen's size, run PRELUDE + `probe` (an expression), save the
    screenshot (kept under OODRL_TEST_ARTIFACTS when set) and return what the probe found; the
    page must not touch the network nor raise."""
    report = load_offline(
        url, f"(() => {{ {PRELUDE} return {probe}; }})()",
        f"document.readyState === 'complete' && ({ready})",
        screenshot=screenshot, viewport=FIRST_SCREEN,
    )  # fmt: skip
    assert report.network_requests == [] and report.exceptions == []
    assert report.console_errors == []
    image = screenshot.read_bytes()
    assert image[:4] == b"\x89PNG"
    assert (int.from_bytes(image[16:20]), int.from_bytes(image[20:24])) == FIRST_SCREEN
    if artifacts := os.environ.get("OODRL_TEST_ARTIFACTS"):
        Path(artifacts).mkdir(parents=True, exist_ok=True)
        shutil.copy(screenshot, Path(artifacts) / screenshot.name)
    return report.facts


def hue(css: str) -> float:
    """The hue (degrees) of a computed `rgb(r, g, b)` colour: 0 red, 60 yellow, 120 green."""
    r, g, b = (int(v) / 255 for v in re.findall(r"\d+", css)[:3])
    return colorsys.rgb_to_hls(r, g, b)[0] * 360


def fragment(**state: str) -> str:
    return "#" + "&".join(f"{k}={quote(v, safe='')}" for k, v in state.items())


def interval_text(iv: dict) -> str:
    return f"{iv['value']:.3f} [{iv['ci_low']:.3f}, {iv['ci_high']:.3f}]"


def ranked(data: dict, metric: str, tier: str, key=None, descending=True) -> list[str]:
    """The ranking the page should show: the detectors over every cell by `key` (IQM), best
    first, ties by name; then those of some environments only."""
    key = key or (lambda d, iv: iv[d]["value"])
    overall = data["iqm"][metric][tier]
    sign = -1 if descending else 1
    first = sorted(overall, key=lambda d: (sign * key(d, overall), d))
    scoped = {d: s["iqm"][d] for s in data["iqm_where_more_detectors_run"][metric].get(tier, [])
              for d in s["iqm"] if d not in overall}  # fmt: skip
    return first + sorted(scoped, key=lambda d: (sign * key(d, scoped), d))


def cells_of(data: dict, tier: str, metric: str, **match: str) -> list[int]:
    return [
        i for i, c in enumerate(data["cells"])
        if c["tier"] == tier and c["scores"].get(metric)
        and all(c[k] == v for k, v in match.items())
    ]  # fmt: skip


@pytest.mark.slow
@needs_chromium
def test_the_first_screen_is_the_ranking_with_its_cis(built, tmp_path: Path):
    page, data = built
    probe = """({
      ...view(),
      rows: rankingRows().map(r => ({
        detector: r.dataset.detector, box: box(r), iqm: cell(r, 'iqm').textContent,
        mean: cell(r, 'mean').textContent, harmless: cell(r, 'harmless').textContent,
        gap: cell(r, 'gap').textContent,
        ci: [...r.querySelectorAll('td.figure svg line.ci')]
          .map(l => [+l.getAttribute('x1'), +l.getAttribute('x2')]),
        dot: [...r.querySelectorAll('td.figure svg circle.iqm')].map(c => +c.getAttribute('cx')),
      })),
      table: box($('ranking')), cells_top: box($('cells-section'))[1],
      cost_column: !!header('ranking', 'cost'), foot: $('ranking-foot').textContent,
      note: $('ranking-note').textContent,
    })"""
    facts = browse(file_url(page), probe, tmp_path / "leaderboard_first_screen.png")
    tier, metric = data["lead"]["tier"], data["lead"]["metric"]
    assert (tier, metric) == ("mild", RATE)
    assert facts["tier"] == tier and facts["metric"] == metric and facts["hash"] == ""
    assert facts["title"] == f"Ranking · tier mild · {RATE} at α = 0.05"
    assert facts["direction"] == "higher is better" and facts["empty"] is None
    n_cells = data["n_cells"][metric][tier]
    assert n_cells == len(RUNS[1:]) * len(FAULTS)  # (environment, fault): policies apart
    assert facts["note"].startswith(
        "IQM: the mean of the middle 50% of the (policy, cell) scores of tier mild "
        f"({n_cells} environment × fault cells, {len(RUNS) * len(FAULTS)} with their policies)"
    )
    # Best first by IQM; the detector of some runs only after the others, unranked.
    assert facts["ranking"] == ranked(data, metric, tier)
    assert facts["ranking"][-1] == ONLY_CARTPOLE and facts["ranks"] == ["1", "2", ""]
    assert facts["ranking_aria"] == [["iqm", "descending"]]
    # The whole ranking is on the first screen, above the cells.
    width, height = FIRST_SCREEN
    assert all(r["box"][1] >= 0 and r["box"][3] <= height for r in facts["rows"])
    assert facts["table"][2] <= width and facts["table"][3] <= facts["cells_top"]
    harm = data["iqm"][RATE]
    for row in facts["rows"]:
        d = row["detector"]
        scope = data["iqm_where_more_detectors_run"][metric][tier][0]
        iqm = data["iqm"][metric][tier].get(d) or scope["iqm"][d]
        mean = data["mean"][metric][tier].get(d) or scope["mean"][d]
        assert row["iqm"] == interval_text(iqm) and row["mean"] == interval_text(mean)
        if d in harm["benign"]:
            assert row["harmless"] == interval_text(harm["benign"][d])
            gap = harm["mild"][d]["value"] - harm["benign"][d]["value"]
            assert row["gap"] == f"{'+' if gap >= 0 else '−'}{abs(gap):.3f}"
        # The interval figure: a CI bar (line and two caps) around the IQM's dot.
        (low, high), *caps = row["ci"]
        (dot,) = row["dot"]
        assert len(caps) == 2 and low <= dot <= high and low < high
    dots = {r["detector"]: r["dot"][0] for r in facts["rows"]}
    values = {r["detector"]: float(r["iqm"].split()[0]) for r in facts["rows"]}
    assert sorted(dots, key=dots.get) == sorted(values, key=values.get)  # one axis for all
    # The cells come after: this tier's only, each with a score for the metric.
    assert facts["cells"] == cells_of(data, tier, metric)
    assert facts["count"] == f"{len(facts['cells'])} of {len(facts['cells'])} cells of tier mild"
    assert facts["columns"] == facts["ranking"]  # in the ranking's order
    assert not facts["cost_column"] and "µs per step: not on this page" in facts["foot"]


@pytest.mark.slow
@needs_chromium
def test_sort_and_filter_are_kept_in_the_url_and_a_link_reproduces_them(built, tmp_path: Path):
    page, data = built
    probe = """(() => {
      const seen = {initial: view()};
      click('ranking', 'mean'); seen.mean = view();
      click('ranking', 'mean'); seen.mean_again = view();
      click('ranking', 'harmless'); seen.harmless = view();
      click('ranking', 'detector'); seen.detector = view();
      choose('environment', 'CartPole-v1'); seen.cartpole = view();
      click('board', 'detector:pedm'); seen.pedm = view();
      click('board', 'detector:pedm'); seen.pedm_again = view();
      choose('tier', 'moderate'); choose('family', 'action'); seen.moderate = view();
      return seen;
    })()"""
    seen = browse(file_url(page), probe, tmp_path / "leaderboard_sorted.png")
    mild = data["iqm"][RATE]["mild"]

    def mean(d, iv):
        return data["mean"][RATE]["mild"].get(d, {}).get("value") or next(
            s["mean"][d]["value"] for s in data["iqm_where_more_detectors_run"][RATE]["mild"]
        )

    assert seen["initial"]["ranking"] == ranked(data, RATE, "mild")
    # The ranking: a column's first click sorts its best first, a second reverses.
    assert seen["mean"]["ranking"] == ranked(data, RATE, "mild", key=mean)
    assert seen["mean"]["ranking_aria"] == [["mean", "descending"]]
    assert seen["mean"]["hash"] == f"#tier=mild&metric={quote(RATE, safe='')}&sort=mean"
    assert seen["mean_again"]["ranking"] == ranked(data, RATE, "mild", key=mean, descending=False)
    assert seen["mean_again"]["hash"].endswith("&sort=mean&order=asc")
    # Fewest alarms on harmless shifts first: LOUD, which alarms most, last of its group.
    benign = data["iqm"][RATE]["benign"]
    assert seen["harmless"]["ranking"][: len(mild)] == sorted(
        mild, key=lambda d: (benign[d]["value"], d)
    )
    assert seen["harmless"]["ranking"][len(mild) - 1] == LOUD
    assert seen["harmless"]["ranking_aria"] == [["harmless", "ascending"]]
    assert seen["detector"]["ranking"] == [*sorted(mild), ONLY_CARTPOLE]
    # The cell filters narrow the cells, not the ranking (over every cell of the tier).
    cartpole = cells_of(data, "mild", RATE, environment="CartPole-v1")
    assert seen["cartpole"]["cells"] == cartpole and len(cartpole) == 2 * len(FAULTS)
    assert seen["cartpole"]["ranking"] == seen["detector"]["ranking"]
    assert seen["cartpole"]["count"] == f"{len(cartpole)} of {len(FAULTS) * 3} cells of tier mild"
    assert "environment=CartPole-v1" in seen["cartpole"]["hash"]

    def pedm(i):
        return data["cells"][i]["scores"][RATE]["pedm"]

    assert seen["pedm"]["cells"] == sorted(cartpole, key=lambda i: (-pedm(i), i))
    assert seen["pedm"]["cells_aria"] == [["detector:pedm", "descending"]]
    assert seen["pedm_again"]["cells"] == sorted(cartpole, key=lambda i: (pedm(i), i))
    assert "cells=detector%3Apedm&cells_order=asc" in seen["pedm_again"]["hash"]
    moderate = cells_of(data, "moderate", RATE, environment="CartPole-v1", family="action")
    final = seen["moderate"]
    assert final["cells"] == sorted(moderate, key=lambda i: (pedm(i), i)) and moderate
    assert final["ranking"] == [*sorted(data["iqm"][RATE]["moderate"]), ONLY_CARTPOLE]

    # The link reproduces the view: the same selects, ranking, cells and sort marks.
    again = browse(file_url(page) + final["hash"], "view()", tmp_path / "leaderboard_link.png")
    assert again == final
    assert (again["tier"], again["environment"], again["family"]) == (
        "moderate",
        "CartPole-v1",
        "action",
    )

    # A hand-written link: another tier, metric and sorts; a value the page does not know is
    # left at its default.
    link = fragment(tier="benign", metric="matched_auroc", sort="gap", cells="fault",
                    cells_order="desc", policy="1", environment="Nowhere-v0")  # fmt: skip
    written = browse(file_url(page) + link, "view()", tmp_path / "leaderboard_written.png")
    assert (written["tier"], written["metric"], written["environment"]) == (
        "benign",
        "matched_auroc",
        "",
    )
    assert written["policy"] == "1" and written["ranking_aria"] == [["gap", "descending"]]
    gap = {d: mild[d]["value"] - benign[d]["value"] for d in mild}
    assert written["ranking"][: len(gap)] == sorted(gap, key=lambda d: (-gap[d], d))
    chosen = cells_of(data, "benign", "matched_auroc", policy="1")
    fault = {i: data["cells"][i]["fault"] for i in chosen}
    # by fault, Z to A; within a fault, the data's order (a stable sort keeps it)
    assert written["cells"] == sorted(chosen, key=fault.get, reverse=True)
    assert written["cells_aria"] == [["fault", "descending"]]


@pytest.mark.slow
@needs_chromium
def test_rows_without_a_value_for_the_metric_are_hidden(built, tmp_path: Path):
    """Headline cells are scored by matched AUROC alone: under a detection rate, neither the
    ranking nor the cells show a row, and the page says what does rank them."""
    page, data = built
    url = file_url(page) + fragment(tier="headline", metric=RATE)
    facts = browse(url, "view()", tmp_path / "leaderboard_headline_rate.png")
    headline = sum(c["tier"] == "headline" for c in data["cells"])
    assert facts["ranking"] == [] and facts["cells"] == [] and facts["columns"] == []
    assert facts["empty"] == (
        f"No detector has a {RATE} at α = 0.05 score on tier headline. {RATE} at α = 0.05 ranks "
        "tiers mild, moderate, severe, benign; tier headline is ranked by matched AUROC."
    )
    assert facts["count"] == (
        f"0 of {headline} cells of tier headline "
        f"({headline} without a {RATE} at α = 0.05 score hidden)"
    )
    # Hopper's runs have no kde_density: its column is not shown when only they are.
    url = file_url(page) + fragment(tier="mild", metric=RATE, environment="Hopper-v5")
    facts = browse(url, "view()", tmp_path / "leaderboard_hopper.png")
    assert ONLY_CARTPOLE not in facts["columns"] and ONLY_CARTPOLE in facts["ranking"]
    assert facts["cells"] == cells_of(data, "mild", RATE, environment="Hopper-v5")


@pytest.mark.slow
@needs_chromium
def test_colours_follow_each_metric_direction_fewer_alarms_are_green_on_benign(
    built, tmp_path: Path
):
    page, data = built
    probe = """(() => {
      const colours = () => ({
        paint: rankingRows().map(r => [r.dataset.detector, cell(r, 'iqm').textContent,
          background(cell(r, 'iqm')), background(cell(r, 'harmless')), cell(r, 'gap').textContent,
          background(cell(r, 'gap'))]),
        cells: [...document.querySelectorAll('#board tbody td.score')]
          .filter(td => td.textContent !== '—').map(td => [td.textContent, background(td)]),
      });
      const seen = {benign: {...view(), ...colours()}};
      choose('tier', 'mild'); seen.mild = {...view(), ...colours()};
      choose('metric', 'matched_auroc'); seen.auroc = {...view(), ...colours()};
      return seen;
    })()"""
    url = file_url(page) + fragment(tier="benign", metric=RATE)
    seen = browse(url, probe, tmp_path / "leaderboard_benign.png")
    benign = data["iqm"][RATE]["benign"]
    loudest = max(benign, key=lambda d: benign[d]["value"])
    assert loudest == LOUD and benign[LOUD]["value"] >= 0.7
    view = seen["benign"]
    assert view["direction"].startswith("lower is better")
    # Quietest first; the detector that alarms most is last of its group, and red, not green.
    assert view["ranking"] == ranked(data, RATE, "benign", descending=False)
    colour = {d: hue(iqm) for d, _, iqm, *_ in view["paint"]}
    assert view["ranking"][len(benign) - 1] == LOUD and colour[LOUD] < 40
    assert colour[view["ranking"][0]] > 90  # the quietest: green
    # Every score's colour: 120° × (1 − rate) on benign, 120° × rate on mild, and for matched
    # AUROC from red at chance (½) to green at 1.
    for tier, goodness in (
        ("benign", lambda v: 1 - v),
        ("mild", lambda v: v),
        ("auroc", lambda v: (v - 0.5) / 0.5),
    ):
        shown = seen[tier]["cells"] + [
            (text.split()[0], iqm) for _, text, iqm, *_ in seen[tier]["paint"]
        ]
        assert len(shown) > 20
        for text, css in shown:
            expected = 120 * min(max(goodness(float(text)), 0), 1)
            assert abs(hue(css) - expected) < 2.5, (tier, text, css)
    # The harmless alarm rate is lower-is-better whatever the chosen tier; the gap higher.
    for tier in ("benign", "mild", "auroc"):
        rows = {r[0]: r for r in seen[tier]["paint"]}
        assert hue(rows[LOUD][3]) < 40
        assert all(hue(r[3]) > 90 for d, r in rows.items() if d != LOUD and d in benign)
        for _, _, _, _, gap, css in rows.values():
            if gap != "—":
                value = float(gap.replace("−", "-"))
                assert abs(hue(css) - 120 * min(max(0.5 + value, 0), 1)) < 2.5
    assert seen["mild"]["direction"] == "higher is better"
    assert seen["mild"]["ranking"] == ranked(data, RATE, "mild")


def _evidence_probe(**marks: object) -> str:
    probe = """(() => {
      const open = (index, detector) => document
        .querySelector(`#board tbody tr[data-cell="${index}"] td[data-detector="${detector}"]`)
        .click();
      const panel = () => Object.fromEntries(['ev-title', 'ev-scores', 'ev-verification',
        'ev-detection', 'ev-delays', 'ev-false-alarms', 'ev-auroc', 'ev-no-operating-point']
        .map(id => [id, $(id) ? $(id).textContent : null]));
      const facts = {version: $('protocol-version').textContent,
                     hash: $('params-hash').textContent};
      choose('metric', 'matched_auroc'); choose('tier', 'headline');
      open(@HEADLINE@, 'pedm');
      facts.headline = panel();
      choose('metric', '@RATE@'); choose('tier', '@FEW_TIER@');
      open(@FEW@, '@FEW_DETECTOR@');
      facts.few = panel();
      choose('tier', 'mild');
      facts.closed = $('evidence').hidden;
      open(@VERIFIED@, 'cusum');
      facts.verified = panel();
      facts.impact_points = $('ev-impact').querySelectorAll('svg circle.raw').length;
      facts.impact_tier_line = !!$('ev-impact').querySelector('svg line.tier');
      facts.detection_path = !!$('ev-detection').querySelector('svg path.curve');
      facts.open_cells = document.querySelectorAll('#board td.score.open').length;
      facts.evidence_visible = !$('evidence').hidden;
      return facts;
    })()"""
    for mark, value in marks.items():
        probe = probe.replace(f"@{mark}@", str(value))
    return probe


def _first(cells: list[dict], **match) -> int:
    return next(i for i, c in enumerate(cells) if all(c[k] == v for k, v in match.items()))


@pytest.mark.slow
@needs_chromium
def test_a_score_opens_its_evidence_in_a_real_browser(built, tmp_path: Path):
    page, data = built
    cells = data["cells"]
    env, policy, fault, tier = VERIFIED
    verified = _first(cells, environment=env, policy=policy, fault=fault, tier=tier)
    headline = _first(cells, tier="headline")
    few = next(  # a tier cell with fewer than 5 detected streams: its delays are not shown
        (i, d)
        for i, c in enumerate(cells)
        for d, e in c["evidence"].items()
        if i != verified
        and c["tier"] != "mild"
        and "operating_point" in e
        and e["operating_point"]["delay"]["n_detected"] < 5
    )
    probe = _evidence_probe(
        HEADLINE=headline, FEW=few[0], FEW_DETECTOR=few[1], FEW_TIER=cells[few[0]]["tier"],
        VERIFIED=verified, RATE=RATE,
    )  # fmt: skip
    facts = browse(file_url(page), probe, tmp_path / "leaderboard_evidence.png")
    assert facts["version"] == "2" and facts["hash"] == data["params_hash"]
    # A headline cell: matched AUROC alone, no operating point, no tier to verify.
    headline_panel = facts["headline"]
    assert headline_panel["ev-no-operating-point"] is not None
    assert headline_panel["ev-verification"] is None and headline_panel["ev-detection"] is None
    auroc = cells[headline]["evidence"]["pedm"]["matched_auroc"]
    assert headline_panel["ev-auroc"].startswith(f"{auroc['mean']:.3f} [0.500, 1.000]")
    # Fewer than 5 detected streams: no delays; an unverified tier says so.
    point = cells[few[0]]["evidence"][few[1]]["operating_point"]
    assert facts["few"]["ev-delays"] == (
        f"median —, p90 — ({point['delay']['n_detected']} detected streams: fewer than 5, "
        "not shown)"
    )
    assert facts["few"]["ev-verification"] == "not verified"
    assert facts["closed"]  # another tier: its cell is gone, and so is its panel
    # The verified cell: its numbers, as the results files hold them.
    panel = facts["verified"]
    point = cells[verified]["evidence"]["cusum"]["operating_point"]
    assert panel["ev-title"] == "cusum · CartPole-v1 · policy 0 · gradual_drift · tier mild"
    assert panel["ev-verification"] == (
        "verification: ci [0.931, 0.962], n_episodes 100, normalised 0.947"
    )
    low, high = point["detection_rate_ci"]
    detected = round(point["detection_rate"] * N_FAULTY)
    assert (
        f"detection_rate@{K} = {point['detection_rate']:.3f} [{low:.3f}, {high:.3f}]: "
        f"{detected} of {N_FAULTY} faulty streams" in panel["ev-detection"]
    )
    delay = point["delay"]
    if delay["n_detected"] >= 5:
        assert panel["ev-delays"] == (
            f"median {delay['median']:g} steps, p90 {round(delay['p90'], 1):g} steps "
            f"({delay['n_detected']} detected streams)"
        )
    fa_low, fa_high = point["clean_false_alarm_ci"]
    assert panel["ev-false-alarms"].startswith(
        f"achieved {point['clean_false_alarm_rate']:.3f} [{fa_low:.3f}, {fa_high:.3f}] on "
        f"{N_CLEAN} clean streams, beside α = 0.05"
    )
    assert facts["impact_points"] == 10 and facts["impact_tier_line"] and facts["detection_path"]
    assert facts["open_cells"] == 1 and facts["evidence_visible"]


@pytest.mark.slow
@needs_chromium
def test_a_page_given_each_detectors_cost_ranks_by_it(results, tmp_path: Path):
    """µs per step is the machine's, so only a caller that measured it passes it (page_data)."""
    inputs = read_inputs(results)
    board = build_board(inputs.cells, n_boot=50, ci=0.95, seed=0)
    cost = {"cusum": 3.4, "pedm": 41.0, "kde_density": 12.5}
    data = page_data(inputs, board, n_boot=50, ci=0.95, seed=0, us_per_step=cost)
    assert data["us_per_step"] == cost
    page = tmp_path / "leaderboard.html"
    page.write_text(page_html(data), encoding="utf-8")
    probe = """(() => {
      const costs = () => rankingRows().map(r => [r.dataset.detector, cell(r, 'cost').textContent]);
      const seen = {costs: costs(), foot: $('ranking-foot').textContent};
      click('ranking', 'cost'); seen.sorted = view();
      return seen;
    })()"""
    seen = browse(file_url(page), probe, tmp_path / "leaderboard_cost.png")
    assert sorted(seen["costs"]) == [["cusum", "3.4"], ["kde_density", "12.5"], ["pedm", "41.0"]]
    assert "µs per step" not in seen["foot"]
    # Fewest µs first, within each group (kde_density runs on CartPole only).
    assert seen["sorted"]["ranking"] == ["cusum", "pedm", "kde_density"]
    assert seen["sorted"]["ranking_aria"] == [["cost", "ascending"]]


@pytest.mark.slow
@needs_chromium
@pytest.mark.skipif(not COMMITTED.is_file(), reason="the suite's page is not built")
def test_the_committed_page_opens_on_the_ranking_with_its_cis(tmp_path: Path):
    """The suite's page as committed: its first screen (1400×1000) is the lead tier's whole
    ranking with CIs; on benign, the detector that alarms most is not green."""
    data = embedded(COMMITTED)
    tier, metric = data["lead"]["tier"], data["lead"]["metric"]
    probe = """({...view(), rows: rankingRows().map(r => [r.dataset.detector, box(r)[3],
      r.querySelectorAll('td.figure svg line.ci').length, cell(r, 'iqm').textContent]),
      cells_top: box($('cells-section'))[1]})"""
    facts = browse(file_url(COMMITTED), probe, tmp_path / "committed_first_screen.png",
                   ready="document.querySelectorAll('#ranking tbody tr').length > 0")  # fmt: skip
    assert (facts["tier"], facts["metric"]) == (tier, metric)
    assert facts["ranking"] == ranked(data, metric, tier)
    assert len(facts["rows"]) == len(data["iqm"][metric][tier]) + sum(
        1 for s in data["iqm_where_more_detectors_run"][metric][tier][:1] for d in s["iqm"]
        if d not in data["iqm"][metric][tier]
    )  # fmt: skip
    assert all(bottom <= FIRST_SCREEN[1] and ci == 3 for _, bottom, ci, _ in facts["rows"])
    best = facts["rows"][0]
    assert best[3] == interval_text(data["iqm"][metric][tier][best[0]])
    harm = data["harm"]
    url = file_url(COMMITTED) + fragment(tier=harm["harmless"], metric=harm["metric"])
    probe = "rankingRows().map(r => [r.dataset.detector, background(cell(r, 'iqm'))])"
    rows = browse(url, probe, tmp_path / "committed_benign.png",
                  ready="document.querySelectorAll('#ranking tbody tr').length > 0")  # fmt: skip
    rates = data["iqm"][harm["metric"]][harm["harmless"]]
    loudest = max(rates, key=lambda d: rates[d]["value"])
    quietest = min(rates, key=lambda d: rates[d]["value"])
    colours = {d: hue(css) for d, css in rows}
    assert rates[loudest]["value"] > rates[quietest]["value"]
    assert colours[loudest] < colours[quietest]  # the more alarms, the further from green
    for d in (loudest, quietest):
        assert abs(colours[d] - 120 * (1 - rates[d]["value"])) < 2.5


@pytest.mark.slow
@needs_chromium
def test_what_the_time_aware_rule_changes_is_shown_for_the_chosen_tier(tmp_path: Path):
    """SPEC §24: CartPole's tier results hold both rules (pedm gains 5 streams a cell under the
    time-aware one), Hopper's the constant rule only (protocol 3's): the page shows, below the
    ranking, each detector's difference on the chosen tier's cells with both rules."""
    results = write_results(tmp_path / "runs")
    for run, (_, tiers) in results.items():
        if run[0] != "CartPole-v1":
            continue
        document = load_tier_results(tiers)
        for record in document["records"]:
            hits = record["episodes"][RATE]
            detected = int(sum(hits)) + (5 if record["detector"] == "pedm" else 0)
            aware = [1.0] * min(detected, N_FAULTY) + [0.0] * (N_FAULTY - min(detected, N_FAULTY))
            record["episodes"][f"time_aware_{RATE}"] = aware
        tiers.write_text(tier_results_text(document))
    run_leaderboard(results, tmp_path / "out", n_boot=50, ci=0.95, seed=0)
    page = tmp_path / "out" / "leaderboard.html"
    data = embedded(page)
    assert RATE in data["rule_change"] and f"time_aware_{RATE}" not in data["metrics"]
    probe = """(() => {
      const shown = () => ({
        hidden: $('rule-change-section').hidden, title: $('rule-change-title').textContent,
        rows: [...document.querySelectorAll('#rule-change tbody tr')]
          .map(r => [r.dataset.detector, r.children[1].textContent]),
        foot: $('rule-change-foot').textContent,
        below: box($('rule-change-section'))[1] >= box($('ranking'))[3],
      });
      const seen = {mild: shown()};
      choose('tier', 'benign'); seen.benign = shown();
      choose('metric', 'matched_auroc'); seen.auroc = shown();
      return seen;
    })()"""
    facts = browse(file_url(page), probe, tmp_path / "leaderboard_rule_change.png")
    for tier, seen in (("mild", facts["mild"]), ("benign", facts["benign"])):
        change = data["rule_change"][RATE][tier]
        assert not seen["hidden"] and seen["below"]
        title = f"What the time-aware rule changes · tier {tier} · {RATE} at α = 0.05"
        assert seen["title"] == title
        assert [d for d, _ in seen["rows"]] == ["pedm", "cusum", "kde_density"]  # largest first
        diff = change["detectors"]["pedm"]["difference"]
        assert seen["rows"][0][1].startswith(f"+{diff['value']:.3f} [")
        assert seen["rows"][1][1] == "+0.000 [+0.000, +0.000]"
        assert seen["foot"].startswith("Kendall τ between the two rules' IQM rankings: ")
    # Another metric chosen: the detection rate's change on that tier is still shown.
    assert facts["auroc"]["rows"] == facts["benign"]["rows"]
