"""SPEC §20's detectors in the suite (issue 41): every environment's pipeline runs the nine it
can, the policy-view ones exactly where its policy has a discrete value head; a detector that
reads the policy has its fit stage depend on the policy file; the root stays the paper's eight.
Cheap: params, committed policies and generated DVC files are read, nothing is built."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from oodrl.config import read_params_data
from oodrl.detectors import DETECTORS
from oodrl.detectors.policy_view import PolicyDetector, QMargin
from oodrl.io.layout import detector_pipeline
from oodrl.policies.load import load_policy
from oodrl.suite.pipeline import POLICY, Project, pipeline_dirs, policy_file, rendered_detector

POLICY_VIEW = ["q_margin", "q_entropy", "q_energy", "max_softmax"]
EVERYWHERE = ["fqe_td", "riqn", "conformal_martingale", "deedee", "random_scores"]
#: SPEC §24's sequential baselines (protocol 4), in every environment's list too.
SEQUENTIAL = ["cusum_tv", "action_consistency"]
PAPER = [
    "mahalanobis_distance",
    "time_series_features",
    "pedm",
    "autoencoder",
    "ensemble_disagreement",
    "cusum",
    "kde_density",
    "lyapunov_divergence",
]
LUNAR_LANDER = Path("pipeline") / "lunar_lander"


def _environments(root: Path) -> list[Path]:
    return [d for d in pipeline_dirs(root) if d != root]


def _detectors(directory: Path) -> list[str]:
    return read_params_data(directory / "params.yaml")["benchmark"]["detectors"]


def _fit_deps(root: Path, directory: Path, detector: str) -> list[str]:
    stages = yaml.safe_load(rendered_detector(directory, root, detector))["stages"]
    return stages["fit"]["deps"]


def test_every_environment_runs_the_new_detectors_its_policy_supports(repo_root):
    suite = _detectors(repo_root / "pipeline")
    assert suite[-11:] == POLICY_VIEW + EVERYWHERE + SEQUENTIAL
    environments = _environments(repo_root)
    assert len(environments) == 21  # 7 environments, 3 policies each
    value_heads = 0
    for directory in environments:
        detectors = _detectors(directory)
        params = read_params_data(directory / "params.yaml")
        for name in POLICY_VIEW + EVERYWHERE + SEQUENTIAL:
            assert name in params["detectors"], f"{directory.name}: no detectors.{name} block"
        # The committed policy decides, in the detectors' own words.
        policy = load_policy(str(directory / POLICY))
        supported = QMargin.policy_support(policy) is None
        value_heads += supported
        expected = suite if supported else [d for d in suite if d not in POLICY_VIEW]
        assert detectors == expected, directory.name
    assert value_heads == 9  # LunarLander, CartPole and Acrobot: three policies each


@pytest.mark.parametrize("name", POLICY_VIEW + EVERYWHERE + SEQUENTIAL)
def test_a_fit_stage_depends_on_the_policy_exactly_when_its_detector_reads_it(repo_root, name):
    """fqe_td reads the policy too (π(s′) of its targets): its fit depends on the file."""
    directory = repo_root / LUNAR_LANDER
    reads = issubclass(DETECTORS.get(name), PolicyDetector)
    assert reads == (name in POLICY_VIEW or name in ("fqe_td", "action_consistency"))
    deps = _fit_deps(repo_root, directory, name)
    assert (POLICY in deps) == reads
    assert deps[-1] == (POLICY if reads else "data/id.zarr")
    # The committed file is the generated one (`oodrl pipeline check` says so for all).
    committed = yaml.safe_load((directory / detector_pipeline(name)).read_text())
    assert committed["stages"]["fit"]["deps"] == deps
    # Scoring reads the fitted detector, which holds the policy's network, not the file.
    assert POLICY not in committed["stages"]["score_clean"]["deps"]


def test_the_policy_dep_is_the_policy_params_name(repo_root):
    directory = repo_root / LUNAR_LANDER
    project = Project(repo_root, directory)
    params = read_params_data(directory / "params.yaml")
    assert policy_file("q_margin", params, project) == POLICY
    params["detectors"]["q_margin"] = {**params["detectors"]["q_margin"], "policy": "other.pt"}
    assert policy_file("q_margin", params, project) == "other.pt"
    params["detectors"]["fqe_td"] = {}  # the class's default
    assert policy_file("fqe_td", params, project) == POLICY
    # A library class is not imported to ask (PyOD's import costs seconds): no policy.
    assert policy_file("pyod_knn", params, project) is None
    assert policy_file("mahalanobis_distance", params, project) is None


def test_the_root_stays_the_papers_eight(repo_root):
    assert _detectors(repo_root) == PAPER
    for name in POLICY_VIEW + EVERYWHERE:
        assert not (repo_root / detector_pipeline(name)).exists()
    # A SAC environment's own list: the suite's without the policy view.
    assert not set(POLICY_VIEW) & set(_detectors(repo_root / "pipeline" / "pendulum"))
