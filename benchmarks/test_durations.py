"""Where a test run's time went, from pytest's junit XML: the slowest tests and a per-module table.

    python benchmarks/test_durations.py JUNIT.xml [--top 25]

CI (.ci/run) runs the README's test command with `--junitxml` and prints this after the tests,
pass or fail, so a module that got slower shows in every run's log. A test's seconds are pytest's
junit `time`, which by default (`junit_duration_report = total`) sums its setup, call and
teardown; a module's are its tests' summed, which with `-n 2` is worker time, not wall time.
"""

from __future__ import annotations

import argparse
import sys
import xml.etree.ElementTree as ET
from collections import defaultdict
from pathlib import Path


def module_of(classname: str) -> str:
    """The test file of a junit `classname`: pytest writes the module's dotted path, then any
    test classes (CamelCase by pytest's own naming rule); `tests.api.test_x.TestY` ->
    `tests/api/test_x.py`."""
    parts = classname.split(".") if classname else []
    while parts and parts[-1][:1].isupper():
        parts.pop()
    return "/".join(parts) + ".py" if parts else "(collection)"


def durations(junit: Path) -> list[tuple[str, str, float]]:
    """(module, test name, seconds) for every testcase in the file, skipped and failed ones
    included (their setup costs time too)."""
    root = ET.parse(junit).getroot()
    return [
        (module_of(case.get("classname", "")), case.get("name", ""), float(case.get("time") or 0))
        for case in root.iter("testcase")
    ]


def report(rows: list[tuple[str, str, float]], top: int = 25) -> str:
    lines = [f"Slowest {min(top, len(rows))} tests (setup + call + teardown, seconds):"]
    for module, name, seconds in sorted(rows, key=lambda r: -r[2])[:top]:
        lines.append(f"{seconds:9.1f}  {module}::{name}")
    per_module: dict[str, list[float]] = defaultdict(list)
    for module, _, seconds in rows:
        per_module[module].append(seconds)
    width = max((len(m) for m in per_module), default=6)
    lines += ["", f"{'module':<{width}}  {'tests':>5}  {'seconds':>9}"]
    for module, times in sorted(per_module.items(), key=lambda item: -sum(item[1])):
        lines.append(f"{module:<{width}}  {len(times):>5}  {sum(times):>9.1f}")
    total = sum(seconds for _, _, seconds in rows)
    lines.append(f"{'total':<{width}}  {len(rows):>5}  {total:>9.1f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("junit", type=Path, help="pytest --junitxml output")
    parser.add_argument("--top", type=int, default=25, help="how many slowest tests to list")
    args = parser.parse_args(argv)
    if not args.junit.is_file():
        print(f"error: no junit file at {args.junit} (the tests did not start?)", file=sys.stderr)
        return 1
    print(report(durations(args.junit), args.top))
    return 0


if __name__ == "__main__":
    sys.exit(main())
