"""Old vs new `oodrl check-params --code` (the first stage of every build), timed in the same run.

    python benchmarks/stamp_speed.py --base HEAD~1 --new worktree --repeats 3 [--all]

Stage check_params writes the pipeline's code stamps (SPEC §12) before any other stage runs, in
every fresh build and after every source edit, and it runs cold: the warm stage server is only
starting then. Both revisions' `src/` are exported from git (benchmarks/numerics_speed.py's
`export`) and run in fresh interpreters with `PYTHONPATH` at them, alternating old and new so
that load on the machine hits both alike, on this checkout's projects (the root and two
environments; `--all`: all of them). Figures are CPU seconds of the command (best of
`--repeats`), the ratio new/old, and whether both wrote the same stamps, byte for byte: the
stamps hash this checkout's files whichever code computes them, so they must not differ.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

from numerics_speed import ROOT, export, revisions_parser

#: The root and two environments (one MuJoCo): the projects timed without --all.
DEFAULT_PROJECTS = (".", "pipeline/cartpole", "pipeline/hopper")


def projects(every: bool) -> list[str]:
    if not every:
        return list(DEFAULT_PROJECTS)
    from oodrl.suite.pipeline import pipeline_dirs

    return [str(d.relative_to(ROOT)) for d in pipeline_dirs(ROOT)]


def check_params(src: Path, project: str, stamps: Path) -> float:
    """CPU seconds of one cold `oodrl check-params --code` in `project`, stamps into `stamps`."""
    env = {**os.environ, "PYTHONPATH": str(src), "OODRL_WARM": "0"}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(
        [sys.executable, "-m", "oodrl", "check-params", "params.yaml", "--pipeline", "dvc.yaml",
         "--out", str(stamps / "checked"), "--code", str(stamps)],
        cwd=ROOT / project, env=env, capture_output=True, text=True, check=False,
    )  # fmt: skip
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise SystemExit(f"check-params in {project} under {src} failed:\n{done.stderr[-3000:]}")
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def stamp_bytes(stamps: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(stamps.glob("*.txt"))}


def main() -> None:
    parser = revisions_parser(__doc__.split("\n")[0])
    parser.add_argument("--all", action="store_true", help="every project, not three")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        scratch = Path(tmp)
        sources = {
            label: export(revision, scratch / label)
            for label, revision in (("old", args.base), ("new", args.new))
        }
        print(f"{'project':24s} {'old s':>7s} {'new s':>7s} {'new/old':>8s}  stamps")
        totals = dict.fromkeys(sources, 0.0)
        differing = []
        for project in projects(args.all):
            best = dict.fromkeys(sources, float("inf"))
            written = {}
            for _ in range(args.repeats):
                for label, src in sources.items():  # alternating: load hits both alike
                    stamps = scratch / "stamps" / label / project
                    stamps.mkdir(parents=True, exist_ok=True)
                    best[label] = min(best[label], check_params(src, project, stamps))
                    written[label] = stamp_bytes(stamps)
            same = "same" if written["old"] == written["new"] else "DIFFER"
            if same != "same":
                differing.append(project)
            ratio = best["new"] / best["old"]
            print(f"{project:24s} {best['old']:7.2f} {best['new']:7.2f} {ratio:8.2f}  {same}")
            totals = {label: totals[label] + best[label] for label in sources}
        ratio = totals["new"] / totals["old"]
        print(f"{'all':24s} {totals['old']:7.2f} {totals['new']:7.2f} {ratio:8.2f}")
    if differing:
        raise SystemExit(f"error: the two revisions wrote different stamps in {differing}")


if __name__ == "__main__":
    main()
