"""The suite's leaderboard statistics (SPEC §12, §15, §16), with rliable's definitions
(Agarwal et al. 2021, "Deep RL at the edge of the statistical precipice").

A *cell* is (environment, policy, fault, tier): a policy is one training seed of the
environment's policy (runs before policy seeds are policy "0"); a tier is an impact tier
(`mild`, `moderate`, `severe`; `benign`, the harmless-shift control, where a detection is a
false alarm) or, for results scored at one fixed severity, `headline`.
A *task* is a cell without its policy, (environment, fault, tier): the policies of a task are
its *runs*. In each cell a detector has one value per episode (matched AUROC per episode, or
0/1 per faulty stream for `detection_rate@K`); the *score* of a (run, task) is their mean.
Per detector, over the tasks of one aggregate:

- mean: the mean over tasks of the mean over runs (rliable's `aggregate_mean`);
- IQM: the 25%-trimmed mean of all (run, task) scores (rliable's `aggregate_iqm`; tasks with
  more runs put more scores into the pool);
- optimality gap: 1 − the mean of all (run, task) scores capped at 1 (rliable's
  `aggregate_optimality_gap` with γ = 1);
- performance profile: the share of (run, task) scores ≥ τ for τ in [0.5, 1] (rliable counts
  > τ; ≥ keeps the ceiling visible: at τ = 1 it is the share of perfect scores);
- P(A > B): per task the Mann-Whitney statistic of A's runs against B's, U / (n_A · n_B) with
  ties ½, averaged over tasks (rliable's `probability_of_improvement`);
- a detector × environment table: the mean over an environment's tasks of the task means.

CIs are stratified percentile bootstraps, the strata being the tasks, so tasks are never mixed
and each keeps its weight. A task with several runs resamples its runs, each detector's
independently (rliable's `StratifiedBootstrap`, and `StratifiedIndependentBootstrap` for
P(improvement)). A task with one run cannot resample runs: it resamples its episodes instead,
every detector of the task with the same episodes (they are paired: same episodes, same
seeds), as the suite's leaderboard did before policies had seeds. `Aggregate.bootstrap` says
which one a table used. Task number c (in sorted order) draws from `default_rng([seed, c])`.

The time-aware per-stream rule's detections (`time_aware_detection_rate@K`, SPEC §24) are not
ranked: `build_board` compares them per tier with `detection_rate@K` on the same streams, over
the cells that hold both (`rule_changes`, `oodrl.metrics.rule_change`; `Board.rule_change`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from oodrl.metrics.aggregate import interquartile_mean

if TYPE_CHECKING:
    from oodrl.metrics.rule_change import RuleChange


class Cell(NamedTuple):
    """One (environment, policy, fault, tier)."""

    environment: str
    policy: str
    fault: str
    tier: str


#: A cell without its policy: (environment, fault, tier).
Task = tuple[str, str, str]
#: cell → detector → per-episode values.
CellValues = Mapping[Cell, Mapping[str, Sequence[float]]]

#: Impact tiers, the hardest to detect first (SPEC §15).
TIERS = ("mild", "moderate", "severe")
#: The harmless-shift control (SPEC §19): detection there is a false alarm, so lower is better.
BENIGN_TIER = "benign"
#: The tier of results scored at one fixed severity (the protocol before impact tiers).
HEADLINE_TIER = "headline"
#: The policy of an environment that has one (results before policy seeds).
FIRST_POLICY = "0"
FAULT_FAMILIES: dict[str, tuple[str, ...]] = {
    "observation": (
        "gaussian_state_noise",
        "state_feature_dropout",
        "correlation_break",
        "regime_switch",
        "observation_delay",
    ),
    "action": ("stuck_actuator", "action_conditioned_dynamics"),
    "dynamics": ("dynamics_scaling", "gradual_drift"),
}
#: The family of a fault outside the built-in ones (a plugin injector).
OTHER_FAMILY = "other"
#: The thresholds τ of the performance profiles.
PROFILE_TAUS: tuple[float, ...] = tuple(round(0.5 + 0.01 * i, 2) for i in range(51))
#: Detectors that see only a trivial signal (the time index; the episode return).
TRIVIAL_DETECTORS = ("time_index", "episode_return")
#: A task is flagged when a trivial detector's matched AUROC there reaches this.
TRIVIAL_THRESHOLD = 0.9
#: The floor every ranking shows (SPEC §20): scores that ignore the data, thresholded like any
#: detector's, so its detection rate is what alarms alone buy.
FLOOR_DETECTOR = "random_scores"
#: The metric every results file holds per episode.
MATCHED_AUROC = "matched_auroc"
#: What names a record's per-stream detections under the time-aware rule (SPEC §24) beside the
#: constant rule's `detection_rate@K`: `time_aware_detection_rate@K` (`time_aware_metric`).
TIME_AWARE_PREFIX = "time_aware_"


def time_aware_metric(metric: str) -> str:
    """The per-episode values of `metric` (a `detection_rate@K`) under the time-aware rule."""
    return TIME_AWARE_PREFIX + metric


def constant_metric(metric: str) -> str | None:
    """The constant rule's metric whose time-aware values `metric` holds; None for a metric of
    its own."""
    return metric.removeprefix(TIME_AWARE_PREFIX) if metric.startswith(TIME_AWARE_PREFIX) else None


def fault_family(fault: str) -> str:
    """observation, action or dynamics (SPEC §15); `other` for a fault outside them."""
    return next((f for f, faults in FAULT_FAMILIES.items() if fault in faults), OTHER_FAMILY)


def tier_order(tiers: Iterable[str]) -> list[str]:
    """Tiers mild first, then moderate, severe, benign, headline, then any other by name."""
    known = (*TIERS, BENIGN_TIER, HEADLINE_TIER)
    return sorted(set(tiers), key=lambda t: (known.index(t) if t in known else len(known), t))


def metric_order(metrics: Iterable[str]) -> list[str]:
    """`detection_rate@K` metrics first (the operating point people deploy), then the rest."""
    return sorted(set(metrics), key=lambda m: (not m.startswith("detection_rate"), m))


def policy_key(policy: str) -> tuple[int, int, str]:
    """Numbered policies in numeric order ("2" before "10"), then named ones."""
    return (0, int(policy), "") if policy.isdigit() else (1, 0, policy)


@dataclass(frozen=True)
class Interval:
    """A point estimate with its bootstrap percentile CI."""

    value: float
    ci_low: float
    ci_high: float

    def as_dict(self, decimals: int = 6) -> dict[str, float]:
        return {k: round(float(v), decimals) + 0.0 for k, v in vars(self).items()}


#: `Aggregate.bootstrap` when every task resamples its runs / its episodes.
BOOTSTRAP_RUNS = "runs"
BOOTSTRAP_EPISODES = "episodes"


@dataclass(frozen=True)
class Aggregate:
    """One metric aggregated over a set of tasks (see the module doc)."""

    detectors: tuple[str, ...]
    tasks: tuple[Task, ...]
    #: The number of runs (policies) of each task, in `tasks` order.
    runs: tuple[int, ...]
    #: "runs", "episodes", or "runs; episodes in k of n cells with one run".
    bootstrap: str
    table: dict[str, dict[str, float]]
    mean: dict[str, Interval]
    iqm: dict[str, Interval]
    optimality_gap: dict[str, Interval]
    #: (A, B) → P(A > B), the Mann-Whitney statistic over runs averaged over tasks.
    improvement: dict[tuple[str, str], Interval]
    taus: tuple[float, ...]
    #: detector → the share of (run, task) scores ≥ τ, one Interval per τ of `taus`.
    profile: dict[str, tuple[Interval, ...]]

    @property
    def n_cells(self) -> int:
        return len(self.tasks)

    @property
    def n_scores(self) -> int:
        return sum(self.runs)

    @property
    def environments(self) -> tuple[str, ...]:
        return tuple(sorted({task[0] for task in self.tasks}))

    def ranked(self) -> list[str]:
        """Detectors by IQM, best first (ties by name)."""
        return sorted(self.detectors, key=lambda d: (-self.iqm[d].value, d))


def _mann_whitney(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """U / (n_a · n_b) over the last axes (a: (..., n_a), b: (..., n_b)): the share of pairs
    with a > b, ties ½. U = (pairs + Σ sign(a − b)) / 2 is a whole or half count, so the one
    division that remains gives scipy's statistic to the bit."""
    a, b = np.broadcast_arrays(a[..., :, None], b[..., None, :])
    signs = np.subtract(a > b, a < b, dtype=np.int8).reshape(*a.shape[:-2], -1)
    return (signs.shape[-1] + signs.sum(axis=-1, dtype=np.int64)) / 2 / signs.shape[-1]


def _task_runs(
    cells: CellValues, detectors: tuple[str, ...]
) -> dict[Task, list[dict[str, np.ndarray]]]:
    """Task → its runs in policy order, each detector → per-episode values."""
    runs: dict[Task, list[tuple[str, dict[str, np.ndarray]]]] = {}
    for cell, values in cells.items():
        cell = Cell(*cell)
        if tuple(sorted(values)) != detectors:
            raise ValueError(f"cell {tuple(cell)} has detectors {sorted(values)}, not {detectors}")
        episodes = {d: np.asarray(values[d], dtype=np.float64) for d in detectors}
        for d, v in episodes.items():
            if v.ndim != 1 or v.size == 0 or not np.isfinite(v).all():
                raise ValueError(f"cell {tuple(cell)}: {d} needs finite per-episode values")
        task = (cell.environment, cell.fault, cell.tier)
        runs.setdefault(task, []).append((cell.policy, episodes))
    return {
        task: [v for _, v in sorted(found, key=lambda pv: policy_key(pv[0]))]
        for task, found in sorted(runs.items())
    }


def _replicates(
    runs: list[dict[str, np.ndarray]], detectors: tuple[str, ...], n_boot: int, rng
) -> tuple[np.ndarray, np.ndarray | None]:
    """(detectors, n_boot, runs) replicate run scores of one task (see the module doc) and,
    where runs are resampled, how often each run was drawn (detectors, n_boot, runs)."""
    if len(runs) == 1:
        sizes = {runs[0][d].size for d in detectors}
        if len(sizes) != 1:
            raise ValueError(
                f"one-run cells need one episode count for every detector; got {sizes}"
            )
        episodes = np.stack([runs[0][d] for d in detectors])  # (detectors, episodes)
        n = episodes.shape[1]
        index = rng.integers(0, n, size=(n_boot, n))
        return episodes[:, index].mean(axis=2)[:, :, None], None
    scores = np.array([[run[d].mean() for run in runs] for d in detectors])  # (detectors, runs)
    index = rng.integers(0, len(runs), size=(len(detectors), n_boot, len(runs)))
    counts = (index[..., None] == np.arange(len(runs))).sum(axis=2)
    return scores[np.arange(len(detectors))[:, None, None], index], counts


def _signs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """sign(a − b) as int8, by comparison (exact for any finite floats)."""
    return np.subtract(a > b, a < b, dtype=np.int8)


def _replicate_wins(scores: np.ndarray, replicates: np.ndarray, counts: np.ndarray | None):
    """(D, D, n_boot): every detector pair's U / (n · n) on one task in every replicate.

    With resampled runs, U counts the pairs of drawn runs: Σ_ij c_a[i] c_b[j] sign(s_a[i] −
    s_b[j]) over the original run scores s and draw counts c, which is `_mann_whitney` of the
    replicate scores without comparing n × n drawn values anew in every replicate.
    """
    if counts is None:  # one run: the replicate scores compared directly
        one = replicates[..., 0]
        return (1 + _signs(one[:, None], one[None, :])) / 2
    pairs = scores.shape[1] ** 2
    signs = _signs(scores[:, None, :, None], scores[None, :, None, :]).astype(np.float64)
    weights = counts.transpose(0, 2, 1).astype(np.float64)  # (D, R, n_boot)
    # Whole numbers throughout, so the float products and sums are exact.
    by_b = signs @ weights[None]  # (D, D, R, n_boot): Σ_j sign[a, b, i, j] c_b[j]
    total = (weights[:, None] * by_b).sum(axis=2)  # Σ_i c_a[i] (…)
    return (pairs + total) / 2 / pairs


def aggregate(
    cells: CellValues,
    n_boot: int = 1000,
    ci: float = 0.95,
    seed: int = 0,
    taus: Sequence[float] = PROFILE_TAUS,
) -> Aggregate:
    """Aggregate per-episode values ``cells[Cell(env, policy, fault, tier)][detector]``.

    Every cell must hold every detector; a task with one run needs the same number of
    episodes for each detector (they are resampled together).
    """
    if not cells:
        raise ValueError("no cells to aggregate")
    detectors = tuple(sorted(next(iter(cells.values()))))
    by_task = _task_runs(cells, detectors)
    tasks = tuple(by_task)
    runs = tuple(len(by_task[t]) for t in tasks)
    scores = [np.array([[r[d].mean() for r in by_task[t]] for d in detectors]) for t in tasks]
    drawn = [
        _replicates(by_task[t], detectors, n_boot, np.random.default_rng([seed, c]))
        for c, t in enumerate(tasks)
    ]
    replicates = [r for r, _ in drawn]
    # The pool of (run, task) scores, run-major: with equal runs, rliable's (runs × tasks) in C
    # order, so the IQM is computed on the same sequence of numbers.
    pool = [(r, c) for r in range(max(runs)) for c in range(len(tasks)) if r < runs[c]]
    point_pool = np.stack([scores[c][:, r] for r, c in pool], axis=-1)  # (D, P)
    replicate_pool = np.stack([replicates[c][:, :, r] for r, c in pool], axis=-1)  # (D, B, P)
    task_means = np.stack([s.mean(axis=1) for s in scores], axis=-1)  # (D, T)
    replicate_task_means = np.stack([r.mean(axis=2) for r in replicates], axis=-1)  # (D, B, T)

    def intervals(points: np.ndarray, draws: np.ndarray) -> np.ndarray:
        """(..., 3): each point with the percentile CI of its draws (..., n_boot)."""
        low, high = np.quantile(draws, [(1 - ci) / 2, (1 + ci) / 2], axis=-1)
        return np.stack([points, low, high], axis=-1)

    def by_detector(values: np.ndarray) -> dict[str, Interval]:
        return {d: Interval(*map(float, values[i])) for i, d in enumerate(detectors)}

    def gap(pooled: np.ndarray) -> np.ndarray:
        return 1.0 - np.minimum(pooled, 1.0).mean(axis=-1)

    environments = sorted({t[0] for t in tasks})
    table = {
        d: {
            env: float(np.mean([task_means[i, c] for c, t in enumerate(tasks) if t[0] == env]))
            for env in environments
        }
        for i, d in enumerate(detectors)
    }
    mean = intervals(task_means.mean(axis=-1), replicate_task_means.mean(axis=-1))
    iqm = intervals(interquartile_mean(point_pool), interquartile_mean(replicate_pool))
    optimality_gap = intervals(gap(point_pool), gap(replicate_pool))
    point_wins = np.stack([_mann_whitney(s[:, None], s[None, :]) for s in scores], axis=-1)
    replicate_wins = sum(
        _replicate_wins(s, r, counts) for s, (r, counts) in zip(scores, drawn, strict=True)
    ) / len(tasks)  # (D, D, n_boot)
    wins = intervals(point_wins.mean(axis=-1), replicate_wins)
    improvement = {
        (a, b): Interval(*map(float, wins[i, j]))
        for i, a in enumerate(detectors)
        for j, b in enumerate(detectors)
        if i != j
    }
    size = point_pool.shape[-1]
    shares = intervals(
        np.stack([np.count_nonzero(point_pool >= t, axis=-1) / size for t in taus], axis=-1),
        np.stack([np.count_nonzero(replicate_pool >= t, axis=-1) / size for t in taus], axis=1),
    )  # (D, taus, 3)
    profile = {
        d: tuple(Interval(*map(float, v)) for v in shares[i]) for i, d in enumerate(detectors)
    }
    return Aggregate(
        detectors, tasks, runs, _bootstrap_name(runs), table, by_detector(mean),
        by_detector(iqm), by_detector(optimality_gap), improvement,
        tuple(float(t) for t in taus), profile,
    )  # fmt: skip


def _bootstrap_name(runs: Sequence[int]) -> str:
    single = sum(1 for r in runs if r == 1)
    if single == 0:
        return BOOTSTRAP_RUNS
    if single == len(runs):
        return BOOTSTRAP_EPISODES
    return f"{BOOTSTRAP_RUNS}; {BOOTSTRAP_EPISODES} in {single} of {len(runs)} cells with one run"


@dataclass(frozen=True)
class Stability:
    """How stable the ranking is across policies (SPEC §16): each policy's own ranking by the
    IQM of its scores on the shared tasks, its winner, and Kendall's τ-b between every two
    policies. The shared tasks are the (environment, fault, tier) that every policy has a cell
    of: a policy's ranking over other environments than another's would measure the
    environments, not the policies (most environments have one policy)."""

    policies: tuple[str, ...]
    #: The tasks every policy has a cell of, sorted.
    tasks: tuple[Task, ...]
    iqm: dict[str, dict[str, float]]
    winners: dict[str, str]
    #: (p, q) → Kendall's τ between the detectors' IQMs under p and under q (p before q).
    kendall_tau: dict[tuple[str, str], float]

    @property
    def mean_tau(self) -> float | None:
        taus = [t for t in self.kendall_tau.values() if np.isfinite(t)]
        return float(np.mean(taus)) if taus else None


def ranking_stability(cells: CellValues) -> Stability:
    """Per policy, the detectors' IQM over the shared tasks, the winner, and Kendall's τ."""
    from scipy.stats import kendalltau

    by_policy: dict[str, dict[Task, Mapping[str, Sequence[float]]]] = {}
    for cell, values in cells.items():
        environment, policy, fault, tier = Cell(*cell)
        by_policy.setdefault(policy, {})[(environment, fault, tier)] = values
    policies = tuple(sorted(by_policy, key=policy_key))
    tasks = tuple(sorted(set.intersection(*(set(by_policy[p]) for p in policies))))
    detectors = sorted(next(iter(cells.values())))
    if not tasks:
        return Stability(policies, tasks, {}, {}, {})
    iqm = {}
    for p in policies:
        mine = [by_policy[p][task] for task in tasks]
        scores = np.array([[np.mean(values[d]) for values in mine] for d in detectors])
        iqm[p] = {d: float(interquartile_mean(scores[i])) for i, d in enumerate(detectors)}
    winners = {p: min(detectors, key=lambda d, p=p: (-iqm[p][d], d)) for p in policies}
    kendall = {
        (p, q): float(
            kendalltau([iqm[p][d] for d in detectors], [iqm[q][d] for d in detectors]).statistic
        )
        for i, p in enumerate(policies)
        for q in policies[i + 1 :]
    }
    return Stability(policies, tasks, iqm, winners, kendall)


def above_floor(board: Aggregate, floor: str = FLOOR_DETECTOR) -> dict[str, bool] | None:
    """Per detector, whether it beats the floor: P(detector > floor) on a random cell, whose
    stratified-bootstrap CI lies above ½. None when the floor is not in the board."""
    if floor not in board.detectors:
        return None
    return {d: board.improvement[(d, floor)].ci_low > 0.5 for d in board.detectors if d != floor}


def trivial_flags(
    auroc_cells: CellValues,
    detectors: Sequence[str] = TRIVIAL_DETECTORS,
    threshold: float = TRIVIAL_THRESHOLD,
) -> dict[Task, dict[str, float]]:
    """Tasks a trivial signal already detects → {trivial detector: its score there}.

    A task is flagged when a trivial detector present in the results reaches `threshold` on
    the task's matched AUROC (the mean over runs of the per-episode means), i.e. when knowing
    the time step alone, or the episode's return, already tells the faulty stream apart.
    """
    runs: dict[Task, dict[str, list[float]]] = {}
    for cell, values in auroc_cells.items():
        cell = Cell(*cell)
        task = (cell.environment, cell.fault, cell.tier)
        for d in detectors:
            if d in values:
                runs.setdefault(task, {}).setdefault(d, []).append(float(np.mean(values[d])))
    flagged: dict[Task, dict[str, float]] = {}
    for task, found in sorted(runs.items()):
        over = {d: float(np.mean(v)) for d, v in found.items() if np.mean(v) >= threshold}
        if over:
            flagged[task] = over
    return flagged


@dataclass(frozen=True)
class Board:
    """Leaderboard v2: every (metric, tier) aggregated over all its tasks and per fault
    family, the ranking's stability across policies, and the trivially detected tasks."""

    metrics: tuple[str, ...]
    tiers: tuple[str, ...]
    overall: dict[tuple[str, str], Aggregate]
    families: dict[tuple[str, str], dict[str, Aggregate]]
    stability: dict[tuple[str, str], Stability]
    flagged: dict[Task, dict[str, float]]
    #: (metric, tier) → the aggregate without the flagged tasks, where some but not all are.
    unflagged: dict[tuple[str, str], Aggregate]
    #: (metric, tier) → the aggregates over the cells where more detectors run than on every
    #: cell (`detector_scopes`); empty where every cell has the same detectors.
    scoped: dict[tuple[str, str], tuple[Aggregate, ...]] = field(default_factory=dict)
    #: (metric, tier) → what the time-aware rule changes of `metric` on that tier's cells that
    #: hold both rules (`rule_changes`); empty where no record holds the time-aware rule.
    rule_change: dict[tuple[str, str], RuleChanges] = field(default_factory=dict)

    def order(self) -> list[tuple[str, str]]:
        """Every (metric, tier) aggregated: tiers mild first, within one `detection_rate@K`
        first."""
        return sorted(
            self.overall, key=lambda k: (self.tiers.index(k[1]), self.metrics.index(k[0]))
        )

    @property
    def lead(self) -> tuple[str, str]:
        """The (metric, tier) the leaderboard leads with: the first of `order`."""
        return self.order()[0]


@dataclass(frozen=True)
class RuleChanges:
    """What the time-aware rule changes of a detection rate on one tier (SPEC §24;
    `oodrl.metrics.rule_change`): over the cells whose records hold both rules, per scope of
    detectors (`detector_scopes`: the detectors every such cell has, then each larger set)
    the paired comparison, with the environments of its cells."""

    #: The cells of the tier with both rules, and all the tier's cells of the metric.
    n_cells: int
    n_tier_cells: int
    #: (environments, comparison) per scope, the scope of every cell first.
    scopes: tuple[tuple[tuple[str, ...], RuleChange], ...]

    @property
    def detectors(self) -> list[str]:
        """Every detector compared, those of every cell first, then the others by name."""
        first = list(self.scopes[0][1].detectors)
        rest = {d for _, change in self.scopes[1:] for d in change.detectors} - set(first)
        return first + sorted(rest)

    def of(self, detector: str) -> tuple[tuple[str, ...], RuleChange]:
        """(environments, comparison) of the first scope that compares `detector`: over every
        cell where it runs."""
        return next((e, c) for e, c in self.scopes if detector in c.detectors)


def rule_changes(
    constant: CellValues, time_aware: CellValues, *, n_boot: int = 1000, ci: float = 0.95,
    seed: int = 0,
) -> RuleChanges | None:  # fmt: skip
    """The time-aware rule against the constant one on one tier's cells (`constant`: every cell
    of the tier; `time_aware`: the cells whose records hold the time-aware rule): over the cells
    where every detector of the cell has both (results of protocol 3 hold one rule: not in it),
    per scope of detectors. None when no cell has both."""
    from oodrl.metrics.rule_change import rule_change

    both = {
        Cell(*c): v for c, v in constant.items() if c in time_aware and set(time_aware[c]) == set(v)
    }
    if not both:
        return None
    scopes = []
    for scope in detector_scopes(both):
        paired = {c: {d: time_aware[c][d] for d in v} for c, v in scope.items()}
        environments = tuple(sorted({c.environment for c in scope}))
        scopes.append((environments, rule_change(scope, paired, n_boot=n_boot, ci=ci, seed=seed)))
    return RuleChanges(len(both), len(constant), tuple(scopes))


def detector_scopes(cells: CellValues) -> list[dict[Cell, Mapping[str, Sequence[float]]]]:
    """The cells with the detectors every one of them has; then, for each larger set S of
    detectors some cells have, the cells that have all of S, with S (largest S first).

    A detector that cannot run everywhere (SPEC §20: the policy view needs a discrete value
    head) is ranked only where it runs, beside every detector that runs there: aggregates
    compare detectors on the same tasks (rliable), so a detector is never averaged over other
    cells than the detectors it is ranked against.
    """
    sets = {frozenset(values) for values in cells.values()}
    common = frozenset.intersection(*sets)
    if not common:
        raise ValueError("no detector has values on every cell")
    every = {Cell(*c): {d: v[d] for d in sorted(common)} for c, v in cells.items()}
    larger = sorted(sets - {common}, key=lambda s: (-len(s), sorted(s)))
    scopes = [
        {Cell(*c): {d: v[d] for d in sorted(found)} for c, v in cells.items() if found <= set(v)}
        for found in larger
    ]
    return [every, *scopes]


def build_board(
    cells_by_metric: Mapping[str, CellValues],
    *,
    n_boot: int = 1000,
    ci: float = 0.95,
    seed: int = 0,
    flagged: Mapping[Task, Mapping[str, float]] | None = None,
    taus: Sequence[float] = PROFILE_TAUS,
) -> Board:
    """Aggregate every metric per tier and per (tier, fault family).

    `flagged` defaults to `trivial_flags` of the matched AUROC cells.
    """
    if not cells_by_metric or not any(cells_by_metric.values()):
        raise ValueError("no cells to aggregate")
    # The time-aware rule's detections are not ranked: they are compared with the constant
    # rule's on the same streams (`Board.rule_change`, SPEC §24).
    time_aware = {
        constant: cells_by_metric[metric]
        for metric in cells_by_metric
        if (constant := constant_metric(metric)) is not None and constant in cells_by_metric
    }
    cells_by_metric = {m: v for m, v in cells_by_metric.items() if constant_metric(m) is None}
    if not any(cells_by_metric.values()):
        raise ValueError("no cells to aggregate")
    metrics = tuple(metric_order(cells_by_metric))
    tiers = tuple(tier_order(Cell(*c).tier for m in metrics for c in cells_by_metric[m]))
    if flagged is None:
        flagged = trivial_flags(cells_by_metric.get(MATCHED_AUROC, {}))
    flagged = {task: dict(v) for task, v in sorted(flagged.items())}
    options = {"n_boot": n_boot, "ci": ci, "seed": seed, "taus": taus}
    overall, families, stability, unflagged, scoped = {}, {}, {}, {}, {}
    for metric in metrics:
        for tier in tiers:
            cells = {
                Cell(*c): v for c, v in cells_by_metric[metric].items() if Cell(*c).tier == tier
            }
            if not cells:
                continue
            key = (metric, tier)
            cells, *scopes = detector_scopes(cells)
            if scopes:
                scoped[key] = tuple(aggregate(scope, **options) for scope in scopes)
            overall[key] = aggregate(cells, **options)
            stability[key] = ranking_stability(cells)
            by_family: dict[str, dict[Cell, Any]] = {}
            for cell, values in cells.items():
                by_family.setdefault(fault_family(cell.fault), {})[cell] = values
            families[key] = {
                family: aggregate(by_family[family], **options)
                for family in (*FAULT_FAMILIES, OTHER_FAMILY)
                if family in by_family
            }
            kept = {
                c: v for c, v in cells.items() if (c.environment, c.fault, c.tier) not in flagged
            }
            if kept and len(kept) < len(cells):
                unflagged[key] = aggregate(kept, **options)
    changes = {}
    for metric, paired in time_aware.items():
        for tier in tiers:
            of_tier = {
                Cell(*c): v for c, v in cells_by_metric[metric].items() if Cell(*c).tier == tier
            }
            change = of_tier and rule_changes(
                of_tier, {Cell(*c): v for c, v in paired.items()}, n_boot=n_boot, ci=ci, seed=seed
            )
            if change:
                changes[(metric, tier)] = change
    return Board(metrics, tiers, overall, families, stability, flagged, unflagged, scoped, changes)
