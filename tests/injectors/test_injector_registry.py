import subprocess
import sys

import numpy as np
import pytest

from oodrl.core.injector import OnlineInjector, PostHocInjector
from oodrl.errors import ConfigError, RegistryError
from oodrl.injectors import INJECTORS
from oodrl.injectors.apply import injector_rng

EXPECTED = {
    "gaussian_state_noise": "posthoc",
    "state_feature_dropout": "posthoc",
    "correlation_break": "posthoc",
    "regime_switch": "posthoc",
    "observation_delay": "posthoc",
    "stuck_actuator": "online",
    "dynamics_scaling": "online",
    "action_conditioned_dynamics": "online",
    "gradual_drift": "online",
}
DEFAULTS = {
    "observation_delay": {"max_delay": 10},
    # The predicate is the environment's to choose (params.yaml): no default target.
    "dynamics_scaling": {"gain": 1.5},
    "action_conditioned_dynamics": {
        "gain": 1.5,
        "target_action": None,
        "target_dim": None,
        "target_threshold": None,
    },
    "gradual_drift": {"gain": 1.5, "ramp_steps": 200},
}


def test_the_nine_injectors_are_registered():
    assert set(EXPECTED) <= set(INJECTORS.names())


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_each_injector_knows_its_name_mode_and_defaults(name):
    cls = INJECTORS.get(name)
    base = PostHocInjector if EXPECTED[name] == "posthoc" else OnlineInjector
    assert issubclass(cls, base) and cls.name == name and cls.mode == EXPECTED[name]
    injector = cls.from_params({})
    assert injector.get_params() == {"severity": None, **DEFAULTS.get(name, {})}
    spec = injector.spec(0.4, 10)
    recorded = {k: v for k, v in DEFAULTS.get(name, {}).items() if v is not None}
    assert (spec.name, spec.mode, dict(spec.params)) == (name, cls.mode, recorded)


def test_importing_the_registry_imports_no_injector_module():
    code = (
        "import sys, oodrl.injectors; "
        "print([m for m in ('oodrl.injectors.posthoc', 'oodrl.injectors.online', 'gymnasium') "
        "if m in sys.modules])"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    assert result.stdout.strip() == "[]"


def test_unknown_injector_suggests_the_closest_name():
    with pytest.raises(RegistryError, match="Did you mean 'regime_switch'"):
        INJECTORS.get("regime_swtich")


@pytest.mark.parametrize("name", sorted(EXPECTED))
@pytest.mark.parametrize("severity", [-0.1, 1.5, "0.5"])
def test_severity_outside_the_unit_interval_is_refused(name, severity):
    with pytest.raises(ConfigError, match="'severity' parameter .* Got"):
        INJECTORS.get(name).from_params({"severity": severity})


@pytest.mark.parametrize(
    ("name", "params", "message"),
    [
        ("observation_delay", {"max_delay": 0}, "'max_delay' parameter of ObservationDelay"),
        ("observation_delay", {"max_delay": 2.5}, "'max_delay' parameter"),
        ("gradual_drift", {"ramp_steps": 0}, "'ramp_steps' parameter of GradualDrift"),
        ("action_conditioned_dynamics", {"target_action": -1}, "'target_action' parameter"),
        ("action_conditioned_dynamics", {"target_dim": 1.5}, "'target_dim' parameter"),
        ("action_conditioned_dynamics", {"target_threshold": "0"}, "'target_threshold' param"),
        (
            "action_conditioned_dynamics",
            {"target_action": 2, "target_dim": 0, "target_threshold": 0.0},
            "either 'target_action' .* or both 'target_dim' and 'target_threshold'",
        ),
        (
            "action_conditioned_dynamics",
            {"target_dim": 0},
            "either 'target_action' .* or both 'target_dim' and 'target_threshold'",
        ),
        ("gaussian_state_noise", {"sigma": 0.1}, "has no parameter 'sigma'"),
    ],
)
def test_invalid_parameters_are_refused(name, params, message):
    with pytest.raises(ConfigError, match=message):
        INJECTORS.get(name).from_params(params)


def test_valid_parameters_are_accepted_and_kept():
    delay = INJECTORS.get("observation_delay").from_params({"max_delay": 1, "severity": 0.0})
    assert (delay.max_delay, delay.severity) == (1, 0.0)
    drift = INJECTORS.get("gradual_drift").from_params({"ramp_steps": 1, "severity": 1.0})
    assert (drift.ramp_steps, drift.severity) == (1, 1.0)
    conditioned = INJECTORS.get("action_conditioned_dynamics")
    continuous = conditioned.from_params({"target_dim": 1, "target_threshold": -0.5})
    assert (continuous.target_dim, continuous.target_threshold) == (1, -0.5)
    spec = conditioned.from_params({"target_action": 0}).spec(0.5, 3)
    assert spec.params == {"gain": 1.5, "target_action": 0}


def test_injector_rng_depends_on_seed_name_and_episode_and_on_nothing_else():
    draw = injector_rng(5, "regime_switch", 3).integers(0, 2**32, 4)
    np.testing.assert_array_equal(draw, injector_rng(5, "regime_switch", 3).integers(0, 2**32, 4))
    for other in [(6, "regime_switch", 3), (5, "correlation_break", 3), (5, "regime_switch", 4)]:
        assert not np.array_equal(draw, injector_rng(*other).integers(0, 2**32, 4))
    code = (
        "from oodrl.injectors.apply import injector_rng; "
        "print(injector_rng(5, 'regime_switch', 3).integers(0, 2**32, 4).tolist())"
    )
    for hash_seed in ("1", "2"):  # str hashing differs between processes; the generator may not
        result = subprocess.run(
            [sys.executable, "-c", code],
            capture_output=True,
            text=True,
            check=True,
            env={"PYTHONHASHSEED": hash_seed},
        )
        assert result.stdout.strip() == str(draw.tolist())
