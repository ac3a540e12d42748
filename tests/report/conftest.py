"""Realistic fake results and sweep files (the shapes the metrics stage writes)."""

import numpy as np
import pytest

DETECTORS = [
    "autoencoder", "cusum", "ensemble_disagreement", "kde_density", "lyapunov_divergence",
    "mahalanobis_distance", "pedm", "time_series_features",
]  # fmt: skip
ANOMALIES = {
    "gaussian_state_noise": "posthoc", "state_feature_dropout": "posthoc",
    "correlation_break": "posthoc", "regime_switch": "posthoc", "observation_delay": "posthoc",
    "stuck_actuator": "online", "dynamics_scaling": "online",
    "action_conditioned_dynamics": "online", "gradual_drift": "online",
}  # fmt: skip
SEVERITIES = [0.1, 0.2, 0.4, 0.6, 0.8]
LATENCY = {"lyapunov_divergence": 5, "pedm": 1, "cusum": 1}


def stats(rng, mean, spread=0.04, n=20):
    return {
        "mean": round(float(mean), 6),
        "std": round(float(spread * 2), 6),
        "ci_low": round(float(mean - spread), 6),
        "ci_high": round(float(mean + spread), 6),
        "n_episodes": n,
    }


def make_results(seed=0):
    rng = np.random.default_rng(seed)
    records = []
    for d_index, detector in enumerate(DETECTORS):
        for null_mode in ("online", "posthoc"):
            records.append(
                {
                    "kind": "null",
                    "detector": detector,
                    "injector": None,
                    "mode": null_mode,
                    "severity": None,
                    "latency": LATENCY.get(detector, 0),
                    "metrics": {
                        "null_auroc": stats(rng, rng.uniform(0.45, 0.6)),
                        "clean_alarm_rate": stats(rng, rng.uniform(0.005, 0.03), 0.003),
                    },
                }
            )
        for a_index, (anomaly, mode) in enumerate(ANOMALIES.items()):
            auroc = float(np.clip(0.5 + 0.45 * np.sin(d_index * 1.3 + a_index), 0.02, 0.99))
            records.append(
                {
                    "kind": "anomaly",
                    "detector": detector,
                    "injector": anomaly,
                    "mode": mode,
                    "severity": 0.5,
                    "latency": LATENCY.get(detector, 0),
                    "metrics": {
                        "matched_auroc": stats(rng, auroc),
                        "matched_auprc": stats(rng, min(auroc + 0.03, 1.0)),
                        "matched_fpr95": stats(rng, max(0.0, 1.0 - auroc)),
                        "detection_delay": stats(rng, 334 * (1 - auroc), 10.0),
                        "clean_alarm_rate": stats(rng, 0.01, 0.002),
                    },
                }
            )
    records.sort(
        key=lambda r: (r["kind"], r["detector"], r["injector"] or "", r["mode"], r["severity"] or 0)
    )
    return {"records": records}


def make_sweep(seed=0):
    rng = np.random.default_rng(seed)
    sweep = {}
    for a_index, injector in enumerate(ANOMALIES):
        sweep[injector] = {}
        for severity in SEVERITIES:
            sweep[injector][severity] = {
                detector: {
                    "matched_auroc": stats(
                        rng, 0.5 + (0.45 * severity) * np.cos(d_index + a_index) ** 2, 0.03
                    )
                }
                for d_index, detector in enumerate(DETECTORS)
            }
    return {"modes": dict(ANOMALIES), "sweep": sweep}


@pytest.fixture
def results():
    return make_results()


@pytest.fixture
def sweep():
    return make_sweep()
