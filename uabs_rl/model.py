"""The shared dueling Q-network: one set of parameters for every agent."""

from __future__ import annotations

import torch
from torch import nn


class DuelingQNet(nn.Module):
    """Q(o, ·) = V(o) + A(o, ·) − mean_a A(o, a) over an MLP trunk.

    Maps the last dimension, so ``[..., M, obs_dim] -> [..., M, n_actions]``: applied to
    all agents at once it shares its parameters across them (parameter sharing)."""

    def __init__(self, obs_dim: int, n_actions: int, hidden: list[int] | tuple[int, ...]):
        super().__init__()
        layers: list[nn.Module] = []
        width = obs_dim
        for h in hidden:
            layers += [nn.Linear(width, h), nn.ReLU()]
            width = h
        self.trunk = nn.Sequential(*layers)
        self.value = nn.Linear(width, 1)
        self.advantage = nn.Linear(width, n_actions)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        z = self.trunk(obs)
        a = self.advantage(z)
        return self.value(z) + a - a.mean(-1, keepdim=True)
