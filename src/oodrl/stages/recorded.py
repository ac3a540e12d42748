"""The clean sets of a recorded pipeline (SPEC §18): a Minari dataset's episodes as streams.

Which streams each set holds: `oodrl.protocol.recorded`.
"""

from __future__ import annotations

from pathlib import Path

from oodrl.config import Params
from oodrl.io.store import write_trajectories


def import_clean_set(params: Params, split: str, dataset: Path, out: Path) -> None:
    from oodrl.protocol.recorded import clean_set

    write_trajectories(out, clean_set(params, split, dataset))
