"""The UABS env as a PettingZoo ``ParallelEnv`` (docs/interop.md).

One episode at a time (``n_envs = 1``) of the env :func:`uabs_rl.safety.make.make_env`
builds, over the same traces and through the same masking rule. Agents are
``uabs_0 … uabs_{M-1}``; each one observes a dict ``{"observation": float32 [obs_dim],
"action_mask": int8 [4]}`` (PettingZoo's convention, which
``torchrl.envs.PettingZooWrapper`` and ``pettingzoo.test`` read) and acts with
``Discrete(4)`` (up, right, down, left).

What each masking mode's ``action_mask`` is (a ParallelEnv asks every agent for its
action at once, from masks computed before any agent chooses):

* ``penalty``: the boundary mask, as in training (no anti-collision mask).
* ``flat``: the flat rule's mask, exactly the one the trainer acts under: it depends on
  the state alone, so nothing is lost.
* ``rank`` (recoverable, the default): the rank rule masks a lower-ranked agent against
  the *chosen* moves of the higher-ranked ones, which one parallel step cannot tell it.
  The adapter gives each agent the **parallel rank mask** (:func:`parallel_rank_mask`):
  a move of u is legal if it keeps d_th along its path from the backup path of every
  lower-ranked potential collider, and (unless it is u's own backup) from the path of
  every boundary-legal move of every higher-ranked one. Any joint choice from these
  masks is safe and passes the sequential rank rule unchanged; it contains the
  recoverable flat mask (the top-ranked agent keeps rank's extra freedom) and is
  contained in the sequential rank mask. A rule of yours built on ``RankRule`` gets it
  too, from its own ``d_th`` and moves; where its ``choose`` differs from rank's, the
  repair below applies its choice (a move it refuses is replaced, never executed).
* ``rank`` with ``masking.recoverable=false`` (the paper's literal rule): there is no
  backup to build a parallel mask on; the mask given is the boundary mask (an upper
  bound of every agent's legal set) and the repair below applies the rank rule.

Repair: the actions received are applied through the rule's own choice
(:meth:`~uabs_rl.safety.rules.MaskingRule.choose`, in rank order for rank) with each
agent's action preferred, then its backup: an action inside the mask given is executed
as is (for rank: whatever the higher-ranked agents did); one outside it (a learner that
ignores the mask) is executed if the rule allows it (rank: given the higher-ranked
agents' actual moves), else replaced by the agent's backup (else the rule's first legal
move). Each agent's info holds the action executed
(``executed_action``; -1 after a reset) and whether it was ``repaired``;
:attr:`UABSParallelEnv.last_step` and :attr:`~UABSParallelEnv.totals` hold the env's
per-step diagnostics.
"""

from __future__ import annotations

import math
from typing import Any

import torch

try:
    import numpy as np
    from gymnasium import spaces
    from pettingzoo import ParallelEnv
except ImportError as err:  # pragma: no cover - the message is the point
    raise ImportError(
        f"uabs_rl.interop.pettingzoo needs PettingZoo ({err}): "
        f'pip install -e ".[interop]"') from err

from torchrl.envs import TransformedEnv

from uabs_rl.config import (
    ChannelConfig,
    ConfigError,
    MaskingConfig,
    MaskingMode,
    ObsConfig,
    ScenarioConfig,
    TracesConfig,
)
from uabs_rl.env.geometry import path_distance
from uabs_rl.env.uabs_env import (
    ACTION,
    BACKUP,
    DIAG,
    DIAG_KEYS,
    FALLBACK,
    MASK,
    OBS,
    POSITION,
    REWARD,
)
from uabs_rl.safety.make import make_env
from uabs_rl.safety.modules import DirectEnv
from uabs_rl.safety.rules import (
    COLLIDERS,
    RANK_ORDER,
    SAFETY_TOLERANCE,
    MaskingRule,
    RankRule,
)
from uabs_rl.traces.build import SPLITS
from uabs_rl.traces.cache import TraceSet

N_ACTIONS = 4
TOTALS = ("steps", "repaired", "collisions", "proximity", "fallbacks")


def parallel_rank_mask(pos: torch.Tensor, boundary: torch.Tensor, backup: torch.Tensor,
                       order: torch.Tensor, colliders: torch.Tensor, moves: torch.Tensor,
                       d_th: float) -> torch.Tensor:
    """``[E, M, 4]``: the recoverable rank rule made parallel (module docstring).

    A move a of u is legal if it is boundary-legal, its path keeps d_th from the backup
    path of every lower-ranked potential collider, and either a is u's backup or its
    path keeps d_th from the path of every boundary-legal move of every higher-ranked
    potential collider. Any joint choice is safe, pair by pair (h above l): if l
    retraces, h's move keeps d_th from that backup path; otherwise l's move keeps d_th
    from every move h may make. u's backup is always legal (backups retrace the last,
    safe, step), so no mask is empty."""
    e, m = order.shape
    dev = pos.device
    rank_of = torch.empty_like(order)
    rank_of.scatter_(1, order, torch.arange(m, device=dev).expand(e, m))
    higher = (rank_of[:, None, :] < rank_of[:, :, None]) & colliders  # [E, u, w]
    lower = (rank_of[:, None, :] > rank_of[:, :, None]) & colliders
    r0 = pos[:, :, None, :] - pos[:, None, :, :]  # [E, u, w, 2]
    # the other's move b as the rank rule writes it: (p_w + Δb) − p_w
    other = (pos[:, :, None, :] + moves) - pos[:, :, None, :]  # [E, w, 4(b), 2]
    dr = moves[None, :, None, None, :] - other[:, None, :, :, :]  # [E, 4(a), w, 4(b), 2]
    d = path_distance(r0[:, :, None, :, None, :], dr[:, None])  # [E, u, a, w, b]
    unsafe = d < d_th - SAFETY_TOLERANCE
    vs_any = (unsafe & boundary[:, None, None, :, :]).any(-1)  # [E, u, a, w]
    idx = backup[:, None, None, :, None].expand(e, m, N_ACTIONS, m, 1)
    vs_backup = unsafe.gather(-1, idx).squeeze(-1)  # [E, u, a, w]
    is_backup = torch.nn.functional.one_hot(backup, N_ACTIONS).bool()
    ok_lower = ~(vs_backup & lower[:, :, None, :]).any(-1)
    ok_higher = ~(vs_any & higher[:, :, None, :]).any(-1) | is_backup
    return boundary & ok_lower & ok_higher


class UABSParallelEnv(ParallelEnv):
    """PettingZoo ``ParallelEnv`` over a one-env :func:`~uabs_rl.safety.make.make_env`
    env (module docstring: the masks per mode and the repair).

    ``last_step`` holds, after each step, the actions asked for and executed
    (``requested``, ``executed``: int arrays ``[M]``), ``repaired`` (how many differ)
    and the env's diagnostics of the step (``min_pair_distance``, ``closest_approach``,
    ``collisions``, ``proximity``, ``fallbacks``, ...) as floats; ``totals`` adds them
    up over every step since the adapter was built (``closest_approach``: the minimum)."""

    metadata = {"name": "uabs_v0", "render_modes": [], "is_parallelizable": True}
    render_mode = None

    def __init__(self, env: TransformedEnv):
        base = env.base_env
        if base.n_envs != 1:
            raise ValueError(f"UABSParallelEnv needs an env of n_envs=1, got {base.n_envs}")
        self._env = DirectEnv(env)
        self.rule: MaskingRule = self._env.rule
        self.params = base.params
        self.mode = MaskingMode(self.rule.cfg.mode)
        # the rank rule's (a rule of yours built on it too: the same d_th and moves)
        self.parallel_rank = isinstance(self.rule, RankRule) and self.rule.recoverable
        m, obs_dim = self.params.n_uabs, self.params.obs_dim
        self.possible_agents = [f"uabs_{i}" for i in range(m)]
        self.agents: list[str] = []
        obs_space = spaces.Dict({
            "observation": spaces.Box(-np.inf, np.inf, (obs_dim,), np.float32),
            "action_mask": spaces.Box(0, 1, (N_ACTIONS,), np.int8)})
        self._obs_spaces = {a: obs_space for a in self.possible_agents}
        self._act_spaces = {a: spaces.Discrete(N_ACTIONS) for a in self.possible_agents}
        self._out: Any = None
        self._mask: torch.Tensor | None = None  # [1, M, 4], the mask given
        self.last_step: dict[str, Any] = {}
        self.totals: dict[str, float] = dict.fromkeys(TOTALS, 0.0) | {
            "closest_approach": math.inf}

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.Space:
        return self._obs_spaces[agent]

    def action_space(self, agent: str) -> spaces.Space:
        return self._act_spaces[agent]

    # ------------------------------------------------------------------ masks
    def _given_mask(self, out) -> torch.Tensor:
        """The mask the agents are given (module docstring)."""
        if self.parallel_rank:
            return parallel_rank_mask(out.get(POSITION), out.get(MASK), out.get(BACKUP),
                                      out.get(RANK_ORDER), out.get(COLLIDERS),
                                      self.rule.moves, self.rule.d_th)
        return out.get(MASK)

    def _observe(self, out) -> dict[str, dict[str, np.ndarray]]:
        self._out, self._mask = out, self._given_mask(out)
        obs = out.get(OBS)[0].detach().cpu().numpy().astype(np.float32)
        mask = self._mask[0].cpu().numpy().astype(np.int8)
        return {a: {"observation": obs[i], "action_mask": mask[i]}
                for i, a in enumerate(self.possible_agents)}

    # ------------------------------------------------------------------ API
    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self._env.base.set_seed(int(seed))
        obs = self._observe(self._env.reset())
        self.agents = list(self.possible_agents)
        self.last_step = {}
        return obs, {a: {"executed_action": -1, "repaired": False} for a in self.agents}

    def step(self, actions: dict[str, Any]):
        if not self.agents:
            raise RuntimeError("step() after the episode ended: call reset() first")
        out, dev = self._out, self._mask.device
        backup = out.get(BACKUP)
        # an agent that sent no action keeps its backup (always legal when recoverable)
        requested = backup.clone()
        for i, a in enumerate(self.possible_agents):
            if a in actions and actions[a] is not None:
                requested[0, i] = int(actions[a])
        if ((requested < 0) | (requested >= N_ACTIONS)).any():
            raise ValueError(f"actions must be in 0..{N_ACTIONS - 1}, got {actions}")
        onehot = torch.nn.functional.one_hot
        pref = (2.0 * onehot(requested, N_ACTIONS) + onehot(backup, N_ACTIONS)).float()
        # the rule's own mask (rank: the boundary mask; its choice masks in rank order)
        executed, _, fallback = self.rule.choose(
            pref, out.get(MASK), *(out.get(k) for k in self.rule.choice_keys), eps=0.0,
            u=None)
        if fallback is None:
            fallback = out.get(FALLBACK, None)
        td = {ACTION: executed.to(dev)}
        if fallback is not None:
            td[FALLBACK] = fallback
        nxt = self._env.step(_Entries(td))
        rew = nxt.get(REWARD)[0, :, 0].tolist()
        term = bool(nxt.get("terminated")[0, 0])
        trunc = bool(nxt.get("truncated")[0, 0])
        self.last_step = {
            "requested": requested[0].cpu().numpy(), "executed": executed[0].cpu().numpy(),
            "repaired": int((requested != executed).sum()),
            **{k: float(nxt.get((DIAG, k))[0]) for k in DIAG_KEYS}}
        for k in TOTALS:
            self.totals[k] += 1 if k == "steps" else self.last_step[k]
        self.totals["closest_approach"] = min(self.totals["closest_approach"],
                                              self.last_step["closest_approach"])
        obs = self._observe(nxt)
        agents = self.possible_agents
        result = (obs, {a: float(rew[i]) for i, a in enumerate(agents)},
                  dict.fromkeys(agents, term), dict.fromkeys(agents, trunc),
                  {a: {"executed_action": int(executed[0, i]),
                       "repaired": bool(requested[0, i] != executed[0, i])}
                   for i, a in enumerate(agents)})
        if term or trunc:
            self.agents = []
        return result

    def render(self) -> None:
        return None

    def close(self) -> None:
        return None

    def state(self) -> np.ndarray:
        """The UABS positions in metres, ``[M, 2]``."""
        return self._out.get(POSITION)[0].cpu().numpy()


class _Entries(dict):
    """The ``get`` that :class:`~uabs_rl.safety.modules.DirectEnv.step` reads."""

    def get(self, key, default=None):
        return super().get(key, default)


def make_parallel_env(scenario: ScenarioConfig, channel: ChannelConfig,
                      masking: MaskingConfig, traces: TraceSet | TracesConfig,
                      split: str = "train",
                      seed: int | None = None, obs: ObsConfig | None = None,
                      n_eval_windows: int | None = None) -> UABSParallelEnv:
    """A :class:`UABSParallelEnv` over the env :func:`~uabs_rl.safety.make.make_env`
    builds from the same settings (one env, no TorchRL ``ActionMask``); ``traces`` a
    :class:`TraceSet` or the ``traces`` config (then loaded or built). ``split`` is
    "train" (random windows) or "eval" / "test" (the fixed held-out windows), and must
    name the split ``traces`` were built for (:func:`~uabs_rl.traces.get_traces`), so
    that a learner does not train on held-out traces by a slip."""
    if split not in SPLITS:
        raise ConfigError(f"split must be one of {', '.join(SPLITS)} (eval: the validation "
                          f"traces), got {split!r}.")
    # traces config: make_env loads that split's traces
    built = traces.meta.get("split") if isinstance(traces, TraceSet) else None
    if built in SPLITS and built != split:
        raise ConfigError(
            f"split={split!r} but the traces given are the {built} split: pass "
            f"get_traces(scenario, traces_cfg, {split!r}) for them, or split={built!r} to "
            f"walk these ({'random' if built == 'train' else 'the fixed held-out'} "
            f"windows).")
    env = make_env(scenario, channel, masking, traces, split=split, n_envs=1, seed=seed,
                   spec_mask=False, obs=obs, n_eval_windows=n_eval_windows)
    return UABSParallelEnv(env)


__all__ = ["UABSParallelEnv", "make_parallel_env", "parallel_rank_mask"]
