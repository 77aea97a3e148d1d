"""The hybrid policy: the deployable planner's scores plus a learned policy's Q-values.

``uabs-eval RUN --policy hybrid --hybrid-weight λ`` scores move a of UABS u as

    score(u, a) = mpc(u, a) + λ · Q(o_u, a),

where mpc(u, a) is the receding-horizon planner's score over the predicted traffic
(:class:`~uabs_rl.evaluation.planner.PlannerScore` with the mpc's predictor, horizon and
visibility: ``--mpc-horizon``, ``--predictor``, ``--sees``) and Q the run's learned
network on the agent's own observation; the masking mode's selector then picks the best
legal move, as for every policy, so the masks and their guarantees are the learned
policy's. Both terms are in the reward's units: the planner sums the priority a path
covers over H steps, Q the discounted priority the agent expects to cover (γ = 0.8: about
five steps). Where the prediction fails (the planner sees H steps of extrapolated motion,
the vehicles turn) the learned values carry what training saw of the traffic beyond it.

λ = 0 is the mpc itself, action for action (the same scores and the same seeded
tie-break); λ is chosen on validation traces (``--split eval``), never on the test
traces it is reported on (``benchmarks/hybrid.py`` does both). Its cost per decision is
the mpc's plus one forward pass of the network.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from uabs_rl.env.uabs_env import BEAM_PRIORITY, MASK, OBS, POSITION
from uabs_rl.evaluation.planner import PlannerScore
from uabs_rl.safety.rules import ACTION_VALUE

HYBRID = "hybrid"  # --policy hybrid


class HybridScore(TensorDictModuleBase):
    """``planner``'s scores plus ``weight`` times ``qnet``'s Q-values (module docstring)."""

    def __init__(self, planner: PlannerScore, qnet: nn.Module, weight: float):
        super().__init__()
        if not weight >= 0:
            raise ValueError(f"the hybrid's weight must be >= 0, got {weight}")
        self.planner, self.qnet, self.weight = planner, qnet, float(weight)
        self.in_keys, self.out_keys = [OBS, POSITION, MASK, BEAM_PRIORITY], [ACTION_VALUE]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        with torch.no_grad():
            q = self.qnet(td.get(OBS)) if self.weight else None
        td = self.planner(td)
        if q is not None:
            td.set(ACTION_VALUE, td.get(ACTION_VALUE) + self.weight * q)
        return td
