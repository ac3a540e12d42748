"""`load_results`: any pipeline's or the suite's results as one tidy pandas DataFrame.

The frame has one row per environment, policy, fault, tier, detector and metric; `COLUMNS`
names its columns. How each results file's records become rows: `tier_rows`, `results_rows`,
`sweep_rows`, `leaderboard_rows`, `ranking_rows`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from oodrl.api.project import (
    Pipeline,
    is_pipeline,
    is_suite,
    pipeline_at,
    project_root,
    resolve_directory,
)
from oodrl.errors import ConfigError, StoreError

if TYPE_CHECKING:
    import pandas as pd

#: Every results frame's columns, in order.
COLUMNS = (
    "env", "policy", "fault", "tier", "detector", "metric", "value", "ci_low", "ci_high",
    "n_streams", "alpha", "severity", "mode", "verified", "family", "protocol",
)  # fmt: skip
#: kind -> the file holding it, relative to a pipeline's (or the suite's) directory; a
#: protocol-4 pipeline's tiers are in reports/tier_results.yaml until it is rebuilt
#: (`oodrl.metrics.tier_results.load_tier_results` reads either).
PIPELINE_FILES = {
    "results": Path("reports/results.yaml"),
    "tiers": Path("reports/tier_results.json"),
    "sweep": Path("reports/sweep_results.yaml"),
}
SUITE_FILES = {
    "leaderboard": Path("reports/leaderboard.json"),
    "ranking": Path("reports/leaderboard.json"),
}
KINDS = (*PIPELINE_FILES, *SUITE_FILES)
#: The ranking's aggregates over cells (leaderboard.json's keys), and its frame's columns.
RANKING_STATISTICS = ("iqm", "mean")
RANKING_COLUMNS = (*COLUMNS, "statistic", "n_cells")
#: A results file's name -> its kind, for a file passed as `where`.
FILE_KINDS = {
    "results.yaml": "results",
    "tier_results.json": "tiers",
    "tier_results.yaml": "tiers",
    "sweep_results.yaml": "sweep",
    "leaderboard.json": "leaderboard",
}
#: The tier of the records at the headline severity (the paper's protocol) and of the null
#: baselines in results.yaml; every sweep record's tier (its severity is in `severity`).
HEADLINE_TIER = "headline"
NULL_TIER = "null"
SWEEP_TIER = "sweep"


def load_results(
    where: str | Path = ".", kind: str | None = None, *, alpha_curves: bool = False
) -> pd.DataFrame:
    """Load a pipeline's or the suite's results as one tidy DataFrame.

    Parameters
    ----------
    where : str or path-like, default "."
        A pipeline directory (the project root is the paper's LunarLander pipeline;
        ``pipeline/<env>`` each environment's), the suite directory (``pipeline/suite``), or
        a results file (``results.yaml``, ``tier_results.json`` or a protocol-4
        ``tier_results.yaml``, ``sweep_results.yaml``, ``leaderboard.json``). A pipeline's
        name (``"cartpole"``), an environment id of the suite (``"CartPole-v1"``) or
        ``"suite"`` is looked up in the project around the working directory.
    kind : {"results", "tiers", "sweep", "leaderboard", "ranking"}, optional
        Which results. For a pipeline (default ``"results"``):

        - ``"results"``: ``reports/results.yaml``, every detector × fault at the headline
          severity (tier ``"headline"``) and the null baselines (tier ``"null"``);
        - ``"tiers"``: ``reports/tier_results.json`` (a protocol-4 pipeline's
          ``reports/tier_results.yaml`` until it is rebuilt), every detector × fault × impact
          tier (``benign``, ``mild``, ``moderate``, ``severe``) at the per-stream false-alarm
          budget α: ``detection_rate@K`` with its Clopper-Pearson CI, the delays of the
          detected streams, the achieved clean false-alarm rate and every per-episode
          metric with its bootstrap CI; from protocol version 4 also the time-aware
          per-stream rule's operating point (SPEC §24), its metrics named with the prefix
          ``time_aware_`` (``time_aware_detection_rate@K``, ...), where the record has one;
        - ``"sweep"``: ``reports/sweep_results.yaml``, every severity of the sweep (tier
          ``"sweep"``, the severity in ``severity``).

        For the suite (default ``"leaderboard"``): ``"leaderboard"``, every (environment,
        policy, fault, tier) cell of ``reports/leaderboard.json`` with each detector's
        matched AUROC and, at the tiers, its operating point (the cells whose tier was
        verified, as the leaderboard aggregates them); ``"ranking"``, the leaderboard's
        aggregates over those cells, best first (on the ``benign`` tier, where an alarm is
        a cost, the quietest first), with their stratified-bootstrap CIs: two
        more columns, ``statistic`` (``"iqm"``, the interquartile mean the leaderboard ranks
        by, or ``"mean"``) and ``n_cells``; ``env`` is None for the ranking over every
        environment, else the environments, joined by ``"|"``, where more detectors run.
        ``"results"``, ``"tiers"`` and ``"sweep"`` of the suite concatenate those of all its
        runs (the tiers of 21 runs take minutes, see Notes). For a file, its name says its
        kind.
    alpha_curves : bool, default False
        With ``kind="tiers"`` only: also each rule's operating point at every other α of its
        α curve (protocol version 4's records), the same metrics as the operating point's at
        their own ``alpha``. Off by default so that a query by metric finds one row a record:
        the operating point at the pipeline's α (``tiers.alpha``). An α that the calibration
        streams cannot support under the threshold rule has no rows.

    Returns
    -------
    pandas.DataFrame
        One row per environment, policy, fault, tier, detector and metric, with the columns
        ``env``, ``policy`` (``"0"`` for an environment's first policy), ``fault``, ``tier``,
        ``detector``, ``metric``, ``value``, ``ci_low``, ``ci_high``, ``n_streams`` (the
        streams or episodes behind the value), ``alpha`` (the per-stream false-alarm budget of
        an operating point's row; NaN on other rows), ``severity`` (σ of the fault),
        ``mode`` (``online`` or ``posthoc``), ``verified`` (whether the tier's severity was
        verified, SPEC §19) and ``family`` (observation, action or dynamics), None or NaN
        where the results hold no such value, and ``protocol``, the protocol version of the
        file the row comes from (SPEC §15, §26). The metrics of a record keep their results
        file's names (``matched_auroc``, ``detection_rate@100``, ...); from the operating
        point also ``delay_median@K``, ``delay_p90@K`` (``n_streams``: the streams detected
        within K; NaN below 5 of them), ``clean_false_alarm_rate`` (on the audit streams)
        and ``early_false_alarm_rate``. ``frame.attrs`` holds the files' protocol version,
        params hash and paths.

    Raises
    ------
    oodrl.errors.ConfigError
        An unknown `where` or `kind`: one line naming what is allowed.
    oodrl.errors.StoreError
        A results file that is missing or is not one; the suite's pipelines' results of two
        protocol versions (during a change of protocol, SPEC §26), which no frame mixes.

    Notes
    -----
    The suite's leaderboard loads in about a second (JSON). A pipeline's tier results are
    JSON from protocol 5 (``tier_results.json``: parsed in a fraction of a second); a
    protocol-4 pipeline's ``tier_results.yaml``, until it is rebuilt, is a large YAML
    document: parsing it takes 3-13 s with libyaml (PyYAML's ``CSafeLoader``, used when
    available) and far longer without.

    Examples
    --------
    >>> board = oodrl.load_results("pipeline/suite")
    >>> mild = board.query("tier == 'mild' and metric == 'detection_rate@100'")
    >>> mild.groupby("detector").value.mean().sort_values(ascending=False).head()
    """
    import pandas as pd

    rows, attrs = _load_rows(where, kind, alpha_curves)
    if alpha_curves and attrs["kind"] != "tiers":  # the kind a file's name or a directory gives
        raise ConfigError(
            f"alpha_curves=True asks for the tier results' α curves, so kind must be 'tiers'; "
            f"got {attrs['kind']!r}."
        )
    columns = RANKING_COLUMNS if attrs["kind"] == "ranking" else COLUMNS
    frame = pd.DataFrame.from_records(list(rows), columns=list(columns))
    frame["protocol"] = attrs["protocol_version"]  # one version a frame (see _suite_rows)
    frame.attrs.update(attrs)
    return frame


def _load_rows(
    where: str | Path, kind: str | None, alpha_curves: bool = False
) -> tuple[Iterable[dict], dict]:
    if kind is not None and kind not in KINDS:
        raise ConfigError(f"kind {kind!r} is not a kind of results. Allowed: {', '.join(KINDS)}.")
    path = resolve_directory(where, "where")
    if path.is_file():
        return _file_rows(path, kind, alpha_curves)
    if is_suite(path):
        return _suite_rows(path, kind or "leaderboard", alpha_curves)
    if is_pipeline(path):
        kind = kind or "results"
        if kind not in PIPELINE_FILES:
            raise ConfigError(
                f"kind {kind!r} is the suite's (pass the suite directory, pipeline/suite); a "
                f"pipeline's kinds: {', '.join(PIPELINE_FILES)}."
            )
        return _pipeline_rows(pipeline_at(path), kind, alpha_curves)
    raise ConfigError(
        f"where {str(where)!r}: a directory that is neither a pipeline (params.yaml and "
        "dvc.yaml) nor the suite (pipeline/suite). Allowed: a pipeline directory, the suite "
        f"directory, or a results file ({', '.join(FILE_KINDS)})."
    )


def _file_rows(path: Path, kind: str | None, alpha_curves: bool) -> tuple[Iterable[dict], dict]:
    file_kind = FILE_KINDS.get(path.name)
    if file_kind is None:
        raise ConfigError(
            f"where {str(path)!r}: not a results file by its name. Allowed: "
            f"{', '.join(FILE_KINDS)} (or a pipeline or suite directory)."
        )
    if kind is not None and kind != file_kind and {kind, file_kind} != {"leaderboard", "ranking"}:
        raise ConfigError(
            f"kind {kind!r} does not match {path.name}, which holds {file_kind!r} results."
        )
    kind = kind or file_kind
    if kind in SUITE_FILES:
        return _board_rows(read_json(path), kind, path)
    pipeline_dir = path.parent.parent
    pipeline = pipeline_at(pipeline_dir) if is_pipeline(pipeline_dir) else None
    return _document_rows(_read(path, kind), kind, pipeline, path, alpha_curves)


def _pipeline_rows(
    pipeline: Pipeline, kind: str, alpha_curves: bool
) -> tuple[Iterable[dict], dict]:
    from oodrl.metrics.tier_results import tier_results_path

    if kind == "tiers":
        path = tier_results_path(pipeline.directory)
    else:
        path = pipeline.directory / PIPELINE_FILES[kind]
    return _document_rows(_read(path, kind), kind, pipeline, path, alpha_curves)


def _read(path: Path, kind: str) -> Any:
    """A pipeline's results file: tier results in either form, the others YAML."""
    from oodrl.metrics.tier_results import load_tier_results

    return load_tier_results(path) if kind == "tiers" else read_yaml(path)


def _suite_rows(directory: Path, kind: str, alpha_curves: bool) -> tuple[Iterable[dict], dict]:
    if kind in SUITE_FILES:
        path = directory / SUITE_FILES[kind]
        return _board_rows(read_json(path), kind, path)
    from oodrl.metrics.stamp import one_protocol_version
    from oodrl.suite.environments import suite_runs

    root = project_root(directory) or directory.parent.parent
    rows: list[dict] = []
    files: list[str] = []
    versions: dict[str, dict[str, Any]] = {}
    for relative in suite_runs().values():
        pipeline = pipeline_at(root / relative)
        found, attrs = _pipeline_rows(pipeline, kind, alpha_curves)
        rows.extend(found)
        files.extend(attrs["files"])
        versions[attrs["files"][0]] = {"protocol_version": attrs["protocol_version"]}
    # During a change of protocol the runs hold two versions: no frame mixes them.
    version = one_protocol_version(versions)
    return rows, {"kind": kind, "protocol_version": version, "files": files}


def _document_rows(
    document: Any, kind: str, pipeline: Pipeline | None, path: Path, alpha_curves: bool
) -> tuple[Iterable[dict], dict]:
    if not isinstance(document, Mapping):
        raise StoreError(f"{path}: not a results file (a mapping of records).")
    env = pipeline.env if pipeline else None
    policy = pipeline.policy if pipeline else None
    attrs = {
        "kind": kind,
        "protocol_version": _version(document, path),
        "params_hash": document.get("params_hash"),
        "files": [str(path)],
    }
    if kind == "sweep":
        if not isinstance(document.get("sweep"), Mapping):
            raise StoreError(f"{path}: not a sweep results file (no 'sweep' mapping).")
        return list(sweep_rows(document, env, policy)), attrs
    if not isinstance(document.get("records"), list):
        raise StoreError(f"{path}: not a results file (no 'records' list).")
    if kind == "tiers":
        return list(tier_rows(document["records"], env, policy, alpha_curves)), attrs
    return list(results_rows(document["records"], env, policy)), attrs


def _board_rows(document: Any, kind: str, path: Path) -> tuple[Iterable[dict], dict]:
    if not isinstance(document, Mapping) or not isinstance(document.get("cells"), list):
        raise StoreError(f"{path}: not the suite's leaderboard.json (no 'cells' list).")
    attrs = {
        "kind": kind,
        "protocol_version": _version(document, path),
        "params_hash": document.get("params_hash"),
        "alpha": document.get("alpha"),
        "files": [str(path)],
    }
    rows = ranking_rows(document) if kind == "ranking" else leaderboard_rows(document)
    return list(rows), attrs


def _version(document: Mapping[str, Any], path: Path) -> int:
    """A results document's protocol version (an unstamped one is version 1), or a one-line
    StoreError."""
    from oodrl.metrics.stamp import protocol_version

    try:
        return protocol_version(document)
    except ValueError as error:
        raise StoreError(f"{path}: {error}.") from None


# -- reading -------------------------------------------------------------------------------
def read_yaml(path: Path) -> Any:
    """A YAML results file through libyaml when PyYAML has it (`oodrl.io.yamlio`)."""
    import yaml

    from oodrl.io import yamlio

    if not path.is_file():
        raise StoreError(f"{path}: no results file here; {_restore_hint(path)}.")
    try:
        return yamlio.load(path.read_text(encoding="utf-8"))
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise StoreError(f"{path}: not a YAML results file ({_first_line(error)}).") from None


def read_json(path: Path) -> Any:
    if not path.is_file():
        raise StoreError(f"{path}: no leaderboard here; {_restore_hint(path)}.")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as error:
        raise StoreError(f"{path}: not a JSON leaderboard ({_first_line(error)}).") from None


def _restore_hint(path: Path) -> str:
    return (
        "the pipeline writes it (results files are tracked by git: `git checkout` restores a "
        "committed one; `dvc repro` in its pipeline builds one that was never made)"
    )


def _first_line(error: BaseException) -> str:
    return " ".join(str(error).split())[:200]


# -- records -> rows -----------------------------------------------------------------------
def _number(value: Any) -> float:
    """A results value as a float; NaN where there is none (None, "beyond range")."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return math.nan
    return float(value)


def _family(fault: str | None) -> str | None:
    from oodrl.metrics.leaderboard import fault_family

    return fault_family(fault) if fault else None


def _row(
    base: Mapping[str, Any],
    metric: str,
    value: Any,
    ci: Any = None,
    n: Any = None,
    alpha: Any = None,
) -> dict:
    low, high = ci if isinstance(ci, list | tuple) and len(ci) == 2 else (None, None)
    return {
        **base,
        "metric": metric,
        "value": _number(value),
        "ci_low": _number(low),
        "ci_high": _number(high),
        "n_streams": _number(n),
        "alpha": _number(alpha),
    }


def metric_rows(base: Mapping[str, Any], metrics: Mapping[str, Any]) -> Iterator[dict]:
    """One row per metric of a record's `metrics` (mean, CI and episodes)."""
    for name, stats in sorted(metrics.items()):
        if isinstance(stats, Mapping):
            ci = [stats.get("ci_low"), stats.get("ci_high")]
            yield _row(base, name, stats.get("mean"), ci, stats.get("n_episodes"))


def operating_rows(
    base: Mapping[str, Any], point: Mapping[str, Any], prefix: str = ""
) -> Iterator[dict]:
    """The rows of a per-stream operating point (`oodrl.metrics.operating`): the detection
    rate within K with its CI, the delays of the detected streams, the false-alarm rates, at
    the point's α; `prefix` names the rule where it is not the constant one (`time_aware_`)."""
    k, alpha = point.get("k"), point.get("alpha")
    delay = point.get("delay") or {}
    n_faulty = point.get("n_faulty")

    def row(metric: str, value: Any, ci: Any, n: Any) -> dict:
        return _row(base, prefix + metric, value, ci, n, alpha)

    yield row(f"detection_rate@{k}", point.get("detection_rate"), point.get("detection_rate_ci"),
              n_faulty)  # fmt: skip
    yield row(f"delay_median@{k}", delay.get("median"), None, delay.get("n_detected"))
    yield row(f"delay_p90@{k}", delay.get("p90"), None, delay.get("n_detected"))
    yield row("clean_false_alarm_rate", point.get("clean_false_alarm_rate"),
              point.get("clean_false_alarm_ci"), point.get("n_clean"))  # fmt: skip
    yield row("early_false_alarm_rate", point.get("early_false_alarm_rate"), None, n_faulty)


def rule_points(record: Mapping[str, Any], alpha_curves: bool) -> Iterator[tuple[str, dict]]:
    """A tier record's per-stream operating points as (metric prefix, point): the constant
    rule's, then the time-aware rule's where the record has one (protocol version 4, SPEC
    §24); with `alpha_curves`, each rule's α-curve entries at its other supported α, which keep
    K and the stream counts of the rule's operating point (`oodrl.metrics.tiers.CURVE_KEYS`)."""
    from oodrl.metrics.leaderboard import TIME_AWARE_PREFIX
    from oodrl.metrics.time_aware import RULES

    points = {
        "constant": record.get("operating_point") or {},  # rows of NaN where it has none
        "time_aware": (record.get("time_aware") or {}).get("operating_point"),
    }
    curves = record.get("alpha_curve") or {}
    for rule in RULES:
        point = points[rule]
        if point is None:  # no time-aware rule: an older protocol, or too few ID scores
            continue
        prefix = "" if rule == "constant" else TIME_AWARE_PREFIX
        yield prefix, point
        if alpha_curves:
            counts = {key: point.get(key) for key in ("k", "n_faulty", "n_clean")}
            for entry in curves.get(rule) or ():
                if entry.get("supported", True) and entry.get("alpha") != point.get("alpha"):
                    yield prefix, {**counts, **entry}


def _base(env, policy, fault, tier, detector, severity, mode, verified) -> dict[str, Any]:
    return {
        "env": env, "policy": policy, "fault": fault, "tier": tier, "detector": detector,
        "severity": _number(severity), "mode": mode, "verified": verified,
        "family": _family(fault),
    }  # fmt: skip


def tier_rows(
    records: Iterable[Mapping[str, Any]],
    env: str | None,
    policy: str | None,
    alpha_curves: bool = False,
):
    """Rows of the tier results' records (`oodrl.metrics.tiers`): each rule's operating
    point (`rule_points`), then the per-episode metrics."""
    for r in records:
        base = _base(env, policy, r.get("injector"), r.get("tier"), r.get("detector"),
                     r.get("severity"), r.get("mode"), r.get("verified"))  # fmt: skip
        for prefix, point in rule_points(r, alpha_curves):
            yield from operating_rows(base, point, prefix)
        yield from metric_rows(base, r.get("metrics") or {})


def results_rows(records: Iterable[Mapping[str, Any]], env: str | None, policy: str | None):
    """Rows of results.yaml's records: anomaly records at the headline severity, null
    baselines (their fault None: one per detector and mode)."""
    for r in records:
        tier = NULL_TIER if r.get("kind") == "null" else HEADLINE_TIER
        base = _base(env, policy, r.get("injector"), tier, r.get("detector"),
                     r.get("severity"), r.get("mode"), None)  # fmt: skip
        yield from metric_rows(base, r.get("metrics") or {})


def sweep_rows(document: Mapping[str, Any], env: str | None, policy: str | None):
    """Rows of sweep_results.yaml: fault -> severity -> detector -> metrics."""
    modes = document.get("modes") or {}
    for fault, severities in sorted(document["sweep"].items()):
        for severity, detectors in sorted(severities.items()):
            for detector, metrics in sorted(detectors.items()):
                base = _base(env, policy, fault, SWEEP_TIER, detector, severity,
                             modes.get(fault), None)  # fmt: skip
                yield from metric_rows(base, metrics or {})


def leaderboard_rows(document: Mapping[str, Any]) -> Iterator[dict]:
    """Rows of the leaderboard's cells: each detector's matched AUROC (mean and CI) and, at
    the impact tiers, its operating point."""
    for cell in document["cells"]:
        for detector, evidence in sorted(cell["evidence"].items()):
            base = {
                **_base(
                    cell["environment"],
                    cell["policy"],
                    cell["fault"],
                    cell["tier"],
                    detector,
                    evidence.get("severity"),
                    None,
                    None,
                ),  # fmt: skip
                "family": cell.get("family"),
            }
            point = evidence.get("operating_point")
            auroc = evidence.get("matched_auroc") or {}
            n = point.get("n_faulty") if point else None
            yield _row(base, "matched_auroc", auroc.get("mean"),
                       [auroc.get("ci_low"), auroc.get("ci_high")], n)  # fmt: skip
            if point:
                yield from operating_rows(base, point)


def _best_first(stats: Mapping[str, Any], sign: int) -> tuple[bool, float]:
    """Sort key: the largest value first (sign 1), or the smallest (sign −1: where lower is
    better, the leaderboard's `lower_is_better`, as on harmless shifts); no value last."""
    number = _number(stats.get("value"))
    return math.isnan(number), 0.0 if math.isnan(number) else -sign * number


def ranking_rows(document: Mapping[str, Any]) -> Iterator[dict]:
    """Rows of the leaderboard's aggregates over cells, best first (on harmless shifts, the
    quietest first: the leaderboard's `lower_is_better`): its interquartile mean and
    its mean (`statistic`) with their stratified-bootstrap CIs and the cells behind them
    (`n_cells`), over every environment (env None), then per group of environments where
    more detectors run (env: their ids joined by |). Older leaderboards hold the IQM only."""
    groups: list[tuple[str | None, str, str, str, Mapping, Any]] = []
    n_cells = document.get("n_cells") or {}
    for statistic in RANKING_STATISTICS:
        for metric, tiers in (document.get(statistic) or {}).items():
            for tier, by_detector in tiers.items():
                count = (n_cells.get(metric) or {}).get(tier)
                groups.append((None, metric, tier, statistic, by_detector, count))
    for metric, tiers in (document.get("iqm_where_more_detectors_run") or {}).items():
        for tier, entries in tiers.items():
            for entry in entries:
                env = "|".join(entry["environments"])
                for statistic in RANKING_STATISTICS:
                    if statistic in entry:
                        groups.append((env, metric, tier, statistic, entry[statistic],
                                       entry.get("n_cells")))  # fmt: skip
    lower = document.get("lower_is_better") or {}
    for env, metric, tier, statistic, by_detector, count in groups:
        sign = -1 if tier in lower.get(metric, ()) else 1
        ranked = sorted(by_detector.items(), key=lambda item: _best_first(item[1], sign))
        for detector, stats in ranked:
            base = _base(env, None, None, tier, detector, None, None, None)
            ci = [stats.get("ci_low"), stats.get("ci_high")]
            row = _row(base, metric, stats.get("value"), ci)
            yield {**row, "statistic": statistic, "n_cells": _number(count)}
