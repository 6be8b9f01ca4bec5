"""Validated configuration dataclasses: YAML in, ``key=value`` overrides, resolved YAML out.

Every recipe's config subclasses :class:`ExperimentConfig`. A subclass adds its own fields (with
type hints and defaults) and validates them in ``__post_init__`` (call ``super().__post_init__()``
first), raising :class:`ConfigError` through :func:`check` so that the message names the field
and the allowed range.

Overrides are strings ``key=value``: the value is parsed as YAML (``lr=3e-4``, ``hidden=[64,64]``,
``video=true``) and coerced to the field's annotated type; dotted keys reach into dict fields
(``env_config.n_cavs=4``). An unknown key or a value of the wrong type raises ConfigError.
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, Literal, Union, get_args, get_origin

import yaml

LOGGERS = ("csv", "tensorboard", "wandb", "none")


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
        check(isinstance(value, (int, float)) and not isinstance(value, bool), field,
              "a number", value)
        return float(value)
    if tp is str:
        check(isinstance(value, str), field, "a string", value)
        return value
    return value


@dataclasses.dataclass
class ExperimentConfig:
    """Fields shared by every recipe; subclasses add algorithm fields.

    Frame counts are environment steps of the whole batch of environments (one frame = one
    environment step, all agents of that step included).

    Attributes:
        env: scenario name passed to ``mapets_rl.envs.make_env``.
        env_config: keyword arguments for ``make_env`` (e.g. ``{"n_cavs": 8}``).
        seed: seed of torch / numpy / python RNGs and of the environments.
        device: torch device of the learner (``"cpu"``, ``"cuda"``, ...).
        total_frames: environment steps to train for (> 0).
        frames_per_batch: environment steps per collected batch (> 0).
        num_envs: environment processes; 1 uses ``Collector`` in this process, > 1 uses
            ``MultiSyncCollector`` with one env per process.
        eval_interval: evaluate every this many frames (0: only at the end).
        eval_episodes: episodes per evaluation (>= 1).
        checkpoint_interval: write a checkpoint every this many frames (0: only at the end).
            Environments are re-seeded and reset at every checkpoint boundary so that a resumed
            run continues exactly like an uninterrupted one (an episode in flight is cut there;
            bit-exact with ``num_envs=1``; worker processes of ``num_envs > 1`` re-seed their
            environments but not their own torch RNG).
        keep_last: checkpoints to keep on disk (>= 1).
        logger: ``csv`` (default), ``tensorboard``, ``wandb`` or ``none``.
        video: record a GIF of the first episode of each evaluation.
        progress: show a tqdm progress bar.
    """

    env: str = "figure-eight"
    env_config: dict[str, Any] = dataclasses.field(default_factory=dict)
    seed: int = 0
    device: str = "cpu"
    total_frames: int = 3000
    frames_per_batch: int = 200
    num_envs: int = 1
    eval_interval: int = 1000
    eval_episodes: int = 1
    checkpoint_interval: int = 1000
    keep_last: int = 2
    logger: str = "csv"
    video: bool = False
    progress: bool = True

    def __post_init__(self) -> None:
        self._coerce_fields()
        check(bool(self.env), "env", "a non-empty scenario name", self.env)
        check(self.seed >= 0, "seed", ">= 0", self.seed)
        check(self.total_frames > 0, "total_frames", "> 0", self.total_frames)
        check(self.frames_per_batch > 0, "frames_per_batch", "> 0", self.frames_per_batch)
        check(self.num_envs >= 1, "num_envs", ">= 1", self.num_envs)
        check(self.frames_per_batch % self.num_envs == 0, "frames_per_batch",
              f"a multiple of num_envs={self.num_envs}", self.frames_per_batch)
        check(self.eval_interval >= 0, "eval_interval", ">= 0", self.eval_interval)
        check(self.eval_episodes >= 1, "eval_episodes", ">= 1", self.eval_episodes)
        check(self.checkpoint_interval >= 0, "checkpoint_interval", ">= 0",
              self.checkpoint_interval)
        check(self.keep_last >= 1, "keep_last", ">= 1", self.keep_last)
        check(self.logger in LOGGERS, "logger", f"one of {list(LOGGERS)}", self.logger)

    def _coerce_fields(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, _coerce(getattr(self, f.name), hints[f.name],
                                                     f.name))

    # ----------------------------------------------------------------------------- conversions
    @classmethod
    def field_names(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls)]

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ExperimentConfig:
        """Build from a mapping; unknown keys raise ConfigError naming them."""
        unknown = sorted(set(data) - set(cls.field_names()))
        if unknown:
            raise ConfigError(f"unknown config key {unknown[0]!r} for {cls.__name__} "
                              f"(known: {', '.join(cls.field_names())})")
        return cls(**dict(data))

    @classmethod
    def from_yaml(cls, path: str | os.PathLike) -> ExperimentConfig:
        data = yaml.safe_load(Path(path).read_text()) or {}
        if not isinstance(data, Mapping):
            raise ConfigError(f"config file {str(path)!r} must hold a mapping of fields")
        return cls.from_dict(data)

    def to_dict(self) -> dict[str, Any]:
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)}

    def to_yaml(self, path: str | os.PathLike) -> None:
        """Write the resolved config atomically (temp file + rename)."""
        atomic_write_text(path, yaml.safe_dump(self.to_dict(), sort_keys=False))

    def with_overrides(self, overrides: Iterable[str]) -> ExperimentConfig:
        """A new config with ``key=value`` strings applied (values parsed as YAML)."""
        data = self.to_dict()
        for item in overrides:
            key, sep, raw = item.partition("=")
            key = key.strip()
            if not sep or not key:
                raise ConfigError(f"override {item!r} must look like key=value")
            try:
                value = yaml.safe_load(raw) if raw.strip() else ""
            except yaml.YAMLError:
                value = raw
            head, _, rest = key.partition(".")
            if head not in data:
                raise ConfigError(f"unknown config key {head!r} for {type(self).__name__} "
                                  f"(known: {', '.join(self.field_names())})")
            if rest:
                if not isinstance(data[head], dict):
                    raise ConfigError(f"config key {head!r} is not a mapping; cannot set {key!r}")
                target = data[head]
                *parents, leaf = rest.split(".")
                for p in parents:
                    target = target.setdefault(p, {})
                target[leaf] = value
            else:
                data[head] = value
        return type(self).from_dict(data)


def _plain(value: Any) -> Any:
    """YAML/JSON-safe copy: tuples become lists, nested mappings become dicts."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> None:
    """Create ``path`` by ``write(tmp)`` on a temp file in the same directory + ``os.replace``.

    The temp file keeps ``path``'s suffix (so writers that infer a format from it work) and gets
    the permissions of a normally created file (``mkstemp`` makes it private); it is removed if
    ``write`` fails, and ``path`` is then left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.chmod(tmp, 0o666 & ~umask)
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (see :func:`atomic_write`), fsynced."""

    def write(tmp: str) -> None:
        with open(tmp, "w") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())

    atomic_write(path, write)


def atomic_savefig(fig: Any, path: str | os.PathLike, **savefig_kwargs: Any) -> None:
    """Save the matplotlib figure ``fig`` to ``path`` atomically (see :func:`atomic_write`)."""
    atomic_write(path, lambda tmp: fig.savefig(tmp, **savefig_kwargs))
