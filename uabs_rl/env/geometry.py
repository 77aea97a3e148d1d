"""UABS geometry (docs/model.md §1, §6, §8): the lattice, start positions, the boundary mask,
pair distances and the closest approach between two steps, as batched tensor math."""

from __future__ import annotations

import math
from functools import lru_cache

import torch

from uabs_rl import rng
from uabs_rl.env.params import EnvParams

# the four actions: up (+y), right (+x), down (−y), left (−x)
UNIT_MOVES = torch.tensor([[0.0, 1.0], [1.0, 0.0], [0.0, -1.0], [-1.0, 0.0]])


class Geometry:
    """Positions of M UABS in a W × H area; every tensor is ``[E, M, ...]``."""

    def __init__(self, p: EnvParams, device: torch.device):
        self.p = p
        self.device = device
        self.moves = (UNIT_MOVES * p.step_m).to(device)  # [4, 2]
        self.area = torch.tensor([p.width, p.height], device=device)
        # lattice: pitch v·δt, centred in the area
        n = torch.floor(self.area / p.step_m).long() + 1  # lattice points per axis
        self.lattice_n = n
        self.lattice_lo = (self.area - (n - 1).float() * p.step_m) / 2.0
        self.eye = torch.eye(p.n_uabs, dtype=torch.bool, device=device)

    # ------------------------------------------------------------------ start
    def lattice_point(self, ix: torch.Tensor, iy: torch.Tensor) -> torch.Tensor:
        return torch.stack([self.lattice_lo[0] + ix * self.p.step_m,
                            self.lattice_lo[1] + iy * self.p.step_m], dim=-1)

    def perimeter_point(self, s: torch.Tensor) -> torch.Tensor:
        """Point at arc length ``s`` along the outer lattice ring, counter-clockwise from
        the lower-left corner."""
        lo = self.lattice_lo
        w, h = ((self.lattice_n - 1).float() * self.p.step_m).tolist()
        perim = 2.0 * (w + h)
        s = torch.remainder(s, perim)
        if self.p.lattice:
            s = torch.remainder(torch.round(s / self.p.step_m) * self.p.step_m, perim)
        x = torch.where(s < w, s, torch.where(s < w + h, torch.full_like(s, w),
                        torch.where(s < 2 * w + h, w - (s - w - h), torch.zeros_like(s))))
        y = torch.where(s < w, torch.zeros_like(s), torch.where(s < w + h, s - w,
                        torch.where(s < 2 * w + h, torch.full_like(s, h), perim - s)))
        return torch.stack([x + lo[0], y + lo[1]], dim=-1)

    def start_positions(self, n_envs: int, gen: torch.Generator,
                        candidates: int = 32) -> torch.Tensor:
        """[E, M, 2]: UABS 0 inside the area, the others equally spaced on the perimeter
        from a random point; with ``safe_start`` the inner one is the first of
        ``candidates`` draws that keeps d_th from all the others (else the farthest)."""
        p, dev = self.p, self.device
        w, h = ((self.lattice_n - 1).float() * p.step_m).tolist()
        perim = 2.0 * (w + h)
        k = torch.arange(p.n_uabs - 1, device=dev).float()
        s0 = rng.rand((n_envs, 1), gen, dev) * perim
        ring = self.perimeter_point(s0 + k * perim / max(p.n_uabs - 1, 1))  # [E, M-1, 2]
        c = candidates if p.safe_start and p.n_uabs > 1 else 1
        if p.lattice:
            ix = rng.randint(0, int(self.lattice_n[0]), (n_envs, c), gen, dev)
            iy = rng.randint(0, int(self.lattice_n[1]), (n_envs, c), gen, dev)
            inner = self.lattice_point(ix.float(), iy.float())  # [E, C, 2]
        else:
            inner = rng.rand((n_envs, c, 2), gen, dev) * self.area
        if c > 1:
            mind = torch.cdist(inner, ring).amin(-1)  # [E, C]
            ok = mind >= p.d_th
            pick = torch.where(ok.any(-1), ok.int().argmax(-1), mind.argmax(-1))
            inner = inner.gather(1, pick[:, None, None].expand(-1, 1, 2))
        return torch.cat([inner[:, :1], ring], dim=1)

    # ------------------------------------------------------------------ packing
    def packing(self, spacing: float) -> torch.Tensor:
        """[K, 2] the largest set of lattice points found with every pair at least
        ``spacing`` apart (see :func:`lattice_packing`; computed once per area)."""
        return lattice_packing(self.p, spacing).to(self.device, copy=True)

    def spread_start(self, pos: torch.Tensor, packing: torch.Tensor, spacing: float,
                     gen: torch.Generator) -> torch.Tensor:
        """Start positions with every pair at least ``spacing`` apart: ``pos`` where it
        already is, else M random points of ``packing`` (mirrored at random)."""
        if isinstance(gen, rng.Generators):  # whether to draw is each member's own case
            return torch.cat([self.spread_start(pos[sl], packing, spacing, g)
                              for sl, g in gen.blocks(pos.shape[0])])
        e, m = pos.shape[:2]
        ok = self.pair_distances(pos).flatten(1).amin(-1) >= spacing - 1e-6  # [E]
        if bool(ok.all()):  # no draw: the paper's placement stands everywhere
            return pos
        pick = torch.rand(e, packing.shape[0], generator=gen, device=self.device).argsort(-1)
        alt = packing[pick[:, :m]]  # [E, M, 2]
        flip = torch.rand(e, 1, 2, generator=gen, device=self.device) < 0.5
        lo, hi = self.lattice_lo, self.lattice_lo + (self.lattice_n - 1).float() * self.p.step_m
        alt = torch.where(flip, lo + hi - alt, alt)
        return torch.where(ok[:, None, None], pos, alt)

    # ------------------------------------------------------------------ geometry
    def boundary_mask(self, pos: torch.Tensor,
                      bounds: torch.Tensor | None = None) -> torch.Tensor:
        """[E, M, 4] True where the move (up, right, down, left) keeps the UABS inside
        the area, or inside each env's own (W, H) ``bounds [E, 2]`` (a family of cities)."""
        x, y, s = pos[..., 0], pos[..., 1], self.p.step_m
        w, h = (self.p.width, self.p.height) if bounds is None else (bounds[:, None, 0],
                                                                      bounds[:, None, 1])
        return torch.stack([y + s <= h, x + s <= w, y - s >= 0.0, x - s >= 0.0], dim=-1)

    def pair_distances(self, pos: torch.Tensor) -> torch.Tensor:
        """[E, M, M] distances, +inf on the diagonal."""
        d = torch.cdist(pos, pos)
        return d.masked_fill(self.eye, math.inf)

    def closest_approach(self, old: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
        """[E] smallest pair distance along the straight paths from ``old`` to ``new``."""
        r0 = old[:, :, None, :] - old[:, None, :, :]  # [E, M, M, 2]
        dv = (new - old)[:, :, None, :] - (new - old)[:, None, :, :]
        d = path_distance(r0, dv).masked_fill(self.eye, math.inf)
        return d.flatten(1).amin(-1)


PACKING_BUDGET = 500_000_000  # restarts x lattice points², about 2 s of CPU (dense)


@lru_cache(maxsize=32)
def lattice_packing(p: EnvParams, spacing: float, restarts: int = 2000) -> torch.Tensor:
    """[K, 2] (CPU) the largest set of lattice points found with every pair at least
    ``spacing`` apart: greedy packings over ``restarts`` seeded random orders (the first
    in lattice order), run side by side. A lower bound on the largest such fleet;
    deterministic for given params, and cached (the train and eval envs share it).
    The work grows as restarts x points²: on large areas (a city of thousands of
    lattice points, which holds far more UABS than a fleet) fewer restarts are run, at
    most PACKING_BUDGET / points² (the paper's area keeps all 2000)."""
    geo = Geometry(p, torch.device("cpu"))
    n = geo.lattice_n.tolist()
    pts = torch.cartesian_prod(torch.arange(n[0]), torch.arange(n[1])).float()
    xy = geo.lattice_point(pts[:, 0], pts[:, 1])
    p_n = xy.shape[0]
    restarts = min(restarts, max(8, PACKING_BUDGET // (p_n * p_n)))
    near = _close_points(xy, spacing)  # [P, K] each point's close points, P = padding
    gen = torch.Generator().manual_seed(0)
    order = torch.rand(restarts, p_n, generator=gen).argsort(-1)
    order[0] = torch.arange(p_n)
    rows = torch.arange(restarts)
    taken = torch.zeros(restarts, p_n + 1, dtype=torch.bool)  # + the padding column
    chosen = torch.zeros(restarts, p_n, dtype=torch.bool)
    sparse = near.shape[1] * 8 < p_n  # a large area: mark the close points only
    if not sparse:  # a small one: whole rows of the dense [P, P + 1] matrix are faster
        close = torch.zeros(p_n, p_n + 1, dtype=torch.bool).scatter_(1, near, True)
    for j in range(p_n):
        idx = order[:, j]
        free = ~taken[rows, idx]
        chosen[rows, idx] = free
        if sparse:
            taken[rows[:, None], near[idx]] |= free[:, None]
        else:
            taken |= close[idx] & free[:, None]
    return xy[chosen[chosen.sum(-1).argmax()]]


def _close_points(xy: torch.Tensor, spacing: float, chunk: int = 1024) -> torch.Tensor:
    """[P, K] long: for each lattice point, the points closer than ``spacing`` (itself
    included), padded with P; the pairs a dense [P, P] ``cdist < spacing`` would mark,
    found a block of rows at a time (a city-size lattice's dense matrix is gigabytes)."""
    pts = xy.double()
    lists = []
    for a in range(0, pts.shape[0], chunk):
        close = torch.cdist(pts[a:a + chunk], pts) < spacing - 1e-9
        lists += [row.nonzero().flatten() for row in close]
    width = max(len(x) for x in lists)
    near = torch.full((len(lists), width), pts.shape[0], dtype=torch.long)
    for i, x in enumerate(lists):
        near[i, :len(x)] = x
    return near


def path_distance(r0: torch.Tensor, dr: torch.Tensor) -> torch.Tensor:
    """Smallest distance between two UABS flying straight at constant speed for one
    step: ``min_{τ in [0, 1]} |r0 + τ dr|`` with ``r0 [..., 2]`` their offset at the
    start and ``dr [..., 2]`` the change of that offset over the step."""
    s = (-(r0 * dr).sum(-1) / (dr * dr).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
    return (r0 + s[..., None] * dr).norm(dim=-1)
