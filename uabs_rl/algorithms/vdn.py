"""VDN (``algo=vdn``): value-decomposition networks (Sunehag et al., 2018) over the team
reward, on the 3DQN's shared dueling Q-network.

The team's value is the sum of the agents' values, Q_tot(s, a) = Σ_i Q(o_i, a_i) (TorchRL's
``VDNMixer``), trained on the team reward Σ_i r_i (the paper's per-agent rewards summed)
with a masked double-DQN target: y = Σ_i r_i + γ (1 − terminated) Σ_i Q_target(o'_i,
argmax_{a' ∈ mask'_i} Q(o'_i, a')), where mask'_i is the target mask the masking rule
stored for agent i (for rank, ``masking.rank_next_mask``, as for the 3DQN). The replay
samples whole env steps; ``algo.batch_size`` still counts per-agent transitions, so an
update sees ``batch_size // M`` steps, as many agent transitions as a 3DQN update.
Acting, the masks, population training, checkpoints and evaluation are the 3DQN's.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict
from torchrl.modules import VDNMixer
from torchrl.objectives import LossModule

from uabs_rl.algorithms.base import register
from uabs_rl.algorithms.dqn3 import DQN3, DQN3Loss
from uabs_rl.config import AlgoConfig, ConfigError, LossKind


class VDNLoss(DQN3Loss):
    """Huber(Q_tot(s, a), y) per env step (see the module docstring), on batches of env
    steps ``[B, M, ...]`` (a population's ``[P, B, M, ...]``, one loss per member)."""

    def __init__(self, qnet: torch.nn.Module, gamma: float, n_agents: int):
        super().__init__(qnet, gamma)
        self.mixer = VDNMixer(n_agents=n_agents, device=None)

    def forward(self, b: TensorDict) -> TensorDict:
        q_taken, q_next = self.agent_values(b)  # [..., B, M]
        q_tot = self.mixer(q_taken[..., None]).squeeze(-1)
        with torch.no_grad():
            next_tot = self.mixer(q_next[..., None]).squeeze(-1)
            alive = (~b.get("terminated").any(-1)).float()  # the episode ends for all
            y = b.get("team_reward") + self.gamma * alive * next_tot
        return self.outputs(q_tot, y, b, q_taken.detach().flatten(-2).mean(-1))


@register
class VDN(DQN3):
    """The 3DQN's network, optimiser and target updater with :class:`VDNLoss`."""

    name = "vdn"
    unit = "step"  # its replay samples whole env steps, with the team reward

    @classmethod
    def check_config(cls, algo: AlgoConfig) -> None:
        if algo.loss != LossKind.fused:  # (its message covers algo=qmix too)
            raise ConfigError(f"algo.loss={algo.loss} is the 3DQN's reference loss; "
                              f"algo={cls.name} has its own loss only: drop algo.loss.")

    def make_loss(self, gamma: float) -> LossModule:
        return VDNLoss(self.policy, gamma, self.dims.n_agents)

    def sample_size(self) -> int:
        return max(1, int(self.algo.batch_size) // self.dims.n_agents)
