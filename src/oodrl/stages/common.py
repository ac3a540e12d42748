"""What every stage shares: its timing record (fitted-detector files: `oodrl.io.store`)."""

from __future__ import annotations

import json
import re
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

#: Side channel for per-stage wall times; deliberately not a DVC output (timings differ per run).
TIMINGS_DIR = Path(".oodrl") / "timings"


@contextmanager
def timed_stage(name: str) -> Iterator[dict[str, Any]]:
    """Record the stage's wall time under .oodrl/timings for run_meta.yaml; the stage may add
    timings of its own to the record it is given (the fit stage: `detector` and `fit_s`)."""
    start = time.perf_counter()
    record: dict[str, Any] = {"stage": name}
    yield record
    TIMINGS_DIR.mkdir(parents=True, exist_ok=True)
    record["wall_s"] = round(time.perf_counter() - start, 3)
    file_name = re.sub(r"[^\w.-]+", "_", name)  # a stage's DVC address holds / : @
    (TIMINGS_DIR / f"{file_name}.json").write_text(json.dumps(record))
