"""One generic lazy registry for detectors, injectors, metrics and environments.

Built-ins register an import path (`"oodrl.detectors.kde:KdeDensity"`) in their subpackage's
`__init__`; the object is imported on first use. Third parties add components through the
entry-point groups `oodrl.<kind>` or by naming a `module:Class` path in params.yaml. Such a
path's module, when no installed one has its name, is looked up in the project directory (the
current directory, where `dvc repro` runs every stage command), so a user's own
`mypkg/detectors.py` next to params.yaml works without packaging it, as under `python -m`.
"""

from __future__ import annotations

import difflib
import importlib
import os
import sys
from collections.abc import Iterator
from functools import cache
from importlib.metadata import EntryPoints, entry_points
from typing import Any

from oodrl.errors import RegistryError


def _is_missing(error: ModuleNotFoundError, module_name: str) -> bool:
    """Whether `error` says `module_name` itself (or a parent package) is missing, as opposed
    to a module it imports."""
    return error.name is not None and (
        module_name == error.name or module_name.startswith(error.name + ".")
    )


def add_project_dir_to_path() -> bool:
    """Add the current directory to sys.path; False if it was there already.

    The `oodrl` console script starts with its own bin directory as sys.path[0], not the
    project's (`python -m` would have the project's), so a plugin module beside params.yaml
    would not import. Appended, so no project file shadows an installed module. The entry
    stays: the plugin's lazy imports and unpickling its fitted detectors need it later.
    """
    cwd = os.getcwd()
    if any(os.path.abspath(entry or os.curdir) == cwd for entry in sys.path):
        return False
    sys.path.append(cwd)
    importlib.invalidate_caches()
    return True


def import_module(module_name: str) -> Any:
    """Import a module; one that is not installed is looked up in the project directory."""
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as error:
        if not _is_missing(error, module_name) or not add_project_dir_to_path():
            raise
    return importlib.import_module(module_name)


def import_path(path: str) -> Any:
    """Import `module:attribute`, with an error that says which part is missing."""
    module_name, sep, attribute = path.partition(":")
    if not sep or not module_name or not attribute:
        raise RegistryError(f"'{path}' is not an import path; expected 'package.module:Class'.")
    try:
        module = import_module(module_name)
    except ImportError as error:
        raise RegistryError(
            f"Cannot import module '{module_name}' of '{path}' (looked in the installed "
            f"packages and in the project directory {os.getcwd()}): {error}"
        ) from None
    try:
        return getattr(module, attribute)
    except AttributeError:
        raise RegistryError(f"Module '{module_name}' has no attribute '{attribute}'.") from None


@cache
def installed_entry_points() -> EntryPoints:
    """Every installed package's entry points, read once per process: each read scans the
    metadata of every installed distribution, and every stage looks up three groups."""
    return entry_points()


class Registry:
    """Names (snake_case) to lazily imported objects of one kind."""

    def __init__(self, kind: str, adapt: str | None = None) -> None:
        self.kind = kind
        #: `module:function` applied to every object the registry imports (detectors: a
        #: library's outlier class becomes a detector, `oodrl.detectors.library`).
        self.adapt = adapt
        self._paths: dict[str, str] = {}
        self._loaded: dict[str, Any] = {}
        self._entry_points_read = False

    def register(self, name: str, path: str) -> None:
        if name in self._paths:
            raise RegistryError(
                f"A {self.kind} named '{name}' is already registered ({self._paths[name]})."
            )
        self._paths[name] = path

    def _read_entry_points(self) -> None:
        if self._entry_points_read:
            return
        self._entry_points_read = True
        for ep in installed_entry_points().select(group=f"oodrl.{self.kind}s"):
            self.register(ep.name, ep.value)

    def names(self) -> list[str]:
        self._read_entry_points()
        return sorted(self._paths)

    def path(self, name: str) -> str:
        self._read_entry_points()
        if name not in self._paths:
            close = difflib.get_close_matches(name, self._paths, n=1)
            hint = f" Did you mean '{close[0]}'?" if close else ""
            raise RegistryError(
                f"Unknown {self.kind} '{name}'.{hint} Known: {', '.join(sorted(self._paths))}."
            )
        return self._paths[name]

    def get(self, name: str) -> Any:
        """The object registered as `name`; a `module:Class` path is imported directly."""
        if ":" in name:
            return self._adapted(import_path(name))
        if name not in self._loaded:
            self._loaded[name] = self._adapted(import_path(self.path(name)))
        return self._loaded[name]

    def _adapted(self, imported: Any) -> Any:
        return import_path(self.adapt)(imported) if self.adapt else imported

    def __contains__(self, name: str) -> bool:
        self._read_entry_points()
        return name in self._paths

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())
