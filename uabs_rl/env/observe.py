"""What each UABS observes (docs/model.md §5), on plain ``[E, M, ...]`` tensors.

Two frames (``obs.frame``):

- ``fleet``, the paper's: (x/W, y/H, t/T, every UABS's x/W and y/H, b_t / scale[,
  lookahead scores / scale]). The fleet's positions make its size 3 + 2M + B (+ 8 or
  12): a policy is tied to its fleet size.
- ``egocentric``: (t/T, b_t / scale, local map / scale, K nearest neighbours, edges),
  1 + B + (2r + 1)^2 (x 2 with ``obs.motion``) + 3K + 4 numbers whatever M and the area.
  The local map is the priority the UABS's footprints would cover at each lattice point
  within r steps of it (:func:`map_offsets`); the neighbours are the offsets of the K
  nearest other UABS in units of ``obs.neighbour_range`` lattice steps, clipped to
  [-1, 1], each with a present flag (zeros where the fleet has fewer than K others);
  the edges are the distances to the area's west, south, east and north edges in units
  of ``obs.edge_range`` lattice steps, clipped to [0, 1]. Nothing in it is absolute:
  translating the whole scene by a lattice step (away from the edges) or renumbering
  the UABS leaves each UABS's observation as it was.
"""

from __future__ import annotations

import torch


def map_offsets(radius: int, step: float, device: torch.device) -> torch.Tensor:
    """[(2r + 1)^2, 2] lattice offsets (metres) within ``radius`` steps in x and y: rows
    from south to north, west to east within a row."""
    k = torch.arange(-radius, radius + 1, device=device, dtype=torch.float32) * step
    dy, dx = torch.meshgrid(k, k, indexing="ij")
    return torch.stack([dx.flatten(), dy.flatten()], dim=-1)


def fleet_observation(pos: torch.Tensor, t: torch.Tensor, b: torch.Tensor,
                      look: torch.Tensor | None, area: torch.Tensor, episode_steps: int,
                      scale: float) -> torch.Tensor:
    """The paper's observation [E, M, 3 + 2M + B (+ scores)]."""
    e, m, _ = pos.shape
    norm = pos / area
    tt = (t.float() / episode_steps)[:, None, None].expand(e, m, 1)
    fleet = norm.reshape(e, 1, 2 * m).expand(e, m, 2 * m)
    parts = [norm, tt, fleet, b / scale]
    if look is not None:
        parts.append(look / scale)
    return torch.cat(parts, dim=-1)


def nearest_neighbours(pos: torch.Tensor, k: int, scale: float,
                       of: torch.Tensor | None = None) -> torch.Tensor:
    """[E, M, 3K]: for each UABS, (dx, dy, 1) of its K nearest others, offsets divided
    by ``scale`` (metres) and clipped to [-1, 1], nearest first; ties broken by dx, then
    dy (never by the UABS's number); (0, 0, 0) for each missing one. ``of [E, R]``: only
    these UABS's rows, ``[E, R, 3K]`` (the same numbers as theirs among all M)."""
    e, m, _ = pos.shape
    n = min(k, m - 1)
    if of is None:  # every UABS's row
        rows, me = m, pos
        itself = torch.eye(m, dtype=torch.bool, device=pos.device)
    else:
        rows, me = of.shape[1], pos.gather(1, of[..., None].expand(e, of.shape[1], 2))
        itself = of[..., None] == torch.arange(m, device=pos.device)  # [E, R, M]
    off = pos[:, None, :, :] - me[:, :, None, :]  # [E, i, j, 2]: j's offset from i
    dist = off.square().sum(-1).masked_fill(itself, float("inf"))
    # lexicographic (dist, dx, dy) by stable sorts from the last key to the first
    order = torch.sort(off[..., 1], dim=-1, stable=True).indices
    for key in (off[..., 0], dist):
        order = order.gather(-1, torch.sort(key.gather(-1, order), dim=-1,
                                            stable=True).indices)
    near = off.gather(2, order[..., :n, None].expand(e, rows, n, 2))
    feats = torch.cat([(near / scale).clamp(-1.0, 1.0), near.new_ones(e, rows, n, 1)], -1)
    pad = feats.new_zeros(e, rows, k - n, 3)
    return torch.cat([feats, pad], dim=2).flatten(-2)


def egocentric_observation(pos: torch.Tensor, t: torch.Tensor, b: torch.Tensor,
                           look: torch.Tensor, area: torch.Tensor, episode_steps: int,
                           scale: float, neighbours: int, neighbour_scale: float,
                           edge_scale: float, near: torch.Tensor | None = None) -> torch.Tensor:
    """The egocentric observation [E, M, 1 + B + scores + 3K + 4] (module docstring);
    ``neighbour_scale`` and ``edge_scale`` in metres. ``near [E, M, 3K]``: the
    neighbours' part, when the UABS at ``pos`` are not one fleet (candidate positions of
    one UABS, :mod:`uabs_rl.evaluation.leaf`); default: :func:`nearest_neighbours` of
    ``pos``."""
    e, m, _ = pos.shape
    if near is None:
        near = nearest_neighbours(pos, neighbours, neighbour_scale)
    tt = (t.float() / episode_steps)[:, None, None].expand(e, m, 1)
    edges = (torch.cat([pos, area - pos], dim=-1) / edge_scale).clamp(0.0, 1.0)
    return torch.cat([tt, b / scale, look / scale, near, edges], dim=-1)
