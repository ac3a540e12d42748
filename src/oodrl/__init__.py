"""oodrl: a benchmark of out-of-distribution detectors for RL trajectories.

Score direction, everywhere in oodrl: a larger detector score means more anomalous.
This module imports nothing heavy so that every pipeline stage starts fast.
"""

__version__ = "0.1.0"


def __getattr__(name: str):
    """The Python API (SPEC §25), imported on first use so that `import oodrl` stays light.

    Only attribute access for a name this module lacks runs this hook; no pipeline stage does
    that, so the stages' code stamps leave it out (`oodrl.suite.pipeline.stage_source`).
    """
    import importlib

    api = importlib.import_module("oodrl.api")
    if name in api.__all__:
        return getattr(api, name)
    raise AttributeError(f"module 'oodrl' has no attribute {name!r}")


def __dir__() -> list[str]:
    import importlib

    return sorted([*globals(), *importlib.import_module("oodrl.api").__all__])
