"""Entry points of the installed packages: the one lookup that the scenario registry
(:mod:`mapets_rl.envs.registry`, group ``mapets_rl.scenarios``) and the recipes
(:mod:`mapets_rl.app.plugins`, group ``mapets_rl.recipes``) share.

Listing names reads only the installed packages' metadata; nothing is imported until a name is
loaded, so ``mapets-rl --help`` stays fast.
"""

from __future__ import annotations

import os
import unicodedata
from importlib import metadata
from typing import Any


def check_name(name: object, what: str) -> str:
    """``name`` when it can name a ``what`` (``"scenario"``, ``"recipe"``); one-line ValueError
    otherwise. The names become part of the default run directory's name
    (``runs/<recipe>_<scenario>_seed<N>_<time>``), so a name must be a non-empty string without
    path separators, ``..`` or control characters (line breaks included) and without leading
    or trailing white space."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"name must be a non-empty {what} name, got {name!r}")
    separators = {"/", "\\", os.sep, os.altsep} - {None}
    bad = next(
        (
            char
            for char in name
            if char in separators or unicodedata.category(char) in ("Cc", "Cf", "Zl", "Zp")
        ),
        None,
    )
    if bad is not None or ".." in name or name != name.strip():
        why = (
            f"the character {bad!r}"
            if bad is not None
            else "'..'"
            if ".." in name
            else "leading or trailing white space"
        )
        raise ValueError(
            f"{what} name {name!r} is refused: it holds {why} (a name becomes part of the run "
            "directory's name: no path separators, '..' or control characters)"
        )
    return name


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
        group: entry-point group, e.g. ``"mapets_rl.recipes"``.
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
