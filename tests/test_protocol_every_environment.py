"""The whole protocol on every environment of the suite, with tiny params (SPEC §3, §11).

For each environment: its own params (pipeline/<env>/params.yaml, extending the shared ones)
shrunk to a few short streams; collection of the clean sets and of all nine injectors at the
headline and one sweep severity; every detector of the suite (the paper's eight, the library
ones and SPEC §20's, those reading the policy given the environment's) fitted, calibrated,
scoring the clean sets and three injectors' sets; the metrics stage's results on those. Environments
whose policy is not committed yet run an untrained exported actor of the right shape: the
protocol, not the policy, is under test here.

Which three injectors an environment's detectors score rotates with the environment
(`scored_injectors`): each injector's sets are scored by every detector on a discrete-action and
on a continuous-action environment. Scoring is most of the cost (one store read and written per
detector and set, ~0.4 s of CPU) and its code does not depend on the injector; all nine (9 x 2
sets x ~23 detectors an environment) took ~120 s of CPU per environment, three take ~45 s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from oodrl.config import merge_params, parse_params, read_params_data
from oodrl.io import yamlio
from oodrl.metrics.results import compute_results
from oodrl.stages import collect, fit, score
from oodrl.suite.environments import PIPELINE_DIRS, policy_path

ROOT = Path(__file__).resolve().parents[1]
CI_PARAMS = read_params_data(ROOT / "ci" / "params.yaml")
TINY = {
    "env": {"T": 36},
    "data": {"n_id": 4, "n_ood": 2},
    "anomaly": {"sweep": [0.7]},
    "metrics": {"n_boot": 10},
    "executor": {"workers": 1, "progress": "never"},
    "detectors": CI_PARAMS["detectors"],  # few members and epochs
}


def untrained_actor(env_id: str, path: Path) -> Path:
    """An oodrl checkpoint of a random tanh_actor for the environment's spaces."""
    import torch

    from oodrl.envs import ENVIRONMENTS

    adapter = ENVIRONMENTS.get(env_id)()
    rng = np.random.default_rng(0)
    sizes = (adapter.state_dim, 16, adapter.action_size)
    state = {}
    for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
        weight = rng.standard_normal((n_out, n_in)) / np.sqrt(n_in)
        state[f"net.{2 * i}.weight"] = torch.tensor(weight, dtype=torch.float32)
        state[f"net.{2 * i}.bias"] = torch.zeros(n_out)
    architecture = {
        "kind": "tanh_actor",
        "action_low": [float(v) for v in adapter.action_low],
        "action_high": [float(v) for v in adapter.action_high],
    }
    torch.save({"format": "oodrl-policy", "version": 1, "architecture": architecture,
                "state_dict": state}, path)  # fmt: skip
    return path


def reading(data: dict, policy: Path) -> dict:
    """The detectors that read the policy (SPEC §20) read this environment's: their `policy`,
    relative to a pipeline's directory, would name the root's from here."""
    from oodrl.detectors import DETECTORS
    from oodrl.detectors.policy_view import PolicyDetector

    names = data["benchmark"]["detectors"]
    readers = [n for n in names if n in DETECTORS and issubclass(DETECTORS.get(n), PolicyDetector)]
    return {"detectors": {n: {"policy": str(policy)} for n in readers}}


#: Injectors whose sets each environment's detectors score (a rotation, see the docstring).
SCORED_PER_ENVIRONMENT = 3


def scored_injectors(env_id: str, injectors: list[str]) -> list[str]:
    """Three of the injectors, the next three in order for the next environment: over the
    discrete environments (listed first) and over the continuous ones, all nine."""
    start = list(PIPELINE_DIRS).index(env_id) * SCORED_PER_ENVIRONMENT
    return [injectors[(start + i) % len(injectors)] for i in range(SCORED_PER_ENVIRONMENT)]


def test_every_injector_is_scored_on_both_action_kinds():
    from oodrl.envs import ENVIRONMENTS

    injectors = read_params_data(ROOT / "params.yaml")["benchmark"]["injectors"]
    scored: dict[str, set[str]] = {"discrete": set(), "continuous": set()}
    for env_id, directory in PIPELINE_DIRS.items():
        data = read_params_data(ROOT / directory / "params.yaml")
        assert data["benchmark"]["injectors"] == injectors, env_id  # one rotation fits all
        scored[ENVIRONMENTS.get(env_id)().action_kind] |= set(scored_injectors(env_id, injectors))
    assert scored == {"discrete": set(injectors), "continuous": set(injectors)}


@pytest.mark.slow
@pytest.mark.parametrize("env_id", list(PIPELINE_DIRS))
def test_the_protocol_runs_on_every_environment(env_id, tmp_path: Path):
    data = read_params_data(ROOT / PIPELINE_DIRS[env_id] / "params.yaml")
    policy = policy_path(env_id, ROOT)
    if not policy.is_file():
        policy = untrained_actor(env_id, tmp_path / "policy.pt")
    merged = merge_params(merge_params(data, TINY), reading(data, policy))
    params = parse_params(merged)
    collect.collect_id(params, policy, tmp_path / "id.zarr")
    collect.collect_eval(params, policy, tmp_path / "eval.zarr")
    for injector in params.benchmark.injectors:
        for kind, write in [("ood", collect.collect_ood), ("sweep", collect.collect_sweep)]:
            write(
                params,
                injector,
                policy,
                tmp_path / "eval.zarr",
                tmp_path / kind / f"{injector}.zarr",
            )
    scored = scored_injectors(env_id, list(params.benchmark.injectors))
    scores = tmp_path / "scores"
    for detector in params.benchmark.detectors:
        model = tmp_path / "models" / f"{detector}.pkl"
        fit.fit_detector(params, detector, tmp_path / "id.zarr", model)
        score.score_clean_sets(detector, model, scores, tmp_path / "eval.zarr", {})
        for injector in scored:
            headline, sweep = tmp_path / "ood", tmp_path / "sweep"
            score.score_injector_sets(detector, injector, model, scores, headline, sweep, None)
    # The metrics stage on the scored injectors (it reads the sets of every injector it is given).
    results = compute_results(
        parse_params(merge_params(merged, {"benchmark": {"injectors": scored}})), scores
    )
    records = [r for r in results.records if r.kind == "anomaly"]
    assert len(records) == len(params.benchmark.detectors) * len(scored)
    assert sorted(results.sweep) == sorted(scored)
    values = [r.metrics["matched_auroc"]["mean"] for r in records]
    assert all(0.0 <= v <= 1.0 for v in values)
    # Something is detected somewhere: no environment is degenerate for the whole protocol.
    assert max(values) > 0.6, yamlio.dump(sorted(values))
