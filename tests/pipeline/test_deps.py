"""Every pipeline is generated from one template, and every stage's code stamp covers its
command's import closure (SPEC §12): a code edit re-runs every stage that can execute the
edited file, and only those."""

from __future__ import annotations

import ast
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
from oodrl.io.layout import detector_pipeline
from oodrl.suite.environments import MORE_POLICIES, PIPELINE_DIRS, suite_runs
from oodrl.suite.pipeline import (
    _LINE,
    DETECTOR_TEMPLATE,
    FILLED_DIRS,
    FILLED_DIRS_IGNORED,
    MERGED_PARAMS,
    SUBREPO_FILES,
    TEMPLATE,
    Project,
    _command_nodes,
    _source_segment,
    check_files,
    check_pipeline,
    kind_files,
    rendered,
    stage_kind,
    stamp_text,
    write,
    write_stamps,
)
from oodrl.testing.pipeline import run

SOURCE_ROOT = Path(oodrl.__file__).resolve().parents[2]  # the checkout the stages import


def _relative(root: Path, files: set[Path]) -> set[str]:
    return {p.relative_to(root).as_posix() for p in files}


def _files(repo_root: Path, verb: str, name: str | None = None, params=None) -> set[str]:
    params = params or yaml.safe_load((repo_root / "params.yaml").read_text())
    return _relative(repo_root, kind_files(Project(repo_root), verb, name, params))


# -- the committed pipelines -----------------------------------------------------------------
def test_committed_pipelines_are_what_pipeline_write_writes(repo_root, monkeypatch):
    check_files(repo_root)
    monkeypatch.chdir(repo_root)
    result = CliRunner().invoke(app, ["pipeline", "check"])
    assert result.exit_code == 0, result.output


def test_a_hand_edited_pipeline_is_refused(tmp_path, repo_root):
    (tmp_path / "src").symlink_to(repo_root / "src")
    shutil.copy(repo_root / "params.yaml", tmp_path / "params.yaml")
    detectors = yaml.safe_load((repo_root / "params.yaml").read_text())["benchmark"]["detectors"]
    assert write(tmp_path) == [
        tmp_path / "dvc.yaml",
        *(tmp_path / detector_pipeline(d) for d in detectors),
        tmp_path / "pipeline/suite/dvc.yaml",
        *(tmp_path / "pipeline/suite" / name for name in SUBREPO_FILES),
    ]
    check_files(tmp_path)
    with (tmp_path / "dvc.yaml").open("a") as pipeline:
        pipeline.write("# an edit\n")
    with pytest.raises(ConfigError, match="run `oodrl pipeline write`") as info:
        check_pipeline(tmp_path / "dvc.yaml")
    assert "\n" not in str(info.value)


def test_every_stage_depends_on_its_code_stamp_and_check_params_on_the_sources(repo_root):
    stages = yaml.safe_load((repo_root / "dvc.yaml").read_text())["stages"]
    assert stages["check_params"]["deps"] == ["params.yaml", "src/oodrl"]
    assert "data/code/collect-ood-${item}.txt" in stages["collect_sweep"]["do"]["deps"]
    assert "data/code/metrics.txt" in stages["metrics"]["deps"]
    kde = yaml.safe_load((repo_root / detector_pipeline("kde_density")).read_text())["stages"]
    assert "data/code/fit-kde_density.txt" in kde["fit"]["deps"]
    assert "data/code/score-kde_density.txt" in kde["score_clean"]["deps"]
    assert "data/code/score-kde_density.txt" in kde["score"]["deps"]
    assert "data/code/cells-kde_density.txt" in kde["cells"]["deps"]
    every = [*stages.values(), *kde.values()]
    deps = [d for s in every for d in s.get("deps", s.get("do", {}).get("deps", []))]
    assert not [d for d in deps if d.startswith("src/") and d != "src/oodrl"]


# -- environment pipelines ---------------------------------------------------------------------
CARTPOLE_PARAMS = (
    "extends: ../../params.yaml\nenv: {id: CartPole-v1, T: 60}\n"
    "policy: {train: {env_id: CartPole-v1}}\n"
    "anomaly: {injectors: {action_conditioned_dynamics: {target_action: 1}}}\n"
)


@pytest.fixture
def env_project(tmp_path, repo_root) -> Path:
    """A project with the shared params and one environment directory extending them."""
    (tmp_path / "src").symlink_to(repo_root / "src")
    shutil.copy(repo_root / "params.yaml", tmp_path / "params.yaml")
    env = tmp_path / "pipeline" / "cartpole"
    env.mkdir(parents=True)
    (env / "params.yaml").write_text(CARTPOLE_PARAMS)
    return tmp_path


def test_environment_pipeline_paths_are_relative_to_its_directory(env_project):
    env = env_project / "pipeline" / "cartpole"
    suite = env_project / "pipeline/suite/dvc.yaml"
    shared = yaml.safe_load((env_project / "params.yaml").read_text())
    detectors = shared["benchmark"]["detectors"]
    assert write(env_project) == [
        *(project / name for project in (env_project, env)
          for name in ["dvc.yaml", *(detector_pipeline(d) for d in detectors)]),
        suite,
        *(project / name for project in (env, suite.parent) for name in SUBREPO_FILES),
    ]  # fmt: skip
    # The environment's and the suite's pipelines are DVC projects sharing the root's cache.
    config = (env / ".dvc" / "config").read_text()
    assert (env / ".dvc" / "../../../.dvc").resolve() == env_project / ".dvc"
    assert "dir = ../../../.dvc/cache" in config
    stages = yaml.safe_load((env / "dvc.yaml").read_text())["stages"]
    # The package's files one by one (DVC applies no .dvcignore outside the project).
    sources = [f"../../{s.relative_to(env_project)}" for s in Project(env_project).source_files()]
    assert stages["check_params"]["deps"] == ["params.yaml", "../../params.yaml", *sources]
    assert "../../src/oodrl/cli.py" in stages["check_params"]["deps"]
    assert "--merged data/params.yaml" in stages["check_params"]["cmd"]
    # DVC reads a key from one file: the merged params check_params writes.
    kde = yaml.safe_load((env / detector_pipeline("kde_density")).read_text())["stages"]
    assert kde["fit"]["params"] == [{MERGED_PARAMS: ["detectors.kde_density"]}]
    assert kde["fit"]["wdir"] == "../.."  # paths stay relative to the environment's directory
    assert stages["collect_id"]["params"][0][MERGED_PARAMS][:2] == ["seed", "env"]
    assert stages["collect_ood"]["foreach"] == shared["benchmark"]["injectors"]
    # A stage reading every injector's set lists each (SPEC §23), written out from the list.
    injectors = shared["benchmark"]["injectors"]
    assert [d for d in kde["score"]["deps"] if d.startswith("data/ood/")] == [
        f"data/ood/{i}.zarr" for i in injectors
    ]
    assert kde["score"]["outs"] == [f"scores/kde_density/{i}.zarr" for i in injectors]
    assert stages["train_policy"]["outs"][0] == {
        "models/policy.pt": {"cache": False, "persist": True}
    }
    check_files(env_project)


def test_bytecode_beside_the_sources_leaves_an_environment_project_up_to_date(tmp_path, repo_root):
    """The interpreter's __pycache__ is in no lock: a clone that ran the code matches it."""
    shutil.copytree(repo_root / "src", tmp_path / "src", ignore=shutil.ignore_patterns("*.pyc"))
    shutil.copy(repo_root / "params.yaml", tmp_path / "params.yaml")
    env = tmp_path / "pipeline" / "cartpole"
    env.mkdir(parents=True)
    (env / "params.yaml").write_text(CARTPOLE_PARAMS)
    write(tmp_path)
    run(tmp_path, "git", "init", "-q")
    run(tmp_path, "dvc", "init", "-q")
    run(env, "dvc", "repro", "check_params")
    package = tmp_path / "src" / "oodrl"
    for cache in (package / "__pycache__", package / "core" / "__pycache__"):
        cache.mkdir(exist_ok=True)
        (cache / "cli.cpython-311.pyc").write_bytes(b"bytecode")
    assert "up to date" in run(env, "dvc", "status", "check_params").stdout
    with (package / "cli.py").open("a") as source:  # a source edit still re-runs the check
        source.write("\n")
    assert "changed deps" in run(env, "dvc", "status", "check_params").stdout


def test_a_shared_fan_out_change_makes_environment_pipelines_stale(env_project):
    write(env_project)
    shared = yaml.safe_load((env_project / "params.yaml").read_text())
    shared["benchmark"]["detectors"].remove("pedm")
    (env_project / "params.yaml").write_text(yaml.safe_dump(shared))
    # The merge stages list every detector's cells file (SPEC §23): the dvc.yaml is stale first.
    with pytest.raises(ConfigError, match="unexpected '- cells/pedm.json'"):
        check_pipeline(env_project / "dvc.yaml")
    with pytest.raises(ConfigError, match="pipeline/cartpole/dvc.yaml is not what the template"):
        check_pipeline(env_project / "pipeline" / "cartpole" / "dvc.yaml")
    orphan = (env_project / detector_pipeline("pedm")).read_text()
    write(env_project)
    assert not (env_project / detector_pipeline("pedm")).exists()
    check_files(env_project)
    # A detector's file left behind, its dvc.yaml current, is named.
    (env_project / detector_pipeline("pedm")).write_text(orphan)
    with pytest.raises(ConfigError, match="detectors/pedm/dvc.yaml belongs to a detector"):
        check_pipeline(env_project / "dvc.yaml")


def test_an_environment_pipeline_without_its_dvc_project_is_refused(env_project):
    write(env_project)
    (env_project / "pipeline" / "cartpole" / ".dvc" / "config").unlink()
    with pytest.raises(ConfigError, match=r"pipeline/cartpole/\.dvc/config is missing"):
        check_pipeline(env_project / "pipeline" / "cartpole" / "dvc.yaml")


def test_environment_stamps_name_its_adapter(env_project):
    write(env_project)
    env = env_project / "pipeline" / "cartpole"
    stamps = write_stamps(env / "dvc.yaml", env / "params.yaml", env / "data" / "code")
    collect = (env / "data" / "code" / "collect-id.txt").read_text()
    assert "  ../../src/oodrl/envs/classic_control.py\n" in collect
    assert "lunar_lander.py" not in collect
    assert len(stamps) == len({p.name for p in stamps})


def _insert_statement(cli: Path, function: str | None) -> None:
    """Add a statement to one function's body of cli.py, or at module level (None)."""
    import ast

    lines = cli.read_text().splitlines(keepends=True)
    if function is None:
        lines.append("EDITED = True\n")
    else:
        tree = ast.parse("".join(lines))
        (node,) = [n for n in tree.body if getattr(n, "name", None) == function]
        lines.insert(node.body[0].end_lineno, "    assert True  # an edit\n")
    cli.write_text("".join(lines))


def test_a_cli_edit_restamps_only_the_verbs_that_run_it(tmp_path, repo_root):
    """cli.py's stamp line hashes the code its verb runs there (SPEC §12): editing one command
    leaves the other verbs' stamps, and so their stages, alone; module-level code is everyone's."""
    shutil.copytree(repo_root / "src", tmp_path / "src", ignore=shutil.ignore_patterns("*.pyc"))
    params = yaml.safe_load((repo_root / "params.yaml").read_text())
    project = Project(tmp_path)
    kinds = [("fit", "kde_density"), ("score", "kde_density"), ("metrics", None),
             ("collect-ood", "gaussian_state_noise"), ("impact", "stuck_actuator")]  # fmt: skip

    def stamps() -> dict[str, str]:
        return {
            verb: stamp_text(project, kind_files(project, verb, name, params), verb)
            for verb, name in kinds
        }

    cli = tmp_path / "src" / "oodrl" / "cli.py"
    before = stamps()
    _insert_statement(cli, "monitor")  # a command no stage runs
    assert stamps() == before
    _insert_statement(cli, "fit")
    after = stamps()
    assert [verb for verb in before if after[verb] != before[verb]] == ["fit"]
    _insert_statement(cli, "_load")  # a helper every stage verb calls
    assert all(stamps()[verb] != after[verb] for verb in before)
    after = stamps()
    _insert_statement(cli, None)
    assert all(stamps()[verb] != after[verb] for verb in before)


def test_cli_code_is_cut_out_as_ast_cuts_it(repo_root):
    """A verb's cli.py code is cut from lines split once, as `ast.get_source_segment` splits
    them (at \\r\\n, \\r and \\n alone), with its padding of a node's indent: the same text, so
    the same stamps, on line endings, tabs, multi-byte characters and a form feed."""
    source = (
        "x = 1\r\ndef f(a,\r\n      b):\r\n\treturn 'é\\u2028'  # é\x0c\u2028ok\n"
        "\x0cclass C:\r    y = ('é', (1,\n         2))\n\nif x:\n\tz = [f(1, 2),\n\t     3]"
    )
    lines = _LINE.findall(source)
    nodes = [n for n in ast.walk(ast.parse(source)) if getattr(n, "end_lineno", None)]
    assert len(nodes) > 20
    for node in nodes:
        assert _source_segment(lines, node) == ast.get_source_segment(source, node, padded=True)
    cli = repo_root / "src" / "oodrl" / "cli.py"
    text = cli.read_text()
    nodes = sorted(_command_nodes(ast.parse(text), "fit"), key=lambda node: node.lineno)
    assert Project(repo_root).command_source("fit") == "\n".join(
        ast.get_source_segment(text, node, padded=True) for node in nodes
    )


# -- the closure -----------------------------------------------------------------------------
def test_closures_follow_the_verb_not_the_whole_cli(repo_root):
    collect = _files(repo_root, "collect-id")
    assert "src/oodrl/stages/collect.py" in collect
    assert not {"src/oodrl/stages/fit.py", "src/oodrl/stages/metrics.py"} & collect
    metrics = _files(repo_root, "metrics")
    assert "src/oodrl/metrics/aggregate.py" in metrics  # imported inside functions only
    assert "src/oodrl/stages/collect.py" not in metrics


def test_a_stage_lists_only_the_components_it_builds(repo_root):
    """fit/score of kde: kde's module, no other detector; collection: its injector's module
    and the environment's adapter; metrics: every detector (their latencies), no injector."""
    for verb in ("fit", "score"):
        files = _files(repo_root, verb, "kde_density")
        assert {"src/oodrl/detectors/kde.py", "src/oodrl/core/detector.py"} <= files
        assert "src/oodrl/io/store.py" in files
        assert not {"src/oodrl/detectors/pedm.py", "src/oodrl/detectors/cusum.py"} & files
    posthoc = _files(repo_root, "collect-ood", "observation_delay")
    assert {"src/oodrl/injectors/posthoc.py", "src/oodrl/envs/lunar_lander.py"} <= posthoc
    assert "src/oodrl/envs/mujoco.py" not in posthoc
    online = _files(repo_root, "collect-ood", "stuck_actuator")
    assert "src/oodrl/injectors/online.py" in online
    metrics = _files(repo_root, "metrics")
    assert {"src/oodrl/detectors/kde.py", "src/oodrl/detectors/pedm.py"} <= metrics
    assert not [f for f in metrics if f.startswith("src/oodrl/injectors/posthoc")]


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
    found = _relative(tmp_path, Project(tmp_path).closure(["demo.a"]))
    assert found == set(files) - {"src/demo/unused.py"}


def test_stage_kind_names_the_component_its_command_builds():
    assert stage_kind("oodrl fit ${item} --id data/id.zarr --out x.pkl") == ("fit", "${item}")
    assert stage_kind("oodrl score kde --injector x --model m") == ("score", "kde")
    assert stage_kind("oodrl cells kde --scores s --out c.json") == ("cells", "kde")
    assert stage_kind("oodrl collect-id --policy p --out o") == ("collect-id", None)
    assert stage_kind("python script.py") is None


# -- plugins named in params -----------------------------------------------------------------
PLUGIN = """from oodrl.core import BaseDetector
import plugin_helpers


class Speed(BaseDetector): ...
"""


@pytest.fixture
def plugin_project(tmp_path, repo_root) -> Path:
    """A project whose params name a detector plugin beside params.yaml."""
    (tmp_path / "src").symlink_to(repo_root / "src")
    (tmp_path / "speed_plugin.py").write_text(PLUGIN)
    (tmp_path / "plugin_helpers.py").write_text("")
    params = yaml.safe_load((repo_root / "params.yaml").read_text())
    params["benchmark"]["detectors"].append("speed")
    params["detectors"]["speed"] = {"class": "speed_plugin:Speed"}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    return tmp_path


def test_plugin_is_in_the_stamps_of_the_stages_that_build_it(plugin_project):
    params = yaml.safe_load((plugin_project / "params.yaml").read_text())
    plugin = {"speed_plugin.py", "plugin_helpers.py"}
    for verb in ("fit", "score"):
        assert plugin <= _files(plugin_project, verb, "speed", params), verb
    assert not plugin & _files(plugin_project, "fit", "kde_density", params)
    assert not plugin & _files(plugin_project, "collect-ood", "stuck_actuator", params)


def test_plugin_is_a_dep_of_check_params_once_written(plugin_project):
    text = rendered(plugin_project, plugin_project)
    deps = yaml.safe_load(text)["stages"]["check_params"]["deps"]
    assert deps == ["params.yaml", "src/oodrl", "plugin_helpers.py", "speed_plugin.py"]
    (plugin_project / "dvc.yaml").write_text(text.replace("  - plugin_helpers.py\n", ""))
    with pytest.raises(ConfigError, match="oodrl pipeline write"):
        check_files(plugin_project)


# -- what the stage commands really import ---------------------------------------------------
#: The `oodrl` command's launcher: every stage process loads it, and no stamp lists it, by
#: choice (docs/SPEC.md §12, warm stage processes): it passes a command through to oodrl.cli and
#: computes nothing of its outputs; tests/pipeline/test_warm.py checks that it changes no byte.
LAUNCHER = {"src/oodrl/__main__.py", "src/oodrl/warm.py"}


@pytest.mark.slow
def test_stage_commands_import_only_modules_their_stamps_list(built_repo):
    """Every oodrl file loaded by a stage command during the build is listed in its stamp."""
    from dvc.repo import Repo

    with Repo(str(built_repo)) as dvc:
        commands = {tuple(shlex.split(s.cmd)[1:]): s.name for s in dvc.index.stages}
    package = SOURCE_ROOT / "src" / "oodrl"
    checked = set()
    for record_path in sorted((built_repo.parent / "import-trace").glob("*.json")):
        record = json.loads(record_path.read_text())
        argv = tuple(record["argv"][1:])
        if argv not in commands or not record["argv"][0].endswith("oodrl"):
            continue
        name = commands[argv]
        loaded = {
            Path(f).relative_to(SOURCE_ROOT).as_posix()
            for f in record["files"]
            if Path(f).is_relative_to(package)
        }
        if name == "check_params":
            listed = {p.relative_to(SOURCE_ROOT).as_posix() for p in package.rglob("*.py")}
        else:
            verb, component = stage_kind(shlex.join(["oodrl", *argv]))
            stamp = built_repo / "data" / "code" / f"{verb}{f'-{component}' * bool(component)}.txt"
            listed = {line.split("  ", 1)[1] for line in stamp.read_text().splitlines()}
        unlisted = loaded - listed - LAUNCHER
        assert sorted(unlisted) == [], f"{name} imported files its stamp does not list"
        checked.add(name.split("@")[0])
    assert {"check_params", "collect_id", "collect_ood", "fit", "score", "metrics", "render"} <= (
        checked
    )


def test_the_suite_pipeline_reads_every_runs_results(repo_root):
    stage = yaml.safe_load((repo_root / "pipeline/suite/dvc.yaml").read_text())["stages"]
    deps = stage["leaderboard"]["deps"]
    results = {d for d in deps if d.endswith("reports/results.yaml")}
    runs = {f"../{directory.name}/reports/results.yaml" for directory in suite_runs().values()}
    assert results == runs and len(runs) == len(PIPELINE_DIRS) + len(MORE_POLICIES)
    assert "../../src/oodrl/metrics/leaderboard.py" in deps
    assert "../../src/oodrl/report/leaderboard_page.html" in deps  # the page's template
    outs = stage["leaderboard"]["outs"]  # the page and its data: git-tracked (SPEC §21)
    assert {"reports/leaderboard.html": {"cache": False}} in outs
    assert {"reports/leaderboard.json": {"cache": False}} in outs
    root_stages = yaml.safe_load((repo_root / "dvc.yaml").read_text())["stages"]
    assert "leaderboard" not in root_stages  # the root `dvc repro` stays the paper default


def test_no_stage_reads_a_directory_other_stages_fill(repo_root):
    """Every dep is one stage's output or a file no stage writes, never a directory several
    stages fill (SPEC §23: `dvc repro --pull --allow-missing` pulls exactly what a stage
    reads). The directories several stages fill are FILLED_DIRS, which every project's
    .gitignore ignores whole, the root's too, so DVC writes no .gitignore inside them."""
    bodies = [
        stage.get("do", stage)
        for template in (TEMPLATE, DETECTOR_TEMPLATE)
        for stage in yaml.safe_load(template.read_text())["stages"].values()
    ]
    outs = [[o if isinstance(o, str) else next(iter(o)) for o in b.get("outs", [])] for b in bodies]
    every_out = {o for stage_outs in outs for o in stage_outs}
    deps = {dep for body in bodies for dep in body.get("deps", [])}
    assert not {d for d in deps - every_out if any(o.startswith(f"{d}/") for o in every_out)}
    for directory in FILLED_DIRS:  # a detector template's stage writes one output a detector
        assert any(o.startswith(f"{directory}/") for o in every_out), directory
    assert FILLED_DIRS_IGNORED in (repo_root / ".gitignore").read_text()
    assert FILLED_DIRS_IGNORED in SUBREPO_FILES[".gitignore"]
