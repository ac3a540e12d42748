"""Anomaly injectors (SPEC §4), registered lazily by name; nothing heavy is imported here."""

from oodrl.registry import Registry

INJECTORS = Registry("injector")
INJECTORS.register("gaussian_state_noise", "oodrl.injectors.posthoc:GaussianStateNoise")
INJECTORS.register("state_feature_dropout", "oodrl.injectors.posthoc:StateFeatureDropout")
INJECTORS.register("correlation_break", "oodrl.injectors.posthoc:CorrelationBreak")
INJECTORS.register("regime_switch", "oodrl.injectors.posthoc:RegimeSwitch")
INJECTORS.register("observation_delay", "oodrl.injectors.posthoc:ObservationDelay")
INJECTORS.register("stuck_actuator", "oodrl.injectors.online:StuckActuator")
INJECTORS.register("dynamics_scaling", "oodrl.injectors.online:DynamicsScaling")
INJECTORS.register(
    "action_conditioned_dynamics", "oodrl.injectors.online:ActionConditionedDynamics"
)
INJECTORS.register("gradual_drift", "oodrl.injectors.online:GradualDrift")
# The observation faults live (SPEC §15): names of their own, so that a results file keyed by
# injector name never mixes a fault's post-hoc and live modes.
for _name, _class in (
    ("gaussian_state_noise", "LiveGaussianStateNoise"),
    ("state_feature_dropout", "LiveStateFeatureDropout"),
    ("correlation_break", "LiveCorrelationBreak"),
    ("regime_switch", "LiveRegimeSwitch"),
    ("observation_delay", "LiveObservationDelay"),
):
    INJECTORS.register(f"live_{_name}", f"oodrl.injectors.live_observation:{_class}")
del _name, _class

__all__ = ["INJECTORS"]
