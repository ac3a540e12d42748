"""Detectors from the libraries people already use, named by `class: "module:Class"` (SPEC §17).

A params block such as

    detectors:
      iforest:
        class: "pyod.models.iforest:IForest"
        features: state
        n_estimators: 100

makes oodrl wrap the library class in a `LibraryDetector`. Three APIs are recognised, on the
constructed object, in this order:

- river's streaming API, `learn_one(x)` / `score_one(x)` on dicts (larger = more anomalous):
  fitted by one pass of `learn_one` over the fit rows, in order, then frozen;
- scikit-learn's `score_samples(X)`, larger = more normal, so its negation is the score;
- PyOD's `decision_function(X)`, larger = more anomalous (any class with `fit(X)` and
  `decision_function(X)` and no `score_samples`).

oodrl's own keys (`features`, `window`, `standardize`, `threshold_rule`, `threshold_percentile`,
`alpha`, `seed`) configure the wrapper; every other key of the block is a constructor argument of
the library class, validated by constructing it (a scikit-learn estimator's value constraints
too), and by `oodrl check-params` fitting it on dummy data (`oodrl.suite.params_check`): some
libraries check an argument only in fit. A key that is oodrl's and the library's too (HBOS's
`alpha`) is oodrl's; where oodrl would not read it, it is refused. `seed` is passed on as the
library's `random_state` (or `seed`, river) unless the block sets that argument itself. The
library's own threshold (`contamination`) is ignored: alarms come from oodrl's calibration.

Feature views (`features`): "state", "state_action", "transition" (`oodrl.detectors.features`),
or "window", the last `window` = L states stacked oldest first (L·d_s columns); the first L − 1
steps of a stream repeat its first state in the missing places. Every view is standardised per
column on the fit set when `standardize` (default true): kNN and LOF measure distances, and a
state's coordinates differ in scale by orders of magnitude.

Exact streaming: a step's score is the model's score of that step's row alone. A library may
compute a row's score differently in a batch (ECOD ranks each row among the batch's rows; BLAS
kernels may sum in another order for one row than for many), so `fit` probes the fitted model:
when scoring rows one at a time and in `CHUNK_ROWS`-row chunks give the same bits, batch scoring
calls it on chunks (`batched_`), else one row at a time, as the stream always does. Scoring uses
a copy of the fitted model (one per `score_many` call, one per stream), so a library that changes
itself while scoring (ECOD stores its last batch's ranks, a KD-tree counts its queries) never
changes the fitted detector.

So a row of the "state", "state_action" and "transition" views scores the same bits alone as in
any batch: such a detector is `row_independent` (its scoring stage then scores a fault's
pre-onset steps once, `oodrl.protocol.scoring`); a "window" row reads the L − 1 steps before it.

Numba: a library that compiles its kernels with numba (PyOD's HBOS) compiles them in every
process that first calls them, seconds per stage. Scoring turns on numba's own on-disk cache for
the compiled functions of the library class's module, so a machine compiles them once for all
its scoring stages; the cached machine code is the code a fresh compile makes (numba keys it by
the source and the CPU), and the scores keep their bytes. Fitting always compiles: see
`_scoring_model`.

Library kernels are not oodrl's machine-independent arithmetic: `machine_independent` is False.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import inspect
import sys
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from typing import Any, ClassVar

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from oodrl.core.detector import BaseDetector
from oodrl.core.stream import DetectorStream, StepScores
from oodrl.core.trajectory import Trajectory
from oodrl.detectors.features import (
    FEATURE_SETS,
    ActionEncoding,
    Standardizer,
    split_scores,
    stacked,
    trajectory_features,
)
from oodrl.errors import ConfigError, DetectorError
from oodrl.validation import Interval, IsType, Options, ParameterError, constructor_params

FEATURE_VIEWS = (*FEATURE_SETS, "window")
#: The library APIs a wrapped class may have (see the module docstring).
APIS = ("river", "score_samples", "decision_function")
#: Rows per call of a model whose rows score independently: one call's overhead (IsolationForest:
#: milliseconds) spread over many rows, memory bounded.
CHUNK_ROWS = 1024
#: Rows the fit-time probe scores one at a time against their chunk's scores.
PROBE_SINGLE_ROWS = 16
#: A chunk size no multiple of a SIMD width, probed too (the last chunk of a batch is ragged).
PROBE_RAGGED_ROWS = 37
#: The constructor argument through which oodrl's `seed` reaches the library, by preference.
SEED_ARGUMENTS = ("random_state", "seed")


def one_line(error: BaseException) -> str:
    """The error's message on one line (libraries' messages can span several)."""
    return " ".join(str(error).split()) or type(error).__name__


def library_api(model: Any) -> str | None:
    """Which of APIS the constructed library object offers, or None."""
    if callable(getattr(model, "learn_one", None)) and callable(getattr(model, "score_one", None)):
        return "river"
    if not callable(getattr(model, "fit", None)):
        return None
    for api in APIS[1:]:
        # hasattr on the instance: scikit-learn offers some methods only for some parameters
        # (LocalOutlierFactor's score_samples only with novelty=True).
        if callable(getattr(model, api, None)):
            return api
    return None


def as_detector(obj: Any) -> Any:
    """What the detector registry returns for an imported `module:Class`: a class of a library's
    outlier API wrapped in a LibraryDetector subclass; anything else as it is."""
    is_library_class = (
        isinstance(obj, type)
        and not issubclass(obj, BaseDetector)
        and any(callable(getattr(obj, method, None)) for method in ("score_one", *APIS[1:]))
    )
    return library_detector_class(obj) if is_library_class else obj


#: What a detector's `class:` may name (SPEC §17).
ALLOWED_CLASSES = (
    "an oodrl detector class, or a class with fit and decision_function or score_samples "
    "(PyOD, scikit-learn) or with learn_one and score_one (river)"
)


def check_detector_class(obj: Any, path: str) -> None:
    """Refuse what the detector registry returned for `path` unless it is a detector class
    (`as_detector` has wrapped any class of a library's outlier API by then)."""
    if isinstance(obj, type) and issubclass(obj, BaseDetector):
        return
    if not isinstance(obj, type):
        what = f"is not a class (it is a {type(obj).__name__})"
    else:
        methods = ("fit", "decision_function", "score_samples", "learn_one", "score_one")
        missing = [m for m in methods if not callable(getattr(obj, m, None))]
        what = f"has no outlier API: no {', '.join(missing)}"
    raise ConfigError(f"{path} {what}. Allowed: {ALLOWED_CLASSES}.")


def blame(params: Mapping[str, Any], attempt: Callable[[dict[str, Any]], object]) -> str | None:
    """The first key of `params` with which alone (the others at their defaults) `attempt`
    raises, or None: a library's message does not always name its argument (PyOD's HBOS: "is
    set to -1. Not in the range of (2, inf)")."""
    for key, value in params.items():
        try:
            attempt({key: value})
        except Exception:  # the library's own error, whatever its type
            return key
    return None


def library_detectors_named(detector_blocks: Any) -> dict[str, str]:
    """params name -> `class:` path of the blocks of a params `detectors` section whose class
    is a library's (not an oodrl detector), sorted by name (`oodrl list` shows them)."""
    from oodrl.detectors import DETECTORS

    named = {
        name: block["class"]
        for name, block in sorted((detector_blocks or {}).items())
        if isinstance(block, dict) and isinstance(block.get("class"), str)
    }
    classes = {name: DETECTORS.get(path) for name, path in named.items()}
    return {
        name: named[name]
        for name, cls in classes.items()
        if isinstance(cls, type) and issubclass(cls, LibraryDetector)
    }


def class_path(cls: type) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


@functools.cache
def library_detector_class(library_class: type) -> type[LibraryDetector]:
    """The LibraryDetector subclass wrapping `library_class`, named by its import path."""
    path = class_path(library_class)
    attributes = {"name": path, "library_class": library_class, "__module__": __name__}
    return type(f"LibraryDetector[{path}]", (LibraryDetector,), attributes)


@functools.cache  # once per process: each scoring model would otherwise walk the module again
def cache_numba_kernels(module_name: str) -> None:
    """Let numba keep on disk what it compiles for the module's numba functions (see the module
    docstring). Nothing to do when the module did not import numba; called once the module is
    imported, as it is once a model of it is fitted or unpickled."""
    dispatcher = sys.modules.get("numba.core.dispatcher")
    module = sys.modules.get(module_name)
    if dispatcher is None or module is None:
        return
    for value in vars(module).values():
        if isinstance(value, dispatcher.Dispatcher):
            # RuntimeError: numba finds nowhere to write, and compiles in each process as before.
            with contextlib.suppress(RuntimeError):
                value.enable_caching()


def _signature(library_class: type) -> Mapping[str, Any]:
    """The library class's constructor parameters; none for a C class without a signature."""
    try:
        return inspect.signature(library_class).parameters
    except (TypeError, ValueError):
        return {}


def _restore(path: str, state: dict[str, Any]) -> LibraryDetector:
    """Unpickle a LibraryDetector: its class is rebuilt from the library class's path."""
    from oodrl.registry import import_path

    cls = library_detector_class(import_path(path))
    detector = cls.__new__(cls)
    detector.__dict__.update(state)
    return detector


#: BaseDetector's own keyword arguments (threshold rule, alpha, seed).
_BASE_PARAMS = tuple(constructor_params(BaseDetector))
#: oodrl's keys that a block may set and oodrl may leave unread: key -> (what it is, the key
#: and value under which oodrl reads it). A library argument of the same name never sees the
#: block's value (oodrl's keys come first), so setting one that oodrl ignores is refused.
_READ_ONLY_WITH = {
    "alpha": ("the episode_max false-alarm bound", "threshold_rule", "episode_max"),
    "threshold_percentile": ("the percentile threshold", "threshold_rule", "percentile"),
    "window": ("the window view's length", "features", "window"),
}


class LibraryDetector(BaseDetector):
    """A PyOD, scikit-learn or river outlier detector on an oodrl feature view.

    Parameters
    ----------
    features : "state" | "state_action" | "transition" | "window", default "state"
        The feature view of a step (see the module docstring).
    window : int >= 1, default 8
        L, the states stacked by the "window" view (ignored by the others). 8 steps: a short
        history, 0.16 s of LunarLander (50 Hz). Past 15 columns scikit-learn's neighbour
        searches go brute force, whose BLAS rounding may differ alone and in a batch: such a
        model scores one row at a time (see the module docstring), unless it is told to use a
        tree (`algorithm: kd_tree`).
    standardize : bool, default True
        Centre and scale each column on the fit set before the library sees it.
    **library_params
        The library class's constructor arguments.
    """

    library_class: ClassVar[type]
    machine_independent: ClassVar[bool] = False

    _parameter_constraints: ClassVar[dict[str, list]] = {
        "features": [Options(FEATURE_VIEWS)],
        "window": [Interval(int, 1, None)],
        "standardize": [IsType(bool)],
    }

    def __init__(
        self, *, features: str = "state", window: int = 8, standardize: bool = True, **params: Any
    ) -> None:
        super().__init__(**{k: params.pop(k) for k in _BASE_PARAMS if k in params})
        self.features = features
        self.window = window
        self.standardize = standardize
        self.library_params = params

    def get_params(self) -> dict[str, Any]:
        return {**super().get_params(), **self.library_params}

    @classmethod
    def from_params(cls, params):
        # Every key oodrl does not own is the library's: the library validates them.
        instance = cls(**params)
        instance.validate_params()
        return instance

    def refuse_shadowed(self, block: Mapping[str, Any]) -> None:
        """Refuse a key the params block sets that is both oodrl's and the library's where
        oodrl ignores it: the user meant the library's argument (HBOS's `alpha`), which never
        gets the value (`oodrl check-params`; a clone built from get_params sets every key)."""
        library_arguments = _signature(self.library_class)
        for key in block:
            if key not in _READ_ONLY_WITH or key not in library_arguments:
                continue
            what, switch, value = _READ_ONLY_WITH[key]
            if getattr(self, switch) != value:
                raise ParameterError(
                    key,
                    f"'{key}' is oodrl's key ({what}), read only with {switch}: {value}, so "
                    f"{self.library_class.__name__}'s own '{key}' cannot be set here and the "
                    f"value would be ignored. Allowed: remove it, or set {switch}: {value}.",
                )

    def __reduce__(self):
        # The class is made at run time, so pickle names the library class instead.
        return _restore, (class_path(self.library_class), self.__dict__)

    @property
    def latency(self) -> int:
        # "transition" rows hold the increment s_{t+1} − s_t: known one step after t.
        return int(self.features == "transition")

    @property
    def row_independent(self) -> bool:  # type: ignore[override]
        # A step's row is scored alone or in probed chunks (see the module docstring).
        return self.features != "window"

    # -- the library object ---------------------------------------------------------------
    def _construct(self, library_params: Mapping[str, Any]) -> Any:
        """The library object built with these arguments (and oodrl's seed)."""
        kwargs = dict(library_params)
        accepted = _signature(self.library_class)
        seed_argument = next((a for a in SEED_ARGUMENTS if a in accepted), None)
        if seed_argument is not None and seed_argument not in kwargs:
            kwargs[seed_argument] = self.seed
        model = self.library_class(**kwargs)
        # scikit-learn checks argument values in fit, against constraints its estimators
        # declare (PyOD's inherit the checker but declare none); the check needs no data.
        if hasattr(model, "_parameter_constraints"):
            model._validate_params()
        return model

    def _new_model(self) -> tuple[Any, str]:
        """A fresh library object and its API; a ConfigError names the detector (and the
        argument, where one alone is refused) otherwise."""
        try:
            model = self._construct(self.library_params)
        except Exception as error:  # the library's own error, whatever its type
            message = f"{self.name}: {one_line(error)}"
            key = blame(self.library_params, self._construct)
            raise (ConfigError(message) if key is None else ParameterError(key, message)) from None
        if getattr(model, "novelty", True) is False:
            # scikit-learn's LocalOutlierFactor (and PyOD's LOF over it) scores only its own
            # fit rows unless novelty=True: it would fail at fit or at scoring, not here.
            raise ParameterError(
                "novelty",
                f"{self.name} scores new rows only in novelty mode (without it, only the rows "
                "it was fitted on). Allowed: novelty: true.",
            )
        api = library_api(model)
        if api is None:
            raise ConfigError(
                f"{self.name}: the object has neither fit and decision_function / score_samples "
                "(PyOD, scikit-learn) nor learn_one and score_one (river)."
            )
        return model, api

    def _validate_extra(self) -> None:
        self._new_model()

    # -- features -------------------------------------------------------------------------
    def _step_rows(self, trajectory: Trajectory) -> np.ndarray:
        """(T, d) per-step rows before windowing, standardised when `standardize`."""
        feature_set = "state" if self.features == "window" else self.features
        rows = trajectory_features(trajectory, feature_set, self.action_encoding_)
        return rows if self.standardizer_ is None else self.standardizer_.transform(rows)

    def _windowed(self, rows: np.ndarray) -> np.ndarray:
        """(T, L·d): each row with the L − 1 before it, oldest first; the first row repeated
        where the stream has no earlier rows."""
        padded = np.concatenate([np.repeat(rows[:1], self.window - 1, axis=0), rows])
        windows = sliding_window_view(padded, self.window, axis=0)  # (T, d, L)
        return windows.transpose(0, 2, 1).reshape(len(rows), -1)

    def _rows(self, trajectory: Trajectory) -> np.ndarray:
        rows = self._step_rows(trajectory)
        return self._windowed(rows) if self.features == "window" else rows

    # -- fit and score --------------------------------------------------------------------
    def _fit(self, trajectories: Sequence[Trajectory]) -> None:
        model, self.api_ = self._new_model()
        self.action_encoding_ = ActionEncoding.fit(trajectories)
        self.standardizer_ = None
        if self.standardize:
            self.standardizer_ = Standardizer.fit(stacked(trajectories, self._step_rows))
        x = stacked(trajectories, self._rows)
        try:
            if self.api_ == "river":
                for row in x.tolist():
                    model.learn_one(dict(enumerate(row)))
            else:
                model.fit(x)
        except Exception as error:  # the library's own error, whatever its type
            raise DetectorError(f"{self.name}: fit failed: {one_line(error)}") from None
        self.model_ = model
        self.batched_ = self.api_ != "river" and self._rows_score_alone(x)

    def _scoring_model(self) -> Any:
        """A copy of the fitted model to score with: scoring must not change the detector.

        Numba's cache is turned on here, for scoring only: code loaded from it returns arrays
        whose (equal) dtype objects pickle to other bytes, so a model fitted with it would
        pickle differently on a machine that has the cache than on one that compiles."""
        cache_numba_kernels(self.library_class.__module__)
        return copy.deepcopy(self.model_)

    def _call(self, model: Any, x: np.ndarray) -> np.ndarray:
        """`model`'s scores of rows x, larger = more anomalous, in one library call (river: one
        call per row)."""
        if self.api_ == "river":
            return np.array([model.score_one(dict(enumerate(row))) for row in x.tolist()])
        if self.api_ == "score_samples":
            return -np.asarray(model.score_samples(x), dtype=np.float64)
        return np.asarray(model.decision_function(x), dtype=np.float64)

    def _rows_score_alone(self, x: np.ndarray) -> bool:
        """Whether rows of x score the same bits alone, in a ragged chunk and in a full one."""
        model, chunk = self._scoring_model(), x[:CHUNK_ROWS]
        scores = self._call(model, chunk)
        singles = np.unique(np.linspace(0, len(chunk) - 1, PROBE_SINGLE_ROWS).astype(int))
        alone = np.array([self._call(model, chunk[i : i + 1])[0] for i in singles])
        ragged = self._call(model, chunk[:PROBE_RAGGED_ROWS])
        return np.array_equal(alone, scores[singles]) and np.array_equal(
            ragged, scores[:PROBE_RAGGED_ROWS]
        )

    def _score_rows(self, x: np.ndarray) -> np.ndarray:
        model, size = self._scoring_model(), CHUNK_ROWS if self.batched_ else 1
        parts = [self._call(model, x[i : i + size]) for i in range(0, len(x), size)]
        return np.concatenate(parts) if parts else np.zeros(0)

    def _score_many(self, trajectories: Sequence[Trajectory]) -> list[np.ndarray]:
        return split_scores(self._score_rows(stacked(trajectories, self._rows)), trajectories)

    def stream(self) -> DetectorStream:
        return LibraryStream(self)


class LibraryStream(DetectorStream):
    """Keeps the last L rows (the "window" view; one row for the others) and scores the new
    step's row alone, as batch scoring does (see the module docstring)."""

    def __init__(self, detector: LibraryDetector) -> None:
        super().__init__(detector)
        self.model = detector._scoring_model()
        self.recent: deque[np.ndarray] = deque(maxlen=detector.window)

    def _update(self, step: Trajectory, t: int) -> StepScores:
        detector = self.detector
        row = detector._step_rows(step)[0]
        if detector.features != "window":
            return self.scored(t, detector._call(self.model, row[None]))
        self.recent.extend([row] * (detector.window if t == 0 else 1))
        return self.scored(t, detector._call(self.model, np.concatenate(self.recent)[None]))

    def _flush(self) -> StepScores:
        self.recent.clear()
        return ()
