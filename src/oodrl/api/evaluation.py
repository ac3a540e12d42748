"""`evaluate`: one detector object on one environment's committed policy and impact tiers, in
this process, by the pipeline's own protocol code.

The steps are the pipeline's stages, called as functions on stores in a temporary directory
(nothing is copied from them): `oodrl.stages.collect` collects the clean ID set (the
detector's fit and calibration split) and the held-out calibration, audit and twin streams;
`oodrl.stages.impact.collect_tiers` each fault's tier streams at the tier severities the
pipeline committed; the detector is fitted and calibrated as `oodrl.stages.fit` does and
pickled; `oodrl.stages.score` scores every set with a freshly loaded copy; and
`oodrl.metrics.tiers.compute_tier_results`, the tier metrics' own entry point, turns the scores
into the tier results' records, with the evaluated detector as the benchmark's only one and
the committed impact records (curve and returns, the chosen tiers) as its faults'. So at the
pipeline's own params (`size="full"`) a built-in detector's numbers are the pipeline's, bit for bit
(tests/api/test_evaluate.py checks it on a tiny pipeline).
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from oodrl.api.project import Pipeline, pipeline_at, resolve_directory
from oodrl.errors import ConfigError, StoreError

if TYPE_CHECKING:
    import pandas as pd

    from oodrl.config import Params
    from oodrl.core.detector import BaseDetector

#: "tiny"'s calibration streams: the fewest the rule allows (`_calibration_needed`).
FEWEST = 0
#: The evaluation sizes: `tiers` keys replaced in the pipeline's params. "full" is the
#: pipeline's own params. "small" keeps its protocol and its calibration streams, so its
#: per-stream threshold is the pipeline's, and scores the first `n_streams` of each cell's
#: faulty streams (with their clean twins) and the first `n_audit` audit streams: the same
#: quantities, estimated on fewer streams. "tiny" also calibrates on the fewest streams the
#: per-stream rule allows at the pipeline's α (and δ), a higher threshold than the pipeline's.
SIZES: dict[str, dict[str, int]] = {
    "full": {},
    "small": {"n_audit": 100, "n_streams": 50},
    "tiny": {"n_calibration": FEWEST, "n_audit": 10, "n_streams": 10},
}

#: Overrides every call's `size` (tests and documentation builds run the examples fast).
SIZE_VARIABLE = "OODRL_EVALUATE_SIZE"
#: Bootstrap resamples at size "tiny" (the others keep the pipeline's `metrics.n_boot`).
TINY_N_BOOT = 100
#: The environment `evaluate` uses when none is named.
DEFAULT_ENV = "cartpole"


def evaluate(
    detector: Any,
    env: str | os.PathLike = DEFAULT_ENV,
    faults: Sequence[str] | None = None,
    tiers: Sequence[str] = ("mild",),
    size: str = "small",
    seed: int | None = None,
    *,
    name: str | None = None,
) -> pd.DataFrame:
    """Evaluate a detector object on one environment's committed policy and impact tiers.

    The detector is fitted on the pipeline's clean fit streams and calibrated on its held-out
    ones (in place: afterwards it can be deployed with `OodMonitor`), then scored on the clean
    calibration, audit and twin streams and on each fault's streams at each tier, live from
    the onset, with the pipeline's own protocol code and seeds (`oodrl.protocol`,
    `oodrl.stages`, `oodrl.metrics`): the per-stream alarm threshold at the pipeline's
    false-alarm budget α, detection within K steps, matched metrics against each stream's
    clean twin, bootstrap and Clopper-Pearson CIs. It runs in the pipeline's directory, as
    the stages do (a detector's params may name paths relative to it, like the policy view's
    ``policy: models/policy.pt``), and writes nothing outside a temporary directory.

    Parameters
    ----------
    detector : BaseDetector or library outlier model
        An unfitted detector object: any `oodrl.BaseDetector` instance that passes
        `oodrl.check_detector` (a plugin's, a built-in's, a `LibraryDetector`), or an instance
        of a PyOD, scikit-learn or river outlier model (e.g. ``pyod.models.knn.KNN()``),
        which is wrapped on the ``state`` feature view as the suite wraps library classes
        (SPEC §17).
    env : str or path-like, default "cartpole"
        The pipeline: a name under ``pipeline/`` (``"cartpole"``, ``"cartpole_policy1"``),
        an environment id of the suite (``"CartPole-v1"``: its first policy), or a pipeline
        directory. Its committed policy (``models/policy.pt``) is the agent, its params the
        protocol, and the tier severities are the ones its committed tier results hold
        (``reports/tier_results.json``; a protocol-4 pipeline's ``reports/tier_results.yaml``).
    faults : sequence of str, optional
        Faults of the pipeline (its ``benchmark.injectors``); default: every fault with one of
        `tiers` reachable.
    tiers : sequence of str, default ("mild",)
        Impact tiers: ``benign``, ``mild``, ``moderate``, ``severe``. A tier a fault cannot
        reach has no rows.
    size : {"small", "full", "tiny"}, default "small"
        ``"full"``: the pipeline's params (in the suite's pipelines 200 calibration streams,
        200 audit streams and 100 faulty streams per cell, each with its clean twin).
        ``"small"``: the same protocol, fit data and calibration streams (so the same
        per-stream threshold), scored on the first 50 faulty streams of each cell and the
        first 100 audit streams: the same quantities as at full size, estimated on half the
        streams (wider CIs). ``"tiny"``: 10 faulty and 10 audit streams, calibration on the
        fewest streams the per-stream rule allows at the pipeline's α (a higher threshold
        than the pipeline's) and 100 bootstrap resamples, for tests and documentation builds:
        too few streams to rank detectors. The environment variable
        ``OODRL_EVALUATE_SIZE``, when set, overrides `size`.
    seed : int, optional
        The protocol's base seed (default: the pipeline's ``seed``). Another seed draws other
        streams: a fresh-data check of the same tiers.
    name : str, optional
        The detector's name in the frame (default: its class's ``name``).

    Returns
    -------
    pandas.DataFrame
        The tidy frame of `oodrl.load_results` (kind ``"tiers"``): one row per fault, tier and
        metric, with ``detection_rate@K`` (its Clopper-Pearson CI, ``n_streams`` faulty
        streams), ``delay_median@K`` and ``delay_p90@K`` of the streams detected within K,
        ``clean_false_alarm_rate`` on the audit streams, ``matched_auroc`` and every other
        per-episode metric with its bootstrap CI; plus two rows of the detector's streaming
        cost, ``step_us_median`` and ``step_us_p99`` (µs per step, one thread; fault and tier
        None), and ``fit_s`` (seconds to fit and calibrate). ``frame.attrs`` holds the size,
        the streams per set, α, K, the seed and the pipeline's directory.

    Raises
    ------
    oodrl.errors.ConfigError
        An unknown environment, fault, tier or size, or an object that is no detector: one
        line naming what is allowed.

    Examples
    --------
    >>> from pyod.models.knn import KNN
    >>> frame = oodrl.evaluate(KNN(n_neighbors=5), env="cartpole")
    >>> frame.query("metric == 'detection_rate@100'")[["fault", "value", "ci_low", "ci_high"]]
    """
    import pandas as pd

    from oodrl.api.results import COLUMNS, tier_rows
    from oodrl.metrics.stamp import PROTOCOL_VERSION
    from oodrl.metrics.tier_results import tier_results_path

    size = os.environ.get(SIZE_VARIABLE) or size
    if size not in SIZES:
        raise ConfigError(f"size {size!r} is not an evaluation size. Allowed: {', '.join(SIZES)}.")
    detector = as_detector(detector)
    label = name or detector.name or type(detector).__name__
    pipeline = pipeline_at(resolve_directory(env, "env"))
    params = sized_params(pipeline, size, seed)
    chosen = _tiers(tiers)
    impacts = committed_impacts(pipeline, params.benchmark.injectors)
    committed = {fault: impact["tiers"] for fault, impact in impacts.items()}
    plan = _plan(committed, _faults(faults, params.benchmark.injectors), chosen)
    if not plan:
        raise ConfigError(
            f"no fault of {pipeline.directory} reaches tier {', '.join(chosen)} (committed "
            f"tiers in {tier_results_path(pipeline.directory)}). Allowed: faults "
            f"with a reachable tier: {', '.join(sorted(_reachable(committed))) or 'none'}."
        )
    params = _with_injectors(params, list(plan))
    with tempfile.TemporaryDirectory(prefix="oodrl-evaluate-") as tmp:
        records, cost = _run(params, pipeline, detector, label, plan, impacts, Path(tmp))
    rows = list(tier_rows(records, pipeline.env, pipeline.policy))
    rows += _cost_rows(pipeline, label, cost)
    frame = pd.DataFrame.from_records(rows, columns=list(COLUMNS))
    frame["protocol"] = PROTOCOL_VERSION  # this code's: what these records follow
    frame.attrs.update({
        "kind": "tiers",
        "size": size,
        "pipeline": str(pipeline.directory),
        "seed": params.seed,
        "alpha": params.tiers.alpha,
        "k": params.tiers.k,
        "n_calibration": params.tiers.n_calibration,
        "n_audit": params.tiers.n_audit,
        "n_streams": params.tiers.n_streams,
        "n_boot": params.metrics.n_boot,
    })  # fmt: skip
    return frame


# -- what is evaluated -----------------------------------------------------------------------
def as_detector(obj: Any) -> BaseDetector:
    """`obj` if it is an oodrl detector; a library outlier model wrapped as the suite wraps its
    class (`oodrl.detectors.library`); else a one-line ConfigError."""
    from oodrl.core.detector import BaseDetector
    from oodrl.detectors.library import ALLOWED_CLASSES, library_api, library_detector_class

    if isinstance(obj, BaseDetector):
        return obj
    if isinstance(obj, type):
        raise ConfigError(
            f"detector {obj.__name__} is a class; pass an instance of it (an unfitted "
            "detector object)."
        )
    if library_api(obj) is not None:
        # The arguments the model was given, as a params block would name them (SPEC §17): a
        # key oodrl reads in its place (HBOS's `alpha`) is refused, never silently taken.
        block = _given_arguments(obj)
        detector = library_detector_class(type(obj)).from_params({"features": "state", **block})
        detector.refuse_shadowed(block)
        return detector
    raise ConfigError(
        f"detector {type(obj).__name__!r} is no detector object. Allowed: an instance of "
        f"{ALLOWED_CLASSES}."
    )


def _given_arguments(model: Any) -> dict[str, Any]:
    """The constructor arguments of a library model that differ from its class's defaults."""
    import inspect

    arguments = _arguments(model)
    if arguments is None:
        return {}
    try:
        # A default instance's, not the signature's: river turns some arguments into other
        # values as it stores them (HalfSpaceTrees' `limits`, None, into a defaultdict).
        defaults = _arguments(type(model)()) or {}
    except Exception:  # a class with required arguments: its signature's defaults
        try:
            signature = inspect.signature(type(model)).parameters
        except (TypeError, ValueError):
            signature = {}
        defaults = {key: parameter.default for key, parameter in signature.items()}
    given = {}
    for key, value in arguments.items():
        default = defaults.get(key, inspect.Parameter.empty)
        try:
            same = default is value or bool(default == value)
        except Exception:  # an array or another value without one truth value
            same = False
        if not same:
            given[key] = value
    return given


def _arguments(model: Any) -> dict[str, Any] | None:
    """A library model's constructor arguments as it stores them: scikit-learn's and PyOD's
    `get_params`, river's `_get_params`; None for a model that lists none."""
    if callable(getattr(model, "get_params", None)):
        return model.get_params(deep=False)
    if callable(getattr(model, "_get_params", None)):
        return model._get_params()
    return None


def sized_params(pipeline: Pipeline, size: str, seed: int | None) -> Params:
    """The pipeline's params at an evaluation size (`SIZES`), its seed replaced by `seed`."""
    from oodrl.config import parse_params, read_params_data

    data = read_params_data(pipeline.params_path)
    params = parse_params(data, str(pipeline.params_path), components=False)
    tiers = {key: min(value, getattr(params.tiers, key)) for key, value in SIZES[size].items()}
    if tiers.get("n_calibration") == FEWEST:
        tiers["n_calibration"] = min(_calibration_needed(params), params.tiers.n_calibration)
    if tiers:
        data = {**data, "tiers": {**data.get("tiers", {}), **tiers}}
        if size == "tiny":
            data["metrics"] = {**data.get("metrics", {}), "n_boot": TINY_N_BOOT}
    if seed is not None:
        data = {**data, "seed": seed}
    return parse_params(data, str(pipeline.params_path), components=False)


def _calibration_needed(params: Params) -> int:
    from oodrl.metrics.operating import (
        min_calibration_streams,
        min_calibration_streams_conditional,
    )

    tiers = params.tiers
    if tiers.threshold_rule == "episode_max_conditional":
        return min_calibration_streams_conditional(tiers.alpha, tiers.delta)
    return min_calibration_streams(tiers.alpha)


def _with_injectors(params: Params, faults: list[str]) -> Params:
    """`params` whose benchmark lists only `faults` (the tier metrics iterate over them)."""
    from oodrl.config import parse_params

    data = params.model_dump()
    data["benchmark"]["injectors"] = faults
    return parse_params(data, "params", components=False)


def _tiers(tiers: Sequence[str]) -> list[str]:
    from oodrl.protocol.impact import LEVELS

    chosen = [tiers] if isinstance(tiers, str) else list(tiers)
    unknown = [t for t in chosen if t not in LEVELS]
    if unknown or not chosen:
        raise ConfigError(
            f"tiers {unknown or chosen!r}: not impact tiers. Allowed: {', '.join(LEVELS)}."
        )
    return [t for t in LEVELS if t in chosen]


def _faults(faults: Sequence[str] | None, known: Sequence[str]) -> list[str]:
    if faults is None:
        return list(known)
    chosen = [faults] if isinstance(faults, str) else list(faults)
    unknown = [f for f in chosen if f not in known]
    if unknown or not chosen:
        raise ConfigError(
            f"faults {unknown or chosen!r}: not faults of this pipeline. Allowed: "
            f"{', '.join(known)}."
        )
    return chosen


# -- the committed tiers ---------------------------------------------------------------------
def committed_impacts(pipeline: Pipeline, faults: Sequence[str]) -> dict[str, dict[str, Any]]:
    """fault -> its impact record as the pipeline committed it (`clean_return`,
    `random_return`, `curve`, `tiers`: tier -> {severity, verification, ...}, and
    `severity_steps` where the fault has them): the `impact` section of its tier results
    (`oodrl.metrics.tier_results.load_tier_results`), git-tracked; for a fault they lack,
    data/impact/<fault>.yaml (the impact stage's output, where present)."""
    from oodrl.metrics.tier_results import load_tier_results, tier_results_path
    from oodrl.protocol.tiers import IMPACT_DIR, impact_path, read_impact

    section: dict[str, Any] = {}
    if tier_results_path(pipeline.directory).is_file():
        section = load_tier_results(pipeline.directory, keys=["impact"]).get("impact") or {}
    found: dict[str, dict[str, Any]] = {}
    for fault in faults:
        if fault in section:
            found[fault] = section[fault]
            continue
        path = impact_path(pipeline.directory / IMPACT_DIR, fault)
        if path.is_file():
            document = read_impact(path, fault)
            found[fault] = {
                "clean_return": document["clean_return"],
                "random_return": document["random_return"],
                **{k: v for k, v in document["fault"].items() if k in _IMPACT_KEYS},
            }
    if not found:
        raise StoreError(
            f"{pipeline.directory}: no committed impact tiers (reports/tier_results.json, a "
            "protocol-4 reports/tier_results.yaml, or data/impact/<fault>.yaml); `git checkout` "
            "restores the committed results, `dvc repro tier_metrics` in the pipeline builds them."
        )
    return found


#: A fault's keys in the tier results' `impact` section besides the returns.
_IMPACT_KEYS = ("tiers", "curve", "severity_steps")


def _reachable(committed: Mapping[str, Mapping[str, Any]]) -> dict[str, list[str]]:
    from oodrl.protocol.impact import tier_severity

    return {
        fault: [t for t, record in tiers.items() if tier_severity(record) is not None]
        for fault, tiers in committed.items()
        if any(tier_severity(record) is not None for record in tiers.values())
    }


def _plan(
    committed: Mapping[str, Mapping[str, Any]], faults: Sequence[str], tiers: Sequence[str]
) -> dict[str, dict[str, Any]]:
    """fault -> {tier: its committed record} for the chosen tiers each fault reaches."""
    reachable = _reachable(committed)
    plan = {}
    for fault in faults:
        chosen = {t: committed[fault][t] for t in tiers if t in reachable.get(fault, [])}
        if chosen:
            plan[fault] = chosen
    return plan


# -- the pipeline's stages, in a temporary directory -----------------------------------------
class _WithDetector:
    """Params whose benchmark has the evaluated object as its only detector, and whose
    `detector(name)` is that object for its name (the tier metrics read the detector's latency
    from it); everything else is the params'."""

    def __init__(self, params: Params, name: str, detector: BaseDetector) -> None:
        self._params, self._name, self._detector = params, name, detector
        self.benchmark = params.benchmark.model_copy(update={"detectors": [name]})

    def __getattr__(self, attribute: str) -> Any:
        return getattr(self._params, attribute)

    def detector(self, name: str) -> Any:
        return self._detector if name == self._name else self._params.detector(name)


def _run(
    params: Params,
    pipeline: Pipeline,
    detector: BaseDetector,
    label: str,
    plan: Mapping[str, Mapping[str, Any]],
    impacts: Mapping[str, Mapping[str, Any]],
    tmp: Path,
) -> tuple[list[dict], dict[str, float]]:
    """Collect, fit, score and measure as the pipeline's stages do; the tier records and
    the detector's cost."""
    from oodrl.io import yamlio
    from oodrl.io.fileio import atomic_write_text
    from oodrl.io.store import read_trajectories, save_detector
    from oodrl.metrics.cost import step_latency_us, timed_streams
    from oodrl.metrics.tiers import compute_tier_results
    from oodrl.protocol.streams import HELDOUT_SETS
    from oodrl.protocol.tiers import IMPACT_DIR, impact_path
    from oodrl.stages.collect import collect_heldout, collect_id
    from oodrl.stages.impact import collect_tiers
    from oodrl.stages.score import score_clean_sets, score_injector_sets

    policy = pipeline.policy_path.resolve()
    tmp = tmp.resolve()
    key = re.sub(r"[^\w.-]+", "_", label)  # the stores' file names
    data, scores = tmp / "data", tmp / "scores"
    id_path = data / "id.zarr"
    heldout = {which: data / f"{which}.zarr" for which in HELDOUT_SETS}
    tier_paths = {fault: data / "tiers" / f"{fault}.zarr" for fault in plan}
    model = tmp / "models" / f"{key}.pkl"
    # In the pipeline's directory, as its stages run: a detector's params name paths relative
    # to it (the policy view's `policy: models/policy.pt`).
    with _single_threaded(detector), _sys_path_kept(), contextlib.chdir(pipeline.directory):
        collect_id(params, policy, id_path)
        for which, path in heldout.items():
            collect_heldout(params, which, policy, path)
        for fault, tiers in plan.items():
            impact = impact_path(tmp / IMPACT_DIR, fault)
            atomic_write_text(impact, yamlio.dump(_impact_document(fault, impacts[fault], tiers)))
            collect_tiers(params, fault, policy, impact, id_path, tier_paths[fault])
        id_set = read_trajectories(id_path, stage="collect_id")
        split = id_set.attrs["split"]
        start = time.perf_counter()
        detector.fit(id_set.subset(split["fit"]).trajectories())
        detector.calibrate(id_set.subset(split["calibration"]).trajectories())
        fit_s = time.perf_counter() - start
        save_detector(model, detector, key, detector.get_params())
        score_clean_sets(key, model, scores, None, heldout, id_path=id_path)
        for fault in tier_paths:
            score_injector_sets(key, fault, model, scores, None, None, data / "tiers")
        with_detector = _WithDetector(params, key, detector)
        records = compute_tier_results(with_detector, scores, tmp / IMPACT_DIR)["records"]
        twins = read_trajectories(heldout["twins"], stage="collect_twins").trajectories()
        cost = {"fit_s": fit_s, **step_latency_us(detector, timed_streams(twins))}
    return [{**r, "detector": label} for r in records], cost


def _impact_document(
    fault: str, impact: Mapping[str, Any], tiers: Mapping[str, Any]
) -> dict[str, Any]:
    """The impact document the tier stages read for `fault`: its committed record with only the
    chosen `tiers`, so that only their streams are collected and scored."""
    record = {k: impact[k] for k in _IMPACT_KEYS if k in impact}
    return {
        "clean_return": impact["clean_return"],
        "random_return": impact["random_return"],
        "faults": {fault: {**record, "tiers": dict(tiers)}},
    }


def _cost_rows(pipeline: Pipeline, label: str, cost: Mapping[str, float]) -> list[dict]:
    from oodrl.api.results import _base, _row

    base = _base(pipeline.env, pipeline.policy, None, None, label, None, None, None)
    return [_row(base, metric, value) for metric, value in cost.items()]


@contextlib.contextmanager
def _single_threaded(detector: BaseDetector) -> Iterator[None]:
    """Library thread pools at one thread, as in every stage process (`oodrl.parallel`): float
    results must not depend on the core count. Torch's own pool too, imported first for a
    detector that fits with it (`uses_torch`)."""
    from threadpoolctl import threadpool_limits

    if getattr(detector, "uses_torch", False):
        import torch  # noqa: F401 - set to one thread below, before the detector trains
    torch = sys.modules.get("torch")
    threads = torch.get_num_threads() if torch is not None else None
    with threadpool_limits(limits=1):
        if torch is not None:
            torch.set_num_threads(1)
        try:
            yield
        finally:
            if torch is not None and threads is not None:
                torch.set_num_threads(threads)


@contextlib.contextmanager
def _sys_path_kept() -> Iterator[None]:
    """Loading a fitted detector adds the working directory to sys.path (for a stage's
    plugin modules); an in-process evaluation leaves the caller's path as it was."""
    saved = list(sys.path)
    try:
        yield
    finally:
        sys.path[:] = saved
