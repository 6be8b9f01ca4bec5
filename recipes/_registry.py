"""Recipe name -> ``"module:Class"`` for the ``mapets-rl`` CLI (imported lazily, so ``--help``
stays fast). A recipe author registers a recipe by adding one line here."""

from __future__ import annotations

import importlib

RECIPES: dict[str, str] = {
    "maddpg": "recipes.maddpg:MADDPG",
    "mapets": "recipes.mapets:MAPETS",
    "mappo": "recipes.mappo:MAPPO",
    "sac": "recipes.sac:SAC",
    "shapley_ac": "recipes.shapley_ac:ShapleyAC",
}


def load_recipe(name: str) -> type:
    """The recipe class registered as ``name`` (ValueError naming the known recipes)."""
    if name not in RECIPES:
        raise ValueError(f"unknown recipe {name!r} (choose from: {', '.join(sorted(RECIPES))})")
    module, _, attr = RECIPES[name].partition(":")
    return getattr(importlib.import_module(module), attr)
