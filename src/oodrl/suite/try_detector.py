"""`oodrl suite try NAME --class module:Class` (SPEC §21): your detector on the whole suite.

1. The class is checked against the detector contract of `oodrl.testing` (`check_detector`, on
   the cheap linear-system trajectories with discrete and with continuous actions), built from
   the block params would hold, in seconds and before anything is written.
2. The suite's params get the detector (`benchmark.detectors` and a `detectors.NAME` block,
   like the library blocks there; an environment that lists its own `benchmark.detectors`, as
   the SAC ones do without the policy-view detectors, gets it appended to that list) and the
   pipelines' DVC files are regenerated as `oodrl
   pipeline write` does: in a scratch clone of HEAD first, where every run's params are then
   validated and the change is committed, so that the checkout is untouched until every
   pipeline has run.
3. `oodrl.suite.run`'s tasks build that commit, each pipeline in its own clone, with DVC
   targets: the detector's DVC file (its fit and scoring stages) and the stages writing the
   results the leaderboard reads. DVC restores every other stage those depend on from the
   cache (or the remote) where its lock is current and builds what is missing.
4. Then, and only then, the checkout changes: the params and DVC files written (each atomically),
   each pipeline's locks and outputs restored as `oodrl suite run` restores them, and the
   leaderboard's project reproduced. An error or a signal before this step leaves the checkout
   as it was (the scratch clones go with their `with` blocks); during it, each file is whole.
5. The detector's rank and interval at each tier of the leaderboard's lead metric is printed
   beside the top five of the leaderboard committed at HEAD.
"""

from __future__ import annotations

import json
import re
import subprocess
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from oodrl.errors import ConfigError, OodrlError

#: A detector's name: a params key, a directory (detectors/NAME/, scores/NAME/) and part of
#: DVC stage addresses, so letters, digits and underscores only.
NAME_PATTERN = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
SUITE_PARAMS = Path("pipeline") / "params.yaml"
LEADERBOARD_JSON = "reports/leaderboard.json"
#: The results files the leaderboard reads, relative to a pipeline, as the pipeline's stages
#: write them (`oodrl.stages.leaderboard.HEADLINE_RESULTS`,
#: `oodrl.metrics.tier_results.TIER_RESULTS`).
LEADERBOARD_INPUTS = ("reports/results.yaml", "reports/tier_results.json")
#: How many of the committed leaderboard's detectors are printed beside the new one.
TOP = 5
#: The identity the scratch commit is made with (the user's git may have none configured).
SCRATCH_IDENTITY = ("-c", "user.name=oodrl suite try", "-c", "user.email=oodrl@localhost")


@dataclass(frozen=True)
class TierRank:
    """The detector at one tier, in one metric: its rank among `of` detectors and its IQM with
    CI, and the committed leaderboard's top five there (name, IQM, CI)."""

    tier: str
    metric: str
    rank: int | None
    of: int
    interval: dict[str, float] | None
    committed_top: tuple[tuple[str, dict[str, float]], ...]


@dataclass(frozen=True)
class TryRun:
    """What `suite try` did, with the seconds of each part."""

    name: str
    contract_seconds: float
    prepare_seconds: float
    tasks_seconds: float
    apply_seconds: float
    leaderboard_seconds: float
    seconds: float
    ran: dict[str, tuple[str, ...]] = field(default_factory=dict)
    head_ran: tuple[str, ...] = ()
    metric: str = ""
    ranks: tuple[TierRank, ...] = ()


def parse_options(options: Sequence[str]) -> dict[str, Any]:
    """`k=v` words → the detector's parameters; each value read as YAML (10 → int)."""
    import yaml

    parsed: dict[str, Any] = {}
    for option in options:
        key, sep, text = option.partition("=")
        if not sep or not re.fullmatch(r"[A-Za-z_]\w*", key):
            raise ConfigError(f"{option!r}: a detector parameter is KEY=VALUE (e.g. n_bins=10).")
        if key == "class":
            raise ConfigError("class=…: name the class with --class module:Class.")
        if key in parsed:
            raise ConfigError(f"{key}: given twice.")
        try:
            parsed[key] = yaml.safe_load(text) if text else ""
        except yaml.YAMLError:
            raise ConfigError(f"{option!r}: the value is not YAML (quote a string).") from None
    return parsed


def detector_block(class_path: str, features: str | None, options: Sequence[str]) -> dict:
    """The `detectors.NAME` block params will hold: `class:`, `features:`, then the options."""
    if not re.fullmatch(r"[A-Za-z_][\w.]*:[A-Za-z_]\w*", class_path):
        raise ConfigError(f"--class {class_path!r}: expected module:Class, e.g. "
                          f"pyod.models.hbos:HBOS.")  # fmt: skip
    parsed = parse_options(options)
    if features is not None and "features" in parsed:
        raise ConfigError("features: given both as --features and as features=….")
    block: dict[str, Any] = {"class": class_path}
    if features is not None:
        block["features"] = features
    return {**block, **parsed}


def suite_runs(root: Path) -> list[str]:
    """The pipelines the leaderboard reads (the root's own pipeline is not one of them)."""
    from oodrl.suite.pipeline import suite_pipelines

    return [pipeline for pipeline in suite_pipelines(root) if pipeline != "."]


def check_name(root: Path, name: str, runs: Sequence[str]) -> None:
    """A new name: not a detector of any run, of the suite's params, or of the registry."""
    from oodrl.config import read_params_data
    from oodrl.detectors import DETECTORS

    if not NAME_PATTERN.fullmatch(name):
        raise ConfigError(f"NAME {name!r}: letters, digits and underscores, starting with a "
                          f"letter (it names a params block and a directory).")  # fmt: skip
    suite = read_params_data(root / SUITE_PARAMS)
    taken = {*(suite.get("detectors") or {}), *_listed(suite)}
    for run in runs:
        data = read_params_data(root / run / "params.yaml")
        taken |= {*(data.get("detectors") or {}), *_listed(data)}
    if name in taken or name in DETECTORS:
        raise ConfigError(f"{name!r} is already a detector of the suite (in {SUITE_PARAMS} or "
                          f"registered); pick another NAME, or edit its block and run `oodrl "
                          f"suite run`.")  # fmt: skip


def _listed(data: dict[str, Any]) -> list[str]:
    return list((data.get("benchmark") or {}).get("detectors") or [])


# -- 1. the contract ---------------------------------------------------------------------------
def check_contract(root: Path, run: str, name: str, block: dict[str, Any]) -> None:
    """Build the detector from `block` as a stage of `run` would and run every contract check
    of `oodrl.testing.check_detector` on it, with discrete and with continuous actions; a
    failure is one ConfigError. The fresh-process check (building it imports no torch) runs
    once, beside the others: it pays the library's imports a second time."""
    from concurrent.futures import ThreadPoolExecutor

    from oodrl.config import parse_params, read_params_data
    from oodrl.testing import detectors as contract

    data = read_params_data(root / run / "params.yaml")
    data.setdefault("detectors", {})[name] = dict(block)
    data.setdefault("benchmark", {})["detectors"] = [*_listed(data), name]
    params = parse_params(data, f"{SUITE_PARAMS} with detectors.{name}", components=False)
    fresh = params.detector(name)  # a params mistake (an unknown class, a bad value) says so

    def factory():
        return params.detector(name)

    with ThreadPoolExecutor(max_workers=1) as pool:
        in_a_fresh_process = pool.submit(contract.check_torch_free_import, fresh)
        for kind, actions in (("discrete", {}), ("continuous", {"action_dim": 2})):
            streams = contract.linear_system_trajectories(10, seed=0, **actions)
            _failing(block, name, kind, _checks, factory, streams[:6], streams[6:8], streams[8:])
        _failing(block, name, "either", in_a_fresh_process.result)


def _checks(factory, fit, calibration, evaluation) -> None:
    """`check_detector` but for its fresh-process check (`check_contract` runs that once)."""
    from oodrl.testing import detectors as contract

    fresh = factory()
    contract.check_parameters(fresh)
    contract.check_not_fitted(fresh, evaluation[0])
    fitted = factory()
    assert fitted.fit(fit) is fitted, "fit must return the detector itself"
    contract.check_scores_use_the_data(factory, fit, evaluation)
    contract.check_reproducible(factory, fit, evaluation)
    contract.check_global_random_state(factory, fit, evaluation)
    contract.check_score_is_pure(fitted, evaluation)
    contract.check_state_dim(fitted, evaluation[0])
    contract.check_threshold(fitted, calibration)
    contract.check_streaming(fitted, evaluation)
    contract.check_pickle_roundtrip(fitted, evaluation)


def _failing(block: dict[str, Any], name: str, kind: str, check, *args) -> None:
    """Run one check; its failure, whatever the plugin raised, as one ConfigError."""
    try:
        check(*args)
    except ConfigError:
        raise
    except Exception as error:  # noqa: BLE001 - the plugin's own failure, whatever it is
        what = str(error).strip().splitlines()
        why = what[0].rstrip(".") if what else type(error).__name__
        if not isinstance(error, AssertionError | OodrlError):
            why = f"{type(error).__name__}: {why}"
        raise ConfigError(
            f"--class {block['class']}: fails the detector contract of oodrl.testing ({kind} "
            f"actions): {why}; {name!r} was not added."
        ) from None


# -- 2. the change, staged in a scratch clone -----------------------------------------------------
@dataclass(frozen=True)
class Staged:
    """The scratch commit: its bundle and hash, each file it changes (None: deleted), and each
    run's DVC targets."""

    bundle: bytes
    commit: str
    files: dict[str, bytes | None]
    targets: dict[str, tuple[str, ...]]


def _round_trip():
    """A YAML parser that keeps line numbers, and a codec for the new detector's block."""
    from ruamel.yaml import YAML

    yaml = YAML()
    yaml.indent(mapping=2, sequence=4, offset=2)
    yaml.width = 100
    yaml.representer.add_representer(  # `null` stays `null`, not an empty value
        type(None), lambda r, _: r.represent_scalar("tag:yaml.org,2002:null", "null")
    )
    return yaml


# The params files are edited by inserting lines where the parser says the list and the mapping
# end, not by dumping the parsed document again: a round trip re-flows every flow-style block
# (`{a: 1, …}` over several lines) onto one line and moves the comments beside it.


def _inserted(text: str, insertions: list[tuple[int, list[str]]]) -> str:
    """`text` with each (line, lines) inserted before that line of the original text."""
    rows = text.splitlines(keepends=True)
    if rows and not rows[-1].endswith("\n"):
        rows[-1] += "\n"
    for line, lines in sorted(insertions, key=lambda insertion: -insertion[0]):
        rows[line:line] = lines  # bottom up: an earlier line keeps its number
    return "".join(rows)


def _end_of_block(text: str, document, key: str) -> int:
    """The line after the top-level `key`'s block (its last line that is not blank or a
    comment): the next top-level key's line, stepped back over blank and comment lines."""
    rows = text.splitlines()
    keys = list(document)
    later = keys[keys.index(key) + 1 :]
    end = document.lc.key(later[0])[0] if later else len(rows)
    while end > 0 and (not rows[end - 1].strip() or rows[end - 1].lstrip().startswith("#")):
        end -= 1
    return end


def _item_after(text: str, listed, name: str) -> tuple[int, list[str]]:
    """The insertion of `- name` after the last item of the parsed block list `listed`."""
    if not listed or listed.fa.flow_style():
        raise ConfigError(
            f"benchmark.detectors is empty or a flow-style list ([a, b, …]); write it one "
            f"`- name` per line for suite try to append '{name}' to it."
        )
    line, _ = listed.lc.item(len(listed) - 1)
    last = text.splitlines()[line]
    return line + 1, [last[: last.index("- ") + 2] + name + "\n"]


def add_to_params(text: str, name: str, block: dict[str, Any], inherited: list[str]) -> str:
    """The suite's params text with the detector added to `benchmark.detectors` (listed there
    now when it was inherited) and to `detectors`; every other line kept as it was."""
    import io

    from ruamel.yaml.comments import CommentedMap
    from ruamel.yaml.scalarstring import DoubleQuotedScalarString

    yaml = _round_trip()
    document = yaml.load(text) or CommentedMap()
    entry = CommentedMap(block)
    entry["class"] = DoubleQuotedScalarString(block["class"])
    buffer = io.StringIO()
    yaml.dump(CommentedMap({name: entry}), buffer)
    lines = ["  " + row for row in buffer.getvalue().splitlines(keepends=True)]
    end = len(text.splitlines())
    if "detectors" in document:
        insertions = [(_end_of_block(text, document, "detectors"), lines)]
    else:
        insertions = [(end, ["detectors:\n", *lines])]
    benchmark = document.get("benchmark")
    listed = ["  detectors:\n", *(f"    - {d}\n" for d in [*inherited, name])]
    if benchmark is None:
        insertions.append((end, ["benchmark:\n", *listed]))
    elif "detectors" in benchmark:
        insertions.append(_item_after(text, benchmark["detectors"], name))
    else:  # inherited from the root's params: listed here now
        insertions.append((document.lc.key("benchmark")[0] + 1, listed))
    return _inserted(text, insertions)


def add_to_own_list(text: str, name: str) -> str | None:
    """An environment's params text with the detector appended to the `benchmark.detectors`
    list it sets itself (the environments that leave some suite detectors out, e.g. the
    policy-view ones where the policy has no value head); None when it sets none."""
    yaml = _round_trip()
    document = yaml.load(text)
    listed = (document.get("benchmark") or {}).get("detectors") if document else None
    if listed is None:
        return None
    return _inserted(text, [_item_after(text, listed, name)])


#: Run in the scratch clone with its own code (the code the tasks run): every run's params
#: loaded and, once per environment, checked as `oodrl check-params` checks them.
VALIDATE = """
import sys
from oodrl.config import load_params
from oodrl.errors import ConfigError
from oodrl.suite.params_check import check_completely

name, runs, checked = sys.argv[1], sys.argv[2:], set()
try:
    for run in runs:
        params = load_params(f"{run}/params.yaml")
        if name not in params.benchmark.detectors:
            raise ConfigError(f"{run}/params.yaml sets its own benchmark.detectors, so {name!r} "
                              f"would not run there; add it there yourself, or drop that list.")
        if params.env.id not in checked:  # the same block: once per environment's sizes
            checked.add(params.env.id)
            try:
                check_completely(params)
            except ConfigError as error:
                raise ConfigError(f"{run}/params.yaml with detectors.{name}: {error}") from None
except ConfigError as error:
    print(" ".join(str(error).split()), file=sys.stderr)
    sys.exit(2)
print(len(checked))
"""


def stage(root: Path, name: str, block: dict[str, Any], runs: Sequence[str], scratch: Path,
          echo: Callable[[str], None]) -> Staged:  # fmt: skip
    """Clone HEAD into `scratch`, add the detector to the suite's params, regenerate every DVC
    file (`oodrl pipeline write`) and validate every run's params there, with the clone's own
    code, the code the tasks run; commit; the result."""
    import sys

    from oodrl.config import read_params_data
    from oodrl.io.layout import detector_pipeline
    from oodrl.suite.run import SuiteRunError, _run, _spawn, task_environment

    commit = _run(root, {}, "git", "rev-parse", "HEAD").stdout.strip()
    _run(scratch, {}, "git", "clone", "-q", "--no-checkout", str(root), "repo")
    clone = scratch / "repo"
    _run(clone, {}, "git", "-c", "advice.detachedHead=false", "checkout", "-q", commit)
    inherited = _listed(read_params_data(clone / SUITE_PARAMS))
    params_file = clone / SUITE_PARAMS
    params_file.write_text(add_to_params(params_file.read_text(), name, block, inherited))
    for own in sorted(params_file.parent.glob("*/params.yaml")):
        text = add_to_own_list(own.read_text(), name)
        if text is not None:
            own.write_text(text)
    _run(clone, {}, "oodrl", "pipeline", "write", "--root", ".")
    command = [sys.executable, "-c", VALIDATE, name, *runs]
    done = _spawn(command, clone, task_environment(clone))
    if done.returncode == 2:
        raise ConfigError(done.stderr.strip().splitlines()[-1])
    if done.returncode != 0:
        lines = (done.stderr or done.stdout).strip().splitlines()
        raise SuiteRunError(f"checking the params: {lines[-1] if lines else done.returncode}")
    echo(f"try: {name} passes `oodrl check-params` in every run ({done.stdout.strip()} "
         f"environments)")  # fmt: skip
    _run(clone, {}, "git", "add", "-A")
    _run(clone, {}, "git", *SCRATCH_IDENTITY, "commit", "-q", "-m", f"oodrl suite try {name}")
    changed = _run(clone, {}, "git", "diff", "--name-only", "--no-renames", commit, "HEAD")
    files = {
        path: (clone / path).read_bytes() if (clone / path).is_file() else None
        for path in changed.stdout.splitlines()
    }
    _run(clone, {}, "git", "bundle", "create", "-q", str(scratch / "try.bundle"), "HEAD")
    targets = {
        run: (detector_pipeline(name), *_results_stages(clone / run / "dvc.yaml")) for run in runs
    }
    staged = _run(clone, {}, "git", "rev-parse", "HEAD").stdout.strip()
    return Staged((scratch / "try.bundle").read_bytes(), staged, files, targets)


def _results_stages(dvc_file: Path) -> list[str]:
    """The stages of a pipeline's dvc.yaml that write the results the leaderboard reads."""
    import yaml

    stages = yaml.safe_load(dvc_file.read_text())["stages"]
    found = []
    for stage_name, body in stages.items():
        outs = [out if isinstance(out, str) else next(iter(out)) for out in _outs(body)]
        if any(out in LEADERBOARD_INPUTS for out in outs):
            found.append(f"dvc.yaml:{stage_name}")
    return found


def _outs(body: dict[str, Any]) -> list:
    body = body.get("do", body)
    return [*(body.get("outs") or []), *(body.get("metrics") or [])]


# -- the command -----------------------------------------------------------------------------------
def try_detector(
    root: Path,
    name: str,
    class_path: str,
    features: str | None = None,
    options: Sequence[str] = (),
    workers: int = 2,
    echo: Callable[[str], None] = print,
) -> TryRun:
    """Check, add and run detector `name` on every run of the suite; print its ranks."""
    from oodrl.suite.run import _ending_processes_on_signals

    root = root.resolve()
    if workers < 1:
        raise ConfigError(f"--workers must be >= 1. Got {workers} instead.")
    start = time.perf_counter()
    from oodrl.suite.checkout_lock import checkout_lock

    with checkout_lock(root, "suite try"), _ending_processes_on_signals():
        return _try(root, name, class_path, features, options, workers, echo, start)


def _try(root: Path, name: str, class_path: str, features: str | None,
         options: Sequence[str], workers: int, echo: Callable[[str], None],
         start: float) -> TryRun:  # fmt: skip
    from dataclasses import replace

    from oodrl.suite.pipeline import SUITE_DIR
    from oodrl.suite.run import (
        _cache_dir,
        _check_remote,
        _dvc_config,
        _local_tasks,
        _push,
        _refuse_uncommitted_inputs,
        _run,
        default_remote,
        ran_stages,
        restore_project,
    )
    from oodrl.suite.scratch import TRY_FOLDER, remove_dead_runs, working_folder

    remove_dead_runs(root)
    runs = suite_runs(root)
    block = detector_block(class_path, features, options)
    check_name(root, name, runs)
    echo(f"try: checking {name} ({class_path}) against the detector contract of oodrl.testing")
    began = time.perf_counter()
    check_contract(root, runs[0], name, block)
    contract_seconds = time.perf_counter() - began
    echo(f"try: contract passed in {contract_seconds:.1f} s; checking the DVC remote and the "
         f"checkout")  # fmt: skip
    began = time.perf_counter()
    remote = default_remote(root)
    read_only = _check_remote(root, remote) if remote is not None else None
    if read_only:
        remote = replace(remote, writable=False)
        echo(f"try: remote {remote.name!r} is read-only ({read_only}): restoring from it, "
             f"pushing nothing")  # fmt: skip
    _refuse_uncommitted_inputs(root, [".", *runs, SUITE_DIR.as_posix()])
    committed = committed_leaderboard(root)
    with working_folder(TRY_FOLDER) as scratch:
        staged = stage(root, name, block, runs, Path(scratch), echo)
    prepare_seconds = time.perf_counter() - began
    echo(f"try: {len(runs)} runs; each builds {name}'s fit and scoring stages and its results "
         f"stages in its own clone ({workers} at a time)")  # fmt: skip
    job = {
        "bundle": staged.bundle,
        "commit": staged.commit,
        "remote": remote,
        "shared_cache": _cache_dir(root, [".", *runs, SUITE_DIR.as_posix()]),
        "targets": staged.targets,
    }
    began = time.perf_counter()
    built = list(_local_tasks(root, runs, job, workers, echo))  # all, before the checkout changes
    tasks_seconds = time.perf_counter() - began
    echo(f"try: every run built in {tasks_seconds:.1f} s; writing {SUITE_PARAMS}, "
         f"{len(staged.files) - 1} DVC files and each run's results into the checkout")  # fmt: skip
    from oodrl.io.fileio import atomic_write_bytes

    began = time.perf_counter()
    with _dvc_config(remote) as env:
        for path, content in staged.files.items():
            if content is None:
                (root / path).unlink(missing_ok=True)
            else:
                atomic_write_bytes(root / path, content)
        for each in built:
            restore_project(root, each, remote, env)
        apply_seconds = time.perf_counter() - began
        echo(f"try: reproducing the leaderboard ({SUITE_DIR.as_posix()})")
        began = time.perf_counter()
        done = _run(root / SUITE_DIR, env, "dvc", "repro", *(["--pull"] if remote else []))
        if remote and remote.writable:
            _push(root / SUITE_DIR, env)
    leaderboard_seconds = time.perf_counter() - began
    head_ran = tuple(f"{SUITE_DIR.as_posix()}:{s}" for s in ran_stages(done.stdout))
    board = json.loads((root / SUITE_DIR / LEADERBOARD_JSON).read_text())
    metric, ranks = ranks_of(name, board, committed)
    result = TryRun(
        name, contract_seconds, prepare_seconds, tasks_seconds, apply_seconds,
        leaderboard_seconds, time.perf_counter() - start,
        {each.pipeline: each.ran for each in built}, head_ran, metric, tuple(ranks),
    )  # fmt: skip
    for line in report(result, board, committed is not None):
        echo(line)
    return result


# -- 5. the ranks ------------------------------------------------------------------------------
def committed_leaderboard(root: Path) -> dict | None:
    """The leaderboard's JSON as committed at HEAD, or None where HEAD has none."""
    from oodrl.suite.pipeline import SUITE_DIR

    path = (SUITE_DIR / LEADERBOARD_JSON).as_posix()
    done = subprocess.run(["git", "show", f"HEAD:{path}"], cwd=root, capture_output=True,
                          text=True, check=False)  # fmt: skip
    if done.returncode != 0:
        return None
    try:
        return json.loads(done.stdout)
    except ValueError:
        return None


def _ranked(scores: dict[str, dict[str, float]]) -> list[str]:
    """Best IQM first, ties by name (as `oodrl.metrics.leaderboard.Aggregate.ranked`)."""
    return sorted(scores, key=lambda d: (-scores[d]["value"], d))


def ranks_of(name: str, board: dict, committed: dict | None) -> tuple[str, list[TierRank]]:
    """The lead metric, and at each tier the detector's rank and IQM (in the lead metric, or
    where a tier has none, such as the headline severity's, the first metric it has) beside
    the committed leaderboard's top five (the new board's where none is committed)."""
    lead = board["lead"]["metric"]
    reference = committed if committed is not None else board
    ranks = []
    for tier in board["tiers"]:
        metrics = [lead, *(m for m in board["metrics"] if m != lead)]
        metric = next((m for m in metrics if board["iqm"].get(m, {}).get(tier)), lead)
        scores = board["iqm"].get(metric, {}).get(tier, {})
        order = _ranked(scores)
        before = reference.get("iqm", {}).get(metric, {}).get(tier, {})
        top = tuple((d, before[d]) for d in _ranked(before)[:TOP])
        rank = order.index(name) + 1 if name in scores else None
        ranks.append(TierRank(tier, metric, rank, len(order), scores.get(name), top))
    return lead, ranks


def _interval(value: dict[str, float]) -> str:
    return f"{value['value']:.3f} [{value['ci_low']:.3f}, {value['ci_high']:.3f}]"


def report(result: TryRun, board: dict, committed: bool) -> list[str]:
    """The lines printed at the end: per tier, the rank and IQM, then the top five."""
    level = board.get("leaderboard_params", {}).get("ci", 0.95)
    against = "the committed leaderboard's" if committed else "(none committed at HEAD) the new"
    lines = [
        f"try: {result.name} on the leaderboard, {result.metric}, the IQM over cells with its "
        f"{level:.0%} CI, beside {against} top {TOP}:"
    ]
    for rank in result.ranks:
        mine = (
            f"rank {rank.rank} of {rank.of}, {_interval(rank.interval)}"
            if rank.rank is not None and rank.interval is not None
            else "not scored at this tier"
        )
        numbered = enumerate(rank.committed_top, 1)
        top = "; ".join(f"{i}. {d} {_interval(v)}" for i, (d, v) in numbered)
        where = rank.tier if rank.metric == result.metric else f"{rank.tier} ({rank.metric})"
        lines.append(f"  {where}: {result.name} {mine} | top {TOP}: {top or 'none'}")
    lines.append(
        f"try: done in {result.seconds:.1f} s (contract {result.contract_seconds:.1f} s, "
        f"staging {result.prepare_seconds:.1f} s, fit and scoring {result.tasks_seconds:.1f} s, "
        f"restoring {result.apply_seconds:.1f} s, leaderboard {result.leaderboard_seconds:.1f} "
        f"s); {SUITE_PARAMS} and the DVC files now hold {result.name}: commit them to keep it, "
        f"and `oodrl suite run` then builds the render stages it left stale"
    )
    return lines
