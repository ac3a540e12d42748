"""The reference pages, generated from the code at build time: every command of the `oodrl` app
(click's own help records, grouped by the panels `oodrl --help` shows) and every key of the
params schema (`oodrl.config.Params`, walked recursively) with its default and range, plus the
parameters of every registered detector and injector."""

from __future__ import annotations

import ast
import inspect
import re
import textwrap
from pathlib import Path
from types import NoneType, UnionType
from typing import Any, Literal, Union, get_args, get_origin

ROOT = Path(__file__).resolve().parents[2]
#: The params blocks that hold one block of keys per component, listed after the schema.
COMPONENT_BLOCKS = {"detectors": "detectors", "anomaly.injectors": "injectors"}
#: typer's name for the panel of commands given none.
DEFAULT_PANEL = "Commands"


# -- markdown helpers --------------------------------------------------------------------------
def escape(text: str) -> str:
    """Text that renders as itself: markdown's specials escaped outside `code` spans."""
    parts = re.split(r"(`[^`]*`)", text)
    for i in range(0, len(parts), 2):
        part = parts[i].replace("\\", "\\\\")
        part = re.sub(r"([*_\[\]|])", r"\\\1", part)
        parts[i] = part.replace("<", "&lt;").replace(">", "&gt;")
    return "".join(parts)


def code(text: str) -> str:
    """`text` as a code span (a table's cell may hold one with a pipe: Python-Markdown's
    tables split no code span)."""
    fence = "``" if "`" in text else "`"
    pad = " " if fence == "``" else ""
    return f"{fence}{pad}{text}{pad}{fence}"


def paragraphs(text: str | None) -> str:
    """A help text or docstring as markdown paragraphs (its line breaks joined)."""
    if not text:
        return ""
    blocks = re.split(r"\n\s*\n", inspect.cleandoc(text).replace("\b", ""))
    return "\n\n".join(escape(" ".join(line.strip() for line in b.splitlines())) for b in blocks)


def anchor_of(path: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", path.lower()).strip("-")


# -- the command line --------------------------------------------------------------------------
def _split_extra(help_text: str) -> tuple[str, str | None, list[str]]:
    """click's help record `help  [default: X; range]` -> (help, default, other entries)."""
    match = re.match(r"(?s)^(.*?)\s*\[([^\[\]]*)\]$", help_text)
    if not match or not re.search(r"default: |required|[<>]=?|deprecated", match.group(2)):
        return help_text, None, []
    default, other = None, []
    for entry in match.group(2).split("; "):
        if entry.startswith("default: "):
            default = entry[len("default: ") :]
        else:
            other.append(entry)
    return match.group(1), default, other


def _param_rows(command: Any, context: Any) -> list[str]:
    rows = []
    for param in command.get_params(context):
        record = param.get_help_record(context)
        if record is None or param.name == "help":
            continue
        names, help_text = record
        metavar = ""
        if m := re.match(r"^(.*?)\s+(<[^<>]+>)$", names):
            names, metavar = m.groups()
        help_text, default, other = _split_extra(help_text)
        kind = "argument" if param.param_type_name == "argument" else "option"
        rows.append(
            "| "
            + " | ".join(
                [
                    code(names) + ("" if kind == "option" else " (argument)"),
                    code(metavar.strip("<>")) if metavar else "flag",
                    code(default) if default is not None else "",
                    escape("; ".join(other)),
                    escape(help_text),
                ]
            )
            + " |"
        )
    return rows


def _command_section(command: Any, context: Any, level: int) -> list[str]:
    path = context.command_path
    lines = [f"{'#' * level} `{path}` {{#{anchor_of(path)}}}", ""]
    if command.help:
        lines += [paragraphs(command.help), ""]
    pieces = " ".join(command.collect_usage_pieces(context))
    lines += ["```text", f"{path} {pieces}".rstrip(), "```", ""]
    rows = _param_rows(command, context)
    if rows:
        lines += [
            "| option | type | default | range / required | description |",
            "| --- | --- | --- | --- | --- |",
            *rows,
            "",
        ]
    return lines


def _walk(group: Any, context: Any):
    """(command, context) for every command reachable from `group`, groups included."""
    from typer._click.core import Context

    for name in group.list_commands(context):
        command = group.get_command(context, name)
        if command is None or command.hidden:
            continue
        sub = Context(command, info_name=name, parent=context)
        yield command, sub
        if hasattr(command, "commands"):
            yield from _walk(command, sub)


def command_paths(app: Any) -> list[str]:
    """Every command's full path, `oodrl suite try` and the like (groups left out)."""
    import typer.main
    from typer._click.core import Context

    root = typer.main.get_command(app)
    return [
        context.command_path
        for command, context in _walk(root, Context(root, info_name="oodrl"))
        if not hasattr(command, "commands")
    ]


def cli_page() -> str:
    import typer.main
    from typer._click.core import Context

    from oodrl.cli import app

    root = typer.main.get_command(app)
    context = Context(root, info_name="oodrl")
    lines = [
        "# Command line",
        "",
        "<!-- Generated at build time from the `oodrl` app (docs/hooks/reference_pages.py): "
        "edit the commands' help, not this page. -->",
        "",
        "Every command of `oodrl`, generated from the app itself when the site is built: "
        "`oodrl COMMAND --help` prints the same. A command exits 0 when it succeeds, 2 for a "
        "usage or params error and 1 for a runtime failure, with one `error:` line and no "
        "traceback unless `OODRL_DEBUG=1` ([SPEC §22](../SPEC.md#22-errors)).",
        "",
        paragraphs(root.help),
        "",
        "```text",
        "oodrl " + " ".join(root.collect_usage_pieces(context)),
        "```",
        "",
    ]
    rows = _param_rows(root, context)
    if rows:
        lines += [
            "| option | type | default | range / required | description |",
            "| --- | --- | --- | --- | --- |",
            *rows,
            "",
        ]
    # The panels in the order `oodrl --help` shows them: the default one first.
    panels: dict[str, list[tuple[Any, Any]]] = {DEFAULT_PANEL: []}
    for name in root.list_commands(context):
        command = root.get_command(context, name)
        if command is None or command.hidden:
            continue
        panel = getattr(command, "rich_help_panel", None) or DEFAULT_PANEL
        panels.setdefault(panel, []).append(
            (command, Context(command, info_name=name, parent=context))
        )
    for panel, commands in panels.items():
        if not commands:
            continue
        lines += [f"## {escape(panel)}", ""]
        lines += [
            "| command | what it does |",
            "| --- | --- |",
            *(
                f"| [`{ctx.command_path}`](#{anchor_of(ctx.command_path)}) | "
                f"{escape(cmd.get_short_help_str(limit=200))} |"
                for cmd, ctx in commands
            ),
            "",
        ]
        for command, sub in commands:
            lines += _command_section(command, sub, 3)
            if hasattr(command, "commands"):
                for inner, inner_context in _walk(command, sub):
                    depth = len(inner_context.command_path.split()) - len(sub.command_path.split())
                    lines += _command_section(inner, inner_context, 3 + depth)
    return "\n".join(lines).rstrip() + "\n"


# -- params ------------------------------------------------------------------------------------
def type_name(annotation: Any) -> str:
    """A field's type as a reader writes it: `int`, `float | None`, `'greedy' | 'noisy'`."""
    origin = get_origin(annotation)
    if annotation is NoneType:
        return "null"
    if origin is Literal:
        return " | ".join(repr(a) for a in get_args(annotation))
    if origin in (Union, UnionType):
        return " | ".join(type_name(a) for a in get_args(annotation))
    if origin is not None:
        args = ", ".join(type_name(a) for a in get_args(annotation))
        return f"{getattr(origin, '__name__', str(origin))}[{args}]"
    if annotation is Any:
        return "any"
    return getattr(annotation, "__name__", str(annotation))


def _constraints(field: Any) -> list[str]:
    """The field's range and length limits, from its pydantic metadata."""
    symbols = {
        "ge": "≥",
        "gt": ">",
        "le": "≤",
        "lt": "<",
        "min_length": "length ≥",
        "max_length": "length ≤",
        "multiple_of": "multiple of",
    }
    out = []
    for item in field.metadata:
        for attribute, symbol in symbols.items():
            value = getattr(item, attribute, None)
            if value is not None:
                out.append(f"{symbol} {value}")
    return out


def _range(field: Any) -> str:
    """`0 < x < 1` from gt/lt pairs, else the constraints listed."""
    found = {}
    for item in field.metadata:
        for attribute in ("ge", "gt", "le", "lt"):
            if getattr(item, attribute, None) is not None:
                found[attribute] = getattr(item, attribute)
    low = f"{found['ge']} ≤ " if "ge" in found else f"{found['gt']} < " if "gt" in found else ""
    high = f" ≤ {found['le']}" if "le" in found else f" < {found['lt']}" if "lt" in found else ""
    parts = [f"{low}x{high}"] if low or high else []
    parts += [c for c in _constraints(field) if c.startswith(("length", "multiple"))]
    return ", ".join(parts)


def default_of(field: Any) -> tuple[bool, Any]:
    """(required, default): a default factory's value is computed, as pydantic would."""
    if field.is_required():
        return True, None
    if field.default_factory is not None:
        return False, field.default_factory()
    return False, field.default


def _comments(model: type) -> dict[str, str]:
    """Each field's comment in the model's source: the `#:` or `#` lines right above it, or
    the comment at the end of its line."""
    try:
        source = textwrap.dedent(inspect.getsource(model))
    except (OSError, TypeError):
        return {}
    lines = source.splitlines()
    found = {}
    for node in ast.parse(source).body[0].body:
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        above = []
        k = node.lineno - 2
        while k >= 0 and lines[k].strip().startswith("#"):
            above.insert(0, lines[k].strip().lstrip("#:").strip())
            k -= 1
        line = lines[node.lineno - 1]
        trailing = line.split("  # ", 1)[1].strip() if "  # " in line else ""
        text = " ".join(above + ([trailing] if trailing else []))
        if text:
            found[node.target.id] = text
    return found


def params_file_comments(path: Path) -> dict[str, str]:
    """The comment at the end of each key's line in a params file, by key path: the committed
    params.yaml explains its knobs there."""
    found: dict[str, str] = {}
    stack: list[tuple[int, str]] = []
    for line in path.read_text().splitlines():
        match = re.match(
            r"^( *)([A-Za-z_]\w*):(?:[ \t]+([^#\s].*?))?(?:[ \t]+#[ \t]*(.*))?[ \t]*$", line
        )
        if not match:
            continue
        indent, key, _, comment = (
            len(match.group(1)),
            match.group(2),
            match.group(3),
            match.group(4),
        )
        while stack and stack[-1][0] >= indent:
            stack.pop()
        stack.append((indent, key))
        if comment:
            found[".".join(k for _, k in stack)] = comment
    return found


def params_leaves(model: type | None = None, prefix: str = "") -> list[tuple[str, Any, type]]:
    """(key path, field, owning model) for every leaf key of the params schema, in order."""
    from pydantic import BaseModel

    if model is None:
        from oodrl.config import Params

        model = Params
    out = []
    for name, field in model.model_fields.items():
        path = f"{prefix}{name}"
        annotation = field.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            out += params_leaves(annotation, path + ".")
        else:
            out.append((path, field, model))
    return out


def format_default(value: Any) -> str:
    import json

    if isinstance(value, str):
        return value
    try:
        return json.dumps(value, ensure_ascii=False)
    except TypeError:
        return repr(value)


def _model_sections(model: type, prefix: str) -> list[tuple[str, type]]:
    from pydantic import BaseModel

    out = [(prefix, model)]
    for name, field in model.model_fields.items():
        annotation = field.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            out += _model_sections(annotation, f"{prefix}{name}.")
    return out


def _components_section() -> list[str]:
    """detectors.NAME.* and anomaly.injectors.NAME.*: each registered component's own keys."""
    from oodrl.detectors import DETECTORS
    from oodrl.injectors import INJECTORS
    from oodrl.validation import constructor_params

    lines = [
        "## Component parameters {#params-components}",
        "",
        "The blocks `detectors.NAME` and `anomaly.injectors.NAME` hold each component's own "
        "parameters: the keyword arguments of its class, validated by its declared constraints "
        "(`oodrl check-params` checks them all). Listed here for every registered component, "
        "with the class's default.",
        "",
    ]
    for prefix, registry in (("detectors", DETECTORS), ("anomaly.injectors", INJECTORS)):
        classes = {name: registry.get(name) for name in registry.names()}
        base = None
        if prefix == "detectors":
            # The keys every detector shares (its base class's), listed once.
            shared = set.intersection(*(set(constructor_params(c)) for c in classes.values()))
            base = [p for p in constructor_params(next(iter(classes.values()))) if p in shared]
            lines += [f"### `{prefix}.*`: every detector", ""]
            lines += _component_table(prefix, "NAME", next(iter(classes.values())), base)
        for name, cls in classes.items():
            own = [p for p in constructor_params(cls) if not base or p not in base]
            lines += [f"### `{prefix}.{name}`", ""]
            summary = (inspect.getdoc(cls) or "").split("\n\n")[0]
            if summary:
                lines += [paragraphs(summary), ""]
            if own:
                lines += _component_table(prefix, name, cls, own)
            else:
                lines += ["No parameters of its own.", ""]
    return lines


def _component_table(prefix: str, name: str, cls: type, params: list[str]) -> list[str]:
    from oodrl.validation import constraints_of

    constraints = constraints_of(cls)
    defaults = {}
    for klass in cls.__mro__:
        init = klass.__dict__.get("__init__")
        if init is None or klass is object:
            continue
        for p in inspect.signature(init).parameters.values():
            if p.name not in defaults:
                defaults[p.name] = p.default
    rows = ["| key | default | allowed |", "| --- | --- | --- |"]
    for param in params:
        default = defaults.get(param, inspect.Parameter.empty)
        shown = "required" if default is inspect.Parameter.empty else code(format_default(default))
        allowed = " or ".join(str(c) for c in constraints.get(param, ()))
        rows.append(f"| `{prefix}.{name}.{param}` | {shown} | {escape(allowed)} |")
    return rows + [""]


def params_page(params_file: Path | None = None) -> str:
    """The params reference; `params_file`: a committed params file whose end-of-line comments
    describe the keys the schema's source does not."""
    from oodrl.config import Params

    lines = [
        "# Params",
        "",
        "<!-- Generated at build time from oodrl.config.Params (docs/hooks/reference_pages.py): "
        "edit the schema, not this page. -->",
        "",
        "Every key of `params.yaml`, generated from the pydantic schema that validates it "
        "(`oodrl.config.Params`) when the site is built: its type, its default (what a params "
        "file that leaves it out gets), the range it must lie in, and what it sets. Unknown keys "
        "are refused, and `oodrl check-params` validates a file completely "
        "([SPEC §8](../SPEC.md#8-pipeline-dvcyaml-and-knobs-paramsyaml), "
        "[§22](../SPEC.md#22-errors)).",
        "",
    ]
    leaves = {path for path, _, _ in params_leaves()}
    explained = params_file_comments(params_file) if params_file else {}
    for prefix, model in _model_sections(Params, ""):
        name = prefix.rstrip(".")
        title = f"`{name}`" if name else "Top level"
        lines += [f"## {title} {{#{anchor_of('params-' + (name or 'top'))}}}", ""]
        if model is not Params and model.__doc__:
            lines += [paragraphs(model.__doc__), ""]
        comments = _comments(model)
        rows = []
        for key, field in model.model_fields.items():
            path = f"{prefix}{key}"
            if path not in leaves:
                about = escape(explained.get(path, ""))
                link = f"[below](#{anchor_of('params-' + path)})"
                rows.append(f"| `{path}` | section | | | {about + '; ' if about else ''}{link} |")
                continue
            required, default = default_of(field)
            cells = [
                f"`{path}`",
                code(type_name(field.annotation)),
                "required" if required else code(format_default(default)),
                escape(_range(field)),
                escape(field.description or comments.get(key) or explained.get(path, "")),
            ]
            if path in COMPONENT_BLOCKS:
                cells[-1] += f"; each one's keys: [{COMPONENT_BLOCKS[path]}](#params-components)"
            rows.append("| " + " | ".join(cells) + " |")
        lines += [
            "| key | type | default | range | description |",
            "| --- | --- | --- | --- | --- |",
            *rows,
            "",
        ]
    lines += _components_section()
    return "\n".join(lines).rstrip() + "\n"


def write(directory: Path) -> None:
    """Write the pages to `directory` (for a look without a build)."""
    (directory / "cli.md").write_text(cli_page())
    (directory / "params.md").write_text(params_page(ROOT / "params.yaml"))
