"""A monotone value mixer that is a graph neural network over the agents' communication graph
(SVMIX's mixer, Xiao et al. 2023; see :mod:`mapets_rl.recipes.svmix` for what is the paper's and
what is chosen here).

Each agent's node embedding is computed from its own features and, over ``layers`` rounds of
message passing, from those of the agents it is linked to (a batched ``[*, I, I]`` adjacency:
sampled link failures are edges set to ``False``; no Python loop over agents). A hypernetwork
reads the embedding and gives the agent's mixing weights, made non-negative by ``abs`` as in
QMIX (Rashid et al. 2018, eq. 5's monotonicity constraint), and its contribution to the joint
value is a monotone function of its own value alone:

    h_i^0 = relu(W_in x_i)
    h_i^(k+1) = relu(W_self h_i^k + W_nbr mean_{j in N(i)} h_j^k)      (0 for an empty N(i))
    c_i = sum_e |w2_e(h_i)| elu(|w1_e(h_i)| v_i + b1_e(h_i)) + b2(h_i)
    V_tot = sum_i m_i c_i

so ``dV_tot / dv_i = m_i sum_e |w2_e| |w1_e| elu'(.) >= 0``. An agent linked to nobody (out of
range of everyone, or all of whose links failed) changes no other agent's embedding, weights or
contribution; the mixer is equivariant to a permutation of the agents (shared weights, a mean
over neighbours, a sum over agents).
"""

from __future__ import annotations

import torch
from torch import nn

from mapets_rl.modules.arguments import require_positive_ints

__all__ = ["GraphValueMixer"]


class GraphValueMixer(nn.Module):
    """Monotone mixing of per-agent values over a graph: ``value [*, I, 1]``, ``features [*, I,
    F]``, ``adjacency [*, I, I]`` bool and an optional ``mask [*, I]`` bool (agents still
    driving) -> ``(total [*, 1], contribution [*, I, 1], weight [*, I, E])``.

    ``weight`` holds the first-layer mixing weights ``|w1(h_i)|`` (non-negative), which the
    tests read to show what each agent's embedding depends on; ``contribution`` is ``c_i`` of
    the module docstring (zero for a masked agent), ``total`` their sum. A masked agent's links
    are ignored (its row and column of ``adjacency``).

    Args:
        n_features: ``F``, size of each agent's node features (e.g. its observation).
        hidden: width ``H`` of the node embeddings.
        layers: rounds of message passing (>= 1; ``k`` rounds reach the ``k``-hop
            neighbourhood).
        embed: ``E``, width of the per-agent monotone mixing layer.
        device: parameter device.
    """

    def __init__(
        self,
        n_features: int,
        *,
        hidden: int = 32,
        layers: int = 2,
        embed: int = 8,
        device: torch.device | str | None = None,
    ) -> None:
        require_positive_ints(n_features=n_features, hidden=hidden, layers=layers, embed=embed)
        super().__init__()
        self.n_features = n_features
        self.embed = embed
        self.encode = nn.Linear(n_features, hidden, device=device)
        self.self_weights = nn.ModuleList(
            nn.Linear(hidden, hidden, device=device) for _ in range(layers)
        )
        self.neighbour_weights = nn.ModuleList(
            nn.Linear(hidden, hidden, bias=False, device=device) for _ in range(layers)
        )
        # hypernetwork heads: w1 [E], b1 [E], w2 [E], b2 [1] per agent
        self.hyper = nn.Linear(hidden, 3 * embed + 1, device=device)

    def embed_nodes(self, features: torch.Tensor, adjacency: torch.Tensor) -> torch.Tensor:
        """Node embeddings ``[*, I, H]`` after the message passing over ``adjacency``."""
        links = adjacency.to(features.dtype)
        degree = links.sum(-1, keepdim=True).clamp_min(1.0)  # [*, I, 1]
        mean_neighbours = links / degree  # [*, I, I], row i averages i's neighbours
        h = torch.relu(self.encode(features))
        for own, neighbour in zip(self.self_weights, self.neighbour_weights, strict=True):
            h = torch.relu(own(h) + neighbour(mean_neighbours @ h))
        return h

    def forward(
        self,
        value: torch.Tensor,
        features: torch.Tensor,
        adjacency: torch.Tensor,
        mask: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        n = features.shape[-2] if features.ndim >= 2 else -1
        if features.ndim < 2 or features.shape[-1] != self.n_features:
            raise ValueError(
                f"features must have shape [*, I, {self.n_features}], got {tuple(features.shape)}"
            )
        if value.shape[-2:] != (n, 1):
            raise ValueError(f"value must have shape [*, {n}, 1], got {tuple(value.shape)}")
        if adjacency.shape[-2:] != (n, n) or adjacency.dtype != torch.bool:
            raise ValueError(
                f"adjacency must be a bool tensor of shape [*, {n}, {n}], got "
                f"{adjacency.dtype} {tuple(adjacency.shape)}"
            )
        if mask is not None:
            if mask.ndim == value.ndim:  # [*, I, 1]
                mask = mask.squeeze(-1)
            if mask.shape[-1:] != (n,) or mask.dtype != torch.bool:
                raise ValueError(
                    f"mask must be a bool tensor of shape [*, {n}], got {mask.dtype} "
                    f"{tuple(mask.shape)}"
                )
            adjacency = adjacency & mask.unsqueeze(-1) & mask.unsqueeze(-2)
        h = self.embed_nodes(features, adjacency)
        w1, b1, w2, b2 = self.hyper(h).split([self.embed, self.embed, self.embed, 1], dim=-1)
        w1, w2 = w1.abs(), w2.abs()
        hidden = nn.functional.elu(w1 * value.to(h.dtype) + b1)  # [*, I, E]
        contribution = (w2 * hidden).sum(-1, keepdim=True) + b2  # [*, I, 1]
        if mask is not None:
            contribution = contribution * mask.unsqueeze(-1).to(contribution.dtype)
        return contribution.sum(-2), contribution, w1
