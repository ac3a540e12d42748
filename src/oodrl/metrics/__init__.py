"""Metrics of SPEC §6, registered by name.

Each name maps to a `oodrl.metrics.aggregate.Metric` (per-episode `compute` and a
`higher_is_better` flag), imported on first use. The numeric building blocks live in
`ranking` (AUROC, AUPRC, FPR at a TPR target, temporal AUROC), `alarms` (precision, recall,
delay, segments) and `bootstrap`; `aggregate` is the API the metrics stage calls. Plugins add
a metric through the `oodrl.metrics` entry-point group.
"""

from oodrl.config import OPT_IN_METRICS
from oodrl.registry import Registry

METRICS = Registry("metric")

for _name in (
    "adjusted_auroc",
    "clean_alarm_rate",
    "clean_episode_alarm",
    "detection_delay",
    "f1",
    "lift_over_null",
    "matched_auprc",
    "matched_auroc",
    "matched_fpr95",
    "null_auprc",
    "null_auroc",
    "precision",
    "raw_auprc",
    "raw_auroc",
    "recall",
    "segment_precision",
    "segment_recall",
    "temporal_auroc",
):
    METRICS.register(_name, f"oodrl.metrics.aggregate:{_name.upper()}")
del _name
# Registered, but computed only where params list them in `metrics.extra` (SPEC §20).
for _name in OPT_IN_METRICS:
    METRICS.register(_name, f"oodrl.metrics.aggregate:{_name.upper()}")
del _name


def computed_metrics(extra: tuple[str, ...] | list[str] = ()) -> list[str]:
    """The registered metrics every results record holds, with the opt-in ones named."""
    return [name for name in METRICS.names() if name not in OPT_IN_METRICS or name in extra]


def higher_is_better(name: str) -> bool:
    """Whether a larger value of the registered metric `name` is better."""
    return bool(METRICS.get(name).higher_is_better)


__all__ = ["METRICS", "higher_is_better"]
