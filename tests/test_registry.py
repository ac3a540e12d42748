import pytest

from oodrl.errors import RegistryError
from oodrl.registry import Registry, import_path


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

    assert len(DETECTORS.names()) == 8
    assert len(INJECTORS.names()) == 9
    assert "LunarLander-v3" in ENVIRONMENTS
