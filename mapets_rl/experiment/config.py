"""Validated configuration dataclasses: YAML in, ``key=value`` overrides, resolved YAML out.

Every recipe's config subclasses :class:`RunConfig` (the fields every recipe shares), through
:class:`ExperimentConfig` (plus a frame budget) for the recipes trained batch by batch; the
model-free recipes' configs subclass the shared training blocks of
:mod:`mapets_rl.experiment.training` (``OffPolicyConfig``, ``OnPolicyConfig``), which declare
and validate the fields those recipes share under one set of names. A subclass adds its own
fields (with type hints and defaults) and validates them in ``__post_init__`` (call
``super().__post_init__()`` first), raising :class:`ConfigError` through :func:`check` so that
the message names the field and the allowed range. A keyword that is not
a field is a ConfigError too.

Every float field must be finite (NaN and +-inf are refused) unless its dataclass field says
``metadata={"allow_inf": True}`` (then only NaN is refused), e.g.
``comm_range: float = dataclasses.field(default=100.0, metadata={"allow_inf": True})``.
``device`` must name a device this machine has, ``env`` a registered scenario and ``logger`` a
logger whose package is installed, so that a bad value fails when the config is built, before a
run directory is created.

Overrides are strings ``key=value``: the value is parsed as YAML (``lr=3e-4``, ``hidden=[64,64]``,
``video=true``) and coerced to the field's annotated type; dotted keys reach into dict fields
(``env_config.n_cavs=4``) and into nested config sections (``planner.horizon=25``,
``comm.comm_range=inf``). An unknown key or a value of the wrong type raises ConfigError.

A field may itself be a config section: a frozen dataclass deriving from
:class:`mapets_rl.config.ConfigSection` (the ground floor that ``comm``, ``models`` and
``planning`` declare their sections on, with :class:`ConfigError`, :func:`check`, override
parsing and the YAML reader), which validates its own fields in ``__post_init__``. Such a field is
written to YAML as a nested mapping, read back from one (an unknown key inside it is a
ConfigError naming the dotted key, ``planner.bogus``) and its errors name the dotted field
(``planner.horizon must be >= 1, got 0``). NaN / inf checks reach into it with its own fields'
``allow_inf`` metadata.

Renamed fields: a config class maps the old names of renamed fields to the new ones in
``renamed_fields`` (e.g. ``ShapleyACConfig.renamed_fields["actor_lr"] == ("lr_actor",)``);
a ``config.yaml`` read by ``from_yaml`` or by resuming a run has its old keys renamed, with a
one-line ``UserWarning`` naming each old key, so run directories written before the rename
resume (and are rewritten with the new names).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import warnings
from collections.abc import Iterable, Mapping
from typing import Any, ClassVar

import yaml

from mapets_rl.config import (
    MAX_SEED,
    ConfigError,
    ConfigFields,
    check,
    check_finite,
    coerce_fields,
    parse_override,
    read_yaml_mapping,
    to_plain,
    unknown_key_error,
)
from mapets_rl.experiment.files import atomic_write_text

LOGGERS = ("csv", "tensorboard", "wandb", "mlflow", "none")
LOGGER_PACKAGES = {
    "tensorboard": ("tensorboard",),
    "wandb": ("wandb",),
    "mlflow": ("mlflow", "sqlalchemy", "alembic"),
}
"""Logger kind -> the packages it needs (checked when a config is built): MLflow's SQLite
store, where ``logger=mlflow`` logs without a tracking server, needs SQLAlchemy and Alembic
(``pip install 'mapets-rl[mlflow]'`` installs the three)."""
DEVICE_TYPES = ("cpu", "cuda", "mps")
COLLECTORS = ("auto", "single", "multi_sync", "ray")
MAX_EVAL_ROADS = 65_536
"""The most roads of an in-training protocol evaluation (``eval_roads``)."""


@dataclasses.dataclass
class RunConfig(ConfigFields):
    """Fields shared by every recipe; subclasses add algorithm fields (and, for the recipes
    trained on a frame budget, :class:`ExperimentConfig` adds that budget).

    Attributes:
        env: a registered scenario name (``mapets_rl.envs.make_env`` or ``register_env``).
        env_config: keyword arguments for ``make_env`` (e.g. ``{"n_cavs": 8}``).
        seed: seed of torch / numpy / python RNGs and of the environments.
        device: torch device of the learner (``"cpu"``, ``"cuda"``, ``"cuda:1"``, ``"mps"``),
            one this machine has.
        eval_episodes: episodes per evaluation (>= 1).
        keep_last: checkpoints to keep on disk (>= 1).
        logger: ``csv`` (default), ``tensorboard``, ``wandb``, ``mlflow`` or ``none``;
            tensorboard, wandb and mlflow need their package installed (``mapets-rl[mlflow]``,
            ``mapets-rl[tensorboard]``).
        video: record the first episode of each evaluation: a GIF in ``videos/`` and, with a
            logger, a video of that logger (torchrl's ``log_video``).
        progress: show a tqdm progress bar.
        eval_roads: > 0: every evaluation is the evaluation protocol
            (:mod:`mapets_rl.experiment.protocol`) on this many roads of the scenario's batched
            backend, with the gain over each of ``eval_references`` (metrics
            ``gain_vs_<reference>``, in percent) beside the system return and the behaviour
            metrics; 0 (default): ``eval_episodes`` episodes on one road.
        eval_references: the reference policies of the protocol (names registered for the
            scenario, :mod:`mapets_rl.envs.references`; empty: every one registered).
    """

    env: str = "figure-eight"
    env_config: dict[str, Any] = dataclasses.field(default_factory=dict)
    seed: int = 0
    device: str = "cpu"
    eval_episodes: int = 1
    keep_last: int = 2
    logger: str = "csv"
    video: bool = False
    progress: bool = True
    eval_roads: int = 0
    eval_references: list[str] = dataclasses.field(default_factory=list)

    # keys that config.yaml files written by an older version hold and this class no longer
    # has; resuming such a run ignores them
    retired_fields: ClassVar[tuple[str, ...]] = ()
    # keys that config.yaml files written by an older version hold under an old name: old name
    # -> the new field name(s) that take its value (several when one field was split, e.g.
    # SAC's ``lr`` -> ``lr_actor``, ``lr_critic``, ``lr_alpha``); reading such a file
    # (``from_yaml``, resuming a run) renames them with a one-line warning naming the old key
    renamed_fields: ClassVar[Mapping[str, tuple[str, ...]]] = {}
    # whether the recipe collects from a batched env (``env_config.num_envs``, see
    # ExperimentConfig); a config that steps one road refuses ``num_envs``
    collects_env_batches: ClassVar[bool] = False

    def __post_init__(self) -> None:
        coerce_fields(self)
        check_finite(self)
        check(bool(self.env), "env", "a non-empty scenario name", self.env)
        check_env_name(self.env)
        check_device(self.device)
        check(0 <= self.seed <= MAX_SEED, "seed", f"in [0, {MAX_SEED}] (2**62 - 1)", self.seed)
        check(
            "seed" not in self.env_config,
            "env_config.seed",
            "left out (the run's seed seeds every env it builds: set seed= instead)",
            self.env_config.get("seed"),
        )
        check(self.eval_episodes >= 1, "eval_episodes", ">= 1", self.eval_episodes)
        check(self.keep_last >= 1, "keep_last", ">= 1", self.keep_last)
        check(self.logger in LOGGERS, "logger", f"one of {list(LOGGERS)}", self.logger)
        check_logger_package(self.logger)
        self._check_protocol()
        self._derived_fields: set[str] = set()
        if not self.collects_env_batches:
            check(
                self.env_batch_size is None,
                "env_config.num_envs",
                f"left out for {type(self).__name__}, which steps one road (batched envs feed "
                "the collectors of the frame-budget recipes)",
                self.env_batch_size,
            )

    def _check_protocol(self) -> None:
        """``eval_roads`` and ``eval_references`` against the scenario (the envs are imported
        only when the protocol is asked for)."""
        check(
            0 <= self.eval_roads <= MAX_EVAL_ROADS,
            "eval_roads",
            f"in [0, {MAX_EVAL_ROADS}]",
            self.eval_roads,
        )
        if not self.eval_roads:
            check(
                not self.eval_references,
                "eval_references",
                "empty unless eval_roads > 0 (the references are scored by the protocol)",
                self.eval_references,
            )
            return
        from mapets_rl.envs.factory import has_batched_backend
        from mapets_rl.envs.references import check_reference_names

        check(
            has_batched_backend(self.env),
            "eval_roads",
            f"0 for {self.env!r}, which has no batched backend (mapets-rl evaluate --roads "
            "scores its episodes one road at a time)",
            self.eval_roads,
        )
        try:
            check_reference_names(self.env, self.eval_references)
        except ValueError as err:
            raise ConfigError(f"eval_{err}") from None

    def derive(self, name: str, value: Any) -> None:
        """Set field ``name``, which was left to its default ``None``, to ``value`` derived from
        the other fields; :meth:`with_overrides` derives it again from the new values instead
        of keeping this one."""
        setattr(self, name, value)
        self._derived_fields.add(name)

    # ------------------------------------------------------------------------- batched envs
    @property
    def env_batch_size(self) -> int | None:
        """``env_config["num_envs"]``: the number of roads ``B`` of a batched env (the torch
        freeway, ``env_config.backend="torch"``), None when the env steps one road."""
        return self.env_config.get("num_envs")

    def unbatched_env_config(self) -> dict[str, Any]:
        """``env_config`` without ``num_envs``: one road of the same backend and scenario (the
        env that evaluation, video and the recipe's specs use)."""
        return {k: v for k, v in self.env_config.items() if k != "num_envs"}

    # ----------------------------------------------------------------------------- conversions
    @classmethod
    def rename_old_keys(cls, data: Mapping[str, Any], source: str) -> dict[str, Any]:
        """``data`` with the old keys of :attr:`renamed_fields` renamed to their new names (a
        ``UserWarning`` naming the old key and ``source`` for each); a new key already present
        in ``data`` wins over the old one. Deprecated names (:attr:`deprecated_names`) are
        renamed too, with a DeprecationWarning."""
        out = cls.current_names(data)
        for old, new in cls.renamed_fields.items():
            if old not in out or old in cls.field_names():
                continue
            value = out.pop(old)
            warnings.warn(
                f"{source}: config key {old!r} is now {' / '.join(map(repr, new))}; "
                "read under the new name",
                UserWarning,
                stacklevel=2,
            )
            for name in new:
                out.setdefault(name, value)
        return out

    @classmethod
    def upgrade_dict(cls, data: Mapping[str, Any]) -> dict[str, Any]:
        """The mapping of a ``config.yaml`` written by an older version, in today's layout:
        :attr:`retired_fields` dropped; a subclass may also map an older layout (MA-PETS: flat
        planner/model/comm keys to its nested sections). A config written before the
        evaluation protocol's fields existed evaluated on one road: ``eval_roads`` 0."""
        upgraded = {k: v for k, v in data.items() if k not in cls.retired_fields}
        upgraded.setdefault("eval_roads", 0)
        upgraded.setdefault("eval_references", [])
        return upgraded

    @classmethod
    def from_yaml(cls, path: str | os.PathLike, overrides: Iterable[str] = ()) -> RunConfig:
        """Build from a YAML file of fields (old keys renamed by :meth:`rename_old_keys`, older
        layouts upgraded by :meth:`upgrade_dict`) with ``key=value`` ``overrides`` applied to
        it; the result is validated once, as a whole (a file may leave to an override what
        only the combination makes valid). Every error is a one-line ConfigError."""
        return cls.from_fields(read_yaml_mapping(path), overrides, f"config file {str(path)!r}")

    @classmethod
    def from_fields(
        cls, fields: Mapping[str, Any], overrides: Iterable[str] = (), source: str = "config"
    ) -> RunConfig:
        """Build from a mapping of fields (a config file's, named ``source`` in errors) as
        :meth:`from_yaml` does: old keys renamed, older layouts upgraded, ``key=value``
        ``overrides`` applied, validated once; every error is a one-line ConfigError."""
        data = cls.upgrade_dict(cls.rename_old_keys(dict(fields), source))
        overrides = list(overrides)
        data = cls._apply_overrides(data, overrides)
        try:
            return cls.from_dict(data)
        except ConfigError as err:
            with_overrides = " with the key=value overrides" if overrides else ""
            raise ConfigError(f"{source}{with_overrides}: {err}") from None

    def to_dict(self) -> dict[str, Any]:
        return {f.name: to_plain(getattr(self, f.name)) for f in dataclasses.fields(self)}

    def to_yaml(self, path: str | os.PathLike) -> None:
        """Write the resolved config atomically (temp file + rename)."""
        atomic_write_text(path, yaml.safe_dump(self.to_dict(), sort_keys=False))

    def with_overrides(self, overrides: Iterable[str]) -> RunConfig:
        """A new config with ``key=value`` strings applied (values parsed as YAML); dotted keys
        reach into dict fields and nested config sections (``planner.horizon=25``). A field
        this config derived (:meth:`derive`) is derived again from the new values."""
        data = {k: v for k, v in self.to_dict().items() if k not in self._derived_fields}
        return type(self).from_dict(self._apply_overrides(data, overrides))

    @classmethod
    def _apply_overrides(cls, data: dict[str, Any], overrides: Iterable[str]) -> dict[str, Any]:
        """``data`` (a :meth:`to_dict` mapping, or the fields a config file gives: a field it
        leaves out starts from its default) with ``key=value`` strings applied. Two overrides
        of the same key, or of a key and a key inside it (``planner={horizon: 6}
        planner.horizon=5``), are refused: which one would win is not obvious."""
        given: dict[str, str] = {}
        for item in overrides:
            key, value = parse_override(item)
            head, dot, rest = key.partition(".")
            (head,) = cls.current_names({head: None})  # a deprecated name: its field
            key = f"{head}{dot}{rest}"
            clash = next(
                (
                    k
                    for k in given
                    if k == key or key.startswith(f"{k}.") or k.startswith(f"{key}.")
                ),
                None,
            )
            if clash is not None:
                inner = min(clash, key, key=len)
                raise ConfigError(f"{given[clash]!r} and {item!r} both set {inner}: give it once")
            given[key] = item
            if head not in data and head in cls.field_names():
                data[head] = cls._plain_default(head)
            if head not in data:
                raise unknown_key_error(cls, head)
            if rest and data[head] is None:
                data[head] = {}  # a section a preset fills (MA-PETS' planner, model)
            if rest:
                if not isinstance(data[head], dict):
                    raise ConfigError(f"config key {head!r} is not a mapping; cannot set {key!r}")
                target = data[head]
                *parents, leaf = rest.split(".")
                for i, p in enumerate(parents):
                    target = target.setdefault(p, {})
                    if not isinstance(target, dict):
                        inner = ".".join([head, *parents[: i + 1]])
                        raise ConfigError(
                            f"config key {inner!r} is not a mapping; cannot set {key!r}"
                        )
                target[leaf] = value
            else:
                data[head] = value
        return data

    @classmethod
    def _plain_default(cls, name: str) -> Any:
        """The default of field ``name`` as :meth:`to_dict` writes it (``None`` when it has
        none)."""
        field = next(f for f in dataclasses.fields(cls) if f.name == name)
        if field.default is not dataclasses.MISSING:
            return to_plain(field.default)
        if field.default_factory is not dataclasses.MISSING:
            return to_plain(field.default_factory())
        return None


_FRAMES = {"unit": "frames"}


@dataclasses.dataclass
class ExperimentConfig(RunConfig):
    """The shared fields of :class:`RunConfig` plus a frame budget, for the recipes that
    :meth:`Experiment.train <mapets_rl.experiment.Experiment.train>` drives batch by batch.

    Frame counts are environment steps of the whole batch of environments (one frame = one
    environment step, all agents of that step included).

    Attributes:
        total_frames: environment steps to train for (> 0).
        frames_per_batch: environment steps per collected batch (> 0, a multiple of the
            environment copies: ``collector_workers`` times the roads ``env_config.num_envs``
            of a batched env). Left out (``None``), it is the recipe's
            :attr:`default_frames_per_batch` (200; 40 for ``coma`` and ``shapley_ac``) rounded
            up to a multiple of the copies: the recipe's batch on one road, one step per road
            on 256 roads (256 frames); an explicit value that is not a multiple is refused.
        collector_workers: environment copies, one per collector process (``multi_sync``) or
            Ray collector (``ray``); 1 with ``collector="single"`` and with a batched env. Its
            old name ``num_envs`` still works, with a DeprecationWarning.
        collector: the torchrl collector that gathers the batches: ``"single"``
            (``Collector`` in this process), ``"multi_sync"`` (``MultiSyncCollector``,
            ``collector_workers`` worker processes), ``"ray"`` (torchrl's ``RayCollector``,
            ``collector_workers`` remote collectors on a local Ray instance, or the cluster of
            ``RAY_ADDRESS``; needs ``mapets-rl[ray]``) or ``"auto"`` (default: ``single`` when
            ``collector_workers == 1``, else ``multi_sync``).
        eval_interval: evaluate every this many frames (0: only at the end).
        checkpoint_interval: write a checkpoint every this many frames (0: only at the end).
            Environments are re-seeded and reset at every checkpoint boundary so that a resumed
            run continues exactly like an uninterrupted one (an episode in flight is cut there;
            bit-exact with ``collector_workers=1``; worker processes of
            ``collector_workers > 1`` re-seed their environments but not their own torch RNG).

    A batched env (``env_config={"backend": "torch", "num_envs": B, ...}``: ``B`` roads of the
    torch freeway as one env of ``batch_size=[B]``) is collected by one ``Collector`` in this
    process (``collector_workers`` 1, ``collector`` ``auto`` or ``single``); a frame is then one
    step of one road (all its agents), so a batch of ``frames_per_batch`` frames holds
    ``frames_per_batch / B`` steps of every road (a ``[B, T]`` TensorDict) and
    ``frames_per_batch`` must be a multiple of ``B`` (left out, it is one: see above).
    Evaluation and video run on one road of the same backend (``env_config`` without
    ``num_envs``).
    """

    collects_env_batches: ClassVar[bool] = True
    deprecated_names: ClassVar[Mapping[str, str]] = {"num_envs": "collector_workers"}
    # the recipe's frames per batch on one road, which a frames_per_batch left out rounds up
    default_frames_per_batch: ClassVar[int] = 200

    total_frames: int = dataclasses.field(default=3000, metadata=_FRAMES)
    frames_per_batch: int | None = dataclasses.field(default=None, metadata=_FRAMES)
    collector_workers: int = 1
    collector: str = "auto"
    eval_interval: int = dataclasses.field(default=1000, metadata=_FRAMES)
    checkpoint_interval: int = dataclasses.field(default=1000, metadata=_FRAMES)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.frames_per_batch is None:
            copies = self.env_copies()
            self.derive("frames_per_batch", -(-self.default_frames_per_batch // copies) * copies)
        check(self.total_frames > 0, "total_frames", "> 0", self.total_frames)
        check(self.frames_per_batch > 0, "frames_per_batch", "> 0", self.frames_per_batch)
        check(
            self.total_frames >= self.frames_per_batch,
            "total_frames",
            f">= frames_per_batch={self.frames_per_batch} (one collected batch)",
            self.total_frames,
        )
        check(self.collector_workers >= 1, "collector_workers", ">= 1", self.collector_workers)
        check(
            self.collector in COLLECTORS, "collector", f"one of {list(COLLECTORS)}", self.collector
        )
        check(
            self.collector != "single" or self.collector_workers == 1,
            "collector_workers",
            "1 with collector='single' (several envs: collector='multi_sync' or 'ray')",
            self.collector_workers,
        )
        if self.collector == "ray" and importlib.util.find_spec("ray") is None:
            raise ConfigError(
                "collector='ray' needs the ray package, which is not installed: "
                "pip install 'mapets-rl[ray]' (or use collector='multi_sync')"
            )
        check(
            self.frames_per_batch % self.collector_workers == 0,
            "frames_per_batch",
            f"a multiple of collector_workers={self.collector_workers}",
            self.frames_per_batch,
        )
        check(self.eval_interval >= 0, "eval_interval", ">= 0", self.eval_interval)
        check(
            self.checkpoint_interval >= 0, "checkpoint_interval", ">= 0", self.checkpoint_interval
        )
        self.check_env_batch()

    def check_env_batch(self) -> None:
        """ConfigError unless ``env_config.num_envs`` (when given) is an int >= 1 that divides
        ``frames_per_batch``, collected by the single in-process collector."""
        batch = self.env_batch_size
        if batch is None:
            return
        check(
            isinstance(batch, int) and not isinstance(batch, bool) and batch >= 1,
            "env_config.num_envs",
            "an int >= 1 (the roads of the batched torch env)",
            batch,
        )
        check(
            self.collector_workers == 1 and self.collector in ("auto", "single"),
            "collector_workers",
            f"1 with collector 'auto' or 'single' when env_config.num_envs={batch} batches the "
            f"env (one Collector steps the {batch} roads; got collector={self.collector!r})",
            self.collector_workers,
        )
        check(
            self.frames_per_batch % batch == 0,
            "frames_per_batch",
            f"a multiple of env_config.num_envs={batch} (a batch holds the same number of "
            "steps of every road)",
            self.frames_per_batch,
        )

    def env_copies(self) -> int:
        """The environment copies a batch holds the same number of steps of:
        ``collector_workers`` times the roads of a batched env (1 where either is not a valid
        count yet; the checks name it)."""
        roads = self.env_batch_size
        roads_ok = isinstance(roads, int) and not isinstance(roads, bool) and roads >= 1
        workers_ok = isinstance(self.collector_workers, int) and self.collector_workers >= 1
        return (roads if roads_ok else 1) * (self.collector_workers if workers_ok else 1)

    @classmethod
    def upgrade_dict(cls, data: Mapping[str, Any]) -> dict[str, Any]:
        """A config written before ``collector`` existed gets ``"auto"``: the collector that
        ``num_envs`` (now ``collector_workers``) chose then."""
        data = super().upgrade_dict(data)
        data.setdefault("collector", "auto")
        return data


def check_env_name(env: str) -> None:
    """ConfigError unless ``env`` is a registered scenario (see ``register_env``)."""
    from mapets_rl.envs.registry import available_envs

    known = available_envs()
    check(env in known, "env", f"one of the registered scenarios {known}", env)


def available_devices() -> list[str]:
    """Device names this machine can run on: ``cpu``, ``cuda`` / ``cuda:<i>``, ``mps``."""
    import torch

    devices = ["cpu"]
    if torch.cuda.is_available():
        devices += ["cuda", *(f"cuda:{i}" for i in range(torch.cuda.device_count()))]
    mps = getattr(torch.backends, "mps", None)
    if mps is not None and mps.is_available():
        devices.append("mps")
    return devices


def check_device(device: str) -> None:
    """ConfigError unless ``device`` names a torch device that this machine has."""
    import torch

    available = available_devices()
    allowed = f"one of {available} on this machine"
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        parsed = None
    name = None
    if parsed is not None and parsed.type in DEVICE_TYPES:
        name = parsed.type if parsed.index is None else f"{parsed.type}:{parsed.index}"
    check(name in available, "device", allowed, device)


def check_logger_package(kind: str) -> None:
    """ConfigError when logger ``kind`` needs a package that is not installed (naming every
    missing one)."""
    missing = [p for p in LOGGER_PACKAGES.get(kind, ()) if importlib.util.find_spec(p) is None]
    if len(missing) == 1:
        raise ConfigError(
            f"logger={kind!r} needs the {missing[0]} package, which is not installed; install "
            "it or use logger=csv"
        )
    if missing:
        raise ConfigError(
            f"logger={kind!r} needs the {' and '.join(missing)} packages, which are not "
            f"installed (pip install 'mapets-rl[{kind}]') or use logger=csv"
        )
