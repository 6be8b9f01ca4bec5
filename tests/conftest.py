"""Fixtures shared by the test modules: entry points installed for one test only."""

from __future__ import annotations

from collections.abc import Callable
from importlib import metadata

import pytest


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
def toy_recipe(add_entry_point) -> None:
    """The toy learner of ``test_experiment`` installed as recipe ``toy`` (its module also
    registers the ``toy`` scenario)."""
    import test_experiment  # noqa: F401

    add_entry_point("mapets_rl.recipes", "toy", "test_experiment:ToyLearner")
