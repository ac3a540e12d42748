"""A built project's scoring or results stages, this checkout against a baseline commit, in one run.

    python benchmarks/score_stages.py --baseline REV [--project pipeline/pendulum]
                                      [--injector stuck_actuator] [--json OUT] [detectors...]
    python benchmarks/score_stages.py --baseline REV --results [--project pipeline/cartpole]

For each detector (default: every one the project fits), runs its `score@<injector>` stage
command (headline set, sweep and tiers) as `dvc repro` would; with `--results`, the `metrics` and
`tier_metrics` stage commands instead (every detector's results from the built score stores).
Each command runs once with this checkout's sources and once with REV's (a clone; the command
imports REV's `src` first), alternately so that both see the same load, each writing to a
temporary directory. A scoring command of REV scores with the model REV's lock records (read
from the DVC cache), so a params change that refits a detector is timed too. Prints the
seconds of each, the ratio and whether the two wrote the same bytes; the project's own outputs
are not touched.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def stage_command(name: str, injector: str, scores: Path, model: Path) -> list[str]:
    return [
        "oodrl", "score", name, "--injector", injector,
        "--model", str(model), "--scores", str(scores),
        "--ood", f"data/ood/{injector}.zarr", "--sweep", f"data/sweep/{injector}.zarr",
        "--tiers", f"data/tiers/{injector}.zarr",
    ]  # fmt: skip


def timed(project: Path, command: list[str], env: dict) -> float:
    start = time.perf_counter()
    subprocess.run(command, cwd=project, env=env, check=True, capture_output=True)
    return time.perf_counter() - start


#: The results stages `--results` times, by name.
RESULT_STAGES = ("metrics", "tier_metrics")


def results_command(name: str, out: Path) -> list[str]:
    return {
        "metrics": [
            "oodrl", "metrics", "--scores", "scores", "--results", f"{out}/results.yaml",
            "--sweep-results", f"{out}/sweep_results.yaml",
            "--metrics-file", f"{out}/metrics.json", "--tables", f"{out}/tables.md",
        ],
        "tier_metrics": [
            "oodrl", "tier-metrics", "--scores", "scores", "--impact", "data/impact",
            "--results", f"{out}/tier_results.yaml", "--report", f"{out}/tiers",
        ],
    }[name]  # fmt: skip


def model_at(project: Path, name: str, rev: str) -> Path:
    """The fitted model of `name` that the project's lock at `rev` records, in the DVC cache."""
    import yaml

    lock = (project / "detectors" / name / "dvc.lock").relative_to(ROOT)
    shown = subprocess.run(["git", "show", f"{rev}:{lock.as_posix()}"], cwd=ROOT, check=True,
                           capture_output=True, text=True).stdout  # fmt: skip
    md5 = yaml.safe_load(shown)["stages"]["fit"]["outs"][0]["md5"]
    cache = subprocess.run(["dvc", "cache", "dir"], cwd=project, check=True, capture_output=True,
                           text=True).stdout.strip()  # fmt: skip
    path = Path(cache) / "files" / "md5" / md5[:2] / md5[2:]
    if not path.is_file():
        raise SystemExit(f"{name}: the model {rev}'s lock records ({md5}) is not in {cache}")
    return path


def tree_hash(directory: Path) -> str:
    digest = hashlib.sha256()
    for path in sorted(p for p in directory.rglob("*") if p.is_file()):
        digest.update(str(path.relative_to(directory)).encode() + path.read_bytes())
    return digest.hexdigest()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("detectors", nargs="*")
    parser.add_argument("--project", type=Path, default=Path("pipeline/pendulum"))
    parser.add_argument("--injector", default="stuck_actuator")
    parser.add_argument("--results", action="store_true", help="time the results stages")
    parser.add_argument("--baseline", metavar="REV", required=True)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    project = (ROOT / args.project).resolve()
    if args.results:
        names = list(RESULT_STAGES)
    else:
        names = args.detectors or sorted(
            p.stem for p in (project / "models/detectors").glob("*.pkl")
        )
    rows, totals = {}, {"baseline": 0.0, "current": 0.0}
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "baseline"
        subprocess.run(["git", "clone", "-q", str(ROOT), str(base)], check=True)
        subprocess.run(["git", "-C", str(base), "checkout", "-q", args.baseline], check=True)
        pythonpath = os.pathsep.join(
            filter(None, [str(base / "src"), os.environ.get("PYTHONPATH")])
        )
        envs = {"baseline": {**os.environ, "PYTHONPATH": pythonpath}, "current": dict(os.environ)}
        for name in names:
            row = {}
            models = {"current": Path("models/detectors") / f"{name}.pkl"}
            if not args.results:
                models["baseline"] = model_at(project, name, args.baseline)
            for which, env in envs.items():
                out = Path(tmp) / which / name
                command = (
                    results_command(name, out)
                    if args.results
                    else stage_command(name, args.injector, out, models[which])
                )
                row[which] = timed(project, command, env)
                row[f"{which}_sha256"] = tree_hash(out)
                totals[which] += row[which]
            same = row["baseline_sha256"] == row["current_sha256"]
            rows[name] = {**row, "same_bytes": same}
            print(
                f"{name:24s} baseline {row['baseline']:6.2f} s  current {row['current']:6.2f} s"
                f"  {row['current'] / row['baseline']:5.2f}x  same bytes: {same}",
                flush=True,
            )
    ratio = totals["current"] / totals["baseline"]
    print(f"{'all':24s} baseline {totals['baseline']:6.2f} s  current {totals['current']:6.2f} s"
          f"  {ratio:5.2f}x")  # fmt: skip
    if args.json:
        summary = {"project": str(args.project), **totals}
        summary |= {"stages": "results"} if args.results else {"injector": args.injector}
        args.json.write_text(json.dumps({"stages": rows, "total": summary}, indent=1) + "\n")


if __name__ == "__main__":
    main()
