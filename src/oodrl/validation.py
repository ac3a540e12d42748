"""Declared parameter constraints, checked by one function with one message shape.

A component class declares `_parameter_constraints = {"bandwidth": [Interval(float, 0, None,
closed="neither")], ...}`; `check_params` raises
    "The 'bandwidth' parameter of KdeDensity must be > 0. Got -1 instead."
A parameter is valid when it satisfies any one of its listed constraints (like scikit-learn).
"""

from __future__ import annotations

import inspect
import numbers
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from oodrl.errors import ConfigError


class ParameterError(ConfigError):
    """A ConfigError about one parameter of a component: params errors name it by its key
    (`detectors.<name>.<param>`) where the message alone might not (a library's may not)."""

    def __init__(self, param: str, message: str) -> None:
        super().__init__(message)
        self.param = param

    def __reduce__(self):
        # Rebuilt from both arguments when it crosses a process boundary (stage workers).
        return type(self), (self.param, str(self))


@dataclass(frozen=True)
class Interval:
    """A number of `kind` (int or float) between `low` and `high` (None = unbounded)."""

    kind: type
    low: float | None
    high: float | None
    closed: str = "both"  # "both", "left", "right", "neither"

    def __call__(self, value: Any) -> bool:
        if isinstance(value, bool):
            return False
        number_type = numbers.Integral if self.kind is int else numbers.Real
        if not isinstance(value, number_type):
            return False
        left = self.closed in ("both", "left")
        right = self.closed in ("both", "right")
        if self.low is not None and (value < self.low or (value == self.low and not left)):
            return False
        return not (
            self.high is not None and (value > self.high or (value == self.high and not right))
        )

    def __str__(self) -> str:
        name = "an int" if self.kind is int else "a float"
        if self.low is not None and self.high is not None:
            lb = "[" if self.closed in ("both", "left") else "("
            rb = "]" if self.closed in ("both", "right") else ")"
            return f"{name} in the range {lb}{self.low}, {self.high}{rb}"
        if self.low is not None:
            return f"{name} {'>=' if self.closed in ('both', 'left') else '>'} {self.low}"
        if self.high is not None:
            return f"{name} {'<=' if self.closed in ('both', 'right') else '<'} {self.high}"
        return name


@dataclass(frozen=True)
class Options:
    """One of a fixed set of values."""

    values: tuple[Any, ...]

    def __call__(self, value: Any) -> bool:
        return isinstance(value, str | int | float | bool | type(None)) and value in self.values

    def __str__(self) -> str:
        return "one of " + ", ".join(repr(v) for v in self.values)


@dataclass(frozen=True)
class SequenceOf:
    """A non-empty list whose every item satisfies `item`."""

    item: Callable[[Any], bool]
    min_length: int = 1

    def __call__(self, value: Any) -> bool:
        return (
            isinstance(value, list | tuple)
            and len(value) >= self.min_length
            and all(self.item(v) for v in value)
        )

    def __str__(self) -> str:
        return f"a list (at least {self.min_length} items) of {self.item}"


@dataclass(frozen=True)
class IsNone:
    def __call__(self, value: Any) -> bool:
        return value is None

    def __str__(self) -> str:
        return "None"


@dataclass(frozen=True)
class IsType:
    kind: type

    def __call__(self, value: Any) -> bool:
        return isinstance(value, self.kind) and not (
            isinstance(value, bool) and self.kind is not bool
        )

    def __str__(self) -> str:
        return f"a {self.kind.__name__}"


def constructor_params(cls: type) -> list[str]:
    """Keyword parameters of `cls.__init__` and of every base class `__init__`."""
    names: list[str] = []
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None or klass is object:
            continue
        for p in inspect.signature(init).parameters.values():
            keyword = p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)
            if keyword and p.name != "self" and p.name not in names:
                names.append(p.name)
    return names


def constraints_of(cls: type) -> dict[str, list[Callable[[Any], bool]]]:
    """`_parameter_constraints` merged along the MRO (a subclass overrides its bases)."""
    merged: dict[str, list] = {}
    for klass in reversed(cls.__mro__):
        merged.update(klass.__dict__.get("_parameter_constraints", {}))
    return merged


def check_unknown(cls: type, params: Mapping[str, Any]) -> None:
    allowed = constructor_params(cls)
    for name in params:
        if name not in allowed:
            raise ConfigError(
                f"{cls.__name__} has no parameter '{name}'. Allowed: {', '.join(sorted(allowed))}."
            )


def check_params(owner: str, params: Mapping[str, Any], constraints: Mapping[str, Iterable]):
    """Raise ConfigError for the first parameter that satisfies none of its constraints."""
    for name, value in params.items():
        options = list(constraints.get(name, ()))
        if options and not any(c(value) for c in options):
            allowed = " or ".join(str(c) for c in options)
            raise ConfigError(
                f"The '{name}' parameter of {owner} must be {allowed}. Got {value!r} instead."
            )


class Component:
    """Shared parameter handling: `__init__` stores keyword arguments, `validate_params` checks."""

    _parameter_constraints: dict[str, list] = {}

    def get_params(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in constructor_params(type(self))}

    def validate_params(self) -> None:
        check_params(type(self).__name__, self.get_params(), constraints_of(type(self)))
        self._validate_extra()

    def _validate_extra(self) -> None:
        """Cross-parameter checks a subclass needs beyond per-parameter constraints."""

    @classmethod
    def from_params(cls, params: Mapping[str, Any]):
        """Build from a params.yaml block, refusing unknown keys with the allowed ones listed."""
        check_unknown(cls, params)
        instance = cls(**params)
        instance.validate_params()
        return instance

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"
