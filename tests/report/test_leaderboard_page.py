"""The leaderboard page (SPEC §21) on synthetic results of three runs: its bytes, its data, and
what it does in a real headless chromium with every network path cut (sort, filter, evidence)."""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from headless_chromium import chromium_path, file_url, load_offline

from oodrl.io import yamlio
from oodrl.metrics.operating import OperatingPoint
from oodrl.report.leaderboard_page import curve_steps
from oodrl.stages.leaderboard import run_leaderboard

DETECTORS = ("cusum", "kde_density", "pedm")
FAULTS = ("gaussian_state_noise", "stuck_actuator", "gradual_drift")
RUNS = (("CartPole-v1", "0"), ("CartPole-v1", "1"), ("Hopper-v5", "0"))
TIERS = {"mild": (0.95, 0.2), "moderate": (0.90, 0.4), "severe": (0.75, 0.7)}
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
    """A run's results.yaml (headline: matched AUROC alone) and tier_results.yaml."""
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
    paths = [directory / "results.yaml", directory / "tier_results.yaml"]
    directory.mkdir(parents=True, exist_ok=True)
    paths[0].write_text(yamlio.dump(stamp | {"records": headline}))
    tier_impact = {fault: impact(fault, run) for fault in FAULTS}
    paths[1].write_text(yamlio.dump(stamp | {"records": tiered, "impact": tier_impact}))
    return paths


@pytest.fixture
def results(tmp_path: Path) -> dict[tuple[str, str], list[Path]]:
    return {run: write_run(tmp_path / "runs" / f"{i}", run, i) for i, run in enumerate(RUNS)}


@pytest.fixture
def page(results, tmp_path: Path) -> Path:
    run_leaderboard(results, tmp_path / "out", n_boot=50, ci=0.95, seed=0)
    return tmp_path / "out" / "leaderboard.html"


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
    # Every (environment, policy, fault) × (3 tiers + headline), less the unreachable tier.
    assert len(data["cells"]) == len(RUNS) * len(FAULTS) * 4 - 1
    assert data["tiers"] == ["mild", "moderate", "severe", "headline"]
    assert data["families"] == ["observation", "action", "dynamics"]


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

#: Sort by a detector, filter by tier and environment, open cells; what the DOM shows each time.
PROBE = """
(() => {
  const $ = id => document.getElementById(id);
  const order = () => [...document.querySelectorAll('#board tbody tr')].map(r => +r.dataset.cell);
  const header = key => document.querySelector(`#board thead th[data-sort="${key}"]`);
  const choose = (key, value) => {
    $(`filter-${key}`).value = value;
    $(`filter-${key}`).dispatchEvent(new Event('change'));
  };
  const open = (index, detector) => document
    .querySelector(`#board tbody tr[data-cell="${index}"] td[data-detector="${detector}"]`).click();
  const panel = () => Object.fromEntries(['ev-title', 'ev-scores', 'ev-verification',
    'ev-detection', 'ev-delays', 'ev-false-alarms', 'ev-auroc', 'ev-no-operating-point']
    .map(id => [id, $(id) ? $(id).textContent : null]));
  const facts = {version: $('protocol-version').textContent, hash: $('params-hash').textContent,
                 initial: order(), count: $('row-count').textContent};
  header('detector:cusum').click();
  facts.sorted = order();
  facts.sorted_aria = header('detector:cusum').getAttribute('aria-sort');
  header('detector:cusum').click();
  facts.reversed = order();
  choose('tier', 'mild');
  facts.mild = order();
  choose('environment', 'Hopper-v5');
  facts.mild_hopper = order();
  facts.count_text = $('row-count').textContent;
  choose('environment', '');
  choose('family', 'action');
  facts.mild_action = order();
  choose('family', '');
  facts.footer = $('board').tFoot.textContent;
  choose('tier', '');
  open(@HEADLINE@, 'pedm');
  facts.headline = panel();
  open(@FEW@, '@FEW_DETECTOR@');
  facts.few = panel();
  choose('tier', 'mild');
  open(@VERIFIED@, 'cusum');
  facts.verified = panel();
  facts.impact_points = $('ev-impact').querySelectorAll('svg circle.raw').length;
  facts.impact_tier_line = !!$('ev-impact').querySelector('svg line.tier');
  facts.detection_path = !!$('ev-detection').querySelector('svg path.curve');
  facts.open_cells = document.querySelectorAll('#board td.score.open').length;
  facts.evidence_visible = !$('evidence').hidden;
  return facts;
})()
"""


def _first(cells: list[dict], **match) -> int:
    return next(i for i, c in enumerate(cells) if all(c[k] == v for k, v in match.items()))


@pytest.mark.slow
@needs_chromium
def test_sort_filter_and_open_the_evidence_in_a_real_browser(page: Path, tmp_path: Path):
    data = embedded(page)
    cells, metric = data["cells"], data["lead"]["metric"]
    assert metric == f"detection_rate@{K}"
    env, policy, fault, tier = VERIFIED
    verified = _first(cells, environment=env, policy=policy, fault=fault, tier=tier)
    headline = _first(cells, tier="headline")
    few = next(  # a tier cell with fewer than 5 detected streams: its delays are not shown
        (i, d)
        for i, c in enumerate(cells)
        for d, e in c["evidence"].items()
        if i != verified
        and "operating_point" in e
        and e["operating_point"]["delay"]["n_detected"] < 5
    )
    probe = (
        PROBE.replace("@HEADLINE@", str(headline))
        .replace("@FEW@", str(few[0]))
        .replace("@FEW_DETECTOR@", few[1])
        .replace("@VERIFIED@", str(verified))
    )
    screenshot = tmp_path / "leaderboard_page.png"
    report = load_offline(
        file_url(page), probe, "document.querySelectorAll('#board tbody tr').length > 0",
        screenshot=screenshot, viewport=(1500, 950),
    )  # fmt: skip
    assert report.network_requests == [] and report.exceptions == []
    assert report.console_errors == []
    facts = report.facts
    assert facts["version"] == "2" and facts["hash"] == data["params_hash"]
    assert facts["initial"] == list(range(len(cells)))
    assert facts["count"] == f"{len(cells)} of {len(cells)} cells"

    # Sorting by a detector: best first (cells without the metric last), then reversed.
    def score(i):
        return cells[i]["scores"].get(metric, {}).get("cusum")

    scored = [i for i in range(len(cells)) if score(i) is not None]
    unscored = [i for i in range(len(cells)) if score(i) is None]
    assert facts["sorted"] == sorted(scored, key=lambda i: (-score(i), i)) + unscored
    assert facts["sorted_aria"] == "descending"
    assert facts["reversed"] == sorted(scored, key=lambda i: (score(i), i)) + unscored
    assert facts["sorted"] != facts["initial"]
    # Filters keep the sort and narrow the rows.
    mild = [i for i in facts["reversed"] if cells[i]["tier"] == "mild"]
    assert facts["mild"] == mild and len(mild) == len(RUNS) * len(FAULTS)
    assert facts["mild_hopper"] == [i for i in mild if cells[i]["environment"] == "Hopper-v5"]
    assert facts["count_text"] == f"{len(FAULTS)} of {len(cells)} cells"
    assert facts["mild_action"] == [i for i in mild if cells[i]["fault"] == "stuck_actuator"]
    iqm = data["iqm"][metric]["mild"]["cusum"]
    assert "IQM [95% CI] over every cell of tier mild" in facts["footer"]
    assert f"{iqm['value']:.3f} [{iqm['ci_low']:.3f}, {iqm['ci_high']:.3f}]" in facts["footer"]
    # A detector of some runs only: its IQM over the cells where it runs, marked.
    assert ONLY_CARTPOLE not in data["iqm"][metric]["mild"]
    (scope,) = data["iqm_where_more_detectors_run"][metric]["mild"]
    assert scope["environments"] == ["CartPole-v1"] and scope["n_cells"] == len(FAULTS)
    only = scope["iqm"][ONLY_CARTPOLE]
    assert f"{only['value']:.3f} [{only['ci_low']:.3f}, {only['ci_high']:.3f}] *" in facts["footer"]

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
    assert screenshot.read_bytes()[:4] == b"\x89PNG"
    if artifacts := os.environ.get("OODRL_TEST_ARTIFACTS"):
        Path(artifacts).mkdir(parents=True, exist_ok=True)
        shutil.copy(screenshot, Path(artifacts) / screenshot.name)
