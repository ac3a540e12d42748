"""Where the suite stands in a change of protocol (SPEC §26): `oodrl.suite.migration` decides
from git-tracked files alone whether a project is current, pending or stale, and every reader
names the protocol version of what it prints.

The project is the real CartPole pipeline, its tracked files as the commit that last relocked it
wrote them (`git archive`: its locks, results, params and the sources they hash), edited the way
a maintainer would edit it."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest
import yaml

from oodrl.errors import ConfigError, StoreError
from oodrl.metrics import stamp
from oodrl.suite import migration
from oodrl.testing.pipeline import run

PROJECT = "pipeline/cartpole"


@pytest.fixture(scope="module")
def archived(repo_root, tmp_path_factory) -> Path:
    """The tracked files of pipeline/cartpole (and what its locks name) at its last relock."""
    commit = subprocess.run(
        ["git", "log", "-1", "--format=%H", "--", f"{PROJECT}/dvc.lock"],
        cwd=repo_root, capture_output=True, text=True, check=True,
    ).stdout.strip()  # fmt: skip
    folder = tmp_path_factory.mktemp("archived")
    paths = ["src", "params.yaml", "pipeline/params.yaml", PROJECT, "pipeline/suite/dvc.yaml"]
    archive = subprocess.run(
        ["git", "archive", commit, "--", *paths], cwd=repo_root, capture_output=True, check=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive, check=True)
    return folder


@pytest.fixture(autouse=True)
def _target_is_the_archived_version(archived, monkeypatch) -> None:
    """The archive's sources and locks are one commit's: its code's protocol is the version its
    results were built at (between two versions, main's code targets the next one)."""
    monkeypatch.setattr(stamp, "PROTOCOL_VERSION", migration.built_version(archived / PROJECT))


@pytest.fixture
def repo(archived, tmp_path) -> Path:
    copy = tmp_path / "repo"
    subprocess.run(["cp", "-a", str(archived), str(copy)], check=True)
    return copy


def state(repo: Path, **options) -> migration.ProjectState:
    (found,) = migration.project_states(repo, [PROJECT], **options)
    return found


def edit(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text, f"{path} lacks {old!r}"
    path.write_text(text.replace(old, new, 1))


def test_a_project_as_its_relock_left_it_is_current(repo):
    found = state(repo)
    assert found == migration.ProjectState(PROJECT, "current", stamp.PROTOCOL_VERSION, ())
    # The copy holds no other project's results: never built, pending, which the check allows.
    states = migration.check(repo)
    assert migration.summary(states) == (
        f"22 projects at target protocol {stamp.PROTOCOL_VERSION}: 1 current, 21 pending "
        f"(never built)"
    )


def test_an_edited_param_makes_it_stale_naming_the_file(repo):
    edit(repo / PROJECT / "params.yaml", "  T: 500 ", "  T: 499 ")
    found = state(repo)
    assert found.status == "stale" and found.built_version == stamp.PROTOCOL_VERSION
    assert found.reasons == ("check_params: params.yaml changed since its lock",)


def test_an_edited_source_makes_it_stale_naming_the_file(repo):
    kde = repo / "src" / "oodrl" / "detectors" / "kde.py"
    kde.write_text(kde.read_text() + "# an edit\n")
    found = state(repo)
    assert found.status == "stale"
    assert found.reasons == (
        "check_params: ../../src/oodrl/detectors/kde.py changed since its lock",
    )


def test_a_lock_edited_by_hand_is_stale_naming_the_stage_and_key(repo):
    lock = repo / PROJECT / "dvc.lock"
    edit(lock, "      data.n_id: 30\n", "      data.n_id: 31\n")
    found = state(repo)
    assert found.status == "stale"
    assert (
        found.reasons[0] == "collect_id: param data.n_id (data/params.yaml) is not the locked value"
    )


def test_with_stamps_the_reasons_name_the_stamps_that_moved_or_say_none_did(repo):
    """docs/how-to/change-protocol.md: `stamps=True` tells a source edit that changes stage code
    from one that does not, by computing the code stamps as check_params would (seconds)."""
    kde = repo / "src" / "oodrl" / "detectors" / "kde.py"
    kde.write_text(kde.read_text() + "# an edit\n")
    found = state(repo, stamps=True)
    assert found.status == "stale"
    assert "detectors/kde_density:fit: code stamp data/code/fit-kde_density.txt changed" in (
        found.reasons
    )
    kde.write_text(kde.read_text().removesuffix("# an edit\n"))
    edit(repo / PROJECT / "params.yaml", "  T: 500 ", "  T: 499 ")  # read by no stamp
    assert state(repo, stamps=True).reasons == (
        "check_params: params.yaml changed since its lock",
        "no code stamp changed with it",
    )


def edit_entry(lock: Path, stage: str, change) -> None:
    """Replace a stage's entry in a lock by `change(entry)`, as text: a YAML round trip would
    change how its params values read."""
    text = lock.read_text()
    start = text.index(f"\n  {stage}:\n") + 1
    end = text.find("\n  ", start + 1)
    while text[end + 3] == " ":  # a deeper line: the entry goes on
        end = text.find("\n  ", end + 1)
    lock.write_text(text[:start] + change(text[start : end + 1]) + text[end + 1 :])


def zero_md5(path: str):
    """An entry's change: the md5 it records for `path`, zeroed."""

    def change(entry: str) -> str:
        md5 = re.search(rf"{re.escape(path)}\n\s+hash: md5\n\s+md5: (\w+)", entry)[1]
        return entry.replace(md5, "0" * 32)

    return change


@pytest.mark.parametrize(
    "stage, change, reason",
    [
        ("collect_id", lambda entry: entry.replace("--out data/id.zarr", "--out data/x.zarr"),
         "collect_id: its command is not the locked one"),
        ("collect_eval", lambda entry: "", "dvc.yaml: stage collect_eval is not in its lock"),
        ("collect_eval", zero_md5("models/policy.pt"),
         "collect_eval: models/policy.pt is not what its stage wrote"),
    ],
    ids=["command", "no entry", "another dep"],
)  # fmt: skip
def test_a_lock_entry_unlike_its_stage_is_stale_naming_it(repo, stage, change, reason):
    edit_entry(repo / PROJECT / "dvc.lock", stage, change)
    found = state(repo)
    assert found.status == "stale" and found.reasons[0] == reason, found.reasons


def test_a_stamp_two_stages_read_at_two_hashes_is_stale(repo):
    lock = repo / PROJECT / "detectors" / "kde_density" / "dvc.lock"
    edit_entry(lock, "score", zero_md5("data/code/score-kde_density.txt"))
    assert any(
        "code stamp data/code/score-kde_density.txt is not the other stages' one" in reason
        for reason in state(repo).reasons
    )


def test_a_results_stamp_that_is_no_version_is_stale_naming_the_file(repo):
    results = repo / PROJECT / "reports" / "results.yaml"
    results.write_text(re.sub(r"(?m)^protocol_version: .*$", "protocol_version: four",
                              results.read_text()))  # fmt: skip
    found = state(repo)
    assert (found.status, found.built_version) == ("stale", migration.NOT_BUILT)
    assert found.reasons == (
        "reports/results.yaml: protocol_version must be an integer; got 'four'",
    )


def test_a_committed_result_that_is_not_its_locks_is_stale(repo):
    results = repo / PROJECT / "reports" / "results.yaml"
    results.write_text(results.read_text() + "# edited\n")
    found = state(repo)
    assert found.reasons == ("metrics: reports/results.yaml is not what its lock records",)


def test_stages_whose_stamps_are_not_check_params_ones_are_stale(repo):
    """A stage relocked alone (`dvc commit` of one stage) against other code: its stamp dep is
    not the one check_params' lock records, though every file is as locked."""
    lock = repo / PROJECT / "detectors" / "kde_density" / "dvc.lock"
    document = yaml.safe_load(lock.read_text())
    dep = document["stages"]["fit"]["deps"][0]
    assert dep["path"] == "data/code/fit-kde_density.txt"
    edit(lock, dep["md5"], "0" * 32)
    found = state(repo)
    assert found.status == "stale"
    assert "the stages' code stamps are not the ones check_params last wrote" in found.reasons[0]


def test_a_lock_entry_of_a_stage_no_longer_in_dvc_yaml_is_ignored_as_dvc_ignores_it(repo):
    """DVC rewrites only the lock entries of the stages it runs: one left by a stage since
    removed (another stamp among them) does not make a built project stale."""
    lock = repo / PROJECT / "detectors" / "kde_density" / "dvc.lock"
    document = yaml.safe_load(lock.read_text())
    gone = json.loads(json.dumps(document["stages"]["fit"]))
    gone["deps"][0] = {**gone["deps"][0], "path": "data/code/fit-gone.txt", "md5": "0" * 32}
    document["stages"]["fit_gone"] = gone
    lock.write_text(yaml.safe_dump(document, sort_keys=False))
    assert state(repo).status == "current"


def test_a_bump_makes_the_project_pending_whatever_its_locks(repo, monkeypatch):
    monkeypatch.setattr(stamp, "PROTOCOL_VERSION", stamp.PROTOCOL_VERSION + 1)
    edit(repo / PROJECT / "params.yaml", "  T: 500 ", "  T: 499 ")  # pending: stale in any way
    version = stamp.PROTOCOL_VERSION - 1
    found = state(repo)
    assert found == migration.ProjectState(
        PROJECT,
        "pending",
        version,
        (f"reports/results.yaml: protocol {version}, the target is {version + 1}",),
    )


def test_results_newer_than_the_code_are_stale(repo, monkeypatch):
    monkeypatch.setattr(stamp, "PROTOCOL_VERSION", stamp.PROTOCOL_VERSION - 1)
    found = state(repo)
    assert found.status == "stale"
    assert "newer than this code's" in found.reasons[0]


def test_the_check_names_each_stale_project_in_a_line(repo):
    edit(repo / PROJECT / "params.yaml", "  T: 500 ", "  T: 499 ")
    with pytest.raises(ConfigError) as error:
        migration.check(repo)  # the other projects are not in the copy: never built, pending
    lines = str(error.value).splitlines()
    assert lines[0].startswith("1 of 22 projects are stale")
    assert lines[1:] == [
        f"{PROJECT}: stale (protocol {stamp.PROTOCOL_VERSION}): check_params: params.yaml "
        "changed since its lock"
    ]


def test_an_unknown_project_is_one_line(repo):
    with pytest.raises(ConfigError) as error:
        migration.project_states(repo, ["pipeline/nope"])
    assert "\n" not in str(error.value)
    assert str(error.value).startswith("pipeline/nope: not a project of the suite")


@pytest.mark.slow
def test_dvc_agrees_on_current_and_stale(repo):
    """`dvc repro --allow-missing --dry` in a git repository of the copy, no DVC output in it:
    up to date exactly when the project is current."""

    def dvc_up_to_date() -> bool:
        done = run(repo / PROJECT, "dvc", "repro", "--allow-missing", "--dry")
        return "Data and pipelines are up to date" in done.stdout

    for command in (["git", "init", "-q"], ["git", "add", "-A"], ["git", "commit", "-qm", "c"]):
        subprocess.run(command, cwd=repo, check=True, capture_output=True)
    assert state(repo).status == "current" and dvc_up_to_date()
    edit(repo / PROJECT / "params.yaml", "  T: 500 ", "  T: 499 ")
    assert state(repo).status == "stale" and not dvc_up_to_date()


# -- every reader names the version -------------------------------------------------------------
def test_load_results_has_a_protocol_column(repo):
    import oodrl

    frame = oodrl.load_results(repo / PROJECT)
    assert set(frame.protocol) == {stamp.PROTOCOL_VERSION}
    assert frame.attrs["protocol_version"] == stamp.PROTOCOL_VERSION


def test_load_results_refuses_the_suite_s_runs_of_two_versions(repo_root, tmp_path):
    """During a change of protocol the suite's pipelines hold two versions: no frame mixes
    them (one line, naming both). The suite's real pipeline files; results files with no
    records, one at the previous version."""
    import oodrl
    from oodrl.suite.environments import suite_runs

    runs = list(suite_runs().values())
    paths = ["pipeline/suite", "pipeline/params.yaml", "params.yaml"]
    paths += [f"{path}/{name}" for path in runs for name in ("params.yaml", "dvc.yaml")]
    archive = subprocess.run(
        ["git", "archive", "HEAD", "--", *paths], cwd=repo_root, capture_output=True, check=True
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(tmp_path)], input=archive, check=True)
    version = stamp.PROTOCOL_VERSION
    for path in runs:
        (tmp_path / path / "reports").mkdir(parents=True, exist_ok=True)
        older = path == runs[0]
        text = f"protocol_version: {version - older}\nrecords: []\n"
        (tmp_path / path / "reports" / "results.yaml").write_text(text)
    with pytest.raises(StoreError) as error:
        oodrl.load_results(tmp_path / "pipeline" / "suite", kind="results")
    message = str(error.value)
    assert "\n" not in message and "cannot be ranked together" in message
    assert f"version {version - 1}: {tmp_path / runs[0] / 'reports' / 'results.yaml'}" in message
    (tmp_path / runs[0] / "reports" / "results.yaml").write_text(
        f"protocol_version: {version}\nrecords: []\n"
    )
    frame = oodrl.load_results(tmp_path / "pipeline" / "suite", kind="results")
    assert frame.empty and frame.attrs["protocol_version"] == version


def test_show_names_the_version(repo):
    from typer.testing import CliRunner

    from oodrl.cli import app

    results = repo / PROJECT / "reports" / "results.yaml"
    done = CliRunner().invoke(app, ["show", str(results)])
    assert done.exit_code == 0, done.output
    assert done.stdout.splitlines()[:3] == [
        f"Protocol version {stamp.PROTOCOL_VERSION}.",
        "",
        "# oodrl results",
    ]


def few_detectors(repo: Path, tmp_path: Path) -> Path:
    """CartPole's results, the records of three detectors kept: a board in seconds."""
    from oodrl.io import yamlio

    document = yamlio.load((repo / PROJECT / "reports" / "results.yaml").read_text())
    kept = {"cusum", "kde_density", "random_scores"}
    document["records"] = [r for r in document["records"] if r.get("detector") in kept]
    path = tmp_path / "few" / "results.yaml"
    path.parent.mkdir()
    path.write_text(yamlio.dump(document))
    return path


def test_the_leaderboard_ranks_one_version_and_names_the_pending_runs(repo, tmp_path):
    """A run rebuilt at the target is ranked, the one still at the previous version is not,
    and every file of the leaderboard says so (the page links the previous version's archive).
    Two runs: CartPole's real results, and a copy stamped one version older."""
    from oodrl.io import yamlio
    from oodrl.report.leaderboard import newest_runs
    from oodrl.stages.leaderboard import run_leaderboard

    version = stamp.PROTOCOL_VERSION
    results = few_detectors(repo, tmp_path)
    older = tmp_path / "older" / "results.yaml"
    older.parent.mkdir()
    older.write_text(results.read_text())
    edit(older, f"protocol_version: {version}\n", f"protocol_version: {version - 1}\n")
    ranked, pending = newest_runs({("CartPole-v1", "0"): [results], ("CartPole-v1", "1"): older})
    assert ranked == {("CartPole-v1", "0"): [results]}
    assert pending == {("CartPole-v1", "1"): version - 1}
    out = tmp_path / "out"
    run_leaderboard(ranked, out, n_boot=50, ci=0.95, seed=0, pending=pending)
    line = (
        f"Protocol {version}: 1 of 2 runs ranked; pending (results of an older protocol, ranked "
        f"by none of this page's numbers): CartPole-v1/1 (protocol {version - 1}). The previous "
        f"version's complete leaderboard: pipeline/suite/archive/protocol-{version - 1}/."
    )
    markdown = (out / "leaderboard.md").read_text().splitlines()
    assert markdown[2].startswith(f"Protocol version {version}; 1 environment;")
    assert markdown[4] == line
    keys = {
        "protocol_version": version,
        "runs_at_version": 1,
        "pending": [{"environment": "CartPole-v1", "policy": "1", "protocol_version": version - 1}],
    }
    board = json.loads((out / "leaderboard.json").read_text())
    assert {key: board[key] for key in keys} == keys
    assert [run["policy"] for run in board["runs"]] == ["0"]  # ranked: the target's run only
    mapping = yamlio.load((out / "leaderboard.yaml").read_text())
    assert {key: mapping[key] for key in keys} == keys
    page = (out / "leaderboard.html").read_text()
    link = f'<a href="../archive/protocol-{version - 1}/leaderboard.html">'
    assert f'<p class="stamp" id="protocol-runs">{line[:40]}' in page and link in page


def test_the_leaderboard_with_nothing_pending_says_so(repo, tmp_path):
    from oodrl.stages.leaderboard import run_leaderboard

    results = few_detectors(repo, tmp_path)
    run_leaderboard({("CartPole-v1", "0"): results}, tmp_path, 50, 0.95, 0, pending={})
    line = f"Protocol {stamp.PROTOCOL_VERSION}: all 1 run ranked; none pending."
    assert (tmp_path / "leaderboard.md").read_text().splitlines()[4] == line
    assert f'id="protocol-runs">{line}</p>' in (tmp_path / "leaderboard.html").read_text()


def test_the_readme_table_names_the_version(repo_root):
    from oodrl.report.readme import leaderboard_headline

    board = json.loads((repo_root / "pipeline/suite/reports/leaderboard.json").read_text())
    assert f"protocol version {board['protocol_version']};" in leaderboard_headline(board)


def test_the_readme_table_names_the_pending_runs(repo_root):
    from oodrl.report.readme import leaderboard_headline

    board = json.loads((repo_root / "pipeline/suite/reports/leaderboard.json").read_text())
    assert "Pending" not in leaderboard_headline(board)  # the committed board: nothing pending
    board["pending"] = [{"environment": "Hopper-v5", "policy": "1", "protocol_version": 3}]
    caption = leaderboard_headline(board).splitlines()[-1]
    assert "Pending, ranked by none of these numbers: Hopper-v5/1 (protocol 3)." in caption
