"""Every stage's deps cover its command's import closure (SPEC §12): a code edit re-runs
every stage that can execute the edited file."""

from __future__ import annotations

import json
import shlex
import shutil
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

import oodrl
from oodrl.cli import app
from oodrl.errors import ConfigError
from oodrl.pipeline import (
    Project,
    check,
    check_coverage,
    missing_deps,
    rendered,
    required_deps,
    stages_and_required,
    write,
)

SOURCE_ROOT = Path(oodrl.__file__).resolve().parents[2]  # the checkout the stages import


def _closure(repo_root: Path, verb: str) -> set[str]:
    project = Project(repo_root)
    return {p.relative_to(repo_root).as_posix() for p in project.command_closure(verb)}


# -- the committed dvc.yaml ------------------------------------------------------------------
def test_committed_dvc_yaml_covers_every_stage_import_closure(repo_root):
    missing = missing_deps(*stages_and_required(repo_root / "dvc.yaml", repo_root / "params.yaml"))
    assert missing == [], f"run `oodrl pipeline write`; stage deps miss: {missing}"


def test_committed_dvc_yaml_is_what_pipeline_write_writes(repo_root):
    text = (repo_root / "dvc.yaml").read_text()
    assert rendered(repo_root / "dvc.yaml", repo_root / "params.yaml") == text, (
        "run `oodrl pipeline write`"
    )


@pytest.mark.parametrize(
    ("stage", "dep"),
    [
        ("fit", "src/oodrl/store.py"),  # the store its command reads
        ("score", "src/oodrl/core/detector.py"),  # BaseDetector.score, through the pickle
        ("score", "src/oodrl/detectors"),  # unpickling imports the detector's module
        ("collect_id", "src/oodrl/stages/collect.py"),
    ],
)
def test_a_stage_missing_a_module_its_command_imports_is_reported(repo_root, stage, dep):
    stages, required = stages_and_required(repo_root / "dvc.yaml", repo_root / "params.yaml")
    body = stages[stage]["do"] if "foreach" in stages[stage] else stages[stage]
    (entry,) = [d for d in body["deps"] if dep == d or dep.startswith(f"{d}/")]
    assert missing_deps(stages, required) == []
    body["deps"].remove(entry)
    assert missing_deps(stages, required) == [(stage, entry)]


def test_check_stage_reads_every_stage_code(repo_root):
    stages, required = stages_and_required(repo_root / "dvc.yaml", repo_root / "params.yaml")
    every = {dep for name, deps in required.items() if name != "check_params" for dep in deps}
    covered = required["check_params"]
    assert all(any(d == c or d.startswith(f"{c}/") for c in covered) for d in every)
    assert "params.yaml" in stages["check_params"]["deps"]
    assert all("data/params.checked" in deps for deps in _listed_deps(stages, "check_params"))


def _listed_deps(stages: dict, skip: str) -> list[list[str]]:
    return [
        list((body["do"] if "foreach" in body else body)["deps"])
        for name, body in stages.items()
        if name != skip
    ]


def test_pipeline_check_verb_passes_on_the_committed_pipeline(repo_root, monkeypatch):
    monkeypatch.chdir(repo_root)
    result = CliRunner().invoke(app, ["pipeline", "check"])
    assert result.exit_code == 0, result.output


# -- the closure -----------------------------------------------------------------------------
def test_closures_follow_the_verb_not_the_whole_cli(repo_root):
    collect = _closure(repo_root, "collect-id")
    assert "src/oodrl/stages/collect.py" in collect
    assert not {"src/oodrl/stages/fit.py", "src/oodrl/stages/metrics.py"} & collect
    metrics = _closure(repo_root, "metrics")
    assert "src/oodrl/metrics/aggregate.py" in metrics  # imported inside functions only
    assert "src/oodrl/stages/collect.py" not in metrics
    score = _closure(repo_root, "score")
    assert {"src/oodrl/store.py", "src/oodrl/core/detector.py", "src/oodrl/detectors/kde.py"} <= (
        score
    )


def test_closure_counts_nested_imports_parents_and_import_path_strings(tmp_path):
    files = {
        "src/demo/__init__.py": "",
        "src/demo/a.py": "def later():\n    from demo import b\n",
        "src/demo/b.py": "REGISTERED = 'demo.sub.c:Thing'\nLAZY = f'demo.d:{1}'\n",
        "src/demo/sub/__init__.py": "",
        "src/demo/sub/c.py": "import numpy\n\nclass Thing: ...\n",
        "src/demo/d.py": "import importlib\nimportlib.import_module('demo.e')\n",
        "src/demo/e.py": "",
        "src/demo/unused.py": "",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    found = {p.relative_to(tmp_path).as_posix() for p in Project(tmp_path).closure(["demo.a"])}
    assert found == set(files) - {"src/demo/unused.py"}


def test_pipeline_in_a_subdirectory_lists_code_relative_to_itself(tmp_path, repo_root):
    """A per-environment dvc.yaml (SPEC §12) below the project root, as DVC reads its paths."""
    (tmp_path / "src").symlink_to(repo_root / "src")
    sub = tmp_path / "envs" / "demo"
    sub.mkdir(parents=True)
    stage = {"cmd": "oodrl fit x --id data/id.zarr --out x.pkl", "deps": ["data/id.zarr"]}
    (sub / "dvc.yaml").write_text(yaml.safe_dump({"stages": {"fit": stage}}))
    (sub / "params.yaml").write_text("seed: 0\n")
    assert write(sub / "dvc.yaml", sub / "params.yaml")
    deps = yaml.safe_load((sub / "dvc.yaml").read_text())["stages"]["fit"]["deps"]
    assert deps[0] == "data/id.zarr" and "../../src/oodrl/stages/fit.py" in deps
    check(sub / "dvc.yaml", sub / "params.yaml")
    assert not write(sub / "dvc.yaml", sub / "params.yaml")


# -- plugins named in params -----------------------------------------------------------------
PLUGIN = """from oodrl.core import BaseDetector
import plugin_helpers


class Speed(BaseDetector): ...
"""


@pytest.fixture
def plugin_project(tmp_path, repo_root) -> Path:
    """A project whose params name a detector plugin beside params.yaml."""
    (tmp_path / "src").symlink_to(repo_root / "src")
    shutil.copy(repo_root / "dvc.yaml", tmp_path / "dvc.yaml")
    (tmp_path / "speed_plugin.py").write_text(PLUGIN)
    (tmp_path / "plugin_helpers.py").write_text("")
    params = yaml.safe_load((repo_root / "params.yaml").read_text())
    params["benchmark"]["detectors"].append("speed")
    params["detectors"]["speed"] = {"class": "speed_plugin:Speed"}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    return tmp_path


def test_plugin_is_a_dep_of_the_stages_that_build_it(plugin_project):
    stages, _ = stages_and_required(plugin_project / "dvc.yaml", plugin_project / "params.yaml")
    params = yaml.safe_load((plugin_project / "params.yaml").read_text())
    required = required_deps(Project(plugin_project), stages, params)
    plugin = {"speed_plugin.py", "plugin_helpers.py"}
    for stage in ("fit", "score_clean", "score", "check_params"):
        assert plugin <= set(required[stage]), stage
    for stage in ("collect_id", "collect_ood", "metrics", "render"):
        assert not plugin & set(required[stage]), stage


def test_dvc_yaml_missing_a_plugin_is_refused_until_rewritten(plugin_project):
    pipeline, params = plugin_project / "dvc.yaml", plugin_project / "params.yaml"
    with pytest.raises(ConfigError) as info:
        check_coverage(pipeline, params)
    message = str(info.value)
    assert "\n" not in message
    assert "plugin_helpers.py" in message or "speed_plugin.py" in message
    assert "`oodrl pipeline write`" in message
    assert write(pipeline, params)
    check_coverage(pipeline, params)
    fit = yaml.safe_load(pipeline.read_text())["stages"]["fit"]["do"]["deps"]
    assert {"speed_plugin.py", "plugin_helpers.py"} <= set(fit)


# -- what the stage commands really import ---------------------------------------------------
@pytest.mark.slow
def test_stage_commands_import_only_modules_their_deps_list(built_repo):
    """Every oodrl file loaded by a stage command during the build is covered by its deps."""
    from dvc.repo import Repo

    with Repo(str(built_repo)) as dvc:
        stages = {
            tuple(shlex.split(stage.cmd)[1:]): (stage.name, [str(d.def_path) for d in stage.deps])
            for stage in dvc.index.stages
        }
    package = SOURCE_ROOT / "src" / "oodrl"
    checked = set()
    for record_path in sorted((built_repo.parent / "import-trace").glob("*.json")):
        record = json.loads(record_path.read_text())
        if tuple(record["argv"][1:]) not in stages or not record["argv"][0].endswith("oodrl"):
            continue
        name, deps = stages[tuple(record["argv"][1:])]
        loaded = {
            Path(f).relative_to(SOURCE_ROOT).as_posix()
            for f in record["files"]
            if Path(f).is_relative_to(package)
        }
        uncovered = [f for f in loaded if not any(f == d or f.startswith(f"{d}/") for d in deps)]
        assert uncovered == [], f"{name} imported {uncovered} without listing them"
        checked.add(name.split("@")[0])
    assert {"check_params", "collect_id", "collect_ood", "fit", "score", "metrics", "render"} <= (
        checked
    )
