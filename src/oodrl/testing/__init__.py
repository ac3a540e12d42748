"""Reusable checks for oodrl components, for oodrl's own tests and for plugin authors.

`oodrl.testing.detectors` holds the detector contract checks (`check_detector` and the single
`check_*` functions) and a cheap synthetic trajectory generator; `oodrl.testing.pipeline` runs
the DVC pipeline in a throw-away copy. The detector checks are re-exported here lazily, so
importing one submodule does not load the other's dependencies.
"""

from __future__ import annotations

import importlib
from typing import Any

__all__ = [
    "check_detector",
    "check_global_random_state",
    "check_not_fitted",
    "check_parameters",
    "check_pickle_roundtrip",
    "check_reproducible",
    "check_score_is_pure",
    "check_scores_use_the_data",
    "check_state_dim",
    "check_streaming",
    "check_threshold",
    "check_torch_free_import",
    "linear_system_policy",
    "linear_system_trajectories",
    "with_extra_state_dimension",
]


def __getattr__(name: str) -> Any:
    if name in __all__:
        return getattr(importlib.import_module("oodrl.testing.detectors"), name)
    raise AttributeError(f"module 'oodrl.testing' has no attribute '{name}'")
