"""The root pipeline (LunarLander) and CartPole, the suite's one environment, at tiny params,
in a fresh git + DVC repository holding one commit of the project: what `oodrl suite run` and
the DVC remote tests build. Stage commands run the copy's own code (`code_env`), so edits
other people have in the working tree never reach a test build."""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

from oodrl.testing.pipeline import TINY_TIERS
from oodrl.testing.suite import SUITE, code_env, head_commit, locks, serial_build, suite_copy

PIPELINES = [".", "pipeline/cartpole"]
__all__ = ["SUITE", "checkout", "code_env", "head_commit", "locks", "serial_suite"]


def _tiny(params: dict) -> None:
    params["env"]["T"] = 60
    params["data"].update(n_id=4, n_ood=3)
    params["anomaly"]["sweep"] = [0.5]
    params["benchmark"] = {"detectors": ["mahalanobis_distance"], "injectors": ["stuck_actuator"]}
    params["metrics"].update(n_boot=20, traces_per_anomaly=1)
    params["executor"]["workers"] = 1
    if "tiers" in params:  # impact tiers (SPEC §15, §19): tiny counts
        params["tiers"].update(TINY_TIERS)


def root_detectors_only(params: dict) -> None:
    """The suite's params add the library detectors to the root's list: keep the root's."""
    params.pop("benchmark", None)


def _tiny_environment(params: dict) -> None:
    params["env"] = {**params.get("env", {}), "T": 60, "onset": None}


#: (source, commit) -> the suite made once in this process, which each call copies.
_MADE: dict[tuple[Path, str], Path] = {}


def two_environment_suite(source: Path, commit: str, dest: Path) -> Path:
    """`commit` of `source` in `dest`: root and CartPole, one detector and one injector, T=60,
    a handful of episodes. A process makes it once (`git archive`, `oodrl pipeline write`, a
    commit: 6 s) and copies it for each call (0.4 s): no path inside it names its directory."""
    key = (source.resolve(), commit)
    made = _MADE.get(key)
    if made is None or not made.is_dir():
        folder = Path(tempfile.mkdtemp(prefix="suite-repo-"))
        atexit.register(shutil.rmtree, folder, True)
        edits = (_tiny, _tiny_environment, root_detectors_only)
        made = _MADE[key] = suite_copy(source, commit, folder / "repo", PIPELINES, *edits)
    shutil.copytree(made, dest, symlinks=True)
    return dest


def serial_suite(repo: Path) -> list[str]:
    """The reference: `dvc repro` of each project in turn, then the suite's; what ran."""
    built = serial_build(repo, PIPELINES)
    return [f"{project}:{stage}" for project, (_, ran) in built.items() for stage in ran]


def checkout(repo: Path) -> dict[Path, bytes]:
    """Every file of the checkout but git's and DVC's own scratch (.dvc/tmp: locks, indexes)."""
    files = (path for path in repo.rglob("*") if path.is_file() and not _scratch(path))
    return {path: path.read_bytes() for path in files}


def _scratch(path: Path) -> bool:
    pairs = zip(path.parts, path.parts[1:], strict=False)
    return ".git" in path.parts or any(pair == (".dvc", "tmp") for pair in pairs)
