"""Fixtures of the application's tests: the matplotlib figures ``compare`` saves."""

from __future__ import annotations

from types import ModuleType

import pytest


def _saved_figures(monkeypatch: pytest.MonkeyPatch, modules: list[ModuleType]) -> list:
    """Record every figure that ``modules`` save through their ``atomic_savefig`` (still
    saving it), in order."""
    saved: list = []
    for module in modules:
        original = module.atomic_savefig

        def savefig(fig, path, _original=original, **kwargs) -> None:
            saved.append(fig)
            _original(fig, path, **kwargs)

        monkeypatch.setattr(module, "atomic_savefig", savefig)
    return saved


@pytest.fixture
def figures(monkeypatch: pytest.MonkeyPatch) -> list:
    """The learning-curve figures ``compare`` saves, in order."""
    from mapets_rl.app import comparison

    return _saved_figures(monkeypatch, [comparison])


@pytest.fixture
def all_figures(monkeypatch: pytest.MonkeyPatch) -> list:
    """Every figure ``compare`` saves, in order (learning curves, then profiles)."""
    from mapets_rl.app import comparison, rliable_report

    return _saved_figures(monkeypatch, [comparison, rliable_report])
