"""One error hierarchy; every message says what is wrong and what to change."""


class OodrlError(Exception):
    """Base class of every error oodrl raises on purpose."""


class ConfigError(OodrlError):
    """params.yaml (or a component's parameters) is invalid."""


class RegistryError(OodrlError):
    """A component name is unknown, duplicated, or its import path is broken."""


class StoreError(OodrlError):
    """A trajectory or score store, or a pickled detector, is missing or unreadable."""


class NotFittedError(OodrlError):
    """A detector was used before `fit` (or `calibrate`)."""


class ContractError(OodrlError):
    """Data does not satisfy an oodrl contract (shape, dtype, length, finiteness)."""


class PolicyError(OodrlError):
    """A policy file cannot be loaded or does not fit the environment."""


class DetectorError(OodrlError):
    """A detector failed while fitting or scoring a given trajectory."""
