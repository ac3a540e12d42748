"""The DVC stages' code dependencies, derived from the code itself (SPEC §12).

Editing a module must re-run every stage whose command can execute it, so each stage's `deps`
list the import closure of its command inside the project. The closure is a static walk of
every `import` and `from … import` statement — those nested in functions too, since oodrl
imports lazily — and of `module:Class` import-path strings (how the registries name their
built-ins), starting from the stage's verb in `oodrl/cli.py` and following every module it
reaches. In cli.py only the verb's own function and the helpers it calls count; every other
module counts whole (importing a package runs its `__init__.py`, so those count too). The
closure therefore over-approximates: an extra re-run is safe, a missed one is not.

Components that params.yaml names by a `module:Class` path to a file inside the project
(`detectors.<name>.class`, `anomaly.injectors.<name>.class`) are deps of the stages that
build them, and the check_params stage reads the code of every stage, since it checks them all.

`oodrl pipeline write` rewrites the code entries of every stage's `deps` in dvc.yaml (the other
entries, the comments and the layout stay as written); `oodrl pipeline check` fails when
dvc.yaml differs from what `write` would produce; `oodrl check-params --pipeline dvc.yaml`
(the check_params stage) refuses a `dvc repro` whose dvc.yaml misses a dependency.
"""

from __future__ import annotations

import ast
import io
import os
import re
import shlex
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from oodrl.errors import ConfigError

CLI_MODULE = "oodrl.cli"
#: The package sources' directory in the project; code deps are `.py` files and anything in it.
CODE_DIR = "src"
#: The verb whose stage checks every other stage, so it reads all their code.
CHECK_VERB = "check-params"
#: The params sections whose `module:Class` components each verb builds.
COMPONENT_SECTIONS: dict[str, tuple[str, ...]] = {
    "fit": ("detectors",),
    "score": ("detectors",),
    "collect-ood": ("injectors",),
    CHECK_VERB: ("detectors", "injectors"),
}

_DOTTED = r"[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*"
_IMPORT_PATH = re.compile(rf"({_DOTTED}):[A-Za-z_]\w*")
_IMPORT_PATH_PREFIX = re.compile(rf"({_DOTTED}):")


# -- the import closure --------------------------------------------------------------------
@dataclass(frozen=True)
class Project:
    """Where a pipeline's modules live: the package sources under `root/src`, and plugins in
    `base`, the pipeline's own directory (its stage commands run there; see registry.py).
    Dep paths are written relative to `base`, as DVC reads them."""

    root: Path
    base: Path | None = None  # None: the root

    @classmethod
    def of_pipeline(cls, pipeline_path: Path) -> Project:
        """The project of a dvc.yaml: the nearest directory up from it holding the sources."""
        base = pipeline_path.resolve().parent
        cli = Path(CODE_DIR, *CLI_MODULE.split(".")).with_suffix(".py")
        root = next((d for d in (base, *base.parents) if (d / cli).is_file()), base)
        return cls(root, base)

    @property
    def pipeline_dir(self) -> Path:
        return self.base or self.root

    def module_file(self, module: str) -> Path | None:
        """The project file that `import module` executes, or None if it is not ours."""
        relative = Path(*module.split("."))
        for source in (self.root / CODE_DIR, self.pipeline_dir):
            base = source / relative
            for candidate in (base.with_suffix(".py"), base / "__init__.py"):
                if candidate.is_file():
                    return candidate
        return None

    def relative(self, path: Path) -> str:
        return Path(os.path.relpath(path, self.pipeline_dir)).as_posix()

    def is_code_dep(self, dep: str) -> bool:
        """A `.py` file, or anything inside the package sources; every other dep is data."""
        code_dir = os.path.normpath(self.root / CODE_DIR)
        path = os.path.normpath(self.pipeline_dir / dep)
        return dep.endswith(".py") or path == code_dir or path.startswith(code_dir + os.sep)

    def closure(
        self, modules: Iterable[str], known: Mapping[str, set[str]] | None = None
    ) -> set[Path]:
        """Every project file that importing `modules` can execute, transitively.

        `known` gives some modules' imports instead of every import statement in their file.
        """
        known = known or {}
        files: set[Path] = set()
        pending = [parent for module in modules for parent in _with_parents(module)]
        seen: set[str] = set()
        while pending:
            module = pending.pop()
            if module in seen:
                continue
            seen.add(module)
            path = self.module_file(module)
            if path is None:
                continue
            files.add(path)
            names: Iterable[str]
            if module in known:
                names = known[module]
            else:
                package = module if path.name == "__init__.py" else module.rpartition(".")[0]
                names = _module_imports(path, path.stat().st_mtime_ns, package)
            for name in names:
                pending.extend(_with_parents(name))
        return files

    def command_closure(self, verb: str) -> set[Path]:
        """The project files the CLI command `oodrl <verb>` can execute."""
        cli = self.module_file(CLI_MODULE)
        if cli is None:
            raise ConfigError(f"{self.root}: no {CLI_MODULE} module under {CODE_DIR}/.")
        package = CLI_MODULE.rpartition(".")[0]
        names = imported_modules(_command_nodes(_parse(cli), verb), package)
        return self.closure([CLI_MODULE], known={CLI_MODULE: names})


def _with_parents(module: str) -> list[str]:
    """`a.b.c` -> a, a.b, a.b.c: importing a submodule runs every parent's `__init__`."""
    parts = module.split(".")
    return [".".join(parts[: i + 1]) for i in range(len(parts))]


@cache
def _module_imports(path: Path, mtime_ns: int, package: str) -> frozenset[str]:
    """Every module a file's import statements and strings name (cached per file version)."""
    return frozenset(imported_modules(ast.walk(_parse(path)), package))


@cache
def _parse_cached(path: Path, mtime_ns: int) -> ast.Module:
    return ast.parse(path.read_text(), filename=str(path))


def _parse(path: Path) -> ast.Module:
    return _parse_cached(path, path.stat().st_mtime_ns)


def imported_modules(nodes: Iterable[ast.AST], package: str) -> set[str]:
    """Module names that `nodes` import: statements, import-path strings, import_module calls.

    `from a import b` yields both `a` and `a.b` (b may be a submodule); names that are not
    project modules are dropped later, when they resolve to no file.
    """
    names: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = _absolute(node.module, node.level, package)
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names if alias.name != "*")
        elif (module := _string_import(node)) is not None:
            names.add(module)
    return names


def _string_import(node: ast.AST) -> str | None:
    """The module a string names for a later import: a registry's "pkg.module:Class" (an
    f-string's literal prefix included) or the argument of `import_module("pkg.module")`."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        match = _IMPORT_PATH.fullmatch(node.value)
        return match.group(1) if match else None
    if isinstance(node, ast.JoinedStr) and node.values:
        first = node.values[0]  # f"oodrl.metrics.aggregate:{name}"
        if isinstance(first, ast.Constant) and isinstance(first.value, str):
            match = _IMPORT_PATH_PREFIX.match(first.value)
            return match.group(1) if match else None
    if isinstance(node, ast.Call) and _called_name(node) == "import_module" and node.args:
        argument = node.args[0]
        if isinstance(argument, ast.Constant) and isinstance(argument.value, str):
            return argument.value
    return None


def _absolute(module: str | None, level: int, package: str) -> str:
    if level == 0:
        return module or ""
    parts = package.split(".")
    base = ".".join(parts[: len(parts) - level + 1])
    return f"{base}.{module}" if module else base


def _called_name(call: ast.Call) -> str | None:
    if isinstance(call.func, ast.Name):
        return call.func.id
    if isinstance(call.func, ast.Attribute):
        return call.func.attr
    return None


def _command_nodes(tree: ast.Module, verb: str) -> Iterator[ast.AST]:
    """The nodes of cli.py that `oodrl <verb>` runs: module-level code, the verb's function
    and every module-level function these reach by name (other verbs' bodies do not run)."""
    functions = {
        node.name: node
        for node in tree.body
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
    }
    roots: list[ast.AST] = [node for node in tree.body if node not in functions.values()]
    roots += [decorator for node in functions.values() for decorator in node.decorator_list]
    roots.append(_verb_function(functions.values(), verb))
    reached: list[ast.AST] = []
    pending, seen = list(roots), set()
    while pending:
        node = pending.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        reached.append(node)
        for child in ast.walk(node):
            if isinstance(child, ast.Name) and child.id in functions:
                pending.append(functions[child.id])
    for node in reached:
        yield from ast.walk(node)


def _verb_function(
    functions: Iterable[ast.FunctionDef | ast.AsyncFunctionDef], verb: str
) -> ast.FunctionDef | ast.AsyncFunctionDef:
    """The function registered as `verb` (`@command("verb")` or `@app.command("verb")`)."""
    for function in functions:
        for decorator in function.decorator_list:
            if (
                isinstance(decorator, ast.Call)
                and _called_name(decorator) == "command"
                and decorator.args
                and isinstance(decorator.args[0], ast.Constant)
                and decorator.args[0].value == verb
            ):
                return function
    raise ConfigError(f"{CLI_MODULE} has no command '{verb}'.")


# -- stages ----------------------------------------------------------------------------------
def stage_verb(cmd: str) -> str | None:
    """`oodrl fit ${item} …` -> 'fit'; None for a command that is not an oodrl verb."""
    words = shlex.split(cmd)
    return words[1] if len(words) > 1 and words[0] == "oodrl" else None


def _stage_bodies(stages: dict[str, Any]) -> Iterator[tuple[str, dict[str, Any]]]:
    """(name, the mapping holding cmd and deps) for every stage, `foreach` ones included."""
    for name, stage in stages.items():
        yield name, stage["do"] if "foreach" in stage else stage


def component_files(project: Project, params: dict[str, Any], section: str) -> set[Path]:
    """Project files of the `module:Class` components a params section names (plugins)."""
    if section == "detectors":
        blocks = params.get("detectors")
    else:
        blocks = (params.get("anomaly") or {}).get(section)
    files: set[Path] = set()
    for block in (blocks or {}).values():
        path = block.get("class") if isinstance(block, dict) else None
        if isinstance(path, str) and (match := _IMPORT_PATH.fullmatch(path)):
            files |= project.closure([match.group(1)])
    return files


def required_deps(project: Project, stages: dict[str, Any], params: dict[str, Any]) -> dict:
    """Stage name -> the sorted code deps its command needs (what `write` lists)."""
    files: dict[str, set[Path]] = {}
    verbs: dict[str, str] = {}
    for name, body in _stage_bodies(stages):
        verb = stage_verb(body.get("cmd", ""))
        if verb is None:
            continue
        verbs[name] = verb
        files[name] = set(project.command_closure(verb))
        for section in COMPONENT_SECTIONS.get(verb, ()):
            files[name] |= component_files(project, params, section)
    every_stage = set().union(*files.values()) if files else set()
    for name, verb in verbs.items():
        if verb == CHECK_VERB:
            files[name] = every_stage
    return {name: _dep_entries(project, found) for name, found in files.items()}


def _dep_entries(project: Project, files: set[Path]) -> list[str]:
    """Sorted relative paths; a directory under src/ whose files are all listed is one entry."""
    covered = _covered_directories(project, files)
    entries = {project.relative(d) for d in covered}
    entries |= {project.relative(f) for f in files if not any(d in f.parents for d in covered)}
    return sorted(entries)


def _covered_directories(project: Project, files: set[Path]) -> set[Path]:
    """The largest directories under src/ (not src itself) whose every file is in `files`."""
    code_dir = project.root / CODE_DIR
    candidates = {p for f in files for p in f.parents if code_dir in p.parents}
    covered = {d for d in candidates if all(f in files for f in _dvc_files(d))}
    return {d for d in covered if not any(parent in covered for parent in d.parents)}


def _dvc_files(directory: Path) -> Iterator[Path]:
    """The files DVC hashes for a directory dep: .dvcignore keeps __pycache__ and *.pyc out."""
    for path in directory.rglob("*"):
        if path.is_file() and "__pycache__" not in path.parts and path.suffix != ".pyc":
            yield path


# -- dvc.yaml ----------------------------------------------------------------------------------
def _yaml():
    from ruamel.yaml import YAML

    # The layout dvc.yaml is written in: a round trip leaves every other byte as it was.
    rt = YAML()
    rt.indent(mapping=2, sequence=4, offset=2)
    rt.width = 4096
    rt.preserve_quotes = True
    return rt


def _load_params(path: Path) -> dict[str, Any]:
    """The params mapping, `extends` chain merged, unvalidated: only `class:` paths are read."""
    from oodrl.config import read_params_data

    return read_params_data(path)


def _load_pipeline(path: Path):
    if not path.is_file():
        raise ConfigError(f"{path}: no such pipeline file.")
    return _yaml().load(path.read_text())


def _with_code_deps(project: Project, deps: list[str], code: list[str]) -> list[str]:
    """Data deps as written, then the code deps."""
    return [d for d in deps if not project.is_code_dep(d)] + code


def rendered(pipeline_path: Path, params_path: Path) -> str:
    """dvc.yaml's text with every stage's code deps set to its command's closure."""
    document = _load_pipeline(pipeline_path)
    project = Project.of_pipeline(pipeline_path)
    stages = document.get("stages", {})
    required = required_deps(project, stages, _load_params(params_path))
    for name, body in _stage_bodies(stages):
        if name not in required:
            continue
        deps = _with_code_deps(project, list(body.get("deps") or []), required[name])
        if "deps" in body:
            body["deps"].clear()
            body["deps"].extend(deps)
        else:
            body["deps"] = deps
    buffer = io.StringIO()
    _yaml().dump(document, buffer)
    return buffer.getvalue()


def write(pipeline_path: Path, params_path: Path) -> bool:
    """Rewrite dvc.yaml's code deps; True if the file changed."""
    text = rendered(pipeline_path, params_path)
    if text == pipeline_path.read_text():
        return False
    pipeline_path.write_text(text)
    return True


def missing_deps(stages: dict[str, Any], required: dict[str, list[str]]) -> list[tuple[str, str]]:
    """(stage, path) for every required code dep that a stage's listed deps do not cover."""
    missing = []
    for name, body in _stage_bodies(stages):
        listed = [str(dep).rstrip("/") for dep in body.get("deps") or []]
        for needed in required.get(name, []):
            if not any(needed == dep or needed.startswith(f"{dep}/") for dep in listed):
                missing.append((name, needed))
    return missing


def stages_and_required(pipeline_path: Path, params_path: Path) -> tuple[dict, dict]:
    stages = _load_pipeline(pipeline_path).get("stages", {})
    project = Project.of_pipeline(pipeline_path)
    return stages, required_deps(project, stages, _load_params(params_path))


def check_coverage(pipeline_path: Path, params_path: Path) -> None:
    """Raise a one-line ConfigError when a stage's deps miss a file its command can execute."""
    missing = missing_deps(*stages_and_required(pipeline_path, params_path))
    if missing:
        raise ConfigError(_missing_message(pipeline_path, missing))


def check(pipeline_path: Path, params_path: Path) -> None:
    """Raise a one-line ConfigError unless dvc.yaml is exactly what `write` produces."""
    check_coverage(pipeline_path, params_path)
    if rendered(pipeline_path, params_path) != pipeline_path.read_text():
        raise ConfigError(
            f"{pipeline_path}: its code deps list more than the stages' import closures, or "
            f"in another order; run `oodrl pipeline write` to regenerate them."
        )


def _missing_message(pipeline_path: Path, missing: list[tuple[str, str]]) -> str:
    stage, needed = missing[0]
    more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
    return (
        f"{pipeline_path}: stage {stage} can execute {needed} but does not list it in its "
        f"deps{more}; run `oodrl pipeline write` to regenerate the code deps."
    )
