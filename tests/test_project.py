"""Project-level promises: the README's two commands, CI's params, pinned dependencies,
nothing host-specific."""

from __future__ import annotations

import subprocess
from importlib import metadata

import yaml
from packaging.requirements import Requirement
from packaging.specifiers import SpecifierSet
from packaging.utils import canonicalize_name

from oodrl.config import load_params


def _command_after(readme: str, marker: str) -> str:
    lines = readme.splitlines()
    index = lines.index(marker)
    assert lines[index + 1] == "```bash"
    return lines[index + 2]


def test_readme_has_the_two_setup_commands(repo_root):
    readme = (repo_root / "README.md").read_text()
    run_command = _command_after(readme, "<!-- run-command -->")
    test_command = _command_after(readme, "<!-- test-command -->")
    for command in (run_command, test_command):
        assert "-c constraints.txt" in command
    assert run_command.endswith("dvc repro")
    assert "pytest" in test_command


def test_ci_runs_the_readme_test_command(repo_root):
    extract = subprocess.run(
        ["awk", "/<!-- test-command -->/{getline; getline; print; exit}", "README.md"],
        cwd=repo_root, capture_output=True, text=True, check=True,
    )  # fmt: skip
    readme = (repo_root / "README.md").read_text()
    assert extract.stdout.strip() == _command_after(readme, "<!-- test-command -->")
    assert "<!-- test-command -->" in (repo_root / ".ci" / "run").read_text()


def test_ci_params_are_valid_and_reuse_the_committed_policy(repo_root):
    ci = load_params(repo_root / "ci" / "params.yaml")
    default = load_params(repo_root / "params.yaml")
    assert ci.policy.train == default.policy.train, "CI would retrain the policy"
    assert ci.benchmark == default.benchmark, "CI must exercise every stage of the pipeline"
    # Its tiers block copies the tests' tiny pipelines' sizes (a YAML file cannot import them).
    from oodrl.config import read_params_data
    from oodrl.testing.pipeline import TINY_TIERS

    tiers = read_params_data(repo_root / "ci" / "params.yaml")["tiers"]  # merged: search has more
    copied = dict(TINY_TIERS, search={**tiers["search"], **TINY_TIERS["search"]})
    assert {key: tiers[key] for key in TINY_TIERS} == copied


def _pins(constraints: str) -> dict[str, SpecifierSet]:
    """Each pinned distribution's canonical name and its `==` specifier."""
    pins = {}
    for line in constraints.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            requirement = Requirement(line)
            pins[canonicalize_name(requirement.name)] = requirement.specifier
    return pins


def _installed_closure(name: str, extras: tuple[str, ...]) -> set[str]:
    """Canonical names of `name`[extras] and of every distribution it needs, transitively, as
    the installed metadata and this interpreter's markers say."""
    seen: set[tuple[str, str]] = set()
    pending = [(name, extra) for extra in ("", *extras)]
    names = set()
    while pending:
        current, extra = pending.pop()
        key = canonicalize_name(current)
        if (key, extra) in seen:
            continue
        seen.add((key, extra))
        names.add(key)
        for line in metadata.distribution(current).requires or []:
            requirement = Requirement(line)
            if requirement.marker is None or requirement.marker.evaluate({"extra": extra}):
                pending += [(requirement.name, e) for e in ("", *requirement.extras)]
    return names


def test_constraints_pin_every_installed_dependency_to_the_installed_version(repo_root):
    """The README installs with `-c constraints.txt`: a dependency it does not pin is whatever
    the index serves that day, and an installed version off its pin means this environment is
    not the pinned one."""
    pins = _pins((repo_root / "constraints.txt").read_text())
    needed = _installed_closure("oodrl", ("dev",)) - {"oodrl"}
    unpinned = sorted(f"{n}=={metadata.version(n)}" for n in needed if n not in pins)
    assert not unpinned, f"constraints.txt lacks pins; add the lines {unpinned}."
    off = {n: metadata.version(n) for n in needed if metadata.version(n) not in pins[n]}
    assert not off, f"installed versions differ from their pins in constraints.txt: {off}"
    assert all(str(spec).startswith("==") for spec in pins.values()), "pins must be exact"


def test_constraints_pin_the_cpu_build_of_torch(repo_root):
    pins = _pins((repo_root / "constraints.txt").read_text())
    assert "torch" in pins
    assert not any(name.startswith(("nvidia", "cuda")) for name in pins), "a CUDA package"


def test_params_yaml_is_plain_yaml(repo_root):
    data = yaml.safe_load((repo_root / "params.yaml").read_text())
    assert set(data) >= {"seed", "env", "data", "policy", "benchmark", "anomaly", "detectors"}
