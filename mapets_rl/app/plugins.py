"""Recipes that installed packages provide through entry points.

The library never imports its applications: the ``mapets-rl`` command, ``resume`` and
``evaluate`` find a recipe by name in the entry-point group ``mapets_rl.recipes`` (scenarios
beyond the built-in ones come from the group ``mapets_rl.scenarios``, which the scenario
registry :mod:`mapets_rl.envs.registry` reads). A package declares them in its
``pyproject.toml``::

    [project.entry-points."mapets_rl.recipes"]
    myalgo = "mypackage.myalgo:MyAlgo"            # an Experiment subclass

    [project.entry-points."mapets_rl.scenarios"]
    my-road = "mypackage.roads:make_my_road"      # factory(**env_config) -> torchrl EnvBase

Entry points exist once the package's metadata is installed (``pip install -e .`` again after
editing them). Listing names reads only that metadata; nothing is imported until a name is
loaded, so ``mapets-rl --help`` stays fast.
"""

from __future__ import annotations

from mapets_rl._entry_points import entry_points, load_entry_point

RECIPE_GROUP = "mapets_rl.recipes"


def available_recipes() -> list[str]:
    """Names of the installed recipes (entry-point group ``mapets_rl.recipes``), sorted."""
    return sorted(entry_points(RECIPE_GROUP))


def load_recipe(name: str) -> type:
    """The recipe class installed as ``name`` (an ``Experiment`` subclass); one-line ValueError
    naming the known recipes when there is none of that name, and when the entry point names
    anything but an ``Experiment`` subclass."""
    recipe = load_entry_point(RECIPE_GROUP, name, "recipe")  # an unknown name: before torch
    from mapets_rl.experiment.runner import Experiment

    if not (isinstance(recipe, type) and issubclass(recipe, Experiment)):
        raise ValueError(
            f"recipe {name!r} ({entry_points(RECIPE_GROUP)[name].value}) is not an Experiment "
            f"subclass (it is {type(recipe).__name__} {recipe!r:.60}); the installed package "
            "that declares it is broken"
        )
    return recipe
