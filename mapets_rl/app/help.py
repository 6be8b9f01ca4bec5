"""``mapets-rl train RECIPE --help``: RECIPE's config documented field by field, with the values
of the preset and ``key=value`` options given on the command line (else the defaults), the
scenarios whose actions RECIPE takes, and the ``env_config`` keys of the chosen scenario
(``--env NAME``, else the config's) with what each accepts
(:func:`mapets_rl.envs.factory.env_config_help`).

Each description is the first whole sentence of the field's entry in the ``Attributes:``
section of its config class (or of a base class), rid of its Sphinx markup (````x```` becomes
``x``, ``:class:`~a.B``` becomes ``B``) and wrapped at :data:`WIDTH` columns.

Making the text imports the recipe (torch) and builds every scenario once, seconds of work, so
the text is kept in a private cache directory (``$XDG_CACHE_HOME/mapets_rl/help``, the owner
and mode checks of :mod:`mapets_rl._compile_cache`) under a key of everything it is made of:
the recipe's entry point, the options, the installed entry points of this project's groups,
the scenarios registered in this process, the interpreter, and the size and modification time
of every source file of ``mapets_rl`` and of the recipe's package. A later ``--help`` reads it
without importing torch, well under a second (``benchmarks/startup.py``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
import os
import re
import sys
import tempfile
import textwrap
import typing
from collections.abc import Sequence
from importlib import metadata, util
from pathlib import Path
from typing import Any

import mapets_rl
from mapets_rl._compile_cache import make_private_dir, private_default
from mapets_rl.app.plugins import RECIPE_GROUP, load_recipe
from mapets_rl.app.prog import PROG
from mapets_rl.config import ConfigSection

WIDTH = 100
"""Columns the descriptions are wrapped at."""
CACHE_ENTRIES = 64
"""Help texts the cache keeps (the newest)."""
_FORMAT = 2
"""Version of the text's layout, part of the cache key."""

_ROLE = re.compile(r":[a-z]+:`(~?)([^`]+)`")
_LITERAL = re.compile(r"``([^`]+)``")


def plain(text: str) -> str:
    """``text`` without Sphinx markup: ``:class:`~a.b.C``` -> ``C``, ``:func:`a.f``` -> ``a.f``,
    ````x```` -> ``x``."""
    text = _ROLE.sub(lambda m: m[2].rsplit(".", 1)[-1] if m[1] else m[2], text)
    return _LITERAL.sub(r"\1", text)


def first_sentence(text: str) -> str:
    """``text`` up to the end of its first sentence: the first ``"."`` followed by a space (or
    the end) outside parentheses and not after an abbreviation (``e.g``, ``i.e``, ``eq``)."""
    depth = 0
    for i, char in enumerate(text):
        depth += {"(": 1, ")": -1}.get(char, 0)
        if depth == 0 and char == "." and text[i + 1 : i + 2] in (" ", ""):
            word = text[:i].rsplit(" ", 1)[-1].lower()
            if word not in ("e.g", "i.e", "eq", "eqs", "sec", "cf", "vs"):
                return text[: i + 1]
    return text


def attribute_docs(cls: type) -> dict[str, str]:
    """Field name -> first sentence (plain text) of its entry in the ``Attributes:`` sections
    of the docstrings of ``cls`` and its bases (the nearest class wins); ``a, b: text``
    documents both ``a`` and ``b``."""
    docs: dict[str, str] = {}
    for klass in cls.__mro__:
        doc = inspect.getdoc(klass) if klass.__doc__ else None
        if not doc or "Attributes:" not in doc:
            continue
        entries: list[tuple[list[str], list[str]]] = []
        for line in doc.split("Attributes:", 1)[1].splitlines():
            if not line.strip():
                if entries:
                    break
                continue
            head = re.match(r"^    ([A-Za-z_][\w, ]*):(.*)$", line)
            if head and not line.startswith("     "):
                names = [n.strip() for n in head.group(1).split(",")]
                entries.append((names, [head.group(2).strip()]))
            elif entries and line.startswith("     "):
                entries[-1][1].append(line.strip())
            else:
                break
        for names, text in entries:
            sentence = first_sentence(plain(" ".join(t for t in text if t)))
            for n in names:
                docs.setdefault(n, sentence)
    return docs


def _wrapped(text: str, indent: str = "") -> list[str]:
    """``text`` wrapped at :data:`WIDTH` columns, each line indented by ``indent``."""
    return textwrap.wrap(
        text, WIDTH, initial_indent=indent, subsequent_indent=indent, break_on_hyphens=False
    )


def summary(config_cls: type) -> str:
    """The first paragraph of ``config_cls``'s docstring as plain text, without a last
    sentence that introduces what follows it (ends with ``":"``)."""
    paragraph = " ".join(plain((inspect.getdoc(config_cls) or "").split("\n\n", 1)[0]).split())
    head, _, last = paragraph.rpartition(". ")
    return f"{head}." if head and last.endswith(":") else paragraph


def _field_unit(cls: type, name: str) -> str:
    """The ``unit`` metadata of field ``name`` of ``cls``, or of the nearest base declaring
    it with one (a subclass that only changes a default keeps the unit)."""
    for klass in cls.__mro__:
        if dataclasses.is_dataclass(klass):
            for f in dataclasses.fields(klass):
                if f.name == name and f.metadata.get("unit"):
                    return f.metadata["unit"]
    return ""


def field_lines(config_cls: type, values: object, prefix: str = "") -> list[str]:
    """Help lines of every field of ``config_cls`` (nested sections as ``section.field``):
    ``name: type = value [unit]`` (the value that ``values`` holds, else the default) and its
    description."""
    hints = typing.get_type_hints(config_cls)
    docs = attribute_docs(config_cls)
    lines = []
    for f in dataclasses.fields(config_cls):
        if values is not None:
            value = getattr(values, f.name)
        elif f.default is not dataclasses.MISSING:
            value = f.default
        elif f.default_factory is not dataclasses.MISSING:
            value = f.default_factory()
        else:
            value = dataclasses.MISSING
        if isinstance(value, ConfigSection):
            lines.append(f"  {prefix}{f.name}: section {type(value).__name__}")
            lines += _wrapped(docs[f.name], " " * 6) if f.name in docs else []
            lines += field_lines(type(value), value, f"{prefix}{f.name}.")
            continue
        tp = hints[f.name]
        type_name = tp.__name__ if isinstance(tp, type) else str(tp).replace("typing.", "")
        default = "(required)" if value is dataclasses.MISSING else repr(value)
        unit = _field_unit(config_cls, f.name)
        lines.append(
            f"  {prefix}{f.name}: {type_name} = {default}" + (f" [{unit}]" if unit else "")
        )
        lines += _wrapped(docs[f.name], " " * 6) if f.name in docs else []
    return lines


def recipe_action_kinds(cls: type) -> tuple[str, ...]:
    """The action kinds RECIPE ``cls`` takes (``Experiment.action_kinds``)."""
    return tuple(getattr(cls, "action_kinds", ("continuous", "discrete")))


def scenario_group(env_name: str, env_config: Any) -> tuple[Any, str]:
    """``(AgentGroupSpec, "discrete" | "continuous")`` of scenario ``env_name`` built with
    ``env_config`` (the env is closed again)."""
    from mapets_rl.envs.registry import build_env
    from mapets_rl.modules import AgentGroupSpec

    env = build_env(env_name, env_config)
    try:
        group = AgentGroupSpec.from_env(env)
    finally:
        env.close()
    return group, "discrete" if group.discrete else "continuous"


def supported_scenarios(cls: type, config: object) -> list[str]:
    """One line per available scenario: whether RECIPE ``cls`` handles its actions (built with
    its default config; a scenario that cannot be built says why)."""
    from mapets_rl.envs.registry import available_envs

    kinds = recipe_action_kinds(cls)
    supported, other = [], []
    for env_name in available_envs():
        env_config = getattr(config, "env_config", {}) if env_name == config.env else {}
        try:
            group, kind = scenario_group(env_name, env_config)
        except Exception as err:  # noqa: BLE001 - a broken plug-in must not break --help
            other.append(f"{env_name} (cannot be built: {str(err).splitlines()[0][:80]})")
            continue
        detail = f"{env_name} ({group.n_agents} agents, obs {group.obs_dim}, {kind} actions)"
        (supported if kind in kinds else other).append(detail)
    lines = [f"scenarios ({' or '.join(kinds)} actions; --env SCENARIO):"]
    lines += [f"  {line}" for line in supported] or ["  (none installed)"]
    if other:
        lines.append("not supported:")
        lines += [f"  {line}" for line in other]
    return lines


def env_config_lines(env_name: str) -> list[str]:
    """Help lines of scenario ``env_name``'s ``env_config`` keys, each with what it accepts and
    its default (a built-in scenario); one line for another scenario, whose keys are its
    factory's keyword arguments."""
    from mapets_rl.envs.factory import env_config_help
    from mapets_rl.envs.registry import builtin_envs

    if env_name not in builtin_envs():
        return [f"env_config keys of {env_name}: the keyword arguments of its factory"]
    lines = [f"env_config keys of {env_name} (set as env_config.KEY=VALUE):"]
    for key, words in env_config_help(env_name).items():
        lines += textwrap.wrap(
            f"{key}: {words}",
            WIDTH,
            initial_indent="  ",
            subsequent_indent=" " * 6,
            break_on_hyphens=False,
        )
    return lines


def help_overrides(options: Sequence[str]) -> list[str]:
    """The config overrides among the options after ``train RECIPE``: its ``key=value`` items
    and ``--env SCENARIO`` (as ``env=SCENARIO``); other options are ignored."""
    overrides = []
    for i, item in enumerate(options):
        if item.startswith("--env="):
            overrides.append(f"env={item.partition('=')[2]}")
        elif item == "--env" and i + 1 < len(options):
            overrides.append(f"env={options[i + 1]}")
        elif not item.startswith("-") and "=" in item and options[i - 1 : i] != ["--env"]:
            overrides.append(item)
    return overrides


def render_recipe_help(name: str, overrides: Sequence[str]) -> str:
    """The help text of recipe ``name`` with ``overrides`` applied to its config (imports the
    recipe and builds every scenario); ValueError for an unknown recipe or a bad override."""
    cls = load_recipe(name)
    config_cls = cls.Config
    try:
        config = config_cls()
    except (ValueError, TypeError):  # a config that needs fields set: its defaults only
        config = None
    if config is not None and overrides:
        config = config.with_overrides(list(overrides))
    lines = [
        f"usage: {PROG} train {name} --env SCENARIO [--seed N] [--config FILE] "
        "[--run-dir DIR] [key=value ...]",
        "",
        *_wrapped(summary(config_cls)),
        "",
    ]
    if config is not None:
        lines += [*supported_scenarios(cls, config), "", *env_config_lines(config.env), ""]
    lines += _wrapped(
        f"fields of {config_cls.__name__} (set as key=value, a section's fields as "
        "section.field=value; values parsed as YAML; [unit]):"
    )
    preset = getattr(config, "preset", None)
    if isinstance(preset, str):
        given = any(o.partition("=")[0].strip() == "preset" for o in overrides)
        lines.append(
            f"  (the values of preset {preset!r}, "
            + (
                "given on the command line)"
                if given
                else "the default; preset=NAME shows another's)"
            )
        )
    lines += field_lines(config_cls, config)
    return "\n".join(lines) + "\n"


def _cache_key(name: str, overrides: Sequence[str]) -> str | None:
    """The cache key of recipe ``name``'s help with ``overrides``; ``None`` when the recipe's
    module cannot be located without running it (then the text is not cached)."""
    ours = sorted(
        {
            (ep.group, ep.name, ep.value)
            for dist in metadata.distributions()
            for ep in dist.entry_points
            if ep.group.startswith("mapets_rl.")
        }
    )
    target = next((v for g, n, v in ours if g == RECIPE_GROUP and n == name), None)
    if target is None:
        return None
    module = target.partition(":")[0]
    try:
        spec = util.find_spec(module)
        top = util.find_spec(module.split(".")[0])
    except (ImportError, ValueError):
        return None
    if spec is None or spec.origin is None or top is None:
        return None
    roots = {Path(spec.origin).parent, *map(Path, mapets_rl.__path__)}
    roots |= set(map(Path, top.submodule_search_locations or []))
    files = sorted({p for root in roots for p in root.rglob("*.py")})
    registry = sys.modules.get("mapets_rl.envs.registry")  # scenarios registered in-process
    registered = registry.available_envs() if registry is not None else []
    stats = [(str(p), st.st_mtime_ns, st.st_size) for p in files for st in (p.stat(),)]
    payload = [_FORMAT, sys.version, sys.executable, name, list(overrides), ours, registered]
    text = json.dumps([*payload, stats])
    return hashlib.sha256(text.encode()).hexdigest()


def _cache_dir() -> Path | None:
    """The private cache directory of help texts, ``None`` when it cannot be used."""
    path = private_default(os.environ).parent / "help"
    return path if make_private_dir(path) is None else None


def recipe_help(name: str, options: Sequence[str]) -> str:
    """The help of ``mapets-rl train RECIPE [options] --help``: from the cache when its key
    matches, else made (:func:`render_recipe_help`) and kept."""
    overrides = help_overrides(options)
    key = _cache_key(name, overrides)
    folder = _cache_dir() if key is not None else None
    if folder is not None:
        try:
            return (folder / f"{key}.txt").read_text()
        except OSError:
            pass
    text = render_recipe_help(name, overrides)
    if folder is not None:
        _keep(folder, f"{key}.txt", text)
    return text


def _keep(folder: Path, name: str, text: str) -> None:
    """Write ``folder/name`` atomically and drop all but the newest :data:`CACHE_ENTRIES`
    texts; a cache that cannot be written (a full disk) is skipped."""
    try:
        fh = tempfile.NamedTemporaryFile("w", dir=folder, suffix=".tmp", delete=False)
    except OSError:
        return
    try:
        with fh:
            fh.write(text)
        os.replace(fh.name, folder / name)
        for old in sorted(folder.glob("*.txt"), key=os.path.getmtime)[:-CACHE_ENTRIES]:
            old.unlink(missing_ok=True)
    except OSError:
        Path(fh.name).unlink(missing_ok=True)
