"""CoalitionCritic, coalition actors and ShapleyActorCriticLoss."""

import pytest
import torch
from tensordict import TensorDict
from torchrl.objectives import LossModule, SoftUpdate

from mapets_rl.objectives import ShapleyActorCriticLoss
from mapets_rl.shapley import (
    CoalitionCritic,
    CoalitionObservation,
    coalition_masks,
    exact_shapley,
    make_coalition_actor,
)

N, OBS, ACT, B = 4, 3, 4, 16


def _batch(n=N, act=ACT, b=B, seed=0, discrete=True):
    g = torch.Generator().manual_seed(seed)
    if discrete:
        action = torch.nn.functional.one_hot(torch.randint(act, (b, n), generator=g), act)
    else:
        action = torch.rand(b, n, act, generator=g) * 2 - 1
    return TensorDict(
        {
            ("agents", "observation"): torch.randn(b, n, OBS, generator=g),
            ("agents", "action"): action.float(),
            ("agents", "coalition"): torch.rand(b, n, generator=g) > 0.4,
            "next": {
                ("agents", "observation"): torch.randn(b, n, OBS, generator=g),
                ("agents", "reward"): torch.rand(b, n, 1, generator=g),
                ("agents", "terminated"): torch.zeros(b, n, 1, dtype=torch.bool),
            },
        },
        [b],
    )


def _loss(discrete=True, n=N, embed_cells=(), member_heads=False, **kwargs):
    torch.manual_seed(0)
    actor = make_coalition_actor(n, OBS, ACT, discrete=discrete, num_cells=(16,))
    critic = CoalitionCritic(
        n, OBS, ACT, num_cells=(32, 32), embed_cells=embed_cells, member_heads=member_heads
    )
    space = "discrete" if discrete else "continuous"
    return ShapleyActorCriticLoss(actor, critic, action_space=space, **kwargs)


def test_critic_equals_mlp_on_zeroed_inputs():
    torch.manual_seed(1)
    critic = CoalitionCritic(N, OBS, ACT, num_cells=(8, 8))
    obs, act = torch.randn(5, N, OBS), torch.randn(5, N, ACT)
    values = critic.all_coalition_values(obs, act)
    assert values.shape == (5, 2**N)
    assert (values[:, 0] == 0).all()  # v(empty) = 0
    masks = coalition_masks(N)
    # Dense first layer on [s^C, a^C, 1_C] (non-members zeroed), rebuilt from the parameters.
    w = torch.cat([critic.agent_weight.reshape(-1, 8), critic.membership], dim=0)
    for k in (3, 10, 15):
        m = masks[k].float()
        x = torch.cat([(torch.cat([obs, act], -1) * m[:, None]).flatten(1), m.expand(5, N)], -1)
        dense = critic.head(x @ w + critic.bias).squeeze(-1)
        assert torch.allclose(values[:, k], dense, atol=1e-5)
        td = TensorDict(
            {
                ("agents", "observation"): obs,
                ("agents", "action"): act,
                ("agents", "coalition"): masks[k].expand(5, N),
            },
            [5],
        )
        assert torch.allclose(critic(td)["coalition_value"].squeeze(-1), values[:, k])
    with pytest.raises(ValueError, match="masks"):
        critic.coalition_values(obs, act, torch.ones(2, N + 1, dtype=torch.bool))
    with pytest.raises(ValueError, match="coalition"):
        critic(td.set(("agents", "coalition"), torch.ones(5, N + 1, dtype=torch.bool)))


def test_coalition_observation_views():
    module = CoalitionObservation(3)
    obs = torch.arange(1.0, 7.0).view(1, 3, 2)
    view = module.view(obs, torch.tensor([[True, False, True]])).view(1, 3, 3, 3)
    # agent 0 (in C) sees agents 0 and 2; agent 1 (outside C) sees only itself
    assert view[0, 0].tolist() == [[1, 2, 1], [0, 0, 0], [5, 6, 1]]
    assert view[0, 1].tolist() == [[0, 0, 0], [3, 4, 1], [0, 0, 0]]
    assert view[0, 2].tolist() == [[1, 2, 1], [0, 0, 0], [5, 6, 1]]
    # ego-first: row i lists agents i, i+1, ..., i-1
    ego = CoalitionObservation(3, ego_first=True)
    view = ego.view(obs, torch.tensor([[True, False, True]])).view(1, 3, 3, 3)
    assert view[0, 0].tolist() == [[1, 2, 1], [0, 0, 0], [5, 6, 1]]
    assert view[0, 1].tolist() == [[3, 4, 1], [0, 0, 0], [0, 0, 0]]
    assert view[0, 2].tolist() == [[5, 6, 1], [1, 2, 1], [0, 0, 0]]


def test_is_loss_module_with_keys():
    loss = _loss()
    assert isinstance(loss, LossModule)
    out = loss(_batch())
    assert {"loss_actor", "loss_value"} <= set(out.keys())
    assert all(out[k].shape == () for k in out.keys())
    assert ("next", ("agents", "reward")) in loss.in_keys


@pytest.mark.parametrize("member_heads", [False, True])
def test_critic_td_error_falls_on_fixed_batch(member_heads):
    loss = _loss(member_heads=member_heads)
    updater = SoftUpdate(loss, tau=0.05)
    td = _batch(b=64)
    opt = torch.optim.Adam(loss.critic_network_params.values(True, True), lr=3e-3)
    first = loss(td)["td_error"].item()
    for _ in range(150):
        value_loss = loss.loss_value(td)[0]
        opt.zero_grad()
        value_loss.backward()
        opt.step()
        updater.step()
    assert loss(td)["td_error"].item() < 0.2 * first


def test_target_uses_coalition_reward_and_termination():
    loss = _loss(gamma=0.9)
    td = _batch()
    td["next", "agents", "terminated"][:] = True  # every agent ends: y = R(C)
    coalition = td["agents", "coalition"].float()
    expected = (td["next", "agents", "reward"].squeeze(-1) * coalition).sum(-1).mean()
    assert torch.isclose(loss.loss_value(td)[1]["target_value"], expected)
    td["next", "agents", "terminated"] = torch.zeros(B, 1, dtype=torch.bool)  # root-shaped flag
    assert not torch.isclose(loss.loss_value(td)[1]["target_value"], expected)


def _reference_phi(loss, td):
    """phi_i with only agent i's action replaced by pi_i(s^C), by exact Shapley per agent."""
    actor, critic = loss.actor_network, loss.critic_network
    with loss.actor_network_params.to_module(actor, preserve_module_state=False):
        a_pol = actor(td.select(("agents", "observation"), ("agents", "coalition")).clone())[
            "agents", "action"
        ]
    obs, a_batch = td["agents", "observation"], td["agents", "action"]
    phis = []
    with loss.critic_network_params.detach().to_module(critic, preserve_module_state=False):
        for i in range(N):
            joint = a_batch.clone()
            joint[:, i] = a_pol[:, i]
            phis.append(exact_shapley(critic.all_coalition_values(obs, joint), N)[:, i])
    return torch.stack(phis, -1)


@pytest.mark.parametrize("member_heads", [False, True])
def test_actor_gradient_flows_only_through_own_action(member_heads):
    loss = _loss(discrete=False, member_heads=member_heads)
    td = _batch(discrete=False)
    params = [p for _, p in loss.actor_network_params.items(True, True) if p.requires_grad]
    phi = loss.shapley_values(td)
    ref = _reference_phi(loss, td)
    assert torch.allclose(phi, ref, atol=1e-5)
    got = torch.autograd.grad(-phi.mean(), params)
    want = torch.autograd.grad(-ref.mean(), params)
    for g, w in zip(got, want, strict=True):
        assert torch.allclose(g, w, atol=1e-6)
    # phi_0 moves only agent 0's policy parameters (leading dim = agent).
    grads = torch.autograd.grad(loss.shapley_values(td)[:, 0].sum(), params)
    assert any(g[0].abs().sum() > 0 for g in grads)
    assert all((g[1:] == 0).all() for g in grads)
    # and never the critic's
    loss.loss_actor(td)[0].backward()
    assert all(p.grad is None for _, p in loss.critic_network_params.items(True, True))


def test_discrete_gumbel_straight_through_reaches_actor():
    loss = _loss(discrete=True)
    loss.loss_actor(_batch())[0].backward()
    params = loss.actor_network_params.items(True, True)
    grads = [p.grad for _, p in params if p.requires_grad]
    assert all(g is not None for g in grads) and any(g.abs().sum() > 0 for g in grads)


def test_sampled_path_matches_exact():
    exact = _loss(discrete=False)
    sampled = _loss(discrete=False, exact_max_agents=2, num_permutations=20000)
    sampled.load_state_dict(exact.state_dict())
    td = _batch(discrete=False, b=4)
    torch.manual_seed(3)
    with torch.no_grad():
        phi_exact, phi_sampled = exact.shapley_values(td), sampled.shapley_values(td)
    scale = phi_exact.abs().mean()
    assert (phi_exact - phi_sampled).abs().max() < 0.05 * scale + 1e-4


def test_set_keys():
    loss = _loss()
    td = _batch()
    loss.set_keys(reward=("agents", "r"), terminated="terminated")
    td["next", "agents", "r"] = td["next", "agents", "reward"]
    td["next", "terminated"] = torch.zeros(B, 1, dtype=torch.bool)
    del td["next", "agents", "reward"]
    del td["next", "agents", "terminated"]
    out = loss(td)
    assert torch.isfinite(out["loss_value"]) and torch.isfinite(out["loss_actor"])


def test_bad_input():
    actor = make_coalition_actor(N, OBS, ACT, discrete=True)
    critic = CoalitionCritic(N, OBS, ACT)
    with pytest.raises(ValueError, match="action_space"):
        ShapleyActorCriticLoss(actor, critic, action_space="box")
    with pytest.raises(ValueError, match="exact_max_agents"):
        ShapleyActorCriticLoss(actor, critic, exact_max_agents=21)
    with pytest.raises(ValueError, match="num_permutations"):
        ShapleyActorCriticLoss(actor, critic, num_permutations=0)
    with pytest.raises(ValueError, match="critic_network"):
        ShapleyActorCriticLoss(actor, actor)
    td = _batch()
    td["agents", "coalition"] = torch.ones(B, N + 1, dtype=torch.bool)
    with pytest.raises(ValueError, match="coalition"):
        ShapleyActorCriticLoss(actor, critic)(td)
    with pytest.raises(ValueError, match="n_agents"):
        CoalitionCritic(0, OBS, ACT)


def test_random_coalition_modes_and_mask():
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from mapets_rl.shapley import RandomCoalition

    td = TensorDict(
        {
            ("agents", "observation"): torch.zeros(2000, 3, 1),
            ("agents", "mask"): torch.tensor([True, True, False]).expand(2000, 3),
        },
        [2000],
    )
    module = RandomCoalition(3, join_prob=0.3)
    with set_exploration_type(ExplorationType.RANDOM):
        c = module(td)["agents", "coalition"]
    assert abs(c[:, :2].float().mean().item() - 0.3) < 0.05
    assert not c[:, 2].any()  # masked-out agents never join
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        c = module(td)["agents", "coalition"]
    assert c[:, :2].all() and not c[:, 2].any()  # grand coalition of the alive agents
    with pytest.raises(ValueError, match="eval_mode"):
        RandomCoalition(3, eval_mode="half")


def test_reward_scale_scales_the_target():
    td = _batch()
    plain, scaled = _loss(gamma=0.0), _loss(gamma=0.0, reward_scale=0.1)
    _, meta = plain.loss_value(td)
    _, meta_scaled = scaled.loss_value(td)
    torch.testing.assert_close(meta_scaled["target_value"], 0.1 * meta["target_value"])
    with pytest.raises(ValueError, match="reward_scale"):
        _loss(reward_scale=0.0)


def test_logits_penalty():
    td = _batch()
    plain, reg = _loss(logits_reg=0.0), _loss(logits_reg=0.5)
    reg.load_state_dict(plain.state_dict())
    actor = plain.actor_network
    with plain.actor_network_params.to_module(actor, preserve_module_state=False):
        view = td.select(("agents", "observation"), ("agents", "coalition")).clone()
        logits = actor(view)["agents", "logits"]
    torch.manual_seed(4)
    base = plain.loss_actor(td)[0]
    torch.manual_seed(4)
    penalised = reg.loss_actor(td)[0]
    assert torch.allclose(penalised - base, 0.5 * logits.pow(2).mean(), atol=1e-5)
    with pytest.raises(ValueError, match="logits_reg"):
        _loss(logits_reg=-1.0)


def test_alive_mask_excludes_dead_agents_from_actor_loss():
    loss = _loss(discrete=False)
    td = _batch(discrete=False)
    mask = torch.ones(B, N, dtype=torch.bool)
    mask[:, 1] = False
    td["agents", "mask"] = mask
    params = [p for _, p in loss.actor_network_params.items(True, True) if p.requires_grad]
    grads = torch.autograd.grad(loss.loss_actor(td)[0], params)
    assert all((g[1] == 0).all() for g in grads)  # agent 1 (dead) gets no update
    assert any(g[0].abs().sum() > 0 for g in grads)


def _naive_sampled_phi(loss, td, seed):
    """The sampled estimate the direct way: agent i's own action substituted into a copy of the
    joint action and the critic called on every prefix coalition, autograd through all of it
    (the same orderings as the loss draws after ``torch.manual_seed(seed)``)."""
    from mapets_rl.shapley import permutation_prefix_masks, sample_permutations

    actor, critic = loss.actor_network, loss.critic_network
    obs, a_batch = td["agents", "observation"], td["agents", "action"]
    torch.manual_seed(seed)
    with loss.actor_network_params.to_module(actor, preserve_module_state=False):
        a_pol = actor(td.select(("agents", "observation"), ("agents", "coalition")).clone())[
            "agents", "action"
        ]
    perms = sample_permutations(loss.num_permutations, N, antithetic=True)
    before = permutation_prefix_masks(perms)  # [P, n, n]
    phis = []
    with loss.critic_network_params.detach().to_module(critic, preserve_module_state=False):
        for i in range(N):
            joint = a_batch.clone()
            joint[:, i] = a_pol[:, i]
            with_i = before[:, i].clone()
            with_i[:, i] = True
            v_with = critic.coalition_values(obs, joint, with_i)
            v_before = critic.coalition_values(obs, a_batch, before[:, i])
            phis.append((v_with - v_before).mean(-1))
    return torch.stack(phis, -1)


def test_embedded_critic_sums_a_per_agent_network_over_the_members():
    """``embed_cells``: each member's (observation, action) passes through its own network
    before the members are summed; ``v(empty) = 0`` still."""
    torch.manual_seed(2)
    critic = CoalitionCritic(N, OBS, ACT, num_cells=(8, 8), embed_cells=(5,))
    obs, act = torch.randn(3, N, OBS), torch.randn(3, N, ACT)
    values = critic.all_coalition_values(obs, act)
    assert (values[:, 0] == 0).all()
    x = torch.cat([obs, act], -1)
    for k, mask in enumerate(coalition_masks(N)):
        if not mask.any():
            continue
        z = critic.bias.expand(3, -1)
        for j in mask.nonzero().flatten().tolist():
            f = torch.relu(x[:, j] @ critic.embed_weights[0][j] + critic.embed_biases[0][j])
            z = z + f @ critic.agent_weight[j] + critic.membership[j]
        torch.testing.assert_close(values[:, k], critic.head(z).squeeze(-1))
    with pytest.raises(ValueError, match="embed_cells"):
        CoalitionCritic(N, OBS, ACT, embed_cells=(4, 0))


def test_member_heads_sum_one_term_per_member():
    """``member_heads``: ``v(C) = sum_{j in C} q_j(z_C)``, one head output per agent; the terms
    of non-members are zero and ``v(empty) = 0``."""
    torch.manual_seed(3)
    critic = CoalitionCritic(N, OBS, ACT, num_cells=(8, 8), member_heads=True)
    obs, act = torch.randn(3, N, OBS), torch.randn(3, N, ACT)
    masks = coalition_masks(N)
    terms = critic.coalition_values(obs, act, masks, per_member=True)  # [3, 2**N, N]
    values = critic.all_coalition_values(obs, act)
    torch.testing.assert_close(values, terms.sum(-1))
    assert (terms[:, ~masks] == 0).all() and (values[:, 0] == 0).all()
    h = critic.embed(obs, act)
    for k in (1, 6, 15):
        q = critic.head(masks[k].float() @ h + critic.bias)  # [3, N]: every agent's q_j(z_C)
        torch.testing.assert_close(values[:, k], (q * masks[k]).sum(-1))
    with pytest.raises(ValueError, match="member_heads"):
        CoalitionCritic(N, OBS, ACT).coalition_values(obs, act, masks, per_member=True)


def test_member_heads_regress_each_member_on_its_own_reward():
    """With member heads each member's term has its own TD target ``r_j + gamma q'_j`` (zero
    outside ``C``); summed, the targets are the paper's ``R(C) + gamma v'(C')``."""
    loss = _loss(gamma=0.9, member_heads=True)
    td = _batch()
    td["next", "agents", "terminated"][:] = True  # y_j = r_j for members
    coalition = td["agents", "coalition"].float()
    reward = td["next", "agents", "reward"].squeeze(-1)
    value, meta = loss.loss_value(td)
    assert torch.isclose(meta["target_value"], (reward * coalition).sum(-1).mean())
    obs, act = td["agents", "observation"], td["agents", "action"]
    with torch.no_grad():
        q = loss.critic_network.coalition_values(
            obs, act, td["agents", "coalition"].unsqueeze(-2), per_member=True
        ).squeeze(-2)
    # sum over members of (q_j - r_j)^2, not (sum_j q_j - r_j)^2
    assert torch.isclose(value, ((q - reward * coalition) ** 2).sum(-1).mean())
    assert not torch.isclose(value, ((q - reward * coalition).sum(-1) ** 2).mean())


@pytest.mark.parametrize(("embed_cells", "member_heads"), [((), False), ((6,), False), ((), True)])
def test_sampled_path_value_and_gradient_match_direct_computation(embed_cells, member_heads):
    loss = _loss(
        discrete=False,
        exact_max_agents=2,
        num_permutations=6,
        embed_cells=embed_cells,
        member_heads=member_heads,
    )
    td = _batch(discrete=False)
    params = [p for _, p in loss.actor_network_params.items(True, True) if p.requires_grad]
    torch.manual_seed(5)
    phi = loss.shapley_values(td)
    ref = _naive_sampled_phi(loss, td, seed=5)
    torch.testing.assert_close(phi, ref, atol=1e-5, rtol=1e-5)
    got = torch.autograd.grad(-phi.mean(), params)
    want = torch.autograd.grad(-ref.mean(), params)
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize("exact_max_agents", [10, 2])
def test_chunked_equals_unchunked(exact_max_agents):
    td = _batch(discrete=False)
    results = []
    for chunk in (None, 3):
        loss = _loss(
            discrete=False,
            exact_max_agents=exact_max_agents,
            num_permutations=8,
            chunk_states=chunk,
        )
        params = [p for _, p in loss.actor_network_params.items(True, True) if p.requires_grad]
        torch.manual_seed(7)
        phi, stderr = loss.shapley_values(td, return_stderr=True)
        results.append((phi, stderr, torch.autograd.grad(phi.sum(), params)))
    (phi0, se0, g0), (phi1, se1, g1) = results
    torch.testing.assert_close(phi0, phi1, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(se0, se1, atol=1e-6, rtol=1e-5)
    for a, b in zip(g0, g1, strict=True):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-5)
    critic = _loss().critic_network
    obs, act = td["agents", "observation"], td["agents", "action"]
    torch.testing.assert_close(
        critic.all_coalition_values(obs, act),
        critic.all_coalition_values(obs, act, chunk_states=5),
    )


def test_sampled_estimate_within_reported_standard_error():
    """On the critic's game at N = 4 (exact value known), the permutation estimate lies within
    its reported standard error for most entries (about 68% expected) and within 4 for all."""
    exact = _loss(discrete=False)
    sampled = _loss(discrete=False, exact_max_agents=2, num_permutations=400)
    sampled.load_state_dict(exact.state_dict())
    td = _batch(discrete=False, b=8)
    torch.manual_seed(3)
    with torch.no_grad():
        phi_exact = exact.shapley_values(td)
        phi, stderr = sampled.shapley_values(td, return_stderr=True)
    assert (stderr > 0).all()
    err = (phi - phi_exact).abs()
    assert (err <= 4 * stderr).all()
    assert (err <= stderr).float().mean() >= 0.5
    loss, meta = sampled.loss_actor(td)
    assert meta["shapley_stderr"] > 0


def test_bf16_autocast_close_to_fp32():
    fp32 = _loss(discrete=False, exact_max_agents=2, num_permutations=8)
    bf16 = _loss(discrete=False, exact_max_agents=2, num_permutations=8, autocast_bf16=True)
    td = _batch(discrete=False)
    torch.manual_seed(1)
    phi32 = fp32.shapley_values(td)
    torch.manual_seed(1)
    phi16 = bf16.shapley_values(td)
    assert phi16.dtype == torch.float32
    assert (phi16 - phi32).abs().max() < 0.05 * phi32.abs().mean() + 1e-3


def test_uniform_size_coalitions_have_uniform_sizes_over_the_alive_agents():
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from mapets_rl.shapley import RandomCoalition

    torch.manual_seed(0)
    n, draws = 6, 12000
    alive = torch.ones(draws, n, dtype=torch.bool)
    alive[draws // 2 :, 4:] = False  # half the states have 4 alive agents
    td = TensorDict(
        {("agents", "observation"): torch.zeros(draws, n, 1), ("agents", "mask"): alive}, [draws]
    )
    module = RandomCoalition(n, sizes="uniform")
    with set_exploration_type(ExplorationType.RANDOM):
        c = module(td)["agents", "coalition"]
    assert not (c & ~alive).any()
    for rows, m in ((slice(0, draws // 2), 6), (slice(draws // 2, None), 4)):
        sizes = torch.bincount(c[rows].sum(-1), minlength=n + 1).float() / (draws // 2)
        assert sizes[0] == 0 and sizes[m + 1 :].sum() == 0  # never empty, never above m
        torch.testing.assert_close(sizes[1 : m + 1], torch.full((m,), 1 / m), atol=0.02, rtol=0)
        # given its size, every alive agent is equally likely to be a member
        membership = c[rows][:, :m].float().mean(0)
        torch.testing.assert_close(membership, membership.mean().expand(m), atol=0.03, rtol=0)
    binomial = RandomCoalition(n, sizes="binomial")
    with set_exploration_type(ExplorationType.RANDOM):
        sizes = binomial(td)["agents", "coalition"][: draws // 2].sum(-1).float()
    assert abs(sizes.mean().item() - 3.0) < 0.1 and sizes.std().item() < 1.4  # Bin(6, 1/2)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        assert torch.equal(module(td)["agents", "coalition"], alive)  # grand coalition
    with pytest.raises(ValueError, match="sizes must be one of"):
        RandomCoalition(n, sizes="poisson")


def test_policy_action_is_the_actor_under_given_parameters():
    """``policy_action``: the greedy action is the one-hot argmax of the actor's logits under
    the parameters passed (here the target's, equal to the online ones at the start), the
    sampled one a one-hot of the same shape; continuous actors return no logits."""
    loss, td = _loss(), _batch()
    obs, coalition = td["agents", "observation"], td["agents", "coalition"]
    greedy, logits = loss.policy_action(loss.actor_network_params, obs, coalition, greedy=True)
    assert logits.shape == (B, N, ACT)
    assert torch.equal(greedy.argmax(-1), logits.argmax(-1))
    assert torch.equal(greedy.sum(-1), torch.ones(B, N))
    sampled, _ = loss.policy_action(loss.actor_network_params, obs, coalition, greedy=False)
    assert sampled.shape == (B, N, ACT) and torch.equal(sampled.sum(-1), torch.ones(B, N))
    cont = _loss(discrete=False)
    action, none = cont.policy_action(cont.actor_network_params, obs, coalition, greedy=True)
    assert action.shape == (B, N, ACT) and none is None
