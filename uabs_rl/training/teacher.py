"""A privileged teacher for learners that imitate a planner (``algo=dqfd``).

The teacher is the clairvoyant receding-horizon planner of
:mod:`uabs_rl.evaluation.planner` (``uabs-eval --policy planner --horizon H``) run on the
training env itself: it reads the training traces' true future, which no deployed policy
has, and so is used in training only. At every collection step it scores the four moves
of every UABS in the state the learner's own ε-greedy policy reached (DAgger: labels on
the learner's states, not on the teacher's); once the masked selector has chosen, the
label of each agent is the teacher's best move among those its mask left legal, so under
rank masks a lower-ranked UABS is taught the best move given the moves its higher-ranked
neighbours actually took. The learner sees only its observation.

Labels cost one planner decision per collection step: measured on the 2-core development
CPU (1 thread, the default grid, M = 3, H = 5), 39 ms per step for 4 windows and 112 ms
for 20 (a population of 5 with ``train.n_envs=4``).
"""

from __future__ import annotations

import torch

from uabs_rl.env.uabs_env import UABSEnv
from uabs_rl.evaluation.planner import PlannerScore

# an agent whose applied mask allows no move gets no label. The masked selector never
# leaves one so (an agent with no legal move flies the fallback move, and its applied
# mask is that move alone): in training a forced move is labelled with itself, adds
# nothing to the margin term and counts in its mean
NO_LABEL = -1


class Teacher:
    """The clairvoyant planner of horizon ``horizon`` over ``env`` (the training env, the
    base :class:`UABSEnv`), as a labeller (module docstring). Deterministic: the
    planner's seeded tie-break is not used, ties go to the first move."""

    def __init__(self, env: UABSEnv, horizon: int):
        self.planner = PlannerScore(env, horizon, torch.Generator(device=env.device))

    def scores(self, td) -> torch.Tensor:
        """[E, M, 4] the planner's scores of each move in the env's current state (``td``:
        the env's outputs there, before the selector runs)."""
        return self.planner.scores(td)

    @staticmethod
    def best_moves(scores: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """[E, M, 4] True for every move of best score among those ``mask`` allows (ties
        kept): what the agreement benchmarks count a policy's move against."""
        legal = scores.masked_fill(~mask, -torch.inf)
        return (legal == legal.amax(-1, keepdim=True)) & mask

    @staticmethod
    def label(scores: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """[E, M] the best-scored move among those ``mask [E, M, 4]`` allows (the mask
        that applied to the chosen moves), :data:`NO_LABEL` where none is allowed."""
        best = scores.masked_fill(~mask, -torch.inf).argmax(-1)
        return torch.where(mask.any(-1), best, torch.full_like(best, NO_LABEL))
