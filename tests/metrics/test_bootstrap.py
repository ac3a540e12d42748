"""Episode and paired bootstrap."""

import numpy as np
import pytest

from oodrl.errors import ContractError
from oodrl.metrics.bootstrap import (
    BootstrapSummary,
    bootstrap_indices,
    episode_bootstrap,
    paired_bootstrap,
)


def test_bootstrap_is_reproducible_and_seeded():
    values = np.random.default_rng(1).normal(size=25)
    first = episode_bootstrap(values, n_boot=300, seed=7)
    assert first == episode_bootstrap(values, n_boot=300, seed=7)
    assert first != episode_bootstrap(values, n_boot=300, seed=8)
    assert first.mean == pytest.approx(values.mean())
    assert first.std == pytest.approx(values.std(ddof=1))
    assert first.n_episodes == 25


def test_ci_contains_the_mean_and_shrinks_with_more_episodes():
    rng = np.random.default_rng(2)
    small = episode_bootstrap(rng.normal(0.7, 0.1, size=10), n_boot=500)
    large = episode_bootstrap(rng.normal(0.7, 0.1, size=400), n_boot=500)
    for result in (small, large):
        assert result.ci_low <= result.mean <= result.ci_high
    assert large.ci_high - large.ci_low < small.ci_high - small.ci_low
    # The percentile CI of the mean of N(0.7, 0.1²), 400 episodes: about ±1.96 · 0.1 / 20.
    assert large.ci_high - large.ci_low == pytest.approx(2 * 1.96 * 0.1 / 20, rel=0.25)


def test_single_episode_and_constant_values():
    assert episode_bootstrap(np.array([0.3]), n_boot=50) == BootstrapSummary(0.3, 0.0, 0.3, 0.3, 1)
    constant = episode_bootstrap(np.full(5, 2.0), n_boot=50)
    assert (constant.std, constant.ci_low, constant.ci_high) == (0.0, 2.0, 2.0)


def test_indices_depend_only_on_seed_and_size():
    a = bootstrap_indices(20, 100, seed=3)
    assert a.shape == (100, 20)
    assert a.min() >= 0 and a.max() < 20
    np.testing.assert_array_equal(a, bootstrap_indices(20, 100, seed=3))


def test_paired_bootstrap_equals_the_bootstrap_of_differences():
    rng = np.random.default_rng(4)
    null = rng.normal(0.5, 0.2, size=30)
    raw = null + 0.1 + rng.normal(0, 0.01, size=30)
    paired = paired_bootstrap(raw, null, np.subtract, n_boot=400, seed=5)
    assert paired == episode_bootstrap(raw - null, n_boot=400, seed=5)
    assert paired.mean == pytest.approx(0.1, abs=0.01)


def test_paired_bootstrap_is_narrower_than_independent_resampling():
    rng = np.random.default_rng(6)
    null = rng.normal(0.5, 0.2, size=30)
    raw = null + 0.1 + rng.normal(0, 0.01, size=30)
    paired = paired_bootstrap(raw, null, np.subtract, n_boot=400, seed=5)
    i = bootstrap_indices(30, 400, seed=5)
    j = bootstrap_indices(30, 400, seed=6)
    independent = raw[i].mean(axis=1) - null[j].mean(axis=1)
    low, high = np.percentile(independent, [2.5, 97.5])
    assert paired.ci_high - paired.ci_low < (high - low) / 5


def test_as_dict_is_plain_and_rounded():
    summary = BootstrapSummary(0.12345678, -1e-9, 0.1, 0.2, np.int64(3)).as_dict()
    assert summary == {"mean": 0.123457, "std": 0.0, "ci_low": 0.1, "ci_high": 0.2, "n_episodes": 3}
    assert all(type(v) in (float, int) for v in summary.values())
    assert str(summary["std"]) == "0.0"  # not -0.0


def test_bad_inputs_are_contract_errors():
    with pytest.raises(ContractError, match="non-empty"):
        episode_bootstrap(np.array([]))
    with pytest.raises(ContractError, match="NaN"):
        episode_bootstrap(np.array([1.0, np.nan]))
    with pytest.raises(ContractError, match="n_boot"):
        episode_bootstrap(np.ones(3), n_boot=0)
    with pytest.raises(ContractError, match="ci"):
        episode_bootstrap(np.ones(3), ci=1.0)
    with pytest.raises(ContractError, match="one length"):
        paired_bootstrap(np.ones(3), np.ones(4), np.subtract)
