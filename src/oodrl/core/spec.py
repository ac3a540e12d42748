"""AnomalySpec and the label helper (SPEC §1)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from oodrl.errors import ContractError

Mode = Literal["posthoc", "online"]
MODES: tuple[str, ...] = ("posthoc", "online")


def default_onset(T: int) -> int:  # noqa: N803 - T is the protocol's name for the horizon
    """The protocol's default onset t* = floor(T / 3)."""
    return T // 3


def make_labels(T: int, onset: int, offset: int | None = None) -> np.ndarray:  # noqa: N803
    """y_t = 1 for onset <= t < offset (offset None = until the end), else 0; dtype bool."""
    if not 0 <= onset <= T:
        raise ContractError(f"onset must be in [0, T={T}]; got {onset}.")
    end = T if offset is None else offset
    if not onset <= end <= T:
        raise ContractError(f"offset must be in [onset={onset}, T={T}]; got {offset}.")
    labels = np.zeros(T, dtype=bool)
    labels[onset:end] = True
    return labels


@dataclass(frozen=True)
class AnomalySpec:
    """What anomaly a perturbed trajectory carries; stored with every perturbed set."""

    name: str
    severity: float
    onset: int
    offset: int | None = None
    mode: Mode = "posthoc"
    params: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not 0.0 <= float(self.severity) <= 1.0:
            raise ContractError(f"AnomalySpec.severity must be in [0, 1]; got {self.severity}.")
        if self.mode not in MODES:
            raise ContractError(f"AnomalySpec.mode must be one of {MODES}; got {self.mode!r}.")
        if self.onset < 0 or (self.offset is not None and self.offset <= self.onset):
            raise ContractError(
                f"AnomalySpec needs 0 <= onset < offset; got onset={self.onset}, "
                f"offset={self.offset}."
            )
        object.__setattr__(self, "severity", float(self.severity))
        object.__setattr__(self, "params", dict(sorted(self.params.items())))

    def labels(self, T: int) -> np.ndarray:  # noqa: N803
        return make_labels(T, self.onset, self.offset)

    def to_dict(self) -> dict[str, Any]:
        return {
            "mode": self.mode,
            "name": self.name,
            "offset": self.offset,
            "onset": self.onset,
            "params": dict(self.params),
            "severity": self.severity,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> AnomalySpec:
        return cls(**dict(data))
