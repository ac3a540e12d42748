"""The root pipeline (LunarLander) and CartPole, the suite's one environment, at tiny params,
in a fresh git + DVC repository holding one commit of the project: what `oodrl suite run` and
the DVC remote tests build. Stage commands run the copy's own code (`code_env`), so edits
other people have in the working tree never reach a test build."""

from __future__ import annotations

import atexit
import json
import os
import shutil
import tempfile
from pathlib import Path

from oodrl.testing.pipeline import TINY_TIERS
from oodrl.testing.suite import SUITE, code_env, head_commit, locks, serial_build, suite_copy

PIPELINES = [".", "pipeline/cartpole"]
#: The tiny suite's benchmark: what every one of its pipelines scores.
SUITE_DETECTORS = ["mahalanobis_distance"]
SUITE_INJECTORS = ["stuck_actuator"]
__all__ = [
    "SUITE", "SUITE_DETECTORS", "SUITE_INJECTORS", "checkout", "code_env", "copy_built",
    "head_commit", "locks", "run_folder", "serial_built_suite", "serial_suite",
]  # fmt: skip


def _tiny(params: dict) -> None:
    params["env"]["T"] = 60
    params["data"].update(n_id=5, n_ood=3)  # 300 ID scores: the time-aware rule's least
    params["anomaly"]["sweep"] = [0.5]
    params["benchmark"] = {"detectors": list(SUITE_DETECTORS), "injectors": list(SUITE_INJECTORS)}
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


def run_folder(tmp_path_factory) -> Path:
    """A folder every process of this test run sees: pytest's base temporary directory, or
    under pytest-xdist the run's, above each worker's own."""
    here = tmp_path_factory.getbasetemp()
    return here.parent if os.environ.get("PYTEST_XDIST_WORKER") else here


def serial_built_suite(source: Path, commit: str, shared: Path) -> tuple[Path, list[str]]:
    """The two-environment suite built by `serial_suite` (each project's `dvc repro` in turn),
    and what ran: read it, or `copy_built` it to change it. The build takes minutes of one
    core, so a test run makes it once, in `shared` (`run_folder`): the first process to ask
    builds it, the others wait for it."""
    from filelock import FileLock

    made = shared / f"serial-suite-{commit}"
    with FileLock(f"{made}.lock"):
        if not (made / "ran.json").is_file():
            shutil.rmtree(made, ignore_errors=True)  # a build that died half-way
            repo = two_environment_suite(source, commit, made / "repo")
            ran = serial_suite(repo)
            assert f"{SUITE}:leaderboard" in ran and len(ran) > 20, ran
            (made / "ran.json").write_text(json.dumps(ran))
    return made / "repo", json.loads((made / "ran.json").read_text())


def copy_built(built: Path, dest: Path) -> Path:
    """A copy of a built suite, byte for byte with its DVC cache and git index, but DVC's
    scratch (.dvc/tmp: locks, indexes), which DVC makes anew."""

    def scratch(folder: str, names: list[str]) -> list[str]:
        return ["tmp"] if Path(folder).name == ".dvc" and "tmp" in names else []

    return Path(shutil.copytree(built, dest, symlinks=True, ignore=scratch))


def checkout(repo: Path) -> dict[Path, bytes]:
    """Every file of the checkout but git's and DVC's own scratch (.dvc/tmp: locks, indexes)."""
    files = (path for path in repo.rglob("*") if path.is_file() and not _scratch(path))
    return {path: path.read_bytes() for path in files}


def _scratch(path: Path) -> bool:
    pairs = zip(path.parts, path.parts[1:], strict=False)
    return ".git" in path.parts or any(pair == (".dvc", "tmp") for pair in pairs)
