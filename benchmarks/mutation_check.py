"""Does the test suite catch a behaviour it guards when that behaviour breaks? (issue 59)

    python benchmarks/mutation_check.py [--only NAME[,NAME...]] [--keep]

For each mutation below (a behaviour the tests guard, broken on purpose by a textual edit of
the code), a scratch worktree of HEAD gets the edit and runs the tests named for it, in a fresh
pytest process that imports the worktree's package (PYTHONPATH). A mutation is *caught* when
those tests fail (pytest's exit 1); the same tests are first run on the unedited worktree and
must pass, so a catch is the edit's doing (`--assume-green` skips that run, for a commit
whose whole suite passed). An edit that no longer applies (its text is not in
the file exactly once) is reported as such, never as caught.

Prints one line per mutation and a summary; exit 1 if any is not caught.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Mutation:
    name: str
    behaviour: str  # what breaks, in the words
    file: str
    edits: tuple[tuple[str, str], ...]  # (text, replacement), each text found exactly once
    tests: tuple[str, ...]  # pytest node ids or paths


MUTATIONS = (
    Mutation(
        "stale_lock_accepted",
        "a stale lock accepted",
        "src/oodrl/suite/migration.py",
        (("STALE if reasons else CURRENT", "CURRENT"),),
        ("tests/test_migration_state.py",),
    ),
    Mutation(
        "knob_reruns_unrelated_stage",
        "a knob re-running an unrelated stage",
        "src/oodrl/suite/detector_pipeline.yaml",
        # The fit stage's (the cells stage reads its own block too, SPEC §23).
        (("      - detectors.${detector}\n    outs:\n", "      - detectors\n    outs:\n"),),
        ("tests/pipeline/test_pipeline.py::test_detector_param_reruns_only_that_detector",),
    ),
    Mutation(
        "alarm_rule_reads_calibration",
        "an alarm rule reading calibration streams",
        "src/oodrl/metrics/tiers.py",
        (
            (
                'twins, audit = heldout("twins"), heldout("audit")',
                'twins, audit = heldout("twins"), heldout("calibration")',
            ),
        ),  # fmt: skip
        ("tests/pipeline/test_pipeline.py::test_full_pipeline_writes_every_output",),
    ),
    Mutation(
        "corrupt_remote_object_kept",
        "a corrupt remote object kept",
        "src/oodrl/suite/run.py",
        (('"verify": "true"', '"verify": "false"'),),
        ("tests/faults/test_remote_faults.py",),
    ),
    Mutation(
        "second_suite_run_not_refused",
        "a second suite run not refused",
        "src/oodrl/suite/checkout_lock.py",
        (("fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)", "pass"),),
        ("tests/faults/test_runs.py",),
    ),
    Mutation(
        "readme_command_broken",
        "a README command that no longer runs",
        "README.md",
        (
            (
                "pip install -c constraints.txt -e . && dvc repro\n",
                "pip install -c constraints.txt -e . && dvc repro --no-such-option\n",
            ),
        ),  # fmt: skip
        ("tests/test_project.py", "tests/test_readme.py"),
    ),
    Mutation(
        "leaderboard_colour_reversed",
        "a leaderboard colour reversed",
        "src/oodrl/report/leaderboard_page.html",
        (
            (
                "hue(lowerIsBetter(metric, tier) ? 1 - goodness : goodness)",
                "hue(lowerIsBetter(metric, tier) ? goodness : 1 - goodness)",
            ),
        ),  # fmt: skip
        ("tests/report/test_leaderboard_page.py",),
    ),
    Mutation(
        "params_mistake_not_caught",
        "a params mistake not caught",
        "src/oodrl/config.py",
        (("severity: float = Field(0.5, ge=0, le=1)", "severity: float = Field(0.5)"),),
        ("tests/test_config.py", "tests/hostile/test_check_params_hostile.py"),
    ),
    Mutation(
        "half_written_store",
        "a half-written store",
        "src/oodrl/io/store.py",
        (
            ("        _pack(tmp, packed)\n", "        _pack(tmp, path)\n"),
            ("        os.replace(packed, path)\n", ""),
        ),  # fmt: skip
        ("tests/hostile/test_runtime_hostile.py", "tests/test_store.py"),
    ),
    Mutation(
        "non_deterministic_output",
        "a non-deterministic output",
        "src/oodrl/envs/collect.py",
        (("obs[i] = env.reset(seed=seed)[0]", "obs[i] = env.reset(seed=None)[0]"),),
        ("tests/envs/test_collect.py",),
    ),
)


def git(*args: str, cwd: Path = ROOT) -> str:
    done = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, check=True)
    return done.stdout


def pytest(worktree: Path, tests: tuple[str, ...]) -> tuple[int, float, str]:
    env = {**os.environ, "PYTHONPATH": str(worktree / "src")}
    command = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:xdist",
               "-p", "no:cacheprovider", *tests]  # fmt: skip
    start = time.perf_counter()
    done = subprocess.run(command, cwd=worktree, env=env, capture_output=True, text=True)
    last = (done.stdout.strip().splitlines() or [""])[-1]
    return done.returncode, time.perf_counter() - start, last


def apply(worktree: Path, mutation: Mutation) -> str | None:
    """Edit the worktree's file; None, or why the edit does not apply."""
    path = worktree / mutation.file
    text = path.read_text()
    for old, new in mutation.edits:
        if text.count(old) != 1:
            return f"{old!r} is in {mutation.file} {text.count(old)} times, not once"
        text = text.replace(old, new)
    path.write_text(text)
    return None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", help="comma-separated mutation names")
    parser.add_argument("--keep", action="store_true", help="keep the scratch worktree")
    parser.add_argument(
        "--assume-green",
        action="store_true",
        help="skip the unedited run (only when the whole suite passed on this commit)",
    )
    args = parser.parse_args()
    chosen = [m for m in MUTATIONS if not args.only or m.name in args.only.split(",")]
    missed = 0
    scratch = Path(tempfile.mkdtemp(prefix="oodrl-mutation-"))
    worktree = scratch / "tree"
    git("worktree", "add", "--detach", str(worktree), "HEAD")
    try:
        for mutation in chosen:
            rc, seconds, last = (
                (0, 0.0, "") if args.assume_green else pytest(worktree, mutation.tests)
            )
            if rc != 0:
                print(f"{mutation.name}: the unedited tests fail ({last}): cannot judge")
                missed += 1
                continue
            why = apply(worktree, mutation)
            if why:
                print(f"{mutation.name}: NOT APPLIED: {why}")
                missed += 1
                continue
            rc, mutated_s, last = pytest(worktree, mutation.tests)
            git("checkout", "--", mutation.file, cwd=worktree)
            caught = rc == 1
            missed += not caught
            print(f"{mutation.name} ({mutation.behaviour}): {'caught' if caught else 'MISSED'} "
                  f"by {' '.join(mutation.tests)} [exit {rc}; {last}; {seconds:.0f} s unedited, "
                  f"{mutated_s:.0f} s edited]", flush=True)  # fmt: skip
    finally:
        if not args.keep:
            git("worktree", "remove", "--force", str(worktree))
    print(f"{len(chosen) - missed} of {len(chosen)} mutations caught")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
