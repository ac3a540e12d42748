"""Detectors from PyOD, scikit-learn and river named by `class: "module:Class"` (SPEC §17):
oodrl's detector contract over each wrapped library, a plugin class with only fit and
decision_function, a wrong constructor argument through `oodrl check-params`, streaming equal
to batch scoring bit for bit, and which detectors are certified machine-independent."""

from __future__ import annotations

import inspect
import os
import pickle
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from oodrl.cli import app
from oodrl.detectors import DETECTORS
from oodrl.detectors.library import LibraryDetector
from oodrl.detectors.time_index import TimeIndex
from oodrl.testing import (
    check_detector,
    check_global_random_state,
    check_not_fitted,
    check_parameters,
    check_pickle_roundtrip,
    check_reproducible,
    check_score_is_pure,
    check_scores_use_the_data,
    check_state_dim,
    check_streaming,
    check_threshold,
    linear_system_trajectories,
)

#: Short streams and small models, so that every library runs the whole contract in seconds.
DISCRETE = linear_system_trajectories(10, T=40, episode_length=30, seed=0)
CONTINUOUS = linear_system_trajectories(10, T=40, episode_length=30, action_dim=2, seed=0)


def splits(data):
    return data[:6], data[6:8], data[8:]


#: id -> (class path, params block without `class`, data). Between them the cases cover every
#: feature view and both action kinds.
LIBRARY_CASES = {
    "pyod_knn": ("pyod.models.knn:KNN", {"features": "state_action"}, DISCRETE),
    "pyod_iforest": (
        "pyod.models.iforest:IForest",
        {"features": "transition", "n_estimators": 20},
        CONTINUOUS,
    ),
    "pyod_lof": ("pyod.models.lof:LOF", {"n_neighbors": 10}, DISCRETE),
    "pyod_ecod": ("pyod.models.ecod:ECOD", {"features": "window", "window": 3}, DISCRETE),
    "pyod_hbos": ("pyod.models.hbos:HBOS", {"features": "state_action"}, CONTINUOUS),
    "sklearn_isolation_forest": (
        "sklearn.ensemble:IsolationForest",
        {"n_estimators": 20},
        DISCRETE,
    ),
    "sklearn_lof_novelty": (
        "sklearn.neighbors:LocalOutlierFactor",
        {"novelty": True, "n_neighbors": 10, "features": "window", "window": 2},
        DISCRETE,
    ),
    "river_half_space_trees": (
        "river.anomaly:HalfSpaceTrees",
        {"n_trees": 5, "height": 4, "window_size": 50},
        CONTINUOUS,
    ),
}


def factory(path: str, params: dict):
    cls = DETECTORS.get(path)
    return lambda: cls.from_params(params)


def check_contract_but_the_torch_free_import(make, fit, calibration, evaluation) -> None:
    """`check_detector`'s checks, in its order, all but `check_torch_free_import`: a process
    start that imports oodrl and the library, ~6 s of CPU a detector here, made once for every
    detector of this file by test_building_library_detectors_does_not_import_torch."""
    fresh = make()
    check_parameters(fresh)
    check_not_fitted(fresh, evaluation[0])
    fitted = make()
    assert fitted.fit(fit) is fitted, "fit must return the detector itself"
    check_scores_use_the_data(make, fit, evaluation)
    check_reproducible(make, fit, evaluation)
    check_global_random_state(make, fit, evaluation)
    check_score_is_pure(fitted, evaluation)
    check_state_dim(fitted, evaluation[0])
    check_threshold(fitted, calibration)
    check_streaming(fitted, evaluation)
    check_pickle_roundtrip(fitted, evaluation)


def test_the_contract_here_is_check_detectors_but_the_torch_free_import():
    """If check_detector gains a check, this file's contract runs it too."""
    called = set(re.findall(r"\b(check_\w+)\(", inspect.getsource(check_detector)))
    here = set(re.findall(r"\b(check_\w+)\(",
                          inspect.getsource(check_contract_but_the_torch_free_import)))  # fmt: skip
    assert called - {"check_detector"} == here - {"check_contract_but_the_torch_free_import"} | {
        "check_torch_free_import"
    }


@pytest.mark.parametrize("case", LIBRARY_CASES, ids=list(LIBRARY_CASES))
def test_library_detector_passes_the_contract(case):
    path, params, data = LIBRARY_CASES[case]
    make = factory(path, params)
    detector = make()
    assert isinstance(detector, LibraryDetector)
    assert not detector.machine_independent
    check_contract_but_the_torch_free_import(make, *splits(data))


#: oodrl.testing.check_torch_free_import for many detectors in one fresh interpreter: each
#: unpickled, built and validated in turn; the first that imports torch is named. A detector
#: that passes imports no torch, so those after it are judged as in a process of their own.
TORCH_FREE = """
import pickle, sys
for name, pickled in pickle.load(sys.stdin.buffer):
    detector = pickle.loads(pickled)
    type(detector).from_params(detector.get_params()).validate_params()
    if "torch" in sys.modules:
        sys.exit(f"building {name} imported torch")
"""


def test_building_library_detectors_does_not_import_torch(project):
    """check_detector's torch-free import check of every library case and of the plugin, at
    one process start instead of nine (check_torch_free_import itself: test_contract.py)."""
    made = [factory(path, params)() for path, params, _ in LIBRARY_CASES.values()]
    made.append(factory("my_outliers:CentroidDistance", {"power": 1.5, "features": "transition"})())
    pickled = pickle.dumps([(d.name, pickle.dumps(d)) for d in made])
    done = subprocess.run([sys.executable, "-c", TORCH_FREE], input=pickled, capture_output=True)
    assert done.returncode == 0, done.stderr.decode()
    # The check can fail: a build that imports torch is named.
    failing = TORCH_FREE.replace("validate_params()", "validate_params(); import torch")
    done = subprocess.run([sys.executable, "-c", failing], input=pickled, capture_output=True)
    assert done.stderr.decode().strip() == f"building {made[0].name} imported torch"


#: A user's own outlier class beside params.yaml: fit and decision_function, nothing else.
PLUGIN_SOURCE = textwrap.dedent(
    '''
    import numpy as np


    class CentroidDistance:
        """Sum of |x - fit mean|^power: the PyOD API and no more (no oodrl base class)."""

        def __init__(self, power=2.0):
            self.power = power

        def fit(self, X, y=None):
            self.center_ = np.asarray(X).mean(axis=0)
            return self

        def decision_function(self, X):
            return (np.abs(np.asarray(X) - self.center_) ** self.power).sum(axis=1)
    '''
)


@pytest.fixture
def project(tmp_path, monkeypatch):
    """A project directory holding the plugin module, as the working directory."""
    (tmp_path / "my_outliers.py").write_text(PLUGIN_SOURCE)
    monkeypatch.chdir(tmp_path)
    yield tmp_path
    sys.modules.pop("my_outliers", None)


def test_plugin_with_only_fit_and_decision_function(project):
    make = factory("my_outliers:CentroidDistance", {"power": 1.5, "features": "transition"})
    detector = make()
    assert detector.name == "my_outliers:CentroidDistance" and not detector.machine_independent
    check_contract_but_the_torch_free_import(make, *splits(DISCRETE))  # and one process below
    fitted = make().fit(DISCRETE[:6])
    assert fitted.api_ == "decision_function" and fitted.batched_
    # Larger = more anomalous, as the plugin's decision_function says: a far state scores more.
    near = DISCRETE[8]
    far = near.replace(states=near.states + 10, next_states=near.next_states + 10)
    assert fitted.score(far).scores.min() > fitted.score(near).scores.max()


def write_params(project, default_params, blocks: dict) -> str:
    default_params["benchmark"]["detectors"] += list(blocks)
    default_params["detectors"].update(blocks)
    (project / "params.yaml").write_text(yaml.safe_dump(default_params))
    return "params.yaml"


def test_wrong_constructor_argument_through_the_oodrl_command(project, default_params):
    """The real console command in a fresh process: exit 2, one line, no traceback."""
    block = {"class": "pyod.models.iforest:IForest", "n_trees": 10}
    path = write_params(project, default_params, {"library_one": block})
    done = subprocess.run(
        [sys.executable, "-m", "oodrl", "check-params", path], capture_output=True, text=True
    )
    assert done.returncode == 2, done.stdout + done.stderr
    message = done.stderr.strip()
    assert "\n" not in message and "Traceback" not in message
    # The argument is named in the key: `detectors.<name>.<argument>`.
    assert message.startswith("error: params.yaml: detectors.library_one.n_trees: ")
    assert "IForest" in message and "'n_trees'" in message


@pytest.mark.parametrize(
    ("block", "argument"),
    [
        ({"class": "sklearn.ensemble:IsolationForest", "n_estimators": -1}, "n_estimators"),
        ({"class": "river.anomaly:HalfSpaceTrees", "n_tree": 5}, "n_tree"),
        ({"class": "my_outliers:CentroidDistance", "powr": 2}, "powr"),
    ],
    ids=["sklearn_invalid_value", "river_unknown_argument", "plugin_unknown_argument"],
)
def test_wrong_constructor_argument_is_one_line_naming_detector_and_argument(
    project, default_params, block, argument
):
    path = write_params(project, default_params, {"library_one": block})
    result = CliRunner().invoke(app, ["check-params", path])
    assert result.exit_code == 2, result.output
    assert result.output.count("\n") == 1
    assert "detectors.library_one" in result.output
    assert block["class"].split(":")[1] in result.output and f"'{argument}'" in result.output


def test_check_params_and_list_accept_library_detectors(project, default_params):
    blocks = {
        "pyod_iforest": {"class": "pyod.models.iforest:IForest", "n_estimators": 10},
        "centroid": {"class": "my_outliers:CentroidDistance"},
    }
    path = write_params(project, default_params, blocks)
    checked = CliRunner().invoke(app, ["check-params", path])
    assert checked.exit_code == 0, checked.output
    listed = CliRunner().invoke(app, ["list"])
    assert listed.exit_code == 0, listed.output
    section = listed.output.split("library detectors named in params.yaml:\n")[1]
    assert section.splitlines() == [
        "  centroid  my_outliers:CentroidDistance",
        "  pyod_iforest  pyod.models.iforest:IForest",
    ]


def test_seed_reaches_the_library_unless_the_block_sets_it():
    fit, _, evaluation = splits(DISCRETE)
    cls = DETECTORS.get("pyod.models.iforest:IForest")

    def scores(**params):
        return cls(n_estimators=10, **params).fit(fit).score(evaluation[0]).scores

    assert np.array_equal(scores(seed=3), scores(seed=3, random_state=3))
    assert not np.array_equal(scores(seed=3), scores(seed=4))
    assert np.array_equal(scores(seed=3, random_state=7), scores(seed=4, random_state=7))


def test_batch_scoring_follows_the_probe():
    """ECOD ranks each row among the rows of its call, so a row scores differently alone and
    in a batch: oodrl scores it one row at a time, as a stream does. IsolationForest's rows
    score alike either way: batches."""
    fit, _, evaluation = splits(DISCRETE)
    ecod = DETECTORS.get("pyod.models.ecod:ECOD")().fit(fit)
    assert not ecod.batched_
    x = ecod._rows(evaluation[0])
    in_one_call = ecod.model_.decision_function(x)
    assert not np.array_equal(in_one_call, ecod.score(evaluation[0]).scores)
    forest = DETECTORS.get("sklearn.ensemble:IsolationForest")(n_estimators=10).fit(fit)
    assert forest.batched_
    check_streaming(ecod, evaluation)
    check_streaming(forest, evaluation)


FIT_OR_SCORE_HBOS = """
import pickle, sys
from pathlib import Path
from oodrl.detectors import DETECTORS
from oodrl.testing import linear_system_trajectories
data = linear_system_trajectories(4, T=60, action_dim=2, seed=0)
if sys.argv[1] == "fit":
    detector = DETECTORS.get("pyod.models.hbos:HBOS")().fit(data[:3])
    Path(sys.argv[2]).write_bytes(pickle.dumps(detector))
else:
    pickle.loads(Path(sys.argv[2]).read_bytes()).score(data[3])
"""


def test_a_fitted_hbos_pickles_alike_with_and_without_the_numba_cache(tmp_path):
    """A scoring process keeps HBOS's compiled kernel in numba's on-disk cache, so the next
    stage process loads it; fitting compiles afresh, so on a machine whose scoring filled the
    cache a fit writes the same bytes as on one that never scored."""

    def run(cache: Path, *args: str) -> None:
        env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
        command = [sys.executable, "-c", FIT_OR_SCORE_HBOS, *args]
        subprocess.run(command, env=env, capture_output=True, check=True)

    cold, warm = tmp_path / "cold.pkl", tmp_path / "warm.pkl"
    run(tmp_path / "cold", "fit", str(cold))
    run(tmp_path / "warm", "score", str(cold))  # a scoring process compiles into the cache
    assert list((tmp_path / "warm").rglob("*.nbi"))
    run(tmp_path / "warm", "fit", str(warm))
    assert warm.read_bytes() == cold.read_bytes()


def test_window_view_stacks_the_last_states_oldest_first():
    fit, _, evaluation = splits(DISCRETE)
    detector = DETECTORS.get("pyod.models.knn:KNN")(features="window", window=3).fit(fit)
    trajectory = evaluation[0]
    states = detector.standardizer_.transform(trajectory.states.astype(np.float64))
    rows = detector._rows(trajectory)
    assert rows.shape == (trajectory.T, 3 * trajectory.state_dim)
    np.testing.assert_array_equal(rows[5], np.concatenate(states[3:6]))
    np.testing.assert_array_equal(rows[1], np.concatenate([states[0], states[0], states[1]]))
    assert detector.latency == 0
    assert DETECTORS.get("pyod.models.knn:KNN")(features="transition").latency == 1


@pytest.mark.parametrize(
    ("path", "params"),
    [("sklearn.neighbors:LocalOutlierFactor", {}), ("pyod.models.lof:LOF", {"novelty": False})],
    ids=["sklearn_default", "pyod_novelty_false"],
)
def test_lof_without_novelty_is_told_to_set_it(path, params):
    """Without novelty=True scikit-learn's LOF scores only its fit rows (no score_samples;
    PyOD's LOF fails in fit): the message says what to set, not that the API is missing."""
    from oodrl.validation import ParameterError

    with pytest.raises(ParameterError, match="Allowed: novelty: true") as info:
        DETECTORS.get(path).from_params(params)
    assert info.value.param == "novelty"


def test_time_index_scores_the_step_and_streams_it():
    fit, calibration, evaluation = splits(DISCRETE)
    check_parameters(TimeIndex())
    check_not_fitted(TimeIndex(), evaluation[0])
    check_reproducible(TimeIndex, fit, evaluation)
    detector = TimeIndex().fit(fit)
    np.testing.assert_array_equal(detector.score(evaluation[0]).scores, np.arange(40.0))
    check_score_is_pure(detector, evaluation)
    check_state_dim(detector, evaluation[0])
    check_threshold(detector, calibration)
    check_streaming(detector, evaluation)
    check_pickle_roundtrip(detector, evaluation)
    assert TimeIndex.machine_independent


class _PluginSubclass(TimeIndex):
    """A detector subclass defined outside oodrl: not certified unless it says so."""


class _CertifiedPlugin(TimeIndex):
    machine_independent = True


def test_machine_independence_is_declared_per_detector():
    assert all(DETECTORS.get(name).machine_independent for name in DETECTORS.names())
    assert not _PluginSubclass.machine_independent
    assert _CertifiedPlugin.machine_independent
    assert not DETECTORS.get("pyod.models.knn:KNN").machine_independent


def _results_document(uncertified: list[str]) -> dict:
    """A results.yaml as the metrics stage writes it: two detectors on two faults."""
    rng = np.random.default_rng(0)
    records = []
    for fault in ("gaussian_state_noise", "stuck_actuator"):
        for detector, strength in (("cusum", 0.9), ("pyod_iforest", 0.7)):
            episodes = np.clip(strength + 0.05 * rng.standard_normal(6), 0, 1)
            metric = {"mean": float(episodes.mean()), "ci_low": 0.0, "ci_high": 1.0}
            records.append(
                {"kind": "anomaly", "detector": detector, "injector": fault, "mode": "posthoc",
                 "severity": 0.5, "latency": 0, "metrics": {"matched_auroc": metric},
                 "episodes": {"matched_auroc": episodes.tolist()}}
            )  # fmt: skip
    document = {"records": records}
    if uncertified:
        document["uncertified_detectors"] = uncertified
    return document


def test_results_and_leaderboard_mark_uncertified_detectors_per_row(tmp_path):
    from oodrl.io import yamlio
    from oodrl.metrics.results import Results
    from oodrl.report.tables import headline_table
    from oodrl.stages.leaderboard import run_leaderboard

    # Every detector certified (the root pipeline): results.yaml has no section for it.
    assert "uncertified_detectors" not in Results([], {}, {}, {}).results_document()
    assert Results([], {}, {}, {}, ["pyod_iforest"]).results_document()[
        "uncertified_detectors"
    ] == ["pyod_iforest"]
    paths = {}
    for env, uncertified in (("CartPole-v1", ["pyod_iforest"]), ("Pendulum-v1", [])):
        paths[env] = tmp_path / env / "results.yaml"
        paths[env].parent.mkdir()
        paths[env].write_text(yamlio.dump(_results_document(uncertified)))
    rows = headline_table(_results_document(["pyod_iforest"])).splitlines()[2:]
    assert [row.split("|")[1].strip() for row in rows] == ["cusum", "pyod_iforest †"]
    run_leaderboard(paths, tmp_path / "out", n_boot=50, ci=0.95, seed=0)
    markdown = (tmp_path / "out" / "leaderboard.md").read_text()
    assert "| pyod_iforest † |" in markdown and "| cusum |" in markdown
    assert "† not certified machine-independent" in markdown
    board = yamlio.load((tmp_path / "out" / "leaderboard.yaml").read_text())
    assert board["uncertified_detectors"] == ["pyod_iforest"]
    # Without uncertified detectors, no mark, no note, no key: outputs as before.
    for path in paths.values():
        path.write_text(yamlio.dump(_results_document([])))
    run_leaderboard(paths, tmp_path / "plain", n_boot=50, ci=0.95, seed=0)
    assert "†" not in (tmp_path / "plain" / "leaderboard.md").read_text()
    assert "uncertified_detectors" not in (tmp_path / "plain" / "leaderboard.yaml").read_text()


def test_the_peer_families_blocks_validate_fit_and_stream(default_params):
    """Every block of src/oodrl/library_detectors.yaml passes params validation as a params
    file would hold it, and fits, scores and streams (streams equal to batch bit for bit)."""
    from pathlib import Path

    import oodrl
    from oodrl.config import parse_params

    blocks = yaml.safe_load((Path(oodrl.__file__).parent / "library_detectors.yaml").read_text())
    assert set(blocks) == {"pyod_knn", "pyod_iforest", "pyod_lof", "pyod_ecod", "ecod",
                           "pyod_hbos", "time_index"}  # fmt: skip
    default_params["benchmark"]["detectors"] = list(blocks)
    default_params["detectors"] = blocks
    params = parse_params(default_params)
    fit, _, evaluation = splits(DISCRETE)
    for name in blocks:
        detector = params.detector(name).fit(fit)
        # oodrl's own classes are certified; a library's kernels are not.
        assert detector.machine_independent == (name in ("ecod", "time_index"))
        check_streaming(detector, evaluation[:1])


def test_cross_kernel_checks_run_the_certified_detectors(default_params):
    from oodrl.testing.kernels import certified_only, detector_outputs

    default_params["detectors"]["pyod_knn"] = {"class": "pyod.models.knn:KNN"}
    default_params["benchmark"]["detectors"].append("pyod_knn")
    certified, left_out = certified_only(default_params)
    assert left_out == ["pyod_knn"]
    assert certified["benchmark"]["detectors"] == default_params["benchmark"]["detectors"][:-1]
    assert "pyod_knn" in default_params["benchmark"]["detectors"]  # the input is not changed
    hashes = {"models/pyod_knn.pkl": "a", "scores/pyod_knn/eval.zarr": "b",
              "scores/pyod_knn_2/eval.zarr": "c", "data/id.zarr": "d"}  # fmt: skip
    assert detector_outputs(hashes, "pyod_knn") == {
        "models/pyod_knn.pkl": "a",
        "scores/pyod_knn/eval.zarr": "b",
    }
