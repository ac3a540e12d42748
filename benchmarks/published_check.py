"""A suite published read-only, checked as a new user meets it (SPEC §21; issue 40).

    python benchmarks/published_check.py [--cache DIR] [--projects P …] [--knob KEY=VALUE]
                                         [--suite-run] [--json OUT]

1. Serves DIR (default: this checkout's DVC cache, which `oodrl suite run` filled) read-only
   over HTTP on loopback (`python -m http.server`: GET and HEAD only), as a lab publishes its
   suite (docs/how-to/remotes.md).
2. Clones HEAD into a temporary directory with an empty DVC cache; every DVC project of the
   clone (the root, each `pipeline/<env>/`, `pipeline/suite`) gets the HTTP URL as its default
   remote (`dvc remote add --local`, so no tracked file changes).
3. In every project (or those `--projects` names, paths from the root: `.`,
   `pipeline/cartpole`), `dvc repro --pull --allow-missing`: the stages it ran (a complete
   remote: none), its exit code and seconds; then `git status --porcelain` of the clone (clean).
4. `--knob KEY=VALUE` (a dotted key of the root's params.yaml, e.g.
   `detectors.kde_density.bandwidth=0.6`): the edit, then the root's `dvc repro --pull`: the
   stages it ran against the stages that depend on the knob (those declaring the key or a parent
   of it in `params:`, and every stage downstream of them in DVC's graph; check_params re-runs
   for any edit of params.yaml). Not `--allow-missing` here: with it DVC skips an unchanged
   stage whose outputs are missing instead of pulling them, and a stage that must run then
   finds a directory several stages fill (`scores`, `data/impact`) absent, which `--pull` cannot
   fetch as a whole (docs/how-to/remotes.md).
5. `--suite-run`: a second fresh clone, the HTTP remote as the root's default remote only, and
   `oodrl suite run --workers 2`: the stages its tasks ran (none) and `git status --porcelain`.

Exit 0 when every project ran nothing and stayed clean, the knob ran exactly its stages and the
suite run ran nothing; 1 otherwise, with what differed.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from oodrl.suite.pipeline import SUITE_DIR, pipeline_dirs
from oodrl.suite.run import ran_stages
from oodrl.testing.pipeline import edit_params, run

ROOT = Path(__file__).resolve().parents[1]
REMOTE = "published"


def say(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


@contextlib.contextmanager
def served(directory: Path):
    """`python -m http.server` over `directory` on a free loopback port; yields its URL."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = subprocess.Popen(
        [sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1",
         "--directory", str(directory)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        for _ in range(100):
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 1):
                break
            time.sleep(0.1)
        yield f"http://127.0.0.1:{port}/"
    finally:
        server.terminate()
        server.wait()


def projects(clone: Path) -> list[Path]:
    return [*pipeline_dirs(clone), clone / SUITE_DIR]


def fresh_clone(dest: Path, url: str, every_project: bool) -> Path:
    run(ROOT, "git", "clone", "--quiet", "--no-hardlinks", str(ROOT), str(dest))
    for project in projects(dest) if every_project else [dest]:
        run(project, "dvc", "remote", "add", "--local", "-d", REMOTE, url)
    return dest


def dirty(clone: Path) -> list[str]:
    return run(clone, "git", "status", "--porcelain").stdout.splitlines()


def repro_every_project(clone: Path, chosen: list[str] | None) -> list[dict]:
    rows = []
    for project in projects(clone):
        if chosen and project.relative_to(clone).as_posix() not in chosen:
            continue
        name = project.relative_to(clone).as_posix()
        started = time.perf_counter()
        done = run(project, "dvc", "repro", "--pull", "--allow-missing", check=False)
        rows.append({"project": name, "exit": done.returncode, "ran": list(ran_stages(done.stdout)),
                     "seconds": round(time.perf_counter() - started, 1)})  # fmt: skip
        say(f"  {name}: exit {done.returncode}, {len(rows[-1]['ran'])} stages ran, "
            f"{rows[-1]['seconds']} s")  # fmt: skip
        if done.returncode:
            say(done.stderr.strip().splitlines()[-1] if done.stderr.strip() else done.stdout[-500:])
    return rows


def depending_stages(project: Path, key: str) -> set[str]:
    """The stages declaring `key` (or a parent of it) in `params:`, and all downstream of them."""
    import networkx as nx
    from dvc.dependency.param import ParamsDependency
    from dvc.repo import Repo

    prefixes = {".".join(key.split(".")[:n]) for n in range(1, key.count(".") + 2)}
    # A stage's `addressing` is relative to the working directory, as `dvc repro` prints it.
    with contextlib.chdir(project), Repo(".") as repo:
        graph = repo.index.graph
        direct = [
            stage for stage in graph.nodes
            for dep in stage.deps if isinstance(dep, ParamsDependency)
            and prefixes & set(dep.params)
        ]  # fmt: skip
        # DVC's graph points from a stage to the stages it depends on.
        found = {stage for s in direct for stage in [s, *nx.ancestors(graph, s)]}
        return {stage.addressing for stage in found}


def edit_knob(project: Path, key: str, value: str) -> None:
    """Set the dotted `key` of the project's params.yaml to `value` (read as YAML)."""
    import yaml

    def edit(params: dict) -> None:
        *parents, leaf = key.split(".")
        node = params
        for part in parents:
            node = node[part]
        if leaf not in node:
            raise SystemExit(f"error: {key} is not a key of {project / 'params.yaml'}")
        node[leaf] = yaml.safe_load(value)

    edit_params(project, edit)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", type=Path, default=ROOT / ".dvc" / "cache")
    parser.add_argument("--projects", nargs="+", help="only these projects (default: all)")
    parser.add_argument("--knob", help="KEY=VALUE of the root's params.yaml to edit, then repro")
    parser.add_argument("--suite-run", action="store_true", help="also `oodrl suite run`")
    parser.add_argument("--json", type=Path, help="also write the findings here")
    args = parser.parse_args(argv)
    if not (args.cache / "files").is_dir():
        raise SystemExit(f"error: {args.cache} holds no DVC cache (no files/ folder)")
    report: dict = {}
    failures: list[str] = []
    with (
        tempfile.TemporaryDirectory(prefix="oodrl-published-") as scratch,
        served(args.cache) as url,
    ):
        say(f"serving {args.cache} read-only at {url}")
        clone = fresh_clone(Path(scratch) / "clone", url, every_project=True)
        say("dvc repro --pull --allow-missing in every project of a fresh clone:")
        rows = report["projects"] = repro_every_project(
            clone, [Path(p).as_posix() for p in args.projects or []]
        )
        report["dirty"] = dirty(clone)
        failures += [f"{r['project']}: exit {r['exit']}, ran {r['ran']}" for r in rows
                     if r["exit"] or r["ran"]]  # fmt: skip
        failures += [f"git status after the restore: {line}" for line in report["dirty"]]
        if args.knob:
            key, _, value = args.knob.partition("=")
            edit_knob(clone, key, value)
            expected = depending_stages(clone, key) | {"check_params"}
            started = time.perf_counter()
            done = run(clone, "dvc", "repro", "--pull", check=False)
            ran = set(ran_stages(done.stdout))
            report["knob"] = {
                "knob": args.knob, "exit": done.returncode, "ran": sorted(ran),
                "expected": sorted(expected), "seconds": round(time.perf_counter() - started, 1),
            }  # fmt: skip
            say(f"after {args.knob}: exit {done.returncode}, {len(ran)} stages ran "
                f"({len(expected)} depend on it), {report['knob']['seconds']} s")  # fmt: skip
            if done.returncode or ran != expected:
                failures.append(
                    f"knob {args.knob}: exit {done.returncode}, ran but not expected "
                    f"{sorted(ran - expected)}, expected but not ran {sorted(expected - ran)}; "
                    f"{done.stderr.strip()[-500:]}"
                )
        if args.suite_run:
            second = fresh_clone(Path(scratch) / "suite", url, every_project=False)
            started = time.perf_counter()
            done = run(second, "oodrl", "suite", "run", "--workers", "2", check=False)
            report["suite_run"] = {
                "exit": done.returncode, "output": done.stdout[-3000:] + done.stderr[-3000:],
                "dirty": dirty(second), "seconds": round(time.perf_counter() - started, 1),
            }  # fmt: skip
            say(done.stdout + done.stderr)
            if done.returncode or report["suite_run"]["dirty"]:
                failures.append(f"oodrl suite run: exit {done.returncode}, "
                                f"git status {report['suite_run']['dirty']}")  # fmt: skip
    report["failures"] = failures
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, sort_keys=True) + "\n")
    print(f"{len(rows)} projects restored from a read-only remote: "
          f"{sum(1 for r in rows if not r['exit'] and not r['ran'])} ran no stage; "
          f"git status {'clean' if not report['dirty'] else 'not clean'}")  # fmt: skip
    for failure in failures:
        print(f"FAILED: {failure}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
