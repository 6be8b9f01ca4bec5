"""Published configurations: the YAML files behind every headline table, shipped with the
package (``mapets_rl/configs/``) and found by name (``freeway-merge/maddpg-individual``) or
by path.

A file holds config fields, and two keys of its own: ``recipe`` (the recipe it trains; absent
in a fragment) and ``include`` (names of other files, fragments such as
``fragments/openai-maddpg``, whose fields come first: the file's own fields win, mappings such
as ``env_config`` are merged key by key). Its leading comment says what it is, what differs
from its twin and which table it produces; its first line is a one-line summary.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

from mapets_rl.config import ConfigError, read_yaml_mapping

CONFIG_SUFFIX = ".yaml"
MAX_INCLUDE_DEPTH = 8


@dataclasses.dataclass(frozen=True)
class PublishedConfig:
    """One published configuration, its includes resolved.

    Attributes:
        name: its name (path under the shipped folder, without ``.yaml``), or the file path.
        path: the file.
        recipe: the recipe it trains (None for a fragment).
        summary: the first line of its leading comment (one line: what it is).
        description: its whole leading comment, one paragraph.
        fields: the config fields, the included files' merged under its own.
    """

    name: str
    path: Path
    recipe: str | None
    summary: str
    description: str
    fields: dict[str, Any]


def config_root() -> Path:
    """The folder of the shipped configurations."""
    return Path(str(resources.files("mapets_rl") / "configs"))


def _comment(path: Path) -> list[str]:
    """The leading ``#`` comment lines of ``path``, stripped."""
    lines = []
    with open(path, encoding="utf-8") as handle:
        for line in handle:
            if not line.startswith("#"):
                break
            lines.append(line[1:].strip())
    return lines


def _merge(base: Mapping[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    """``top`` over ``base``; mappings present in both are merged key by key."""
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _resolve(name_or_path: str | os.PathLike) -> tuple[str, Path]:
    """The name and file of a published configuration: an existing file, else a shipped name."""
    given = Path(name_or_path)
    if given.exists() or given.suffix in (".yaml", ".yml") or given.is_absolute():
        return str(given), given  # a file: read_yaml_mapping says what is wrong with it
    name = str(name_or_path).removesuffix(CONFIG_SUFFIX)
    path = config_root() / f"{name}{CONFIG_SUFFIX}"
    if ".." in Path(name).parts or not path.is_file():
        known = ", ".join(c.name for c in available_configs(fragments=True))
        raise ConfigError(
            f"config {str(name_or_path)!r} is neither a file nor a published configuration "
            f"(`mapets-rl configs` lists them: {known})"
        )
    return name, path


def _load(name_or_path: str | os.PathLike, depth: int) -> PublishedConfig:
    name, path = _resolve(name_or_path)
    data = read_yaml_mapping(path)
    include = data.pop("include", [])
    if isinstance(include, str):
        include = [include]
    if not isinstance(include, list) or not all(isinstance(i, str) for i in include):
        raise ConfigError(f"config {name!r}: include must be a list of config names")
    if include and depth >= MAX_INCLUDE_DEPTH:
        raise ConfigError(
            f"config {name!r}: includes nest deeper than {MAX_INCLUDE_DEPTH} (a cycle?)"
        )
    recipe = data.pop("recipe", None)
    if recipe is not None and not isinstance(recipe, str):
        raise ConfigError(f"config {name!r}: recipe must be a recipe name, got {recipe!r}")
    fields: dict[str, Any] = {}
    for included in include:
        fields = _merge(fields, _load(included, depth + 1).fields)
    fields = _merge(fields, data)
    comment = _comment(path)
    summary = comment[0] if comment else ""
    return PublishedConfig(name, path, recipe, summary, " ".join(comment), fields)


def load_published(name_or_path: str | os.PathLike) -> PublishedConfig:
    """The published configuration ``name_or_path`` (a shipped name such as
    ``freeway-merge/maddpg-individual``, or a YAML file), includes resolved; ConfigError naming
    the published ones when it is neither."""
    return _load(name_or_path, 0)


def available_configs(fragments: bool = False) -> list[PublishedConfig]:
    """The shipped configurations, sorted by name (``fragments``: those without a recipe
    too)."""
    root = config_root()
    found = []
    for path in sorted(root.rglob(f"*{CONFIG_SUFFIX}")):
        name = path.relative_to(root).with_suffix("").as_posix()
        config = load_published(name)
        if config.recipe is not None or fragments:
            found.append(config)
    return found


def recipe_and_env(
    command: str, recipe: str | None, env: str | None, published: PublishedConfig | None
) -> tuple[str, str]:
    """The recipe and scenario of a ``train`` or ``sweep`` (``command``): each as given (RECIPE,
    ``--env``) or read from its ``--config`` (``published``); ConfigError when a given recipe
    is not the configuration's, or when either is missing."""
    named = published.recipe if published is not None else None
    if recipe is not None and named is not None and recipe != named:
        raise ConfigError(
            f"RECIPE {recipe!r} differs from --config {published.name!r}'s recipe, {named}"
        )
    recipe = recipe or named
    if recipe is None:
        raise ConfigError(
            f"{command} needs RECIPE, or a --config that names one (`mapets-rl configs` lists them)"
        )
    env = env or (published.fields.get("env") if published is not None else None)
    if not isinstance(env, str):
        raise ConfigError(f"{command} needs --env SCENARIO, or a --config that sets env")
    return recipe, env
