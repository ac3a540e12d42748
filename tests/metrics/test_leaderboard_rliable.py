"""The leaderboard's aggregates against rliable's own implementation (Agarwal et al. 2021).

Score matrices are (runs × tasks) as rliable takes them; tasks are named so that the
leaderboard's sorted task order is the matrices' column order, so point estimates are computed
on the same numbers in the same order and must agree exactly. Bootstrap CIs agree within
Monte-Carlo tolerance: both sides draw 2,000 replicates (1,000 for P(improvement), whose
rliable bootstrap calls scipy per task and replicate); their endpoints moved by at most 5% of
the interval's width across seeds, the tolerance is 10%, and a different scheme (rliable's
bootstrap over tasks too) misses by 100-600%.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from oodrl.metrics.leaderboard import Cell, aggregate, detector_scopes

ROOT = Path(__file__).resolve().parents[2]
TOLERANCE = 0.1  # of the CI's width


def import_rliable_library():
    """rliable.library, which imports arch; arch 7.2 calls pandas' `deprecate_kwarg` with the
    signature of pandas < 3 (pandas 3 put the warning class first), so the import is retried
    with that one call adapted, and pandas is restored at once."""
    try:
        from rliable import library
    except TypeError:
        import pandas.util._decorators as decorators

        original = decorators.deprecate_kwarg

        def compatible(*args, **kwargs):
            if args and isinstance(args[0], str):
                return original(FutureWarning, *args, **kwargs)
            return original(*args, **kwargs)

        for name in [m for m in sys.modules if m.split(".")[0] in ("arch", "rliable")]:
            del sys.modules[name]
        decorators.deprecate_kwarg = compatible
        try:
            from rliable import library
        finally:
            decorators.deprecate_kwarg = original
    return library


@pytest.fixture(scope="module")
def rly():
    return import_rliable_library()


@pytest.fixture
def numpy_global_seed():
    """rliable's bootstrap draws from numpy's global generator."""
    state = np.random.get_state()  # noqa: NPY002 - rliable draws from the legacy global generator
    np.random.seed(0)  # noqa: NPY002
    yield
    np.random.set_state(state)  # noqa: NPY002


def cells_from_episodes(episodes: dict[str, np.ndarray]) -> dict:
    """Per detector (runs, tasks, episodes) values → leaderboard cells, task t named so that
    sorting keeps column order; the run's index is its policy."""
    runs, tasks, _ = next(iter(episodes.values())).shape
    return {
        Cell(f"E{t // 4}", str(r), f"fault{t:03d}", "mild"): {
            d: list(values[r, t]) for d, values in episodes.items()
        }
        for r in range(runs)
        for t in range(tasks)
    }


def synthetic_episodes(kind: str, runs: int = 5, tasks: int = 12, n: int = 6) -> dict:
    """Three detectors of increasing skill: AUROC-like values, or 0/1 detections (many ties)."""
    rng = np.random.default_rng(7)
    out = {}
    for k in range(3):
        task_level = rng.beta(2 + 2 * k, 2, size=(1, tasks, 1))
        values = np.clip(task_level + 0.1 * rng.standard_normal((runs, tasks, n)), 0, 1)
        out[f"det{k}"] = values if kind == "auroc" else (rng.random(values.shape) < values) * 1.0
    return out


def assert_within_mc(ours, low: float, high: float) -> None:
    width = max(high - low, ours.ci_high - ours.ci_low, 1e-9)
    assert abs(ours.ci_low - low) <= TOLERANCE * width, (ours, low, high)
    assert abs(ours.ci_high - high) <= TOLERANCE * width, (ours, low, high)


@pytest.mark.parametrize("kind", ["auroc", "detections"])
def test_point_estimates_equal_rliables(kind):
    from rliable import metrics

    episodes = synthetic_episodes(kind)
    board = aggregate(cells_from_episodes(episodes), n_boot=10)
    assert board.bootstrap == "runs"
    scores = {d: e.mean(axis=-1) for d, e in episodes.items()}  # (runs, tasks)
    for d, matrix in scores.items():
        assert board.iqm[d].value == metrics.aggregate_iqm(matrix)
        assert board.mean[d].value == metrics.aggregate_mean(matrix)
        assert board.optimality_gap[d].value == metrics.aggregate_optimality_gap(matrix)
        for other, other_matrix in scores.items():
            if other != d:
                expected = metrics.probability_of_improvement(matrix, other_matrix)
                assert board.improvement[(d, other)].value == expected


@pytest.mark.slow
def test_iqm_mean_and_gap_cis_agree_with_rliables_stratified_bootstrap(rly, numpy_global_seed):
    from rliable import metrics

    episodes = synthetic_episodes("auroc")
    board = aggregate(cells_from_episodes(episodes), n_boot=2000, seed=0)
    scores = {d: e.mean(axis=-1) for d, e in episodes.items()}

    def statistics(x):
        return np.array(
            [
                metrics.aggregate_iqm(x),
                metrics.aggregate_mean(x),
                metrics.aggregate_optimality_gap(x),
            ]
        )

    _, intervals = rly.get_interval_estimates(scores, statistics, reps=2000)
    for d, (low, high) in intervals.items():
        for i, ours in enumerate((board.iqm[d], board.mean[d], board.optimality_gap[d])):
            assert_within_mc(ours, low[i], high[i])
    # The tolerance tells schemes apart: resampling tasks as well gives other intervals.
    _, over_tasks = rly.get_interval_estimates(scores, statistics, reps=2000, task_bootstrap=True)
    with pytest.raises(AssertionError):
        assert_within_mc(board.iqm["det0"], *over_tasks["det0"][:, 0])


@pytest.mark.slow
def test_probability_of_improvement_cis_agree_with_rliables(rly, numpy_global_seed):
    """rliable's Mann-Whitney bootstrap calls scipy per task and replicate: a smaller suite."""
    from rliable import metrics

    episodes = synthetic_episodes("auroc", runs=4, tasks=6)
    board = aggregate(cells_from_episodes(episodes), n_boot=1000, seed=0)
    scores = {d: e.mean(axis=-1) for d, e in episodes.items()}
    pairs = {("det2", "det1"): [scores["det2"], scores["det1"]]}
    points, intervals = rly.get_interval_estimates(
        pairs, metrics.probability_of_improvement, reps=1000
    )
    for pair, (low, high) in intervals.items():
        assert board.improvement[pair].value == points[pair]
        assert_within_mc(board.improvement[pair], float(low[0]), float(high[0]))


def committed_results() -> dict[str, Path]:
    from oodrl.suite.environments import PIPELINE_DIRS

    paths = {env: ROOT / d / "reports" / "results.yaml" for env, d in PIPELINE_DIRS.items()}
    skip_unless_checked_out(paths.values())
    return one_protocol(paths)


def one_protocol(paths: dict[str, Path]) -> dict[str, Path]:
    """The results files of the protocol version most of them hold: during a change of protocol
    the suite's runs hold two, which no board ranks together (SPEC §26)."""
    from collections import Counter

    from oodrl.suite.migration import built_version

    # Each file's stamp line alone (a results file is megabytes of YAML; read_inputs reads it).
    versions = {env: built_version(p.parent.parent) for env, p in paths.items()}
    version, _ = max(Counter(versions.values()).items(), key=lambda item: (item[1], item[0]))
    return {env: path for env, path in paths.items() if versions[env] == version}


def skip_unless_checked_out(paths) -> None:
    """The suite's results are DVC outputs: a clean clone (CI's) has none."""
    missing = [str(p.relative_to(ROOT)) for p in paths if not p.is_file()]
    if missing:
        pytest.skip(f"the suite's results are DVC outputs not in this checkout: {missing[0]} …")


@pytest.mark.slow
def test_committed_results_reshaped_into_runs_agree_with_rliable(rly, numpy_global_seed):
    """Today's results, each cell's episodes split into 4 pseudo-runs of equal size."""
    from rliable import metrics

    from oodrl.report.leaderboard import read_inputs

    # The detectors every run has (the policy view runs on discrete actions only).
    cells = detector_scopes(read_inputs(committed_results()).cells["matched_auroc"])[0]
    tasks = sorted(cells)
    detectors = sorted(cells[tasks[0]])
    runs = 4
    episodes = {
        d: np.stack(
            [
                np.array(cells[t][d][: len(cells[t][d]) // runs * runs]).reshape(runs, -1)
                for t in tasks
            ],
            axis=1,
        )
        for d in detectors
    }  # (runs, tasks, episodes per run)
    board = aggregate(cells_from_episodes(episodes), n_boot=2000, seed=0)
    scores = {d: e.mean(axis=-1) for d, e in episodes.items()}
    _, intervals = rly.get_interval_estimates(
        scores, lambda x: np.array([metrics.aggregate_iqm(x), metrics.aggregate_mean(x)]), reps=2000
    )
    for d in detectors:
        # Equal up to the last bits: rliable's scipy trim_mean sums the 1,400-odd values in
        # another order than oodrl's sorted-slice mean (1 ulp apart on the current results).
        assert board.iqm[d].value == pytest.approx(metrics.aggregate_iqm(scores[d]), rel=1e-13)
        assert board.mean[d].value == pytest.approx(metrics.aggregate_mean(scores[d]), rel=1e-13)
        assert_within_mc(board.iqm[d], intervals[d][0, 0], intervals[d][1, 0])
        assert_within_mc(board.mean[d], intervals[d][0, 1], intervals[d][1, 1])
    a, b = board.ranked()[:2]
    assert board.improvement[(a, b)].value == metrics.probability_of_improvement(
        scores[a], scores[b]
    )


#: The environment whose committed runs the policies-as-runs test reads, with its three
#: policies: the arithmetic compared is the same for every run. Its six runs' YAML tier results
#: with CartPole's were 43 MB at protocol version 4 (42 s of libyaml on an idle core, 60 s in
#: CI's run; all 21 runs 180 s); Acrobot's alone are 20 MB, and at protocol version 5, 4 of its
#: 6 mild tasks have a cell for every policy (5 at version 4).
POLICIES_AS_RUNS = ("Acrobot-v1",)


@pytest.fixture(scope="module")
def committed_runs():
    """Each metric's mild cells of the committed runs of `POLICIES_AS_RUNS` (every policy of
    each, SPEC §16), as the suite's leaderboard reads them."""
    from oodrl.report.leaderboard import read_inputs
    from oodrl.stages.leaderboard import results_files

    files = {key: paths for key, paths in results_files(ROOT).items() if key[0] in POLICIES_AS_RUNS}
    assert len(files) == 3 * len(POLICIES_AS_RUNS), sorted(files)
    skip_unless_checked_out(paths[0] for paths in files.values())
    cells = read_inputs(files).cells
    return {  # the detectors every run has, as the lead board ranks them
        m: detector_scopes({c: v for c, v in cells[m].items() if c.tier == "mild"})[0]
        for m in cells
    }


@pytest.mark.slow
@pytest.mark.parametrize("metric", ["detection_rate@100", "matched_auroc"])
def test_the_suites_policies_as_runs_agree_with_rliable(committed_runs, metric):
    """The policies are the runs: on the mild tasks all policies share, the (runs × tasks)
    matrices rliable takes give the leaderboard's point estimates to the last bits."""
    from rliable import metrics

    mild = committed_runs[metric]
    policies = sorted({c.policy for c in mild})
    tasks = sorted({(c.environment, c.fault) for c in mild})
    shared = [(e, f) for e, f in tasks if all(Cell(e, p, f, "mild") in mild for p in policies)]
    # A real matrix: at protocol version 5, 4 of Acrobot's 6 mild tasks have a cell for every
    # policy (a tier is found per policy, and some policy cannot reach it; 5 at version 4).
    assert len(policies) == 3 and len(shared) >= 4
    cells = {
        Cell(e, p, f, "mild"): mild[Cell(e, p, f, "mild")] for e, f in shared for p in policies
    }
    board = aggregate(cells, n_boot=10)
    detectors = sorted(next(iter(cells.values())))
    scores = {  # (runs, tasks), tasks in the leaderboard's sorted order
        d: np.array(
            [[np.mean(cells[Cell(e, p, f, "mild")][d]) for e, f in shared] for p in policies]
        )
        for d in detectors
    }
    for d, matrix in scores.items():
        assert board.iqm[d].value == pytest.approx(metrics.aggregate_iqm(matrix), rel=1e-13)
        assert board.mean[d].value == pytest.approx(metrics.aggregate_mean(matrix), rel=1e-13)
        gap = metrics.aggregate_optimality_gap(matrix)
        assert board.optimality_gap[d].value == pytest.approx(gap, rel=1e-13, abs=1e-15)
    leader, second = board.ranked()[:2]
    expected = metrics.probability_of_improvement(scores[leader], scores[second])
    assert board.improvement[(leader, second)].value == pytest.approx(expected, rel=1e-13)
