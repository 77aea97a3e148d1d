"""Which vehicles each UABS's beams cover and which of them are served (docs/model.md §3),
batched over ``[E, M, V]`` links, from the channel functions of :mod:`uabs_rl.env.channel`."""

from __future__ import annotations

import math

import torch

from uabs_rl import rng
from uabs_rl.env.channel import ChannelModel, beam_cells, beam_grid_side, make_channel, snr_db
from uabs_rl.env.params import EnvParams


class ServiceRadii:
    """Horizontal distances within which a link's SNR reaches SNR_th, for one receive
    gain: ``r_los`` if LoS, ``r_nlos`` if NLoS, ``r_exp`` with the expected path loss.
    Valid without shadowing (the path loss then grows with distance)."""

    def __init__(self, p: EnvParams, model: ChannelModel, gain_db: float, reach: float):
        self.p, self.model = p, model
        f = lambda pl: snr_db(pl, p.tx_dbm, p.tx_gain_db, gain_db, p.noise_dbm)  # noqa: E731

        def pl(kind: str):
            def fn(d: torch.Tensor) -> torch.Tensor:
                d3 = (d * d + (p.altitude - p.h_ut) ** 2).sqrt()
                los = model.pathloss_los(d, d3)
                nlos = model.pathloss_nlos(d, d3)
                rho = model.los_probability(d)
                return {"los": los, "nlos": nlos, "exp": rho * los + (1 - rho) * nlos}[kind]
            return fn

        self.r_los, self.r_nlos, self.r_exp = (
            _radius(lambda d, k=k: f(pl(k)(d)) >= p.snr_th_db) for k in ("los", "nlos", "exp"))
        # a LoS draw can change the outcome only between the two radii, within reach
        self.needs_draw = p.los_mode == "sample" and self.r_nlos < min(self.r_los, reach)

    def always_within(self, reach: float) -> bool:
        """True if every link up to ``reach`` metres is served whatever its LoS state."""
        r = {"los": self.r_los, "expected": self.r_exp}.get(self.p.los_mode, self.r_nlos)
        return r >= reach

    def served(self, d2: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        """Served flags from squared horizontal distances ``d2``."""
        mode = self.p.los_mode
        if mode == "los":
            return d2 <= _squared(self.r_los)
        if mode == "expected":
            return d2 <= _squared(self.r_exp)
        sure = d2 <= _squared(self.r_nlos)
        if not self.needs_draw:
            return sure
        maybe = d2 <= _squared(self.r_los)
        los = rng.rand(d2.shape, gen, d2.device) < self.model.los_probability(d2.sqrt())
        return sure | (maybe & los)


def _squared(r: float) -> float:
    """The squared radius, or -1 for "no distance is served" (r < 0): no d² is <= -1."""
    return r * r if r >= 0 else -1.0


def footprint_reach(r_b: float, n_beams: int) -> float:
    """Farthest ground distance from the UABS that a footprint of its k × k grid covers:
    the corner beam's centre, (k − 1)·r_b from the middle along each axis, plus r_b."""
    k = beam_grid_side(n_beams)
    return ((k - 1) * math.sqrt(2.0) + 1.0) * r_b


def _radius(ok, hi: float = 1e6, iters: int = 80) -> float:
    """Largest d in [0, hi] with ok(d), for ok true up to a point and false beyond
    (-1 if never, inf if always)."""
    t = lambda d: bool(ok(torch.tensor([d], dtype=torch.float64)).item())  # noqa: E731
    if not t(0.0):
        return -1.0
    if t(hi):
        return math.inf
    lo = 0.0
    for _ in range(iters):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if t(mid) else (lo, mid)
    return lo


def link_bytes(n_uabs: int, n_vehicles: int) -> int:
    """One step's beam-grid coordinates of every link of one env (``gx`` and ``gy`` of
    :meth:`LinkModel.links`, float32 ``[M, V]`` each)."""
    return 2 * 4 * n_uabs * n_vehicles


class LinkModel:
    """Which vehicles each UABS's beams cover and which are served (docs/model.md §3), batched
    over ``[E, M, V]`` links.

    Without shadowing the SNR falls monotonically with distance, so "served" is "closer
    than a radius" per LoS state (:class:`ServiceRadii`): exact, and far cheaper than the
    SNR. With shadowing the SNR is computed per link."""

    def __init__(self, p: EnvParams, device: torch.device):
        self.p = p
        self.model = make_channel(p.channel, p.altitude, p.h_ut, p.fc_ghz)
        # beam index space of all agents: agent u's beams are u·B .. u·B + B − 1
        self.agent_offset = (torch.arange(p.n_uabs, device=device, dtype=torch.float32)
                             * p.n_beams)[None, :, None]
        self.radii: dict[float, ServiceRadii] = {}
        if not p.shadow:
            gains = [p.gain_db] + ([p.outside_gain_db] if p.outside_gain_db is not None else [])
            # farthest link that can be a candidate: the footprints' reach, or the area
            reach = footprint_reach(p.r_b, p.n_beams) if p.outside_gain_db is None else \
                math.hypot(p.width, p.height)
            self.radii = {g: ServiceRadii(p, self.model, g, reach) for g in gains}
        self.always_served = p.outside_gain_db is None and bool(self.radii) and \
            self.radii[p.gain_db].always_within(reach)
        self.beam_k = beam_grid_side(p.n_beams)
        self.inv_pitch = 1.0 / (2.0 * p.r_b)

    def links(self, pos: torch.Tensor, veh: torch.Tensor, present: torch.Tensor,
              gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Footprint membership ``inside [E,M,V]``, beam index ``[E,M,V]`` (all agents'
        beams in one index space: u·B + i) and served flags ``[E,V]``, for vehicles
        ``veh [E,2,V]`` (planar) under UABS at ``pos [E,M,2]``."""
        p, k, half = self.p, self.beam_k, (self.beam_k - 1) / 2.0
        gx, gy = self.grid_coordinates(pos, veh)
        if not self.always_served:
            d2 = ((gx - half) ** 2 + (gy - half) ** 2) * (2.0 * p.r_b) ** 2
        inside, beam = beam_cells(gx, gy, k, self.agent_offset)
        inside &= present[:, None, :]
        if self.always_served:  # every link inside a footprint reaches SNR_th
            return inside, beam, inside.any(1)
        if p.outside_gain_db is None:  # ideal beams: only links inside a footprint
            ok = self.radii[p.gain_db].served(d2, gen) if self.radii else \
                self.snr(d2, gen) + p.gain_db >= p.snr_th_db
            return inside, beam, (inside & ok).any(1)
        if self.radii:
            ok_in = self.radii[p.gain_db].served(d2, gen)
            ok_out = self.radii[p.outside_gain_db].served(d2, gen)
        else:
            snr = self.snr(d2, gen)
            ok_in = snr + p.gain_db >= p.snr_th_db
            ok_out = snr + p.outside_gain_db >= p.snr_th_db
        return inside, beam, torch.where(inside, ok_in, ok_out).any(1) & present

    def grid_coordinates(self, pos: torch.Tensor,
                         veh: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Beam-grid coordinates ``(gx, gy) [E,M,V]`` of every link (as
        :func:`~uabs_rl.env.channel.beam_cells` takes them), from [E,V] and [E,M] pieces:
        one [E,M,V] subtraction per axis."""
        half, inv = (self.beam_k - 1) / 2.0, self.inv_pitch
        vx, vy = veh[:, 0, :] * inv, veh[:, 1, :] * inv
        ux, uy = pos[..., 0] * inv - half, pos[..., 1] * inv + half
        return vx[:, None, :] - ux[:, :, None], uy[:, :, None] - vy[:, None, :]

    def snr(self, d2d_sq: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        """SNR in dB without the receive gain, per link (LoS state per ``los_mode``)."""
        p = self.p
        d2d = d2d_sq.sqrt()
        d3d = (d2d_sq + (p.altitude - p.h_ut) ** 2).sqrt()
        pl_los = self.model.pathloss_los(d2d, d3d)
        if p.los_mode == "los":
            pl, los = pl_los, None
        else:
            pl_nlos = self.model.pathloss_nlos(d2d, d3d)
            rho = self.model.los_probability(d2d)
            if p.los_mode == "expected":
                pl, los = rho * pl_los + (1.0 - rho) * pl_nlos, None
            else:
                los = rng.rand(d2d.shape, gen, d2d.device) < rho
                pl = torch.where(los, pl_los, pl_nlos)
        if p.shadow:
            sigma = p.sigma_los if los is None else torch.where(los, p.sigma_los, p.sigma_nlos)
            pl = pl + sigma * rng.randn(d2d.shape, gen, d2d.device)
        return snr_db(pl, p.tx_dbm, p.tx_gain_db, 0.0, p.noise_dbm)
