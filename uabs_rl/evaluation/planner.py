"""A planning reference and two classic heuristics, acting through the masked selector.

Like :mod:`uabs_rl.evaluation.baselines`, each writes scores into ``("agents", "action_value")``
and the masking mode's :class:`~uabs_rl.safety.modules.MaskedActionSelector` (ε = 0) picks the
best legal action, so every one of them obeys the masks the learned policy obeys.

* :class:`PlannerScore` (``uabs-eval --policy planner --horizon H``): a centralised
  receding-horizon planner over the vehicles' true future positions: the clairvoyant
  ceiling. See its docstring. Fed by a predictor of :mod:`uabs_rl.evaluation.predict`
  instead of the true future (``uabs-eval --policy mpc --predictor cv``: constant
  velocity from the vehicles' current and previous positions) the same search is a
  deployable model-predictive controller.
* :class:`ClusterScore` (``kmeans``): each UABS flies towards the weighted centroid of
  its cluster of a k-means of the vehicles' current positions, weighted by priority.
* :class:`SiteScore` (``junctions``): each UABS flies to one of the M busiest junctions
  of the street network (busiest on the validation traces) and hovers over it.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from uabs_rl.config import ConfigError
from uabs_rl.env.channel import beam_grid_side, footprint_inside
from uabs_rl.env.service import SCORE_BLOCK, move_scores, near_sets
from uabs_rl.env.uabs_env import BEAM_PRIORITY, MASK, POSITION, UABSEnv
from uabs_rl.evaluation.predict import Predictor, TrueFuture
from uabs_rl.safety.rules import ACTION_VALUE, rank_order

JITTER = 1e-3  # the baselines' seeded tie-break, scaled as in baselines.CoverageScore


def footprint(cand: torch.Tensor, veh: torch.Tensor, r_b: float,
              n_beams: int) -> torch.Tensor:
    """[E, *K, V] True where vehicle ``veh [E, 2, V]`` lies in a footprint of a UABS at
    ``cand [E, *K, 2]``."""
    lead = (slice(None),) + (None,) * (cand.dim() - 2)
    dx = veh[lead + (0, slice(None))] - cand[..., 0:1]
    dy = veh[lead + (1, slice(None))] - cand[..., 1:2]
    return footprint_inside(dx, dy, r_b, n_beams)


def footprint_path(path: torch.Tensor, veh: torch.Tensor, r_b: float,
                   n_beams: int) -> torch.Tensor:
    """[E, H, V] True where vehicle v at step k (``veh [H, E, 2, V]``) lies in a
    footprint of a UABS at ``path [E, H, 2]``."""
    h, e = veh.shape[:2]
    inside = footprint(path.transpose(0, 1).reshape(h * e, 1, 2),
                       veh.reshape(h * e, *veh.shape[2:]), r_b, n_beams)
    return inside.reshape(h, e, -1).transpose(0, 1)


def on_lattice(pos: torch.Tensor, step: float, reach: int) -> bool:
    """Whether every point ``pos [..., 2] + n · step`` (per axis, |n| <= ``reach``) is a
    value of ``pos``'s dtype: then each sum of moves along a path is exact, whatever the
    order, and a lattice offset names one position bit for bit."""
    n = torch.arange(-reach, reach + 1, device=pos.device, dtype=torch.float64)
    offset = torch.tensor(step, dtype=pos.dtype).double() * n
    exact = pos.double()[..., None] + offset  # exact in float64
    return bool((exact == exact.to(pos.dtype).double()).all()
                and (offset == offset.to(pos.dtype).double()).all())


def lattice_offsets(n: int, device: torch.device) -> torch.Tensor:
    """[(n+1)², 2] the lattice offsets (i, j) reachable in exactly ``n`` moves
    (|i| + |j| <= n, i + j ≡ n mod 2), offset ``a (n+1) + b`` being
    (a + b − n, a − b) for a, b in 0..n (:func:`lattice_index` inverts it)."""
    a, b = torch.meshgrid(torch.arange(n + 1, device=device),
                          torch.arange(n + 1, device=device), indexing="ij")
    return torch.stack([a + b - n, a - b], dim=-1).reshape(-1, 2)


def lattice_index(off: torch.Tensor, n: int) -> torch.Tensor:
    """[...] the index in :func:`lattice_offsets` ``(n)`` of the offsets ``off [..., 2]``
    (integers, reachable in exactly n moves)."""
    i, j = off[..., 0], off[..., 1]
    return torch.div(i + j + n, 2, rounding_mode="floor") * (n + 1) + torch.div(
        i - j + n, 2, rounding_mode="floor")


# the largest footprint table a decision builds (:func:`table_bytes`); a longer horizon
# or a larger fleet, traffic or batch of windows tests each candidate instead (the same
# booleans, more time, a few MB)
TABLE_BYTES = 256 << 20


def table_bytes(e: int, m: int, horizon: int, v: int) -> int:
    """Bytes of :func:`footprint_table` for E windows, M UABS, horizon H, V vehicles:
    E·M·V booleans per lattice offset, Σ_{n=1..H} (n+1)² offsets."""
    return e * m * v * sum((n + 1) ** 2 for n in range(1, horizon + 1))


def footprint_table(pos: torch.Tensor, veh: torch.Tensor, step: torch.Tensor, r_b: float,
                    n_beams: int) -> list[torch.Tensor]:
    """For n = 1..H, ``[E, M, (n+1)², V]`` True where vehicle v at step n
    (``veh [H, E, 2, V]``) lies in a footprint of a UABS at ``pos [E, M, 2]`` moved by
    :func:`lattice_offsets` ``(n)`` lattice steps (``step``, a scalar tensor). Computed in
    blocks of at most :data:`~uabs_rl.env.service.SCORE_BLOCK` elements."""
    e, m = pos.shape[:2]
    block = max(1, SCORE_BLOCK // max(1, e * veh.shape[-1]))
    out = []
    for n in range(1, veh.shape[0] + 1):
        cand = pos[:, :, None, :] + lattice_offsets(n, pos.device).to(pos.dtype) * step
        cand = cand.reshape(e, -1, 2)  # [E, M (n+1)², 2]
        inside = torch.cat([footprint(c, veh[n - 1], r_b, n_beams)
                            for c in cand.split(block, dim=1)], dim=1)
        out.append(inside.reshape(e, m, (n + 1) ** 2, -1))
    return out


BEAM = 16  # paths the beam search keeps per first move, by default (PlannerScore.beam)
ROUNDS = 2  # passes over the fleet per decision, by default (PlannerScore.rounds)


def axis_reach(r_b: float, n_beams: int) -> float:
    """Metres, per axis, beyond which no footprint of a UABS reaches a vehicle: a k x k
    beam grid of pitch 2 r_b spans k·r_b from its centre; 1 m more, as a margin."""
    return beam_grid_side(n_beams) * r_b + 1.0


def within(veh: torch.Tensor, origin: torch.Tensor, reach: float) -> torch.Tensor:
    """``[E, M, V]`` True where vehicle ``veh [E, 2, V]`` lies within ``reach`` metres of
    ``origin [E, M, 2]`` on each axis."""
    return (veh[:, None] - origin[..., None]).abs().amax(2) <= reach


def sub_world(w: dict[str, torch.Tensor], sel: torch.Tensor,
              valid: torch.Tensor) -> dict[str, torch.Tensor]:
    """The world ``w`` (:meth:`PlannerScore.world`; ``now [E, 2, V]`` too, where given)
    cut to the vehicles ``sel [E, M, K]`` of each UABS (:func:`near_sets`): positions
    ``veh [H, E, M, 2, K]``, presence ``present [H+1, E, M, K]`` (False on the padding)
    and ``now [E, M, 2, K]``; the per-window entries as they are."""
    e, m, k = sel.shape
    out = dict(w)
    h, v = w["veh"].shape[0], w["veh"].shape[-1]
    out["veh"] = w["veh"][:, :, None].expand(h, e, m, 2, v).gather(
        -1, sel[None, :, :, None, :].expand(h, e, m, 2, k))
    n = w["present"].shape[0]
    out["present"] = w["present"][:, :, None].expand(n, e, m, v).gather(
        -1, sel[None].expand(n, e, m, k)) & valid
    if "now" in w:
        out["now"] = w["now"][:, None].expand(e, m, 2, v).gather(
            -1, sel[:, :, None, :].expand(e, m, 2, k))
    return out


def one_uabs(w: dict[str, torch.Tensor], rows: torch.Tensor,
             u: torch.Tensor) -> dict[str, torch.Tensor]:
    """UABS ``u [E]``'s world of :func:`sub_world` (window ``rows [E]``), laid out as a
    whole world: ``veh [H, E, 2, K]``, ``present [H+1, E, K]``, ``now [E, 2, K]``."""
    out = dict(w)
    out["veh"] = w["veh"][:, rows, u]
    out["present"] = w["present"][:, rows, u]
    if "now" in w:
        out["now"] = w["now"][rows, u]
    return out


def next_priority(p: torch.Tensor, served: torch.Tensor, present: torch.Tensor,
                  prev_present: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
    """Priorities one step on (docs/model.md §4, as ``service.update_service``): + 1
    where served, 1 at a window's start ``start [E]`` and for a vehicle that appears,
    0 where absent. ``p``, ``served`` broadcast against ``present [E, V]``."""
    lead = (slice(None),) + (None,) * (p.dim() - 2)
    present, prev_present = present[lead], prev_present[lead]
    reset = start[lead + (None,)] | (present & ~prev_present)
    return torch.where(present & ~reset, p + served, present.to(p.dtype))


class PlannerScore(TensorDictModuleBase):
    """Receding-horizon planner over the vehicles' positions ``horizon`` steps ahead, as
    ``predictor`` gives them (:mod:`uabs_rl.evaluation.predict`; default: the true future,
    the clairvoyant planner; a constant-velocity predictor makes it the deployable mpc).

    The score of move a of UABS u is the oracle's (the priority under u's footprints
    after a, at the vehicles' next positions and current priorities) plus the best
    value of steps 2..H over the paths that start with a (the first step is scored
    alone, as the oracle scores it: the others' first moves are settled only when the
    masked selector runs, in rank order under rank masks). Step k of a path earns the
    priority (at least 1 per present vehicle) of the vehicles under its footprints that
    no other UABS's plan covers at step k, with the priorities simulated along the path
    (+1 per served step, 1 at each window start and for an arriving vehicle, §4), so a
    path that keeps serving the same vehicles earns more. Steps past the episode's end
    earn nothing. The fleet is coordinated: the UABS are planned one after another in
    rank order (highest ||b_t||₁ first), each given the plans of those before it (their
    coverage taken out, their service in the priorities, and its path kept d_th from
    their planned positions at steps 2..H); then ``rounds - 1`` more passes replan each
    UABS given all the others' plans. Each path search is a beam search over lattice
    moves, ``beam`` paths per first move, one per position (the best so far). With
    :attr:`leaf` set (:mod:`uabs_rl.evaluation.leaf`, ``--policy leaf``) each path kept
    at the end also earns a learned value of where it ends, and the best of them by
    that total is the first move's.

    With ``coordinated=False`` each UABS plans alone: no other plan takes vehicles out of
    its paths' gains or keeps its path from theirs, and one pass is made (a diagnostic of
    what coordination is worth: ``benchmarks/planning_vs_learning.py --uncoordinated``).

    Only the first move is flown, through the masked selector; the plan is made again at
    the next step. With ``horizon = 1`` the scores are the oracle's, bit for bit, and
    the seeded tie-break draws the same numbers, so the actions are the oracle's (with
    the true future; with a predictor, those of greedy on the predicted next positions).
    """

    def __init__(self, env: UABSEnv, horizon: int, generator: torch.Generator,
                 beam: int = BEAM, rounds: int = ROUNDS, predictor: Predictor | None = None,
                 coordinated: bool = True):
        super().__init__()
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        if horizon > env.params.episode_steps:  # a longer look cannot change a move
            raise ConfigError(f"the planning horizon {horizon} is longer than an episode "
                              f"({env.params.episode_steps} steps): choose at most "
                              f"{env.params.episode_steps}.")
        if beam < 1:
            raise ValueError(f"the beam must keep at least one path, got {beam}")
        if rounds < 1:
            raise ValueError(f"the planner makes at least one pass, got rounds={rounds}")
        self.env, self.horizon, self.generator = env, horizon, generator
        self.beam, self.rounds = beam, rounds if coordinated else 1
        self.coordinated = coordinated
        self.predictor = predictor if predictor is not None else TrueFuture()
        # learned values at the paths' ends (uabs_rl.evaluation.leaf; None: the search alone)
        self.leaf: Callable[..., torch.Tensor] | None = None
        # each UABS's search over the vehicles it can reach only (see future); False: over
        # every vehicle (the same scores, bit for bit; tests compare the two)
        self.cut = True
        self.in_keys, self.out_keys = [POSITION, MASK, BEAM_PRIORITY], [ACTION_VALUE]

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        score = self.scores(td)
        jitter = torch.rand(score.shape, generator=self.generator, device=score.device)
        td.set(ACTION_VALUE, score + JITTER * jitter)
        return td

    @torch.no_grad()
    def scores(self, td: TensorDictBase) -> torch.Tensor:
        """[E, M, 4] each move's score (the class docstring), before the tie-break."""
        env, p = self.env, self.env.params
        w = self.world()
        cand = td.get(POSITION)[:, :, None, :] + env.math.moves  # [E, M, 4, 2]
        score = move_scores(cand, w["veh"][0], w["present"][1], env.priority, p.r_b,
                            p.n_beams)
        if self.horizon > 1 or self.leaf is not None:  # H = 1: the leaf values alone
            score = score + self.future(td, w, first=score)
        return score

    # ------------------------------------------------------------------ the plan
    def world(self) -> dict[str, torch.Tensor]:
        """The vehicles at steps t+1..t+H as the predictor gives them: positions
        ``veh [H, E, 2, V]``, presence ``present [H+1, E, V]`` (index 0: now), window
        starts ``start [H, E]`` and whether the step is still in the episode,
        ``live [H, E]``."""
        return self.predictor(self.env, self.horizon)

    @torch.no_grad()
    def future(self, td: TensorDictBase, w: dict[str, torch.Tensor] | None = None,
               first: torch.Tensor | None = None) -> torch.Tensor:
        """[E, M, 4] the best value of steps 2..H after each first move of each UABS
        (over the world ``w``, default :meth:`world`; ``first``: the first moves' own
        scores in that world, as :meth:`forward` has them, else computed here).

        Every position a path of UABS u can reach at step n lies on the lattice within n
        moves of u's position, so where the positions are exact lattice values
        (:func:`on_lattice`) the footprint tests are made once per decision, for each
        UABS and each such position (:func:`footprint_table`), and every search looks
        its candidates up there (:class:`Lookup`: the same booleans as testing them one
        by one).

        Each UABS's search reads only the vehicles it can reach (:meth:`reachable`: at
        step k, within k moves plus a footprint's reach of it, per axis; with
        :attr:`leaf`, also those the value at a path's end reads): on a city a few
        hundred of its thousands. The vehicles left out are under no footprint a path of
        that UABS can take, every sum is of whole priorities (exact in any order), and
        a plan's coverage is written back to every vehicle, so the scores are those of
        the search over all of them, bit for bit (``tests/test_mpc.py``). (The coverage
        written back leaves out the vehicles absent at a step, which the search over
        every vehicle marks too: ``cover`` and ``covers`` are read only where a vehicle
        is present.)"""
        p = self.env.params
        pos, allowed = td.get(POSITION), td.get(MASK)
        e, m = pos.shape[:2]
        rows = torch.arange(e, device=pos.device)
        w = self.world() if w is None else w
        moves = self.env.math.moves
        step = moves.abs().amax()
        if first is None:  # [E, M, 4]
            first = move_scores(pos[:, :, None, :] + moves, w["veh"][0], w["present"][1],
                                self.env.priority, p.r_b, p.n_beams)
        n_veh = w["veh"].shape[-1]
        keep = self.reachable(pos, w, float(step))
        sets = None if keep is None else near_sets(keep)
        if sets is None:  # every UABS over every vehicle
            ws, prio, k = w, None, n_veh
        else:  # UABS u over its vehicles sel[:, u] only
            sel, valid = sets
            if self.leaf is not None and self.horizon == 1 and "now" not in w:
                # the leaf's step t (its motion half at H = 1)
                w = {**w, "now": self.env.vehicles(0)[0]}
            ws, k = sub_world(w, sel, valid), sel.shape[-1]
            prio = self.env.priority.gather(1, sel.flatten(1)).view(sel.shape)  # [E, M, K]
        table = None
        if (on_lattice(pos, float(step), self.horizon)
                and table_bytes(e, m, self.horizon, k) <= TABLE_BYTES):
            if sets is None:
                table = footprint_table(pos, w["veh"], step, p.r_b, p.n_beams)
            else:  # each UABS's table over its own vehicles
                flat = footprint_table(pos.reshape(e * m, 1, 2),
                                       ws["veh"].flatten(1, 2), step, p.r_b, p.n_beams)
                table = [t.view(e, m, *t.shape[2:]) for t in flat]
        order = rank_order(td.get(BEAM_PRIORITY))  # [E, M]
        plan = pos[:, :, None, :].expand(e, m, self.horizon, 2).clone()  # [E, M, H, 2]
        cover = torch.zeros(e, m, self.horizon, w["veh"].shape[-1], dtype=torch.bool,
                            device=pos.device)  # [E, M, H, V] each plan's coverage
        covers = torch.zeros(cover[:, 0].shape, dtype=torch.int32, device=pos.device)
        # [E, H, V] how many plans cover each vehicle (a UABS not planned yet covers none)
        planned = torch.zeros(e, m, dtype=torch.bool, device=pos.device)
        out = torch.zeros(e, m, 4, device=pos.device)
        keeps = self.leaf is not None and hasattr(self.leaf, "tables")
        if keeps:  # the leaf's tables of this step, per UABS: each is searched every round
            self.leaf.tables = {}
        try:
            for r in range(self.rounds * m):
                u = order[:, r % m]
                others = planned.clone()
                others[rows, u] = False
                own = cover[rows, u]  # [E, H, V]; the others cover where covers > own
                look = None if table is None else Lookup(pos[rows, u], step,
                                                        [t[rows, u] for t in table])
                oth = covers > own
                if sets is None:
                    wu, prio_u = w, None
                else:  # u's vehicles only
                    idx = sel[rows, u]  # [E, K]
                    wu, prio_u = one_uabs(ws, rows, u), prio[rows, u]
                    oth = oth.gather(2, idx[:, None, :].expand(-1, self.horizon, -1))
                value, path = self.search(pos[rows, u], plan, others, oth, wu, look, u, prio_u)
                out[rows, u] = value
                if not self.coordinated:  # no plan is kept: the next UABS plans alone too
                    continue
                total = value + first[rows, u]
                best = total.masked_fill(~allowed[rows, u], -math.inf).argmax(-1)  # [E]
                plan[rows, u] = path[rows, best]
                new = (footprint_path(plan[rows, u], wu["veh"], p.r_b, p.n_beams)
                       if look is None else look.path(plan[rows, u]))
                if sets is not None:  # back to every vehicle: u's path covers none of the rest
                    # (nor, unlike footprint_path over every vehicle, one absent at that step:
                    # every reader of cover/covers masks them by presence at the same step)
                    new = torch.zeros_like(own).scatter_(
                        2, idx[:, None, :].expand(-1, self.horizon, -1),
                        new & valid[rows, u][:, None, :])
                covers += new.int() - own.int()
                cover[rows, u] = new
                planned[rows, u] = True
        finally:
            if keeps:
                self.leaf.tables = None
        return out

    def reachable(self, pos: torch.Tensor, w: dict[str, torch.Tensor],
                  step: float) -> torch.Tensor | None:
        """``[E, M, V]`` the vehicles each UABS's search can read: present at a step k of
        the horizon within k lattice steps plus :func:`axis_reach` of the UABS at ``pos
        [E, M, 2]``, per axis (a path is within k moves of it at step k), and, with a
        :attr:`leaf`, those its values read (its ``reads``). None: every vehicle (a
        leaf that does not say what it reads, or :attr:`cut` off)."""
        if not self.cut or (self.leaf is not None and not hasattr(self.leaf, "reads")):
            return None
        p = self.env.params
        fp = axis_reach(p.r_b, p.n_beams)
        keep = torch.zeros(*pos.shape[:2], w["veh"].shape[-1], dtype=torch.bool,
                           device=pos.device)
        for k in range(w["veh"].shape[0]):  # step k + 1
            keep |= within(w["veh"][k], pos, (k + 1) * step + fp) & w["present"][k + 1][:, None]
        if self.leaf is not None:
            keep |= self.leaf.reads(pos, w)
        return keep

    def search(self, pos: torch.Tensor, plan: torch.Tensor, others: torch.Tensor,
               oth_cover: torch.Tensor, w: dict[str, torch.Tensor],
               look: Lookup | None = None, u: torch.Tensor | None = None,
               priority: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Beam search of one UABS, ``u [E]``, at ``pos [E, 2]`` given the plans ``plan
        [E, M, H, 2]`` of ``others [E, M]`` and the vehicles they cover, ``oth_cover
        [E, H, V]``: ``(value [E, 4], path [E, 4, H, 2])``, the best value of steps 2..H
        (plus, with :attr:`leaf`, the learned value at the path's end) and its path
        (positions at steps 1..H) per first move. A first move with no path that keeps
        d_th gets a value just below the others'. ``look``: its footprint tests, made in
        advance (:class:`Lookup`; default: tested here). The vehicles are those of the
        world ``w`` (all, or the ones u can reach), ``priority [E, V]`` their current
        priorities (default: the env's, every vehicle)."""
        p, geo, h = self.env.params, self.env.math.geometry, self.horizon
        moves = self.env.math.moves
        e = pos.shape[0]
        first = pos[:, None, :] + moves  # [E, 4, 2]
        own = (footprint(first, w["veh"][0], p.r_b, p.n_beams) if look is None
               else look(first, 1))  # [E, 4, V]
        now = self.env.priority if priority is None else priority
        prio = next_priority(now[:, None, :], own | oth_cover[:, None, 0],
                             w["present"][1], w["present"][0], w["start"][0])
        beams = {"pos": first[:, :, None, :], "prio": prio[:, :, None, :],
                 "value": torch.zeros(e, 4, 1, device=pos.device),
                 "path": first[:, :, None, None, :].expand(e, 4, 1, h, 2).clone()}
        for k in range(1, h):
            beams = self.expand(beams, k, plan, others, oth_cover, w, geo, look)
        if self.leaf is None:
            value = beams["value"].amax(-1)  # [E, 4]
            path = beams["path"][:, :, 0]  # the best beam per first move (sorted)
        else:  # each beam's value plus the learned value where it ends; the best of them
            total = beams["value"] + self.leaf(beams["pos"], beams["prio"],
                                               plan[:, :, -1], u, w, pos)
            value, best = total.max(-1)  # [E, 4]
            path = beams["path"].gather(2, best[:, :, None, None, None].expand(
                -1, -1, 1, h, 2)).squeeze(2)
        dead = torch.isinf(value)
        floor = value.masked_fill(dead, math.inf).amin(-1, keepdim=True) - 1.0
        value = torch.where(dead, torch.where(dead.all(-1, keepdim=True), 0.0, floor), value)
        return value, path

    def expand(self, beams: dict[str, torch.Tensor], k: int, plan: torch.Tensor,
               others: torch.Tensor, oth_cover: torch.Tensor, w: dict[str, torch.Tensor],
               geo, look: Lookup | None = None) -> dict[str, torch.Tensor]:
        """One step (index ``k`` = step k+1) of the beam search: every beam × 4 moves,
        scored, one per position, the best ``beam`` kept per first move. Beam b's
        candidates are c = 4 b .. 4 b + 3: each earns the priorities ``beams["prio"]
        [E, a, b, V]`` under its footprints, and one kept inherits b's priorities and
        path."""
        p = self.env.params
        e, a, b = beams["value"].shape
        cand = (beams["pos"][:, :, :, None, :] + self.env.math.moves).reshape(e, a, b * 4, 2)
        ok = geo.boundary_mask(beams["pos"]).reshape(e, a, b * 4) & torch.isfinite(
            beams["value"]).repeat_interleave(4, -1)
        near = (cand[:, :, :, None, :] - plan[:, None, None, :, k, :]).norm(dim=-1)  # [E,a,c,M]
        ok &= ~((near < p.d_th) & others[:, None, None, :]).any(-1)
        veh, present = w["veh"][k], w["present"][k + 1]
        weight = torch.where(present & ~oth_cover[:, k], 1.0, 0.0)[:, None, None, :]
        parent = beams["prio"].clamp_min(1.0).mul_(weight)  # [E, a, b, V]
        # each sum is over whole priorities (integers): exact in any order
        if look is None:
            inside = footprint(cand, veh, p.r_b, p.n_beams)  # [E, a, c, V]
            gain = inside.reshape(e, a, b, 4, -1).to(parent.dtype) @ parent[..., None]
        else:
            where = look.index(cand, k + 1)  # [E, a, c]
            gain = look.gain(parent, where, k + 1)
        gain = gain.reshape(e, a, b * 4) * w["live"][k][:, None, None]
        value = (beams["value"].repeat_interleave(4, -1) + gain).masked_fill(~ok, -math.inf)
        # one beam per position: the best path that reaches it
        value, idx = value.sort(-1, descending=True)
        cand = cand.gather(2, idx[..., None].expand(-1, -1, -1, 2))
        key = torch.round(cand * 8.0).long()
        key = key[..., 0] * 1_000_003 + key[..., 1]
        same = key[..., :, None] == key[..., None, :]
        value = value.masked_fill(torch.tril(same, diagonal=-1).any(-1), -math.inf)
        value, top = value.topk(min(self.beam, value.shape[-1]), dim=-1)
        src = idx.gather(-1, top)  # the candidates kept, as indices before sorting
        new_pos = cand.gather(2, top[..., None].expand(-1, -1, -1, 2))
        served = (inside.gather(2, src[..., None].expand(-1, -1, -1, inside.shape[-1]))
                  if look is None else look.at(where.gather(-1, src), k + 1))
        served = served | oth_cover[:, None, None, k]
        src = torch.div(src, 4, rounding_mode="floor")  # their parents
        prio = next_priority(beams["prio"].gather(2, src[..., None].expand_as(served)),
                             served, present, w["present"][k], w["start"][k])
        path = beams["path"].gather(
            2, src[..., None, None].expand(-1, -1, -1, *beams["path"].shape[-2:]))
        path[:, :, :, k:] = new_pos[:, :, :, None, :]
        return {"pos": new_pos, "prio": prio, "value": value, "path": path}


class Lookup:
    """The footprint tests of one UABS at ``origin [E, 2]``, made in advance:
    ``table[n-1] [E, (n+1)², V]`` for the lattice offsets reachable in n moves
    (:func:`footprint_table`), the lattice step being ``step`` (a scalar tensor). The
    positions looked up must be exact lattice values (:func:`on_lattice`)."""

    def __init__(self, origin: torch.Tensor, step: torch.Tensor, table: list[torch.Tensor]):
        self.origin, self.step, self.table = origin, step, table
        self.weights: dict[int, torch.Tensor] = {}  # the tables as 0/1 floats, as needed

    def index(self, cand: torch.Tensor, n: int) -> torch.Tensor:
        """[E, *K] the table index of positions ``cand [E, *K, 2]`` n moves from
        ``origin``."""
        lead = (slice(None),) + (None,) * (cand.dim() - 2)
        return lattice_index(torch.round((cand - self.origin[lead]) / self.step).long(), n)

    def at(self, where: torch.Tensor, n: int) -> torch.Tensor:
        """[E, *K, V] the tests at table indices ``where [E, *K]`` (n moves)."""
        rows = torch.arange(where.shape[0], device=where.device)
        return self.table[n - 1][rows[(slice(None),) + (None,) * (where.dim() - 1)], where]

    def __call__(self, cand: torch.Tensor, n: int) -> torch.Tensor:
        """[E, *K, V] the tests of positions ``cand [E, *K, 2]`` n moves from ``origin``."""
        return self.at(self.index(cand, n), n)

    def gain(self, parent: torch.Tensor, where: torch.Tensor, n: int) -> torch.Tensor:
        """[E, A, B, 4] the sum of ``parent [E, A, B, V]`` over the vehicles under the
        footprints of each of its 4 children, at table indices ``where [E, A, 4 B]``:
        one product with the whole table (n moves), then the children's columns."""
        if n not in self.weights:
            self.weights[n] = self.table[n - 1].to(parent.dtype).transpose(1, 2)
        e, a, b = parent.shape[:3]
        g = parent.reshape(e, a * b, -1) @ self.weights[n]  # [E, A B, (n+1)²]
        return g.reshape(e, a, b, -1).gather(-1, where.reshape(e, a, b, 4))

    def path(self, path: torch.Tensor) -> torch.Tensor:
        """[E, H, V] the tests of ``path [E, H, 2]`` (step n: n moves from ``origin``),
        as :func:`footprint_path`."""
        return torch.stack([self(path[:, n - 1], n) for n in range(1, path.shape[1] + 1)], 1)


# ----------------------------------------------------------------------------- heuristics
class TargetScore(TensorDictModuleBase):
    """Scores each move by minus the distance from where it leads to the UABS's target
    (from :meth:`targets`), with the baselines' seeded tie-break: at its target a UABS
    steps off and back (there is no hover action)."""

    def __init__(self, env: UABSEnv, generator: torch.Generator):
        super().__init__()
        self.env, self.generator = env, generator
        self.in_keys, self.out_keys = [POSITION], [ACTION_VALUE]

    def targets(self, pos: torch.Tensor) -> torch.Tensor:
        """[E, M, 2] where each UABS should go."""
        raise NotImplementedError

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        pos = td.get(POSITION)
        goal = self.targets(pos)
        cand = pos[:, :, None, :] + self.env.math.moves  # [E, M, 4, 2]
        score = -(cand - goal[:, :, None, :]).norm(dim=-1)
        jitter = torch.rand(score.shape, generator=self.generator, device=score.device)
        td.set(ACTION_VALUE, score + JITTER * jitter)
        return td


def weighted_kmeans(x: torch.Tensor, weight: torch.Tensor, centres: torch.Tensor,
                    iters: int = 10) -> torch.Tensor:
    """Lloyd's k-means of points ``x [E, V, 2]`` with weights ``weight [E, V]`` (0 = no
    point) from ``centres [E, K, 2]``: the final centres ``[E, K, 2]``. A cluster that
    loses all its points keeps its centre."""
    for _ in range(iters):
        near = torch.cdist(x, centres).argmin(-1)  # [E, V]
        onehot = torch.nn.functional.one_hot(near, centres.shape[1]).float()
        onehot = onehot * weight[..., None]  # [E, V, K]
        mass = onehot.sum(1)  # [E, K]
        mean = onehot.transpose(1, 2) @ x / mass.clamp_min(1e-9)[..., None]
        centres = torch.where(mass[..., None] > 0, mean, centres)
    return centres


class ClusterScore(TargetScore):
    """k-means heuristic: a k-means (k = M) of the present vehicles' current positions,
    weighted by priority (at least 1), started from the UABS positions so that cluster u
    stays UABS u's; each UABS flies towards its cluster's weighted centroid."""

    def __init__(self, env: UABSEnv, generator: torch.Generator, iters: int = 10):
        super().__init__(env, generator)
        self.iters = iters

    def targets(self, pos: torch.Tensor) -> torch.Tensor:
        veh, present = self.env.vehicles(0)  # [E, 2, V], [E, V]
        weight = torch.where(present, self.env.priority.clamp_min(1.0), 0.0)
        x = torch.where(present[..., None], veh.transpose(1, 2), 0.0)  # absent: no point
        return weighted_kmeans(x, weight, pos, self.iters)


def nearest_assignment(pos: torch.Tensor, sites: torch.Tensor) -> torch.Tensor:
    """[E, M, 2]: a site for each UABS, ``sites [M, 2]`` matched greedily (the closest
    remaining UABS-site pair first), so each site has one UABS."""
    e, m = pos.shape[:2]
    d = torch.cdist(pos, sites.expand(e, -1, -1))  # [E, M, S]
    rows = torch.arange(e, device=pos.device)
    goal = torch.empty_like(pos)
    for _ in range(m):
        flat = d.flatten(1).argmin(-1)
        u, s = flat // d.shape[2], flat % d.shape[2]
        goal[rows, u] = sites[s]
        d[rows, u, :] = math.inf
        d[rows, :, s] = math.inf
    return goal


class SiteScore(TargetScore):
    """Junction heuristic: the UABS hover over fixed sites ``sites [M, 2]`` (the busiest
    junctions, :func:`busiest_sites`), each flying to the site the greedy matching of
    positions to sites gives it."""

    def __init__(self, env: UABSEnv, generator: torch.Generator, sites: torch.Tensor):
        super().__init__(env, generator)
        self.sites = sites.to(env.device)

    def targets(self, pos: torch.Tensor) -> torch.Tensor:
        return nearest_assignment(pos, self.sites)


def busiest_sites(candidates: torch.Tensor, veh: torch.Tensor, present: torch.Tensor,
                  m: int, r_b: float, n_beams: int, spacing: float) -> torch.Tensor:
    """[M, 2] the ``m`` candidate sites (``[S, 2]``) under whose footprints the most
    vehicles pass (mean over the steps of ``veh [N, 2, V]``, ``present [N, V]``), chosen
    busiest first among those at least ``spacing`` from the sites already chosen (the
    spacing halved until m fit, down to none)."""
    from uabs_rl.config import ConfigError

    if candidates.shape[0] < m:
        raise ConfigError(f"the junctions heuristic needs at least as many junctions inside "
                          f"the area as UABS: {candidates.shape[0]} for scenario.n_uabs={m}; "
                          f"compare with another baseline (kmeans, greedy) here.")
    inside = footprint(candidates[None].expand(veh.shape[0], -1, -1), veh, r_b, n_beams)
    busy = (inside & present[:, None, :]).float().sum(-1).mean(0)  # [S]
    order = busy.argsort(descending=True)
    while True:
        chosen: list[int] = []
        for i in order.tolist():
            pt = candidates[i]
            if all(float((pt - candidates[j]).norm()) >= spacing for j in chosen):
                chosen.append(i)
            if len(chosen) == m:
                return candidates[chosen]
        spacing = spacing / 2.0 if spacing > 1e-3 else 0.0  # at 0 every candidate fits


def junctions(scenario, geometry) -> torch.Tensor:
    """[S, 2] the street network's junctions inside the area, area-relative and moved to
    the nearest lattice point (where a UABS can be); every lattice point for a scenario
    given as a .sumocfg (no network file to read)."""
    from uabs_rl.traces.inputs import read_net, scenario_inputs

    lo, n, step = geometry.lattice_lo, geometry.lattice_n, geometry.p.step_m
    net = scenario_inputs(scenario)["net_file"]
    if net is None:
        ij = torch.cartesian_prod(torch.arange(int(n[0])), torch.arange(int(n[1]))).float()
    else:
        a = scenario.area
        xy = torch.tensor([node.getCoord()[:2] for node in read_net(net).getNodes()],
                          dtype=torch.float32) - torch.tensor([a.x_min, a.y_min])
        inside = ((xy >= 0) & (xy <= geometry.area.cpu())).all(-1)
        ij = torch.round((xy[inside] - lo.cpu()) / step)
        ij = torch.minimum(ij.clamp_min(0), (n - 1).cpu().float()).unique(dim=0)
    return geometry.lattice_point(ij[:, 0].to(lo.device), ij[:, 1].to(lo.device))


def junction_sites(cfg, env: UABSEnv) -> torch.Tensor:
    """[M, 2] the busiest junctions of ``cfg``'s scenario for ``env``'s fleet, busiest on
    the validation traces (``traces.eval``, never the evaluated ones), at least
    d_th + v·δt apart (so that, hovering a step off, they keep d_th) where M such
    sites exist."""
    from uabs_rl.traces.build import get_traces

    p = env.params
    geo = env.math.geometry
    tr = get_traces(cfg.scenario, cfg.traces, "eval", verbose=False)
    veh = tr.positions.transpose(-1, -2).reshape(-1, 2, tr.positions.shape[-2])
    present = tr.present.reshape(-1, tr.present.shape[-1])
    cand = junctions(cfg.scenario, geo).cpu()
    return busiest_sites(cand, veh.float(), present, p.n_uabs, p.r_b, p.n_beams,
                         p.d_th + p.step_m)


def gap_share(learned: list[float], greedy: list[float], planner: list[float],
              n_boot: int = 10_000, seed: int = 0) -> dict[str, float]:
    """The share of the greedy-to-planner gap a policy closes, (learned − greedy) /
    (planner − greedy), from per-window values of the same windows, with a 95 %
    percentile bootstrap CI (the windows resampled together for all three):
    ``{share, ci_low, ci_high, n}``."""
    import numpy as np

    a, g, p = (np.asarray(x, dtype=float) for x in (learned, greedy, planner))
    if not a.shape == g.shape == p.shape:
        raise ValueError(f"per-window values of unequal shapes {a.shape}, {g.shape}, {p.shape}")
    kept = ~(np.isnan(a) | np.isnan(g) | np.isnan(p))  # windows without a vehicle: left out
    a, g, p = a[kept], g[kept], p[kept]
    nan = float("nan")
    if a.size == 0 or (p - g).mean() <= 0:  # no gap to share: the planner is not above greedy
        return {"share": nan, "ci_low": nan, "ci_high": nan, "n": int(a.size)}
    idx = np.random.default_rng(seed).integers(0, a.size, size=(n_boot, a.size))
    num, den = (a - g)[idx].mean(-1), (p - g)[idx].mean(-1)
    boots = num[den != 0] / den[den != 0]  # resamples without a gap left out
    lo, hi = np.quantile(boots, [0.025, 0.975])
    return {"share": float((a - g).mean() / (p - g).mean()), "ci_low": float(lo),
            "ci_high": float(hi), "n": int(a.size)}


def scale_to_gap(diff: float, ci_low: float, ci_high: float, gap: float) -> dict[str, float]:
    """A difference learned − greedy with its interval as shares of the greedy-to-planner
    ``gap`` (``share``, ``ci_low``, ``ci_high``); NaN where the planner is not above
    greedy (no gap to share), as :func:`gap_share`."""
    if gap <= 0:
        nan = float("nan")
        return {"share": nan, "ci_low": nan, "ci_high": nan}
    return {"share": diff / gap, "ci_low": ci_low / gap, "ci_high": ci_high / gap}
