"""params.yaml validation: every bad edit is one line naming the key, exit code 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.config import load_params, parse_params
from oodrl.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_default_params_are_valid(default_params):
    params = parse_params(default_params)
    assert params.env.resolved_onset == 166
    assert params.data.n_calibration == 6
    assert params.injector_severity("gaussian_state_noise") == params.anomaly.severity


def _set(path: str, value):
    def edit(p):
        *parents, leaf = path.split(".")
        for key in parents:
            p = p[key]
        p[leaf] = value

    return edit


def _delete(path: str):
    def edit(p):
        *parents, leaf = path.split(".")
        for key in parents:
            p = p[key]
        del p[leaf]

    return edit


BAD = [
    ("unknown top-level key", _set("sedd", 1), "sedd: unknown key"),
    ("unknown nested key", _set("env.horizon", 3), "env.horizon: unknown key"),
    ("wrong type", _set("env.T", "500"), "env.T: Input should be a valid integer"),
    ("negative seed", _set("seed", -1), "seed: Input should be greater than or equal to 0"),
    ("severity above 1", _set("anomaly.severity", 1.5), "anomaly.severity"),
    ("onset at T", _set("env.onset", 500), "env.onset: must be in [1, T=500)"),
    ("onset zero", _set("env.onset", 0), "env.onset: must be in [1, T=500)"),
    ("n_id below 2", _set("data.n_id", 1), "data.n_id"),
    ("negative n_ood", _set("data.n_ood", -3), "data.n_ood"),
    ("unsorted sweep", _set("anomaly.sweep", [0.4, 0.2]), "anomaly.sweep: must be strictly"),
    ("sweep out of range", _set("anomaly.sweep", [0.2, 1.2]), "anomaly.sweep: every severity"),
    ("empty sweep", _set("anomaly.sweep", []), "anomaly.sweep"),
    ("calibration fraction 1", _set("data.calibration_fraction", 1.0), "calibration_fraction"),
    ("unknown policy mode", _set("policy.mode", "eps"), "policy.mode"),
    (
        "unknown detector",
        _set("benchmark.detectors", ["kde_densty"]),
        "benchmark.detectors: 'kde_densty' has no parameter block",
    ),
    (
        "unknown component class",
        _set("detectors.kde_densty", {}),
        "detectors.kde_densty: Unknown detector 'kde_densty'. Did you mean 'kde_density'?",
    ),
    (
        "bad plugin path",
        _set("detectors.mine", {"class": "no_such_module_xyz:Detector"}),
        "detectors.mine: Cannot import module 'no_such_module_xyz'",
    ),
    (
        "unknown detector parameter",
        _set("detectors.kde_density.bandwith", 0.3),
        "detectors.kde_density: KdeDensity has no parameter 'bandwith'",
    ),
    (
        "injector severity above 1",
        _set("anomaly.injectors.gaussian_state_noise.severity", 2.0),
        "anomaly.injectors.gaussian_state_noise: The 'severity' parameter",
    ),
    (
        "max_delay below 1",
        _set("anomaly.injectors.observation_delay.max_delay", 0),
        "anomaly.injectors.observation_delay: The 'max_delay' parameter",
    ),
    (
        "ramp_steps below 1",
        _set("anomaly.injectors.gradual_drift.ramp_steps", 0),
        "anomaly.injectors.gradual_drift: The 'ramp_steps' parameter",
    ),
    (
        "negative threshold percentile",
        _set("detectors.cusum.threshold_percentile", -5.0),
        "detectors.cusum: The 'threshold_percentile' parameter",
    ),
    (
        "unknown threshold rule",
        _set("detectors.pedm.threshold_rule", "mean"),
        "detectors.pedm: The 'threshold_rule' parameter",
    ),
    ("unknown env", _set("env.id", "LunarLander-v9"), "env.id: Unknown environment"),
    ("missing injector block", _delete("anomaly.injectors.regime_switch"), "benchmark.injectors"),
    ("negative workers", _set("executor.workers", -1), "executor.workers"),
    ("offset before onset", _set("anomaly.offset", 100), "anomaly.offset"),
    ("unknown policy.train key", _set("policy.train.learning_rate", 0.1), "policy.train"),
    ("closest top-level key", _set("sedd", 1), "sedd: unknown key. Did you mean 'seed'? Allowed:"),
    ("closest section key", _set("tiers.alhpa", 0.1), "tiers.alhpa: unknown key. Did you mean"),
    ("empty tiers grid", _set("tiers.grid", []), "tiers.grid: must be at least one severity"),
    ("negative lr", _set("policy.train.lr", -0.1), "policy.train.lr: must be a float > 0"),
    ("hidden size zero", _set("policy.train.hidden_sizes", [64, 0]), "policy.train.hidden_sizes"),
    ("policy of another env", _set("policy.train.env_id", "CartPole-v1"), "policy.train.env_id"),
    ("eval seeds on ID seeds", _set("data.eval_seed_offset", 29), "data.eval_seed_offset: the"),
    (
        "calibration seeds on eval seeds",
        _set("tiers.calibration_seed_offset", 10_099),
        "tiers.calibration_seed_offset: the tier calibration streams (seeds seed + 10099..10298) "
        "overlap the evaluation streams and the tier cells' twins (seed + 10000..10099)",
    ),
    (
        "impact episodes overlap",
        _set("tiers.episodes", 100_001),
        "tiers.episodes: the random policy's impact episodes",
    ),
    (
        "tier search episodes overflow their seed block",
        _set("tiers.search.search_episodes", 50_001),
        "tiers.search.search_episodes: Input should be less than or equal to 50000",
    ),
    (
        "tier verification overflows its seed block",
        _set("tiers.search.verify_batch", 1_001),
        "tiers.search.verify_batch: max_verify_batches 50 × verify_batch 1001 = 50050 "
        "verification seeds overflow their block of 50000 (from seed + 950000). Allowed: "
        "max_verify_batches × verify_batch <= 50000.",
    ),
    (
        "fewer verification batches than tiers",
        _set("tiers.search.max_verify_batches", 3),
        "tiers.search.max_verify_batches: 3 batches cannot verify each of the 4 tiers once. "
        "Allowed: 4 or more.",
    ),
    (
        "tier search budget below its probes",
        _set("tiers.search.budget", 700),
        "tiers.search.budget: 700 is below 800, the most probes (max_probes 6 × search_episodes "
        "100) and one verification batch of 50 for each of 4 tiers. Allowed: 800 or more.",
    ),
    (
        "protocol 3's tier search key",
        _set("tiers.search.probe_episodes", 50),
        "tiers.search.probe_episodes: unknown key.",
    ),
    (
        "audit streams on the tier search's seeds",
        _set("tiers.audit_seed_offset", 950_100),
        "tiers.audit_seed_offset: the audit streams (seeds seed + 950100..950299) overlap the "
        "tier verification's episodes",
    ),
    (
        "episode_max without the held-out streams",
        _set("detectors.cusum.threshold_rule", "episode_max"),
        "detectors.cusum.alpha: threshold_rule episode_max at alpha=0.05 needs at least 19",
    ),
    (
        "detector class without the outlier API",
        _set("detectors.mine", {"class": "sklearn.linear_model:LinearRegression"}),
        "detectors.mine: sklearn.linear_model:LinearRegression has no outlier API",
    ),
    (
        "hbos alpha under the percentile rule",
        _set("detectors.mine", {"class": "pyod.models.hbos:HBOS", "alpha": 0.2}),
        "detectors.mine.alpha: 'alpha' is oodrl's key",
    ),
]


def _checked(data: dict):
    """What `oodrl check-params` runs: loading, then the checks beyond it, file-prefixed."""
    from oodrl.suite.params_check import check_completely

    params = parse_params(data, "params.yaml")
    try:
        check_completely(params)
    except ConfigError as error:
        raise ConfigError(f"params.yaml: {error}") from None
    return params


@pytest.mark.parametrize(("case", "edit", "message"), BAD, ids=[b[0] for b in BAD])
def test_bad_params_are_one_line_errors(default_params, case, edit, message):
    edit(default_params)
    with pytest.raises(ConfigError) as info:
        _checked(default_params)
    text = str(info.value)
    assert "\n" not in text
    assert text.startswith("params.yaml: ")
    assert message in text
    assert len(text) < 400, "a one-line error never quotes a whole section"


def test_a_target_action_the_environment_lacks_is_refused_by_check_completely(default_params):
    from oodrl.suite.params_check import check_completely

    default_params["anomaly"]["injectors"]["action_conditioned_dynamics"]["target_action"] = 4
    params = parse_params(default_params, "params.yaml")  # stages validate without gymnasium
    with pytest.raises(ConfigError) as info:
        check_completely(params)
    text = str(info.value)
    assert "\n" not in text
    assert "anomaly.injectors.action_conditioned_dynamics: The 'target_action' parameter" in text


def test_an_environment_file_extends_the_shared_params(tmp_path):
    shared = yaml.safe_load((ROOT / "params.yaml").read_text())
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(shared))
    (tmp_path / "pendulum").mkdir()
    (tmp_path / "pendulum" / "params.yaml").write_text(
        "extends: ../params.yaml\n"
        "env: {id: Pendulum-v1, T: 200}\n"
        "policy: {train: {algorithm: sac, env_id: Pendulum-v1, total_steps: 1000}}\n"
    )
    params = load_params(tmp_path / "pendulum" / "params.yaml")
    assert (params.env.id, params.env.T, params.env.onset) == ("Pendulum-v1", 200, None)
    assert params.data == parse_params(shared).data  # sections it does not name are shared
    # policy.train is replaced whole: one environment's training settings never fit another.
    assert type(params.policy_train_config()).__name__ == "SacConfig"
    assert params.policy_train_config().total_steps == 1000
    (tmp_path / "params.yaml").write_text("extends: pendulum/params.yaml\n")
    with pytest.raises(ConfigError, match="loops back"):
        load_params(tmp_path / "pendulum" / "params.yaml")


def test_cross_section_error_does_not_quote_the_params(default_params):
    """A check across sections used to append pydantic's input: all of params (3,193 chars)."""
    default_params["env"]["onset"] = 600
    with pytest.raises(ConfigError) as info:
        parse_params(default_params, "params.yaml")
    assert str(info.value) == "params.yaml: env.onset: must be in [1, T=500); got 600"


def test_missing_section_does_not_quote_the_params(default_params):
    del default_params["benchmark"]
    with pytest.raises(ConfigError) as info:
        parse_params(default_params, "params.yaml")
    assert str(info.value) == "params.yaml: benchmark: Field required"


@pytest.mark.parametrize(
    ("key", "typo", "meant"),
    [("detectors", "kde_densty", "kde_density"), ("injectors", "stuck_actuater", "stuck_actuator")],
)
def test_misspelt_benchmark_name_suggests_the_closest(default_params, key, typo, meant):
    names = default_params["benchmark"][key]
    names[names.index(meant)] = typo
    with pytest.raises(ConfigError) as info:
        parse_params(default_params, "params.yaml")
    assert f"benchmark.{key}: '{typo}' has no parameter block" in str(info.value)
    assert f"Did you mean '{meant}'?" in str(info.value)


def test_too_short_T_with_default_onset_blames_T(default_params):
    """onset: null means floor(T/3); with T = 2 that is 0, and T is the key to change."""
    default_params["env"].update(T=2, onset=None)
    with pytest.raises(ConfigError) as info:
        parse_params(default_params, "params.yaml")
    assert str(info.value).startswith("params.yaml: env.T: must be at least 3")
    assert "got 2" in str(info.value)
    default_params["env"]["onset"] = 1
    assert parse_params(default_params).env.resolved_onset == 1


def test_check_params_cli_exit_codes(tmp_path, default_params):
    good = tmp_path / "good.yaml"
    good.write_text(yaml.safe_dump(default_params))
    runner = CliRunner()
    result = runner.invoke(app, ["check-params", str(good)])
    assert result.exit_code == 0, result.output
    assert "ok (8 detectors, 9 injectors" in result.output

    default_params["anomaly"]["severity"] = -0.1
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(default_params))
    result = runner.invoke(app, ["check-params", str(bad)])
    assert result.exit_code == 2
    assert result.output.count("\n") == 1 and "anomaly.severity" in result.output


def test_check_params_refuses_a_tier_search_that_overflows_its_seeds(tmp_path, default_params):
    """Exit 2 and one line naming the key, before any stage runs (SPEC §22)."""
    default_params["tiers"]["search"].update(verify_batch=2_000, max_verify_batches=30)
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(default_params))
    result = CliRunner().invoke(app, ["check-params", str(bad)])
    assert result.exit_code == 2
    assert result.output.count("\n") == 1 and "tiers.search.verify_batch: " in result.output


def test_episode_max_alpha_the_message_allows_passes(default_params):
    """Six held-out streams allow alpha >= 1/7: the message offers 0.1429 (1/7 as a float is
    a hair below 1/7, and needs seven)."""
    cusum = default_params["detectors"]["cusum"]
    cusum.update(threshold_rule="episode_max", alpha=0.1428)
    with pytest.raises(ConfigError, match=r"Allowed: alpha >= 1/7 \(0.1429 or more\)"):
        _checked(default_params)
    cusum["alpha"] = 0.1429
    assert _checked(default_params).detector("cusum").alpha == 0.1429


def test_missing_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="params file not found"):
        load_params(tmp_path / "absent.yaml")
    broken = tmp_path / "broken.yaml"
    broken.write_text("seed: [1,\n")
    with pytest.raises(ConfigError, match="not valid YAML at line"):
        load_params(broken)


def test_check_params_subprocess_has_no_traceback(tmp_path, default_params):
    default_params["env"]["T"] = 1
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(default_params))
    done = subprocess.run(
        [sys.executable, "-m", "oodrl", "check-params", str(bad)], capture_output=True, text=True
    )
    assert done.returncode == 2
    assert done.stderr.strip().count("\n") == 0
    assert "env.T" in done.stderr and "Traceback" not in done.stderr


def test_validating_params_imports_no_heavy_library(repo_root):
    """Every stage validates params.yaml on start: that must not cost torch's import."""
    code = (
        "import sys; from oodrl.config import load_params; load_params('params.yaml'); "
        "heavy = {'torch', 'sklearn', 'scipy', 'gymnasium', 'zarr'} & set(sys.modules); "
        "assert not heavy, heavy"
    )
    subprocess.run([sys.executable, "-c", code], cwd=repo_root, check=True)
