"""The teacher-guided 3DQN (``algo=dqfd``): the 3DQN's TD loss plus a large-margin term
that pulls a privileged teacher's move above the others (DQfD, Hester et al., AAAI 2018),
on labels of the learner's own states (DAgger, Ross et al., AISTATS 2011).

The teacher is the clairvoyant receding-horizon planner (:mod:`uabs_rl.training.teacher`,
horizon ``algo.teacher_horizon``): it labels every transition the ε-greedy policy
collects with the best move its mask allowed. The loss of a batch is

    L = Huber(Q(o, a), y) + λ_E · J_E,
    J_E = max_{a' legal} [Q(o, a') + ℓ · (a' != a_E)] − Q(o, a_E),

y the 3DQN's double-DQN target, a_E the teacher's label, ℓ = ``algo.teacher_margin``,
λ_E = ``algo.imitation_weight`` and J_E averaged over the batch's labelled agents. J_E is
zero exactly when the teacher's move beats every other legal move by ℓ, so the greedy
policy is the teacher's wherever it holds, and the TD loss keeps the values consistent
with the rewards (where the teacher is wrong for the agent's own view, the values may
still disagree with it). With λ_E = 0 and eager updates the learner is the
3DQN, transition for transition: the teacher draws no random numbers
(``tests/test_dqfd.py`` checks the metrics are the 3DQN's); the compiled update of this
loss is another program, equal to float rounding.

The student flies on its observation alone: the checkpoint is a 3DQN's (the same
network under ``learner.qnet``), so ``uabs-eval`` and every benchmark take it as any run.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from tensordict import TensorDict
from torch import nn
from torchrl.objectives import LossModule

from uabs_rl.algorithms.base import Dims, register
from uabs_rl.algorithms.dqn3 import DQN3, DQN3Loss
from uabs_rl.config import AlgoConfig, ConfigError, LossKind
from uabs_rl.training.teacher import NO_LABEL

TEACHER = "teacher"  # the replay field of the teacher's labels ([..., M], NO_LABEL: none)


def margin_loss(q: torch.Tensor, label: torch.Tensor, legal: torch.Tensor,
                margin: float) -> torch.Tensor:
    """J_E (module docstring) of values ``q [..., B, A]`` for labels ``label [..., B]``
    (:data:`~uabs_rl.training.teacher.NO_LABEL`: left out) over the moves ``legal
    [..., B, A]`` allows: the mean over the labelled items of the last batch dim (0 when
    none is labelled), one per member for ``[P, B, A]``."""
    has = label != NO_LABEL
    a_e = label.clamp_min(0)
    push = margin * (1.0 - F.one_hot(a_e, q.shape[-1]).to(q.dtype))
    # an unlabelled item (no legal move) counts every move, and is then left out
    best = (q + push).masked_fill(~(legal | ~has[..., None]), -torch.inf).amax(-1)
    gap = best - q.gather(-1, a_e[..., None]).squeeze(-1)
    n = has.sum(-1).clamp_min(1).to(q.dtype)
    return torch.where(has, gap, torch.zeros_like(gap)).sum(-1) / n


class DQfDLoss(DQN3Loss):
    """The 3DQN's loss plus ``weight`` times :func:`margin_loss` (module docstring); also
    returns ``imitation`` (J_E, without gradient) and ``agreement`` (the share of
    labelled agents whose greedy legal move is the teacher's)."""

    def __init__(self, qnet: nn.Module, gamma: float, margin: float, weight: float):
        super().__init__(qnet, gamma)
        self.margin, self.weight = float(margin), float(weight)

    def forward(self, b: TensorDict) -> TensorDict:
        q = self.value_network(b.get("obs"))
        q_taken = q.gather(-1, b.get("action")[..., None]).squeeze(-1)
        out = self.td_outputs(q_taken, self.next_values(b), b)
        label, legal = b.get(TEACHER), b.get("mask")
        j_e = margin_loss(q, label, legal, self.margin)
        out.set("loss", out.get("loss") + self.weight * j_e)
        with torch.no_grad():
            has = label != NO_LABEL
            greedy = q.masked_fill(~legal, -torch.inf).argmax(-1)
            agree = ((greedy == label) & has).sum(-1) / has.sum(-1).clamp_min(1)
        out.set("imitation", j_e.detach())
        out.set("agreement", agree.to(q.dtype))
        return out


@register
class DQfD(DQN3):
    """The 3DQN with a clairvoyant planner as teacher (module docstring)."""

    name = "dqfd"

    def __init__(self, algo: AlgoConfig, dims: Dims, seeds: list[int], device: torch.device):
        self.teacher_horizon = int(algo.teacher_horizon)
        super().__init__(algo, dims, seeds, device)

    @classmethod
    def check_config(cls, algo: AlgoConfig) -> None:
        if algo.loss != LossKind.fused:
            raise ConfigError(f"algo.loss={algo.loss} is the 3DQN's reference loss; "
                              f"algo={cls.name} has its own loss only: drop algo.loss.")

    def extra_fields(self) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
        return {TEACHER: ((), torch.long)}

    def make_loss(self, gamma: float) -> LossModule:
        return DQfDLoss(self.policy, gamma, self.algo.teacher_margin,
                        self.algo.imitation_weight)
