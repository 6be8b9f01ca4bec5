"""The ground floor of configuration: validated config sections, ``key=value`` overrides and
the YAML reader. It imports nothing of the project, so every layer (``comm``, ``models``,
``planning``, ``modules``, the experiment runner) declares its config here.

A config section is a frozen dataclass deriving from :class:`ConfigSection`: its fields are
coerced to their annotated types, refused when NaN or infinite (infinite ones allowed where the
field says ``metadata={"allow_inf": True}``, e.g.
``comm_range: float = dataclasses.field(default=100.0, metadata={"allow_inf": True})``) and
validated by the subclass's ``__post_init__`` (call ``super().__post_init__()`` first), which
raises :class:`ConfigError` through :func:`check` so that the message names the field and the
allowed range. A keyword that is not a field is a ConfigError too. A section nested in another
config is written to YAML as a mapping and read back from one (an unknown key inside it is a
ConfigError naming the dotted key, ``planner.bogus``); its errors name the dotted field
(``planner.horizon must be >= 1, got 0``).

Overrides are strings ``key=value`` (:func:`parse_override`): the value is parsed as YAML
(``lr=3e-4``, ``hidden=[64,64]``, ``video=true``). Config files are read by
:func:`read_yaml_mapping` (bounded size, duplicate keys and aliases refused).

The run configs built on this (``RunConfig``, ``ExperimentConfig``: the fields every recipe
shares, checked against this machine's devices and the registered scenarios) live in the
experiment layer above.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import stat
import types
import typing
import warnings
from collections.abc import Hashable, Iterable, Mapping
from typing import Any, ClassVar, Literal, Union, get_args, get_origin

import yaml

MAX_SEED = 2**62 - 1
"""The largest ``seed``: the seeds derived from it (offsets per evaluation and checkpoint
boundary) must stay signed 64-bit integers."""


class ConfigError(ValueError):
    """A configuration field has an unknown name or a value outside its allowed set."""


def check(condition: bool, field: str, allowed: str, value: Any) -> None:
    """Raise ConfigError ``"<field> must be <allowed>, got <value>"`` unless ``condition``."""
    if not condition:
        raise ConfigError(f"{field} must be {allowed}, got {value!r}")


def _coerce(value: Any, tp: Any, field: str) -> Any:
    """Coerce a YAML-parsed ``value`` to the annotated type ``tp`` or raise ConfigError."""
    origin = get_origin(tp)
    if tp is Any:
        return value
    if isinstance(tp, type) and issubclass(tp, ConfigSection):
        return coerce_section(value, tp, field)
    if origin in (Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, field)
            except ConfigError as err:
                errors.append(str(err))
        raise ConfigError(errors[0] if errors else f"{field} must not be None")
    if origin is Literal:
        choices = get_args(tp)
        check(value in choices, field, f"one of {list(choices)}", value)
        return value
    if origin in (list, tuple) or tp in (list, tuple):
        check(isinstance(value, (list, tuple)), field, "a list", value)
        args = get_args(tp)
        if origin is tuple and args and args[-1] is not Ellipsis:
            check(len(value) == len(args), field, f"a list of {len(args)} items", value)
            items = [_coerce(v, a, field) for v, a in zip(value, args, strict=True)]
        else:
            items = [_coerce(v, args[0], field) for v in value] if args else list(value)
        return tuple(items) if (origin or tp) is tuple else items
    if origin is dict or tp is dict:
        check(isinstance(value, Mapping), field, "a mapping", value)
        return dict(value)
    if tp is bool:
        check(isinstance(value, bool), field, "true or false", value)
        return value
    if tp in (int, float) and isinstance(value, str):
        try:  # YAML 1.1 reads "3e-4" as a string
            value = float(value) if tp is float else int(value)
        except ValueError:
            pass
    if tp is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
        if isinstance(value, float) and value.is_integer():
            value, ok = int(value), True
        check(ok, field, "an integer", value)
        return value
    if tp is float:
        check(
            isinstance(value, (int, float)) and not isinstance(value, bool),
            field,
            "a number",
            value,
        )
        return float(value)
    if tp is str:
        check(isinstance(value, str), field, "a string", value)
        return value
    return value


def coerce_section(value: Any, tp: type[ConfigSection], field: str) -> ConfigSection:
    """A :class:`ConfigSection` from an instance of it or a mapping of its fields; errors name
    the dotted key (``planner.horizon``)."""
    if isinstance(value, tp):
        return value
    check(isinstance(value, Mapping), field, f"a mapping of {tp.__name__} fields", value)
    known = tp.field_names()
    unknown = sorted(set(value) - set(known))
    if unknown:
        raise ConfigError(
            f"unknown config key '{field}.{unknown[0]}' ({field} knows: {', '.join(known)})"
        )
    try:
        return tp(**dict(value))
    except ConfigError as err:
        raise ConfigError(f"{field}.{err}") from None


def coerce_fields(config: Any) -> None:
    """Coerce every field of the dataclass instance ``config`` to its annotated type."""
    hints = typing.get_type_hints(type(config))
    for f in dataclasses.fields(config):
        value = _coerce(getattr(config, f.name), hints[f.name], f.name)
        object.__setattr__(config, f.name, value)


def check_finite(config: Any, prefix: str = "") -> None:
    """Refuse NaN and infinite floats in the fields of ``config`` (infinite ones where the field
    says ``metadata={"allow_inf": True}``), recursing into nested config sections."""
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if isinstance(value, ConfigSection):
            check_finite(value, f"{prefix}{f.name}.")
            continue
        allow_inf = f.metadata.get("allow_inf", False)
        bad = [x for x in _floats(value) if math.isnan(x) or (math.isinf(x) and not allow_inf)]
        allowed = "a number (inf allowed), not NaN" if allow_inf else "a finite number"
        check(not bad, f"{prefix}{f.name}", allowed, value)


def unknown_key_error(cls: type, key: str) -> ConfigError:
    """The ConfigError for a key ``key`` that is not a field of the dataclass ``cls``."""
    names = [f.name for f in dataclasses.fields(cls)]
    return ConfigError(f"unknown config key {key!r} for {cls.__name__} (known: {', '.join(names)})")


class _ConfigFieldsMeta(type):
    """Renames a config class's deprecated keywords (:attr:`ConfigFields.deprecated_names`)
    before the dataclass ``__init__`` sees them."""

    def __call__(cls, *args: Any, **kwargs: Any) -> Any:
        return super().__call__(*args, **cls.current_names(kwargs))


class ConfigFields(metaclass=_ConfigFieldsMeta):
    """What every config dataclass shares: a keyword that is not a field is a ConfigError
    naming it (the dataclass ``__init__`` would raise a TypeError), in the constructor and in
    :meth:`from_dict`; a deprecated name of a field (:attr:`deprecated_names`) is read under
    the field's name, with a DeprecationWarning."""

    # old name -> the field that took its place; the old name still works as a keyword, in
    # from_dict (config files) and as a key=value override, with a DeprecationWarning
    deprecated_names: ClassVar[Mapping[str, str]] = {}

    @classmethod
    def current_names(cls, data: Mapping[str, Any]) -> dict[str, Any]:
        """``data`` with each deprecated key renamed to its field (a DeprecationWarning naming
        both); a ConfigError when both names are given."""
        out = dict(data)
        for old, new in cls.deprecated_names.items():
            if old not in out:
                continue
            if new in out:
                raise ConfigError(f"{old!r} is the deprecated name of {new!r}: give {new!r} only")
            warnings.warn(
                f"config key {old!r} of {cls.__name__} is deprecated: it is now {new!r}",
                DeprecationWarning,
                stacklevel=3,
            )
            out[new] = out.pop(old)
        return out

    def __new__(cls, *args: Any, **kwargs: Any) -> Any:
        unknown = sorted(set(kwargs) - set(cls.field_names()))
        if unknown:
            raise unknown_key_error(cls, unknown[0])
        return super().__new__(cls)

    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls)]

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Any:
        """Build from a mapping of fields (deprecated names read under their field's);
        unknown keys raise ConfigError naming them."""
        data = cls.current_names(data)
        unknown = sorted(set(data) - set(cls.field_names()))
        if unknown:
            raise unknown_key_error(cls, unknown[0])
        return cls(**dict(data))


@dataclasses.dataclass(frozen=True)
class ConfigSection(ConfigFields):
    """Base of a nested config section: a frozen dataclass whose fields are coerced to their
    annotated types, checked for NaN / inf (see ``allow_inf``) and validated by the subclass's
    ``__post_init__`` (call ``super().__post_init__()`` first, raise through :func:`check`).
    A keyword that is not a field is a ConfigError naming it."""

    def __post_init__(self) -> None:
        coerce_fields(self)
        check_finite(self)

    def to_dict(self) -> dict[str, Any]:
        return {f.name: to_plain(getattr(self, f.name)) for f in dataclasses.fields(self)}

    def replace(self, **changes: Any) -> ConfigSection:
        """A copy with ``changes`` applied (validated again)."""
        return dataclasses.replace(self, **changes)


MAX_CONFIG_BYTES = 1 << 20
"""The largest config file read (1 MiB: a config is a few hundred bytes; this bounds a read of
a wrong file)."""
MAX_CONFIG_DEPTH = 32
"""The deepest nesting of mappings and lists a config (file, override value or dotted key)
may have: a config nests two or three levels; this bounds the recursion of reading it."""


class ConfigTooDeep(yaml.composer.ComposerError):
    """A YAML document nests deeper than :data:`MAX_CONFIG_DEPTH`."""


class _ConfigLoader(yaml.SafeLoader):
    """PyYAML's safe loader, minus what a config file never needs and an attacker can abuse:
    a key given twice is refused (the safe loader keeps the last silently), and so are aliases
    (``*name``), whose nested expansion ("billion laughs") can take unbounded memory."""

    _depth = 0

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node | None:
        if self.check_event(yaml.AliasEvent):
            mark = self.peek_event().start_mark
            raise yaml.composer.ComposerError(
                None, None, "aliases (*name) are not accepted in a config", mark
            )
        if self._depth >= MAX_CONFIG_DEPTH:
            mark = self.peek_event().start_mark
            raise ConfigTooDeep(
                None, None, f"nested deeper than {MAX_CONFIG_DEPTH} levels (not a config)", mark
            )
        self._depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if isinstance(key, Hashable):
                if key in seen:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"key {key!r} given twice", key_node.start_mark
                    )
                seen.add(key)
        return super().construct_mapping(node, deep=deep)


# YAML 1.2 floats: PyYAML (YAML 1.1) reads 1e3, 3e-4 and 1.5e3 as strings (its floats need a
# dot and a signed exponent); ints still resolve first, as the int resolver comes before
_ConfigLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)(?:[eE][-+]?[0-9]+)?$"),
    list("-+0123456789."),
)


def load_yaml(text: str) -> Any:
    """``text`` parsed as YAML by the config loader (safe types only; duplicate keys, aliases
    and nesting deeper than :data:`MAX_CONFIG_DEPTH` refused with a ``yaml.YAMLError``;
    ``1e3`` is a float, as in YAML 1.2)."""
    return yaml.load(text, Loader=_ConfigLoader)  # noqa: S506 - a SafeLoader subclass


def parse_override(item: str) -> tuple[str, Any]:
    """``"key=value"`` -> ``(key, value parsed as YAML)`` (the raw string if it is not YAML)."""
    key, sep, raw = item.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"override {item!r} must look like key=value")
    if key.count(".") >= MAX_CONFIG_DEPTH:
        raise ConfigError(
            f"override key {key[:40]!r}... nests deeper than {MAX_CONFIG_DEPTH} levels"
        )
    try:
        value = load_yaml(raw) if raw.strip() else ""
    except ConfigTooDeep:
        raise ConfigError(
            f"the value of {key} nests deeper than {MAX_CONFIG_DEPTH} levels (not a config value)"
        ) from None
    except yaml.YAMLError:
        value = raw
    return key, value


def read_yaml_mapping(path: str | os.PathLike) -> dict[str, Any]:
    """The mapping a YAML file holds; ConfigError (one line naming the file) when it is not a
    regular file (a FIFO or terminal would block the read), cannot be read, is larger than
    :data:`MAX_CONFIG_BYTES`, is not valid YAML (a key given twice, aliases and nesting deeper
    than :data:`MAX_CONFIG_DEPTH` included) or does not hold a mapping."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
        with os.fdopen(fd, "rb") as fh:
            if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
                raise ConfigError(
                    f"config file {str(path)!r} is not a regular file (a FIFO, device or "
                    "directory): not a config"
                )
            raw = fh.read(MAX_CONFIG_BYTES + 1)
        if len(raw) > MAX_CONFIG_BYTES:
            raise ConfigError(
                f"config file {str(path)!r} is larger than {MAX_CONFIG_BYTES} bytes: not a config"
            )
        text = raw.decode()
    except (OSError, UnicodeDecodeError) as err:
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        raise ConfigError(f"config file {str(path)!r} cannot be read: {reason}") from None
    try:
        data = load_yaml(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(err, "problem", None) or type(err).__name__
        raise ConfigError(
            f"config file {str(path)!r} is not valid YAML: {problem}{where}"
        ) from None
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise ConfigError(
            f"config file {str(path)!r} must hold a mapping of config fields, "
            f"got a {type(data).__name__}"
        )
    return dict(data)


def _floats(value: Any) -> Iterable[float]:
    """The floats of a field value (itself, or the items of a list / tuple / mapping)."""
    if isinstance(value, float):
        yield value
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from _floats(item)
    elif isinstance(value, ConfigSection):
        for f in dataclasses.fields(value):
            yield from _floats(getattr(value, f.name))


def to_plain(value: Any) -> Any:
    """YAML/JSON-safe copy: tuples become lists, nested mappings and config sections dicts."""
    if isinstance(value, ConfigSection):
        return value.to_dict()
    if isinstance(value, Mapping):
        return {str(k): to_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_plain(v) for v in value]
    return value
