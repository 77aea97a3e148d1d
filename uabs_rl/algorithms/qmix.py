"""QMIX (``algo=qmix``): monotonic value factorisation (Rashid et al., 2018) over the team
reward, on the 3DQN's shared dueling Q-network.

Q_tot(s, a) = f_s(Q(o_1, a_1), ..., Q(o_M, a_M)), where f_s is TorchRL's ``QMixer``: a
two-layer mixing network whose weights a hypernetwork computes from the global state s
and takes the absolute value of, so Q_tot never decreases when an agent's Q does, and
the agents' greedy actions (under their masks) are the team's. Trained on the team
reward Σ_i r_i with a masked double-DQN target: y = Σ_i r_i + γ (1 − terminated)
f'_{s'}(Q_target(o'_i, argmax_{a' ∈ mask'_i} Q(o'_i, a'))), mask'_i the target mask the
masking rule stored (for rank, ``masking.rank_next_mask``, as for the 3DQN), and f' the
target mixer, copied with the target network every ``algo.target_update`` updates.

The global state s is the fleet's joint observation, the M agents' observations
concatenated (M · obs_dim numbers): every UABS's position, every UABS's per-beam
priorities and, with the lookahead features, what each sees ahead. It needs no entry
in the replay beyond the observations the agents already store, and it is exactly
what the paper's observation knows of the scene. ``algo.mixing_embed_dim`` (its own
setting: :class:`~uabs_rl.config.QmixConfig`) is the mixing network's width. Each
member of a population has its own mixer (and its own Adam for it), built right after
its network from the same seeded draws, so member p starts as the single run of its
seed starts.
"""

from __future__ import annotations

import copy
import warnings

import torch
from tensordict import TensorDict, TensorDictParams
from torch import nn
from torchrl.modules import QMixer
from torchrl.objectives import LossModule

from uabs_rl.algorithms.base import Dims, register
from uabs_rl.algorithms.dqn3 import TARGET_WARNING, DQN3Loss
from uabs_rl.algorithms.vdn import VDN
from uabs_rl.config import QmixConfig


def mix(mixers: nn.ModuleList, q: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
    """Q_tot of agent values ``q`` ``[B, M]`` and states ``[B, S]`` (a single run's
    mixer), or ``[P, B, M]`` and ``[P, B, S]`` (member p's rows through mixer p)."""
    if q.dim() == 2:
        return mixers[0](q[..., None], state).squeeze(-1)
    return torch.stack([m(q[p, ..., None], state[p]).squeeze(-1)
                        for p, m in enumerate(mixers)])


class QMIXLoss(DQN3Loss):
    """Huber(Q_tot(s, a), y) per env step (see the module docstring) on batches of env
    steps ``[B, M, ...]`` (a population's ``[P, B, M, ...]``, one loss per member). The
    mixers are a second functional network of the loss, so TorchRL's target updater
    copies them with the Q-network."""

    mixer: nn.ModuleList
    mixer_params: TensorDictParams
    target_mixer_params: TensorDictParams

    def __init__(self, qnet: nn.Module, gamma: float, mixers: nn.ModuleList):
        super().__init__(qnet, gamma)
        self.convert_to_functional(mixers, "mixer", create_target_params=True)
        self.target_mixers = copy.deepcopy(mixers)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=TARGET_WARNING)
            self.target_mixer_params.to_module(self.target_mixers)  # shares them

    def forward(self, b: TensorDict) -> TensorDict:
        q_taken, q_next = self.agent_values(b)  # [..., B, M]
        q_tot = mix(self.mixer, q_taken, b.get("obs").flatten(-2))
        with torch.no_grad():
            next_tot = mix(self.target_mixers, q_next, b.get("next_obs").flatten(-2))
            alive = (~b.get("terminated").any(-1)).float()  # the episode ends for all
            y = b.get("team_reward") + self.gamma * alive * next_tot
        return self.outputs(q_tot, y, b, q_taken.detach().flatten(-2).mean(-1))


@register
class QMIX(VDN):
    """The 3DQN's network, optimiser and target updater, VDN's whole-step replay, and a
    mixer per member trained with :class:`QMIXLoss`."""

    name = "qmix"
    algo: QmixConfig  # its own settings beside the shared ones

    def member_extra(self) -> nn.Module:
        d = self.dims
        return QMixer(state_shape=(d.n_agents * d.obs_dim,),
                      mixing_embed_dim=int(self.algo.mixing_embed_dim),
                      n_agents=d.n_agents, device=self.device)

    def make_loss(self, gamma: float) -> LossModule:
        self.mixers = nn.ModuleList(self.extras)
        # one Adam per member's mixer, so a member's state is a single run's
        self.mixer_optims = [torch.optim.Adam(m.parameters(), lr=self.algo.lr, fused=True)
                             for m in self.mixers]
        return QMIXLoss(self.policy, gamma, self.mixers)

    def __init__(self, algo: QmixConfig, dims: Dims, seeds: list[int], device: torch.device):
        super().__init__(algo, dims, seeds, device)
        self.optims += self.mixer_optims  # an update steps the mixers with the network

    # ------------------------------------------------------------------ state
    def member_state_dict(self, p: int) -> dict:
        """The 3DQN's member state, plus ``mixer``, ``target_mixer`` (``QMixer`` state
        dicts) and ``mixer_optim`` (its Adam's)."""
        state = super().member_state_dict(p)
        state["mixer"] = self.mixers[p].state_dict()
        state["target_mixer"] = self.loss_module.target_mixers[p].state_dict()
        state["mixer_optim"] = self.mixer_optims[p].state_dict()
        return state

    def load_member(self, p: int, state: dict) -> None:
        super().load_member(p, state)
        self.mixers[p].load_state_dict(state["mixer"])
        self.loss_module.target_mixers[p].load_state_dict(state["target_mixer"])
        self.mixer_optims[p].load_state_dict(state["mixer_optim"])
