"""Where the API finds a project's pipelines: the root (the paper's LunarLander pipeline), each
environment's `pipeline/<name>/`, and the suite's `pipeline/suite/`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from oodrl.errors import ConfigError
from oodrl.suite.pipeline import PARAMS_FILE, SUITE_DIR, pipeline_dirs

#: A pipeline's committed policy, relative to its directory.
POLICY_FILE = Path("models/policy.pt")


def project_root(start: Path | None = None) -> Path | None:
    """The oodrl project holding `start` (default: the working directory), else the checkout
    this package was installed from (an editable install), else None."""
    here = Path.cwd() if start is None else Path(start)
    for directory in (here.resolve(), *here.resolve().parents):
        if _is_project(directory):
            return directory
    checkout = Path(__file__).resolve().parents[3]  # src/oodrl/api/project.py
    return checkout if _is_project(checkout) else None


def _is_project(directory: Path) -> bool:
    return (directory / PARAMS_FILE).is_file() and (directory / SUITE_DIR).is_dir()


def is_suite(directory: Path) -> bool:
    return (directory / "reports" / "leaderboard.json").is_file() or (
        directory.name == SUITE_DIR.name and (directory / "dvc.yaml").is_file()
        and not (directory / PARAMS_FILE).is_file()
    )  # fmt: skip


def is_pipeline(directory: Path) -> bool:
    return (directory / PARAMS_FILE).is_file() and (directory / "dvc.yaml").is_file()


@dataclass(frozen=True)
class Pipeline:
    """One (environment, policy) pipeline: its directory and the labels results carry."""

    directory: Path
    env: str
    policy: str

    @property
    def params_path(self) -> Path:
        return self.directory / PARAMS_FILE

    @property
    def policy_path(self) -> Path:
        return self.directory / POLICY_FILE


def pipeline_names(root: Path | None) -> list[str]:
    """The names `pipeline/<name>` of the project's environment pipelines."""
    return [] if root is None else [d.name for d in pipeline_dirs(root)[1:]]


def resolve_directory(where: str | Path, what: str) -> Path:
    """A directory or file the user named: a path (relative to the working directory), a
    pipeline's name (`cartpole`, `cartpole_policy1`), an environment id of the suite
    (`CartPole-v1`: its first policy's pipeline) or `suite`; a one-line error naming what is
    allowed otherwise."""
    path = Path(where).expanduser()
    if path.exists():
        return path
    root = project_root()
    text = str(where)
    if root is not None:
        from oodrl.suite.environments import PIPELINE_DIRS

        if text == "suite":
            return root / SUITE_DIR
        if text in PIPELINE_DIRS:
            return root / PIPELINE_DIRS[text]
        if text in pipeline_names(root):
            return root / "pipeline" / text
    names = pipeline_names(root)
    known = f" Known here: {', '.join(names)}, suite." if names else ""
    raise ConfigError(
        f"{what} {text!r}: no such file or directory. Allowed: a pipeline directory (the "
        f"project root, pipeline/<env>), the suite directory (pipeline/suite), a results file, "
        f"a pipeline's name or an environment id of the suite.{known}"
    )


def pipeline_at(directory: Path) -> Pipeline:
    """The pipeline in `directory`, labelled with its environment id (from its params) and
    its policy (the suite's label: "0" for an environment's first policy)."""
    from oodrl.config import read_params_data

    directory = Path(directory)
    if not is_pipeline(directory):
        raise ConfigError(
            f"{directory}: not a pipeline directory (it needs {PARAMS_FILE} and dvc.yaml). "
            "Allowed: the project root or pipeline/<env>."
        )
    env = read_params_data(directory / PARAMS_FILE).get("env", {}).get("id", "LunarLander-v3")
    return Pipeline(directory, str(env), _policy_label(directory))


def _policy_label(directory: Path) -> str:
    from oodrl.metrics.leaderboard import FIRST_POLICY
    from oodrl.suite.environments import suite_runs

    root = project_root(directory)
    if root is not None:
        resolved = directory.resolve()
        for (_, policy), relative in suite_runs().items():
            if (root / relative).resolve() == resolved:
                return policy
    return FIRST_POLICY
