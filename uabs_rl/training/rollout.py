"""Collection (docs/model.md §7): ε-greedy episodes in the training env, every env step's
transitions (all agents, the agent dimension kept) stored in the learner's replay, and
the update schedule that interleaves gradient steps with env steps."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.envs import TransformedEnv

from uabs_rl.algorithms import Algorithm
from uabs_rl.algorithms.replay import TransitionReplay
from uabs_rl.config import AlgoConfig
from uabs_rl.env.uabs_env import ACTION, DIAG, DIAG_ENTRIES, MASK, OBS, REWARD
from uabs_rl.safety.modules import DirectEnv, MaskedActionSelector
from uabs_rl.training.teacher import Teacher


def epsilon(algo: AlgoConfig, env_steps: int, total_steps: int) -> float:
    """Linear ε from ``eps_start`` to ``eps_end`` over ``eps_fraction`` of the per-env
    steps of the protocol, then constant."""
    frac = min(1.0, env_steps / max(1.0, algo.eps_fraction * total_steps))
    return algo.eps_start + frac * (algo.eps_end - algo.eps_start)


class UpdateSchedule:
    """T_u = ``algo.update_every``: one update per T_u env steps of each env, so the
    paper's one update per step with n_envs = 1, and n_envs updates per collector step
    otherwise. Updates start once the buffer holds ``algo.learning_starts`` transitions."""

    def __init__(self, algorithm: Algorithm, algo: AlgoConfig):
        self.algorithm, self.buffer, self.algo = algorithm, algorithm.buffer, algo
        self.credit = 0.0

    def __call__(self, new_env_steps: int) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
        """Yields (loss, mean chosen Q) per update due after ``new_env_steps``."""
        self.credit += new_env_steps / self.algo.update_every
        while self.credit >= 1.0:
            self.credit -= 1.0
            if len(self.buffer) >= self.algo.learning_starts:
                yield self.algorithm.update(self.buffer.sample())


class Collector:
    """Runs ``n_envs`` training episodes per round with the ε-greedy masked policy.
    With ``members`` > 1 (a population) the env's rows are ``members`` blocks, one per
    member, and the updates are due per member's envs (each update is one batched
    step of every member)."""

    def __init__(self, env: TransformedEnv, qnet: nn.Module, selector: MaskedActionSelector,
                 buffer: TransitionReplay, members: int = 1,
                 n_step: int = 1, gamma: float = 1.0, teacher: Teacher | None = None):
        self.env, self.qnet, self.selector, self.buffer = env, qnet, selector, buffer
        # a learner that imitates a planner (algo=dqfd): each transition also holds the
        # teacher's move for the state the ε-greedy policy reached ("teacher" [E, M])
        self.teacher = teacher
        self.direct = DirectEnv(env)  # env.reset / env.step without TensorDicts
        self.params = env.base_env.params
        self.n_envs = env.base_env.n_envs
        self.members = members
        self.n_step, self.gamma = n_step, gamma  # n-step returns (algo.n_step)
        self.env_steps = 0  # per-env steps so far

    def _transition(self, record: list[dict[str, torch.Tensor]],
                    i: int) -> dict[str, torch.Tensor]:
        """Transition ``i`` with an n-step return (``algo.n_step``): the reward
        r_i + γ r_{i+1} + ... + γ^{n-1} r_{i+n-1} (fewer terms where the episode ends
        first) and the state n steps on; n = 1 is step i's own transition."""
        last = min(i + self.n_step, len(record)) - 1
        tr = dict(record[i])
        for k in range(1, last - i + 1):
            tr["reward"] = tr["reward"] + self.gamma ** k * record[i + k]["reward"]
        tr["next_obs"], tr["terminated"] = record[last]["next_obs"], record[last]["terminated"]
        return tr

    def _push(self, tr: dict[str, torch.Tensor], next_mask: torch.Tensor) -> None:
        # a plain mapping: building a TensorDict per step (its checks) cost more than the
        # buffer's copies
        self.buffer.extend({**tr, "next_mask": next_mask})

    def round(self, eps_at: Callable[[int], float],
              optimise: Callable[[int], Iterator[tuple[torch.Tensor, torch.Tensor]]]):
        """One episode per env to its end. ``eps_at(env_steps)`` gives ε; after each step
        ``optimise(n_envs)`` runs the updates due. Returns the last step's diagnostics,
        the summed served fractions, ε, and the mean loss / chosen Q of the updates
        (tensors: 0-d, or ``[P]`` per member of a population; NaN without updates)."""
        steps, e = self.params.episode_steps, self.n_envs
        # a transition waits for the next step's Q-values when the rule's target mask
        # needs them (rank, greedy target mask)
        defer = self.selector.rule.target_needs_q
        n = self.n_step
        td = self.direct.reset()
        served = torch.zeros(e, device=self.env.device)
        loss_sum = q_sum = torch.zeros((), device=self.env.device)
        n_updates, pushed, record = 0, 0, []  # record[i]: step i's one-step transition
        for t in range(steps):
            eps = eps_at(self.env_steps)
            self.selector.eps.fill_(eps)
            # the teacher labels the state before the selector writes the mask that applied
            scores = self.teacher.scores(td) if self.teacher is not None else None
            # Q-values, the target mask at s_t (under a deferring rule), the ε-greedy
            # choice and the env step after it. The mask is computed at every step, also
            # at t < n where no transition waits for it (dropped: it draws no random
            # numbers): one compiled program for the whole episode instead of a second
            # for its first n steps, whose compile cost 20-30 s of every run
            target_mask, nxt = self.direct.act_and_step(self.selector, self.qnet, td,
                                                        target=defer)
            if defer and t >= n:  # s_t's target mask completes transition t - n
                self._push(self._transition(record, pushed), target_mask)
                pushed += 1
            record.append({"obs": td.get(OBS), "action": td.get(ACTION), "mask": td.get(MASK),
                           "reward": nxt.get(REWARD).squeeze(-1), "next_obs": nxt.get(OBS),
                           "terminated": nxt.get(("agents", "terminated")).squeeze(-1)})
            if scores is not None:  # the best move the mask that applied allows
                record[-1]["teacher"] = Teacher.label(scores, td.get(MASK))
            if not defer and t >= n - 1:
                self._push(self._transition(record, pushed), nxt.get(MASK))
                pushed += 1
            while t == steps - 1 and pushed < steps:  # the end: cut at T, no bootstrap
                self._push(self._transition(record, pushed), nxt.get(MASK))  # mask unused
                pushed += 1
            served += nxt[DIAG, "served_fraction"]
            self.env_steps += 1
            for loss, q in optimise(e // self.members):
                loss_sum = loss_sum + loss
                q_sum = q_sum + q
                n_updates += 1
            td = nxt
        nan = torch.full((), float("nan"))
        loss = loss_sum / n_updates if n_updates else nan
        q_mean = q_sum / n_updates if n_updates else nan
        last = TensorDict({k: nxt[DIAG, k] for k in DIAG_ENTRIES},
                          batch_size=[e], device=self.env.device)
        return last, served, eps, loss, q_mean


def episode_records(last: TensorDictBase, served: torch.Tensor, steps: int, first_episode: int,
                    env_steps: int, extra: dict[str, Any]) -> list[dict[str, Any]]:
    """One ``metrics.jsonl`` record per env of a finished round."""
    return [{"kind": "train", "episode": first_episode + i, "env_steps": env_steps,
             "return": last["ep_return"][i].item(),
             "collisions": last["ep_collisions"][i].item(),
             "proximity": last["ep_proximity"][i].item(),
             "fallbacks": last["ep_fallbacks"][i].item(),
             "served_fraction": (served[i] / steps).item(),
             "pg": last["pg"][i].item(), **extra}
            for i in range(served.shape[0])]
