import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from oodrl.config import read_params_data
from oodrl.errors import RegistryError
from oodrl.io.store import load_detector, save_detector
from oodrl.registry import Registry, add_project_dir_to_path, import_path


def test_lazy_registry_resolves_and_suggests():
    registry = Registry("widget")
    registry.register("ordered_dict", "collections:OrderedDict")
    from collections import OrderedDict

    assert registry.get("ordered_dict") is OrderedDict
    assert registry.names() == ["ordered_dict"]
    with pytest.raises(RegistryError, match="Did you mean 'ordered_dict'.*Known: ordered_dict"):
        registry.get("ordered_dct")


def test_duplicate_name_is_an_error():
    registry = Registry("widget")
    registry.register("a", "collections:OrderedDict")
    with pytest.raises(RegistryError, match="already registered"):
        registry.register("a", "collections:Counter")


def test_module_class_paths():
    registry = Registry("widget")
    from collections import Counter

    assert registry.get("collections:Counter") is Counter
    with pytest.raises(RegistryError, match="Cannot import module"):
        import_path("no_such_module_xyz:Thing")
    with pytest.raises(RegistryError, match="has no attribute"):
        import_path("collections:NoSuchThing")
    with pytest.raises(RegistryError, match="not an import path"):
        import_path("collections.Counter")


def test_builtin_registries_list_the_protocol_components():
    from oodrl.detectors import DETECTORS
    from oodrl.envs import ENVIRONMENTS
    from oodrl.injectors import INJECTORS

    assert len(DETECTORS.names()) == 19  # the eight of SPEC §5, nine of §20 and two of §24
    assert len(INJECTORS.names()) == 14  # the nine of SPEC §4 and five live observation faults
    assert "LunarLander-v3" in ENVIRONMENTS


PROJECT_MODULE = """
import numpy as np

from oodrl.core import BaseDetector


class Constant(BaseDetector):
    name = "constant"

    def _fit(self, trajectories):
        pass

    def _score(self, trajectory):
        return np.zeros(trajectory.T)
"""


@pytest.fixture
def project_dir(tmp_path, monkeypatch):
    """An empty project directory as the current one, neither it nor '' on sys.path (as under
    the `oodrl` console script); modules imported from it are forgotten afterwards."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p not in ("", str(tmp_path))])
    before = set(sys.modules)
    yield tmp_path
    for name in set(sys.modules) - before:
        if name.startswith("oodrl_project_plugin"):
            del sys.modules[name]


def test_module_class_path_imports_from_the_project_directory(project_dir):
    package = project_dir / "oodrl_project_plugin"
    package.mkdir()
    (package / "detectors.py").write_text(PROJECT_MODULE)
    cls = Registry("detector").get("oodrl_project_plugin.detectors:Constant")
    assert cls.name == "constant"
    # The project directory stays importable: unpickling a fitted plugin detector needs it.
    assert str(project_dir) in sys.path


def test_a_plugin_detectors_pickle_loads_from_the_project_directory(project_dir, monkeypatch):
    """load_detector (score stages, cost measurement, monitor) finds the module of a pickled
    plugin detector beside params.yaml, with the project directory not on sys.path."""
    package = project_dir / "oodrl_project_plugin"
    package.mkdir()
    (package / "detectors.py").write_text(PROJECT_MODULE)
    cls = Registry("detector").get("oodrl_project_plugin.detectors:Constant")
    save_detector(project_dir / "constant.pkl", cls(), "constant", {})
    for name in [n for n in sys.modules if n.startswith("oodrl_project_plugin")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p != str(project_dir)])
    detector = load_detector(project_dir / "constant.pkl", stage="fit")
    assert type(detector).__module__ == "oodrl_project_plugin.detectors"


def test_add_project_dir_to_path_appends_it_once(project_dir):
    assert add_project_dir_to_path() is True
    assert sys.path[-1] == str(project_dir)  # appended: no project file shadows a package
    assert add_project_dir_to_path() is False
    assert sys.path.count(str(project_dir)) == 1


def test_a_project_module_missing_a_dependency_names_the_dependency(project_dir):
    (project_dir / "oodrl_project_plugin_broken.py").write_text("import no_such_dependency_xyz\n")
    with pytest.raises(RegistryError, match="No module named 'no_such_dependency_xyz'"):
        import_path("oodrl_project_plugin_broken:Thing")


def test_the_oodrl_command_finds_a_plugin_beside_params_yaml(tmp_path, repo_root):
    """The console script (sys.path[0] = its bin directory) validates params naming a
    `module:Class` in the directory it runs in."""
    (tmp_path / "oodrl_project_plugin.py").write_text(PROJECT_MODULE)
    params = read_params_data(repo_root / "ci" / "params.yaml")
    params["benchmark"]["detectors"].append("constant")
    params["detectors"]["constant"] = {"class": "oodrl_project_plugin:Constant"}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    oodrl = Path(sys.executable).parent / "oodrl"
    done = subprocess.run(
        [str(oodrl), "check-params"], cwd=tmp_path, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    assert f"ok ({len(params['benchmark']['detectors'])} detectors" in done.stdout
