"""The metrics stage API: episode_metrics, null_episode_metrics, summarise, the registry."""

import numpy as np
import pytest
import yaml
from sklearn.metrics import roc_auc_score

from oodrl.config import MetricsConfig, parse_params
from oodrl.errors import ConfigError, ContractError, DetectorError
from oodrl.metrics import METRICS, higher_is_better
from oodrl.metrics.aggregate import (
    NULL_METRICS,
    PAIRED_METRICS,
    Metric,
    episode_metrics,
    null_episode_metrics,
    summarise,
)

N, T, ONSET = 6, 60, 20
SETTINGS = MetricsConfig(n_boot=200, extra=["vus_pr"])  # every registered metric, opt-in ones too

SPEC_METRICS = {
    "raw_auroc", "raw_auprc", "null_auroc", "null_auprc", "lift_over_null", "adjusted_auroc",
    "matched_auroc", "matched_auprc", "matched_fpr95", "precision", "recall", "f1",
    "clean_alarm_rate", "detection_delay", "segment_precision", "segment_recall",
    "temporal_auroc",
}  # fmt: skip
LOWER_IS_BETTER = {
    "matched_fpr95",
    "detection_delay",
    "clean_alarm_rate",
    "null_auroc",
    "null_auprc",
}


def episodes(shift: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    labels = np.zeros((N, T), bool)
    labels[:, ONSET:] = True
    clean = rng.normal(size=(N, T))
    perturbed = clean + shift * labels + rng.normal(0, 0.1, size=(N, T))
    return perturbed, clean, labels


def test_every_spec_metric_is_registered_with_its_direction():
    assert set(METRICS.names()) >= SPEC_METRICS
    for name in SPEC_METRICS:
        assert isinstance(METRICS.get(name), Metric)
        assert higher_is_better(name) is (name not in LOWER_IS_BETTER)


@pytest.mark.parametrize("name", METRICS.names(), ids=str)
def test_metric_contract(name):
    """Shape (N,), finite, deterministic, and a clear detector is no worse than a useless one."""
    metric = METRICS.get(name)
    clear = episode_metrics(*episodes(4.0), 2.0, ONSET, None, SETTINGS, "clear")[name]
    again = episode_metrics(*episodes(4.0), 2.0, ONSET, None, SETTINGS, "clear")[name]
    perturbed, clean, labels = episodes(0.0)
    useless = episode_metrics(clean, clean, labels, 2.0, ONSET, None, SETTINGS, "useless")[name]
    assert clear.shape == (N,) and np.isfinite(clear).all()
    np.testing.assert_array_equal(clear, again)
    if metric.higher_is_better:
        assert clear.mean() >= useless.mean()
    else:
        assert clear.mean() <= useless.mean()


def test_episode_metrics_values():
    perturbed, clean, labels = episodes(1.0)
    result = episode_metrics(perturbed, clean, labels, 1.5, ONSET, None, SETTINGS)
    assert list(result) == sorted(result)
    for i in range(N):
        truth = np.r_[np.ones(T - ONSET), np.zeros(T - ONSET)]
        matched = np.r_[perturbed[i, ONSET:], clean[i, ONSET:]]
        assert result["matched_auroc"][i] == pytest.approx(roc_auc_score(truth, matched))
        assert result["raw_auroc"][i] == pytest.approx(roc_auc_score(labels[i], perturbed[i]))
        assert result["null_auroc"][i] == pytest.approx(roc_auc_score(labels[i], clean[i]))
    np.testing.assert_allclose(result["lift_over_null"], result["raw_auroc"] - result["null_auroc"])
    np.testing.assert_allclose(
        result["adjusted_auroc"], np.clip(result["lift_over_null"] + 0.5, 0, 1)
    )
    np.testing.assert_allclose(result["clean_alarm_rate"], (clean >= 1.5).mean(axis=1))


def test_adjusted_auroc_is_clipped():
    perturbed, clean, labels = episodes(0.0)
    # Clean scores that rise exactly at the onset (null AUROC 1) and a perturbed copy that falls.
    clean = np.tile(labels[0].astype(float), (N, 1))
    result = episode_metrics(-clean, clean, labels, 0.5, ONSET, None, SETTINGS)
    np.testing.assert_array_equal(result["lift_over_null"], -1.0)
    np.testing.assert_array_equal(result["adjusted_auroc"], 0.0)


def test_alarm_metrics_use_the_threshold_and_window():
    perturbed = np.zeros((1, 10))
    perturbed[0, [1, 6, 7]] = 1.0
    labels = np.zeros((1, 10), bool)
    labels[0, 5:8] = True
    result = episode_metrics(perturbed, np.zeros((1, 10)), labels, 1.0, 5, 8, SETTINGS)
    assert result["precision"][0] == pytest.approx(2 / 3)
    assert result["recall"][0] == pytest.approx(2 / 3)
    assert result["detection_delay"][0] == 1.0
    assert result["segment_precision"][0] == 0.5
    assert result["segment_recall"][0] == 1.0
    assert result["clean_alarm_rate"][0] == 0.0


def test_detection_delay_adds_the_detector_latency():
    perturbed = np.zeros((1, 10))
    perturbed[0, [4, 7]] = 1.0
    labels = np.zeros((1, 10), bool)
    labels[0, 5:] = True
    clean = np.zeros((1, 10))
    # The alarm at t = 4 is before t* = 5 without look-ahead; with latency 1 it is raised at 5.
    plain = episode_metrics(perturbed, clean, labels, 1.0, 5, None, SETTINGS)
    ahead = episode_metrics(perturbed, clean, labels, 1.0, 5, None, SETTINGS, latency=1)
    assert (plain["detection_delay"][0], ahead["detection_delay"][0]) == (2.0, 0.0)
    null = null_episode_metrics(perturbed, labels, 1.0, 5, None, SETTINGS, latency=3)
    assert null["detection_delay"][0] == 2.0  # the alarm at 4 is raised at 7
    # Only the delay depends on the latency.
    for name in plain:
        if name != "detection_delay":
            np.testing.assert_array_equal(plain[name], ahead[name])
    with pytest.raises(ContractError, match="latency"):
        episode_metrics(perturbed, clean, labels, 1.0, 5, None, SETTINGS, latency=-1)


def test_null_episode_metrics():
    _, clean, labels = episodes(0.0)
    result = null_episode_metrics(clean, labels, 1.5, ONSET, None, SETTINGS, "kde_density")
    assert tuple(result) == NULL_METRICS
    full = episode_metrics(clean, clean, labels, 1.5, ONSET, None, SETTINGS)
    for name in NULL_METRICS:
        np.testing.assert_array_equal(result[name], full[name])


def test_nan_scores_name_the_detector_and_episode():
    perturbed, clean, labels = episodes(1.0)
    perturbed[3, 7] = np.nan
    with pytest.raises(DetectorError, match=r"'pedm'.*perturbed episode 3"):
        episode_metrics(perturbed, clean, labels, 1.0, ONSET, None, SETTINGS, "pedm")
    clean[2, 0] = np.inf
    with pytest.raises(DetectorError, match=r"'kde_density'.*clean episode 2"):
        null_episode_metrics(clean, labels, 1.0, ONSET, None, SETTINGS, "kde_density")


def test_contract_errors():
    perturbed, clean, labels = episodes(1.0)
    with pytest.raises(ContractError, match="labels bool"):
        episode_metrics(perturbed, clean, labels.astype(int), 1.0, ONSET, None, SETTINGS)
    with pytest.raises(ContractError, match="onset"):
        episode_metrics(perturbed, clean, labels, 1.0, T, None, SETTINGS)
    with pytest.raises(ContractError, match="threshold"):
        episode_metrics(perturbed, clean, labels, float("nan"), ONSET, None, SETTINGS)


@pytest.mark.parametrize(
    ("key", "value"), [("n_boot", 0), ("ci", 1.0), ("tpr_target", 1.5), ("temporal_buffer", -1)]
)
def test_settings_are_validated_with_params(default_params, key, value):
    default_params["metrics"][key] = value
    with pytest.raises(ConfigError, match=f"metrics.{key}"):
        parse_params(default_params, components=False)


def test_settings_reach_the_metrics():
    perturbed, clean, labels = episodes(1.0)
    loose = MetricsConfig(n_boot=10, tpr_target=0.5, temporal_buffer=0)
    strict = MetricsConfig(n_boot=10, tpr_target=1.0, temporal_buffer=0)
    a = episode_metrics(perturbed, clean, labels, 1.0, ONSET, None, loose)
    b = episode_metrics(perturbed, clean, labels, 1.0, ONSET, None, strict)
    assert (a["matched_fpr95"] <= b["matched_fpr95"]).all()
    np.testing.assert_allclose(a["temporal_auroc"], a["raw_auroc"])


def test_summarise_is_yaml_safe_reproducible_and_rounded():
    result = episode_metrics(*episodes(1.0), 1.5, ONSET, None, SETTINGS)
    summary = summarise(result, SETTINGS, seed=0)
    assert summary == summarise(result, SETTINGS, seed=0)
    assert list(summary) == sorted(result)
    for stats in summary.values():
        assert list(stats) == ["mean", "std", "ci_low", "ci_high", "n_episodes"]
        assert stats["n_episodes"] == N and type(stats["n_episodes"]) is int
        assert all(type(stats[k]) is float for k in ("mean", "std", "ci_low", "ci_high"))
        assert all(round(stats[k], 6) == stats[k] for k in ("mean", "std", "ci_low", "ci_high"))
        assert stats["ci_low"] <= stats["mean"] <= stats["ci_high"]
    assert yaml.safe_load(yaml.safe_dump(summary)) == summary
    # The run's seed draws the resamples: another seed moves the interval, not the mean.
    other = summarise(result, SETTINGS, seed=1)["matched_auroc"]
    assert other["mean"] == summary["matched_auroc"]["mean"]
    assert other != summary["matched_auroc"]


def test_summarise_paired_matches_the_per_episode_pairs():
    result = episode_metrics(*episodes(1.0), 1.5, ONSET, None, SETTINGS)
    paired = {name: (result["raw_auroc"], result["null_auroc"]) for name in PAIRED_METRICS}
    summary = summarise({"matched_auroc": result["matched_auroc"]}, SETTINGS, paired, seed=0)
    assert set(summary) == {"matched_auroc", *PAIRED_METRICS}
    direct = summarise(result, SETTINGS, seed=0)
    for name in PAIRED_METRICS:
        assert summary[name] == direct[name]
    with pytest.raises(ContractError, match="No paired definition"):
        summarise({}, SETTINGS, {"f1": (result["f1"], result["f1"])}, seed=0)
    with pytest.raises(ContractError, match="'f1'"):
        summarise({"f1": np.array([np.nan, 1.0])}, SETTINGS, seed=0)


def test_clean_false_alarms_per_step_and_per_episode():
    clean = np.zeros((4, 10))
    clean[0, 3] = clean[0, 7] = 2.0  # two false alarms in episode 0
    clean[2, 9] = 1.0  # one in episode 2, at the threshold (z ≥ θ alarms)
    labels = np.zeros((4, 10), dtype=bool)
    labels[:, 5:] = True
    null = null_episode_metrics(clean, labels, 1.0, 5, None, SETTINGS)
    assert null["clean_alarm_rate"].tolist() == [0.2, 0.0, 0.1, 0.0]
    assert null["clean_episode_alarm"].tolist() == [1.0, 0.0, 1.0, 0.0]
