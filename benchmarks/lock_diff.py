"""What a build changed against the committed locks, and whether SPEC §14 allows it.

    python benchmarks/lock_diff.py [--rev HEAD] [--json OUT]

After a build on this machine (`oodrl suite run`, or `dvc repro` in some projects), compares
every project's dvc.lock files in the working tree with those at REV: each output whose hash
changed, by stage. SPEC §14 promises byte-identical outputs on any x86-64 machine for the
certified detectors only; a library detector's kernels are the machine's (`machine_independent`
False, marked † in every table). So a changed output is explained when it belongs to such a
detector (its fit or its scoring), or when it is a results file whose changed values all sit
under such a detector's name (a YAML or JSON key path through the name; a table row naming it).
The code stamps (`check_params`' `data/code`) change with the code by design (SPEC §12): reported,
not judged, so a build after a change of code alone shows which outputs moved besides them.
Anything else is a reproduction failure. Results files are compared value by value, so the
report names each detector whose numbers moved. A figure (PNG) mixes detectors and is reported,
not judged, and so is a page (HTML): it renders a JSON beside it, which is judged. The suite's
project has no params of its own: its leaderboard gathers every environment's detectors, so the
uncertified ones of any environment explain its changes.

Exit 1 when some change is not explained.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from oodrl.config import read_params_data
from oodrl.io import yamlio
from oodrl.io.layout import DETECTOR_PIPELINES
from oodrl.suite.pipeline import PARAMS_FILE, project_dirs
from oodrl.testing.kernels import uncertified_detectors

ROOT = Path(__file__).resolve().parents[1]
#: (stage, output) of the code stamps: sha256 of the files each stage kind can execute.
CODE_STAMPS = ("check_params", "data/code")


def at_rev(rev: str, path: Path) -> str | None:
    done = subprocess.run(["git", "show", f"{rev}:{path.relative_to(ROOT).as_posix()}"],
                          cwd=ROOT, capture_output=True, text=True)  # fmt: skip
    return done.stdout if done.returncode == 0 else None


def outs(lock_text: str | None) -> dict[tuple[str, str], str]:
    """(stage, output path) → its md5, from a dvc.lock's text."""
    stages = (yamlio.load(lock_text) or {}).get("stages", {}) if lock_text else {}
    return {(name, out["path"]): out.get("md5", "") for name, stage in stages.items()
            for out in stage.get("outs", [])}  # fmt: skip


def leaf_paths(old: Any, new: Any, at: tuple = ()) -> list[tuple]:
    """The key paths where two parsed documents differ; a record's `detector` field joins the
    path (results list records, each naming its detector)."""
    if isinstance(old, dict) and isinstance(new, dict):
        if isinstance(old.get("detector"), str):
            at = (*at, old["detector"])
        return [p for k in sorted(set(old) | set(new), key=str)
                for p in leaf_paths(old.get(k), new.get(k), (*at, str(k)))]  # fmt: skip
    if isinstance(old, list) and isinstance(new, list) and len(old) == len(new):
        return [p for i, (a, b) in enumerate(zip(old, new, strict=True))
                for p in leaf_paths(a, b, (*at, str(i)))]  # fmt: skip
    return [] if old == new else [at]


def changed_detectors(path: Path, old: str, new: str, names: set[str]) -> tuple[set, int]:
    """The detector names the changes of a results file sit under, and how many changes
    sit under none."""
    if path.suffix in (".yaml", ".json"):
        load = json.loads if path.suffix == ".json" else yamlio.load
        found, unexplained = set(), 0
        for key_path in leaf_paths(load(old), load(new)):
            # A key may join a name with other words (metrics.json: `iqm.pyod_iforest`).
            hit = {n for n in names if any(n in part.split(".") for part in key_path)}
            found |= hit
            unexplained += not hit
        return found, unexplained
    old_lines, new_lines = set(old.splitlines()), set(new.splitlines())
    found, unexplained = set(), 0
    for line in old_lines ^ new_lines:
        hit = {n for n in names if n in line}
        found |= hit
        unexplained += not hit
    return found, unexplained


def judged(project: Path, key: tuple[str, str], owner: str | None, uncertified: set[str],
           rev: str) -> dict:  # fmt: skip
    """The report row of one changed output `key` = (stage, output) of `project`: the detectors
    it sits under and how many of its changes are not explained. `owner`: the detector whose
    DVC file holds the stage (None for the project's own dvc.yaml)."""
    stage, out = key
    row = {"project": project.relative_to(ROOT).as_posix(), "stage": stage,
           "output": out, "detectors": [], "unexplained": 0}  # fmt: skip
    if key == CODE_STAMPS:
        row["note"] = "the code stamps: they change with the code, not judged"
    elif owner is not None:
        row["detectors"] = [owner]
        row["unexplained"] = int(owner not in uncertified)
    elif not out.startswith("reports/"):
        row["unexplained"], row["note"] = 1, "data of the certified protocol"
    elif out.endswith((".png", ".html")) or not (project / out).is_file():
        row["note"] = "a figure, page or directory of reports/: reported, not judged"
    else:
        old = at_rev(rev, project / out)
        if old is None:
            row["unexplained"], row["note"] = 1, "not in git at the revision"
        else:
            found, bad = changed_detectors(project / out, old, (project / out).read_text(),
                                           uncertified)  # fmt: skip
            row["detectors"], row["unexplained"] = sorted(found), bad
    return row


def uncertified_by_project(projects: list[Path]) -> dict[Path, set[str]]:
    """Each project's detectors not certified machine-independent; a project without params
    (the suite's, whose leaderboard gathers every environment's detectors) gets them all."""
    own = {project: set(uncertified_detectors(read_params_data(project / PARAMS_FILE)))
           for project in projects if (project / PARAMS_FILE).is_file()}  # fmt: skip
    everywhere = set().union(*own.values())
    return {project: own.get(project, everywhere) for project in projects}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rev", default="HEAD")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    report, unexplained_total = [], 0
    projects = project_dirs(ROOT)
    uncertified_in = uncertified_by_project(projects)
    for project in projects:
        uncertified = uncertified_in[project]
        detector_locks = sorted(project.glob(f"{DETECTOR_PIPELINES}/*/dvc.lock"))
        for lock in [project / "dvc.lock", *detector_locks]:
            if not lock.is_file():
                continue
            before, after = outs(at_rev(args.rev, lock)), outs(lock.read_text())
            for key in sorted(set(before) | set(after)):
                if before.get(key) == after.get(key):
                    continue
                owner = lock.parent.name if lock in detector_locks else None
                row = judged(project, key, owner, uncertified, args.rev)
                unexplained_total += row["unexplained"]
                report.append(row)
    for row in report:
        verdict = (
            "UNEXPLAINED"
            if row["unexplained"]
            else ("uncertified only" if row["detectors"] else "reported")
        )
        print(f"{row['project']}: {row['stage']} {row['output']}: {verdict} "
              f"{', '.join(row['detectors'])} {row.get('note', '')}".rstrip())  # fmt: skip
    changed_projects = len({row["project"] for row in report})
    moved = sorted({name for row in report for name in row["detectors"]})
    print(f"detectors whose outputs changed: {', '.join(moved) or 'none'}")
    print(
        f"{len(report)} changed outputs in {changed_projects} projects; "
        f"{unexplained_total} changes not under a detector uncertified machine-independent"
    )
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, sort_keys=True) + "\n")
    return 1 if unexplained_total else 0


if __name__ == "__main__":
    sys.exit(main())
