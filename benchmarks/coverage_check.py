"""Line coverage of src/oodrl by the test suite, at one commit or several (issue 59).

    python benchmarks/coverage_check.py REV [REV ...] [--tests PATH ...] [--workers N]

For each REV, a fresh clone at REV gets the README's install (a virtual environment, the
constraints file, `.[dev]`) plus coverage.py, and runs the README's test command under
`coverage run`. Most of oodrl runs in processes the tests start (the CLI, DVC's stages, xdist's
workers), so coverage.py's `patch = subprocess` starts it in every Python process of that
environment; only files under the clone's own src/oodrl count (a test that imports a scratch
copy of the package elsewhere adds nothing). The revisions run one after the other, never side
by side: a loaded machine makes time-limited tests fail, and a failed test covers less.

Prints, per REV, the tests that failed, the pytest summary line and the line coverage (statements
run / statements), then exits 1 if any REV's tests failed, since its coverage then understates
what passes cover.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: coverage.py's version (PyPI, 2026-11): `patch = subprocess` needs 7.10 or newer.
COVERAGE = "coverage==7.17.3"


def run(cwd: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=cwd, check=check, capture_output=True, text=True)


def coverage_rc(clone: Path, data: Path) -> str:
    return (
        "[run]\n"
        f"source = {clone / 'src' / 'oodrl'}\n"
        f"data_file = {data / '.coverage'}\n"  # absolute: the tests' processes run elsewhere
        "parallel = true\n"
        "patch = subprocess\n"
        "sigterm = true\n"  # the hostile tests stop commands with SIGTERM
    )


def measure(
    rev: str, base: Path, tests: list[str], workers: int, keep: Path | None
) -> tuple[str, float, bool]:
    """(pytest's summary line, percent of src/oodrl's statements run, whether pytest passed);
    coverage.py's JSON report (per file, the lines missed) copied into `keep` as REV.json."""
    clone = base / "clone"
    run(base, "git", "clone", "-q", str(ROOT), str(clone))
    run(clone, "git", "checkout", "-q", rev)
    venv = clone / ".venv" / "bin"
    run(clone, sys.executable, "-m", "venv", ".venv")
    run(clone, str(venv / "pip"), "install", "-q", "-c", "constraints.txt", "-e", ".[dev]")
    run(clone, str(venv / "pip"), "install", "-q", COVERAGE)
    data = base / "data"
    data.mkdir()
    rc = base / "coveragerc"
    rc.write_text(coverage_rc(clone, data))
    done = run(
        clone,
        str(venv / "coverage"), "run", f"--rcfile={rc}", "-m", "pytest", "-q",
        "-p", "no:cacheprovider", "-n", str(workers), *tests,
        check=False,
    )  # fmt: skip
    lines = done.stdout.strip().splitlines()
    summary = (lines or ["(no output)"])[-1]
    for line in lines:  # pytest's short summary: which tests failed, so a rerun can tell why
        if line.startswith(("FAILED ", "ERROR ")):
            print(f"{rev}: {line}", flush=True)
    run(clone, str(venv / "coverage"), "combine", f"--rcfile={rc}", "-q")
    report = base / "coverage.json"
    run(clone, str(venv / "coverage"), "json", f"--rcfile={rc}", "-q", "-o", str(report))
    totals = json.loads(report.read_text())["totals"]
    if keep is not None:
        keep.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(report, keep / f"{rev}.json")
    return summary, 100.0 * totals["covered_lines"] / totals["num_statements"], done.returncode == 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("revs", nargs="+", help="commits to measure, one after the other")
    parser.add_argument("--tests", nargs="*", default=[], help="test paths (default: all)")
    parser.add_argument("--workers", type=int, default=2, help="pytest -n (the README's: 2)")
    parser.add_argument("--keep-json", type=Path, help="a folder for each REV's JSON report")
    args = parser.parse_args(argv)
    passed = True
    for rev in args.revs:
        with tempfile.TemporaryDirectory(prefix="oodrl-coverage-") as tmp:
            summary, percent, ok = measure(rev, Path(tmp), args.tests, args.workers, args.keep_json)
        passed &= ok
        print(f"{rev}: {percent:.2f}% of src/oodrl's lines run  [{summary}]", flush=True)
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
