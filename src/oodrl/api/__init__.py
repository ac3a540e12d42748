"""oodrl's Python API (SPEC §25): results as pandas DataFrames, a detector object evaluated
in-process with the pipeline's own protocol code, and what plugin authors use.

    import oodrl

    board = oodrl.load_results("pipeline/suite")             # the suite's leaderboard cells
    mild = board.query("tier == 'mild' and metric == 'detection_rate@100'")
    frame = oodrl.evaluate(MyDetector(), env="cartpole")     # one environment, in minutes

Every name is imported on first use, so `import oodrl` (and `import oodrl.api`) stays light:
neither imports pandas, numpy or torch.

Results frames are tidy: one row per environment, policy, fault, tier, detector and metric,
with the columns `env`, `policy`, `fault`, `tier`, `detector`, `metric`, `value`, `ci_low`,
`ci_high`, `n_streams`, `alpha`, `severity`, `mode`, `verified`, `family` and `protocol` (None
or NaN where a results file has no such value).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # what the lazy names are, for type checkers and the API reference
    from oodrl.api.evaluation import evaluate
    from oodrl.api.results import load_results
    from oodrl.core.detector import BaseDetector
    from oodrl.monitor import OodMonitor, run_monitor
    from oodrl.testing.detectors import check_detector

__all__ = [
    "BaseDetector",
    "OodMonitor",
    "check_detector",
    "evaluate",
    "load_results",
    "run_monitor",
]

#: Each public name's home module.
_HOMES = {
    "BaseDetector": "oodrl.core.detector",
    "OodMonitor": "oodrl.monitor",
    "check_detector": "oodrl.testing.detectors",
    "evaluate": "oodrl.api.evaluation",
    "load_results": "oodrl.api.results",
    "run_monitor": "oodrl.monitor",
}


def __getattr__(name: str) -> Any:
    if name in _HOMES:
        value = getattr(importlib.import_module(_HOMES[name]), name)
        globals()[name] = value  # later lookups skip this hook
        return value
    raise AttributeError(f"module 'oodrl.api' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
