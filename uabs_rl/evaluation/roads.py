"""The road-aware predictor: each vehicle moves on along its lane of the SUMO network and
the straightest successor lanes after it, at its current speed.

What it knows is what a controller with the city's map and the vehicles' V2X awareness
messages knows: the network (lanes' centre lines and their connections) and every
vehicle's current and previous position. Not its route, its lane, its signal or the
lights ahead: the lane is found from the position and the heading, and at each junction
the prediction goes straight on (the connection whose outgoing lane continues the
incoming one's direction best), the most common move and the only one the past motion
says nothing against.

:class:`RoadNetwork` holds the network area-relative (the traces' frame: SUMO's
coordinates minus ``scenario.area.x_min``, ``y_min``):

* every lane's centre line as segments (start, unit direction, length, offset along the
  lane), indexed by a grid of ``CELL_M`` cells, each cell listing the segments within
  ``SNAP_M`` of it;
* for every lane its *chain*: the lane's points followed by those of its straightest
  successors (internal junction lanes included, as SUMO drives them) up to ``reach_m``
  metres, with the cumulative length at each point.

:class:`RoadAware` (``--predictor road``) snaps each vehicle present now and one step
before and moving (more than ``MOVING_M`` in that step) to the nearest segment within
``SNAP_M`` whose direction is within ``ALIGN`` of its heading (a two-way street's
opposite lane heads the other way), and moves it k · |x_t − x_{t−1}| metres along that
lane's chain at step t + k (a dead end holds it at the end). A vehicle with no such
segment (off the network, in a car park) moves at constant velocity, one standing still
stays, one seen first now stays (no past); presence stays as now, as for constant
velocity. It reads the traces at steps t and t − 1 only.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from uabs_rl.config import ConfigError
from uabs_rl.env.uabs_env import UABSEnv
from uabs_rl.evaluation.predict import Predictor, observed, schedule

CELL_M = 25.0  # the spatial index's cell side
SNAP_M = 8.0  # farthest a vehicle's position is from its lane's centre line
ALIGN = math.cos(math.radians(45))  # heading within 45° of the lane's direction
MOVING_M = 0.5  # metres in the last step below which a vehicle counts as standing


def network_file(scenario) -> Path:
    """The scenario's SUMO network file: ``scenario.sumo.net_file``, or the network a
    ``scenario.sumo.sumocfg`` names; a ConfigError when there is none to read."""
    from uabs_rl.traces.inputs import scenario_inputs, sumocfg_inputs

    found = scenario_inputs(scenario)
    if found["net_file"] is not None:
        return found["net_file"]
    nets = [p for p in sumocfg_inputs(found["sumocfg"]) if ".net.xml" in p.name]
    if not nets:
        raise ConfigError(f"scenario.sumo.sumocfg: {found['sumocfg']} names no network file "
                          f"(net-file) that exists: the road-aware predictor needs the "
                          f"network; use --predictor cv.")
    return nets[0]


def _unit(d: tuple[float, float]) -> tuple[float, float]:
    n = math.hypot(*d)
    return (d[0] / n, d[1] / n) if n > 0 else (0.0, 0.0)


def straightest(lane, net) -> list:
    """The lanes a vehicle at the end of ``lane`` drives next when it goes straight on:
    through the connection whose outgoing lane's first direction is closest to
    ``lane``'s last, its internal junction lane (if any) then that lane; [] at a dead
    end. For an internal lane, its own successor."""
    shape = lane.getShape()
    d_in = _unit((shape[-1][0] - shape[-2][0], shape[-1][1] - shape[-2][1]))
    best, best_cos = None, -2.0
    for c in lane.getOutgoing():
        to = c.getToLane()
        s = to.getShape()
        d_out = _unit((s[1][0] - s[0][0], s[1][1] - s[0][1]))
        cos = d_in[0] * d_out[0] + d_in[1] * d_out[1]
        if cos > best_cos:
            best, best_cos = c, cos
    if best is None:
        return []
    via = best.getViaLaneID()
    return ([net.getLane(via)] if via else []) + [best.getToLane()]


class RoadNetwork:
    """A SUMO network's lanes, area-relative, for snapping and straight-on chains (see
    the module docstring)."""

    def __init__(self, net, origin: tuple[float, float], reach_m: float,
                 device: torch.device | str = "cpu"):
        ox, oy = origin
        lanes = [lane for edge in net.getEdges(withInternal=True) for lane in edge.getLanes()]
        self.index = {lane.getID(): i for i, lane in enumerate(lanes)}
        shapes = [[(x - ox, y - oy) for x, y, *_ in lane.getShape()] for lane in lanes]
        # segments of every lane: start, direction, length, offset along the lane
        seg = []
        for i, pts in enumerate(shapes):
            off = 0.0
            for (x0, y0), (x1, y1) in zip(pts[:-1], pts[1:], strict=True):
                length = math.hypot(x1 - x0, y1 - y0)
                if length > 1e-6:
                    seg.append((x0, y0, (x1 - x0) / length, (y1 - y0) / length, length, off, i))
                off += length
        t = torch.tensor(seg, dtype=torch.float64)
        self.seg_a, self.seg_d = t[:, 0:2].float(), t[:, 2:4].float()
        self.seg_len, self.seg_off = t[:, 4].float(), t[:, 5].float()
        self.seg_lane = t[:, 6].long()
        # straight-on chains, padded with their last point (and length)
        chains = []
        for lane, shape in zip(lanes, shapes, strict=True):
            pts = list(shape)
            length, cur, seen = lane.getLength(), lane, {lane.getID()}
            while length < reach_m:
                nxt = straightest(cur, net)
                if not nxt or any(n.getID() in seen for n in nxt):
                    break
                for n in nxt:
                    seen.add(n.getID())
                    more = shapes[self.index[n.getID()]]
                    pts += more[1:] if math.dist(pts[-1], more[0]) < 1e-3 else more
                    length += n.getLength()
                cur = nxt[-1]
            chains.append(pts)
        p = max(len(c) for c in chains)
        pts = torch.tensor([c + [c[-1]] * (p - len(c)) for c in chains], dtype=torch.float64)
        cum = torch.cat([torch.zeros(len(chains), 1, dtype=torch.float64),
                         (pts[:, 1:] - pts[:, :-1]).norm(dim=-1).cumsum(-1)], dim=1)
        self.chain_pts, self.chain_cum = pts.float(), cum.float()
        self._grid(device)
        for name in ("seg_a", "seg_d", "seg_len", "seg_off", "seg_lane", "chain_pts",
                     "chain_cum"):
            setattr(self, name, getattr(self, name).to(device))

    def _grid(self, device) -> None:
        """``cells [C, K]``: per grid cell the segments within SNAP_M of it (−1 padded)."""
        a, b = self.seg_a, self.seg_a + self.seg_d * self.seg_len[:, None]
        lo = torch.minimum(a, b) - SNAP_M
        hi = torch.maximum(a, b) + SNAP_M
        self.grid_lo = lo.amin(0)
        n = ((hi.amax(0) - self.grid_lo) / CELL_M).floor().long() + 1
        self.grid_n = n
        c0 = ((lo - self.grid_lo) / CELL_M).floor().long()
        c1 = ((hi - self.grid_lo) / CELL_M).floor().long()
        buckets: dict[int, list[int]] = {}
        for s, (i0, j0, i1, j1) in enumerate(torch.cat([c0, c1], 1).tolist()):
            for i in range(i0, i1 + 1):
                for j in range(j0, j1 + 1):
                    buckets.setdefault(i * int(n[1]) + j, []).append(s)
        k = max(len(v) for v in buckets.values())
        cells = torch.full((int(n[0] * n[1]) + 1, k), -1, dtype=torch.long)  # last: outside
        for c, v in buckets.items():
            cells[c, :len(v)] = torch.tensor(v)
        self.cells = cells.to(device)
        self.grid_lo, self.grid_n = self.grid_lo.to(device), self.grid_n.to(device)

    def snap(self, pos: torch.Tensor, heading: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor]:
        """For points ``pos [N, 2]`` heading along the unit vectors ``heading [N, 2]``:
        the lane ``[N]`` (−1: none within SNAP_M and ALIGN) and the offset along it ``[N]``
        of the nearest aligned lane segment."""
        ij = ((pos - self.grid_lo) / CELL_M).floor().long()
        inside = ((ij >= 0) & (ij < self.grid_n)).all(-1)
        cell = torch.where(inside, ij[:, 0] * self.grid_n[1] + ij[:, 1], self.cells.shape[0] - 1)
        cand = self.cells[cell]  # [N, K]
        ok = cand >= 0
        s = cand.clamp_min(0)
        a, d, length = self.seg_a[s], self.seg_d[s], self.seg_len[s]
        rel = pos[:, None, :] - a
        along = (rel * d).sum(-1).clamp(min=0.0).minimum(length)
        dist = (rel - along[..., None] * d).norm(dim=-1)
        ok &= (dist <= SNAP_M) & ((d * heading[:, None, :]).sum(-1) >= ALIGN)
        dist = dist.masked_fill(~ok, math.inf)
        best = dist.argmin(-1)
        found = ok.any(-1)
        pick = s.gather(1, best[:, None]).squeeze(1)
        lane = torch.where(found, self.seg_lane[pick], -1)
        offset = self.seg_off[pick] + along.gather(1, best[:, None]).squeeze(1)
        return lane, offset

    def along(self, lane: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
        """[N, H, 2] the points ``offset [N, H]`` metres along each ``lane [N]``'s chain
        (held at its end beyond it)."""
        cum, pts = self.chain_cum[lane], self.chain_pts[lane]  # [N, P], [N, P, 2]
        s = torch.minimum(offset, cum[:, -1:])
        hi = torch.searchsorted(cum, s.contiguous()).clamp(1, cum.shape[1] - 1)  # [N, H]
        lo = hi - 1
        c0, c1 = cum.gather(1, lo), cum.gather(1, hi)
        w = ((s - c0) / (c1 - c0).clamp_min(1e-9)).clamp(0.0, 1.0)[..., None]
        p0 = pts.gather(1, lo[..., None].expand(-1, -1, 2))
        p1 = pts.gather(1, hi[..., None].expand(-1, -1, 2))
        return p0 + w * (p1 - p0)


def load_network(scenario, reach_m: float, device: torch.device | str = "cpu") -> RoadNetwork:
    """The scenario's network (:func:`network_file`) as a :class:`RoadNetwork` in the
    traces' frame."""
    from uabs_rl.traces.inputs import read_net

    a = scenario.area
    return RoadNetwork(read_net(network_file(scenario)), (float(a.x_min), float(a.y_min)),
                       reach_m, device)


class RoadAware(Predictor):
    """``predictor(env, horizon)`` along the roads of ``network`` (module docstring)."""

    name = "road"

    def __init__(self, network: RoadNetwork):
        self.network = network

    def __call__(self, env: UABSEnv, horizon: int) -> dict[str, torch.Tensor]:
        now, present = observed(env, 0)  # [E, 2, V], [E, V]
        prev, prev_present = observed(env, 1)
        v = torch.where((present & prev_present)[:, None, :], now - prev, 0.0)
        k = torch.arange(1, horizon + 1, device=now.device, dtype=now.dtype)
        veh = now[None] + k[:, None, None, None] * v[None]  # constant velocity, [H, E, 2, V]
        speed = v.norm(dim=1)  # [E, V]
        moving = speed > MOVING_M
        if moving.any():
            e_idx, v_idx = moving.nonzero(as_tuple=True)
            pos = now[e_idx, :, v_idx]  # [N, 2]
            vel = v[e_idx, :, v_idx]
            lane, offset = self.network.snap(pos, vel / speed[e_idx, v_idx, None])
            on = lane >= 0
            if on.any():
                e_on, v_on = e_idx[on], v_idx[on]
                ahead = offset[on, None] + k * speed[e_on, v_on, None]  # [N, H]
                pts = self.network.along(lane[on], ahead)  # [N, H, 2]
                veh[:, e_on, :, v_on] = pts  # (advanced indices first: [N, H, 2])
        return {"veh": veh,
                "present": torch.stack([env.state["prev_present"], *([present] * horizon)]),
                **schedule(env, horizon)}
