"""`oodrl show PATH`: the tables of a results.yaml or sweep_results.yaml as terminal text."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from oodrl import yamlio
from oodrl.errors import StoreError
from oodrl.report.tables import render_tables, sweep_tables

RECORD_KEYS = frozenset({"kind", "detector", "anomaly", "mode", "severity", "metrics"})


def load_report(path: str | Path) -> tuple[str, dict[str, Any]]:
    """("results" | "sweep", contents) of a report file; StoreError for anything else."""
    path = Path(path)
    if not path.is_file():
        raise StoreError(
            f"No report file at '{path}'. Pass a results.yaml or sweep_results.yaml "
            "(the metrics stage writes them to reports/; run `dvc repro` first)."
        )
    try:
        data = yamlio.load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise StoreError(f"'{path}' is not a YAML report file: {error}") from None
    if isinstance(data, Mapping) and isinstance(data.get("records"), list):
        bad = [i for i, r in enumerate(data["records"]) if not _is_record(r)]
        if bad:
            raise StoreError(
                f"Record {bad[0]} of '{path}' is not a results record; each record needs the "
                f"keys {', '.join(sorted(RECORD_KEYS))}."
            )
        return "results", dict(data)
    if isinstance(data, Mapping) and isinstance(data.get("sweep"), Mapping):
        return "sweep", dict(data)
    raise StoreError(
        f"'{path}' is neither a results file (a 'records' list) nor a sweep file "
        "(a 'sweep' mapping)."
    )


def _is_record(record: Any) -> bool:
    return (
        isinstance(record, Mapping)
        and set(record) >= RECORD_KEYS
        and isinstance(record["metrics"], Mapping)
    )


def show(path: str | Path) -> str:
    """The markdown tables of a results or sweep file, for printing in a terminal."""
    kind, data = load_report(path)
    return render_tables(data) if kind == "results" else sweep_tables(data)
