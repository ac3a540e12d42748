"""The tier results file (SPEC §15): the tier_metrics stage writes its document
(`oodrl.metrics.tiers.assemble_tier_results`) as `reports/tier_results.json` from protocol 5;
a protocol-4 project holds the same document as `reports/tier_results.yaml` until it is
rebuilt. Every reader reads either through `load_tier_results`.

Apart from `oodrl.metrics.tiers` so that a reader (the suite's leaderboard) imports only this:
a DVC stage depends on every module its command can import.
"""

from __future__ import annotations

import contextlib
import json
import re
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

import yaml

from oodrl.errors import ContractError, StoreError
from oodrl.io import yamlio

#: The tier_metrics stage's results, relative to a project's directory (protocol 5 on).
TIER_RESULTS = Path("reports/tier_results.json")
#: The same document as protocol 4 wrote it: a project keeps it until it is rebuilt.
PROTOCOL_4_TIER_RESULTS = Path("reports/tier_results.yaml")


def _canonical_json(value: Any) -> str:
    try:
        return json.dumps(
            value, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False
        )
    except ValueError as error:  # the YAML wrote `.nan`; JSON has no such value
        raise ContractError(
            f"tier results hold a NaN or infinite value, which JSON cannot keep ({error})."
        ) from None


def tier_results_text(document: Mapping[str, Any]) -> str:
    """reports/tier_results.json's text: canonical JSON (sorted keys, no spaces, ASCII, floats
    by their shortest repr), so a document gives the same bytes on any machine. A line per
    top-level key, and one per entry of a top-level list or mapping: each record is one line,
    so a diff names the records that changed."""
    lines = []
    for key, value in sorted(document.items()):
        if isinstance(value, list) and value:
            entries = [_canonical_json(item) for item in value]
            lines.append(f"{_canonical_json(key)}:[\n" + ",\n".join(entries) + "\n]")
        elif isinstance(value, dict) and value:
            # `{k: v}` less its braces: the entry as JSON writes it (an int key quoted).
            entries = [_canonical_json({k: v})[1:-1] for k, v in sorted(value.items())]
            lines.append(f"{_canonical_json(key)}:{{\n" + ",\n".join(entries) + "\n}")
        else:
            lines.append(_canonical_json({key: value})[1:-1])
    return "{\n" + ",\n".join(lines) + "\n}\n"


def tier_results_path(project: Path) -> Path:
    """A project's tier results file: its JSON, else the protocol-4 YAML where only that is
    there; the JSON's path where neither is (the file the tier_metrics stage writes)."""
    found = Path(project) / TIER_RESULTS
    older = Path(project) / PROTOCOL_4_TIER_RESULTS
    return older if older.is_file() and not found.is_file() else found


def load_tier_results(where: Path, keys: Collection[str] | None = None) -> dict[str, Any]:
    """The tier results document of a project directory (`tier_results_path`) or of a tier
    results file: the JSON, or a protocol-4 project's YAML, as the same dict. With `keys`, only
    those top-level keys (a YAML's sections are then parsed alone where they can be: a
    fraction of a second, where the whole file takes seconds). StoreError, one line, where
    there is no such file or it does not parse to a mapping."""
    path = tier_results_path(where) if Path(where).is_dir() else Path(where)
    if not path.is_file():
        raise StoreError(
            f"{path}: no tier results file here (nor a protocol-4 {PROTOCOL_4_TIER_RESULTS.name}); "
            "the tier_metrics stage writes it (tracked by git: `git checkout` restores a "
            "committed one; `dvc repro tier_metrics` in its project builds one)."
        )
    try:
        text = path.read_text(encoding="utf-8")
        if path.suffix == ".json":
            document = _int_curve_keys(json.loads(text))
        else:
            document = _protocol_4_yaml(text, keys)
    except (ValueError, yaml.YAMLError) as error:  # UnicodeDecodeError is a ValueError
        reason = " ".join(str(error).split())[:200]
        raise StoreError(f"{path}: not a tier results file ({reason}).") from None
    if not isinstance(document, dict):
        raise StoreError(f"{path}: not a tier results file (a mapping of its sections).")
    return document if keys is None else {k: document[k] for k in keys if k in document}


def _int_curve_keys(document: Any) -> Any:
    """A detection curve's K is an int (`oodrl.metrics.operating`), which JSON writes as a
    string key: made an int again, so both files load to the same dict."""
    records = document.get("records") if isinstance(document, dict) else None
    for record in records if isinstance(records, list) else []:
        aware = record.get("time_aware") or {}
        for point in (record.get("operating_point"), aware.get("operating_point")):
            if point and "detection_curve" in point:
                point["detection_curve"] = {int(k): v for k, v in point["detection_curve"].items()}
    return document


def _protocol_4_yaml(text: str, keys: Collection[str] | None) -> Any:
    """A protocol-4 tier_results.yaml. Its top-level keys are sorted, each on an unindented
    line, so the blocks of `keys` are parsed alone; the whole file is parsed where one is not
    there or names an anchor outside its block."""
    blocks = [_top_level_block(text, key) for key in keys or ()]
    if blocks and None not in blocks:
        with contextlib.suppress(yaml.YAMLError):
            return yamlio.load("".join(blocks))
    return yamlio.load(text)


def _top_level_block(text: str, key: str) -> str | None:
    """The lines of top-level `key:` and its indented value, or None when there is none."""
    match = re.search(rf"^{re.escape(key)}:[ \t]*\n", text, flags=re.MULTILINE)
    if match is None:
        return None
    end = re.compile(r"^[^\s#-]", flags=re.MULTILINE).search(text, match.end())
    return text[match.start() : end.start() if end else len(text)]
