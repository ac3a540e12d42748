"""Fresh-data check (SPEC §19; issue 39, item 7): do a built pipeline's promises hold on seeds it
never used?

    python benchmarks/fresh_check.py --pipeline P [--streams N] [--episodes M] [--random-episodes R]
        [--seed-offset S] [--detectors D ...] [--faults F ...] [--json OUT] [--workers W]
        [--batch-streams B]

P is a built pipeline's directory: the root `.` (LunarLander) or `pipeline/<env>`. The check reads
what the pipeline committed or built there and nothing else: its params.yaml, the policy
(`models/policy.pt`), each detector's fitted model (the output of the fit stage in
`detectors/<detector>/dvc.yaml`, `models/detectors/<detector>.pkl`), each detector's per-stream
alarm threshold (its operating point's, in `reports/tier_results.json` or a protocol-4
pipeline's `reports/tier_results.yaml`), each fault's tier severities
(`data/impact/<fault>.yaml`) and the clean ID set (`data/id.zarr`: the reference statistics of
the live observation faults, as the impact stage uses them). A missing one is one line naming
the DVC command that restores it (exit 1).

It rolls FRESH seeds and prints two markdown tables (`--json OUT` writes them too):

(a) False alarms: per detector, the share of N fresh clean streams of `env.T` steps (the
    pipeline's stream length) that raise any alarm at the committed per-stream threshold, with
    its exact Clopper-Pearson 95% interval (`oodrl.metrics.operating.achieved_false_alarm_rate`),
    beside α (`tiers.alpha`, as the tier results state it). An alarm is `score >= threshold`;
    an alarm on the score of step t is raised at t + latency (the detector's look-ahead), and a
    raise at or after T is beyond the stream, so no alarm (`oodrl.metrics.operating.first_raise`,
    as `oodrl.metrics.tiers` counts detections). Each stream with an alarm counts once.
    Verdict: "not significantly above α" iff the interval's lower end is ≤ α, else "above α".
    Both per-stream rules (SPEC §24), each at its own committed threshold: the constant rule
    thresholds the scores as they are, the time-aware rule their per-step standardisation by
    the detector's scores of the pipeline's ID set (`scores/<detector>/id.zarr`, what the
    tier_metrics stage fits it on); a detector whose records hold no time-aware operating point
    (fewer than 300 ID scores) has a constant-rule row only.
(b) Tiers: per fault and every tier its impact document reaches (a tier whose severity is
    "unreachable" is listed, not measured), the normalised return R̃ = (R(σ) − R_rand) / (R_clean −
    R_rand) at the committed severity σ, measured on M fresh whole episodes with the fault live from
    step 0 (`oodrl.protocol.impact.faulty_returns`), R_clean on M fresh episodes (`clean_returns`)
    and R_rand on R (`random_policy_returns`, default 1,000: the random policy's mean return anchors
    every R̃ of a run at once, so its noise moves all of them together, and its episodes are cheap;
    150 of Pendulum's sat 57 above the impact stage's 200, lowering each fresh R̃ of the three
    Pendulum runs by up to 0.016), the episode length the impact document's `horizon`. Its 95%
    interval is the impact stage's percentile bootstrap (`metrics.n_boot` replicates; the policy's
    episodes resampled jointly over the clean run and the fault, the random policy's on their own).
    The verdict judges the interval against the band level ± 0.02, since M episodes measure R̃ only
    to within their interval: "within 0.02" iff the interval lies inside the band (shown to hold),
    "misses by ±d" iff it lies wholly outside (shown to fail; d = R̃ − level), else "undecided at M
    episodes" (the point estimate may fall either side; more episodes decide it). A stepped fault's
    tier is a step, not a level the search can hit (SPEC §19): its band is [the next tier's level
    (0.5 after severe), its own level] widened by 0.02, judged the same way and marked "(step)".

Episodes are collected by the project's collector (`oodrl.envs.collect.collect`, the impact
functions) and scored by the project's scoring code (`oodrl.protocol.scoring.score_set`), with the
fitted detectors as the pipeline saved them; nothing here re-implements a detector.

Seeds. With the pipeline's `seed` s and the offset S (default 3,000,000), the check uses
s + S + j (j < N) for the clean streams, s + S + POLICY_SEED_OFFSET + j (j < M) for the
policy's whole episodes (the clean run and every fault share them, as in the impact stage) and
s + S + RANDOM_SEED_OFFSET + j (j < R) for the random policy's; the faults draw from
`injector_rng(s + S, fault, j)`. An offset whose seeds overlap any set of the protocol is
refused (exit 2, one line): the ID streams s + i, the evaluation streams
s + data.eval_seed_offset + j, the tier calibration streams s + tiers.calibration_seed_offset
+ j, any further params set `<section>.<name>_seed_offset` (e.g. an audit set; its count the
section's `n_<name>` key, else a block of 100,000), the impact stage's blocks of 100,000 seeds
from s + POLICY_SEED_OFFSET and s + RANDOM_SEED_OFFSET (whole blocks: a tier search may draw
more episodes there), any other `*_SEED_OFFSET` constant of `oodrl.config` (a block of
100,000 each), the policy's tuning episodes policy.train.seed + 100,000 + i and its final
evaluation policy.train.final_eval_seed + i.

`--streams 0` or `--episodes 0` skips that half. `--detectors` and `--faults` pick subsets.
`--batch-streams B` scores the fresh clean streams B at a time (default: all in one call, as a
scoring stage scores a set): a detector that scores a batch at once holds the batch's work in
memory, and `action_consistency` runs the policy on nine copies of every step (about 73 MB a
500-step LunarLanderContinuous stream, so 400 streams would need about 29 GB). The contract of
a detector lets a stream's scores differ between batches only within `check_score_is_pure`'s
tolerance.

Costs on LunarLander (2 cores): the 400 clean streams of 500 steps and their scoring take a few
minutes; the tiers take (2 + the number of reachable tiers) × M whole episodes of up to 1000 steps.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

#: The default offset of the fresh seeds from the pipeline's `seed`: beyond every protocol set.
DEFAULT_SEED_OFFSET = 3_000_000
#: Seeds reserved for a set whose count is not known here (an impact block, a constant's set).
BLOCK = 100_000
#: The tolerance of the tier verdict (issue 39: "within 0.02 of its level").
TOLERANCE = 0.02
ID_STORE = "data/id.zarr"
SCORES_DIR = "scores"
POLICY = "models/policy.pt"
#: Where the check was started (it runs in the pipeline's directory, as the stages do).
_LAUNCH_DIR = Path.cwd()


# -- seeds ----------------------------------------------------------------------------------------
def _shown(seeds: range) -> str:
    return f"{seeds.start}..{seeds.stop - 1}"


def protocol_ranges(params) -> list[tuple[str, range]]:
    """Every set of seeds the pipeline's protocol uses (absolute seeds), with its name."""
    from pydantic import BaseModel

    import oodrl.config as config
    from oodrl.config import POLICY_SEED_OFFSET, RANDOM_SEED_OFFSET
    from oodrl.policies.train import TUNING_SEED_OFFSET

    seed, data, tiers = params.seed, params.data, params.tiers
    ranges = [
        ("ID streams", range(seed, seed + data.n_id)),
        ("evaluation streams", range(seed + data.eval_seed_offset,
                                     seed + data.eval_seed_offset + data.n_ood)),
        ("tier calibration streams", range(seed + tiers.calibration_seed_offset,
                                           seed + tiers.calibration_seed_offset
                                           + tiers.n_calibration)),
        ("policy's impact episodes (their block)",
         range(seed + POLICY_SEED_OFFSET, seed + POLICY_SEED_OFFSET + BLOCK)),
        ("random policy's impact episodes (their block)",
         range(seed + RANDOM_SEED_OFFSET, seed + RANDOM_SEED_OFFSET + BLOCK)),
    ]  # fmt: skip
    known = {("data", "eval_seed_offset"), ("tiers", "calibration_seed_offset")}
    for section_name in type(params).model_fields:
        section = getattr(params, section_name)
        if not isinstance(section, BaseModel):
            continue
        for key in type(section).model_fields:
            if not key.endswith("seed_offset") or (section_name, key) in known:
                continue
            offset = getattr(section, key)
            stem = key.removesuffix("seed_offset").rstrip("_")
            count = getattr(section, f"n_{stem}", None) if stem else None
            count = count if isinstance(count, int) else BLOCK
            ranges.append((f"{section_name}.{key} streams",
                           range(seed + offset, seed + offset + count)))  # fmt: skip
    for name in dir(config):
        value = getattr(config, name)
        if (
            name.endswith("_SEED_OFFSET")
            and name not in ("POLICY_SEED_OFFSET", "RANDOM_SEED_OFFSET")
            and isinstance(value, int)
        ):
            ranges.append((f"{name} streams", range(seed + value, seed + value + BLOCK)))
    train = params.policy_train_config()
    tuning = train.seed + TUNING_SEED_OFFSET
    ranges += [
        ("policy's tuning episodes", range(tuning, tuning + train.eval_episodes)),
        ("policy's final evaluation", range(train.final_eval_seed,
                                            train.final_eval_seed + train.final_eval_episodes)),
    ]  # fmt: skip
    return ranges


def fresh_ranges(
    params, offset: int, n_streams: int, n_episodes: int, n_random: int
) -> list[tuple[str, range]]:
    """The seeds the check uses (see the module docstring); empty sets left out."""
    from oodrl.config import POLICY_SEED_OFFSET, RANDOM_SEED_OFFSET

    base = params.seed + offset
    sets = [
        ("fresh clean streams", range(base, base + n_streams)),
        ("fresh policy episodes", range(base + POLICY_SEED_OFFSET,
                                        base + POLICY_SEED_OFFSET + n_episodes)),
        ("fresh random-policy episodes", range(base + RANDOM_SEED_OFFSET,
                                               base + RANDOM_SEED_OFFSET + n_random)),
    ]  # fmt: skip
    return [(name, seeds) for name, seeds in sets if len(seeds)]


def check_seeds(
    params, offset: int, n_streams: int, n_episodes: int, n_random: int
) -> list[tuple[str, range]]:
    """The fresh seed sets, or a ConfigError naming the first overlap."""
    from oodrl.errors import ConfigError

    fresh = fresh_ranges(params, offset, n_streams, n_episodes, n_random)
    hint = f"choose an offset whose seeds avoid every protocol set (default {DEFAULT_SEED_OFFSET})"
    for i, (name, seeds) in enumerate(fresh):
        if seeds.start < 0:
            raise ConfigError(
                f"--seed-offset {offset}: the {name} start at seed {seeds.start}; {hint}."
            )
        others = protocol_ranges(params) + fresh[:i]
        for other, used in others:
            if seeds.start < used.stop and used.start < seeds.stop:
                raise ConfigError(
                    f"--seed-offset {offset}: the {name} (seeds {_shown(seeds)}) overlap the "
                    f"{other} (seeds {_shown(used)}); {hint}."
                )
    return fresh


# -- the pipeline's outputs ------------------------------------------------------------------------
def _missing(path: str | Path, stage: str | None, what: str):
    from oodrl.errors import StoreError
    from oodrl.io.store import restore_hint

    where = "" if Path.cwd() == _LAUNCH_DIR else f" (in {os.path.relpath(Path.cwd(), _LAUNCH_DIR)})"
    return StoreError(f"{path}: {what} is missing; {restore_hint(Path(path), stage)}{where}.")


def fitted_detector_path(name: str) -> Path:
    """The fit stage's output in `detectors/<name>/dvc.yaml` (cwd: the pipeline)."""
    from oodrl.io import yamlio
    from oodrl.io.layout import detector_pipeline

    dvc_file = Path(detector_pipeline(name))
    if dvc_file.is_file():
        fit = (yamlio.load(dvc_file.read_text()).get("stages") or {}).get("fit") or {}
        outs = fit.get("outs") or []
        if outs:
            out = outs[0] if isinstance(outs[0], str) else next(iter(outs[0]))
            return Path(os.path.normpath(dvc_file.parent / fit.get("wdir", ".") / out))
    return Path("models/detectors") / f"{name}.pkl"


def committed_thresholds(
    detectors: list[str],
) -> tuple[dict[str, dict[str, float | None]], float, dict]:
    """Each detector's per-stream threshold under each rule (None: the time-aware rule has no
    operating point for it) and α, from the tier results (`load_tier_results`)."""
    from oodrl.api.results import rule_points
    from oodrl.errors import StoreError
    from oodrl.metrics.tier_results import load_tier_results, tier_results_path
    from oodrl.metrics.time_aware import RULES

    path = tier_results_path(Path("."))
    if not path.is_file():
        raise _missing(path, "tier_metrics", "the tier results file")
    document = load_tier_results(path)
    found: dict[tuple[str, str], set[float]] = {}
    alphas = set()
    for record in document.get("records") or []:
        if record.get("detector") not in detectors:
            continue
        for prefix, point in rule_points(record, alpha_curves=False):  # load_results' reading
            rule = "time_aware" if prefix else "constant"
            if "threshold" in point:
                found.setdefault((record["detector"], rule), set()).add(float(point["threshold"]))
                alphas.add(float(point.get("alpha", document.get("alpha"))))
    thresholds: dict[str, dict[str, float | None]] = {}
    for name in detectors:
        for rule in RULES:
            values = found.get((name, rule), set())
            if len(values) > 1 or (not values and rule == "constant"):
                what = "no threshold" if not values else f"{len(values)} different thresholds"
                raise StoreError(
                    f"{path}: {what} of detector {name!r} in its {rule} rule's operating points."
                )
            thresholds.setdefault(name, {})[rule] = values.pop() if values else None
    alpha = float(document.get("alpha", alphas.pop() if len(alphas) == 1 else math.nan))
    return thresholds, alpha, document


def id_scores_path(name: str) -> Path:
    """The detector's scores of the ID set, which the time-aware rule standardises by."""
    from oodrl.io.layout import id_score_store

    return id_score_store(Path(SCORES_DIR), name)


def committed_tiers(faults: list[str]) -> tuple[dict[str, dict], int | None]:
    """fault -> {tier: {level, severity}} of each impact document (unreachable kept as such),
    and the documents' episode horizon."""
    from oodrl.protocol.impact import LEVELS
    from oodrl.protocol.tiers import IMPACT_DIR, impact_path, read_impact

    tiers, horizon = {}, None
    for fault in faults:
        document = read_impact(impact_path(Path(IMPACT_DIR), fault), fault)
        horizon = horizon or document.get("horizon")
        levels = {name: float(t.get("level", LEVELS.get(name, math.nan)))
                  for name, t in (document["fault"].get("tiers") or {}).items()}  # fmt: skip
        stepped = "severity_steps" in document["fault"]
        tiers[fault] = {
            name: {"level": levels[name], "severity": t["severity"],
                   "band": tier_band(name, levels, stepped)}
            for name, t in (document["fault"].get("tiers") or {}).items()
        }  # fmt: skip
    return tiers, horizon


def tier_band(name: str, levels: dict[str, float], stepped: bool) -> tuple[float, float] | None:
    """The band a stepped fault's tier must fall in (see the module docstring); None for a
    continuous fault, whose band is its level ± TOLERANCE."""
    from oodrl.protocol.impact import (
        _tier_floor,  # the band the impact stage verifies a step against
    )

    if not stepped:
        return None
    return _tier_floor(name, levels) - TOLERANCE, levels[name] + TOLERANCE


def tier_verdict(low: float, high: float, value: float, level: float, band, n: int) -> str:
    """Judge R̃'s interval [low, high] from n episodes against the tier's band (see the module
    docstring)."""
    lo, hi = band if band is not None else (level - TOLERANCE, level + TOLERANCE)
    step = " (step)" if band is not None else ""
    if lo - 1e-12 <= low and high <= hi + 1e-12:
        return "within its band (step)" if band is not None else f"within {TOLERANCE}"
    if high < lo or low > hi:
        return f"misses by {value - level:+.3f}{step}"
    return f"undecided at {n} episodes{step}"


# -- (a) false alarms ------------------------------------------------------------------------------
def scores_in_batches(detector, name: str, streams, batch: int) -> np.ndarray:
    """The detector's scores (N, T) of the fresh clean streams, `batch` streams a call (0: all
    in one call)."""
    from oodrl.protocol.scoring import score_set

    step = batch or len(streams)
    parts = [
        score_set(detector, name, streams.subset(range(i, min(i + step, len(streams)))),
                  "the fresh clean streams")
        for i in range(0, len(streams), step)
    ]  # fmt: skip
    return np.concatenate(parts)


def false_alarms(
    params, detectors, thresholds, alpha, seeds: range, workers: int, batch: int = 0
) -> list[dict]:
    """Per detector and per-stream rule, the fresh clean streams' false-alarm rate at its
    committed threshold."""
    from oodrl.envs import ENVIRONMENTS
    from oodrl.envs.collect import collect
    from oodrl.io.layout import detector_stage
    from oodrl.io.store import load_detector
    from oodrl.metrics.operating import achieved_false_alarm_rate
    from oodrl.metrics.tiers import _time_aware_fit  # the tier_metrics stage's own fit
    from oodrl.metrics.time_aware import rule_scores
    from oodrl.policies.load import load_policy

    T = params.env.T  # noqa: N806
    adapter = ENVIRONMENTS.get(params.env.id)()
    policy = load_policy(Path(POLICY), mode=params.policy.mode)
    say(f"collecting {len(seeds)} fresh clean streams of {T} steps (seeds {_shown(seeds)})")
    started = time.perf_counter()
    clean = collect(adapter, policy, list(seeds), T, policy_seed=params.seed, workers=workers,
                    attrs={"mode": "clean", "spec": None})  # fmt: skip
    say(f"  collected in {time.perf_counter() - started:.0f} s")
    rows = []
    for name in detectors:
        started = time.perf_counter()
        detector = load_detector(fitted_detector_path(name), stage=detector_stage(name, "fit"))
        scores = scores_in_batches(detector, name, clean, batch)
        latency = params.detector(name).latency
        standardiser = None
        if thresholds[name]["time_aware"] is not None:
            standardiser, _ = _time_aware_fit(Path(SCORES_DIR), name)
        for rule, threshold in thresholds[name].items():
            if threshold is None:
                continue
            by_rule = standardiser if rule == "time_aware" else None
            alarms = rule_scores(scores, by_rule) >= threshold
            if latency:  # an alarm on step t is raised at t + latency: at or after T is none
                alarms[:, max(T - latency, 0) :] = False
            far = achieved_false_alarm_rate(alarms, params.metrics.ci)
            rows.append({
                "detector": name, "rule": rule, "threshold": threshold, "latency": latency,
                "n_streams": far.n_streams, "n_alarmed": far.n_alarmed, "rate": far.rate,
                "ci": [far.ci_low, far.ci_high], "alpha": alpha,
                "verdict": "not significantly above α" if far.ci_low <= alpha else "above α",
            })  # fmt: skip
            say(f"  {name} ({rule} rule): {far.n_alarmed}/{far.n_streams} alarmed "
                f"({time.perf_counter() - started:.0f} s)")  # fmt: skip
    return rows


# -- (b) tiers -------------------------------------------------------------------------------------
def bootstrap_normalised(faulty, clean, random, n_boot: int, ci: float, seed: int):
    """The impact stage's percentile bootstrap of R̃: π's episodes resampled jointly over the
    clean run and the fault (common seeds), the random policy's on their own."""
    from oodrl.protocol.impact import _normalised

    rng = np.random.default_rng(seed)
    policy_index = rng.integers(0, clean.size, size=(n_boot, clean.size))
    random_index = rng.integers(0, random.size, size=(n_boot, random.size))
    replicates = _normalised(
        faulty[policy_index].mean(axis=1),
        clean[policy_index].mean(axis=1),
        random[random_index].mean(axis=1),
    )
    tail = (1 - ci) / 2
    low, high = np.quantile(replicates, [tail, 1 - tail])
    return float(low), float(high)


def tier_check(
    params, faults, tiers, horizon, base_seed: int, n_episodes: int, n_random: int, workers: int
):
    """R_clean, R_rand and, per reachable (fault, tier), R̃ at the committed severity."""
    from oodrl.envs import ENVIRONMENTS
    from oodrl.policies.load import load_policy
    from oodrl.protocol.impact import (
        _normalised,
        clean_returns,
        episode_limit,
        faulty_returns,
        live_injectors,
        random_policy_returns,
        tier_severity,
    )

    adapter = ENVIRONMENTS.get(params.env.id)()
    policy = load_policy(Path(POLICY), mode=params.policy.mode)
    horizon = int(horizon or episode_limit(adapter))
    say(f"rolling {n_episodes} fresh whole episodes (horizon {horizon}) clean, {n_random} random")
    started = time.perf_counter()
    clean = clean_returns(adapter, policy, n_episodes, seed=base_seed, horizon=horizon,
                          workers=workers)  # fmt: skip
    random = random_policy_returns(adapter, n_random, seed=base_seed, horizon=horizon)
    say(f"  R_clean {clean.mean():.2f}, R_rand {random.mean():.2f} "
        f"({time.perf_counter() - started:.0f} s)")  # fmt: skip
    injectors = live_injectors(params, faults, Path(ID_STORE))
    rows = []
    for fault in faults:
        reachable = {n: tier_severity(t) for n, t in tiers[fault].items()
                     if tier_severity(t) is not None}  # fmt: skip
        for name, t in tiers[fault].items():
            if tier_severity(t) is None:  # unreachable, or not reached by the search
                rows.append({"fault": fault, "tier": name, "level": t["level"],
                             "severity": t["severity"]})  # fmt: skip
        if not reachable:
            continue
        started = time.perf_counter()
        returns = faulty_returns(
            adapter, policy, injectors[fault], sorted(set(reachable.values())), n_episodes,
            seed=base_seed, horizon=horizon, workers=workers,
        )  # fmt: skip
        for name, severity in reachable.items():
            faulty, level = returns[severity], tiers[fault][name]["level"]
            value = float(_normalised(faulty.mean(), clean.mean(), random.mean()))
            low, high = bootstrap_normalised(
                faulty, clean, random, params.metrics.n_boot, params.metrics.ci, base_seed
            )
            gap = value - level
            rows.append({
                "fault": fault, "tier": name, "level": level, "severity": severity,
                "n_episodes": int(faulty.size), "normalised": value, "ci": [low, high],
                "difference": gap, "level_in_ci": bool(low <= level <= high),
                "verdict": tier_verdict(
                    low, high, value, level, tiers[fault][name]["band"], faulty.size
                ),
            })  # fmt: skip
        measured = ", ".join(
            f"{r['tier']} σ {r['severity']:.4g} R̃ {r['normalised']:.3f} "
            f"[{r['ci'][0]:.3f}, {r['ci'][1]:.3f}] (level {r['level']:g})"
            for r in rows[-len(reachable) :]
        )
        say(f"  {fault}: {measured} ({time.perf_counter() - started:.0f} s)")
    summary = {
        "clean_return": float(clean.mean()),
        "random_return": float(random.mean()),
        "n_clean": int(clean.size),
        "n_random": int(random.size),
        "horizon": horizon,
    }
    return summary, rows


# -- output ----------------------------------------------------------------------------------------
def far_table(rows: list[dict], T: int) -> str:  # noqa: N803
    lines = [
        "| detector | rule | threshold | latency | streams | alarmed | FAR [95% CI] | α "
        "| verdict |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['detector']} | {r['rule']} | {r['threshold']:.4g} | {r['latency']} | "
            f"{r['n_streams']} | "
            f"{r['n_alarmed']} | {r['rate']:.3f} [{r['ci'][0]:.3f}, {r['ci'][1]:.3f}] | "
            f"{r['alpha']:g} | {r['verdict']} |"
        )
    return "\n".join(lines)


def tier_table(rows: list[dict]) -> str:
    lines = [
        "| fault | tier | σ | level | episodes | R̃ [95% CI] | R̃ − level | level in CI | verdict |",
        "|---|---|---:|---:|---:|---:|---:|---|---|",
    ]
    for r in rows:
        if r["severity"] == "unreachable":
            lines.append(f"| {r['fault']} | {r['tier']} | unreachable | {r['level']:g} | — | — | "
                         "— | — | not measured |")  # fmt: skip
            continue
        lines.append(
            f"| {r['fault']} | {r['tier']} | {r['severity']:.4g} | {r['level']:g} | "
            f"{r['n_episodes']} | {r['normalised']:.3f} [{r['ci'][0]:.3f}, {r['ci'][1]:.3f}] | "
            f"{r['difference']:+.3f} | {'yes' if r['level_in_ci'] else 'no'} | {r['verdict']} |"
        )
    return "\n".join(lines)


def say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def report(result: dict[str, Any]) -> str:
    """The markdown the check prints."""
    seeds = ", ".join(f"{name} {seeds}" for name, seeds in result["seeds"].items())
    out = [
        f"# Fresh-data check: {result['pipeline']} ({result['env_id']})",
        "",
        f"Seed offset {result['seed_offset']} from seed {result['seed']}: {seeds}.",
        "",
    ]
    if result.get("false_alarms") is not None:
        rows = result["false_alarms"]
        n = rows[0]["n_streams"] if rows else 0
        ok = sum(r["verdict"] == "not significantly above α" for r in rows)
        out += [
            f"## False alarms: {n} fresh clean streams of {result['T']} steps per detector, "
            "at each detector's per-stream thresholds, both rules (the committed tier results)",
            "",
            far_table(rows, result["T"]),
            "",
            f"{ok} of {len(rows)} (detector, rule) pairs not significantly above α "
            f"(Clopper-Pearson 95%; each rate from {n} streams).",
            "",
        ]
    if result.get("tiers") is not None:
        summary, rows = result["tiers"]["returns"], result["tiers"]["rows"]
        measured = [r for r in rows if r["severity"] != "unreachable"]
        verdicts = [r["verdict"] for r in measured]
        shown = sum(v.startswith("within") for v in verdicts)
        missed = sum(v.startswith("misses") for v in verdicts)
        out += [
            f"## Tiers: R̃ at the committed severities (data/impact/<fault>.yaml), "
            f"{summary['n_clean']} fresh whole episodes per condition",
            "",
            f"R_clean = {summary['clean_return']:.2f} ({summary['n_clean']} episodes), "
            f"R_rand = {summary['random_return']:.2f} ({summary['n_random']} episodes), "
            f"episodes of up to {summary['horizon']} steps.",
            "",
            tier_table(rows),
            "",
            f"Of {len(measured)} reachable tiers, {shown} shown within {TOLERANCE} of their level "
            f"(a step: within its band), {missed} shown to miss it, "
            f"{len(measured) - shown - missed} undecided; each R̃ from {summary['n_clean']} "
            f"episodes under the fault, {summary['n_clean']} clean, {summary['n_random']} random; "
            f"{sum(abs(r['difference']) <= TOLERANCE + 1e-12 for r in measured)} point estimates "
            f"within {TOLERANCE} of the level.",
            "",
        ]
    return "\n".join(out)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from oodrl.config import load_params
    from oodrl.errors import ConfigError

    if args.streams < 0 or args.episodes < 0 or args.episodes == 1 or args.batch_streams < 0:
        raise ConfigError(
            f"--streams and --batch-streams must be >= 0 and --episodes 0 or >= 2; got "
            f"{args.streams}, {args.batch_streams} and {args.episodes}."
        )
    if args.random_episodes < 2:
        raise ConfigError(f"--random-episodes must be >= 2; got {args.random_episodes}.")
    n_random = args.random_episodes if args.episodes else 0
    pipeline = Path(args.pipeline)
    if not (pipeline / "params.yaml").is_file():
        raise ConfigError(f"--pipeline {pipeline}: no params.yaml there; a pipeline directory is "
                          "the root (.) or pipeline/<env>.")  # fmt: skip
    json_out = Path(args.json).resolve() if args.json else None
    os.chdir(pipeline)  # as the stage commands run: paths and restore hints read from there
    params = load_params(Path("params.yaml"))
    fresh = check_seeds(params, args.seed_offset, args.streams, args.episodes, n_random)

    def pick(given, allowed, flag):
        unknown = [n for n in given or [] if n not in allowed]
        if unknown:
            raise ConfigError(f"{flag}: {unknown[0]!r} is not in this pipeline's benchmark; "
                              f"allowed: {', '.join(allowed)}.")  # fmt: skip
        return list(given or allowed)

    detectors = pick(args.detectors, params.benchmark.detectors, "--detectors")
    faults = pick(args.faults, params.benchmark.injectors, "--faults")
    # Every input first, so that a missing one is one line before anything runs.
    if not Path(POLICY).is_file():
        raise _missing(POLICY, "train_policy", "the policy")
    thresholds, alpha, tiers, horizon = {}, params.tiers.alpha, {}, None
    if args.streams:
        from oodrl.io.layout import detector_stage

        thresholds, alpha, _ = committed_thresholds(detectors)
        for name in detectors:
            path = fitted_detector_path(name)
            if not path.is_file():
                raise _missing(path, detector_stage(name, "fit"), "the fitted detector")
            if thresholds[name]["time_aware"] is not None and not id_scores_path(name).exists():
                raise _missing(id_scores_path(name), detector_stage(name, "score_clean"),
                               "the detector's scores of the ID set")  # fmt: skip
    if args.episodes:
        tiers, horizon = committed_tiers(faults)
        if not Path(ID_STORE).exists():
            raise _missing(ID_STORE, "collect_id", "the clean ID set")
    workers = args.workers or params.executor.resolved_workers
    base = params.seed + args.seed_offset
    result: dict[str, Any] = {
        "pipeline": args.pipeline, "env_id": params.env.id, "T": params.env.T,
        "seed": params.seed, "seed_offset": args.seed_offset,
        "seeds": {name: _shown(seeds) for name, seeds in fresh},
        "false_alarms": None, "tiers": None,
    }  # fmt: skip
    if args.streams:
        result["false_alarms"] = false_alarms(
            params, detectors, thresholds, alpha, fresh[0][1], workers, args.batch_streams
        )
    if args.episodes:
        summary, rows = tier_check(
            params, faults, tiers, horizon, base, args.episodes, n_random, workers
        )
        result["tiers"] = {"returns": summary, "rows": rows}
    text = report(result)
    print(text, flush=True)
    if json_out:
        json_out.write_text(json.dumps(result, indent=1, ensure_ascii=False) + "\n")
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pipeline", required=True, help="the root (.) or pipeline/<env>")
    parser.add_argument("--streams", type=int, default=400, help="fresh clean streams (0: skip)")
    parser.add_argument("--episodes", type=int, default=150,
                        help="fresh whole episodes per condition (0: skip)")  # fmt: skip
    parser.add_argument("--random-episodes", type=int, default=1000,
                        help="fresh random-policy episodes for R_rand")  # fmt: skip
    parser.add_argument("--seed-offset", type=int, default=DEFAULT_SEED_OFFSET)
    parser.add_argument("--detectors", nargs="+", help="a subset of benchmark.detectors")
    parser.add_argument("--faults", nargs="+", help="a subset of benchmark.injectors")
    parser.add_argument("--json", help="also write the tables' rows as JSON here")
    parser.add_argument("--workers", type=int, default=0, help="0: executor.workers of params")
    parser.add_argument("--batch-streams", type=int, default=0,
                        help="clean streams scored per call (0: all in one)")  # fmt: skip
    args = parser.parse_args(argv)
    from oodrl.errors import ConfigError, OodrlError, RegistryError

    try:
        run(args)
    except OodrlError as error:
        if os.environ.get("OODRL_DEBUG") == "1":
            raise
        message = " ".join(line.strip() for line in str(error).splitlines() if line.strip())
        print(f"error: {message}", file=sys.stderr)
        return 2 if isinstance(error, ConfigError | RegistryError) else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
