"""One-line refusals of bad input, in process and on small real files: broken results files,
missing impact tiers, unusual library models, stage verbs' bad arguments, `oodrl new`'s
environment checks and a read-only HTTP remote that serves nothing."""

from __future__ import annotations

import base64
import http.server
import os
import socket
import ssl
import subprocess
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_cli import _score_params
from typer.testing import CliRunner

import oodrl
from oodrl.api.evaluation import _given_arguments, as_detector, committed_impacts
from oodrl.api.project import Pipeline
from oodrl.cli import app
from oodrl.errors import ConfigError, StoreError
from oodrl.suite import new, remote_check
from oodrl.suite.run import Remote, _spawn

runner = CliRunner()


# -- load_results: files that are not results ------------------------------------------------
@pytest.mark.parametrize(
    ("name", "document", "message"),
    [
        ("results.yaml", [{"detector": "kde"}], "not a results file (a mapping of records)."),
        ("results.yaml", {"protocol_version": 4}, "not a results file (no 'records' list)."),
        ("sweep_results.yaml", {"records": []}, "not a sweep results file (no 'sweep' mapping)."),
        ("tier_results.yaml", {"protocol_version": "4", "records": []},
         "protocol_version must be an integer; got '4'."),
    ],
)  # fmt: skip
def test_a_yaml_file_that_holds_no_results_is_refused_in_one_line(
    tmp_path, name, document, message
):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(document))
    with pytest.raises(StoreError) as raised:
        oodrl.load_results(path)
    assert str(raised.value) == f"{path}: {message}"


def test_a_pipeline_never_built_names_how_to_restore_or_build_its_results(tmp_path):
    (tmp_path / "params.yaml").write_text("env:\n  id: CartPole-v1\n")
    (tmp_path / "dvc.yaml").write_text("stages: {}\n")
    with pytest.raises(StoreError) as raised:
        oodrl.load_results(tmp_path, kind="tiers")
    message = str(raised.value)
    assert message.startswith(f"{tmp_path / 'reports' / 'tier_results.json'}: no tier results")
    assert "`git checkout` restores" in message and "`dvc repro tier_metrics`" in message
    assert "\n" not in message


def test_a_suite_without_its_leaderboard_is_a_store_error_naming_it(tmp_path):
    suite = tmp_path / "pipeline" / "suite"
    suite.mkdir(parents=True)
    (suite / "dvc.yaml").write_text("stages: {}\n")
    with pytest.raises(StoreError, match=r"leaderboard\.json: no leaderboard here; the pipeline"):
        oodrl.load_results(suite)


def test_a_leaderboard_that_is_not_json_is_refused_with_the_parsers_reason(tmp_path):
    path = tmp_path / "leaderboard.json"
    path.write_text("cells: []\n")  # YAML, not JSON
    with pytest.raises(StoreError) as raised:
        oodrl.load_results(path)
    assert str(raised.value) == (
        f"{path}: not a JSON leaderboard (Expecting value: line 1 column 1 (char 0))."
    )


# -- evaluate: the committed impact records and the library model's arguments ---------------
def _impact_document(fault: str, severity: float) -> dict:
    """An impact stage's document, as `oodrl impact` writes it (its keys the reader keeps)."""
    curve = [{"severity": severity, "monotone": 0.5}]
    fault_record = {"tiers": {"mild": {"severity": severity}}, "curve": curve, "probes": []}
    return {"clean_return": 500.0, "random_return": 20.0, "faults": {fault: fault_record}}


def test_a_fault_missing_from_tier_results_takes_its_record_from_the_impact_stage(tmp_path):
    # A tier_results.yaml of no `impact` section (an older one): only data/impact/ holds tiers.
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "tier_results.yaml").write_text("records: []\n")
    (tmp_path / "data" / "impact").mkdir(parents=True)
    (tmp_path / "data" / "impact" / "stuck_actuator.yaml").write_text(
        yaml.safe_dump(_impact_document("stuck_actuator", 0.3))
    )
    pipeline = Pipeline(tmp_path, "CartPole-v1", "0")
    found = committed_impacts(pipeline, ["stuck_actuator", "gaussian_state_noise"])
    # tier_results.yaml's `impact` record of the fault: the returns, the tiers and the curve.
    written = _impact_document("stuck_actuator", 0.3)
    assert found == {
        "stuck_actuator": {
            "clean_return": 500.0,
            "random_return": 20.0,
            "tiers": {"mild": {"severity": 0.3}},
            "curve": written["faults"]["stuck_actuator"]["curve"],
        }
    }


def test_an_impact_section_naming_an_anchor_outside_it_is_read_from_the_whole_file(tmp_path):
    # The section alone cannot resolve `*mild`: the whole file must be parsed instead.
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "tier_results.yaml").write_text(
        "defaults:\n  tiers: &mild\n    mild: {severity: 0.5}\n"
        "impact:\n  stuck_actuator:\n    tiers: *mild\n"
    )
    found = committed_impacts(Pipeline(tmp_path, "CartPole-v1", "0"), ["stuck_actuator"])
    assert found == {"stuck_actuator": {"tiers": {"mild": {"severity": 0.5}}}}


def test_a_pipeline_without_committed_tiers_is_a_store_error_naming_both_sources(tmp_path):
    with pytest.raises(StoreError) as raised:
        committed_impacts(Pipeline(tmp_path, "CartPole-v1", "0"), ["stuck_actuator"])
    message = str(raised.value)
    assert message.startswith(f"{tmp_path}: no committed impact tiers (reports/tier_results.json")
    assert "`dvc repro tier_metrics`" in message and "\n" not in message


def test_an_array_argument_of_a_library_model_is_kept_though_it_has_no_truth_value():
    from pyod.models.gmm import GMM

    weights = np.array([0.25, 0.75])
    wrapped = as_detector(GMM(n_components=2, weights_init=weights))
    assert wrapped.library_params["n_components"] == 2
    assert wrapped.library_params["weights_init"] is weights


def test_a_model_with_required_arguments_is_compared_with_its_signatures_defaults():
    class Needs:  # no default instance to compare with
        def __init__(self, data, k=5):
            self.data, self.k = data, k

        def get_params(self, deep=False):
            return {"data": self.data, "k": self.k}

    assert _given_arguments(Needs([1], k=5)) == {"data": [1]}
    assert _given_arguments(Needs([1], k=7)) == {"data": [1], "k": 7}


def test_a_river_models_arguments_are_kept_when_it_is_wrapped():
    from river.anomaly import HalfSpaceTrees

    wrapped = as_detector(HalfSpaceTrees(n_trees=5, height=3))
    assert wrapped.library_params == {"n_trees": 5, "height": 3}


# -- stage verbs: bad arguments, one line, no traceback --------------------------------------
def _one_line_exit(arguments: list[str], code: int) -> str:
    result = runner.invoke(app, arguments)
    assert result.exit_code == code, result.output
    assert "Traceback" not in result.output and result.output.count("\n") == 1, result.output
    return result.output


def test_impact_refuses_a_grid_that_is_not_numbers(tmp_path, repo_root):
    output = _one_line_exit(
        ["impact", "--policy", "p.pt", "--out", str(tmp_path / "impact.yaml"),
         "--grid", "0.5,big", "--params", str(repo_root / "params.yaml")],
        2,
    )  # fmt: skip
    assert output == "error: --grid must be comma-separated numbers; got '0.5,big'.\n"
    assert not (tmp_path / "impact.yaml").exists()


def test_import_dataset_refuses_a_split_that_is_not_a_set(tmp_path):
    output = _one_line_exit(
        ["import-dataset", "train", "--dataset", "d", "--out", str(tmp_path / "id.zarr")], 2
    )
    assert output == "error: import-dataset: 'train' is not a set; allowed: id, eval.\n"


def test_collect_heldout_refuses_a_set_that_is_not_held_out(tmp_path):
    output = _one_line_exit(
        ["collect-heldout", "eval", "--policy", "p.pt", "--out", str(tmp_path / "e.zarr")], 2
    )
    assert output == "error: 'eval' is not a held-out set. Allowed: calibration, audit, twins.\n"


def test_score_refuses_an_injector_its_params_do_not_list(tmp_path):
    output = _one_line_exit(
        ["score", "mahalanobis_distance", "--model", "m.pkl", "--scores", "scores",
         "--injector", "meteor", "--ood", "ood", "--params", str(_score_params(tmp_path))],
        2,
    )  # fmt: skip
    assert output.startswith("error: 'meteor' is not listed in benchmark.injectors.")
    assert output.endswith(" Listed: stuck_actuator.\n")


# -- oodrl new: the environment --------------------------------------------------------------
@pytest.mark.parametrize(
    ("environment", "message"),
    [
        ([], "--env: name the agent's environment (a Gymnasium id)."),
        (["--env", "CliffWalking-v1", "--flatten"],
         "--env: FlattenObservation(CliffWalking-v1) registers no episode length "
         "(max_episode_steps); give --T."),
    ],
)  # fmt: skip
def test_new_refuses_an_agent_without_an_environment_or_its_length(tmp_path, environment, message):
    output = _one_line_exit(
        ["new", "x", *environment, "--policy", "agent.zip", "--root", str(tmp_path)], 2
    )
    assert output == f"error: {message}\n"
    assert not (tmp_path / "pipeline").exists() or not any((tmp_path / "pipeline").iterdir())


def test_a_recording_without_an_environment_needs_env():
    with pytest.raises(ConfigError, match=r"^--env: test/x-v0 records no environment \(env_spec\)"):
        new._recorded_env("test/x-v0", None, None)


def test_params_of_an_environment_without_a_time_limit_say_t_was_given():
    text = new.params_text(
        "x", "FlattenObservation(CliffWalking-v1)", 40, {"env_id": "x"}, {}, {}, "note"
    )
    (line,) = [line for line in text.splitlines() if line.startswith("  T: 40")]
    assert line.endswith("# steps per stream (--T; episodes have no time limit)")


def test_new_pipeline_params_breaking_a_data_contract_are_a_config_error(tmp_path, repo_root):
    # Made by hand: `oodrl new` refuses a Discrete observation before it writes any params.
    (tmp_path / "params.yaml").write_text((repo_root / "params.yaml").read_text())
    staging = tmp_path / "pipeline" / ".x.new-1"
    staging.mkdir(parents=True)
    (staging / "params.yaml").write_text(
        "extends: ../../params.yaml\nenv:\n  id: CliffWalking-v1\n  T: 40\n"
        "policy:\n  train:\n    algorithm: imported\n    env_id: CliffWalking-v1\n"
        "    source: a test\n"
    )
    with pytest.raises(ConfigError, match=r"^CliffWalking-v1 observes Discrete \(Discrete\(48\)\)"):
        new._check(staging)


# -- a read-only HTTP remote ------------------------------------------------------------------
OIDS = ["ab" + "0" * 30, "cd" + "1" * 30]


@pytest.fixture
def locked_checkout(tmp_path) -> Path:
    """A git checkout holding one DVC project, `proj`, whose committed lock names OIDS."""
    project = tmp_path / "proj"
    (project / ".dvc").mkdir(parents=True)
    outs = [{"path": f"out{i}", "md5": oid} for i, oid in enumerate(OIDS)]
    (project / "dvc.lock").write_text(yaml.safe_dump({"stages": {"s": {"outs": outs}}}))
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    subprocess.run(["git", "add", "proj/dvc.lock"], cwd=tmp_path, check=True)
    return tmp_path


@pytest.fixture
def answering():
    """An HTTP server on loopback answering every request with one status: (start, heard),
    start(status) its URL, heard the (method, path, headers) of each request."""
    servers, heard = [], []

    def start(status: int) -> str:
        class Answer(http.server.BaseHTTPRequestHandler):
            def log_message(self, *args) -> None:
                pass

            def do_HEAD(self) -> None:  # noqa: N802 - http.server's name
                heard.append((self.command, self.path, dict(self.headers)))
                self.send_response(status)
                self.send_header("Content-Length", "0")
                self.end_headers()

        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Answer)
        # A short poll: shutdown() waits for it at teardown.
        threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True).start()
        servers.append(server)
        return f"http://127.0.0.1:{server.server_address[1]}/dvc"

    yield start, heard
    for server in servers:
        server.shutdown()
        server.server_close()


@pytest.mark.parametrize(
    ("auth", "header", "value"),
    [
        ({"auth": "basic", "user": "ann", "password": "pw"}, "Authorization",
         "Basic " + base64.b64encode(b"ann:pw").decode()),
        ({"auth": "custom", "custom_auth_header": "X-Token", "password": "pw"}, "X-Token", "pw"),
    ],
)  # fmt: skip
def test_a_remote_refusing_the_credentials_it_was_sent_is_named_in_one_line(
    locked_checkout, answering, auth, header, value
):
    start, heard = answering
    url = start(401)
    why = remote_check.unserved(locked_checkout, Remote("pub", {"url": url, **auth}), ["proj"], 5)
    assert why == (
        f"DVC remote 'pub' ({url}) refuses the objects the pipelines to build need (HTTP 401 to "
        "each of the 2 objects asked); check its URL and the credentials it wants "
        "(docs/how-to/remotes.md)"
    )
    # DVC's layout, asked with HEAD, each with the header DVC would send.
    assert sorted(path for _, path, _ in heard) == [
        f"/dvc/files/md5/{oid[:2]}/{oid[2:]}" for oid in OIDS
    ]
    assert {method for method, _, _ in heard} == {"HEAD"}
    assert all(headers.get(header) == value for _, _, headers in heard)


def test_a_remote_that_does_not_answer_has_none_and_says_why(locked_checkout):
    with socket.socket() as closed:  # a port just freed: nothing listens there
        closed.bind(("127.0.0.1", 0))
        url = f"http://127.0.0.1:{closed.getsockname()[1]}/dvc"
    why = remote_check.unserved(locked_checkout, Remote("pub", {"url": url}), ["proj"], 5)
    assert why.startswith(
        f"DVC remote 'pub' ({url}) has none of the 2 objects the committed locks of proj name ("
    )
    assert "Connection refused" in why and "HTTP" not in why.split(" name (")[1]


def test_a_project_without_committed_locks_asks_the_remote_nothing(locked_checkout, answering):
    start, heard = answering
    subprocess.run(
        ["git", "rm", "-q", "--cached", "proj/dvc.lock"], cwd=locked_checkout, check=True
    )
    assert (
        remote_check.unserved(locked_checkout, Remote("pub", {"url": start(403)}), ["proj"], 5)
        is None
    )
    assert heard == []


def test_ssl_verify_false_turns_certificate_checks_off():
    assert remote_check.ssl_context({}).verify_mode == ssl.CERT_REQUIRED
    context = remote_check.ssl_context({"ssl_verify": "False"})
    assert (context.check_hostname, context.verify_mode) == (False, ssl.CERT_NONE)


def test_a_check_that_cannot_run_names_no_bad_object(tmp_path):
    """The real check, in a folder that is no DVC project: it fails, and the caller's own
    error (DVC's) stands instead of a guess at an object."""
    environment = {**os.environ, "DVC_NO_ANALYTICS": "1",
                   "DVC_SITE_CACHE_DIR": str(tmp_path / "site")}  # fmt: skip
    remote = Remote("pub", {"url": "http://127.0.0.1:9/dvc"})
    spawned = []

    def spawn(command, cwd, env):
        spawned.append(_spawn(command, cwd, env))
        return spawned[-1]

    assert remote_check.bad_object(tmp_path, environment, remote, spawn) is None
    assert spawned[0].returncode != 0 and "NotDvcRepoError" in spawned[0].stderr


@pytest.mark.parametrize("stdout", ["", "Warning: a plugin's notice\n"])
def test_a_check_whose_output_is_not_json_leaves_the_callers_error_standing(tmp_path, stdout):
    # Stands in for a check that exits 0 without its JSON line: bad_object must not guess.
    def spawn(command, cwd, env):
        return subprocess.CompletedProcess(command, 0, stdout, "")

    remote = Remote("pub", {"url": "http://127.0.0.1:9/dvc"})
    assert remote_check.bad_object(tmp_path, {}, remote, spawn) is None
