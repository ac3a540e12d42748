"""Recovery never destroys work: hints re-run only what is broken, a refused params edit
deletes nothing, and a missing policy stops instead of retraining for 13 minutes."""

from __future__ import annotations

import hashlib
import re
import shlex
from pathlib import Path

import pytest
from conftest import DETECTORS, INJECTORS, POLICY_FILES

from oodrl.errors import OodrlError
from oodrl.io.layout import detector_stage
from oodrl.io.store import load_detector, read_trajectories, restore_hint
from oodrl.metrics.results import read_results_file
from oodrl.stages.train import RETRAIN_COMMAND
from oodrl.testing.pipeline import edit_params, repro, run

pytestmark = pytest.mark.slow

OUTPUT_DIRS = ("data", "models", "scores", "reports")


def _snapshot(repo: Path) -> dict[str, str]:
    """sha256 of every file the pipeline wrote or was given."""
    return {
        path.relative_to(repo).as_posix(): hashlib.sha256(path.read_bytes()).hexdigest()
        for top in OUTPUT_DIRS
        for path in sorted((repo / top).rglob("*"))
        if path.is_file()
    }


def _error_lines(done) -> list[str]:
    return [line for line in (done.stdout + done.stderr).splitlines() if line.startswith("error:")]


def _dry_run(repo: Path, command: str) -> list[str]:
    """The stages a hinted command would run (`--dry` appended), environment prefix honoured."""
    words = shlex.split(command)
    env = dict(word.split("=", 1) for word in words if re.fullmatch(r"[A-Z_]+=.*", word))
    words = [word for word in words if not re.fullmatch(r"[A-Z_]+=.*", word)]
    assert words[:2] == ["dvc", "repro"], command
    return repro(repo, *words[2:], "--dry", env=env)


def _commands(message: str) -> list[str]:
    return re.findall(r"`(dvc repro [^`]*|[A-Z_]+=\S+ dvc repro [^`]*)`", message)


def test_every_hint_reruns_only_the_broken_stage(repo):
    detector, injector = DETECTORS[0], INJECTORS[0]
    fit = detector_stage(detector, "fit")
    broken = {  # stage -> its missing output and the error the stage that reads it raises
        "collect_eval": ("absent.zarr", lambda p: read_trajectories(p, stage="collect_eval")),
        fit: ("absent.pkl", lambda p: load_detector(p, stage=fit)),
        "metrics": ("absent.yaml", read_results_file),
    }
    for stage, (name, fail) in broken.items():
        with pytest.raises(OodrlError) as info:
            fail(repo / name)
        assert restore_hint(repo / name, stage) in str(info.value)
    stages = [
        "collect_id", "collect_eval", f"collect_ood@{injector}", f"collect_sweep@{injector}",
        fit, detector_stage(detector, "score_clean"), detector_stage(detector, "score"),
        detector_stage(detector, "cells"),
        "metrics", "render",
    ]  # fmt: skip
    for stage in stages:
        (command,) = _commands(restore_hint("absent", stage))
        assert _dry_run(repo, command) == [stage], command


def test_no_message_in_the_code_hints_plain_force(repo_root):
    """Every hint comes from `restore_hint`; `dvc repro -f` alone would retrain the policy."""
    sources = sorted((repo_root / "src" / "oodrl").rglob("*.py"))
    offenders = [p.name for p in sources if re.search(r"dvc repro -f", p.read_text())]
    assert offenders == []


def test_retrain_command_runs_train_policy_alone(repo):
    assert _dry_run(repo, RETRAIN_COMMAND) == ["train_policy"]


BAD_EDITS = [
    ("severity above 1", lambda p: p["anomaly"].update(severity=1.5), "anomaly.severity"),
    ("T zero", lambda p: p["env"].update(T=0), "env.T"),
    ("unknown top-level key", lambda p: p.update(sedd=1), "sedd: unknown key"),
]


def test_refused_params_edit_deletes_nothing(repo):
    """Each refused edit in turn on one copy (the params as built between them): a copy each
    would ask the same question of the same pipeline."""
    before, params = _snapshot(repo), (repo / "params.yaml").read_text()
    for case, edit, key in BAD_EDITS:
        (repo / "params.yaml").write_text(params)
        edit_params(repo, edit)
        done = run(repo, "dvc", "repro", check=False)
        assert done.returncode != 0, case
        errors = _error_lines(done)
        assert len(errors) == 1 and key in errors[0], (case, errors)
        assert "Running stage 'check_params'" in done.stdout, case
        assert done.stdout.count("Running stage") == 1, f"{case}: a stage started after it"
        assert _snapshot(repo) == before, case


def test_missing_policy_stops_with_how_to_restore_and_retrain(repo):
    (repo / "models/policy.pt").unlink()
    before = _snapshot(repo)
    done = run(repo, "dvc", "repro", check=False)
    assert done.returncode != 0
    (error,) = _error_lines(done)
    assert "models/policy.pt missing" in error
    assert "`git checkout -- models/policy.pt models/policy.json`" in error
    assert f"`{RETRAIN_COMMAND}`" in error
    assert _snapshot(repo) == before, "nothing deleted, models/policy.json included"

    run(repo, "git", "checkout", "--", *POLICY_FILES)
    assert repro(repo) == []


def test_changed_training_settings_are_refused_not_retrained(repo):
    before = _snapshot(repo)
    edit_params(repo, lambda p: p["policy"]["train"].update(total_steps=1000))
    done = run(repo, "dvc", "repro", check=False)
    assert done.returncode != 0
    (error,) = _error_lines(done)
    assert error.startswith("error: policy.train.total_steps: 1000, but models/policy.pt")
    assert f"`{RETRAIN_COMMAND}`" in error
    assert _snapshot(repo) == before
