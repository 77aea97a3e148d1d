"""Service bookkeeping (docs/model.md §4): which trace rows an env replays, priorities, per-beam
priority sums, service windows and P_g. Plain functions on batched tensors; the state
``st`` is the env's dict of ``[E, ...]`` tensors, updated in place."""

from __future__ import annotations

import torch

from uabs_rl.env.channel import beam_grid_side, footprint_inside


def vehicles_at(st: dict[str, torch.Tensor], veh_pos: torch.Tensor,
                veh_present: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Vehicle positions [E, 2, V] (planar) and presence [E, V] at each env's step."""
    s, steps = veh_pos.shape[:2]
    # a window holds T + 1 steps; an env stepped past its end without a reset (TorchRL
    # expects a reset) sees its vehicles frozen at the window's last step
    t = st["t"].clamp_max(steps - 1 - st["start"])
    row = st["sim"] * steps + st["start"] + t  # flat row: index_select beats fancy indexing
    return (veh_pos.view(s * steps, *veh_pos.shape[2:]).index_select(0, row),
            veh_present.view(s * steps, -1).index_select(0, row))


def extrapolated(st: dict[str, torch.Tensor], veh: torch.Tensor, present: torch.Tensor,
                 veh_pos: torch.Tensor, veh_present: torch.Tensor,
                 steps: int = 1) -> list[torch.Tensor]:
    """Vehicle positions [E, 2, V] k = 1 .. ``steps`` steps ahead of ``veh`` (those at
    step ``st["t"]``), extrapolated from their last move: x_t + k (x_t − x_{t−1}); a
    vehicle not present at t − 1 (or at the window's first step) stays where it is. Past
    positions only. k = 1 is computed as 2 x_t − x_{t−1}, k > 1 as the mpc's
    constant-velocity predictor computes it
    (:class:`~uabs_rl.evaluation.predict.ConstantVelocity`)."""
    prev, prev_present = vehicles_at(dict(st, t=(st["t"] - 1).clamp_min(0)), veh_pos,
                                     veh_present)
    moving = (present & prev_present)[:, None, :]
    out = [torch.where(moving, 2 * veh - prev, veh)]
    if steps > 1:
        v = torch.where(moving, veh - prev, 0.0)
        out += [veh + k * v for k in range(2, steps + 1)]
    return out


def beam_sums(inside: torch.Tensor, beam: torch.Tensor, priority: torch.Tensor,
              n_beams: int) -> torch.Tensor:
    """b: [E, M, B] sum of the priorities of the vehicles under each beam
    (``beam`` indexes all agents' beams at once, as ``LinkModel.links`` returns it)."""
    e, m, v = inside.shape
    idx = beam.reshape(e, m * v)
    src = torch.where(inside, priority[:, None, :], 0.0).reshape(e, m * v)
    b = torch.zeros(e, m * n_beams, device=priority.device, dtype=priority.dtype)
    return b.scatter_add_(1, idx, src).view(e, m, n_beams)


def update_service(st: dict[str, torch.Tensor], served: torch.Tensor, present: torch.Tensor,
                   window_steps: int) -> None:
    """Priorities, per-window served counts and the P_g tallies (docs/model.md §4), in place.
    ``st["t"]`` is the step the flags belong to."""
    n = window_steps
    t = st["t"]
    start = (t % n == 0)[:, None]  # a window starts: p = 1, counts restart
    arrived = present & ~st["prev_present"]  # a vehicle (re)appears: p = 1
    served_f = served.float()
    p_new = (st["priority"] + served_f).masked_fill_(start | arrived, 1.0)
    st["priority"] = p_new.masked_fill_(~present, 0.0)
    count = served.long()
    st["served_count"] = torch.where(start, count, st["served_count"] + count)
    st["window_full"] = torch.where(start, present, st["window_full"] & present)
    st["prev_present"] = present
    ended = (st["window_full"] & (t % n == n - 1)[:, None]).float()  # [E, V]
    st["n_windows"] += ended
    st["ns_hist"].scatter_add_(2, st["served_count"][..., None], ended[..., None])


def pg_curve(n_windows: torch.Tensor, ns_hist: torch.Tensor) -> torch.Tensor:
    """P_g(N̂_s) for N̂_s = 1..N, [E, N]: mean over GUEs with a counted window of the
    share of their windows with N_s ≥ N̂_s.

    The sums run in float64 and the result is rounded once to the tallies' dtype: how a
    kernel orders a float32 sum (eager or compiled, the shape's blocking) would show in
    the last bit, and the compiled and eager evaluations gave figures 1e-7 apart; a
    float64 sum's order changes the rounded result only where the exact value lies
    within ~1e-16 of a float32 rounding boundary."""
    counted = n_windows > 0
    n = n_windows.double()
    inv = torch.where(counted, 1.0 / n.clamp_min(1.0), torch.zeros_like(n))
    per_ns = torch.bmm(inv[:, None, :], ns_hist.double()).squeeze(1)  # [E, N+1] Σ_g share(N_s = j)
    at_least = per_ns.flip(-1).cumsum(-1).flip(-1)[:, 1:]  # Σ_g share(N_s ≥ k), k = 1..N
    return (at_least / counted.sum(-1, keepdim=True).clamp_min(1)).to(n_windows.dtype)


# elements of one [E, chunk, V] block of :func:`move_scores` (4 MiB per float32 block)
SCORE_BLOCK = 1 << 20


def move_scores(cand: torch.Tensor, veh: torch.Tensor, present: torch.Tensor,
                priority: torch.Tensor, r_b: float, n_beams: int) -> torch.Tensor:
    """[E, M, K] priority under the footprints of a UABS at each candidate position
    ``cand [E, M, K, 2]``, for vehicles ``veh [E, 2, V]`` with ``priority [E, V]`` (every
    present vehicle counts at least 1, so a fresh one is worth approaching).

    Only the vehicles near a UABS's candidates can lie under their footprints (within
    k·r_b of a candidate on each axis, for a k x k beam grid): where a street network
    spreads its traffic over a district, each UABS's K candidates are tested against
    its own near vehicles only (:func:`near_vehicles`), and against all V where most are
    near anyway (a small grid). The tests run in blocks of at most :data:`SCORE_BLOCK`
    elements, so the memory stays bounded whatever the fleet and the traffic (a district
    at M = 25 with 700 vehicles and a 5 x 5 map scores 440 000 pairs per window; the
    choice of near vehicles holds E x M x V flags, as the env's links do). Each
    candidate's sum is over whole priorities (integers), so it is exact in float32: the
    blocks and the choice of vehicles change no digit."""
    e, v = veh.shape[0], veh.shape[-1]
    weight = torch.where(present, priority.clamp_min(1.0), 0.0)  # [E, V]
    groups = cand.reshape(e, -1, cand.shape[-2], 2)  # [E, G, K, 2]: one UABS's candidates
    near = near_vehicles(groups, veh, weight, beam_grid_side(n_beams) * r_b)
    if near is None:  # most vehicles are near: every candidate against all V
        flat = cand.reshape(e, -1, 2)
        step = max(1, SCORE_BLOCK // max(1, e * v))
        out = []
        for c in flat.split(step, dim=1):
            dx = veh[:, None, 0, :] - c[..., 0:1]  # [E, chunk, V]
            dy = veh[:, None, 1, :] - c[..., 1:2]
            out.append((footprint_inside(dx, dy, r_b, n_beams) * weight[:, None, :]).sum(-1))
        return torch.cat(out, dim=1).reshape(cand.shape[:-1])
    vx, vy, w = near  # [E, G, n] each: the near vehicles of each group, weight 0 as padding
    k, n = groups.shape[2], vx.shape[-1]
    step = max(1, SCORE_BLOCK // max(1, e * k * n))
    out = []
    for g0 in range(0, groups.shape[1], step):
        c = groups[:, g0:g0 + step]  # [E, chunk, K, 2]
        dx = vx[:, g0:g0 + step, None, :] - c[..., 0:1]  # [E, chunk, K, n]
        dy = vy[:, g0:g0 + step, None, :] - c[..., 1:2]
        inside = footprint_inside(dx, dy, r_b, n_beams)
        out.append((inside * w[:, g0:g0 + step, None, :]).sum(-1))
    return torch.cat(out, dim=1).reshape(cand.shape[:-1])


def near_vehicles(groups: torch.Tensor, veh: torch.Tensor, weight: torch.Tensor,
                  reach: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """The vehicles that may lie under a footprint of some candidate of each group
    ``groups [E, G, K, 2]`` (within ``reach`` of the group's bounding box on each axis,
    plus a metre against rounding), with weight ``weight [E, V]`` > 0: ``(x, y, weight)``,
    each ``[E, G, n]`` with n the largest such count (:func:`near_sets`: the shorter lists
    padded with weight 0); None when n exceeds half of V (no gain in choosing) and inside
    a compiled program (n would be a shape read from the data: a recompile per value)."""
    if veh.shape[-1] == 0 or torch.compiler.is_compiling():  # its count n sets a shape:
        return None  # a compiled step (train.compile) scores against all V, the same sums
    reach = reach + 1.0
    lo, hi = groups.amin(2) - reach, groups.amax(2) + reach  # [E, G, 2]
    x, y = veh[:, None, 0, :], veh[:, None, 1, :]  # [E, 1, V]
    near = ((x >= lo[..., 0:1]) & (x <= hi[..., 0:1]) & (y >= lo[..., 1:2])
            & (y <= hi[..., 1:2]) & (weight[:, None, :] > 0))  # [E, G, V]
    sets = near_sets(near, most=0.5)
    if sets is None:
        return None
    sel, valid = sets  # [E, G, n]
    flat = sel.flatten(1)

    def pick(t: torch.Tensor) -> torch.Tensor:  # [E, V] -> [E, G, n]
        return t.gather(1, flat).view(sel.shape)

    return pick(veh[:, 0, :]), pick(veh[:, 1, :]), pick(weight) * valid


def near_sets(keep: torch.Tensor, most: float = 1.0
              ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The vehicles ``keep [..., V]`` marks for each UABS (``[E, M, V]``), window
    (``[E, V]``) or group of candidates (``[E, G, V]``), as indices ``sel [..., K]`` (in
    ascending order, each set padded to the largest, K, with vehicles it does not keep)
    and ``valid [..., K]`` (False on the padding); None when some set keeps every vehicle
    (nothing to cut) or more than the share ``most`` of them (``most = 0.5``: where the
    sets hold most vehicles anyway, choosing them costs more than it saves). The one
    selection of the env's move scores (:func:`near_vehicles`), the planner's cut to the
    vehicles each UABS can reach and the leaf values' local maps."""
    v = keep.shape[-1]
    k = max(1, int(keep.sum(-1).amax())) if keep.numel() else v
    if k >= v or k > most * v:
        return None
    # the k largest of distinct keys, in order: the kept vehicles by ascending index, then
    # those not kept (the order of a stable sort of the flags, 2-4x faster where k << V)
    order = keep.to(torch.int32) * v - torch.arange(v, dtype=torch.int32, device=keep.device)
    sel = order.topk(k, dim=-1).indices
    return sel, keep.gather(-1, sel)
