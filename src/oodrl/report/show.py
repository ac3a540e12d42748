"""`oodrl show PATH`: the tables of a results.yaml, sweep_results.yaml or run_meta.yaml (its
detectors' cost beside their accuracy) as terminal text."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from oodrl.errors import ConfigError, StoreError
from oodrl.io import yamlio
from oodrl.report.tables import cost_table, render_tables, sweep_tables
from oodrl.suite.pipeline import CHECK_STAGE

RECORD_KEYS = frozenset({"kind", "detector", "injector", "mode", "severity", "metrics"})
#: `injector` was called `anomaly` in results files written before the rename.
OLD_RECORD_KEYS = RECORD_KEYS - {"injector"} | {"anomaly"}


def load_report(path: str | Path) -> tuple[str, dict[str, Any]]:
    """("results" | "sweep" | "meta", contents) of a report file; StoreError for anything else."""
    path = Path(path)
    if not path.is_file():
        raise StoreError(
            f"No report file at '{path}'. Pass a results.yaml, sweep_results.yaml or "
            "run_meta.yaml (the pipeline writes them to reports/: `dvc checkout` restores a built "
            "one from the cache, `dvc pull` from a remote; `dvc repro` builds one that none holds)."
        )
    try:
        data = yamlio.load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise StoreError(f"'{path}' is not a YAML report file: {error}") from None
    if isinstance(data, Mapping) and isinstance(data.get("records"), list):
        bad = [i for i, r in enumerate(data["records"]) if not _is_record(r)]
        if bad:
            raise StoreError(
                f"Record {bad[0]} of '{path}' is not a results record; each record needs the "
                f"keys {', '.join(sorted(RECORD_KEYS))}."
            )
        return "results", dict(data)
    if isinstance(data, Mapping) and isinstance(data.get("sweep"), Mapping):
        return "sweep", dict(data)
    if isinstance(data, Mapping) and isinstance(data.get("cost"), Mapping):
        return "meta", dict(data)
    raise StoreError(
        f"'{path}' is neither a results file (a 'records' list), a sweep file (a 'sweep' "
        "mapping) nor a run_meta.yaml with detector costs (a 'cost' mapping)."
    )


def _is_record(record: Any) -> bool:
    return (
        isinstance(record, Mapping)
        and (set(record) >= RECORD_KEYS or set(record) >= OLD_RECORD_KEYS)
        and isinstance(record["metrics"], Mapping)
    )


def show(path: str | Path, max_us_per_step: float | None = None) -> str:
    """The markdown tables of a results or sweep file, for printing in a terminal; of a
    run_meta.yaml, its detectors' cost beside their accuracy in the results.yaml beside it
    (if there is one), only those at most `max_us_per_step` (median) when given."""
    return _shown(path, max_us_per_step)[1]


def shown(path: str | Path, max_us_per_step: float | None = None) -> str:
    """What `oodrl show` prints: the protocol version of the numbers (SPEC §26; the results
    beside a run_meta.yaml), then `show`'s tables."""
    version, text = _shown(path, max_us_per_step)
    return f"{version}\n\n{text}" if version else text


def _shown(path: str | Path, max_us_per_step: float | None) -> tuple[str | None, str]:
    kind, data = load_report(path)
    if kind != "meta" and max_us_per_step is not None:
        raise ConfigError(
            f"--max-us-per-step filters a run_meta.yaml's detector costs; '{path}' is a {kind} "
            "file. Pass reports/run_meta.yaml."
        )
    if kind == "results":
        return version_line(data), render_tables(data)
    if kind == "sweep":
        return version_line(data), sweep_tables(data)
    results_path = Path(path).with_name("results.yaml")
    results = load_report(results_path)[1] if results_path.is_file() else None
    table = cost_table(data["cost"], results, max_us_per_step)
    return (version_line(results) if results is not None else None), table


def version_line(data: Mapping[str, Any]) -> str:
    """Which protocol the numbers follow (SPEC §15, §26): a change of protocol leaves some
    pipelines' results at the previous version for a while."""
    from oodrl.metrics.stamp import protocol_version

    try:
        version = protocol_version(data)
    except ValueError as error:
        raise ConfigError(f"{error}.") from None
    unstamped = " (unstamped results)" if "protocol_version" not in data else ""
    return f"Protocol version {version}{unstamped}."


#: What `dvc status` says of a dependency or output absent from the workspace, as in a clone
#: that did not pull it: nothing is known to have changed, and the lock still records it.
ABSENT = frozenset({"deleted", "not in cache"})


def _changed(entry: Any) -> bool:
    """Whether one entry of a stage's `dvc status --json` list says something changed: its
    command, a params value (even a deleted one), a file that is there but differs."""
    if not isinstance(entry, Mapping):  # "changed command", "always changed"
        return True
    return any(
        isinstance(state, Mapping) or state not in ABSENT
        for changes in entry.values()  # "changed deps" / "changed outs": {path: state}
        for state in (changes.values() if isinstance(changes, Mapping) else [changes])
    )


def stale_warning(path: str | Path) -> str | None:
    """A warning when DVC finds that a pipeline output's inputs changed since it was computed
    (SPEC §22: no number shown without a word when it may be stale); None when current, or
    when the file is not a DVC output (then nothing is known of its inputs). Inputs absent from
    the workspace (a fresh clone that pulled nothing) are no change: the committed result is
    what the lock records (SPEC §21).

    DVC's `status --with-deps` of a file checks only the stage that writes it, so an oodrl
    project's `check_params` is asked too: every params file and source edit reaches the other
    stages through it (a source edit outside the file's code stamps changes nothing: "may")."""
    import json
    import os
    import shutil
    import subprocess
    import sys

    path = Path(path).resolve()
    project = next((d for d in path.parents if (d / "dvc.yaml").is_file()), None)
    # The dvc installed beside this Python first: the one of oodrl's own environment.
    dvc = shutil.which("dvc", path=os.pathsep.join([str(Path(sys.executable).parent),
                                                    os.environ.get("PATH", "")]))  # fmt: skip
    if project is None or dvc is None:
        return None
    target = path.relative_to(project).as_posix()
    try:
        declared = yamlio.load((project / "dvc.yaml").read_text(encoding="utf-8"))["stages"]
        targets = [target, *([CHECK_STAGE] if CHECK_STAGE in declared else [])]
    except (yaml.YAMLError, UnicodeDecodeError, TypeError, KeyError):
        targets = [target]  # DVC itself says what is wrong with such a dvc.yaml
    done = subprocess.run(
        [dvc, "status", "--with-deps", "--json", *targets],
        cwd=project, capture_output=True, text=True, check=False,
    )  # fmt: skip
    # A failure means the file is no output DVC knows (its inputs are then unknown).
    try:
        status = json.loads(done.stdout) if done.returncode == 0 else {}
    except ValueError:
        status = {}
    if not any(_changed(entry) for entries in status.values() for entry in entries):
        return None
    where = os.path.relpath(project)
    return (
        f"warning: {target} may be stale: its stage or an input changed since it was computed "
        f"(`dvc status --with-deps {' '.join(targets)}`{'' if where == '.' else f' in {where}'} "
        "lists what)"
    )
