"""README.md's Python quickstart (SPEC §25) is real code: at most 12 lines under the heading
`## Python quickstart`, and it runs from a clone's root (`oodrl.evaluate` at its "tiny" size
through OODRL_EVALUATE_SIZE, so that CI runs it in seconds)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

HEADING = "## Python quickstart"
MAX_LINES = 12


def quickstart(readme: str) -> str:
    """The first ```python block of the README's quickstart section; a test failure (never a
    skip) when the section or its block is missing."""
    lines = readme.splitlines()
    if HEADING not in lines:
        pytest.fail(f"README.md has no '{HEADING}' section (SPEC §25: a Python quickstart).")
    start = lines.index(HEADING) + 1
    end = next((i for i in range(start, len(lines)) if lines[i].startswith("## ")), len(lines))
    section = "\n".join(lines[start:end])
    block = re.search(r"^```python\n(.*?)^```", section, flags=re.MULTILINE | re.DOTALL)
    if block is None:
        pytest.fail(f"README.md's '{HEADING}' section holds no ```python block.")
    return block.group(1)


def test_quickstart_is_at_most_twelve_lines(repo_root):
    code = quickstart((repo_root / "README.md").read_text())
    assert 0 < len(code.splitlines()) <= MAX_LINES, code
    assert "oodrl.load_results(" in code and "oodrl.evaluate(" in code


def test_quickstart_runs(repo_root):
    code = quickstart((repo_root / "README.md").read_text())
    env = {**os.environ, "OODRL_EVALUATE_SIZE": "tiny", "MPLBACKEND": "Agg"}
    done = subprocess.run([sys.executable, "-c", code], cwd=repo_root, env=env,
                          capture_output=True, text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, f"the quickstart failed:\n{done.stdout}\n{done.stderr[-3000:]}"
    assert done.stdout.strip(), "the quickstart printed nothing"
