"""Anti-collision mechanisms (SPEC §6): penalty, flat masking and rank masking.

Two pieces cooperate, because a rank mask needs the higher-ranked agents' *chosen*
actions and so cannot be computed before the policy acts:

* :class:`SafetyTransform`, a TorchRL transform on the env's outputs. ``penalty``:
  nothing beyond the env's boundary mask. ``flat``: ``("agents", "action_mask")`` =
  boundary AND the pairwise flat rule, with the empty-mask fallback applied and flagged
  in ``("agents", "mask_fallback")``. ``rank``: ranks from F(u) = ||b_t^(u)||_1 and the
  potential-collider pairs, written as ``("agents", "rank_order")`` and
  ``("agents", "colliders")``; the mask stays the boundary mask (what the top agent faces).
* :class:`MaskedActionSelector`, the last module of every policy: ε-greedy over the
  legal actions of the mask that applies. In ``rank`` mode it chooses agent by agent in
  rank order (vectorised over envs, a loop over the M rank positions only), masking
  each lower-ranked agent against the chosen next positions of its higher-ranked
  potential colliders, and writes the mask that applied and the fallback flags.

Either way the action written is the action executed and ``("agents", "action_mask")``
is the mask that applied to it: the replay buffer stores both.

Empty masks never reach the policy: an agent with no legal action takes the
boundary-legal action that maximises its minimum distance to the agents it is masked
against; its stored mask is that single action and the step counts a fallback.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Binary, Categorical, Composite
from torchrl.envs.transforms import Transform

from uabs_rl._compile import compiled_or_eager
from uabs_rl.env import BEAM_PRIORITY, FALLBACK, MASK, POSITION

MODES = ("penalty", "flat", "rank")
ACTION_VALUE = ("agents", "action_value")
RANK_ORDER = ("agents", "rank_order")  # rank_order[e, r] = the agent at rank r (0 = top)
COLLIDERS = ("agents", "colliders")  # colliders[e, u, w]: u and w may collide this step


# ----------------------------------------------------------------------------- rules
def move_targets(pos: torch.Tensor, moves: torch.Tensor) -> torch.Tensor:
    """[..., 4, 2] the positions each action leads to, from ``pos [..., 2]``."""
    return pos[..., None, :] + moves


def flat_unsafe(pos: torch.Tensor, moves: torch.Tensor, radius: float) -> tuple[torch.Tensor,
                                                                                torch.Tensor]:
    """Flat rule: action a of u is unsafe if ||p_u + Δa − p_w|| < radius for some w ≠ u.

    Returns ``unsafe [E, M, 4]`` and the candidate-to-agent distances ``[E, M, 4, M]``
    (+inf for w = u), reused by the fallback."""
    m = pos.shape[-2]
    cand = move_targets(pos, moves)  # [E, M, 4, 2]
    d = (cand[:, :, :, None, :] - pos[:, None, None, :, :]).norm(dim=-1)  # [E, M, 4, M]
    eye = torch.eye(m, dtype=torch.bool, device=pos.device)[None, :, None, :]
    d = d.masked_fill(eye, math.inf)
    return (d < radius).any(-1), d


def apply_fallback(mask: torch.Tensor, boundary: torch.Tensor,
                   dist: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Replace empty mask rows by the single boundary-legal action that maximises the
    minimum distance ``dist [..., 4, K]`` to the agents masked against (+inf entries
    are ignored). Returns ``(mask, fallback flags)``."""
    empty = ~mask.any(-1)
    clearance = dist.amin(-1).masked_fill(~boundary, -math.inf)  # [..., 4]
    best = torch.nn.functional.one_hot(clearance.argmax(-1), mask.shape[-1]).bool()
    return torch.where(empty[..., None], best, mask), empty


def rank_order(beam_priority: torch.Tensor) -> torch.Tensor:
    """[E, M] agents sorted by F(u) = ||b_t^(u)||_1, highest first; ties: lower index
    first (a stable sort)."""
    score = beam_priority.sum(-1)
    return torch.sort(-score, dim=-1, stable=True).indices


def potential_colliders(pos: torch.Tensor, radius: float) -> torch.Tensor:
    """[E, M, M] True for pairs u ≠ w closer than ``radius`` (d_th + 2 v δt)."""
    d = torch.cdist(pos, pos)
    eye = torch.eye(pos.shape[-2], dtype=torch.bool, device=pos.device)
    return (d < radius) & ~eye


# ----------------------------------------------------------------------------- choice
def uniforms(shape: torch.Size | tuple[int, ...], gen: torch.Generator | None,
             device: torch.device | str) -> torch.Tensor:
    """The exploration draws of one decision, ``[*shape, 5]``: four to pick a random
    action, one to decide whether to explore. Drawn up front in one call, so the
    selection itself is a pure (and compilable) function."""
    return torch.rand(*shape, 5, generator=gen, device=device)


def epsilon_greedy(q: torch.Tensor | None, mask: torch.Tensor, eps: float | torch.Tensor,
                   u: torch.Tensor | None) -> torch.Tensor:
    """Per row: with probability ε a uniform legal action, else the best legal one.
    ``u [..., 5]`` are the row's uniform draws (None: greedy, needs ``q``)."""
    if u is None:
        return q.masked_fill(~mask, -math.inf).argmax(-1)
    random_a = u[..., :4].masked_fill(~mask, -1.0).argmax(-1)  # uniform over legal ones
    if q is None:
        return random_a
    greedy_a = q.masked_fill(~mask, -math.inf).argmax(-1)
    return torch.where(u[..., 4] < eps, random_a, greedy_a)


def rank_select(q: torch.Tensor | None, boundary: torch.Tensor, pos: torch.Tensor,
                order: torch.Tensor, colliders: torch.Tensor, moves: torch.Tensor, d_th: float,
                eps: float | torch.Tensor, u: torch.Tensor | None):
    """Sequential rank-masked selection. Returns ``(action [E, M], applied mask [E, M, 4],
    fallback [E, M])``. Agents choose in rank order; agent u may not end closer than
    d_th to the chosen next position of an already-chosen potential collider.
    ``u [E, M, 5]``: exploration draws (None: greedy)."""
    e, m = order.shape
    rows = torch.arange(e, device=pos.device)
    next_pos = pos.clone()
    chosen = torch.zeros(e, m, dtype=torch.bool, device=pos.device)
    action = torch.zeros(e, m, dtype=torch.long, device=pos.device)
    applied = torch.zeros_like(boundary)
    fallback = torch.zeros(e, m, dtype=torch.bool, device=pos.device)
    for r in range(m):
        a_idx = order[:, r]
        cand = move_targets(pos[rows, a_idx], moves)  # [E, 4, 2]
        against = colliders[rows, a_idx] & chosen  # [E, M]
        d = (cand[:, :, None, :] - next_pos[:, None, :, :]).norm(dim=-1)  # [E, 4, M]
        d = d.masked_fill(~against[:, None, :], math.inf)
        legal = boundary[rows, a_idx] & ~(d < d_th).any(-1)
        legal, fb = apply_fallback(legal, boundary[rows, a_idx], d)
        a = epsilon_greedy(None if q is None else q[rows, a_idx], legal, eps,
                           None if u is None else u[rows, a_idx])
        action[rows, a_idx], applied[rows, a_idx], fallback[rows, a_idx] = a, legal, fb
        next_pos[rows, a_idx] = cand[rows, a]
        chosen[rows, a_idx] = True
    return action, applied, fallback


def next_state_mask(td_next: TensorDictBase, mode: str, rank_next_mask: str,
                    q_next: torch.Tensor | None, moves: torch.Tensor, d_th: float) -> torch.Tensor:
    """The mask the double-DQN target maximises over at s' ([B, M, 4]).

    * ``penalty`` and ``flat``: the mask the transform wrote at s'. It depends on s'
      alone, so it is exactly the mask the agent will face there.
    * ``rank``: the mask of a lower-ranked agent depends on the actions the higher-ranked
      ones will choose at s', unknown when the transition is stored. ``"greedy"`` (the
      default) runs the rank selection greedily with ``q_next`` (the online network's
      Q-values at s', as double DQN selects with) and uses the masks it applies: the
      masks the greedy policy would face. ``"boundary"`` uses the boundary mask, an
      upper bound on every agent's legal set (optimistic for the lower-ranked).
    """
    mask = td_next.get(MASK)
    if mode != "rank" or rank_next_mask == "boundary":
        return mask
    _, applied, _ = rank_select(q_next, mask, td_next.get(POSITION), td_next.get(RANK_ORDER),
                                td_next.get(COLLIDERS), moves, d_th, 0.0, None)
    return applied


def select_actions(mode: str, q: torch.Tensor | None, mask: torch.Tensor, pos: torch.Tensor,
                   order: torch.Tensor | None, colliders: torch.Tensor | None,
                   moves: torch.Tensor, d_th: float, eps: torch.Tensor, u: torch.Tensor):
    """The selector's pure core: ``(action, applied mask, fallback or None)``."""
    if mode == "rank":
        return rank_select(q, mask, pos, order, colliders, moves, d_th, eps, u)
    # flat: the transform already applied the fallback; penalty: none is needed
    return epsilon_greedy(q, mask, eps, u), mask, None


# ----------------------------------------------------------------------------- modules
class SafetyTransform(Transform):
    """Writes what the masking mode needs into the env's outputs (see module doc)."""

    def __init__(self, mode: str, d_th: float, step_m: float, moves: torch.Tensor,
                 flat_margin: float | None = None, collider_margin: float | None = None):
        if mode not in MODES:
            raise ValueError(f"masking mode must be one of {MODES}, got {mode!r}")
        super().__init__(in_keys=[], out_keys=[])
        self.mode = mode
        self.d_th = d_th
        # flat: d_th + v·δt covers the other agent's unknown move [paper]
        self.flat_radius = d_th + (step_m if flat_margin is None else flat_margin)
        # rank: pairs within d_th + 2·v·δt may come closer than d_th this step [paper]
        self.collider_radius = d_th + (2 * step_m if collider_margin is None else collider_margin)
        self.register_buffer("moves", moves.clone())

    def _call(self, td: TensorDictBase) -> TensorDictBase:
        pos = td.get(POSITION)
        if self.mode == "flat":
            boundary = td.get(MASK)
            unsafe, dist = flat_unsafe(pos, self.moves.to(pos.device), self.flat_radius)
            mask, fb = apply_fallback(boundary & ~unsafe, boundary, dist)
            td.set(MASK, mask)
            td.set(FALLBACK, fb)
        elif self.mode == "rank":
            td.set(RANK_ORDER, rank_order(td.get(BEAM_PRIORITY)))
            td.set(COLLIDERS, potential_colliders(pos, self.collider_radius))
        return td

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase):
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        agents = observation_spec["agents"]
        e, m = agents.shape
        dev = observation_spec.device
        if self.mode == "flat":
            agents[FALLBACK[1]] = Categorical(2, shape=(e, m), dtype=torch.bool, device=dev)
        elif self.mode == "rank":
            agents[RANK_ORDER[1]] = Categorical(m, shape=(e, m), dtype=torch.long, device=dev)
            agents[COLLIDERS[1]] = Binary(n=m, shape=(e, m, m), dtype=torch.bool, device=dev)
        return observation_spec


class MaskedActionSelector(TensorDictModuleBase):
    """ε-greedy action choice under the masking mode's masks: the policy's last module.

    Reads ``("agents", "action_value")`` when present (absent: a uniformly random legal
    policy), the mask, and in rank mode the positions, ranks and colliders. Writes the
    action, the mask that applied and the fallback flags. ``eps`` is a buffer the
    trainer anneals; ``generator`` makes exploration reproducible."""

    def __init__(self, mode: str, d_th: float, moves: torch.Tensor, eps: float = 0.0,
                 generator: torch.Generator | None = None, compile: bool = False):
        super().__init__()
        if mode not in MODES:
            raise ValueError(f"masking mode must be one of {MODES}, got {mode!r}")
        self.mode, self.d_th, self.generator = mode, d_th, generator
        self.in_keys = [ACTION_VALUE, MASK, POSITION, RANK_ORDER, COLLIDERS]
        self.out_keys = [("agents", "action"), MASK, FALLBACK]
        self.register_buffer("moves", moves.clone())
        self.register_buffer("eps", torch.tensor(float(eps)))
        self._select = compiled_or_eager(select_actions, "the action selection") if compile \
            else select_actions

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        mask = td.get(MASK)
        u = uniforms(mask.shape[:-1], self.generator, mask.device)
        action, mask, fallback = self._select(
            self.mode, td.get(ACTION_VALUE, None), mask, td.get(POSITION),
            td.get(RANK_ORDER, None), td.get(COLLIDERS, None), self.moves, self.d_th,
            self.eps, u)
        if fallback is None:
            fallback = td.get(FALLBACK, None)
            if fallback is None:
                fallback = torch.zeros(mask.shape[:-1], dtype=torch.bool, device=mask.device)
        td.set(("agents", "action"), action)
        td.set(MASK, mask)
        td.set(FALLBACK, fallback)
        return td
