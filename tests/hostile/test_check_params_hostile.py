"""`oodrl check-params` against hostile params files (issue 37, SPEC §8, §17 and §22).

Every params file here extends the repository's params.yaml and changes one thing. Each is
refused by the real command in one stderr line that names the params key, exit code 2, no
traceback: a class without the outlier API, a library argument the library checks only in fit
(PyOD's kNN hands n_neighbors to scikit-learn there), HBOS's `alpha` (oodrl's key), an empty
`tiers.grid`, LOF without novelty, files that are not a params mapping, misspelt keys, ranges
of every section. Before, several of these passed and failed stages later, or crashed.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from oodrl.cli import app

ROOT = Path(__file__).resolve().parents[2]


def library(block: dict) -> dict:
    """Params that run one detector, `x`, with this block."""
    return {"benchmark": {"detectors": ["x"]}, "detectors": {"x": block}}


KNN, HBOS, IFOREST = "pyod.models.knn:KNN", "pyod.models.hbos:HBOS", "pyod.models.iforest:IForest"

#: id -> (what the file changes, the key its error names, a fragment of what is allowed or wrong)
REFUSED = {
    # Finding 1: a class without the outlier API crashed with a traceback, exit 1.
    "linear_regression": (
        library({"class": "sklearn.linear_model:LinearRegression"}),
        "detectors.x: ",
        "has no outlier API",
    ),
    "numpy_function": (library({"class": "numpy:mean"}), "detectors.x: ", "is not a class"),
    "injector_as_detector": (
        library({"class": "oodrl.injectors.posthoc:GaussianStateNoise"}),
        "detectors.x: ",
        "has no outlier API",
    ),
    "function_as_injector": (
        {"anomaly": {"injectors": {"gaussian_state_noise": {"class": "numpy:mean"}}}},
        "anomaly.injectors.gaussian_state_noise: ",
        "is not an injector class",
    ),
    "classifier_fit_needs_labels": (
        library({"class": "sklearn.svm:SVC"}),
        "detectors.x: ",
        "fit failed",
    ),
    # Finding 2: library arguments checked only in fit passed, and failed in the fit stage.
    "knn_negative_neighbours": (
        library({"class": KNN, "n_neighbors": -3}),
        "detectors.x.n_neighbors: ",
        "must be an int in the range [1, inf)",
    ),
    "knn_more_neighbours_than_fit_rows": (
        library({"class": KNN, "n_neighbors": 100_000}),
        "detectors.x.n_neighbors: ",
        "n_samples_fit = 12000",
    ),
    "knn_unknown_method": (library({"class": KNN, "method": "mean!"}), "detectors.x.method: ", ""),
    "hbos_bins_unnamed_by_pyod": (
        library({"class": HBOS, "n_bins": -1}),
        "detectors.x.n_bins: ",
        "Not in the range",
    ),
    "iforest_more_features_than_the_state": (
        library({"class": IFOREST, "max_features": 50}),
        "detectors.x.max_features: ",
        "max_features must be <= n_features",
    ),
    "sklearn_value_constraint": (
        library({"class": "sklearn.ensemble:IsolationForest", "n_estimators": -1}),
        "detectors.x.n_estimators: ",
        "must be an int in the range [1, inf)",
    ),
    "unknown_library_argument": (
        library({"class": IFOREST, "n_trees": 10}),
        "detectors.x.n_trees: ",
        "unexpected keyword argument 'n_trees'",
    ),
    "hbos_alpha_is_oodrls": (
        library({"class": HBOS, "alpha": 0.2}),
        "detectors.x.alpha: ",
        "Allowed: remove it, or set threshold_rule: episode_max",
    ),
    "episode_max_without_the_streams": (
        {"detectors": {"kde_density": {"threshold_rule": "episode_max"}}},
        "detectors.kde_density.alpha: ",
        "needs at least 19 held-out streams",
    ),
    # Finding 3: LOF without novelty was told it had no fit/score_samples.
    "sklearn_lof_without_novelty": (
        library({"class": "sklearn.neighbors:LocalOutlierFactor"}),
        "detectors.x.novelty: ",
        "Allowed: novelty: true",
    ),
    "pyod_lof_novelty_false": (
        library({"class": "pyod.models.lof:LOF", "novelty": False}),
        "detectors.x.novelty: ",
        "Allowed: novelty: true",
    ),
    # The tiers: an empty grid passed, and the impact stage blamed a --grid flag.
    "tiers_grid_empty": ({"tiers": {"grid": []}}, "tiers.grid: ", "at least one severity"),
    "tiers_grid_unsorted": ({"tiers": {"grid": [0.5, 0.2]}}, "tiers.grid: ", "increasing"),
    "tiers_grid_zero": ({"tiers": {"grid": [0.0, 0.5]}}, "tiers.grid: ", "(0, 1]"),
    "tiers_one_episode": ({"tiers": {"episodes": 1}}, "tiers.episodes: ", "greater than"),
    "tiers_alpha_one": ({"tiers": {"alpha": 1.0}}, "tiers.alpha: ", "less than 1"),
    "tiers_negative_k": ({"tiers": {"k": -1}}, "tiers.k: ", "greater than or equal to 0"),
    "tiers_too_few_streams": ({"tiers": {"n_calibration": 5}}, "tiers.n_calibration: ", "19"),
    "tiers_calibration_on_evaluation_seeds": (
        {"tiers": {"calibration_seed_offset": 10_005}},
        "tiers.calibration_seed_offset: ",
        "overlap the evaluation streams",
    ),
    "evaluation_on_id_seeds": (
        {"data": {"eval_seed_offset": 5}},
        "data.eval_seed_offset: ",
        "overlap the ID streams",
    ),
    # Every other section's ranges.
    "metrics_ci_above_one": ({"metrics": {"ci": 1.5}}, "metrics.ci: ", "less than 1"),
    "metrics_no_bootstrap": ({"metrics": {"n_boot": 0}}, "metrics.n_boot: ", "greater than"),
    "negative_workers": ({"executor": {"workers": -1}}, "executor.workers: ", "greater than"),
    "train_negative_lr": ({"policy": {"train": {"lr": -1}}}, "policy.train.lr: ", "a float > 0"),
    "train_zero_batch": (
        {"policy": {"train": {"batch_size": 0}}},
        "policy.train.batch_size: ",
        "an int >= 1",
    ),
    "train_another_environment": (
        {"policy": {"train": {"env_id": "CartPole-v1"}}},
        "policy.train.env_id: ",
        "must be env.id (LunarLander-v3)",
    ),
    # Misspelt keys: the closest known one.
    "misspelt_top_level_key": ({"sed": 1}, "sed: ", "Did you mean 'seed'?"),
    "misspelt_section_key": ({"tiers": {"alhpa": 0.1}}, "tiers.alhpa: ", "Did you mean 'alpha'?"),
    "misspelt_train_key": ({"policy": {"train": {"lrr": 0.1}}}, "policy.train.lrr: ", "'lr'"),
}


def check_params(path: Path):
    return CliRunner().invoke(app, ["check-params", str(path)])


def write(tmp_path: Path, changes: dict) -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump({"extends": str(ROOT / "params.yaml"), **changes}))
    return path


def assert_one_line(result, *fragments: str) -> None:
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


@pytest.mark.parametrize("case", REFUSED, ids=list(REFUSED))
def test_refused_in_one_line_naming_the_key(tmp_path, case):
    changes, key, allowed = REFUSED[case]
    assert_one_line(check_params(write(tmp_path, changes)), key, allowed)


#: id -> a file that is no params mapping, and what the line says.
NOT_PARAMS = {
    "not_yaml": (b"seed: [1,\n", "not valid YAML at line"),
    "yaml_list": (b"- seed\n- env\n", "must be a mapping of sections"),
    "empty": (b"", "got an empty file"),
    "binary": (b"\xff\xfe\x00\x01", "not a text file"),
}


@pytest.mark.parametrize("case", NOT_PARAMS, ids=list(NOT_PARAMS))
def test_a_file_that_is_no_params_mapping(tmp_path, case):
    content, message = NOT_PARAMS[case]
    path = tmp_path / "params.yaml"
    path.write_bytes(content)
    assert_one_line(check_params(path), f"error: {path}: ", message)


def test_a_base_that_is_no_mapping_is_refused_not_dropped(tmp_path):
    """The merge used to drop a base that was a list, silently."""
    (tmp_path / "base.yaml").write_text("- 1\n")
    path = tmp_path / "params.yaml"
    path.write_text("extends: base.yaml\nseed: 1\n")
    assert_one_line(check_params(path), "extends", "must be a mapping of sections")


@pytest.mark.parametrize(
    "block",
    [
        {"class": HBOS, "alpha": 0.2, "threshold_rule": "episode_max"},  # oodrl reads alpha
        {"class": KNN, "n_neighbors": 100},  # above the first probe's 32 rows, not the fit set's
    ],
    ids=["hbos_alpha_read_by_episode_max", "knn_neighbours_within_the_fit_set"],
)
def test_what_fits_the_real_fit_set_passes(tmp_path, block):
    result = check_params(write(tmp_path, library(block)))
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize(
    "path",
    ["params.yaml", "ci/params.yaml", "pipeline/params.yaml", "pipeline/cartpole/params.yaml"],
)
def test_committed_params_pass(path):
    result = check_params(ROOT / path)
    assert result.exit_code == 0, result.output
    assert result.stderr == ""


@pytest.mark.parametrize("case", ["linear_regression", "numpy_function", "knn_negative_neighbours"])
def test_a_fresh_process_prints_no_traceback(tmp_path, case):
    """The console command itself, as a user runs it (the crash was a 50-line traceback)."""
    changes, key, _ = REFUSED[case]
    oodrl = Path(sys.executable).parent / "oodrl"
    done = subprocess.run(
        [str(oodrl), "check-params", str(write(tmp_path, changes))], capture_output=True, text=True
    )
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.splitlines()) == 1 and "Traceback" not in done.stderr
    assert key in done.stderr
