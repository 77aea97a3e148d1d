"""Physics as plain tensor functions: 3GPP TR 38.901 UMa channel, beams, service.

Everything here is batched elementwise math on tensors (any shape), so a test can
call it with hand-computed inputs and the environment calls it on ``[E, M, V]``
link tensors. Distances in metres, frequencies in GHz, powers in dB/dBm.
"""

from __future__ import annotations

import math
from typing import Protocol

import torch

SPEED_OF_LIGHT = 299_792_458.0


# ----------------------------------------------------------------------------- UMa
def los_probability(d2d: torch.Tensor, h_ut: float = 1.5) -> torch.Tensor:
    """TR 38.901 Table 7.4.2-1, UMa: ρ_L as a function of the horizontal distance.
    C'(h_UT) = 0 up to 13 m, ((h_UT − 13)/10)^1.5 up to 23 m, where the model ends (held
    at its 23 m value beyond)."""
    c_prime = 0.0 if h_ut <= 13.0 else ((min(h_ut, 23.0) - 13.0) / 10.0) ** 1.5
    d = d2d.clamp_min(18.0)  # the formula is used beyond 18 m only
    p = (18.0 / d + torch.exp(-d / 63.0) * (1.0 - 18.0 / d)) * (
        1.0 + c_prime * 1.25 * (d / 100.0) ** 3 * torch.exp(-d / 150.0))
    return torch.where(d2d <= 18.0, torch.ones_like(p), p)


def breakpoint_distance(h_bs: float, h_ut: float, fc_ghz: float) -> float:
    """d'_BP = 4 h'_BS h'_UT f_c / c with effective heights h' = h − 1 m."""
    return 4.0 * (h_bs - 1.0) * (h_ut - 1.0) * fc_ghz * 1e9 / SPEED_OF_LIGHT


def pathloss_los(d2d: torch.Tensor, d3d: torch.Tensor, h_bs: float, h_ut: float,
                 fc_ghz: float) -> torch.Tensor:
    """TR 38.901 Table 7.4.1-1, UMa LoS: PL1 up to the breakpoint, PL2 beyond."""
    d_bp = breakpoint_distance(h_bs, h_ut, fc_ghz)
    log_fc = 20.0 * math.log10(fc_ghz)
    pl1 = 28.0 + 22.0 * torch.log10(d3d) + log_fc
    pl2 = (28.0 + 40.0 * torch.log10(d3d) + log_fc
           - 9.0 * math.log10(d_bp ** 2 + (h_bs - h_ut) ** 2))
    return torch.where(d2d <= d_bp, pl1, pl2)


def pathloss_nlos(d2d: torch.Tensor, d3d: torch.Tensor, h_bs: float, h_ut: float,
                  fc_ghz: float) -> torch.Tensor:
    """TR 38.901 Table 7.4.1-1, UMa NLoS: max(PL_LoS, PL'_NLoS)."""
    pl_nlos = (13.54 + 39.08 * torch.log10(d3d) + 20.0 * math.log10(fc_ghz)
               - 0.6 * (h_ut - 1.5))
    return torch.maximum(pathloss_los(d2d, d3d, h_bs, h_ut, fc_ghz), pl_nlos)


class ChannelModel(Protocol):
    """What :mod:`uabs_rl.env.links` asks of a channel model (``UMa`` below is one):
    built from the UABS altitude, the UE height and the carrier (GHz), the LoS
    probability and the LoS and NLoS path losses (dB) at 2D / 3D distances (m)."""

    def __init__(self, altitude: float, h_ut: float, fc_ghz: float) -> None: ...

    def los_probability(self, d2d: torch.Tensor) -> torch.Tensor: ...

    def pathloss_los(self, d2d: torch.Tensor, d3d: torch.Tensor) -> torch.Tensor: ...

    def pathloss_nlos(self, d2d: torch.Tensor, d3d: torch.Tensor) -> torch.Tensor: ...


class UMa:
    """TR 38.901 UMa between a ground UE at ``h_ut`` and a UABS at ``altitude`` on carrier
    ``fc_ghz``: the channel model ``channel.name=uma`` (docs/model.md §3).

    A channel model is a class with this constructor and these three methods, registered
    in :data:`CHANNELS`; :mod:`uabs_rl.env.links` draws LoS states, applies ``los_mode`` and
    shadowing, and decides service from them."""

    def __init__(self, altitude: float, h_ut: float, fc_ghz: float):
        self.altitude, self.h_ut, self.fc_ghz = altitude, h_ut, fc_ghz

    def los_probability(self, d2d: torch.Tensor) -> torch.Tensor:
        return los_probability(d2d, self.h_ut)

    def pathloss_los(self, d2d: torch.Tensor, d3d: torch.Tensor) -> torch.Tensor:
        return pathloss_los(d2d, d3d, self.altitude, self.h_ut, self.fc_ghz)

    def pathloss_nlos(self, d2d: torch.Tensor, d3d: torch.Tensor) -> torch.Tensor:
        return pathloss_nlos(d2d, d3d, self.altitude, self.h_ut, self.fc_ghz)


# channel.name -> channel model (docs/code.md: how to add a channel model)
CHANNELS: dict[str, type[ChannelModel]] = {"uma": UMa}


def make_channel(name: str, altitude: float, h_ut: float, fc_ghz: float) -> ChannelModel:
    """The channel model registered as ``name`` (checked at start-up by
    ``config.validate_env``)."""
    return CHANNELS[name](altitude, h_ut, fc_ghz)


def snr_db(pathloss_db: torch.Tensor, tx_power_dbm: float, tx_gain_db: float,
           rx_gain_db: float | torch.Tensor, noise_dbm: float) -> torch.Tensor:
    """SNR = P_tx + G_tx + G_rx − PL − P_n."""
    return tx_power_dbm + tx_gain_db + rx_gain_db - pathloss_db - noise_dbm


# ----------------------------------------------------------------------------- beams
def beam_solid_angle(fov_deg: float, n_beams: int) -> float:
    """Φ_beam = 2π(1 − cos(φ/2)) / B, steradians."""
    return 2.0 * math.pi * (1.0 - math.cos(math.radians(fov_deg) / 2.0)) / n_beams


def beam_gain_db(fov_deg: float, n_beams: int) -> float:
    """G = 41000 / (Φ_beam · 360/(2π))², in dB (38.5 dB for φ = 40°, B = 9)."""
    phi_deg2 = beam_solid_angle(fov_deg, n_beams) * 360.0 / (2.0 * math.pi)
    return 10.0 * math.log10(41000.0 / phi_deg2 ** 2)


def beam_footprint_radius(altitude: float, fov_deg: float, n_beams: int) -> float:
    """r_b = h tan θ_b with θ_b the half-angle of a cone of solid angle Φ_beam (≈ 11.6 m)."""
    cos_theta = 1.0 - beam_solid_angle(fov_deg, n_beams) / (2.0 * math.pi)
    return altitude * math.tan(math.acos(cos_theta))


def safety_distance(altitude: float, fov_deg: float) -> float:
    """d_th = 2 h tan(φ/2): twice the coverage radius (≈ 72.8 m for the defaults)."""
    return 2.0 * altitude * math.tan(math.radians(fov_deg) / 2.0)


def beam_grid_side(n_beams: int) -> int:
    k = math.isqrt(n_beams)
    if k * k != n_beams:
        raise ValueError(f"n_beams must be a square (k x k grid), got {n_beams}")
    return k


def beam_centres(r_b: float, n_beams: int = 9) -> torch.Tensor:
    """[B, 2] ground offsets of the beam centres: pitch 2 r_b, index = k·row + col,
    row 0 to the north (+y), col 0 to the west (−x)."""
    k = beam_grid_side(n_beams)
    half = (k - 1) / 2.0
    rows, cols = torch.meshgrid(torch.arange(k), torch.arange(k), indexing="ij")
    x = (cols.flatten() - half) * 2.0 * r_b
    y = (half - rows.flatten()) * 2.0 * r_b
    return torch.stack([x, y], dim=-1)


def assign_beams(dx: torch.Tensor, dy: torch.Tensor, r_b: float, n_beams: int = 9,
                 index_offset: torch.Tensor | float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Footprint membership of ground offsets (dx east, dy north) from the UABS's
    ground point.

    Returns ``(inside, index)``: ``inside`` is True where the point lies in a beam's
    circular footprint (radius r_b); ``index`` is the nearest beam centre (the beam a
    point in two touching footprints belongs to), plus ``index_offset``.
    """
    k = beam_grid_side(n_beams)
    half = (k - 1) / 2.0
    inv_pitch = 1.0 / (2.0 * r_b)
    return beam_cells(dx * inv_pitch + half, half - dy * inv_pitch, k, index_offset)


def footprint_inside(dx: torch.Tensor, dy: torch.Tensor, r_b: float,
                     n_beams: int = 9) -> torch.Tensor:
    """``inside`` of :func:`assign_beams` alone (the same values, without the beam
    index's work and memory)."""
    k = beam_grid_side(n_beams)
    half = (k - 1) / 2.0
    inv_pitch = 1.0 / (2.0 * r_b)
    return _cells(dx * inv_pitch + half, half - dy * inv_pitch, k)[0]


def beam_cells(gx: torch.Tensor, gy: torch.Tensor, k: int,
               index_offset: torch.Tensor | float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`assign_beams` in beam-grid coordinates: ``gx`` (column, grows east) and
    ``gy`` (row, grows south) in units of the pitch 2 r_b, centre beam at
    ((k−1)/2, (k−1)/2). Centres form a square lattice, so the nearest one is a per-axis
    rounding; a point is inside when within half a pitch (= r_b) of it. Consumes
    ``gx`` and ``gy`` (modified in place)."""
    inside, col, row = _cells(gx, gy, k)
    return inside, (col.add_(index_offset).add_(row, alpha=k)).long()


def _cells(gx: torch.Tensor, gy: torch.Tensor,
           k: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(inside, column, row) of :func:`beam_cells`; consumes ``gx`` and ``gy``."""
    col = gx.round().clamp_(0, k - 1)
    row = gy.round().clamp_(0, k - 1)
    fx, fy = gx.sub_(col), gy.sub_(row)
    return torch.addcmul(fx * fx, fy, fy) <= 0.25, col, row  # (r_b / pitch)^2


def coverage_fraction(pos: torch.Tensor, r_b: float, n_beams: int, width: float,
                      height: float, spacing: float = 5.0) -> torch.Tensor:
    """Share of the area under at least one beam footprint, ``pos [..., M, 2]`` -> ``[...]``,
    measured on a grid of sample points ``spacing`` metres apart (cell centres).

    Only the sample points within reach of each UABS (its k × k footprints span
    ± k·r_b) are tested, each against its nearest beam centre, and the covered ones
    are marked on the grid: the cost grows with M, not with the area (a city-size area
    has tens of thousands of sample points)."""
    nx = len(torch.arange(spacing / 2, width, spacing))
    ny = len(torch.arange(spacing / 2, height, spacing))
    k = beam_grid_side(n_beams)
    w = math.ceil(k * r_b / spacing) + 1
    offs = torch.arange(-w, w + 1, device=pos.device)
    batch = pos.shape[:-2]
    flat = pos.reshape(-1, pos.shape[-2], 2)  # [N, M, 2]
    ix = torch.floor(flat[..., 0] / spacing).long()[..., None, None] + offs[:, None]
    iy = torch.floor(flat[..., 1] / spacing).long()[..., None, None] + offs[None, :]
    px = spacing / 2 + ix * spacing  # [N, M, 2w+1, 1]
    py = spacing / 2 + iy * spacing  # [N, M, 1, 2w+1]
    dx = (px - flat[..., 0, None, None]).expand(-1, -1, -1, 2 * w + 1)
    dy = (py - flat[..., 1, None, None]).expand(-1, -1, 2 * w + 1, -1)
    inside, _ = assign_beams(dx.clone(), dy.clone(), r_b, n_beams)
    ixx, iyy = ix.expand_as(inside), iy.expand_as(inside)
    inside &= (ixx >= 0) & (ixx < nx) & (iyy >= 0) & (iyy < ny)
    idx = (ixx.clamp(0, nx - 1) * ny + iyy.clamp(0, ny - 1)).flatten(1)  # [N, M·(2w+1)²]
    covered = torch.zeros(flat.shape[0], nx * ny, device=pos.device)
    covered.scatter_reduce_(1, idx, inside.flatten(1).float(), "amax")
    return covered.mean(-1).reshape(batch)


def coverage_bound(n_uabs: int, n_beams: int, r_b: float, area_m2: float) -> float:
    """Largest share of the area under footprints at one step (ideal beams, no overlap)."""
    return min(1.0, n_uabs * n_beams * math.pi * r_b ** 2 / area_m2)
