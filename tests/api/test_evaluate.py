"""oodrl.evaluate (SPEC §25): at a pipeline's own params, a built-in detector's numbers are the
pipeline's, bit for bit (the tests' tiny pipeline, built by `dvc repro` in a throw-away
repository), and it writes nothing into the pipeline; its arguments are checked before anything
runs, each refusal one line naming what is allowed."""

from __future__ import annotations

import os
import sys

import pandas as pd
import pytest
from tiny_pipeline import DETECTORS, INJECTORS, file_stamps

import oodrl
from oodrl.config import load_params
from oodrl.errors import ConfigError
from oodrl.protocol.impact import LEVELS

DETECTOR = "mahalanobis_distance"
KEYS = ["fault", "tier", "metric"]


@pytest.fixture
def tiny_pipeline(built_repo):
    """The tests' tiny pipeline (tests/tiny_pipeline.py), built once a session: the root
    pipeline on two detectors and two faults, a post-hoc observation fault (live at the tiers)
    and an online one. Other tests read and copy it: evaluate must leave it as it was."""
    assert DETECTOR in DETECTORS and INJECTORS == ["observation_delay", "stuck_actuator"]
    before = file_stamps(built_repo)
    yield built_repo
    assert file_stamps(built_repo) == before, "oodrl.evaluate wrote into the pipeline's directory"


@pytest.mark.slow
def test_at_the_pipelines_params_evaluate_gives_the_pipelines_numbers(tiny_pipeline):
    committed = oodrl.load_results(tiny_pipeline, kind="tiers")
    assert set(committed.detector) == set(DETECTORS)
    committed = committed[committed.detector == DETECTOR]
    assert not committed.empty
    detector = load_params(tiny_pipeline / "params.yaml", components=False).detector(DETECTOR)
    path = list(sys.path)
    frame = oodrl.evaluate(
        detector, env=tiny_pipeline, tiers=list(LEVELS), size="full", name=DETECTOR
    )
    assert sys.path == path  # loading the pickled detector added nothing to the caller's path
    assert detector.threshold_ is not None  # fitted and calibrated in place
    cells = frame[frame.fault.notna()].sort_values(KEYS).reset_index(drop=True)
    cells["verified"] = cells["verified"].astype(bool)  # object beside the cost rows' None
    pd.testing.assert_frame_equal(
        cells, committed.sort_values(KEYS).reset_index(drop=True), check_exact=True
    )
    cost = frame[frame.fault.isna()].set_index("metric").value
    assert cost["step_us_p99"] >= cost["step_us_median"] > 0 and cost["fit_s"] > 0
    assert frame.attrs["size"] == "full" and frame.attrs["n_calibration"] == 19


@pytest.mark.slow
def test_a_library_model_at_a_size_never_takes_more_streams_than_the_pipeline(tiny_pipeline):
    tiers = load_params(tiny_pipeline / "params.yaml", components=False).tiers
    frame = oodrl.evaluate(
        _library_knn(), env=tiny_pipeline, faults=["stuck_actuator"], tiers=list(LEVELS),
        size="tiny",
    )  # fmt: skip
    rates = frame[frame.metric == "detection_rate@100"]
    assert set(rates.fault) <= {"stuck_actuator"}
    # "tiny" asks for 10 faulty and 10 audit streams; this pipeline has fewer of each
    assert set(rates.n_streams) <= {tiers.n_streams} and frame.attrs["n_audit"] == tiers.n_audit
    assert frame.attrs["n_calibration"] == 19  # the fewest the marginal rule allows at α = 0.05
    assert set(frame.detector) == {"pyod.models.knn:KNN"}


def _library_knn():
    from pyod.models.knn import KNN

    return KNN(n_neighbors=3)


def test_a_library_model_is_wrapped_as_the_suite_wraps_its_class():
    from pyod.models.knn import KNN

    from oodrl.api.evaluation import as_detector
    from oodrl.detectors.library import LibraryDetector

    wrapped = as_detector(KNN(n_neighbors=7))
    assert isinstance(wrapped, LibraryDetector) and wrapped.features == "state"
    assert wrapped.library_params["n_neighbors"] == 7


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        ({"size": "huge"}, "size 'huge' is not an evaluation size. Allowed: full, small, tiny."),
        ({"tiers": ["headline"]}, "tiers ['headline']: not impact tiers. Allowed: benign, mild, "
         "moderate, severe."),
        ({"faults": ["meteor"]}, "faults ['meteor']: not faults of this pipeline. Allowed: "
         "gaussian_state_noise, "),
        ({"env": "mars"}, "env 'mars': no such file or directory. Allowed: a pipeline "),
        ({"detector": dict}, "detector dict is a class; pass an instance of it"),
        ({"detector": object()}, "detector 'object' is no detector object. Allowed: an instance "
         "of an oodrl detector class"),
        ({"faults": ["action_conditioned_dynamics"]}, "no fault of "),
    ],
)  # fmt: skip
def test_wrong_arguments_are_one_line_before_anything_runs(monkeypatch, arguments, message):
    from oodrl.detectors.mahalanobis import MahalanobisDistance

    monkeypatch.delenv("OODRL_EVALUATE_SIZE", raising=False)
    arguments = {"detector": MahalanobisDistance(), "env": "cartpole", **arguments}
    with pytest.raises(ConfigError) as raised:
        oodrl.evaluate(**arguments)
    assert str(raised.value).startswith(message)
    assert "\n" not in str(raised.value)


def test_sizes_keep_the_protocol_and_take_fewer_streams(repo_root):
    from oodrl.api.evaluation import sized_params
    from oodrl.api.project import pipeline_at
    from oodrl.metrics.operating import min_calibration_streams_conditional

    pipeline = pipeline_at(repo_root / "pipeline" / "cartpole")
    full = sized_params(pipeline, "full", None)
    small = sized_params(pipeline, "small", None)
    tiny = sized_params(pipeline, "tiny", 7)
    assert full.tiers.n_streams == 100 and full.tiers.n_calibration == 200
    # small: the pipeline's calibration streams (its threshold), half its faulty streams
    assert small.tiers.model_dump(exclude={"n_streams", "n_audit"}) == full.tiers.model_dump(
        exclude={"n_streams", "n_audit"}
    )
    assert (small.tiers.n_streams, small.tiers.n_audit) == (50, 100)
    assert small.model_dump(exclude={"tiers"}) == full.model_dump(exclude={"tiers"})
    rule = full.tiers
    assert tiny.tiers.n_calibration == min_calibration_streams_conditional(rule.alpha, rule.delta)
    assert (tiny.tiers.n_streams, tiny.seed, tiny.metrics.n_boot) == (10, 7, 100)


@pytest.mark.slow
def test_a_detectors_params_paths_are_the_pipelines_as_in_its_stages(monkeypatch, tmp_path):
    """The policy view reads `policy: models/policy.pt` relative to the pipeline, as its fit
    stage does; the caller's working directory is left as it was."""
    from oodrl.api.evaluation import sized_params
    from oodrl.api.project import pipeline_at, resolve_directory

    monkeypatch.chdir(tmp_path)
    params = sized_params(pipeline_at(resolve_directory("cartpole", "env")), "full", None)
    frame = oodrl.evaluate(params.detector("q_margin"), env="cartpole", faults=["stuck_actuator"],
                           size="tiny", name="q_margin")  # fmt: skip
    assert set(frame.detector) == {"q_margin"} and set(frame.fault.dropna()) == {"stuck_actuator"}
    assert frame.attrs["size"] == "tiny"
    assert os.getcwd() == str(tmp_path)
