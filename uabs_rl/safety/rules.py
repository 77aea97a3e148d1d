"""Anti-collision mechanisms (docs/model.md §6): one rule class per masking mode.

Every mode is a :class:`MaskingRule`, registered under its :class:`MaskingMode` in
:data:`RULES`; this is the only module that tells modes apart. A rule says

* what it writes into the env's outputs after every reset and step
  (:meth:`MaskingRule.write`, with the specs of those entries),
* how an action is chosen given Q-values, the mask, the exploration draws and ε
  (:meth:`MaskingRule.choose`, a pure tensor function, compilable),
* which mask the double-DQN target maximises over at s' (:meth:`MaskingRule.target_mask`).

Rules are plain tensor math on ``nn.Module``s (for ``.to()``); the TorchRL modules
that apply one live in :mod:`uabs_rl.safety.modules`: ``SafetyTransform`` (the env
side: :meth:`~MaskingRule.write`) and ``MaskedActionSelector`` (the policy's last
module: :meth:`~MaskingRule.choose`), because a rank mask needs the higher-ranked
agents' *chosen* actions and so cannot be computed before the policy acts. How reports
name and rank the modes (:data:`PAPER_ORDER`, :func:`mode_phrase`) sits beside the
registry. A new mode is a rule class here and a member of ``MaskingMode`` (with its
``conf/masking/<mode>.yaml``).

* ``penalty``: only the env's boundary mask; safety is left to the penalties.
* ``flat``: ``("agents", "action_mask")`` = boundary AND the pairwise flat rule, with the
  empty-mask fallback applied and flagged in ``("agents", "mask_fallback")``.
* ``rank``: ranks from F(u) = ||b_t^(u)||_1 and the potential-collider pairs, written as
  ``("agents", "rank_order")`` and ``("agents", "colliders")``; the written mask stays
  the boundary mask (what the top agent faces). The choice goes agent by agent in rank
  order (vectorised over envs, a loop over the M rank positions only), masking each
  lower-ranked agent against the chosen next positions of its higher-ranked potential
  colliders, and returns the mask that applied and the fallback flags.

Either way the action written is the action executed and ``("agents", "action_mask")``
is the mask that applied to it: the replay buffer stores both.

Recoverable masks (``masking.recoverable=true``, the default for flat and rank)
--------------------------------------------------------------------------------
The paper's literal rules can corner an agent: a higher-ranked UABS (rank) or the
boundary (flat) can leave it no safe move, and then only a fallback is left. The
recoverable rules rest on one fact: *retracing the last step is always safe*. If every
UABS flies its last move backwards (its "backup", ``("agents", "backup_action")``), the
fleet replays the previous step in reverse: the same pair distances along the same
straight paths, which were all at least d_th, and every backup stays in the area.
At reset the env places every pair at least d_th + 2 v·δt apart, and the backup is any
boundary-legal move: two UABS each moving v·δt change their offset by at most 2 v·δt,
so any first joint move keeps d_th.

* rank: agents choose in rank order; a move of agent u is legal if its straight path
  keeps d_th from the *chosen* path of every higher-ranked potential collider and from
  the *backup* path of every lower-ranked one. Invariant, before rank r: the chosen
  paths of ranks < r and the backup paths of ranks >= r are pairwise safe. It holds at
  r = 0 (all backups), u's own backup is then legal (so u's mask is never empty), and
  any legal choice keeps it for r + 1. At the end all chosen paths are pairwise safe.
* flat (agents choose independently): a move of u is legal if its path keeps d_th from
  the path of *every* boundary-legal move of every other UABS, or if it is u's backup.
  Any combination of legal moves is safe: two "any-move-safe" moves are safe, a backup
  against an any-move-safe move is safe, and two backups are safe (the retraced step).
* Pairs further than d_th + 2 v·δt apart cannot come closer than d_th in one step.

So from every state the rules reach, every UABS has a legal move, no fallback is ever
needed, and no pair comes closer than d_th at the end of a step or on the straight
paths between steps (up to :data:`SAFETY_TOLERANCE`), for lattice and continuous
positions alike. The only condition is the start: the fleet must fit in the area with
every pair d_th + 2 v·δt apart (M <= 8 on the default 350 m x 170 m area; a larger
``scenario.n_uabs`` is refused at start-up with the maximum). The cost: an agent may be
held to its backup more often than the literal rule would hold it.

Empty masks (reachable only under the literal rules) never reach the policy: an agent
with no legal action takes the boundary-legal action that maximises its minimum
distance to the agents it is masked against (so never an occupied cell while a free one
exists); its stored mask is that single action and the step counts a fallback.
"""

from __future__ import annotations

import math
from typing import ClassVar

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.data import Binary, Categorical, TensorSpec

from uabs_rl import rng
from uabs_rl.config import (
    ConfigError,
    MaskingConfig,
    MaskingMode,
    RankNextMask,
    enum_value,
    validate_masking,
)
from uabs_rl.env.geometry import UNIT_MOVES, path_distance
from uabs_rl.env.params import EnvParams
from uabs_rl.env.uabs_env import BACKUP, BEAM_PRIORITY, FALLBACK, MASK, POSITION, Outputs

ACTION_VALUE = ("agents", "action_value")
# recoverable masks keep pairs at least d_th − this apart (metres): float round-off of
# retraced paths must not make a backup move look unsafe
SAFETY_TOLERANCE = 1e-3
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
    return rng.rand((*shape, 5), gen, device)


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


def rank_select_recoverable(q: torch.Tensor | None, boundary: torch.Tensor, pos: torch.Tensor,
                            order: torch.Tensor, colliders: torch.Tensor,
                            backup: torch.Tensor, moves: torch.Tensor, d_th: float,
                            eps: float | torch.Tensor, u: torch.Tensor | None):
    """Recoverable rank selection (see :class:`RankRule`): like :func:`rank_select`, but
    an agent's move must keep d_th, along the whole straight path, from the chosen path
    of every higher-ranked potential collider AND from the backup path (retracing its
    last move) of every lower-ranked one. Returns ``(action, applied mask, fallback)``."""
    e, m = order.shape
    rows = torch.arange(e, device=pos.device)
    plan = pos + moves[backup]  # [E, M, 2]: chosen next positions, backups until chosen
    action = torch.zeros(e, m, dtype=torch.long, device=pos.device)
    applied = torch.zeros_like(boundary)
    fallback = torch.zeros(e, m, dtype=torch.bool, device=pos.device)
    for r in range(m):
        a_idx = order[:, r]
        r0 = pos[rows, a_idx][:, None, :] - pos  # [E, M, 2] offsets u − w at the start
        dr = moves[None, :, None, :] - (plan - pos)[:, None, :, :]  # [E, 4, M, 2]
        d = path_distance(r0[:, None], dr).masked_fill(
            ~colliders[rows, a_idx][:, None, :], math.inf)  # [E, 4, M]
        legal = boundary[rows, a_idx] & ~(d < d_th - SAFETY_TOLERANCE).any(-1)
        legal, fb = apply_fallback(legal, boundary[rows, a_idx], d)  # never empty: guard
        a = epsilon_greedy(None if q is None else q[rows, a_idx], legal, eps,
                           None if u is None else u[rows, a_idx])
        action[rows, a_idx], applied[rows, a_idx], fallback[rows, a_idx] = a, legal, fb
        plan[rows, a_idx] = pos[rows, a_idx] + moves[a]
    return action, applied, fallback


def flat_recoverable_mask(pos: torch.Tensor, boundary: torch.Tensor, backup: torch.Tensor,
                          moves: torch.Tensor, d_th: float) -> torch.Tensor:
    """Recoverable flat mask (see :class:`FlatRule`): a move of u is legal if its path
    keeps d_th from the path of every boundary-legal move of every other UABS; the
    backup move (retracing the last one) is always legal. ``[E, M, 4]``."""
    m = pos.shape[-2]
    r0 = pos[:, :, None, :] - pos[:, None, :, :]  # [E, M(u), M(w), 2]
    dr = moves[:, None, :] - moves[None, :, :]  # [4(a), 4(b), 2]
    d = path_distance(r0[:, :, None, :, None, :], dr[None, None, :, None, :, :])
    eye = torch.eye(m, dtype=torch.bool, device=pos.device)[None, :, None, :, None]
    ignore = eye | ~boundary[:, None, None, :, :]  # w = u, or b leaves the area
    unsafe = (d < d_th - SAFETY_TOLERANCE).masked_fill(ignore, False).flatten(-2).any(-1)
    backup_move = torch.nn.functional.one_hot(backup, moves.shape[0]).bool()
    return (boundary & ~unsafe) | backup_move


# ----------------------------------------------------------------------------- rule classes
class MaskingRule(nn.Module):
    """One anti-collision mode. ``moves [4, 2]`` is a buffer, so ``.to()`` moves it."""

    mode: ClassVar[MaskingMode]
    # keys of the env's outputs that :meth:`choose` reads after ``q`` and the mask
    choice_keys: ClassVar[tuple[tuple[str, str], ...]] = ()
    # True if :meth:`target_mask` needs the Q-values at s' (then a transition is stored
    # once the next step's Q-values are known); else it is the mask written at s'
    target_needs_q: bool = False
    # True if the rule masks the moves that could collide; False if safety is left to
    # the reward penalties
    masks_collisions: ClassVar[bool] = True

    def __init__(self, masking: MaskingConfig, d_th: float, step_m: float,
                 moves: torch.Tensor):
        super().__init__()
        self.cfg, self.d_th, self.step_m = masking, d_th, step_m
        self.register_buffer("moves", moves.clone())
        # every episode starts with every pair at least d_th + start_margin apart
        self.start_margin = 0.0

    def write(self, td: TensorDictBase | Outputs) -> None:
        """Write what the choice needs into the env's outputs ``td`` (after a reset or a
        step; a TensorDict, or the training loop's :class:`~uabs_rl.env.uabs_env.Outputs`); the
        default writes nothing beyond the env's boundary mask."""

    def specs(self, e: int, m: int, device: torch.device) -> dict[str, TensorSpec]:
        """Specs of the agent entries :meth:`write` adds, by name under ``"agents"``."""
        return {}

    def choose(self, q: torch.Tensor | None, mask: torch.Tensor, *extra: torch.Tensor,
               eps: float | torch.Tensor = 0.0, u: torch.Tensor | None = None):
        """``(action [E, M], applied mask [E, M, 4], fallback [E, M] or None)``: ε-greedy
        over the legal actions. ``extra`` are the :attr:`choice_keys` entries; ``u`` the
        exploration draws of :func:`uniforms` (None: greedy)."""
        return epsilon_greedy(q, mask, eps, u), mask, None

    def target_mask(self, td: TensorDictBase | Outputs, choose=None) -> torch.Tensor:
        """The mask the double-DQN target maximises over at s' (``td`` = the outputs at
        s' with the online Q-values under ``("agents", "action_value")``). ``choose`` is
        :meth:`choose` or a compiled copy of it."""
        if not self.target_needs_q:
            return td.get(MASK)
        return self.target_mask_of(td.get(ACTION_VALUE), td.get(MASK),
                                   *(td.get(k) for k in self.choice_keys), choose=choose)

    def target_mask_of(self, q: torch.Tensor, mask: torch.Tensor, *extra: torch.Tensor,
                       choose=None) -> torch.Tensor:
        """:meth:`target_mask` from tensors: the online Q-values ``q``, the env's mask
        and the :attr:`choice_keys` entries at s' (what a rule whose target mask needs
        the Q-values overrides)."""
        return mask


RULES: dict[MaskingMode, type[MaskingRule]] = {}
# the paper's ranking of its modes, worst to best: collisions under penalty only, and
# validation return and P_g rank > flat > penalty (the claims uabs-report checks)
PAPER_ORDER = (MaskingMode.penalty, MaskingMode.flat, MaskingMode.rank)


def rule_class(mode: str) -> type[MaskingRule]:
    """The registered rule of masking mode ``mode``; a mode with a ``MaskingMode`` member
    but no rule (a subclass without ``@register``) is a :class:`ConfigError` naming it."""
    mode = enum_value(MaskingMode, mode, "masking.mode (select it with masking=...)")
    if mode not in RULES:
        raise ConfigError(
            f"masking.mode={mode.value} has no rule: a MaskingRule subclass with mode = "
            f"MaskingMode.{mode.name}, decorated with @register, in uabs_rl/safety/rules.py "
            f"(registered: {', '.join(m.value for m in RULES)}).")
    return RULES[mode]


def masks_collisions(mode: str) -> bool:
    """Whether masking mode ``mode`` masks colliding moves (False: penalties only)."""
    return rule_class(mode).masks_collisions


def mode_phrase(mode: str) -> str:
    """How figures and reports name ``mode``: "flat masks", "rank masks", "penalty"."""
    return f"{mode} masks" if masks_collisions(mode) else str(mode)


def register(cls: type[MaskingRule]) -> type[MaskingRule]:
    """Class decorator: make ``cls`` the rule of ``cls.mode``."""
    RULES[cls.mode] = cls
    return cls


@register
class PenaltyRule(MaskingRule):
    """Only the boundary mask: safety is left to the penalties λ_s, λ_c."""

    mode = MaskingMode.penalty
    masks_collisions = False


@register
class FlatRule(MaskingRule):
    """An action of u is illegal if it ends closer than d_th + margin to any other UABS's
    current position (margin v·δt by default: it covers the other's unknown move). The
    mask depends on the state alone, so it is also exactly the target mask at s'."""

    mode = MaskingMode.flat

    def __init__(self, masking: MaskingConfig, d_th: float, step_m: float,
                 moves: torch.Tensor):
        super().__init__(masking, d_th, step_m, moves)
        # flat: d_th + v·δt covers the other agent's unknown move [paper]
        margin = masking.flat_margin
        self.radius = d_th + (step_m if margin is None else margin)
        self.recoverable = masking.recoverable
        if self.recoverable:  # pairs start d_th + 2 v·δt apart: any first joint move is safe
            self.start_margin = 2 * step_m

    def write(self, td: TensorDictBase | Outputs) -> None:
        pos, boundary = td.get(POSITION), td.get(MASK)
        if self.recoverable:
            td.set(MASK, flat_recoverable_mask(pos, boundary, td.get(BACKUP), self.moves,
                                               self.d_th))
            td.set(FALLBACK, torch.zeros(pos.shape[:-1], dtype=torch.bool,
                                         device=pos.device))
            return
        unsafe, dist = flat_unsafe(pos, self.moves, self.radius)
        mask, fb = apply_fallback(boundary & ~unsafe, boundary, dist)
        td.set(MASK, mask)
        td.set(FALLBACK, fb)

    def specs(self, e: int, m: int, device: torch.device) -> dict[str, TensorSpec]:
        return {FALLBACK[1]: Categorical(2, shape=(e, m), dtype=torch.bool, device=device)}


@register
class RankRule(MaskingRule):
    """Agents choose in rank order; a lower-ranked agent may not end closer than d_th to
    the chosen next position of a higher-ranked potential collider (docs/model.md §6).

    Target mask at s' (``masking.rank_next_mask``): a lower-ranked agent's mask depends
    on what the higher-ranked ones will choose there, unknown when the transition is
    stored. ``greedy`` (default) runs the rank choice greedily with the online network's
    Q-values at s' (as double DQN selects with) and uses the masks it applies: those the
    greedy policy would face. ``boundary`` uses the boundary mask, an upper bound on every
    agent's legal set (optimistic for the lower-ranked)."""

    mode = MaskingMode.rank
    choice_keys = (POSITION, RANK_ORDER, COLLIDERS)

    def __init__(self, masking: MaskingConfig, d_th: float, step_m: float,
                 moves: torch.Tensor):
        super().__init__(masking, d_th, step_m, moves)
        # rank: pairs within d_th + 2·v·δt may come closer than d_th this step [paper]
        margin = masking.collider_margin
        self.collider_radius = d_th + (2 * step_m if margin is None else margin)
        self.next_mask = enum_value(RankNextMask, masking.rank_next_mask,
                                    "masking.rank_next_mask")
        self.target_needs_q = self.next_mask == RankNextMask.greedy
        self.recoverable = masking.recoverable
        if self.recoverable:  # pairs start d_th + 2 v·δt apart: any first joint move is safe
            self.start_margin = 2 * step_m
            self.choice_keys = (*self.choice_keys, BACKUP)

    def write(self, td: TensorDictBase | Outputs) -> None:
        td.set(RANK_ORDER, rank_order(td.get(BEAM_PRIORITY)))
        td.set(COLLIDERS, potential_colliders(td.get(POSITION), self.collider_radius))

    def specs(self, e: int, m: int, device: torch.device) -> dict[str, TensorSpec]:
        return {RANK_ORDER[1]: Categorical(m, shape=(e, m), dtype=torch.long, device=device),
                COLLIDERS[1]: Binary(n=m, shape=(e, m, m), dtype=torch.bool, device=device)}

    def choose(self, q, mask, pos, order, colliders, backup=None, eps=0.0, u=None):
        if self.recoverable:
            return rank_select_recoverable(q, mask, pos, order, colliders, backup,
                                           self.moves, self.d_th, eps, u)
        return rank_select(q, mask, pos, order, colliders, self.moves, self.d_th, eps, u)

    def target_mask_of(self, q, mask, *extra, choose=None):
        if not self.target_needs_q:  # boundary
            return mask
        _, applied, _ = (choose or self.choose)(q, mask, *extra, eps=0.0, u=None)
        return applied


def make_rule(masking: MaskingConfig, params: EnvParams) -> MaskingRule:
    """The rule of ``masking.mode`` for an env with ``params``."""
    validate_masking(masking)
    cls = rule_class(masking.mode)
    return cls(masking, params.d_th, params.step_m, UNIT_MOVES * params.step_m)
