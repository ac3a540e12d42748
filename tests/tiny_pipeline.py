"""The tests' tiny pipeline: the root pipeline on 2 detectors x 2 injectors at T=60, built by
`dvc repro` in a throw-away git + DVC repository. tests/conftest.py builds it once a session
(`built_repo`) for tests/pipeline/ and tests/api/test_evaluate.py; under `pytest -n N`
tests/scheduling.py deals those modules to one worker, which builds it once a run."""

from __future__ import annotations

import json
import os
from pathlib import Path

from oodrl.testing.pipeline import TINY_TIERS, copy_project, repro

DETECTORS = ["mahalanobis_distance", "kde_density"]
INJECTORS = ["observation_delay", "stuck_actuator"]
POLICY_FILES = ("models/policy.pt", "models/policy.json")


def tiny_params(default: dict) -> dict:
    params = json.loads(json.dumps(default))
    params["env"]["T"] = 60
    params["data"].update(n_id=5, n_ood=3)  # 300 ID scores: the time-aware rule's least
    params["anomaly"]["sweep"] = [0.2, 0.6]
    params["benchmark"] = {"detectors": DETECTORS, "injectors": INJECTORS}
    params["metrics"]["n_boot"] = 20
    params["metrics"]["traces_per_anomaly"] = 1
    params["tiers"].update(TINY_TIERS)
    params["executor"]["workers"] = 1
    return params


# Imported by every Python process of the build (PYTHONPATH): records the files of the
# modules it loaded, so test_deps can compare what each stage command imported with its deps.
IMPORT_TRACE = """
import atexit, json, os, sys


def _record():
    files = sorted({getattr(m, "__file__", None) or "" for m in list(sys.modules.values())})
    path = os.path.join(os.environ["OODRL_IMPORT_TRACE"], f"{os.getpid()}.json")
    with open(path, "w") as out:
        json.dump({"argv": sys.argv, "files": [f for f in files if f.endswith(".py")]}, out)


atexit.register(_record)
"""


def python_path(first: Path) -> str:
    """PYTHONPATH with `first` ahead of what the environment already has."""
    return os.pathsep.join(p for p in (str(first), os.environ.get("PYTHONPATH", "")) if p)


def build(repo_root: Path, base: Path, default: dict) -> Path:
    """The tiny pipeline built in `base`/repo; `base`/import-trace holds each process's imports."""
    trace = base / "import-trace"
    trace.mkdir()
    (trace / "sitecustomize.py").write_text(IMPORT_TRACE)
    repo = copy_project(repo_root, base / "repo", tiny_params(default))
    policy = {name: (repo / name).read_bytes() for name in POLICY_FILES}
    # Cold stage processes: a warm one (oodrl.warm) holds the modules its server preloaded
    # too.
    trace_env = {"PYTHONPATH": python_path(trace), "OODRL_IMPORT_TRACE": str(trace)}
    repro(repo, env={**trace_env, "OODRL_WARM": "0"})
    # train_policy may run (its deps changed since dvc.lock was written) but never retrains.
    assert {name: (repo / name).read_bytes() for name in POLICY_FILES} == policy
    return repo


def file_stamps(directory: Path) -> dict[str, tuple[int, int]]:
    """Each file's size and mtime under `directory`: a test that reads the shared tiny pipeline
    checks with it that it wrote nothing there (other tests read and copy it)."""
    return {
        p.relative_to(directory).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns)
        for p in directory.rglob("*")
        if p.is_file()
    }
