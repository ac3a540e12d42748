"""The `oodrl` command line. Stage verbs are thin: load params, call one stage function.

Every command validates params.yaml first; an OodrlError becomes one line on stderr and a
non-zero exit (2 for bad params or usage, 1 otherwise), never a traceback.
"""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path
from typing import Annotated, NoReturn

import typer

from oodrl.errors import ConfigError, OodrlError, RegistryError
from oodrl.parallel import THREAD_POOL_VARIABLES

# One thread per library pool (why: oodrl.parallel), set before numpy or torch is imported.
for _variable in THREAD_POOL_VARIABLES:
    os.environ.setdefault(_variable, "1")

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="oodrl: which OOD detector notices which fault in an RL agent's trajectory.",
)

ParamsOption = Annotated[Path, typer.Option("--params", help="params file to validate and use")]
PathOption = functools.partial(typer.Option, help="path (dvc.yaml passes it)")


def _fail(error: OodrlError) -> None:
    """SPEC §22: one line, exit 2 for a usage or params error, 1 for a runtime failure; the
    traceback only with OODRL_DEBUG=1."""
    if os.environ.get(DEBUG_VARIABLE) == "1":
        raise error
    typer.echo(f"error: {one_line(str(error))}", err=True)
    # An unknown component name or import path is a usage or params error too.
    raise typer.Exit(2 if isinstance(error, ConfigError | RegistryError) else 1)


DEBUG_VARIABLE = "OODRL_DEBUG"


def one_line(message: str) -> str:
    """A message as one line: a library's multi-line text would read as several errors."""
    return " ".join(line.strip() for line in message.splitlines() if line.strip())


def _print_version(requested: bool) -> None:
    if requested:
        from importlib.metadata import version

        typer.echo(f"oodrl {version('oodrl')}")
        raise typer.Exit()


@app.callback()
def _options(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_print_version, is_eager=True, help="print the version and exit"
        ),
    ] = False,
) -> None:
    """oodrl: which OOD detector notices which fault in an RL agent's trajectory."""


pipeline_app = typer.Typer(
    no_args_is_help=True,
    help="The DVC pipelines (root and pipeline/<env>/), generated from one template.",
)
app.add_typer(pipeline_app, name="pipeline")
suite_app = typer.Typer(
    no_args_is_help=True, help="The whole suite: every pipeline, then the leaderboard."
)
app.add_typer(suite_app, name="suite")


#: `oodrl --help` lists the commands a person types first, then, in a panel of their own, the
#: stage verbs the generated dvc.yaml files call (a stage's command name never changes).
STAGES_PANEL = "Pipeline stages (dvc repro runs these)"


def command(name: str | None = None, group: typer.Typer = app, panel: str | None = None):
    """Register a command whose OodrlErrors become a one-line message and an exit code; `panel`:
    the --help panel it is listed in (default: Commands)."""

    def decorate(func):
        @functools.wraps(func)
        def wrapper(*args, **kwargs):
            try:
                return func(*args, **kwargs)
            except OodrlError as error:
                _fail(error)

        return group.command(name, rich_help_panel=panel)(wrapper)

    return decorate


def _load(params_path: Path):
    """Params for a stage: structure and ranges; the stage validates what it builds."""
    from oodrl.config import load_params

    return load_params(params_path, components=False)


def _stage(name: str):
    from oodrl.stages.common import timed_stage

    return timed_stage(name)


# -- user verbs ------------------------------------------------------------------------------
@command("list")
def list_components(
    params: Annotated[
        Path, typer.Option(help="also list the library detectors this params file names")
    ] = Path("params.yaml"),
) -> None:
    """List registered components by kind, and the library detectors params name."""
    from oodrl.detectors import DETECTORS
    from oodrl.envs import ENVIRONMENTS
    from oodrl.injectors import INJECTORS
    from oodrl.metrics import METRICS

    for kind, registry in (
        ("detectors", DETECTORS),
        ("injectors", INJECTORS),
        ("metrics", METRICS),
        ("environments", ENVIRONMENTS),
    ):
        typer.echo(f"{kind}:")
        for name in registry.names():
            extra = ""
            if kind == "injectors":
                extra = f"  ({registry.get(name).mode})"
            typer.echo(f"  {name}{extra}")
    if params.is_file():
        from oodrl.config import read_params_data
        from oodrl.detectors.library import library_detectors_named

        library = library_detectors_named(read_params_data(params).get("detectors"))
        if library:
            typer.echo(f"library detectors named in {params}:")
            for name, path in library.items():
                typer.echo(f"  {name}  {path}")


@command("check-params")
def check_params(
    path: Annotated[Path, typer.Argument()] = Path("params.yaml"),
    pipeline: Annotated[
        Path | None, typer.Option(help="also check this dvc.yaml is what its template gives")
    ] = None,
    out: Annotated[Path | None, typer.Option(help="write a constant stamp when valid")] = None,
    code: Annotated[
        Path | None, typer.Option(help="write the pipeline's code stamps in this directory")
    ] = None,
    merged: Annotated[
        Path | None, typer.Option(help="write the params, extends chain merged, here")
    ] = None,
) -> None:
    """Validate a params file; one line per problem and exit code 2 when invalid.

    Stage check_params runs it first, so `dvc repro` refuses a bad params file before any
    stage deletes its outputs; its stamp never changes, so passing re-runs nothing, and each
    code stamp changes only with the code its stages execute."""
    from oodrl.config import load_params
    from oodrl.suite.params_check import check_completely

    params = load_params(path)
    try:
        check_completely(params)
    except ConfigError as error:  # these checks name keys, not the file
        raise ConfigError(f"{path}: {error}") from None
    if pipeline is not None:
        from oodrl.suite import pipeline as pipelines

        pipelines.check_pipeline(pipeline)
        if code is not None:
            pipelines.write_stamps(pipeline, path, code)
    from oodrl.io.fileio import atomic_write_text

    if merged is not None:
        from oodrl.config import read_params_data
        from oodrl.io import yamlio

        atomic_write_text(merged, yamlio.dump(read_params_data(path)))
    if out is not None:
        atomic_write_text(out, f"{path} passed `oodrl check-params`\n")
    typer.echo(
        f"{path}: ok ({len(params.benchmark.detectors)} detectors, "
        f"{len(params.benchmark.injectors)} injectors, T={params.env.T}, "
        f"onset={params.env.resolved_onset})"
    )


@command("evaluate-policy")
def evaluate_policy(
    env: Annotated[
        str, typer.Option(help="environment of the suite; its committed policy by default")
    ] = "LunarLander-v3",
    policy: Annotated[
        Path | None, typer.Option(help="policy file (default: the environment's committed one)")
    ] = None,
    episodes: Annotated[int, typer.Option(min=1)] = 30,
    seed: Annotated[int, typer.Option(min=0)] = 1_000_000,
    mode: Annotated[str, typer.Option(help="greedy or noisy")] = "greedy",
) -> None:
    """Roll out full episodes and print the mean ± std return."""
    from oodrl.policies.evaluate import evaluate_policy as evaluate
    from oodrl.policies.load import load_policy
    from oodrl.suite.environments import POLICY_BARS, policy_path

    if mode not in ("greedy", "noisy"):
        raise ConfigError(f"--mode must be 'greedy' or 'noisy'; got {mode!r}.")
    path = policy if policy is not None else policy_path(env)
    returns = evaluate(load_policy(path, mode=mode), episodes=episodes, seed=seed, env_id=env)
    bar = POLICY_BARS.get(env)
    verdict = (
        "" if bar is None else f"; bar {bar:g}: {'met' if returns.mean() >= bar else 'NOT met'}"
    )
    typer.echo(
        f"{path}: {env} mean return {returns.mean():.1f} ± {returns.std():.1f} over {episodes} "
        f"episodes (seeds {seed}..{seed + episodes - 1}, {mode}){verdict}"
    )


@command("monitor")
def monitor(
    detector: Annotated[
        str, typer.Option(help="registered name (fitted here on clean streams) or a pickle")
    ],
    env: Annotated[str, typer.Option(help="environment of the suite")] = "LunarLander-v3",
    fault: Annotated[str | None, typer.Option(help="online injector, live from the onset")] = None,
    severity: Annotated[float, typer.Option(min=0.0, max=1.0)] = 1.0,
    steps: Annotated[int, typer.Option(min=2, help="longest episode")] = 500,
    onset: Annotated[int | None, typer.Option(help="fault onset (default steps // 3)")] = None,
    seed: Annotated[int, typer.Option(min=0)] = 0,
    episodes: Annotated[
        int, typer.Option(min=1, help="N > 1: rates over seeds seed..seed+N-1 (needs --fault)")
    ] = 1,
    k: Annotated[int, typer.Option("--k", min=0, help="detection window: [onset, onset+K]")] = 100,
    alpha: Annotated[float, typer.Option(help="per-stream false-alarm budget, in (0, 1)")] = 0.05,
) -> None:
    """Run the committed policy under the OOD monitor: alarms as they happen, then a summary;
    with --episodes N, the detection rate, delays and false alarms over N seeds. A detector
    fitted here alarms by the per-stream rule at --alpha (SPEC §15)."""
    from oodrl.monitor import run_monitor, run_monitor_episodes

    if not 0 < alpha < 1:
        raise ConfigError(f"--alpha must be in (0, 1); got {alpha}.")
    if episodes == 1:
        run_monitor(
            env, detector, fault, severity, steps=steps, onset=onset, seed=seed, alpha=alpha,
            echo=typer.echo,
        )  # fmt: skip
        return
    if fault is None:
        raise ConfigError("--episodes N > 1 reports detection rates: name a --fault.")
    run_monitor_episodes(
        env, detector, fault, severity, episodes=episodes, k=k, steps=steps, onset=onset,
        seed=seed, alpha=alpha, echo=typer.echo,
    )  # fmt: skip


@command("impact-reference", panel=STAGES_PANEL)
def impact_reference(
    policy: Annotated[Path, PathOption()],
    out: Annotated[Path, PathOption(help="the clean and random-policy returns (YAML)")],
    horizon: Annotated[
        int | None, typer.Option(min=1, help="longest episode (default: the time limit)")
    ] = None,
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stage impact_reference (SPEC §19): π's clean whole-episode returns on every seed the
    impact stages use and the random policy's, measured once for all faults."""
    from oodrl.stages.impact import run_impact_reference

    config = _load(params)
    with _stage("impact_reference"):
        run_impact_reference(config, policy, out, horizon=horizon)


@command("impact", panel=STAGES_PANEL)
def impact(
    policy: Annotated[Path, PathOption()],
    out: Annotated[Path, PathOption(help="impact.yaml: each fault's curve and tiers")],
    faults: Annotated[
        list[str] | None,
        typer.Argument(help="faults to calibrate (default: every one of benchmark.injectors)"),
    ] = None,
    id: Annotated[  # noqa: A002 - the option is --id
        Path | None,
        typer.Option(help="clean ID set: the live observation faults' reference statistics"),
    ] = None,
    reference: Annotated[
        Path | None,
        typer.Option(help="impact_reference's returns (default: measured here)"),
    ] = None,
    grid: Annotated[
        str | None, typer.Option(help="severities, comma-separated (default: tiers.grid)")
    ] = None,
    episodes: Annotated[
        int | None,
        typer.Option(min=2, help="episodes per severity (default: tiers.episodes)"),
    ] = None,
    horizon: Annotated[
        int | None, typer.Option(min=1, help="longest episode (default: the time limit)")
    ] = None,
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stage impact (SPEC §15, §19): each fault's normalised return over whole episodes on a
    severity grid, then the severity of each tier (benign, mild, moderate, severe) searched for
    where R̃ is measured, and verified on held-out episodes."""
    from oodrl.stages.impact import run_impact

    config = _load(params)
    try:
        severities = config.tiers.grid if grid is None else [float(s) for s in grid.split(",")]
    except ValueError:
        raise ConfigError(f"--grid must be comma-separated numbers; got {grid!r}.") from None
    for name in faults or []:
        _known(name, config.benchmark.injectors, "benchmark.injectors")
    with _stage(f"impact@{faults[0]}" if faults and len(faults) == 1 else "impact"):
        run_impact(
            config, policy, out, id_path=id, reference_path=reference, injectors=faults,
            grid=severities, n_episodes=episodes or config.tiers.episodes, horizon=horizon,
        )  # fmt: skip


@command("show")
def show(
    path: Annotated[Path, typer.Argument(help="results.yaml, sweep_results.yaml or run_meta.yaml")],
    max_us_per_step: Annotated[
        float | None,
        typer.Option(
            min=0.0,
            help="run_meta.yaml only: keep detectors whose median µs/step is at most this, and "
            "name the most accurate",
        ),
    ] = None,
) -> None:
    """Render the tables of a results or sweep file in the terminal, after the protocol version
    of its numbers; of a run_meta.yaml, each detector's fit time, fitted size and µs per
    streamed step beside its matched AUROC."""
    from oodrl.report.show import shown as render
    from oodrl.report.show import stale_warning

    typer.echo(render(path, max_us_per_step))
    if warning := stale_warning(path):
        typer.echo(warning, err=True)


@command("new")
def new(
    name: Annotated[str, typer.Argument(help="the pipeline's directory: pipeline/NAME")],
    env: Annotated[
        str | None,
        typer.Option(
            help="any Gymnasium id (not Gymnasium's module:EnvId) with a flat Box observation; "
            "image observations are not supported (--dataset: the one it names)"
        ),
    ] = None,
    flatten: Annotated[
        bool,
        typer.Option(
            help="wrap --env in gymnasium.wrappers.FlattenObservation (Dict, Tuple, … "
            "observations); params name it FlattenObservation(ID)"
        ),
    ] = False,
    policy: Annotated[
        str | None,
        typer.Option(
            help="SB3 .zip (vecnormalize.pkl beside it is used), RL Zoo run folder, oodrl "
            "checkpoint, or module:function"
        ),
    ] = None,
    train: Annotated[
        str | None, typer.Option(help="train one instead with SB3: sac, ppo or dqn")
    ] = None,
    dataset: Annotated[
        str | None,
        typer.Option(
            help="recorded data instead of an agent: a Minari dataset's directory or local id "
            "(post-hoc faults only)"
        ),
    ] = None,
    steps: Annotated[
        int,
        typer.Option(
            min=1,
            help="--train's budget in environment steps (a policy no better than random is "
            "refused)",
        ),
    ] = 50_000,
    T: Annotated[  # noqa: N803 - the protocol's name
        int | None, typer.Option("--T", min=3, help="steps per stream (default: episode length)")
    ] = None,
    episodes: Annotated[int, typer.Option(min=1, help="held-out episodes of the report")] = 10,
    seed: Annotated[int, typer.Option(min=0, help="--train's seed")] = 0,
    root: Annotated[Path, typer.Option(help="the project root")] = Path("."),
) -> None:
    """Make pipeline/NAME for your agent in any Gymnasium environment, or for recorded data
    (SPEC §18)."""
    from oodrl.suite.new import new_pipeline, summary

    made = new_pipeline(
        root, name, env, policy=policy, train=train, dataset=dataset, flatten=flatten,
        steps=steps, T=T, episodes=episodes, seed=seed,
    )  # fmt: skip
    typer.echo(summary(made, root))


# -- stage verbs (dvc.yaml is their caller) ---------------------------------------------------
@command("train-policy", panel=STAGES_PANEL)
def train_policy(
    out: Annotated[Path, PathOption()],
    report: Annotated[Path, PathOption()],
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stage train_policy: train the NoisyNet DQN policy."""
    from oodrl.stages.train import retrain_requested
    from oodrl.stages.train import train_policy as run

    config = _load(params)
    with _stage("train_policy"):
        run(config, out, report, retrain=retrain_requested())


@command("collect-id", panel=STAGES_PANEL)
def collect_id(
    policy: Annotated[Path, PathOption()],
    out: Annotated[Path, PathOption()],
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stage collect_id: clean in-distribution trajectories with the fit/calibration split."""
    from oodrl.stages.collect import collect_id as run

    config = _load(params)
    with _stage("collect_id"):
        run(config, policy, out)


@command("collect-eval", panel=STAGES_PANEL)
def collect_eval(
    policy: Annotated[Path, PathOption()],
    out: Annotated[Path, PathOption()],
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stage collect_eval: the clean evaluation set (matched counterparts)."""
    from oodrl.stages.collect import collect_eval as run

    config = _load(params)
    with _stage("collect_eval"):
        run(config, policy, out)


@command("import-dataset", panel=STAGES_PANEL)
def import_dataset(
    split: Annotated[str, typer.Argument(help="id (the ID set) or eval (the evaluation set)")],
    dataset: Annotated[Path, PathOption(help="the Minari dataset's copy: pipeline/NAME/dataset")],
    out: Annotated[Path, PathOption()],
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stages collect_id and collect_eval of a pipeline of recorded data (SPEC §18): the clean
    ID or evaluation streams, cut from a Minari dataset's episodes."""
    from oodrl.protocol.recorded import SPLITS
    from oodrl.stages.recorded import import_clean_set

    if split not in SPLITS:
        raise ConfigError(f"import-dataset: {split!r} is not a set; allowed: {', '.join(SPLITS)}.")
    config = _load(params)
    with _stage(f"collect_{split}"):
        import_clean_set(config, split, dataset, out)


def _known(name: str, names: list[str], key: str) -> None:
    from oodrl.config import did_you_mean

    if name not in names:
        raise ConfigError(
            f"'{name}' is not listed in {key}.{did_you_mean(name, names)} "
            f"Listed: {', '.join(names)}."
        )


@command("collect-ood", panel=STAGES_PANEL)
def collect_ood(
    injector: Annotated[str, typer.Argument()],
    policy: Annotated[Path, PathOption()],
    eval: Annotated[Path, PathOption()],  # noqa: A002 - the option is --eval
    out: Annotated[Path, PathOption()],
    sweep: Annotated[bool, typer.Option(help="every severity of anomaly.sweep")] = False,
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stages collect_ood / collect_sweep: one injector's perturbed set(s)."""
    from oodrl.stages import collect

    config = _load(params)
    _known(injector, config.benchmark.injectors, "benchmark.injectors")
    name = f"{'collect_sweep' if sweep else 'collect_ood'}@{injector}"
    run = collect.collect_sweep if sweep else collect.collect_ood
    with _stage(name):
        run(config, injector, policy, eval, out)


@command("collect-heldout", panel=STAGES_PANEL)
def collect_heldout(
    which: Annotated[str, typer.Argument(help="calibration | audit | twins")],
    policy: Annotated[Path, PathOption()],
    out: Annotated[Path, PathOption()],
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stages collect_calibration, collect_audit, collect_twins: held-out clean streams (SPEC
    §19) of the per-stream alarm rule (calibration), of its achieved false-alarm rate (audit,
    used for nothing else), and the clean twins of the tier cells' faulty streams (twins)."""
    from oodrl.protocol.streams import HELDOUT_SETS
    from oodrl.stages.collect import collect_heldout as run

    if which not in HELDOUT_SETS:
        raise ConfigError(f"'{which}' is not a held-out set. Allowed: {', '.join(HELDOUT_SETS)}.")
    config = _load(params)
    with _stage(f"collect_{which}"):
        run(config, which, policy, out)


@command("collect-tiers", panel=STAGES_PANEL)
def collect_tiers(
    injector: Annotated[str, typer.Argument()],
    policy: Annotated[Path, PathOption()],
    impact: Annotated[Path, PathOption(help="the fault's impact document")],
    id: Annotated[Path, PathOption(help="clean ID set: live faults' reference statistics")],  # noqa: A002
    out: Annotated[Path, PathOption()],
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stage collect_tiers: the evaluation streams with one fault live at each reachable tier."""
    from oodrl.stages.impact import collect_tiers as run

    config = _load(params)
    _known(injector, config.benchmark.injectors, "benchmark.injectors")
    with _stage(f"collect_tiers@{injector}"):
        run(config, injector, policy, impact, id, out)


@command("fit", panel=STAGES_PANEL)
def fit(
    detector: Annotated[str, typer.Argument()],
    id: Annotated[Path, PathOption()],  # noqa: A002 - the option is --id
    out: Annotated[Path, PathOption()],
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stage fit: fit and calibrate one detector."""
    from oodrl.io.layout import detector_stage
    from oodrl.stages.fit import fit_detector

    config = _load(params)
    _known(detector, config.benchmark.detectors, "benchmark.detectors")
    with _stage(detector_stage(detector, "fit")) as record:
        record.update(detector=detector, fit_s=round(fit_detector(config, detector, id, out), 3))


@command("score", panel=STAGES_PANEL)
def score(
    detector: Annotated[str, typer.Argument()],
    model: Annotated[Path, PathOption()],
    scores: Annotated[Path, PathOption(help="the scores directory: a store per set in it")],
    injector: Annotated[
        list[str] | None,
        typer.Option(help="score only this injector's sets (repeatable; default: every one)"),
    ] = None,
    id: Annotated[Path | None, PathOption()] = None,  # noqa: A002 - the option is --id
    eval: Annotated[Path | None, PathOption()] = None,  # noqa: A002 - the option is --eval
    calibration: Annotated[Path | None, PathOption()] = None,
    audit: Annotated[Path | None, PathOption()] = None,
    twins: Annotated[Path | None, PathOption()] = None,
    ood: Annotated[Path | None, PathOption(help="directory of the headline sets")] = None,
    sweep: Annotated[Path | None, PathOption(help="directory of the sweeps")] = None,
    tiers: Annotated[Path | None, PathOption(help="directory of the tier streams")] = None,
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stages score_clean, score and score_variants: one detector on the clean sets (--id, the
    ID set, whose scores the time-aware rule standardises by, always; with any of --eval, the
    evaluation set, and --calibration, --audit, --twins, the held-out clean streams), or on the
    injectors' sets, `<injector>.zarr` in each directory given (--ood, the headline sets: stage
    score; --sweep, the sweeps, and --tiers, the tier streams: stage score_variants), for every
    benchmark injector or each --injector; one store per set."""
    from oodrl.io.layout import detector_stage
    from oodrl.stages import score as stages

    config = _load(params)
    _known(detector, config.benchmark.detectors, "benchmark.detectors")
    clean = {"--id": id, "--eval": eval, "--calibration": calibration, "--audit": audit,
             "--twins": twins}  # fmt: skip
    faulty = {"--ood": ood, "--sweep": sweep, "--tiers": tiers}
    given = [option for option, path in {**clean, **faulty}.items() if path is not None]
    if any(clean.values()) == any(faulty.values()) or (injector and any(clean.values())):
        raise ConfigError(
            f"score needs --id (ID set) with any of --eval (clean set), --calibration, --audit "
            f"and --twins (held-out clean streams), or any of --ood (headline sets), --sweep "
            f"(sweeps) and --tiers (tier streams), directories, with --injector optional; got "
            f"{', '.join(given) or 'none'}{' with --injector' if injector else ''}."
        )
    if any(clean.values()):
        if id is None:
            raise ConfigError(
                "score of the clean sets needs --id (the ID set, data/id.zarr): the time-aware "
                "rule standardises each step by its scores there (SPEC §24)."
            )
        with _stage(detector_stage(detector, "score_clean")):
            heldout = {"calibration": calibration, "audit": audit, "twins": twins}
            stages.score_clean_sets(detector, model, scores, eval, heldout, id_path=id)
        return
    for each in injector or ():
        _known(each, config.benchmark.injectors, "benchmark.injectors")
    with _stage(detector_stage(detector, "score" if ood is not None else "score_variants")):
        for each in injector or config.benchmark.injectors:
            stages.score_injector_sets(detector, each, model, scores, ood, sweep, tiers)


@command("cells", panel=STAGES_PANEL)
def cells(
    detector: Annotated[str, typer.Argument()],
    scores: Annotated[Path, PathOption(help="the scores directory (reads <detector>/ in it)")],
    out: Annotated[Path, PathOption(help="the cells file, <cells>/<detector>.json")],
    impact: Annotated[
        Path | None, PathOption(help="the faults' impact documents (with them, the tier cells)")
    ] = None,
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stage cells: one detector's results cells from its own scores (SPEC §23), which the
    metrics and tier_metrics stages merge."""
    from oodrl.io.layout import detector_stage
    from oodrl.stages.cells import run_cells

    config = _load(params)
    _known(detector, config.benchmark.detectors, "benchmark.detectors")
    with _stage(detector_stage(detector, "cells")):
        run_cells(config, detector, scores, impact, out)


@command("tier-metrics", panel=STAGES_PANEL)
def tier_metrics(
    cells_dir: Annotated[
        Path, PathOption("--cells", help="the directory of the detectors' cells files")
    ],
    impact: Annotated[Path, PathOption(help="the directory of the faults' impact documents")],
    results: Annotated[Path, PathOption(help="the tier results file, reports/tier_results.json")],
    report: Annotated[Path, PathOption(help="directory: tables.md, impact_curves.png")],
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stage tier_metrics: every detector at every fault's impact tiers, at the per-stream
    false-alarm budget (SPEC §15), merged from the detectors' cells."""
    from oodrl.stages.tier_metrics import run_tier_metrics

    if results.suffix != ".json":  # protocol 5 writes JSON; a .yaml name would mislead readers
        raise ConfigError(
            f"--results {results}: tier results are written as JSON from protocol 5; name a "
            f".json file (reports/tier_results.json)."
        )
    config = _load(params)
    with _stage("tier_metrics"):
        run_tier_metrics(config, cells_dir, impact, results, report)


@command("metrics", panel=STAGES_PANEL)
def metrics(
    # `cells_dir`, not `cells`: a name of a cli.py function puts that function's code in this
    # verb's code stamp (oodrl.suite.pipeline._command_nodes), and `cells` is a command.
    cells_dir: Annotated[
        Path, PathOption("--cells", help="the directory of the detectors' cells files")
    ],
    results: Annotated[Path, PathOption()],
    sweep_results: Annotated[Path, PathOption()],
    metrics_file: Annotated[Path, PathOption()],
    tables: Annotated[Path, PathOption()],
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stage metrics: per-episode metrics, bootstrap CIs, null baselines, tables, merged from
    the detectors' cells."""
    from oodrl.stages.metrics import run_metrics

    config = _load(params)
    with _stage("metrics"):
        run_metrics(config, cells_dir, results, sweep_results, metrics_file, tables)


@command("leaderboard", panel=STAGES_PANEL)
def leaderboard(
    out: Annotated[Path, PathOption()],
    root: Annotated[Path, typer.Option(help="the project root")] = Path("../.."),
    params: ParamsOption = Path("../../params.yaml"),
) -> None:
    """Stage leaderboard: every environment's results -> the suite's cross-environment report."""
    from oodrl.stages.leaderboard import run

    config = _load(params)
    with _stage("leaderboard"):
        run(config, root, out)


@command("render", panel=STAGES_PANEL)
def render(
    results: Annotated[Path, PathOption()],
    sweep_results: Annotated[Path, PathOption()],
    scores: Annotated[Path, PathOption()],
    policy: Annotated[Path, PathOption()],
    models: Annotated[Path, PathOption()],
    eval: Annotated[Path, PathOption()],  # noqa: A002 - the option is --eval
    figures: Annotated[Path, PathOption()],
    plots: Annotated[Path, PathOption()],
    headline: Annotated[Path, PathOption()],
    meta: Annotated[Path, PathOption()],
    params: ParamsOption = Path("params.yaml"),
) -> None:
    """Stage render: figures, DVC plot data, headline table, run_meta.yaml (with each
    detector's fit time, fitted size and streaming latency, measured on clean --eval streams)."""
    from oodrl.stages.render import run_render

    config = _load(params)
    with _stage("render"):
        run_render(
            config,
            results,
            sweep_results,
            scores,
            policy,
            models,
            eval,
            figures,
            plots,
            headline,
            meta,
        )


# -- pipeline verbs -----------------------------------------------------------------------
RootOption = Annotated[Path, typer.Option("--root", help="the project root")]


@command("write", group=pipeline_app)
def pipeline_write(root: RootOption = Path(".")) -> None:
    """Write every pipeline's dvc.yaml (the root and pipeline/<env>/) from the template."""
    from oodrl.suite.pipeline import pipeline_dirs, write

    changed = write(root)
    typer.echo(f"{len(pipeline_dirs(root))} pipelines, {len(changed)} rewritten: "
               f"{', '.join(map(str, changed)) or 'all current'}")  # fmt: skip


@command("check", group=pipeline_app)
def pipeline_check(root: RootOption = Path(".")) -> None:
    """Fail unless every pipeline's dvc.yaml is what `oodrl pipeline write` writes and every
    project's locks are current, or pending in a change of protocol (SPEC §26)."""
    from oodrl.suite.migration import check, summary
    from oodrl.suite.pipeline import check_files, pipeline_dirs

    check_files(root)
    states = check(root)
    typer.echo(f"{len(pipeline_dirs(root))} pipelines: every dvc.yaml is current; "
               f"{summary(states)}")  # fmt: skip


@command("run", group=suite_app)
def suite_run(
    workers: Annotated[int, typer.Option(help="local worker processes, one pipeline each")] = 2,
    ray: Annotated[
        str | None, typer.Option("--ray", help="a Ray cluster's HOST:PORT: one task per pipeline")
    ] = None,
    commit: Annotated[
        bool,
        typer.Option(
            "--commit",
            help="commit each pipeline's locks and results as soon as it is built (one commit "
            "each, naming it and the protocol version), and the leaderboard once every pipeline "
            "is current: a run stopped at any point resumes in any clone",
        ),
    ] = False,
    only: Annotated[
        str | None,
        typer.Option(
            "--only",
            metavar="PIPELINE[,...]",
            help="build only these pipelines (., pipeline/<env>), if not current",
        ),
    ] = None,
    max_hours: Annotated[
        float | None,
        typer.Option(
            "--max-hours",
            help="start no pipeline whose last build time would end it past this many hours "
            "from the start (local workers); what is left is named",
        ),
    ] = None,
    build_missing: Annotated[
        bool,
        typer.Option(
            "--build-missing",
            help="go on where a read-only remote refuses, or holds none of, what the pipelines "
            "to build need: build it here, from scratch",
        ),
    ] = False,
    root: RootOption = Path("."),
) -> None:
    """Build the pipelines of the suite that are not current (decided from git alone), each in
    its own clone of HEAD, in parallel; then the leaderboard, once every pipeline is current.
    The checkout ends with the dvc.lock files a serial build writes."""
    from oodrl.suite.run import run_suite

    run_suite(root, workers=workers, ray_address=ray, echo=typer.echo, commit=commit,
              only=only.split(",") if only is not None else None, max_hours=max_hours,
              build_missing=build_missing)  # fmt: skip


@command("try", group=suite_app)
def suite_try(
    name: Annotated[str, typer.Argument(help="the detector's name in params: detectors.NAME")],
    class_path: Annotated[
        str,
        typer.Option(
            "--class", help="module:Class, a detector or a class with a library's outlier API"
        ),
    ],
    options: Annotated[
        list[str] | None, typer.Argument(help="the detector's parameters, KEY=VALUE")
    ] = None,
    features: Annotated[
        str | None, typer.Option(help="what a library detector sees, e.g. state")
    ] = None,
    workers: Annotated[int, typer.Option(help="local worker processes, one pipeline each")] = 2,
    root: RootOption = Path("."),
) -> None:
    """Check a detector class against the contract, add it to the suite's params, run only its
    stages in every pipeline, reproduce the leaderboard and print its ranks (SPEC §21)."""
    from oodrl.suite.try_detector import try_detector

    try_detector(root, name, class_path, features, options or (), workers=workers, echo=typer.echo)


@command("readme-table")
def readme_table(
    headline: Annotated[Path, typer.Argument()] = Path("pipeline/suite/reports/leaderboard.json"),
    readme: Annotated[Path, typer.Option()] = Path("README.md"),
) -> None:
    """Write a generated headline into README.md between its markers: the suite leaderboard's
    top detectors (the default), or a pipeline's reports/headline.md (`--readme
    docs/getting-started.md` holds the root's)."""
    from oodrl.report.readme import insert_headline

    insert_headline(readme, headline)
    typer.echo(f"{readme}: headline table updated from {headline}")


def _settle_store_writes() -> None:
    """Wait (a few seconds at most) for the writes zarr's IO thread has in flight.

    zarr runs its synchronous API's coroutines on a thread of its own; an interrupt stops the
    main thread only, so without this a store's `finally` could remove its temporary folder
    while a write was still to land in it, and that write would re-create the folder. An
    interrupted command abandons the coroutines it had not yet handed over: no warning for them.

    It runs in a signal handler, so it imports nothing: the signal may land inside an import, and
    a second import from here would corrupt the first's bookkeeping (importlib's per-thread
    record of the module lock it waits on: a KeyError) or find a module half made. A running
    loop means zarr.core.sync, and with it asyncio, is already whole in sys.modules.
    """
    # Absent when the command never touched a store; without its loop while it is imported.
    loop = getattr(sys.modules.get("zarr.core.sync"), "loop", [None])[0]
    if loop is None or not loop.is_running():
        return
    asyncio, warnings = sys.modules["asyncio"], sys.modules["warnings"]  # asyncio imports warnings
    contextlib = sys.modules["contextlib"]  # typer's, since start-up
    warnings.filterwarnings("ignore", "coroutine .* was never awaited", RuntimeWarning)

    async def settled() -> None:
        while pending := asyncio.all_tasks() - {asyncio.current_task()}:
            await asyncio.wait(pending)

    # A write that will not finish is no reason to keep the process alive.
    with contextlib.suppress(Exception):
        asyncio.run_coroutine_threadsafe(settled(), loop).result(timeout=5)


def _importing_torch() -> bool:
    """Whether torch is being imported (in sys.modules, its initialisation not finished)."""
    spec = getattr(sys.modules.get("torch"), "__spec__", None)
    return bool(getattr(spec, "_initializing", False))


def _removing_a_folder(frame: object) -> bool:
    """Whether `frame` is inside shutil.rmtree: a store's `finally` removing its temporary
    folder, which an interrupt raised there would leave half removed."""
    return _inside(frame, getattr(sys.modules.get("shutil"), "rmtree", None))


def _inside(frame: object, function: object) -> bool:
    """Whether `frame` is inside a call of `function` (None: never)."""
    code = getattr(function, "__code__", None)
    while frame is not None and code is not None:
        if frame.f_code is code:
            return True
        frame = frame.f_back
    return False


def _raised_while_unwinding(error: BaseException | None) -> bool:
    """Whether `error` was raised while a KeyboardInterrupt (a signal, see `main`) unwound."""
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, KeyboardInterrupt):
            return True
        seen.add(id(error))
        error = error.__context__
    return False


def main() -> None:
    """The console entry point: every way out of a command follows SPEC §22's one rule.

    A usage error (click's) is one line and exit 2; SIGTERM and SIGHUP unwind like Ctrl-C, so the
    `finally` blocks that remove temporary files run and nothing half-written is left; an error
    oodrl did not expect is one line naming it and exit 1, its traceback only with OODRL_DEBUG=1.
    """
    import signal
    import threading

    received: list[signal.Signals] = []
    finished = False  # the command has returned: a signal now has nothing left to unwind
    # An interrupt raised in C code that calls back into Python (an extension module's init
    # importing a module) can be swallowed there; a command still running this long after it
    # was raised gets it again, so it stops instead of running to its end.
    still_running_check_s = 0.25
    redeliveries: list[threading.Timer] = []

    def interrupt(signum: int, frame: object) -> None:
        received.append(signal.Signals(signum))
        if finished:
            return  # its outputs are whole; raising now would only print a traceback at exit
        if signal.getsignal(signum) is not interrupt:
            # Chained from another handler (`suite run`'s), which raises itself and decides
            # what a second signal means: a redelivery would look like one.
            return
        if _importing_torch() or _removing_a_folder(frame):
            # Raised inside torch's initialisation, the interrupt can abort the process (C++
            # code that meets the pending exception terminates); raised inside a temporary
            # folder's removal, it leaves the folder half removed: deliver it once either is done.
            deliver_again(0.05)
            return
        if _inside(frame, unraisable):
            # Landed in the hook below while it starts a redelivery (on a loaded machine, that
            # redelivery's own signal can land there): raised there, it would be printed as a
            # traceback and dropped. Delivered again once the hook is done, instead.
            deliver_again(still_running_check_s)
            return
        if _raised_while_unwinding(sys.exc_info()[1]):
            deliver_again(still_running_check_s)  # already unwinding: only check it ends
            return
        _settle_store_writes()
        deliver_again(still_running_check_s)
        raise KeyboardInterrupt

    def unraisable(report) -> None:
        # A signal that lands in code that cannot raise (a __del__, a weakref callback) is
        # printed by Python as a traceback and dropped: stay quiet and deliver it again, so
        # the command still stops at once instead of running to its end.
        if not (received and issubclass(report.exc_type, KeyboardInterrupt)):
            default_unraisable(report)
        elif not finished:
            deliver_again(0.01)

    def deliver_again(after_s: float) -> None:
        def deliver() -> None:
            if not finished:
                os.kill(os.getpid(), received[-1])

        redeliveries[:] = [timer for timer in redeliveries if timer.is_alive()]
        redelivery = threading.Timer(after_s, deliver)
        redelivery.daemon = True
        redelivery.start()
        redeliveries.append(redelivery)

    def interrupted() -> NoReturn:
        # typer turns a KeyboardInterrupt into exit code 130 silently; say which signal it was.
        name = received[0] if received else signal.SIGINT
        typer.echo(f"error: interrupted ({name.name})", err=True)
        sys.exit(128 + name.value)

    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(signum) in (signal.SIG_DFL, signal.default_int_handler):
            signal.signal(signum, interrupt)  # an ignored one stays ignored: `nohup oodrl …`
    default_unraisable, sys.unraisablehook = sys.unraisablehook, unraisable
    debug = os.environ.get(DEBUG_VARIABLE) == "1"
    try:
        try:
            code = app(standalone_mode=False)
        finally:
            finished = True
            # The interpreter's exit restores the default handlers: a late redelivery would end
            # the process by the signal instead of the exit code chosen below.
            for redelivery in redeliveries:
                redelivery.cancel()
    except typer.TyperException as error:  # click's usage errors (exit code 2), as typer has them
        context = getattr(error, "ctx", None)
        where = context.command_path if context else "oodrl"
        if message := one_line(error.format_message()):  # none when the help was printed instead
            typer.echo(f"error: {where}: {message} (see `{where} --help`)", err=True)
        sys.exit(error.exit_code)
    except (KeyboardInterrupt, typer.Abort):
        interrupted()
    except OodrlError as error:  # raised outside a command, e.g. by a callback
        try:
            _fail(error)
        except typer.Exit as done:
            sys.exit(done.exit_code)
    except Exception as error:
        if debug:
            raise
        if received and _raised_while_unwinding(error):
            interrupted()  # a library's clean-up that failed because the signal cut it short
        # A full disk, a refused permission, a read-only filesystem, too many open files: the
        # machine's fault, not oodrl's, named with its path and what to do (oodrl.faults); also
        # when a library wraps the OSError in an exception of its own.
        from oodrl.faults import machine_fault

        fault = machine_fault(error)
        typer.echo(
            f"error: {one_line(fault)}"
            if fault
            else f"error: internal error, {type(error).__name__}: {one_line(str(error))} (a bug "
            f"in oodrl or a plugin; {DEBUG_VARIABLE}=1 shows the traceback)",
            err=True,
        )
        sys.exit(1)
    if received:
        interrupted()
    sys.exit(code if isinstance(code, int) else 0)
