"""The DVC pipelines: one per environment, generated from one template, with exact code deps.

Every pipeline's dvc.yaml is rendered from `pipeline.yaml` beside this module: the root one
(the paper default, params.yaml) and `pipeline/<env>/dvc.yaml` for every environment directory
holding a params.yaml (which `extends` the shared one). `oodrl pipeline write` writes them all;
`oodrl pipeline check` (and the check_params stage) fails when a committed one differs.

Code deps (SPEC §12) are code stamps: the check_params stage depends on the package sources
as one directory (and on plugin files params names) and writes, per stage kind, a stamp
`data/code/<verb>[-<component>].txt` listing the sha256 of every file that kind's command can
execute; each stage depends on its stamp only. A stamp changes exactly when a file it lists
does (for cli.py: when the code its verb runs there does), so a code edit re-runs exactly the
stages that can execute it, and dvc.lock stays small.

A command's files are a static walk of every `import` statement (nested ones too: oodrl
imports lazily) and `module:Class` string from its verb in cli.py, plus the modules of the
components the stage instance builds: its detector (fit, score: unpickling imports it), its
injector and the environment's adapter (collection). The registries of those components name
every built-in by string; the walk does not follow those strings, or every stage would list
every component. It over-approximates otherwise: an extra re-run is safe, a missed one is not.
"""

from __future__ import annotations

import ast
import hashlib
import io
import itertools
import os
import re
import shlex
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

from oodrl.errors import ConfigError

CLI_MODULE = "oodrl.cli"
CODE_DIR = "src"  # the package sources' directory in the project
TEMPLATE = Path(__file__).with_name("pipeline.yaml")
ENVIRONMENTS_DIR = "pipeline"  # pipeline/<env>/{dvc.yaml, params.yaml}
#: The template of each detector's DVC file, layout.detector_pipeline(<detector>).
DETECTOR_TEMPLATE = Path(__file__).with_name("detector_pipeline.yaml")
#: A detector file's stages run in the pipeline's directory: detectors/<detector>/ -> ../..
WDIR = "../.."
PARAMS_FILE = "params.yaml"
#: Where the interpreter caches bytecode beside the sources: never a code dep (.dvcignore).
BYTECODE_DIR = "__pycache__"
CHECK_VERB = "check-params"
#: The stage every params file and source file reaches the others' stages by.
CHECK_STAGE = "check_params"
CHECKED = "data/params.checked"
CODE_STAMPS = "data/code"
#: An environment pipeline's stages read their params keys here: the params file merged with
#: the files it extends, written by check_params (DVC reads a key from one file only).
MERGED_PARAMS = "data/params.yaml"
#: Registries whose built-ins a stage builds one at a time (see `component_modules`).
PER_INSTANCE_REGISTRIES = frozenset({"oodrl.detectors", "oodrl.injectors", "oodrl.envs"})
#: The components a verb's stage instance builds; the first one is named by the verb's argument.
VERB_COMPONENTS: dict[str, tuple[str, ...]] = {
    "fit": ("detector",),
    "score": ("detector",),
    "collect-ood": ("injector", "environment"),
    "collect-id": ("environment",),
    "collect-eval": ("environment",),
    "collect-heldout": ("environment",),
    "impact-reference": ("environment",),
    "collect-tiers": ("injector", "environment"),
    "impact": ("injector", "environment"),
    "tier-metrics": ("detectors",),  # every benchmark detector, built for its latency
    "render": ("environment", "detectors"),  # it streams every benchmark detector (its cost)
    "metrics": ("detectors",),  # every benchmark detector, built for its latency
    "cells": ("detector",),
}

_DOTTED = r"[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*"
_IMPORT_PATH = re.compile(rf"({_DOTTED}):[A-Za-z_]\w*")
_IMPORT_PATH_PREFIX = re.compile(rf"({_DOTTED}):")
_VARIABLE = re.compile(r"\$\{([\w.]+)\}")


# -- the import closure --------------------------------------------------------------------
@dataclass(frozen=True)
class Project:
    """Where a pipeline's modules live: the package sources under `root/src`, and plugins in
    `base`, the pipeline's own directory (its stage commands run there; see registry.py).
    Paths in a pipeline are relative to `base`, as DVC reads them."""

    root: Path
    base: Path | None = None  # None: the root
    # module -> module_file's answer (a pipeline's stamps ask it tens of thousands of times):
    # a Project is asked about one state of the sources, no module added or removed meanwhile.
    _files: dict[str, Path | None] = field(
        default_factory=dict, init=False, compare=False, repr=False
    )

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

    @property
    def package_dir(self) -> Path:
        return self.root / CODE_DIR / CLI_MODULE.partition(".")[0]

    def source_files(self) -> list[Path]:
        """The package's files as the root's directory dep counts them: bytecode left out."""
        return sorted(
            path
            for path in self.package_dir.rglob("*")
            if path.is_file()
            and BYTECODE_DIR not in path.relative_to(self.package_dir).parts
            and path.suffix != ".pyc"
        )

    def module_file(self, module: str) -> Path | None:
        """The project file that `import module` executes, or None if it is not ours."""
        if module not in self._files:
            self._files[module] = self._find_module_file(module)
        return self._files[module]

    def _find_module_file(self, module: str) -> Path | None:
        relative = Path(*module.split("."))
        for source in (self.root / CODE_DIR, self.pipeline_dir):
            base = source / relative
            for candidate in (base.with_suffix(".py"), base / "__init__.py"):
                if candidate.is_file():
                    return candidate
        return None

    def relative(self, path: Path) -> str:
        return Path(os.path.relpath(path, self.pipeline_dir)).as_posix()

    def closure(
        self, modules: Iterable[str], known: dict[str, set[str]] | None = None
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
            if module in known:
                names: Iterable[str] = known[module]
            else:
                package = module if path.name == "__init__.py" else module.rpartition(".")[0]
                strings = module not in PER_INSTANCE_REGISTRIES
                names = _module_imports(path, path.stat().st_mtime_ns, package, strings)
            for name in names:
                pending.extend(_with_parents(name))
        return files

    def command_closure(self, verb: str) -> set[Path]:
        """The project files the CLI command `oodrl <verb>` can execute (components aside)."""
        cli = self.cli_file()
        names = _command_imports(cli, cli.stat().st_mtime_ns, verb)
        return self.closure([CLI_MODULE], known={CLI_MODULE: names})

    def command_source(self, verb: str) -> str:
        """The cli.py code `oodrl <verb>` runs, in file order: its stamp hashes this instead of
        the whole file, so editing another command re-runs none of this verb's stages."""
        cli = self.cli_file()
        return _command_source(cli, cli.stat().st_mtime_ns, verb)

    def cli_file(self) -> Path:
        cli = self.module_file(CLI_MODULE)
        if cli is None:
            raise ConfigError(f"{self.root}: no {CLI_MODULE} module under {CODE_DIR}/.")
        return cli


def _with_parents(module: str) -> list[str]:
    """`a.b.c` -> a, a.b, a.b.c: importing a submodule runs every parent's `__init__`."""
    parts = module.split(".")
    return [".".join(parts[: i + 1]) for i in range(len(parts))]


@cache
def _module_imports(path: Path, mtime_ns: int, package: str, strings: bool) -> frozenset[str]:
    """Every module a file's import statements (and strings) name, cached per file version."""
    tree = _parse(path)
    hooks = _lazy_hooks(path, tree)
    nodes = (n for top in tree.body if top not in hooks for n in ast.walk(top))
    return frozenset(imported_modules(nodes, package, strings))


#: PEP 562's module hooks: in a package's `__init__.py` they resolve names the module lacks
#: (oodrl's Python API, SPEC §25). Only `package.<missing name>` runs them and no stage does
#: that, so a stage's files and stamp leave them out: the API grows without re-running stages.
LAZY_HOOKS = frozenset({"__getattr__", "__dir__"})


def _lazy_hooks(path: Path, tree: ast.Module) -> list[ast.AST]:
    if path.name != "__init__.py":
        return []
    return [
        node
        for node in tree.body
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.name in LAZY_HOOKS
    ]


def stage_source(path: Path) -> bytes:
    """A file's bytes as a stage's stamp hashes them: a package `__init__.py` less its lazy
    hooks (and the blank lines they leave at its end), so adding them changes no stamp."""
    data = path.read_bytes()
    hooks = _lazy_hooks(path, _parse(path))
    if not hooks:
        return data
    lines = data.decode().splitlines(keepends=True)
    dropped = {i for node in hooks for i in range(node.lineno - 1, node.end_lineno or 0)}
    kept = "".join(line for i, line in enumerate(lines) if i not in dropped)
    return (kept.rstrip("\n") + "\n").encode()


#: A line as `ast.get_source_segment` splits source: ended by \r\n, \r or \n (not \f).
_LINE = re.compile(r"[^\r\n]*(?:\r\n|\r|\n)|[^\r\n]+\Z")


def _source_segment(lines: list[str], node: ast.AST) -> str:
    """`ast.get_source_segment(source, node, padded=True)` of a source split into `lines` once:
    ast splits the whole source again for each node, in Python, and cli.py has hundreds of them
    (most of `oodrl check-params --code`'s time went there)."""
    first, last = node.lineno - 1, node.end_lineno - 1
    start, end = node.col_offset, node.end_col_offset
    head = lines[first].encode()
    if first == last:
        return head[start:end].decode()
    padding = re.sub(r"[^\f\t]", " ", head[:start].decode())
    tail = lines[last].encode()[:end].decode()
    return "".join([padding + head[start:].decode(), *lines[first + 1 : last], tail])


@cache
def _command_imports(cli: Path, mtime_ns: int, verb: str) -> frozenset[str]:
    """The modules cli.py's code for `oodrl <verb>` imports, once a cli.py version and verb."""
    nodes = (node for top in _command_nodes(_parse(cli), verb) for node in ast.walk(top))
    return frozenset(imported_modules(nodes, CLI_MODULE.rpartition(".")[0]))


@cache
def _command_source(cli: Path, mtime_ns: int, verb: str) -> str:
    """`Project.command_source`, once a cli.py version and verb: every stage kind of a verb
    asks it."""
    lines = _LINE.findall(cli.read_text())
    nodes = sorted(_command_nodes(_parse(cli), verb), key=lambda node: node.lineno)
    return "\n".join(_source_segment(lines, node) for node in nodes)


@cache
def _parse_cached(path: Path, mtime_ns: int) -> ast.Module:
    return ast.parse(path.read_text(), filename=str(path))


def _parse(path: Path) -> ast.Module:
    return _parse_cached(path, path.stat().st_mtime_ns)


def imported_modules(nodes: Iterable[ast.AST], package: str, strings: bool = True) -> set[str]:
    """Module names that `nodes` import: statements, import_module calls and, with `strings`,
    import-path strings. `from a import b` yields `a` and `a.b` (b may be a submodule); names
    that are not project modules are dropped later, when they resolve to no file."""
    names: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = _absolute(node.module, node.level, package)
            names.add(base)
            names.update(f"{base}.{alias.name}" for alias in node.names if alias.name != "*")
        elif isinstance(node, ast.Call) and _called_name(node) == "import_module" and node.args:
            argument = node.args[0]
            if isinstance(argument, ast.Constant) and isinstance(argument.value, str):
                names.add(argument.value)
        elif strings and (module := _string_import(node)) is not None:
            names.add(module)
    return names


def _string_import(node: ast.AST) -> str | None:
    """The module a registry's "pkg.module:Class" string names (an f-string's literal prefix
    included), for a later import."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        match = _IMPORT_PATH.fullmatch(node.value)
        return match.group(1) if match else None
    if isinstance(node, ast.JoinedStr) and node.values:
        first = node.values[0]  # f"oodrl.metrics.aggregate:{name}"
        if isinstance(first, ast.Constant) and isinstance(first.value, str):
            match = _IMPORT_PATH_PREFIX.match(first.value)
            return match.group(1) if match else None
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


def _command_nodes(tree: ast.Module, verb: str) -> list[ast.AST]:
    """The top-level statements of cli.py that `oodrl <verb>` runs: module-level code, the
    app's callbacks (they run before every command), the verb's function and every module-level
    function these reach by name. Other commands' bodies do not run; their registration does, at
    import, but it cannot change what this verb computes (and if it fails, every command fails).
    """
    functions = {
        node.name: node
        for node in tree.body
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
    }
    roots: list[ast.AST] = [node for node in tree.body if node not in functions.values()]
    roots += [node for node in functions.values() if _is_callback(node)]
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
    return reached


def _is_callback(function: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    """`@app.callback()`: typer runs it before every command."""
    return any(
        isinstance(d, ast.Call) and _called_name(d) == "callback" for d in function.decorator_list
    )


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


# -- stage kinds and their code ----------------------------------------------------------------
def stage_kind(cmd: str) -> tuple[str, str | None] | None:
    """`oodrl fit kde …` -> ('fit', 'kde'); None for a command that is not an oodrl verb."""
    words = shlex.split(cmd)
    if len(words) < 2 or words[0] != "oodrl":
        return None
    verb, kinds = words[1], VERB_COMPONENTS.get(words[1], ())
    named = bool(kinds) and kinds[0] in ("detector", "injector") and len(words) > 2
    return verb, words[2] if named else None


def stamp_path(verb: str, component: str | None) -> str:
    """The code stamp of a stage kind (for a dvc.yaml template, `component` may be `${item}`)."""
    return f"{CODE_STAMPS}/{verb}{f'-{component}' if component else ''}.txt"


def component_modules(verb: str, name: str | None, params: dict[str, Any]) -> list[str]:
    """The modules of the components a stage instance of `verb` builds (SPEC §12): a plugin's
    `class:` path in params, else the registered path of `name` (or of env.id)."""
    modules = []
    for kind in VERB_COMPONENTS.get(verb, ()):
        if kind == "detectors":
            names = (params.get("benchmark") or {}).get("detectors") or []
            paths = [_component_path("detector", each, params) for each in names]
        else:
            paths = [_component_path(kind, name, params)]
        if kind in ("detector", "detectors"):
            from oodrl.detectors import DETECTORS

            # The registry passes every detector class it builds through its adapter (the
            # library wrapper, SPEC §17), whose module a string names.
            paths.append(DETECTORS.adapt)
        modules += [path.partition(":")[0] for path in paths]
    return modules


def _component_path(kind: str, name: str | None, params: dict[str, Any]) -> str:
    if kind == "environment":
        from oodrl.envs import ENVIRONMENTS

        return ENVIRONMENTS.path((params.get("env") or {}).get("id", "LunarLander-v3"))
    if kind == "detector":
        from oodrl.detectors import DETECTORS as registry

        blocks = params.get("detectors") or {}
    else:
        from oodrl.injectors import INJECTORS as registry

        blocks = (params.get("anomaly") or {}).get("injectors") or {}
    block = blocks.get(name) or {}
    return block.get("class") or registry.path(str(name))


def kind_files(project: Project, verb: str, name: str | None, params: dict) -> set[Path]:
    """Every project file a stage instance `oodrl <verb> <name> …` can execute."""
    return project.command_closure(verb) | project.closure(component_modules(verb, name, params))


def stamp_text(project: Project, files: set[Path], verb: str) -> str:
    """`sha256  path` per file, sorted by path: content only, so the stamp is reproducible.
    cli.py's line hashes only the code `verb` runs there (`Project.command_source`)."""
    cli = project.cli_file()

    def content(file: Path) -> bytes:
        return project.command_source(verb).encode() if file == cli else stage_source(file)

    paths = sorted((project.relative(f), f) for f in files)
    return "".join(f"{hashlib.sha256(content(f)).hexdigest()}  {p}\n" for p, f in paths)


def plugin_files(project: Project, params: dict[str, Any]) -> set[Path]:
    """Project files outside the package that params' `class:` paths import (plugins)."""
    blocks = [
        *(params.get("detectors") or {}).values(),
        *((params.get("anomaly") or {}).get("injectors") or {}).values(),
    ]
    modules = [
        match.group(1)
        for block in blocks
        if isinstance(block, dict)
        and isinstance(block.get("class"), str)
        and (match := _IMPORT_PATH.fullmatch(block["class"]))
    ]
    package = project.package_dir
    return {f for f in project.closure(modules) if package not in f.parents}


# -- stage instances -----------------------------------------------------------------------------
def _stage_bodies(stages: dict[str, Any]) -> Iterator[tuple[str, dict[str, Any]]]:
    """(name, the mapping holding cmd and deps) for every stage, `foreach` ones included."""
    for name, stage in stages.items():
        yield name, stage["do"] if "foreach" in stage else stage


def _values(spec: Any, params: dict[str, Any]) -> list:
    """A fan-out list: written out, or `${a.b}` naming a params key."""
    if isinstance(spec, str) and (match := _VARIABLE.fullmatch(spec)):
        value: Any = params
        for key in match.group(1).split("."):
            value = value[key]
        return list(value)
    return list(spec)


def stage_commands(stages: dict[str, Any], params: dict[str, Any]) -> Iterator[str]:
    """Every stage instance's command, `foreach` and `matrix` expanded."""
    for stage in stages.values():
        if "foreach" in stage:
            items = [{"item": v} for v in _values(stage["foreach"], params)]
            cmd = stage["do"]["cmd"]
        elif "matrix" in stage:
            axes = {k: _values(v, params) for k, v in stage["matrix"].items()}
            items = [
                {f"item.{k}": v for k, v in zip(axes, combo, strict=True)}
                for combo in itertools.product(*axes.values())
            ]
            cmd = stage["cmd"]
        else:
            items, cmd = [{}], stage["cmd"]
        for item in items:
            yield _VARIABLE.sub(lambda m, item=item: str(item.get(m.group(1), m.group(0))), cmd)


def write_stamps(pipeline_path: Path, params_path: Path, code_dir: Path) -> list[Path]:
    """Write one code stamp per stage kind of the pipeline into `code_dir` (the pipeline's
    CODE_STAMPS, as the command runs in its directory); remove stale ones."""
    from oodrl.config import read_params_data
    from oodrl.io.fileio import atomic_write_text
    from oodrl.io.layout import detector_pipeline

    project = Project.of_pipeline(pipeline_path)
    params = read_params_data(params_path)
    files = [pipeline_path] + [
        project.pipeline_dir / detector_pipeline(d) for d in params["benchmark"]["detectors"]
    ]
    kinds = {
        kind
        for path in files
        for cmd in stage_commands(_load_pipeline(path)["stages"], params)
        if (kind := stage_kind(cmd)) is not None and kind[0] != CHECK_VERB
    }
    written = []
    for verb, name in sorted(kinds, key=str):
        path = code_dir / Path(stamp_path(verb, name)).name
        text = stamp_text(project, kind_files(project, verb, name, params), verb)
        if not path.is_file() or path.read_text() != text:
            atomic_write_text(path, text)
        written.append(path)
    for stale in set(code_dir.glob("*.txt")) - set(written):
        stale.unlink()  # a component no longer in the benchmark
    return written


# -- rendering the template ----------------------------------------------------------------------
#: How a pipeline of recorded data's DVC files differ from the templates' (SPEC §18).
RECORDED_TEMPLATE = Path(__file__).with_name("recorded_pipeline.yaml")
#: The policy file the template's commands read (a pipeline of recorded data has none).
POLICY = "models/policy.pt"


def _yaml():
    from ruamel.yaml import YAML

    rt = YAML()
    rt.indent(mapping=2, sequence=4, offset=2)
    rt.width = 4096
    rt.preserve_quotes = True
    return rt


@cache
def _parsed_template(path: Path):
    return _yaml().load(path.read_text())


def _template(path: Path):
    """A template's round-trip document, the caller's to edit: parsed once a process and
    copied (`oodrl pipeline write` renders it for each of the suite's pipelines, and a copy
    takes a fraction of ruamel's parse)."""
    import copy

    return copy.deepcopy(_parsed_template(path))


def _load_pipeline(path: Path):
    """A DVC file's data, read as DVC reads it (YAML 1.2: `on` and `no` are strings, `1e-3` a
    number), by ruamel's libyaml-based loader: the stamps need no comments, and the round-trip
    loader took half of `oodrl check-params --code` in an environment's 26 DVC files."""
    from ruamel.yaml import YAML

    if not path.is_file():
        raise ConfigError(f"{path}: no such pipeline file.")
    return YAML(typ="safe").load(path.read_text())


def _params_chain(params_path: Path) -> list[Path]:
    """The params file and the files it `extends`, nearest first."""
    from oodrl.config import EXTENDS_KEY
    from oodrl.io import yamlio

    chain = [params_path.resolve()]
    while True:
        data = yamlio.load(chain[-1].read_text()) if chain[-1].is_file() else None
        if not isinstance(data, dict) or EXTENDS_KEY not in data:
            return chain
        base = (chain[-1].parent / str(data[EXTENDS_KEY])).resolve()
        if base in chain:
            return chain
        chain.append(base)


def rendered(pipeline_dir: Path, root: Path) -> str:
    """The dvc.yaml of the pipeline in `pipeline_dir` (the root or an environment's)."""
    from oodrl.config import read_params_data

    project = Project(root.resolve(), pipeline_dir.resolve())
    params_path = pipeline_dir / PARAMS_FILE
    params = read_params_data(params_path)
    document = _template(TEMPLATE)
    stages = document["stages"]
    if is_recorded(params):
        _as_recorded(stages)
    _write_out_lists(stages, params)
    for _, body in _stage_bodies(stages):
        kind = stage_kind(body["cmd"])
        if kind is not None and kind[0] == CHECK_VERB:
            # The root depends on the package directory, which its .dvcignore rids of
            # bytecode. DVC applies no .dvcignore to a dep outside the project, so an
            # environment's project lists the package's files one by one: a directory dep would
            # count the __pycache__ of whoever ran the code, and no clone would match the lock.
            root = project.pipeline_dir == project.root
            package = [project.package_dir] if root else project.source_files()
            code = [*package, *sorted(plugin_files(project, params))]
            body["deps"].clear()
            body["deps"].extend(project.relative(p) for p in (*_params_chain(params_path), *code))
    _add_stamps(stages)
    if project.pipeline_dir != project.root:
        _read_merged_params(stages, params)
        # DVC finds the Vega-Lite template files from the root only: environments show their
        # PNG figures (the root's page draws the paper default's interactive views).
        document["plots"] = ["reports/figures"]
    return _dumped(document)


def rendered_detector(pipeline_dir: Path, root: Path, detector: str) -> str:
    """detectors/<detector>/dvc.yaml of the pipeline in `pipeline_dir`."""
    from oodrl.config import read_params_data

    params = read_params_data(pipeline_dir / PARAMS_FILE)
    project = Project(root.resolve(), pipeline_dir.resolve())
    policy = policy_file(detector, params, project)
    return _detector_text(pipeline_dir, root, params, policy).replace("${detector}", detector)


def _detector_text(
    pipeline_dir: Path, root: Path, params: dict[str, Any], policy: str | None
) -> str:
    """The detector template rendered for a pipeline, `${detector}` left in: every detector of
    the pipeline whose fit reads `policy` (None: no policy file) has this text, its name put in.
    Rendering it once per policy rather than per detector is what makes `oodrl pipeline write`
    fast: the round trip through ruamel (comments kept) is most of its time."""
    document = _template(DETECTOR_TEMPLATE)
    stages = document["stages"]
    if is_recorded(params):
        _as_recorded(stages)
    _write_out_lists(stages, params)
    _add_stamps(stages)
    _add_policy_dep(stages, policy)
    if pipeline_dir.resolve() != root.resolve():
        _read_merged_params(stages, params)
    for name, body in _stage_bodies(stages):
        if "foreach" in stages[name]:
            stages[name]["foreach"] = _flow(_values(stages[name]["foreach"], params))
        body.insert(0, "wdir", WDIR)
    return _dumped(document)


def policy_file(detector: str, params: dict[str, Any], project: Project) -> str | None:
    """The policy file a detector's fit reads (SPEC §20), relative to the pipeline's directory,
    or None: a `PolicyDetector`'s `policy` parameter, its params' value or else its class's
    default (`POLICY`).

    Only oodrl's own classes are imported to ask (light: no torch, no library); a library's
    class (PyOD's, scikit-learn's: seconds to import) is not, and cannot subclass
    PolicyDetector. A plugin of the project (a `class:` module in the pipeline's directory) is
    not imported either: its fit reads a policy file when its params name one in `policy`.
    """
    from oodrl.registry import import_path

    path = _component_path("detector", detector, params)
    module = path.partition(":")[0]
    block = (params.get("detectors") or {}).get(detector) or {}
    named = block.get("policy") if isinstance(block.get("policy"), str) else None
    if module.partition(".")[0] != CLI_MODULE.partition(".")[0]:
        return named if project.module_file(module) is not None else None
    from oodrl.detectors.policy_view import PolicyDetector

    cls = import_path(path)
    if not (isinstance(cls, type) and issubclass(cls, PolicyDetector)):
        return None
    return named or str(cls.policy)


def _add_policy_dep(stages: dict[str, Any], policy: str | None) -> None:
    """A detector that reads the policy (`policy_file`) has its fit stage depend on the file:
    a retrained policy refits it (the fitted detector keeps the policy's network)."""
    if policy is None:
        return
    for _, body in _stage_bodies(stages):
        kind = stage_kind(body["cmd"])
        if kind is not None and kind[0] == "fit" and policy not in body["deps"]:
            body["deps"].append(policy)


def is_recorded(params: dict[str, Any]) -> bool:
    """Whether params are a pipeline of recorded data's (`oodrl new --dataset`, SPEC §18)."""
    from oodrl.protocol.recorded import SOURCE

    train = (params.get("policy") or {}).get("train") or {}
    return train.get("source") == SOURCE


def _as_recorded(stages: dict[str, Any]) -> None:
    """A template's stages as a pipeline of recorded data has them (RECORDED_TEMPLATE): the
    stages that need a policy or a simulator dropped, the clean sets imported, and the policy
    file named by the commands that still take one replaced."""
    variant = _template(RECORDED_TEMPLATE)  # a copy: its stages move into the pipeline
    kept = None
    for name in list(stages):
        if name in variant["drop"]:
            if kept is not None:  # the comment before the next stage is kept, not this one's
                _set_tail(stages[kept], _tail(stages[name]))
            del stages[name]
            continue
        if name in variant["stages"]:
            replacement = variant["stages"][name]
            _set_tail(replacement, _tail(stages[name]))
            stages[name] = replacement
        kept = name
    policy = str(variant["policy"])
    unscored = variant["unscored"]
    removed_outs = {simulated["out"] for simulated in unscored.values() if "out" in simulated}
    for _, body in _stage_bodies(stages):
        for option, simulated in unscored.items():
            argument = f" {option} {simulated['argument']}"
            if argument in body["cmd"]:
                body["cmd"] = _replaced(body["cmd"], argument, "")
                body["deps"].remove(simulated["dep"])
                if "out" in simulated:
                    body["outs"].remove(simulated["out"])
        # A stage reading a store no stage writes any more (the cells' held-out scores) reads
        # without it.
        deps = body.get("deps") or []
        deps[:] = [dep for dep in deps if dep not in removed_outs]
        if POLICY in body["cmd"]:
            body["cmd"] = _replaced(body["cmd"], POLICY, policy)
        deps = body.get("deps") or []
        for i, dep in enumerate(deps):
            if dep == POLICY:
                deps[i] = policy


#: A template's dep or out naming one of these is written out once per listed component.
EACH = {"${each_detector}": "detectors", "${each_injector}": "injectors"}


def _write_out_lists(stages: dict[str, Any], params: dict[str, Any]) -> None:
    """Each dep or out naming `${each_detector}` or `${each_injector}` written out once per
    benchmark detector or injector (detector-major when it names both): every dep is then a
    stage's own output (SPEC §23), never a directory several stages fill."""
    benchmark = params.get("benchmark") or {}
    lists = {marker: list(benchmark.get(key) or []) for marker, key in EACH.items()}
    for _, body in _stage_bodies(stages):
        for section in ("deps", "outs"):
            entries = body.get(section)
            if not entries:
                continue
            # The blank line and comments after a sequence's last entry (before the next stage)
            # stay after its last entry.
            tail = entries.ca.items.pop(len(entries) - 1, None)
            written = []
            for entry in entries:
                path = entry if isinstance(entry, str) else next(iter(entry))
                paths = [path]
                for marker, names in lists.items():
                    if marker in path:
                        paths = [p.replace(marker, name) for p in paths for name in names]
                if paths == [path]:
                    written.append(entry)
                else:
                    written += [p if isinstance(entry, str) else {p: entry[path]} for p in paths]
            entries[:] = written
            if tail is not None:
                entries.ca.items[len(entries) - 1] = tail


def _tail_holder(node) -> tuple[Any, Any]:
    """(collection, key) of the last scalar under `node`: ruamel keeps the blank lines and
    comments between one stage and the next there."""
    from ruamel.yaml.comments import CommentedMap, CommentedSeq

    while True:
        key = list(node)[-1] if isinstance(node, CommentedMap) else len(node) - 1
        if not isinstance(node[key], CommentedMap | CommentedSeq):
            return node, key
        node = node[key]


def _tail(node) -> Any:
    holder, key = _tail_holder(node)
    return holder.ca.items.get(key)


def _set_tail(node, comment: Any) -> None:
    holder, key = _tail_holder(node)
    if comment is None:
        holder.ca.items.pop(key, None)
    else:
        holder.ca.items[key] = comment


def _replaced(text: str, old: str, new: str) -> str:
    """`text` with its one `old` replaced by `new`; a folded scalar keeps its line breaks."""
    result = type(text)(text.replace(old, new))
    folds = getattr(text, "fold_pos", None)
    if folds:
        at, end = text.index(old), text.index(old) + len(old)
        # A fold inside the replaced text goes with it; those after it move.
        result.fold_pos = [p if p < at else p + len(new) - len(old) for p in folds
                           if not at <= p < end]  # fmt: skip
    return result


def _add_stamps(stages: dict[str, Any]) -> None:
    """Each oodrl stage depends on its kind's code stamp, right after CHECKED."""
    for _, body in _stage_bodies(stages):
        kind = stage_kind(body["cmd"])
        if kind is not None and kind[0] != CHECK_VERB:
            deps = body["deps"]
            deps.insert(deps.index(CHECKED) + 1, stamp_path(*kind))


def _dumped(document) -> str:
    buffer = io.StringIO()
    _yaml().dump(document, buffer)
    return buffer.getvalue()


def _read_merged_params(stages: dict[str, Any], params: dict[str, Any]) -> None:
    """An environment's pipeline: stages read params keys from the merged file check_params
    writes, and fan out over the lists written out (DVC's `${}` reads only the local file)."""
    for name, stage in stages.items():
        if "foreach" in stage:
            stage["foreach"] = _flow(_values(stage["foreach"], params))
        if "matrix" in stage:
            for axis, spec in stage["matrix"].items():
                stage["matrix"][axis] = _flow(_values(spec, params))
        body = stage["do"] if "foreach" in stage else stage
        if name == CHECK_STAGE:
            body["cmd"] += f" --merged {MERGED_PARAMS}"
            # Tracked by git, as params.yaml is: a fresh clone's `dvc repro --pull
            # --allow-missing` reads every stage's params from it (DVC counts a params file
            # that is missing as changed, the first stage reading it would run).
            body["outs"].insert(1, {MERGED_PARAMS: {"persist": True, "cache": False}})
        elif "params" in body:
            body["params"] = [{MERGED_PARAMS: list(body["params"])}]


def _flow(values: list):
    """A list written on one line, as `[a, b]`."""
    from ruamel.yaml.comments import CommentedSeq

    seq = CommentedSeq(values)
    seq.fa.set_flow_style()
    return seq


def pipeline_dirs(root: Path) -> list[Path]:
    """The root, then every environment directory holding a params file; never a hidden one
    (`oodrl new` stages a pipeline in `.NAME.new-<pid>` until it renames it into place)."""
    found = (p.parent for p in (root / ENVIRONMENTS_DIR).glob(f"*/{PARAMS_FILE}"))
    return [root, *sorted(d for d in found if not d.name.startswith("."))]


#: The suite's own pipeline: the leaderboard over every environment's results (SPEC §12).
#: Outside the root pipeline, so the root `dvc repro` stays the paper's default alone.
SUITE_DIR = Path(ENVIRONMENTS_DIR) / "suite"


def rendered_suite(root: Path) -> str:
    """pipeline/suite/dvc.yaml: one stage reading every environment's results."""
    project = Project(root.resolve(), (root / SUITE_DIR).resolve())
    from oodrl.suite.environments import suite_runs

    # The suite's runs only, as the leaderboard reads them: a pipeline `oodrl new` made stays
    # off the leaderboard unless it is added to oodrl.suite.environments's PIPELINE_DIRS (SPEC §18).
    suite = {(root / d).resolve() for d in suite_runs().values()}
    environments = [d for d in pipeline_dirs(root) if d.resolve() in suite]
    from oodrl.metrics.tier_results import TIER_RESULTS
    from oodrl.report.leaderboard_page import PAGE_TEMPLATE

    # The page's template is code the stage runs, though no import names it.
    template = project.package_dir / PAGE_TEMPLATE.relative_to(PAGE_TEMPLATE.parents[1])
    code = sorted(project.relative(p) for p in {*project.command_closure("leaderboard"), template})
    stage = {
        "cmd": "oodrl leaderboard --out reports",
        "deps": [
            *code,
            *(
                project.relative(d.resolve() / "reports" / results)
                for d in environments
                # The suite is built once every pipeline is current (`oodrl.suite.run`): its
                # tier results are then the JSON, never a protocol-4 pipeline's YAML.
                for results in ("results.yaml", TIER_RESULTS.name)
            ),
        ],
        "params": [
            {
                project.relative(root.resolve() / PARAMS_FILE): [
                    "seed",
                    "metrics.n_boot",
                    "metrics.ci",
                ]
            }
        ],
        # Every output is a small result, tracked by git so that every clone shows the
        # leaderboard without computing it (SPEC §21).
        "outs": [
            {f"reports/leaderboard.{kind}": {"cache": False}}
            for kind in ("md", "yaml", "png", "json", "html")
        ],
        "metrics": [{"reports/metrics.json": {"cache": False}}],
    }
    header = (
        "# The suite's leaderboard (SPEC §12), generated by `oodrl pipeline write`: never edit\n"
        "# by hand. A DVC project of its own, like each environment's pipeline: `oodrl suite\n"
        "# run` builds every pipeline, then this one.\n"
    )
    buffer = io.StringIO()
    _yaml().dump({"stages": {"leaderboard": stage}}, buffer)
    return header + buffer.getvalue()


def pipeline_files(pipeline_dir: Path, root: Path) -> dict[Path, str]:
    """A pipeline's generated DVC files and their text: its dvc.yaml, then one per detector."""
    from oodrl.config import read_params_data
    from oodrl.io.layout import detector_pipeline

    params = read_params_data(pipeline_dir / PARAMS_FILE)
    project = Project(root.resolve(), pipeline_dir.resolve())
    files = {pipeline_dir / "dvc.yaml": rendered(pipeline_dir, root)}
    texts: dict[str | None, str] = {}  # _detector_text by policy file: a few, not a detector's
    for detector in params["benchmark"]["detectors"]:
        policy = policy_file(detector, params, project)
        if policy not in texts:
            texts[policy] = _detector_text(pipeline_dir, root, params, policy)
        text = texts[policy].replace("${detector}", detector)
        files[pipeline_dir / detector_pipeline(detector)] = text
    return files


def _stale_files(pipeline_dir: Path, files: Mapping[Path, str]) -> list[Path]:
    """Generated detector files of detectors no longer in the benchmark."""
    from oodrl.io.layout import DETECTOR_PIPELINES

    found = sorted((pipeline_dir / DETECTOR_PIPELINES).glob("*/dvc.yaml"))
    return [path for path in found if path not in files]


def project_dirs(root: Path) -> list[Path]:
    """Every DVC project of the suite: the root, each environment's pipeline, the suite's."""
    return [*pipeline_dirs(root), root / SUITE_DIR]


#: The directories that several stages fill, an output each (protocol 4 reads none of them
#: whole: every dep names one stage's output, SPEC §23). Git ignores each as a whole
#: (FILLED_DIRS_IGNORED, in every project's .gitignore), so DVC writes no .gitignore inside them
#: and a clone holds no directory for them: a fresh clone's `dvc repro --pull --allow-missing`
#: counts a missing output as missing, never a git-made directory as present and changed
#: (SPEC §21). The faults' impact records (data/impact) are git-tracked (SPEC §23).
FILLED_DIRS = ("cells", "models/detectors", "scores")
FILLED_DIRS_IGNORED = (
    "# Directories several stages fill, ignored whole (oodrl.suite.pipeline.FILLED_DIRS: why).\n"
    + "".join(f"/{directory}/\n" for directory in FILLED_DIRS)
)

#: What makes a pipeline directory its own DVC project (a DVC subrepo), and the text of each.
#: The root repository then indexes the paper's default pipeline alone: its `dvc status`,
#: `dvc repro` and `dvc exp` neither list nor re-read the other environments' ~1,100 stages.
#: Every project keeps its outputs and run-cache in the root's cache, so a stage computed by
#: any of them, on any machine sharing a remote, is restored by all.
SUBREPO_FILES: dict[str, str] = {
    ".dvc/config": (
        "# Generated by `oodrl pipeline write`: this pipeline is a DVC project of its own (SPEC\n"
        "# §12), sharing the root's cache (paths are relative to this .dvc directory).\n"
        "[core]\n"
        "    analytics = false\n"
        "    autostage = true\n"
        "[cache]\n"
        "    dir = ../../../.dvc/cache\n"
        "[plots]\n"
        "    html_template = ../../../src/oodrl/report/vega/offline_page.html\n"
    ),
    ".dvc/.gitignore": "/config.local\n/tmp\n/cache\n",
    ".gitignore": "# Generated by `oodrl pipeline write`.\n" + FILLED_DIRS_IGNORED,
    ".dvcignore": (
        "# Byte-compiled files: the code deps are the sources, not what the interpreter caches.\n"
        f"{BYTECODE_DIR}/\n*.pyc\n"
    ),
}


def subrepo_files(directory: Path, root: Path) -> dict[Path, str]:
    """The files that make `directory` a DVC project of its own (none for the root)."""
    if directory.resolve() == root.resolve():
        return {}
    return {directory / name: text for name, text in SUBREPO_FILES.items()}


def _generated(root: Path) -> Iterator[tuple[Path, str]]:
    """Every generated DVC file and the text it must have."""
    for directory in pipeline_dirs(root):
        yield from pipeline_files(directory, root).items()
    yield root / SUITE_DIR / "dvc.yaml", rendered_suite(root)
    for directory in project_dirs(root):
        yield from subrepo_files(directory, root).items()


def write(root: Path) -> list[Path]:
    """Write every pipeline's DVC files from the template; the files that changed or went.

    A detector dropped from the benchmark loses its DVC file and lock (git keeps both)."""
    generated = dict(_generated(root))
    changed = []
    for path, text in generated.items():
        if not path.is_file() or path.read_text() != text:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
            changed.append(path)
    for directory in pipeline_dirs(root):
        for stale in _stale_files(directory, generated):
            for path in (stale, stale.with_suffix(".lock")):
                path.unlink(missing_ok=True)
            changed.append(stale)
    return changed


def check_pipeline(pipeline_path: Path) -> None:
    """Raise a one-line ConfigError unless a pipeline's DVC files (its dvc.yaml and its
    detectors' files) are what `oodrl pipeline write` writes."""
    project = Project.of_pipeline(pipeline_path)
    files = pipeline_files(project.pipeline_dir, project.root)
    for path, expected in files.items():
        text = path.read_text() if path.is_file() else ""
        if expected != text:
            where = os.path.relpath(path.resolve(), project.root)
            raise ConfigError(
                f"{where} is not what the template {TEMPLATE.name} and its params give "
                f"({_first_difference(expected, text)}); run `oodrl pipeline write` "
                f"(never edit a generated DVC file by hand)."
            )
    for path, expected in subrepo_files(project.pipeline_dir, project.root).items():
        if not path.is_file() or path.read_text() != expected:
            where = os.path.relpath(path.resolve(), project.root)
            raise ConfigError(
                f"{where} is missing or not what `oodrl pipeline write` writes (it makes the "
                f"pipeline a DVC project of its own); run `oodrl pipeline write`."
            )
    stale = _stale_files(project.pipeline_dir, files)
    if stale:
        where = os.path.relpath(stale[0].resolve(), project.root)
        raise ConfigError(
            f"{where} belongs to a detector no longer in benchmark.detectors; run `oodrl "
            f"pipeline write`."
        )


def _first_difference(expected: str, text: str) -> str:
    """The first line one text has and the other lacks, e.g. a plugin file params now name."""
    missing = [line for line in expected.splitlines() if line not in text.splitlines()]
    if missing:
        return f"missing {missing[0].strip()!r}"
    extra = [line for line in text.splitlines() if line not in expected.splitlines()]
    return f"unexpected {extra[0].strip()!r}" if extra else "lines in another order"


def check_files(root: Path) -> None:
    """Raise a one-line ConfigError unless every generated DVC file of the suite is what
    `oodrl pipeline write` writes (the locks are `oodrl.suite.migration.check`'s)."""
    for directory in pipeline_dirs(root):
        check_pipeline(directory / "dvc.yaml")
    for path, expected in subrepo_files(root / SUITE_DIR, root).items():
        if not path.is_file() or path.read_text() != expected:
            raise ConfigError(
                f"{path.relative_to(root)} is missing or stale; run `oodrl pipeline write`."
            )
    suite = root / SUITE_DIR / "dvc.yaml"
    text = suite.read_text() if suite.is_file() else ""
    if text != rendered_suite(root):
        raise ConfigError(
            f"{SUITE_DIR / 'dvc.yaml'} is not what `oodrl pipeline write` writes "
            f"({_first_difference(rendered_suite(root), text)}); run `oodrl pipeline write`."
        )


def suite_pipelines(root: Path) -> list[str]:
    """The root's pipeline (the paper's default) and every run the suite's leaderboard reads (the
    pipelines whose results its generated dvc.yaml depends on), relative to the root ('.' is the
    root's own). A pipeline `oodrl new` made, or a policy not yet in
    `oodrl.suite.environments.MORE_POLICIES`, is not the suite's: build it with `dvc repro` in its
    directory."""
    import yaml

    suite = root / SUITE_DIR / "dvc.yaml"
    if not suite.is_file():
        raise ConfigError(f"--root {root}: not an oodrl suite (no {SUITE_DIR}/dvc.yaml); pass the "
                          "repository's root, where `oodrl pipeline write` put it.")  # fmt: skip
    stage = yaml.safe_load(suite.read_text())["stages"]["leaderboard"]
    results = [Path(d) for d in stage["deps"] if d.endswith("/reports/results.yaml")]
    runs = {(root / SUITE_DIR / d).resolve().parent.parent.relative_to(root) for d in results}
    return [".", *sorted(r.as_posix() for r in runs)]
