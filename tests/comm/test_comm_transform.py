"""CommunicationRange transform: known adjacencies, link failures, masks, specs."""

import math

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, TransformedEnv
from torchrl.envs.utils import check_env_specs

from mapets_rl.comm import CommunicationRange, communication_graph


def _positions_td(position: torch.Tensor, mask: torch.Tensor | None = None) -> TensorDict:
    agents = {"position": position}
    if mask is not None:
        agents["mask"] = mask
    return TensorDict({"agents": TensorDict(agents, position.shape[:-1])}, position.shape[:-2])


# Four hand-placed CAVs. Distances: 0-1 = 50 (exactly), 0-2 = 100, 1-2 = 80.6, 1-3 = 162.8,
# 0-3 = 200, 2-3 = 223.6.
HAND = torch.tensor([[0.0, 0.0], [30.0, 40.0], [100.0, 0.0], [0.0, 200.0]])


def _adj(n: int, edges: list[tuple[int, int]]) -> torch.Tensor:
    a = torch.zeros(n, n, dtype=torch.bool)
    for i, j in edges:
        a[i, j] = a[j, i] = True
    return a


@pytest.mark.parametrize(
    "d, edges",
    [
        (49.9, []),
        (50.0, [(0, 1)]),
        (100.0, [(0, 1), (0, 2), (1, 2)]),
        (199.0, [(0, 1), (0, 2), (1, 2), (1, 3)]),
        (200.0, [(0, 1), (0, 2), (1, 2), (1, 3), (0, 3)]),
        (math.inf, [(0, 1), (0, 2), (1, 2), (1, 3), (0, 3), (2, 3)]),
    ],
)
def test_hand_placed_positions_give_known_adjacency(d, edges):
    td = CommunicationRange(d)(_positions_td(HAND.clone()))
    assert torch.equal(td["agents", "neighbors"], _adj(4, edges))


def test_zero_range_gives_no_links_even_for_colocated_agents():
    position = torch.zeros(3, 5, 2)
    out = CommunicationRange(0.0)(_positions_td(position))["agents", "neighbors"]
    assert out.shape == (3, 5, 5) and out.dtype == torch.bool and not out.any()


def test_infinite_range_gives_complete_graph():
    position = torch.randn(2, 6, 2) * 1e6
    out = CommunicationRange(math.inf)(_positions_td(position))["agents", "neighbors"]
    assert torch.equal(out, ~torch.eye(6, dtype=torch.bool).expand(2, 6, 6))


def test_masked_agents_have_no_links():
    mask = torch.tensor([True, False, True, True])
    out = CommunicationRange(math.inf)(_positions_td(HAND.clone(), mask))["agents", "neighbors"]
    expected = _adj(4, [(0, 2), (0, 3), (2, 3)])
    assert torch.equal(out, expected)


def test_p_fail_one_gives_no_links():
    out = communication_graph(torch.zeros(10, 6, 2), math.inf, p_fail=1.0)
    assert not out.any()


def test_p_fail_half_fails_about_half_symmetrically_and_reproducibly():
    n_draws, n_agents = 2000, 6
    position = torch.zeros(n_draws, n_agents, 2)
    t = CommunicationRange(math.inf, p_fail=0.5, seed=3)
    out = t(_positions_td(position))["agents", "neighbors"]
    assert torch.equal(out, out.transpose(-1, -2))
    assert not out.diagonal(dim1=-2, dim2=-1).any()
    pairs = out.triu(1).sum().item()
    n_pairs = n_draws * n_agents * (n_agents - 1) // 2
    frac = pairs / n_pairs
    # 30000 Bernoulli(0.5) pairs: std 0.003; 0.02 is > 6 sigma.
    assert abs(frac - 0.5) < 0.02
    again = CommunicationRange(math.inf, p_fail=0.5, seed=3)(_positions_td(position))
    assert torch.equal(again["agents", "neighbors"], out)
    other = CommunicationRange(math.inf, p_fail=0.5, seed=4)(_positions_td(position))
    assert not torch.equal(other["agents", "neighbors"], out)


@pytest.mark.parametrize("bad", [-1.0, -1e-9, float("nan")])
def test_negative_range_raises(bad):
    with pytest.raises(ValueError, match="comm_range"):
        CommunicationRange(bad)


@pytest.mark.parametrize("bad", [-0.1, 1.5, float("nan")])
def test_p_fail_outside_unit_interval_raises(bad):
    with pytest.raises(ValueError, match="p_fail"):
        CommunicationRange(10.0, p_fail=bad)


@pytest.mark.parametrize("shape", [(4, 3), (2, 4, 1), (4,)])
def test_wrong_position_shape_raises(shape):
    t = CommunicationRange(10.0)
    td = TensorDict({("agents", "position"): torch.zeros(shape)}, [])
    with pytest.raises(ValueError, match="position"):
        t(td)


class TinyPositionsEnv(EnvBase):
    """Agents move in the plane by their action; emits ("agents", "position"/"mask")."""

    def __init__(self, n_agents: int = 4, batch_size: tuple[int, ...] = ()):
        super().__init__(batch_size=torch.Size(batch_size))
        bs = tuple(batch_size)
        n = n_agents
        self.n_agents = n
        self.observation_spec = Composite(
            agents=Composite(
                position=Unbounded(shape=(*bs, n, 2)),
                mask=Categorical(2, shape=(*bs, n), dtype=torch.bool),
                shape=(*bs, n),
            ),
            shape=bs,
        )
        self.action_spec = Composite(
            agents=Composite(action=Bounded(-1.0, 1.0, shape=(*bs, n, 2)), shape=(*bs, n)),
            shape=bs,
        )
        self.reward_spec = Composite(
            agents=Composite(reward=Unbounded(shape=(*bs, n, 1)), shape=(*bs, n)), shape=bs
        )
        self.done_spec = Composite(
            done=Categorical(2, shape=(*bs, 1), dtype=torch.bool),
            terminated=Categorical(2, shape=(*bs, 1), dtype=torch.bool),
            shape=bs,
        )
        self.rng = torch.Generator().manual_seed(0)

    def _reset(self, tensordict: TensorDictBase | None) -> TensorDictBase:
        bs, n = self.batch_size, self.n_agents
        position = torch.rand((*bs, n, 2), generator=self.rng) * 100.0
        mask = torch.rand((*bs, n), generator=self.rng) > 0.2
        out = TensorDict(
            {
                "agents": TensorDict({"position": position, "mask": mask}, (*bs, n)),
                "done": torch.zeros((*bs, 1), dtype=torch.bool),
                "terminated": torch.zeros((*bs, 1), dtype=torch.bool),
            },
            bs,
        )
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        bs, n = self.batch_size, self.n_agents
        position = tensordict["agents", "position"] + 10.0 * tensordict["agents", "action"]
        return TensorDict(
            {
                "agents": TensorDict(
                    {
                        "position": position,
                        "mask": tensordict["agents", "mask"].clone(),
                        "reward": torch.zeros((*bs, n, 1)),
                    },
                    (*bs, n),
                ),
                "done": torch.zeros((*bs, 1), dtype=torch.bool),
                "terminated": torch.zeros((*bs, 1), dtype=torch.bool),
            },
            bs,
        )

    def _set_seed(self, seed: int | None) -> None:
        self.rng.manual_seed(0 if seed is None else seed)


@pytest.mark.parametrize("batch_size", [(), (3,)])
def test_transform_specs_pass_check_env_specs(batch_size):
    env = TransformedEnv(
        TinyPositionsEnv(4, batch_size), CommunicationRange(60.0, p_fail=0.25, seed=0)
    )
    check_env_specs(env, seed=0)
    spec = env.observation_spec["agents", "neighbors"]
    assert spec.shape == (*batch_size, 4, 4) and spec.dtype == torch.bool


def test_rollout_neighbors_match_positions_and_mask():
    env = TransformedEnv(TinyPositionsEnv(5), CommunicationRange(60.0))
    td = env.rollout(6)
    for root in (td, td["next"]):
        adjacency = root["agents", "neighbors"]
        assert adjacency.shape == (6, 5, 5)
        expected = communication_graph(
            root["agents", "position"], 60.0, mask=root["agents", "mask"]
        )
        assert torch.equal(adjacency, expected)
        assert torch.equal(adjacency, adjacency.transpose(-1, -2))


def test_spec_with_wrong_position_shape_raises():
    class Bad3D(TinyPositionsEnv):
        def __init__(self):
            super().__init__(3)
            self.observation_spec["agents", "position"] = Unbounded(shape=(3, 3))

    with pytest.raises(ValueError, match="position"):
        _ = TransformedEnv(Bad3D(), CommunicationRange(10.0)).observation_spec


def test_episode_graph_crashed_agents_share_from_their_crash_site():
    env = TransformedEnv(TinyPositionsEnv(4), CommunicationRange(math.inf))
    rollout = env.rollout(3)
    position = torch.tensor(
        [
            [[0.0, 0.0], [500.0, 0.0], [10.0, 0.0], [900.0, 900.0]],  # step 0
            [[0.0, 0.0], [20.0, 0.0], [10.0, 0.0], [0.0, 0.0]],  # 1 crashed here at (20, 0)
            [[0.0, 0.0], [0.0, 0.0], [10.0, 0.0], [0.0, 0.0]],  # removed agents reported at 0
        ]
    )
    rollout["next", "agents", "position"] = position
    mask = torch.tensor(
        [[True, True, True, False], [True, True, True, False], [True, False, True, False]]
    )  # 3 never drove; 1 drove until step 1 (its crash step)
    rollout["agents", "mask"] = mask
    rollout["next", "agents", "mask"][-1] = False  # PettingZoo-style end: everybody removed
    graph = CommunicationRange(15.0).episode_graph(rollout)
    # 1 shares from its crash site (20, 0): within 15 m of 2 at (10, 0), not of 0 at (0, 0)
    assert torch.equal(graph, _adj(4, [(0, 2), (1, 2)]))
    assert torch.equal(
        CommunicationRange(math.inf).episode_graph(rollout), _adj(4, [(0, 1), (0, 2), (1, 2)])
    )
    assert not CommunicationRange(0.0).episode_graph(rollout).any()


def test_transform_on_figure_eight_env():
    envs = pytest.importorskip("mapets_rl.envs")
    env = envs.make_env("figure-eight", seed=0, horizon=5)
    env = env.append_transform(CommunicationRange(100.0, p_fail=0.25, seed=0))
    check_env_specs(env, seed=0)
    rollout = env.rollout(5, envs.ScriptedCAVPolicy(env), break_when_any_done=True)
    adjacency = rollout["agents", "neighbors"]
    assert adjacency.shape == (5, 8, 8)
    assert torch.equal(adjacency, adjacency.transpose(-1, -2))
    assert adjacency.any()  # 8 CAVs on a ~480 m loop: some within 100 m
    assert CommunicationRange(math.inf).episode_graph(rollout).sum() == 8 * 7
