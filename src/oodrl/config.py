"""Typed, validated params.yaml (SPEC §8).

Loading validates everything a stage could read: structure and types (pydantic, unknown keys
refused), the protocol's ranges, and every detector's and injector's own parameters (their
declared constraints). `oodrl check-params` checks more
(`oodrl.suite.params_check.check_completely`): the seed ranges, the calibration counts, and every
library detector fitted on dummy data. Any problem is one `ConfigError` line naming the key path and
what is allowed; the CLI turns it into exit code 2 before anything is written. Stage commands load
with `components=False` and validate the one component they build (check_params, the first
stage, validated them all), so each imports only its own component's code.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
from fractions import Fraction
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from oodrl.errors import ConfigError, OodrlError
from oodrl.validation import Interval, IsType, Options, ParameterError, SequenceOf

DEFAULT_PARAMS = Path("params.yaml")
#: The impact curves' whole episodes (SPEC §15) start at these offsets from `seed`: the policy's
#: at seed + POLICY_SEED_OFFSET + j, the random policy's at seed + RANDOM_SEED_OFFSET + j. Fixed,
#: not params; `oodrl check-params` keeps every params-set range of streams clear of them.
POLICY_SEED_OFFSET = 500_000
RANDOM_SEED_OFFSET = 600_000
#: Protocol 3's tier search (SPEC §19 before version 4): its probes at seed + SEARCH_SEED_OFFSET
#: + j, its verifications at seed + VERIFY_SEED_OFFSET + j. No stage uses them since protocol 4;
#: reserved for the impact records built at version 3 and benchmarks/tier_search_sim.py, which
#: replays that search.
SEARCH_SEED_OFFSET = 700_000
VERIFY_SEED_OFFSET = 800_000
#: Protocol 4's tier search (SPEC §19, §23; `oodrl.protocol.tier_search`): every probe of a fault
#: on the common seeds seed + CRN_SEARCH_SEED_OFFSET + j (j < tiers.search.search_episodes), the
#: tiers' verification batches on seed + CRN_VERIFY_SEED_OFFSET + …, each block ending where the
#: next begins (the verification's at CRN_SEED_BLOCK_END, the policy's final check's first seed).
#: `TierSearchConfig.check_seed_blocks` refuses sizes that would overflow a block.
CRN_SEARCH_SEED_OFFSET = 900_000
CRN_VERIFY_SEED_OFFSET = 950_000
CRN_SEED_BLOCK_END = 1_000_000
#: Registered metrics computed only where `metrics.extra` names them (`oodrl.metrics`): added
#: after the paper's results were written, so the root's results.yaml keeps its records. Here,
#: not in `oodrl.metrics`, so that loading params never imports the metrics' code (which would
#: put it in every stage's code stamp).
OPT_IN_METRICS = ("vus_pr",)


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)


class EnvConfig(_Section):
    id: str = "LunarLander-v3"
    T: int = Field(500, ge=2)
    onset: int | None = None  # None: floor(T / 3)

    @property
    def resolved_onset(self) -> int:
        from oodrl.core.spec import default_onset

        return default_onset(self.T) if self.onset is None else self.onset


class DataConfig(_Section):
    n_id: int = Field(30, ge=2)
    n_ood: int = Field(20, ge=1)
    calibration_fraction: float = Field(0.2, gt=0, lt=1)
    eval_seed_offset: int = Field(10_000, ge=1)

    @property
    def n_calibration(self) -> int:
        return min(self.n_id - 1, max(1, round(self.n_id * self.calibration_fraction)))


class PolicyConfig(_Section):
    mode: Literal["greedy", "noisy"] = "greedy"
    train: dict[str, Any] = Field(default_factory=dict)


class AnomalyConfig(_Section):
    severity: float = Field(0.5, ge=0, le=1)
    offset: int | None = None
    sweep: list[float] = Field(default_factory=lambda: [0.1, 0.2, 0.4, 0.6, 0.8])
    injectors: dict[str, dict[str, Any]] = Field(default_factory=dict)


class MetricsConfig(_Section):
    """The `metrics` block: the episode bootstrap (`n_boot` resamples, `ci` level; seeded by
    the run's `seed`), the TPR of the FPR operating point, the temporal-AUROC buffer, and how
    many episodes each score-traces panel draws. Metrics read it as their settings."""

    n_boot: int = Field(1000, ge=1)
    ci: float = Field(0.95, gt=0, lt=1)
    tpr_target: float = Field(0.95, gt=0, le=1)
    temporal_buffer: int = Field(10, ge=0)
    traces_per_anomaly: int = Field(1, ge=0)
    #: Opt-in metrics to compute besides the default ones (`OPT_IN_METRICS`, e.g.
    #: `vus_pr`). Left out of the resolved params when empty, so the params hash of results
    #: written before the key existed stays the same.
    extra: list[str] = Field(default_factory=list, exclude_if=lambda extra: not extra)

    @field_validator("extra")
    @classmethod
    def _known_opt_in(cls, extra: list[str]) -> list[str]:
        unknown = [name for name in extra if name not in OPT_IN_METRICS]
        if unknown:
            raise ValueError(
                f"unknown opt-in metric {unknown[0]!r}; allowed: {', '.join(OPT_IN_METRICS)}"
            )
        return extra


class TierSearchConfig(_Section):
    """The `tiers.search` block (SPEC §19, §23; `oodrl.protocol.tier_search`): every probe of a
    fault measures π on the same `search_episodes` reset seeds (common random numbers), at most
    `max_probes` probes, until each tier's bracket on the monotone fit of the probes lies within
    `tolerance` of its level (capped at half the tier's loss, `tier_tolerance`) or narrower than
    `resolution`; each tier is then re-measured on fresh seeds in batches of `verify_batch`
    episodes, at most `max_verify_batches` in all, the next batch to the widest CI while its
    half-width exceeds `ci_target`; search and verification together spend at most `budget`
    episodes a fault. A tier is verified only when its CI meets the level within the tolerance
    and its half-width is at most `ci_target` (protocol 5; `tier_search.tier_verified`), so
    the defaults let a fault's verification spend up to 50 × 50 = 2,500 episodes (what about
    nine faults in ten of the protocol-4 records need, extrapolated to ±0.02) and the budget
    is 6 × 100 + 2,500 = 3,100."""

    tolerance: float = Field(0.015, gt=0, lt=1)
    search_episodes: int = Field(
        100, ge=2, le=CRN_VERIFY_SEED_OFFSET - CRN_SEARCH_SEED_OFFSET
    )  # the search's seed block
    max_probes: int = Field(6, ge=1)
    verify_batch: int = Field(50, ge=2)
    max_verify_batches: int = Field(50, ge=1)
    ci_target: float = Field(0.02, gt=0)
    budget: int = Field(3_100, ge=1)
    resolution: float = Field(0.001, gt=0, lt=1)
    # The random policy's mean return is every R̃'s normaliser, and the interval of R̃ resamples
    # it: from 30 episodes its noise alone held severe tiers wider than ±0.02 on LunarLander and
    # Pendulum (a floor of 0.023-0.025 however many verification episodes); from 200 it is
    # below 0.01 on every run. Seeds seed + RANDOM_SEED_OFFSET + j, inside that block.
    random_episodes: int = Field(200, ge=2, le=SEARCH_SEED_OFFSET - RANDOM_SEED_OFFSET)

    def check_seed_blocks(self, n_tiers: int) -> None:
        """Refuse (one ConfigError naming the key and what is allowed) settings whose
        verification seeds overflow their block, that cannot give each of `n_tiers` tiers a
        verification batch, or whose budget cannot pay for the most probes and one batch a
        tier. `oodrl check-params` runs it, and the tier search before it measures anything."""
        block = CRN_SEED_BLOCK_END - CRN_VERIFY_SEED_OFFSET
        seeds = self.max_verify_batches * self.verify_batch
        if seeds > block:
            raise ConfigError(
                f"tiers.search.verify_batch: max_verify_batches {self.max_verify_batches} × "
                f"verify_batch {self.verify_batch} = {seeds} verification seeds overflow their "
                f"block of {block} (from seed + {CRN_VERIFY_SEED_OFFSET}). Allowed: "
                f"max_verify_batches × verify_batch <= {block}."
            )
        if self.max_verify_batches < n_tiers:
            raise ConfigError(
                f"tiers.search.max_verify_batches: {self.max_verify_batches} batches cannot "
                f"verify each of the {n_tiers} tiers once. Allowed: {n_tiers} or more."
            )
        need = self.max_probes * self.search_episodes + n_tiers * self.verify_batch
        if need > self.budget:
            raise ConfigError(
                f"tiers.search.budget: {self.budget} is below {need}, the most probes "
                f"(max_probes {self.max_probes} × search_episodes {self.search_episodes}) and "
                f"one verification batch of {self.verify_batch} for each of {n_tiers} tiers. "
                f"Allowed: {need} or more."
            )


class TiersConfig(_Section):
    """The `tiers` block (SPEC §15, §19): impact calibration, the tiers' detection streams and
    the per-stream operating point. Each fault's coarse impact curve is measured on `grid` over
    `episodes` whole episodes (π and the random policy each) and each tier is then searched for
    (`search`); every (fault, tier) cell has `n_streams` faulty streams, twins of as many clean
    ones. The per-stream alarm rule is calibrated on `n_calibration` held-out clean streams
    (seeds `seed + calibration_seed_offset + j`) at false-alarm budget `alpha` by
    `threshold_rule` (`episode_max_conditional`: P(FAR > α) ≤ `delta` over calibration draws;
    `episode_max`: marginal, E[FAR] ≤ α), and its achieved false-alarm rate measured on
    `n_audit` more (seeds `seed + audit_seed_offset + j`), used for nothing else.
    `detection_rate@K` counts first alarms within `k` steps of the onset."""

    grid: list[float] = Field(default_factory=lambda: [round(0.1 * i, 1) for i in range(1, 11)])
    episodes: int = Field(30, ge=2)
    search: TierSearchConfig = TierSearchConfig()
    n_streams: int = Field(100, ge=1)
    n_calibration: int = Field(200, ge=1)
    calibration_seed_offset: int = Field(20_000, ge=1)
    n_audit: int = Field(200, ge=1)
    audit_seed_offset: int = Field(30_000, ge=1)
    alpha: float = Field(0.05, gt=0, lt=1)
    k: int = Field(100, ge=0)
    threshold_rule: Literal["episode_max", "episode_max_conditional"] = "episode_max_conditional"
    delta: float = Field(0.1, gt=0, lt=1)


class ExecutorConfig(_Section):
    # 0 = all available cores. Results are identical for any worker count, so no stage lists
    # this key as a DVC param: changing it re-runs nothing.
    workers: int = Field(0, ge=0)
    progress: Literal["auto", "always", "never"] = "auto"

    @property
    def resolved_workers(self) -> int:
        import os

        return self.workers or len(os.sched_getaffinity(0))


class BenchmarkConfig(_Section):
    """Which detectors and injectors run; their parameters live in their own blocks.

    These lists drive the DVC stage fan-out (`foreach`/`matrix` need lists).
    """

    detectors: list[str] = Field(min_length=1)
    injectors: list[str] = Field(min_length=1)


class Params(_Section):
    seed: int = Field(0, ge=0)
    benchmark: BenchmarkConfig
    env: EnvConfig = EnvConfig()
    data: DataConfig = DataConfig()
    policy: PolicyConfig = PolicyConfig()
    anomaly: AnomalyConfig = AnomalyConfig()
    detectors: dict[str, dict[str, Any]] = Field(default_factory=dict)
    metrics: MetricsConfig = MetricsConfig()
    tiers: TiersConfig = TiersConfig()
    executor: ExecutorConfig = ExecutorConfig()

    @model_validator(mode="after")
    def _protocol_ranges(self) -> Params:
        T, onset = self.env.T, self.env.resolved_onset
        if self.env.onset is None and onset < 1:
            # The default onset floor(T/3) is derived from T: T is the key to change.
            raise ValueError(
                f"env.T: must be at least 3 when env.onset is null (the default onset "
                f"floor(T/3) must be at least 1); got {T}"
            )
        if not 1 <= onset < T:
            raise ValueError(f"env.onset: must be in [1, T={T}); got {onset}")
        offset = self.anomaly.offset
        if offset is not None and not onset < offset <= T:
            raise ValueError(
                f"anomaly.offset: must be null or in (onset={onset}, T={T}]; got {offset}"
            )
        grid = self.anomaly.sweep
        if not grid:
            raise ValueError("anomaly.sweep: must list at least one severity")
        if any(not 0 <= s <= 1 for s in grid):
            raise ValueError(f"anomaly.sweep: every severity must be in [0, 1]; got {grid}")
        if any(b <= a for a, b in zip(grid, grid[1:], strict=False)):
            raise ValueError(f"anomaly.sweep: must be strictly increasing; got {grid}")
        tiers = self.tiers
        if (
            not tiers.grid
            or any(b <= a for a, b in zip(tiers.grid, tiers.grid[1:], strict=False))
            or not all(0 < s <= 1 for s in tiers.grid)
        ):
            raise ValueError(
                "tiers.grid: must be at least one severity, strictly increasing, each in (0, 1]; "
                f"got {tiers.grid}"
            )
        needed = math.ceil(1 / Fraction(str(tiers.alpha))) - 1
        if tiers.n_calibration < needed:
            raise ValueError(
                f"tiers.n_calibration: the per-stream rule at alpha={tiers.alpha} needs at least "
                f"{needed} clean calibration streams (ceil(1/alpha) - 1); got "
                f"{tiers.n_calibration}"
            )
        for key, names, blocks in (
            ("detectors", self.benchmark.detectors, self.detectors),
            ("injectors", self.benchmark.injectors, self.anomaly.injectors),
        ):
            if len(set(names)) != len(names):
                raise ValueError(f"benchmark.{key}: names must be unique; got {names}")
            missing = [n for n in names if n not in blocks]
            if missing:
                section = "detectors" if key == "detectors" else "anomaly.injectors"
                raise ValueError(
                    f"benchmark.{key}: {missing[0]!r} has no parameter block under {section}."
                    f"{did_you_mean(missing[0], [*blocks, *_registered(key)])} "
                    f"Blocks: {', '.join(sorted(blocks)) or 'none'}."
                )
        return self

    # -- components, validated on load (all) or when a stage builds one ---------------------
    def detector_class(self, name: str) -> type:
        from oodrl.detectors import DETECTORS
        from oodrl.detectors.library import check_detector_class

        block = self.detectors[name]
        return _component_class(DETECTORS, "detectors", name, block, check_detector_class)

    def injector_class(self, name: str) -> type:
        from oodrl.injectors import INJECTORS

        block = self.anomaly.injectors[name]
        return _component_class(INJECTORS, "anomaly.injectors", name, block, _check_injector_class)

    @property
    def detector_classes(self) -> dict[str, type]:
        return {name: self.detector_class(name) for name in self.detectors}

    @property
    def injector_classes(self) -> dict[str, type]:
        return {name: self.injector_class(name) for name in self.anomaly.injectors}

    def detector(self, name: str):
        """A fresh, validated detector instance built from its params block."""
        return _build(self.detector_class(name), f"detectors.{name}", self.detectors[name])

    def injector(self, name: str):
        block = self.anomaly.injectors[name]
        return _build(self.injector_class(name), f"anomaly.injectors.{name}", block)

    def injector_severity(self, name: str) -> float:
        own = self.anomaly.injectors[name].get("severity")
        return self.anomaly.severity if own is None else float(own)

    def validate_components(self) -> None:
        from oodrl.envs import ENVIRONMENTS

        try:
            ENVIRONMENTS.get(self.env.id)
        except OodrlError as error:
            raise ConfigError(f"env.id: {error}") from None
        for name in self.detectors:
            self.detector(name)
        for name in self.anomaly.injectors:
            self.injector(name)
        self.policy_train_config()

    def policy_train_config(self):
        """policy.train as its trainer's typed settings (unknown keys refused).

        ``algorithm`` picks the trainer: ``noisy_dqn`` (oodrl's own, discrete actions; the
        default) or ``sac`` (Stable-Baselines3 SAC, continuous control).
        """
        from oodrl.policies.settings import TRAINER_CONFIGS

        settings = dict(self.policy.train)
        algorithm = settings.pop("algorithm", "noisy_dqn")
        if algorithm not in TRAINER_CONFIGS:
            raise ConfigError(
                f"policy.train.algorithm: unknown trainer {algorithm!r}. "
                f"Allowed: {', '.join(TRAINER_CONFIGS)}."
            )
        config_class = TRAINER_CONFIGS[algorithm]
        allowed = {f.name for f in dataclasses.fields(config_class)}
        for key, value in settings.items():
            if key not in allowed:
                hint = did_you_mean(key, allowed)
                raise ConfigError(
                    f"policy.train.{key}: unknown key for algorithm {algorithm}.{hint} "
                    f"Allowed: algorithm, {', '.join(sorted(allowed))}."
                )
            allowed_values = _TRAIN_RANGES.get(key, [])
            if allowed_values and not any(check(value) for check in allowed_values):
                allowed_text = " or ".join(str(check) for check in allowed_values)
                raise ConfigError(f"policy.train.{key}: must be {allowed_text}; got {value!r}")
        env_id = settings.get("env_id", self.env.id)
        if env_id != self.env.id:
            raise ConfigError(
                f"policy.train.env_id: must be env.id ({self.env.id}), the environment the "
                f"policy acts in; got {env_id!r}"
            )
        try:
            return config_class(**settings)
        except (TypeError, ValueError) as error:
            raise ConfigError(f"policy.train: {error}") from None


_COUNT = Interval(int, 1, None)
#: The range of every numeric policy.train setting (and the type of every other), whichever
#: trainer has it: the trainers' dataclasses check nothing, and training comes last to read them.
_TRAIN_RANGES: dict[str, list] = {
    key: allowed
    for keys, allowed in (
        (("env_id", "source", "file", "sha256"), [IsType(str)]),
        (("hidden_sizes",), [SequenceOf(_COUNT)]),
        (("total_steps", "batch_size", "buffer_size", "train_freq", "target_sync"), [_COUNT]),
        (("eval_every", "eval_episodes", "final_eval_episodes"), [_COUNT]),
        (("gradient_steps",), [_COUNT, Options((-1,))]),  # Stable-Baselines3: -1 = per env step
        (("learning_starts", "final_eval_seed", "seed"), [Interval(int, 0, None)]),
        (("lr", "adam_eps", "max_grad_norm"), [Interval(float, 0, None, closed="neither")]),
        (("lr_final", "sigma0"), [Interval(float, 0, None)]),
        (("gamma",), [Interval(float, 0, 1)]),
        (("tau",), [Interval(float, 0, 1, closed="right")]),
        (("early_stop_return",), [Interval(float, None, None)]),
    )
    for key in keys
}


def did_you_mean(name: str, candidates: list[str]) -> str:
    """' Did you mean 'x'?' for the closest candidate, or '' when none is close."""
    close = difflib.get_close_matches(name, sorted(set(candidates)), n=1)
    return f" Did you mean '{close[0]}'?" if close else ""


def _registered(key: str) -> list[str]:
    """Names registered for `detectors` or `injectors` (built-ins and entry points)."""
    if key == "detectors":
        from oodrl.detectors import DETECTORS

        return DETECTORS.names()
    from oodrl.injectors import INJECTORS

    return INJECTORS.names()


def _component_class(registry, section: str, name: str, block: dict[str, Any], check) -> type:
    """The class a block names (its `class:` path or its name), checked to be of its kind."""
    path = block.get("class")
    try:
        cls = registry.get(path if path else name)
        check(cls, path or name)
    except OodrlError as error:
        raise ConfigError(f"{section}.{name}: {error}") from None
    return cls


def _check_injector_class(obj: Any, path: str) -> None:
    from oodrl.core.injector import BaseAnomalyInjector

    if not (isinstance(obj, type) and issubclass(obj, BaseAnomalyInjector)):
        raise ConfigError(
            f"{path} is not an injector class. Allowed: a subclass of "
            "oodrl.core.injector:BaseAnomalyInjector."
        )


def _build(cls: type, key: str, block: dict[str, Any]):
    params = {k: v for k, v in block.items() if k != "class"}
    try:
        return cls.from_params(params)
    except ParameterError as error:
        raise ConfigError(f"{key}.{error.param}: {error}") from None
    except OodrlError as error:
        raise ConfigError(f"{key}: {error}") from None


#: Longest offending value quoted in an error; a section's whole mapping is never quoted.
_MAX_QUOTED = 60


def _format_pydantic(error: ValidationError) -> str:
    first = error.errors()[0]
    message = first["msg"].removeprefix("Value error, ")
    if not first["loc"]:
        # A check across sections: its message names the key; its input is all of params.
        return message
    loc = ".".join(str(p) for p in first["loc"])
    if first["type"] == "extra_forbidden":
        known = _section_keys(first["loc"][:-1])
        if len(first["loc"]) == 1:
            known.append(EXTENDS_KEY)  # read before validation, but a top-level key all the same
        return (
            f"{loc}: unknown key.{did_you_mean(str(first['loc'][-1]), known)} "
            f"Allowed: {', '.join(known)}."
        )
    if message.startswith(loc):
        return message
    quoted = repr(first.get("input"))
    if first["type"] == "missing" or len(quoted) > _MAX_QUOTED:
        return f"{loc}: {message}"
    return f"{loc}: {message} (got {quoted})"


def _what(data: Any) -> str:
    """What a params file holds that is not a mapping, in words."""
    return "an empty file" if data is None else f"a YAML {type(data).__name__}"


def _section_keys(loc: tuple) -> list[str]:
    """The keys of the params section at `loc` (() = the top level)."""
    model: Any = Params
    for part in loc:
        model = model.model_fields[part].annotation
    return list(model.model_fields)


def parse_params(data: Any, source: str = "params", *, components: bool = True) -> Params:
    """Validate params; `components=False` checks structure and ranges only, leaving each
    detector, injector and trainer to be validated when a stage builds it (so a stage imports,
    and its code stamp lists, only the components it builds; check_params validates all)."""
    if not isinstance(data, dict):
        raise ConfigError(
            f"{source}: must be a mapping of sections ({', '.join(_section_keys(()))}); "
            f"got {_what(data)}."
        )
    try:
        params = Params.model_validate(data)
    except ValidationError as error:
        raise ConfigError(f"{source}: {_format_pydantic(error)}") from None
    if not components:
        return params
    try:
        params.validate_components()
    except ConfigError as error:
        raise ConfigError(f"{source}: {error}") from None
    return params


def load_params(path: Path | str = DEFAULT_PARAMS, *, components: bool = True) -> Params:
    """Read and validate a params file; every problem is a one-line ConfigError."""
    path = Path(path)
    return parse_params(read_params_data(path), str(path), components=components)


#: A params file may name a base file whose values it overrides (paths relative to itself).
EXTENDS_KEY = "extends"


def read_params_data(path: Path) -> dict[str, Any]:
    """The params mapping of ``path`` with its ``extends`` chain merged in (no validation).

    An environment's params file holds only what is specific to it and extends the shared
    ``params.yaml`` (SPEC §11): mappings merge key by key, anything else replaces the base value.
    """
    data = _read_yaml(path)
    chain = [path.resolve()]
    while isinstance(data, dict) and EXTENDS_KEY in data:
        base_path = (chain[-1].parent / str(data[EXTENDS_KEY])).resolve()
        if base_path in chain:
            raise ConfigError(f"{path}: '{EXTENDS_KEY}' chain loops back to {base_path.name}.")
        base = _read_yaml(base_path, named_by=f"{path}: {EXTENDS_KEY}")
        if not isinstance(base, dict):
            # A base that is no mapping would be dropped by the merge, silently.
            raise ConfigError(
                f"{path}: {EXTENDS_KEY} {base_path}: must be a mapping of sections; got "
                f"{_what(base)}."
            )
        data = merge_params(base, {k: v for k, v in data.items() if k != EXTENDS_KEY})
        chain.append(base_path)
    return data


#: Blocks an override replaces whole: one environment's training settings never fit another's.
REPLACED_BLOCKS = {("policy", "train")}


def merge_params(base: Any, override: Any, at: tuple[str, ...] = ()) -> Any:
    """``override`` on top of ``base``: mappings merge recursively, other values (and the
    REPLACED_BLOCKS) replace."""
    if isinstance(base, dict) and isinstance(override, dict) and at not in REPLACED_BLOCKS:
        merged = dict(base)
        for key, value in override.items():
            merged[key] = merge_params(base[key], value, (*at, key)) if key in base else value
        return merged
    return override


def _read_yaml(path: Path, named_by: str = "") -> Any:
    import yaml

    from oodrl.io import yamlio

    if not path.is_file():
        prefix = f"{named_by} " if named_by else ""
        raise ConfigError(f"{prefix}{path}: params file not found.")
    try:
        return yamlio.load(path.read_text())  # libyaml: every stage reads its params first
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file (not UTF-8); expected YAML.") from None
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark else ""
        raise ConfigError(f"{path}: not valid YAML{where}.") from None
