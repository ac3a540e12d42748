"""YAML in and out through libyaml when PyYAML has it (the pure-Python codec took seconds on
results.yaml). Output keys are sorted, so the same data always gives the same bytes."""

from __future__ import annotations

from typing import Any

import yaml

_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


def load(text: str) -> Any:
    return yaml.load(text, Loader=_LOADER)  # noqa: S506 - a safe loader


def dump(data: Any) -> str:
    return yaml.dump(data, Dumper=_DUMPER, sort_keys=True, default_flow_style=False, width=100)
