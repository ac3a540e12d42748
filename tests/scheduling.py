"""How `pytest -n N` (pytest-xdist) deals the tests out: a module at a time, the costliest first,
so that no worker sits idle at the end while the other runs a long module it was dealt last.

xdist's default (`--dist load`) sends each worker a quarter of its share of tests in file order,
then more as it runs low. The suite's costliest modules sit late in that order
(test_suite_run.py, last but a few, builds a suite serially and then in parallel), so a run ended
on one busy worker; and a module's tests could be split between workers at a chunk's edge, each
building the module's fixtures. Here a worker is dealt a whole module (or a group of modules that
share a session fixture), the next when it is down to its last two tests, and the modules come
costliest first (COST_S; a module without an entry that holds a `slow` test counts SLOW_S), the
rest in file order. Every test still runs once, in its module's order.

tests/conftest.py installs this in place of xdist's `--dist load`, what `-n N` alone gives;
another `--dist`, `-n 0` and `-p no:xdist` keep xdist's own scheduling (or none).
"""

from __future__ import annotations

import pytest

#: Seconds a module's tests took (setup, call and teardown summed, from the junit file of the
#: README's test command in a fresh clone of e0e9bca on an idle 2-core machine: 2,640 s of worker
#: time in 1,351 s), for the modules over 40 s. A group's first module pays its shared build (the
#: serial suite's). Only the order reads them: a stale or missing entry costs time, never a result.
COST_S: dict[str, float] = {
    "tests/test_suite_run_ray.py": 161,
    "tests/test_readme.py": 148,
    "tests/test_suite_run.py": 142,
    "tests/test_migration_resume.py": 127,
    "tests/test_protocol_every_environment.py": 124,
    "tests/hostile/test_runtime_hostile.py": 121,
    "tests/test_remote.py": 118,
    "tests/api/test_evaluate.py": 106,
    "tests/test_suite.py": 94,
    "tests/pipeline/test_environments.py": 94,
    "tests/pipeline/test_warm.py": 90,
    "tests/pipeline/test_pipeline.py": 87,
    "tests/test_suite_try.py": 74,
    "tests/test_readonly_remote.py": 74,
    "tests/metrics/test_leaderboard_rliable.py": 69,
    "tests/pipeline/test_failures.py": 63,
    "tests/pipeline/test_deps.py": 61,
    "tests/test_new.py": 54,
    "tests/test_recorded.py": 47,
    "tests/report/test_leaderboard_page.py": 47,
    "tests/faults/test_remote_faults.py": 42,
    "tests/detectors/test_library.py": 41,
}
#: What a module without an entry in COST_S counts when it holds a test marked `slow`.
SLOW_S = 50.0
#: Modules that use one session fixture are dealt to one worker together, which builds it once:
#: the tests' tiny pipeline (`built_repo`, tests/tiny_pipeline.py), the tiny suite's serial build.
GROUPS: dict[str, str] = {
    **{
        module: "built_repo"
        for module in (
            "tests/api/test_evaluate.py",
            "tests/metrics/test_cells.py",
            "tests/test_fresh_check.py",
            "tests/pipeline/test_deps.py",
            "tests/pipeline/test_failures.py",
            "tests/pipeline/test_leaderboard_pipeline.py",
            "tests/pipeline/test_pipeline.py",
            "tests/pipeline/test_recovery.py",
            "tests/pipeline/test_warm.py",
        )
    },
    # The tiny suite's serial build (tests/suite_repo.py serial_built_suite): a second worker
    # asking for it while the first builds it would wait, idle, under its file lock.
    **{
        module: "serial_built_suite"
        for module in (
            "tests/test_suite_run.py",
            "tests/test_suite_run_ray.py",
            "tests/test_suite_try.py",
            "tests/test_remote.py",
            "tests/test_migration.py",
            "tests/test_migration_resume.py",
            "tests/pipeline/test_environments.py",
        )
    },
}


def module_of(nodeid: str) -> str:
    return nodeid.split("::", 1)[0]


def unit_of(nodeid: str) -> str:
    """The unit a test is dealt in: its module's group, else its module."""
    module = module_of(nodeid)
    return GROUPS.get(module, module)


def costliest_first(items: list[pytest.Item]) -> None:
    """Reorder `items` in place: units costliest first, then in file order; within a unit its
    modules and their tests keep their order (a module's tests stay together)."""
    slow = {module_of(item.nodeid) for item in items if item.get_closest_marker("slow")}
    cost: dict[str, float] = {}
    first: dict[str, int] = {}
    for index, module in enumerate(dict.fromkeys(module_of(item.nodeid) for item in items)):
        unit = unit_of(module)
        cost[unit] = cost.get(unit, 0.0) + COST_S.get(module, SLOW_S if module in slow else 0.0)
        first.setdefault(unit, index)
    order = {id(item): index for index, item in enumerate(items)}

    def key(item: pytest.Item) -> tuple[float, int, int]:
        unit = unit_of(item.nodeid)
        return (-cost[unit], first[unit], order[id(item)])

    items.sort(key=key)


def module_scheduling(config: pytest.Config, log):
    """xdist's scope scheduler with a unit (unit_of) as the scope, dealt in the order the
    workers collected (costliest_first's) rather than by how many tests a scope holds."""
    from xdist.scheduler import LoadScopeScheduling

    class ModuleScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return unit_of(nodeid)

    config.option.loadscopereorder = False
    return ModuleScheduling(config, log)
