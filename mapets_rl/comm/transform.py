"""Communication graph of CAVs within a range ``d`` as a TorchRL transform (MA-PETS sec. III-B)."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Binary, Composite, TensorSpec
from torchrl.envs.transforms import Transform

from mapets_rl.modules.arguments import is_real_number, seed_value
from mapets_rl.modules.tensor_checks import as_mask, check_real, get_tensor

__all__ = ["CommunicationRange", "communication_graph"]


def _as_tuple(key: NestedKey) -> tuple[str, ...]:
    return (key,) if isinstance(key, str) else tuple(key)


def _check_comm_range(comm_range: float) -> float:
    if not is_real_number(comm_range) or math.isnan(comm_range) or comm_range < 0:
        raise ValueError(f"comm_range must be a number in [0, inf], got {comm_range!r}")
    return float(comm_range)


def _check_p_fail(p_fail: float) -> float:
    if not is_real_number(p_fail) or not 0.0 <= p_fail <= 1.0:
        raise ValueError(f"p_fail must be a number in [0, 1], got {p_fail!r}")
    return float(p_fail)


def communication_graph(
    position: torch.Tensor,
    comm_range: float,
    p_fail: float = 0.0,
    mask: torch.Tensor | None = None,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Adjacency of the agents within Euclidean distance ``<= comm_range`` of each other.

    The set ``F_d(i)`` of the paper (sec. III-B): ``j in F_d(i)`` iff ``dis(i, j) <= d``.

    Args:
        position: ``[*B, I, 2]`` agent positions (metres), float or int (cast to float);
            finite for every agent that ``mask`` keeps.
        comm_range: ``d`` in ``[0, inf]``. ``0`` gives no links (even for co-located agents:
            ``d = 0`` means no sharing in the paper), ``inf`` the complete graph.
        p_fail: probability that a link fails, independently per unordered pair.
        mask: optional ``[*B, I]`` bool (or 0/1); agents with ``False`` (crashed/removed) get no
            links, whatever their position.
        generator: random generator (CPU) for link failures.

    Returns:
        ``[*B, I, I]`` bool, symmetric, ``False`` on the diagonal.
    """
    comm_range = _check_comm_range(comm_range)
    p_fail = _check_p_fail(p_fail)
    check_real("position", position, "[*B, I, 2]")
    if position.ndim < 2 or position.shape[-1] != 2:
        raise ValueError(f"position must have shape [*B, I, 2], got {tuple(position.shape)}")
    if not position.is_floating_point():  # e.g. int64 metres
        position = position.to(torch.get_default_dtype())
    n_agents = position.shape[-2]
    if mask is not None:
        if mask.shape == position.shape[:-1] + (1,):
            mask = mask.squeeze(-1)
        if mask.shape != position.shape[:-1]:
            raise ValueError(
                f"mask must have shape {tuple(position.shape[:-1])}, got {tuple(mask.shape)}"
            )
        mask = as_mask("mask", mask, f"{tuple(position.shape[:-1])}")
    finite = torch.isfinite(position).all(-1)  # [*B, I]; masked agents may be anywhere
    if not bool((finite if mask is None else finite | ~mask).all()):
        bad = ~finite if mask is None else ~finite & mask
        agents = torch.nonzero(bad.reshape(-1, n_agents).any(0)).flatten().tolist()
        raise ValueError(
            f"position must be finite for every unmasked agent, got NaN or inf for agent(s) "
            f"{agents} (mask them out or clean the positions)"
        )
    if comm_range == 0.0 or p_fail == 1.0:
        return torch.zeros(
            (*position.shape[:-2], n_agents, n_agents), dtype=torch.bool, device=position.device
        )
    eye = torch.eye(n_agents, dtype=torch.bool, device=position.device)
    diff = position.unsqueeze(-2) - position.unsqueeze(-3)  # [*B, I, I, 2]
    dist = torch.linalg.vector_norm(diff, dim=-1)  # [*B, I, I], exactly symmetric
    adjacency = (dist <= comm_range) & ~eye
    if mask is not None:
        adjacency = adjacency & mask.unsqueeze(-1) & mask.unsqueeze(-2)
    if p_fail > 0.0:
        # One uniform draw per unordered pair (upper triangle), mirrored: symmetric failures.
        u = torch.rand(adjacency.shape, generator=generator, dtype=torch.float64)
        u = torch.triu(u, diagonal=1)
        u = u + u.transpose(-1, -2)
        adjacency = adjacency & (u >= p_fail).to(adjacency.device)
    return adjacency


class CommunicationRange(Transform):
    """Writes the communication graph of the agents within range ``d`` (MA-PETS sec. III-B).

    Reads ``position_key`` (``[*B, I, 2]``) and, when present, ``mask_key`` (``[*B, I]``, agents
    with ``False`` get no links), and writes ``neighbors_key``: a symmetric ``[*B, I, I]`` bool
    adjacency without self-loops, ``True`` where the two CAVs are within Euclidean distance
    ``<= comm_range`` and their link did not fail. Each unordered link fails independently with
    probability ``p_fail``, drawn from the transform's own generator (reproducible under
    ``seed``). Applied at reset and after every step; the paper exchanges data with the graph
    at the last step of each episode.

    Args:
        comm_range: ``d`` in metres, in ``[0, inf]``. ``0`` gives no links, ``inf`` the complete
            graph (of the unmasked agents).
        p_fail: link failure probability in ``[0, 1]``.
        seed: seed of the link-failure generator (an int >= 0, or ``None``).
        position_key, mask_key, neighbors_key: keys read/written.

    The exchange graph of an episode is :meth:`episode_graph` of its rollout: every agent
    takes part from its last driving position (crashed CAVs from their crash site). It differs
    from ``rollout[..., -1]["next", neighbors_key]``, which links only the agents still driving.

    Example:
        >>> env = TransformedEnv(make_env("figure-eight"), CommunicationRange(100.0))
        >>> td = env.rollout(10)
        >>> td["next", "agents", "neighbors"].shape  # [10, I, I]
    """

    def __init__(
        self,
        comm_range: float,
        p_fail: float = 0.0,
        seed: int | None = None,
        *,
        position_key: NestedKey = ("agents", "position"),
        mask_key: NestedKey | None = ("agents", "mask"),
        neighbors_key: NestedKey = ("agents", "neighbors"),
    ) -> None:
        comm_range = _check_comm_range(comm_range)
        p_fail = _check_p_fail(p_fail)
        super().__init__(in_keys=[position_key], out_keys=[neighbors_key])
        self.comm_range = comm_range
        self.p_fail = p_fail
        self.position_key = position_key
        self.mask_key = mask_key
        self.neighbors_key = neighbors_key
        self.generator = torch.Generator()
        self.set_seed(seed)

    def set_seed(self, seed: int | None) -> None:
        """Reseeds the link-failure generator (``None``: a non-deterministic seed)."""
        seed = seed_value("seed", seed)
        if seed is None:
            self.generator.seed()
        else:
            self.generator.manual_seed(seed)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        position = next_tensordict.get(self.position_key, default=None)
        if position is None:
            if self.missing_tolerance:
                return next_tensordict
            raise KeyError(f"{self}: {self.position_key!r} not found in tensordict")
        mask = None
        if self.mask_key is not None:
            mask = next_tensordict.get(self.mask_key, default=None)
        adjacency = communication_graph(
            position, self.comm_range, self.p_fail, mask=mask, generator=self.generator
        )
        next_tensordict.set(self.neighbors_key, adjacency)
        return next_tensordict

    def episode_graph(self, rollout: TensorDictBase) -> torch.Tensor:
        """Communication graph at the end of an episode, when the paper exchanges data.

        Every agent that drove in the episode takes part, from the last position where it was
        driving: a CAV that crashed still holds its transitions and stays at its crash site. The
        position of agent ``i`` is ``("next", position_key)`` of the last step at which it was
        active (``mask_key`` True; every step when the rollout has no mask), so the graph does
        not depend on what an env reports for removed agents.

        Args:
            rollout: an episode, TensorDict ``[*B, T]`` (time last, e.g. ``env.rollout``).

        Returns:
            ``[*B, I, I]`` bool adjacency (link failures drawn from this transform's generator).
        """
        if rollout.batch_dims < 1:
            raise ValueError("rollout must have a time dimension (batch size [*B, T])")
        positions = get_tensor(  # [*B, T, I, 2]
            rollout,
            ("next", *_as_tuple(self.position_key)),
            "[*B, T, I, 2]",
            f"{type(self).__name__}.episode_graph",
        )
        if positions.ndim < 3:
            raise ValueError(
                f"{('next', *_as_tuple(self.position_key))!r} must have shape [*B, T, I, 2], "
                f"got {tuple(positions.shape)}"
            )
        steps = positions.shape[-3]
        active = None
        if self.mask_key is not None:
            active = rollout.get(self.mask_key, default=None)
        if active is None:
            active = torch.ones(positions.shape[:-1], dtype=torch.bool, device=positions.device)
        if active.shape == positions.shape[:-1] + (1,):
            active = active.squeeze(-1)
        active = as_mask(repr(self.mask_key), active, f"{tuple(positions.shape[:-1])}")
        time = torch.arange(steps, device=positions.device).view(steps, 1)
        last = torch.where(active, time, -1).amax(dim=-2)  # [*B, I]
        index = last.clamp_min(0)[..., None, :, None].expand(*last.shape[:-1], 1, -1, 2)
        position = positions.gather(-3, index).squeeze(-3)  # [*B, I, 2]
        return communication_graph(
            position, self.comm_range, self.p_fail, mask=last >= 0, generator=self.generator
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Writes the neighbours of ``tensordict`` (offline use, e.g. on a stored rollout)."""
        return self._call(tensordict)

    def _reset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        if not isinstance(observation_spec, Composite):
            raise ValueError(f"{type(self).__name__} needs a Composite observation spec")
        position_spec = observation_spec[self.position_key]
        shape = position_spec.shape
        if len(shape) < 2 or shape[-1] != 2:
            raise ValueError(
                f"position spec {self.position_key!r} must have shape [*B, I, 2], "
                f"got {tuple(shape)}"
            )
        n_agents = shape[-2]
        observation_spec[self.neighbors_key] = Binary(
            n=n_agents,
            shape=(*shape[:-1], n_agents),
            device=position_spec.device,
            dtype=torch.bool,
        )
        return observation_spec

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(comm_range={self.comm_range}, p_fail={self.p_fail}, "
            f"position_key={self.position_key}, neighbors_key={self.neighbors_key})"
        )
