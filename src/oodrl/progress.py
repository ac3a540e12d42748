"""Progress bars of long library calls (collection, metrics, training): on a terminal only."""

from __future__ import annotations

import os
import sys


def progress_enabled(setting: str = "auto") -> bool:
    """Progress bars on a terminal, never in CI or when output is redirected."""
    if setting != "auto":
        return setting == "always"
    return sys.stderr.isatty() and not os.environ.get("CI")


def progress_bar(total: int, description: str, setting: str = "auto"):
    from tqdm import tqdm

    return tqdm(total=total, desc=description, disable=not progress_enabled(setting), leave=False)
