"""A built project's detector stages or results stages, this checkout against a baseline commit,
in one run.

    python benchmarks/score_stages.py --baseline REV [--project pipeline/pendulum]
                                      [--json OUT] [detectors...]
    python benchmarks/score_stages.py --baseline REV --results [--project pipeline/cartpole]

For each detector (default: every one the project fits), runs the stages of its
`detectors/<detector>/dvc.yaml` after `fit` as `dvc repro` would (protocol version 4:
`score_clean`, `score`, `score_variants` and `cells`, SPEC §12), in that file's order; with
`--results`, the pipeline's `metrics` and `tier_metrics` stages instead (every detector's
results merged from the project's built cells). Each side runs the commands its own commit's
dvc.yaml files hold, once with this checkout's sources and once with REV's (a clone; the
command imports REV's `src` first), alternately stage by stage so that both see the same load.
Every output option (`--scores`, `--out`, `--results`, ...) points into a temporary directory
of the side's own, so a detector's `cells` reads the scores that side's scoring stages just
wrote; a side's detector stages score with the model its commit's lock records (read from the
DVC cache), so a params change that refits a detector is timed too. Prints the seconds of each
stage, the ratio and whether the two wrote the same bytes; the project's own outputs are not
touched. Both sides read the project's built inputs (its data sets; with `--results`, its
cells), so REV is a commit at this checkout's protocol version.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shlex
import subprocess
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
#: The options of the stage commands that name what a stage writes (`--scores` also what a
#: detector's `cells` stage reads: the same side's scores, written just before).
OUTPUT_OPTIONS = frozenset(
    {"--scores", "--out", "--results", "--sweep-results", "--metrics-file", "--tables",
     "--report"}
)  # fmt: skip
#: The pipeline's results stages `--results` times, by name.
RESULT_STAGES = ("metrics", "tier_metrics")


def pipeline_text(path: Path, rev: str | None) -> str:
    """A dvc.yaml (or dvc.lock) of this checkout, or as commit `rev` has it."""
    if rev is None:
        return path.read_text()
    relative = path.relative_to(ROOT).as_posix()
    return subprocess.run(["git", "show", f"{rev}:{relative}"], cwd=ROOT, check=True,
                          capture_output=True, text=True).stdout  # fmt: skip


def stage_commands(path: Path, rev: str | None, names: tuple[str, ...] | None) -> dict[str, str]:
    """Stage name -> command of a dvc.yaml: `names`, or every stage but `fit`, in file order."""
    stages = yaml.safe_load(pipeline_text(path, rev))["stages"]
    chosen = names or tuple(name for name in stages if name != "fit")
    missing = [name for name in chosen if name not in stages]
    if missing:
        raise SystemExit(f"{path.relative_to(ROOT)} at {rev or 'this checkout'} has no stage "
                         f"{', '.join(missing)}; its stages: {', '.join(stages)}")  # fmt: skip
    return {name: " ".join(stages[name]["cmd"].split()) for name in chosen}


def redirected(command: str, out: Path, model: Path | None) -> list[str]:
    """`command` with every output option under `out` and, where given, `--model` set."""
    words = shlex.split(command)
    for i, word in enumerate(words[:-1]):
        if word in OUTPUT_OPTIONS:
            words[i + 1] = str(out / words[i + 1])
        elif word == "--model" and model is not None:
            words[i + 1] = str(model)
    return words


def model_at(project: Path, name: str, rev: str | None) -> Path:
    """The fitted model of `name` that the project's lock (at `rev`) records, in the DVC cache."""
    lock = yaml.safe_load(pipeline_text(project / "detectors" / name / "dvc.lock", rev))
    md5 = lock["stages"]["fit"]["outs"][0]["md5"]
    cache = subprocess.run(["dvc", "cache", "dir"], cwd=project, check=True, capture_output=True,
                           text=True).stdout.strip()  # fmt: skip
    path = Path(cache) / "files" / "md5" / md5[:2] / md5[2:]
    if not path.is_file():
        raise SystemExit(f"{name}: the model {rev or 'this checkout'}'s lock records ({md5}) is "
                         f"not in {cache}")  # fmt: skip
    return path


def timed(project: Path, command: list[str], env: dict) -> float:
    start = time.perf_counter()
    done = subprocess.run(command, cwd=project, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{shlex.join(command)} failed:\n{done.stderr[-2000:]}")
    return time.perf_counter() - start


def tree_hash(directory: Path) -> str:
    digest = hashlib.sha256()
    for path in sorted(p for p in directory.rglob("*") if p.is_file()):
        digest.update(str(path.relative_to(directory)).encode() + path.read_bytes())
    return digest.hexdigest()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("detectors", nargs="*")
    parser.add_argument("--project", type=Path, default=Path("pipeline/pendulum"))
    parser.add_argument("--results", action="store_true", help="time the results stages")
    parser.add_argument("--baseline", metavar="REV", required=True)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    project = (ROOT / args.project).resolve()
    revs = {"baseline": args.baseline, "current": None}
    if args.results:
        units = {"results": (project / "dvc.yaml", RESULT_STAGES)}
    else:
        names = args.detectors or sorted(
            p.stem for p in (project / "models/detectors").glob("*.pkl")
        )
        units = {name: (project / "detectors" / name / "dvc.yaml", None) for name in names}
    rows, totals = {}, {"baseline": 0.0, "current": 0.0}
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "baseline-src"
        subprocess.run(["git", "clone", "-q", str(ROOT), str(base)], check=True)
        subprocess.run(["git", "-C", str(base), "checkout", "-q", args.baseline], check=True)
        pythonpath = os.pathsep.join(
            filter(None, [str(base / "src"), os.environ.get("PYTHONPATH")])
        )
        envs = {"baseline": {**os.environ, "PYTHONPATH": pythonpath}, "current": dict(os.environ)}
        for unit, (dvc_yaml, stage_names) in units.items():
            commands = {w: stage_commands(dvc_yaml, rev, stage_names) for w, rev in revs.items()}
            models = {w: None if args.results else model_at(project, unit, rev)
                      for w, rev in revs.items()}  # fmt: skip
            stages = list(dict.fromkeys([*commands["baseline"], *commands["current"]]))
            row = {"baseline": 0.0, "current": 0.0, "stages": {}}
            for stage in stages:
                for which in envs:  # alternately, stage by stage
                    if stage not in commands[which]:
                        continue
                    out = Path(tmp) / which / unit
                    command = redirected(commands[which][stage], out, models[which])
                    for i, word in enumerate(command[:-1]):  # the writers' parent folders
                        if word in OUTPUT_OPTIONS:
                            Path(command[i + 1]).parent.mkdir(parents=True, exist_ok=True)
                    seconds = timed(project, command, envs[which])
                    row["stages"].setdefault(stage, {})[which] = round(seconds, 3)
                    row[which] += seconds
            for which in envs:
                row[f"{which}_sha256"] = tree_hash(Path(tmp) / which / unit)
                totals[which] += row[which]
            same = row["baseline_sha256"] == row["current_sha256"]
            rows[unit] = {**row, "same_bytes": same}
            shown = "  ".join(
                f"{stage} {t.get('current', float('nan')) / t.get('baseline', float('nan')):.2f}x"
                for stage, t in row["stages"].items()
            )
            print(
                f"{unit:24s} baseline {row['baseline']:7.2f} s  current {row['current']:7.2f} s"
                f"  {row['current'] / row['baseline']:5.2f}x  same bytes: {same}  ({shown})",
                flush=True,
            )
    ratio = totals["current"] / totals["baseline"]
    print(f"{'all':24s} baseline {totals['baseline']:7.2f} s  current {totals['current']:7.2f} s"
          f"  {ratio:5.2f}x")  # fmt: skip
    if args.json:
        summary = {"project": str(args.project), "baseline_rev": args.baseline, **totals}
        summary |= {"stages": "results" if args.results else "detectors"}
        args.json.write_text(json.dumps({"units": rows, "total": summary}, indent=1) + "\n")


if __name__ == "__main__":
    main()
