"""Learned leaf values for the deployable planner: the mpc's paths end in a value.

``uabs-eval RUN --policy leaf --hybrid-weight λ`` flies the mpc
(:class:`~uabs_rl.evaluation.planner.PlannerScore` with the mpc's predictor, horizon and
visibility) whose every path is scored

    Σ_{k=1..H} (priority the path covers at step k) + λ · V(o_{t+H}),

where o_{t+H} is the observation the UABS would have at the path's end (its position
after H moves, at step t + H, over the predicted vehicles with the priorities simulated
along the path, the other UABS where their plans put them) and V(o) = max_a Q(o, a) over
the moves legal at the area's edges, the run's learned network. So the search covers
the H steps it can predict and the learned values the steps after it (γ = 0.8: about
five), which the mpc leaves out; :mod:`uabs_rl.evaluation.hybrid` adds Q at the first
move instead. A path that ends at or past the episode's end gets no value (the episode
is over there). λ = 0 is the mpc, action for action.

Two limits of the search carry over: only the paths the beam search keeps at its last
step (``beam`` per first move, chosen by their covered priority alone) get a value, so a
path pruned before it is never valued; and "where their plans put them" holds for the
UABS planned before this one: in the first pass the others are at their current
positions, and with ``coordinated=False`` every other UABS is.

The observation at a path's end is the egocentric one (docs/model.md §5; a network of
``obs=egocentric``, as ``experiment=generalist`` trains it), computed by the env's own
functions: the beam sums, the local map (and its motion half at the vehicles'
positions extrapolated one step from their last predicted move), the nearest other
UABS and the edges. At the current state it is the env's observation bit for bit
(``tests/test_leaf.py``). The fleet frame's observation (every UABS's position, the
3DQN of ``experiment=lookahead_motion``) is not supported: a ConfigError says so.
"""

from __future__ import annotations

import torch
from torch import nn

from uabs_rl.config import ConfigError
from uabs_rl.env import observe
from uabs_rl.env.channel import beam_cells, footprint_inside
from uabs_rl.env.service import beam_sums, move_scores, near_sets
from uabs_rl.env.uabs_env import UABSEnv
from uabs_rl.evaluation.planner import axis_reach, on_lattice, within

LEAF = "leaf"  # --policy leaf


def near_vehicles(origin: torch.Tensor, veh: torch.Tensor, present: torch.Tensor,
                  reach: float) -> tuple[torch.Tensor | None, torch.Tensor, torch.Tensor]:
    """The present vehicles within ``reach`` metres of ``origin [E, 2]`` on each axis:
    ``(sel, veh, present)``, their indices ``sel [E, K]`` (None: every vehicle, nothing
    cut) and ``veh [E, 2, V]``, ``present [E, V]`` cut to them, each window's padded to
    the most any window keeps (absent there; :func:`cut_priority` cuts the priorities
    alike). On a city the local maps and beam sums near one UABS need a few hundred of
    its thousands of vehicles; those left out are under no footprint within reach, and
    every sum is of whole priorities, so the sums over the rest are the same numbers."""
    sets = near_sets(present & within(veh, origin[:, None], reach)[:, 0])  # over [E, V]
    if sets is None:
        return None, veh, present
    sel, valid = sets
    return sel, veh.gather(2, sel[:, None, :].expand(-1, 2, -1)), valid


def cut_priority(priority: torch.Tensor, sel: torch.Tensor | None) -> torch.Tensor:
    """``priority [E, N, V]`` at the vehicles ``sel [E, K]`` (all where None)."""
    return priority if sel is None else priority.gather(
        2, sel[:, None, :].expand(-1, priority.shape[1], -1))


class LeafValue:
    """λ · V at the end of each path of one UABS (module docstring). ``env``: the base
    (untransformed) env the planner plans in; ``qnet``: the run's network, observation to
    Q-values ``[..., 4]``."""

    def __init__(self, env: UABSEnv, qnet: nn.Module, weight: float):
        p = env.params
        if not p.egocentric:
            raise ConfigError("leaf values need a network of the egocentric observation "
                              "(obs=egocentric, as experiment=generalist trains it); this "
                              "run's observation is the fleet frame's, whose size is tied "
                              "to the fleet: use --policy hybrid for it.")
        if not weight >= 0:
            raise ValueError(f"the leaf values' weight must be >= 0, got {weight}")
        self.env, self.qnet, self.weight = env, qnet, float(weight)
        # the local maps' tables of footprint tests, per UABS and world, kept through one
        # planning step (its rounds search each UABS from the same position in the same
        # world): None outside a step (PlannerScore.future opens and closes it)
        self.tables: dict | None = None

    # ------------------------------------------------------------------ the observation
    def observation(self, pos: torch.Tensor, u: torch.Tensor, fleet: torch.Tensor,
                    t: torch.Tensor, veh: torch.Tensor, present: torch.Tensor,
                    prev: torch.Tensor, prev_present: torch.Tensor,
                    priority: torch.Tensor, origin: torch.Tensor | None = None,
                    reach: int = 0, key: tuple | None = None) -> torch.Tensor:
        """[E, N, obs_dim]: the egocentric observation of UABS ``u [E]`` at ``pos [E, N,
        2]`` (N candidate positions), the others at ``fleet [E, M, 2]`` (u's own entry
        is replaced), at step ``t [E]``, with the vehicles at ``veh [E, 2, V]`` /
        ``present [E, V]``, one step before at ``prev`` / ``prev_present`` (the motion
        half of the map) and the priorities ``priority [E, N, V]`` of each candidate's
        path. With ``origin [E, 2]``, every candidate within ``reach`` lattice steps of
        it (per axis) and every such point exact (:func:`on_lattice`), the local maps
        are read from one table of footprint tests (:meth:`map_scores`: the same
        numbers), kept under ``key`` while :attr:`tables` is open."""
        env, p = self.env, self.env.params
        e, n = pos.shape[:2]
        radius = reach + p.map_radius
        table = origin is not None and on_lattice(origin, p.step_m, radius)
        flat = pos.reshape(e * n, 1, 2)

        def per_candidate(veh, present, priority):  # [E·N, 2, V], [E·N, V], [E·N, V]
            v = veh.shape[-1]
            return (veh[:, None].expand(e, n, 2, v).reshape(e * n, 2, v),
                    present[:, None].expand(e, n, v).reshape(e * n, v),
                    priority.reshape(e * n, v))

        # beam sums, as the env's links compute them for one UABS at each candidate (from
        # a table: over the vehicles a footprint within reach of its origin can cover)
        sel, near, pres = (near_vehicles(origin, veh, present,
                                         reach * p.step_m + self.footprint_reach())
                           if table else (None, veh, present))
        vehs, pres, prio = per_candidate(near, pres, cut_priority(priority, sel))
        gx, gy = env.math.links.grid_coordinates(flat, vehs)
        inside, beam = beam_cells(gx, gy, env.math.links.beam_k)
        b = beam_sums(inside & pres[:, None, :], beam, prio, p.n_beams)  # [E·N, 1, B]
        worlds = self.worlds(veh, present, prev, prev_present)
        if table:  # map_scores keeps the vehicles near the table itself, world by world
            look = torch.cat([self.map_scores(pos, origin, radius, x, present, priority,
                                              key=None if key is None else (key, i, radius))
                              for i, x in enumerate(worlds)], dim=-1)
        else:
            cand = flat[:, :, None, :] + env.math.look_offsets  # [E·N, 1, C, 2]
            look = torch.cat([move_scores(cand, *per_candidate(x, present, priority),
                                          p.r_b, p.n_beams) for x in worlds], dim=-1)
        # the nearest others, with u at each candidate (u's row only)
        rows = torch.arange(e, device=pos.device)
        m = fleet.shape[1]
        full = fleet[:, None].expand(e, n, m, 2).clone()
        full[rows, :, u] = pos
        near = observe.nearest_neighbours(full.reshape(e * n, m, 2), p.neighbours,
                                          p.neighbour_range * p.step_m,
                                          of=u.repeat_interleave(n)[:, None])
        near = near.view(e, n, -1)  # [E, N, 3K]
        bounds = env.state.get("bounds")
        area = env.math.geometry.area if bounds is None else bounds[:, None, :]
        return observe.egocentric_observation(
            pos, t, b.view(e, n, -1), look.view(e, n, -1), area, p.episode_steps, p.obs_scale,
            p.neighbours, p.neighbour_range * p.step_m, p.edge_range * p.step_m, near)

    def map_scores(self, pos: torch.Tensor, origin: torch.Tensor, radius: int,
                   veh: torch.Tensor, present: torch.Tensor,
                   priority: torch.Tensor, key: tuple | None = None) -> torch.Tensor:
        """``[E, N, C]`` the local maps of candidates ``pos [E, N, 2]`` (what
        :func:`~uabs_rl.env.service.move_scores` gives at ``pos + look_offsets``), from
        one table of footprint tests for the lattice points within ``radius`` steps of
        ``origin [E, 2]`` (:meth:`map_table`), the table's sums weighted by each
        candidate's priorities in one product, and each map point read from there. Every
        point is a lattice value of ``origin`` (the caller checks :func:`on_lattice`),
        tested as move_scores tests it, and every sum is of whole priorities, so the
        numbers are move_scores' own. With ``key`` (a UABS's and a world's) inside a
        planning step (:attr:`tables` open), the table is made once and read again by
        the next call with that key: the second round's search of that UABS, from the
        same origin in the same world."""
        p, env = self.env.params, self.env
        kept = None if key is None or self.tables is None else self.tables.get(key)
        if kept is None:
            kept = self.map_table(origin, radius, veh, present)
            if key is not None and self.tables is not None:
                self.tables[key] = kept
        sel, present, table = kept
        side = 2 * radius + 1
        weight = torch.where(present[:, None, :], cut_priority(priority, sel).clamp_min(1.0),
                             0.0)  # [E, N, V]
        sums = weight @ table[..., :-1]  # [E, N, side²]
        cell = torch.round((pos[:, :, None, :] - origin[:, None, None, :]
                            + env.math.look_offsets) / p.step_m).long() + radius  # [E, N, C, 2]
        if cell.numel() and not bool(((cell >= 0) & (cell < side)).all()):
            raise ValueError(f"a candidate lies more than {radius - p.map_radius} lattice "
                             f"steps from the table's origin")
        return sums.gather(2, cell[..., 1] * side + cell[..., 0])

    def map_table(self, origin: torch.Tensor, radius: int, veh: torch.Tensor,
                  present: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor,
                                                  torch.Tensor]:
        """The footprint tests of :meth:`map_scores`: ``(sel, present, table)``, the
        vehicles within reach of the lattice points within ``radius`` steps of ``origin
        [E, 2]`` (:func:`near_vehicles`, the present ones: indices ``sel [E, K]``, None
        for all), their presence ``[E, K]`` and ``table [E, K, side² + 1]``, 1 where a
        footprint of that point covers the vehicle (the last column: off the table).
        Each vehicle is tested against the points near it only (within a footprint's
        reach, k·r_b for a k x k beam grid, on each axis; none farther can cover it)."""
        p = self.env.params
        sel, veh, present = near_vehicles(origin, veh, present,
                                          radius * p.step_m + self.footprint_reach())
        near = int(self.footprint_reach() / p.step_m + 0.5)
        e, v = veh.shape[0], veh.shape[-1]
        side = 2 * radius + 1
        # the lattice columns and rows (steps from origin) near each vehicle
        k = torch.arange(-near, near + 1, device=origin.device, dtype=origin.dtype)
        col = torch.round((veh[:, 0, :] - origin[:, 0:1]) / p.step_m)[..., None] + k  # [E, V, K]
        row = torch.round((veh[:, 1, :] - origin[:, 1:2]) / p.step_m)[..., None] + k
        dx = veh[:, 0, :, None] - (origin[:, 0, None, None] + col * p.step_m)  # [E, V, K]
        dy = veh[:, 1, :, None] - (origin[:, 1, None, None] + row * p.step_m)
        inside = footprint_inside(dx[:, :, None, :].expand(-1, -1, k.numel(), -1),
                                  dy[:, :, :, None].expand(-1, -1, -1, k.numel()),
                                  p.r_b, p.n_beams)  # [E, V, K rows, K cols]
        ok = ((row >= -radius) & (row <= radius))[..., :, None] & (
            (col >= -radius) & (col <= radius))[..., None, :]
        idx = ((row + radius)[..., :, None] * side + (col + radius)[..., None, :]).long()
        table = torch.zeros(e, v, side * side + 1, device=origin.device)
        table.scatter_(2, idx.masked_fill(~ok, side * side).flatten(2),
                       (inside & ok).to(table.dtype).flatten(2))
        return sel, present, table

    def footprint_reach(self) -> float:
        """Metres (per axis) beyond which no footprint reaches a vehicle
        (:func:`~uabs_rl.evaluation.planner.axis_reach`)."""
        p = self.env.params
        return axis_reach(p.r_b, p.n_beams)

    def horizon_worlds(self, w: dict[str, torch.Tensor]) -> tuple[torch.Tensor, ...]:
        """The vehicles the value at a path's end sees, in the planner's world ``w``:
        at the horizon ``veh [E, 2, V]`` / ``present [E, V]`` and one step before
        ``prev`` / ``prev_present`` (``w["now"]``, else the env's, at H = 1)."""
        h = w["veh"].shape[0]
        veh, present = w["veh"][h - 1], w["present"][h]
        if h > 1:
            prev, prev_present = w["veh"][h - 2], w["present"][h - 1]
        else:
            prev = w["now"] if "now" in w else self.env.vehicles(0)[0]
            prev_present = w["present"][0]
        return veh, present, prev, prev_present

    def worlds(self, veh: torch.Tensor, present: torch.Tensor, prev: torch.Tensor,
               prev_present: torch.Tensor) -> list[torch.Tensor]:
        """Where the local map looks for the vehicles ``veh [E, 2, V]`` (present ``[E,
        V]``, one step before at ``prev`` / ``prev_present``): at them, and with the
        motion half, at them extrapolated one step (those present at both)."""
        out = [veh]
        if self.env.params.motion_obs:
            out.append(torch.where((present & prev_present)[:, None, :], 2 * veh - prev, veh))
        return out

    def reads(self, origin: torch.Tensor, w: dict[str, torch.Tensor]) -> torch.Tensor:
        """``[E, M, V]`` the vehicles the values of the paths of a UABS at ``origin [E,
        M, 2]`` can read (a superset): present at the horizon H, at or extrapolated one
        step from a point within H + map_radius lattice steps plus a footprint's reach
        of the origin, per axis (the ends lie within H moves, their local maps
        map_radius steps further). The planner searches over these and its own."""
        p = self.env.params
        veh, present, prev, prev_present = self.horizon_worlds(w)
        reach = (w["veh"].shape[0] + p.map_radius) * p.step_m + self.footprint_reach()
        near = torch.zeros(*origin.shape[:2], veh.shape[-1], dtype=torch.bool,
                           device=origin.device)
        for x in self.worlds(veh, present, prev, prev_present):
            near |= within(x, origin, reach)
        return near & present[:, None, :]

    # ------------------------------------------------------------------ the value
    @torch.no_grad()
    def __call__(self, leaf: torch.Tensor, priority: torch.Tensor, fleet: torch.Tensor,
                 u: torch.Tensor, w: dict[str, torch.Tensor],
                 origin: torch.Tensor) -> torch.Tensor:
        """``[E, A, B]`` λ · V at the ends ``leaf [E, A, B, 2]`` of the beams of UABS ``u
        [E]`` (A first moves, B beams each) from ``origin [E, 2]`` (u's position now),
        their priorities ``priority [E, A, B, V]``, the fleet at the horizon ``fleet [E,
        M, 2]``, in the planner's world ``w``
        (:meth:`~uabs_rl.evaluation.planner.PlannerScore.world`)."""
        env, p = self.env, self.env.params
        e, a, b = leaf.shape[:3]
        h = w["veh"].shape[0]
        t = env.state["t"] + h
        veh, present, prev, prev_present = self.horizon_worlds(w)
        pos = leaf.reshape(e, a * b, 2)
        obs = self.observation(pos, u, fleet, t, veh, present, prev, prev_present,
                               priority.reshape(e, a * b, -1), origin, h,
                               key=tuple(u.tolist()))  # u's tables, kept for its next round
        q = self.qnet(obs)  # [E, A·B, 4]
        legal = env.math.geometry.boundary_mask(pos, env.state.get("bounds"))
        value = q.masked_fill(~legal, -torch.inf).amax(-1).clamp_min(-1e30)
        value = torch.where((t < p.episode_steps)[:, None], value, 0.0)
        return (self.weight * value).view(e, a, b)
