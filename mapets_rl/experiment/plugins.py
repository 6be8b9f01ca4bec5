"""Recipes and scenarios that installed packages provide through entry points.

The library never imports its applications: the ``mapets-rl`` command, ``resume`` and
``evaluate`` find a recipe by name in the entry-point group ``mapets_rl.recipes``, and
:func:`~mapets_rl.experiment.runner.build_env` finds scenarios beyond the built-in ones in
``mapets_rl.scenarios``. A package declares them in its ``pyproject.toml``::

    [project.entry-points."mapets_rl.recipes"]
    myalgo = "mypackage.myalgo:MyAlgo"            # an Experiment subclass

    [project.entry-points."mapets_rl.scenarios"]
    my-road = "mypackage.roads:make_my_road"      # factory(**env_config) -> torchrl EnvBase

Entry points exist once the package's metadata is installed (``pip install -e .`` again after
editing them). Listing names reads only that metadata; nothing is imported until a name is
loaded, so ``mapets-rl --help`` stays fast.
"""

from __future__ import annotations

from importlib import metadata
from typing import Any

RECIPE_GROUP = "mapets_rl.recipes"
SCENARIO_GROUP = "mapets_rl.scenarios"


def entry_points(group: str) -> dict[str, metadata.EntryPoint]:
    """Name -> entry point of ``group`` over the installed distributions.

    The same declaration seen twice (a distribution found on two ``sys.path`` entries, e.g. an
    editable install run from its source tree) counts once; two different targets for one name
    raise a one-line ValueError naming both.
    """
    found: dict[str, metadata.EntryPoint] = {}
    for ep in metadata.entry_points(group=group):
        seen = found.setdefault(ep.name, ep)
        if seen.value != ep.value:
            raise ValueError(
                f"{group} entry point {ep.name!r} is declared twice, as "
                f"{seen.value!r} and {ep.value!r}; uninstall one of the packages"
            )
    return found


def load_entry_point(group: str, name: str, what: str) -> Any:
    """The object that entry point ``name`` of ``group`` names; one-line ValueErrors for an
    unknown name (listing the known ones) and for a target that cannot be imported.

    Args:
        group: entry-point group, e.g. :data:`RECIPE_GROUP`.
        name: the entry point's name.
        what: what the group holds, for messages (``"recipe"``, ``"scenario"``).
    """
    known = entry_points(group)
    if name not in known:
        if not known:
            raise ValueError(
                f"unknown {what} {name!r}: no {what}s are registered (entry-point "
                f"group {group!r} is empty; reinstall the package that provides "
                "them, e.g. pip install -e .)"
            )
        raise ValueError(f"unknown {what} {name!r} (choose from: {', '.join(sorted(known))})")
    ep = known[name]
    try:
        return ep.load()
    except (ImportError, AttributeError) as err:
        lines = str(err).strip().splitlines()
        raise ValueError(
            f"{what} {name!r} ({ep.value}) cannot be imported: "
            f"{lines[0] if lines else type(err).__name__}"
        ) from err


def available_recipes() -> list[str]:
    """Names of the installed recipes (entry-point group ``mapets_rl.recipes``), sorted."""
    return sorted(entry_points(RECIPE_GROUP))


def load_recipe(name: str) -> type:
    """The recipe class installed as ``name`` (an ``Experiment`` subclass); one-line ValueError
    naming the known recipes when there is none of that name."""
    return load_entry_point(RECIPE_GROUP, name, "recipe")
