"""Fixtures shared by the test modules: entry points installed for one test only, and the
toy scenario and recipe of ``examples/extending`` (that folder is put on ``sys.path`` so the
tests import ``toy_scenario`` and ``toy_recipe`` as a researcher's package would), and the
repository's scripts imported as modules."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Callable
from importlib import metadata
from pathlib import Path
from types import ModuleType

import pytest

from mapets_rl.envs import registry
from mapets_rl.experiment import register_env

ROOT = Path(__file__).resolve().parents[1]
EXTENDING = ROOT / "examples" / "extending"
sys.path.insert(0, str(EXTENDING))


@pytest.fixture
def add_entry_point(monkeypatch) -> Callable[[str, str, str], None]:
    """``add_entry_point(group, name, "module:attr")`` makes an entry point look installed for
    this test, next to the really installed ones (``importlib.metadata.entry_points`` is
    patched; the package's metadata is left alone)."""
    extra: list[metadata.EntryPoint] = []
    installed = metadata.entry_points

    def entry_points(**params):
        if set(params) != {"group"}:
            return installed(**params)
        mine = [ep for ep in extra if ep.group == params["group"]]
        return metadata.EntryPoints([*installed(**params), *mine])

    monkeypatch.setattr(metadata, "entry_points", entry_points)

    def add(group: str, name: str, value: str) -> None:
        extra.append(metadata.EntryPoint(name=name, value=value, group=group))

    return add


@pytest.fixture
def toy_scenario(monkeypatch) -> str:
    """``ToyAgentsEnv`` of ``examples/extending/toy_scenario.py`` registered as scenario
    ``toy`` for this test only (in a copy of the scenario registry)."""
    from toy_scenario import ToyAgentsEnv

    monkeypatch.setattr(registry, "_SCENARIOS", dict(registry._SCENARIOS))
    register_env("toy", ToyAgentsEnv)
    return "toy"


@pytest.fixture
def toy_recipe(add_entry_point, toy_scenario) -> None:
    """``ToyLearner`` of ``examples/extending/toy_recipe.py`` installed as recipe ``toy``, with
    the ``toy`` scenario registered."""
    add_entry_point("mapets_rl.recipes", "toy", "toy_recipe:ToyLearner")


@pytest.fixture
def load_script() -> Callable[[str], ModuleType]:
    """``load_script("examples/mixed_traffic.py")``: a script of the repository imported as a
    module (examples and benchmarks are scripts, not packages)."""

    def load(path: str) -> ModuleType:
        spec = importlib.util.spec_from_file_location(Path(path).stem, ROOT / path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load
