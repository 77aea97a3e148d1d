"""``UABSEnv``: a batched TorchRL environment replaying cached vehicle traces (SPEC §1, §3-§5).

Batch ``[n_envs]``; one agent group ``"agents"`` with nested batch ``(n_envs, M)``.
The step math lives in :class:`StepMath`, plain tensors in and out, so a benchmark can
time it without any TensorDict and a test can call it directly; ``UABSEnv`` only
moves state in and out of TensorDicts.

Order inside a step (SPEC §5): agents move → vehicles advance to t+1 → served flags
at t+1 → priorities p_{t+1} → per-beam sums b_{t+1} → rewards and observations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from uabs_rl import channel as ch
from uabs_rl._compile import compiled_or_eager
from uabs_rl.config import ConfigError, validate_env
from uabs_rl.traces import TraceSet

# Nested keys, in one place.
AGENTS = "agents"
OBS = (AGENTS, "observation")
ACTION = (AGENTS, "action")
MASK = (AGENTS, "action_mask")
REWARD = (AGENTS, "reward")
POSITION = (AGENTS, "position")
BEAM_PRIORITY = (AGENTS, "beam_priority")
FALLBACK = (AGENTS, "mask_fallback")
DIAG = "diagnostics"

N_ACTIONS = 4
ACTION_NAMES = ("up", "right", "down", "left")  # +y, +x, −y, −x
_UNIT_MOVES = torch.tensor([[0.0, 1.0], [1.0, 0.0], [0.0, -1.0], [-1.0, 0.0]])

AGENT_OUT = ("observation", "action_mask", "position", "beam_priority", "reward")
DIAG_KEYS = (  # every one is a float [n_envs]
    "served_fraction", "collisions", "proximity", "fallbacks", "illegal_moves",
    "min_pair_distance", "closest_approach",
    "ep_return", "ep_collisions", "ep_proximity", "ep_fallbacks", "pg",
)


@dataclass(frozen=True)
class EnvParams:
    """Every number the step math needs, derived once from the configs."""

    n_uabs: int
    width: float
    height: float
    dt: float
    step_m: float  # v·δt
    altitude: float
    episode_steps: int
    window_steps: int
    nhat_s: int
    lambda_s: float
    lambda_c: float
    collision_distance: float
    d_th: float
    lattice: bool
    safe_start: bool
    obs_scale: float
    time_is_terminal: bool
    # channel
    fc_ghz: float
    h_ut: float
    tx_dbm: float
    tx_gain_db: float
    noise_dbm: float
    snr_th_db: float
    n_beams: int
    r_b: float
    gain_db: float
    outside_gain_db: float | None
    los_mode: str
    shadow: bool
    sigma_los: float
    sigma_nlos: float

    @classmethod
    def from_config(cls, scenario: Any, channel: Any) -> EnvParams:
        validate_env(scenario, channel)
        d_th = scenario.safety_distance
        if d_th is None:
            d_th = ch.safety_distance(scenario.altitude, channel.fov_deg)
        return cls(
            n_uabs=scenario.n_uabs, width=scenario.area.width, height=scenario.area.height,
            dt=scenario.dt, step_m=scenario.speed * scenario.dt, altitude=scenario.altitude,
            episode_steps=scenario.episode_steps, window_steps=scenario.window_steps,
            nhat_s=scenario.nhat_s, lambda_s=scenario.lambda_s, lambda_c=scenario.lambda_c,
            collision_distance=scenario.collision_distance, d_th=float(d_th),
            lattice=scenario.lattice, safe_start=scenario.safe_start,
            obs_scale=scenario.priority_obs_scale, time_is_terminal=scenario.time_is_terminal,
            fc_ghz=channel.carrier_ghz, h_ut=channel.ue_height, tx_dbm=channel.tx_power_dbm,
            tx_gain_db=channel.tx_gain_db, noise_dbm=channel.noise_dbm,
            snr_th_db=channel.snr_threshold_db, n_beams=channel.n_beams,
            r_b=ch.beam_footprint_radius(scenario.altitude, channel.fov_deg, channel.n_beams),
            gain_db=ch.beam_gain_db(channel.fov_deg, channel.n_beams),
            outside_gain_db=channel.outside_beam_gain_db, los_mode=channel.los_mode,
            shadow=channel.shadow_fading, sigma_los=channel.shadow_sigma_los_db,
            sigma_nlos=channel.shadow_sigma_nlos_db,
        )

    @property
    def obs_dim(self) -> int:
        return 3 + 2 * self.n_uabs + self.n_beams


class ServiceRadii:
    """Horizontal distances within which a link's SNR reaches SNR_th, for one receive
    gain: ``r_los`` if LoS, ``r_nlos`` if NLoS, ``r_exp`` with the expected path loss.
    Valid without shadowing (the path loss then grows with distance)."""

    def __init__(self, p: EnvParams, gain_db: float, reach: float):
        self.p = p
        f = lambda pl: ch.snr_db(pl, p.tx_dbm, p.tx_gain_db, gain_db, p.noise_dbm)  # noqa: E731

        def pl(kind: str):
            def fn(d: torch.Tensor) -> torch.Tensor:
                d3 = (d * d + (p.altitude - p.h_ut) ** 2).sqrt()
                los = ch.pathloss_los(d, d3, p.altitude, p.h_ut, p.fc_ghz)
                nlos = ch.pathloss_nlos(d, d3, p.altitude, p.h_ut, p.fc_ghz)
                rho = ch.los_probability(d, p.h_ut)
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
            return d2 <= self.r_los ** 2
        if mode == "expected":
            return d2 <= self.r_exp ** 2
        sure = d2 <= self.r_nlos ** 2
        if not self.needs_draw:
            return sure
        maybe = d2 <= self.r_los ** 2
        los = torch.rand(d2.shape, generator=gen, device=d2.device) < ch.los_probability(
            d2.sqrt(), self.p.h_ut)
        return sure | (maybe & los)


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


class StepMath:
    """The environment's tensor math, free of TensorDict. All state is ``[E, ...]``."""

    def __init__(self, p: EnvParams, device: torch.device):
        self.p = p
        self.device = device
        self.moves = (_UNIT_MOVES * p.step_m).to(device)  # [4, 2]
        self.area = torch.tensor([p.width, p.height], device=device)
        # lattice: pitch v·δt, centred in the area
        n = torch.floor(self.area / p.step_m).long() + 1  # lattice points per axis
        self.lattice_n = n
        self.lattice_lo = (self.area - (n - 1).float() * p.step_m) / 2.0
        self.arange_n1 = torch.arange(p.window_steps + 1, device=device)
        self.eye = torch.eye(p.n_uabs, dtype=torch.bool, device=device)
        # beam index space of all agents: agent u's beams are u·B .. u·B + B − 1
        self.agent_offset = (torch.arange(p.n_uabs, device=device, dtype=torch.float32)
                             * p.n_beams)[None, :, None]
        # Without shadowing the SNR falls monotonically with distance, so "served" is
        # "closer than a radius" (per LoS state): exact, and far cheaper than the SNR.
        self.radii: dict[float, ServiceRadii] = {}
        if not p.shadow:
            gains = [p.gain_db] + ([p.outside_gain_db] if p.outside_gain_db is not None else [])
            reach = 3.0 * p.r_b * math.sqrt(2.0) if p.outside_gain_db is None else math.hypot(
                p.width, p.height)  # farthest link that can be a candidate
            self.radii = {g: ServiceRadii(p, g, reach) for g in gains}
        self.always_served = p.outside_gain_db is None and bool(self.radii) and \
            self.radii[p.gain_db].always_within(reach)
        self.beam_k = ch.beam_grid_side(p.n_beams)
        self.inv_pitch = 1.0 / (2.0 * p.r_b)

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
        s0 = torch.rand(n_envs, 1, generator=gen, device=dev) * perim
        ring = self.perimeter_point(s0 + k * perim / max(p.n_uabs - 1, 1))  # [E, M-1, 2]
        c = candidates if p.safe_start and p.n_uabs > 1 else 1
        if p.lattice:
            ix = torch.randint(0, int(self.lattice_n[0]), (n_envs, c), generator=gen, device=dev)
            iy = torch.randint(0, int(self.lattice_n[1]), (n_envs, c), generator=gen, device=dev)
            inner = self.lattice_point(ix.float(), iy.float())  # [E, C, 2]
        else:
            inner = torch.rand(n_envs, c, 2, generator=gen, device=dev) * self.area
        if c > 1:
            mind = torch.cdist(inner, ring).amin(-1)  # [E, C]
            ok = mind >= p.d_th
            pick = torch.where(ok.any(-1), ok.int().argmax(-1), mind.argmax(-1))
            inner = inner.gather(1, pick[:, None, None].expand(-1, 1, 2))
        return torch.cat([inner[:, :1], ring], dim=1)

    # ------------------------------------------------------------------ geometry
    def boundary_mask(self, pos: torch.Tensor) -> torch.Tensor:
        """[E, M, 4] True where the move (up, right, down, left) keeps the UABS inside."""
        x, y, s = pos[..., 0], pos[..., 1], self.p.step_m
        return torch.stack([y + s <= self.p.height, x + s <= self.p.width,
                            y - s >= 0.0, x - s >= 0.0], dim=-1)

    def pair_distances(self, pos: torch.Tensor) -> torch.Tensor:
        """[E, M, M] distances, +inf on the diagonal."""
        d = torch.cdist(pos, pos)
        return d.masked_fill(self.eye, math.inf)

    def closest_approach(self, old: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
        """[E] smallest pair distance along the straight paths from ``old`` to ``new``."""
        r0 = old[:, :, None, :] - old[:, None, :, :]  # [E, M, M, 2]
        dv = (new - old)[:, :, None, :] - (new - old)[:, None, :, :]
        s = (-(r0 * dv).sum(-1) / (dv * dv).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
        d = (r0 + s[..., None] * dv).norm(dim=-1).masked_fill(self.eye, math.inf)
        return d.flatten(1).amin(-1)

    # ------------------------------------------------------------------ service
    def links(self, pos: torch.Tensor, veh: torch.Tensor, present: torch.Tensor,
              gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Footprint membership ``inside [E,M,V]``, beam index ``[E,M,V]`` (all agents'
        beams in one index space: u·B + i) and served flags ``[E,V]``, for vehicles
        ``veh [E,2,V]`` (planar) under UABS at ``pos [E,M,2]``."""
        p, k, half, inv = self.p, self.beam_k, (self.beam_k - 1) / 2.0, self.inv_pitch
        # beam-grid coordinates of every link, from [E,V] and [E,M] pieces: one
        # [E,M,V] subtraction per axis
        vx, vy = veh[:, 0, :] * inv, veh[:, 1, :] * inv
        ux, uy = pos[..., 0] * inv - half, pos[..., 1] * inv + half
        gx = vx[:, None, :] - ux[:, :, None]
        gy = uy[:, :, None] - vy[:, None, :]
        if not self.always_served:
            d2 = ((gx - half) ** 2 + (gy - half) ** 2) * (2.0 * p.r_b) ** 2
        inside, beam = ch.beam_cells(gx, gy, k, self.agent_offset)
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

    def snr(self, d2d_sq: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
        """SNR in dB without the receive gain, per link (LoS state per ``los_mode``)."""
        p = self.p
        d2d = d2d_sq.sqrt()
        d3d = (d2d_sq + (p.altitude - p.h_ut) ** 2).sqrt()
        pl_los = ch.pathloss_los(d2d, d3d, p.altitude, p.h_ut, p.fc_ghz)
        if p.los_mode == "los":
            pl, los = pl_los, None
        else:
            pl_nlos = ch.pathloss_nlos(d2d, d3d, p.altitude, p.h_ut, p.fc_ghz)
            rho = ch.los_probability(d2d, p.h_ut)
            if p.los_mode == "expected":
                pl, los = rho * pl_los + (1.0 - rho) * pl_nlos, None
            else:
                los = torch.rand(d2d.shape, generator=gen, device=d2d.device) < rho
                pl = torch.where(los, pl_los, pl_nlos)
        if p.shadow:
            sigma = p.sigma_los if los is None else torch.where(los, p.sigma_los, p.sigma_nlos)
            pl = pl + sigma * torch.randn(d2d.shape, generator=gen, device=d2d.device)
        return ch.snr_db(pl, p.tx_dbm, p.tx_gain_db, 0.0, p.noise_dbm)

    def beam_sums(self, inside: torch.Tensor, beam: torch.Tensor,
                  priority: torch.Tensor) -> torch.Tensor:
        """b: [E, M, B] sum of the priorities of the vehicles under each beam
        (``beam`` indexes all agents' beams at once, as ``links`` returns it)."""
        e, m, v = inside.shape
        idx = beam.reshape(e, m * v)
        src = torch.where(inside, priority[:, None, :], 0.0).reshape(e, m * v)
        b = torch.zeros(e, m * self.p.n_beams, device=priority.device, dtype=priority.dtype)
        return b.scatter_add_(1, idx, src).view(e, m, self.p.n_beams)

    # ------------------------------------------------------------------ priorities
    def update_service(self, st: dict[str, torch.Tensor], served: torch.Tensor,
                       present: torch.Tensor) -> None:
        """Priorities, per-window served counts and the P_g tallies (SPEC §4), in place.
        ``st["t"]`` is the step the flags belong to."""
        n = self.p.window_steps
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

    def pg_curve(self, n_windows: torch.Tensor, ns_hist: torch.Tensor) -> torch.Tensor:
        """P_g(N̂_s) for N̂_s = 1..N, [E, N]: mean over GUEs with a counted window of the
        share of their windows with N_s ≥ N̂_s."""
        counted = n_windows > 0
        inv = torch.where(counted, 1.0 / n_windows.clamp_min(1.0), torch.zeros_like(n_windows))
        per_ns = torch.bmm(inv[:, None, :], ns_hist).squeeze(1)  # [E, N+1] Σ_g share(N_s = j)
        at_least = per_ns.flip(-1).cumsum(-1).flip(-1)[:, 1:]  # Σ_g share(N_s ≥ k), k = 1..N
        return at_least / counted.sum(-1, keepdim=True).clamp_min(1)

    # ------------------------------------------------------------------ reward
    def rewards(self, b: torch.Tensor, dist: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """r [E, M] (paper eq. 3) and per-env collision / proximity pair counts."""
        p = self.p
        coll = dist < p.collision_distance
        prox = dist < p.d_th
        r = b.sum(-1).masked_fill_(prox.any(-1), -p.lambda_s).masked_fill_(coll.any(-1),
                                                                          -p.lambda_c)
        return r, coll.flatten(1).sum(-1) / 2.0, prox.flatten(1).sum(-1) / 2.0

    def observation(self, pos: torch.Tensor, t: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """o = (x/W, y/H, t/T, L_t, b_t / scale): [E, M, 3 + 2M + B]."""
        e, m, _ = pos.shape
        norm = pos / self.area
        tt = (t.float() / self.p.episode_steps)[:, None, None].expand(e, m, 1)
        fleet = norm.reshape(e, 1, 2 * m).expand(e, m, 2 * m)
        return torch.cat([norm, tt, fleet, b / self.p.obs_scale], dim=-1)


    # ------------------------------------------------------------------ one step
    def step(self, st: dict[str, torch.Tensor], action: torch.Tensor, veh_pos: torch.Tensor,
             veh_present: torch.Tensor, gen: torch.Generator,
             fallback: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Advance the state ``st`` in place by one step; return the flat outputs.
        ``action [E, M]``; ``fallback [E, M]`` flags agents whose mask was empty."""
        action = action.long()
        old = st["pos"]
        legal = self.boundary_mask(old).gather(-1, action[..., None]).squeeze(-1)  # [E, M]
        new = torch.where(legal[..., None], old + self.moves[action], old)
        st["pos"] = new
        st["t"] = st["t"] + 1
        veh, present = vehicles_at(st, veh_pos, veh_present)
        inside, beam, served = self.links(new, veh, present, gen)
        self.update_service(st, served, present)
        st["b"] = self.beam_sums(inside, beam, st["priority"])
        dist = self.pair_distances(new)
        reward, n_coll, n_prox = self.rewards(st["b"], dist)
        n_fb = (fallback.float().flatten(1).sum(-1) if fallback is not None
                else torch.zeros_like(n_coll))
        st["ep_return"] = st["ep_return"] + reward.sum(-1)
        st["ep_collisions"] = st["ep_collisions"] + n_coll
        st["ep_proximity"] = st["ep_proximity"] + n_prox
        st["ep_fallbacks"] = st["ep_fallbacks"] + n_fb
        step_diag = {"collisions": n_coll, "proximity": n_prox, "fallbacks": n_fb,
                     "illegal_moves": (~legal).float().sum(-1),
                     "min_pair_distance": dist.flatten(1).amin(-1).clamp_max(1e6),
                     "closest_approach": self.closest_approach(old, new).clamp_max(1e6)}
        out = self.outputs(st, served, present, step_diag)
        out["reward"] = reward[..., None]
        return out

    def outputs(self, st: dict[str, torch.Tensor], served: torch.Tensor,
                present: torch.Tensor, diag: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Observation, masks, flags and diagnostics of the current state."""
        p = self.p
        done = (st["t"] >= p.episode_steps)[:, None]  # [E, 1]
        never = torch.zeros_like(done)
        pg_curve = self.pg_curve(st["n_windows"], st["ns_hist"])
        return dict(
            diag, observation=self.observation(st["pos"], st["t"], st["b"]),
            action_mask=self.boundary_mask(st["pos"]), position=st["pos"],
            beam_priority=st["b"], done=done,
            terminated=done if p.time_is_terminal else never,
            truncated=never if p.time_is_terminal else done,
            served_fraction=served.float().sum(-1) / present.float().sum(-1).clamp_min(1.0),
            ep_return=st["ep_return"], ep_collisions=st["ep_collisions"],
            ep_proximity=st["ep_proximity"], ep_fallbacks=st["ep_fallbacks"],
            pg=pg_curve[:, p.nhat_s - 1], pg_curve=pg_curve)


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


class UABSEnv(EnvBase):
    """M UABS over replayed vehicle traces; see the module docstring for the step order.

    ``mode="train"`` draws a random T-step window of the traces at each reset;
    ``mode="eval"`` walks ``n_eval_windows`` fixed, non-overlapping windows: env ``i``
    gets window ``i``, then ``i + n_envs``, ... (mod the number of windows).
    ``compile_step=True`` runs the step math through ``torch.compile`` (``compile`` is
    TorchRL's own argument, which compiles ``step_and_maybe_reset`` as a whole).
    """

    batch_locked = True

    def __init__(self, scenario: Any, channel: Any, traces: TraceSet, n_envs: int = 1,
                 mode: str = "train", device: str | torch.device = "cpu",
                 n_eval_windows: int | None = None, seed: int | None = None,
                 compile_step: bool = False):
        if mode not in ("train", "eval"):
            raise ConfigError(f"mode must be 'train' or 'eval', got {mode!r}")
        if n_envs < 1:
            raise ConfigError(f"n_envs must be >= 1, got {n_envs}")
        device = torch.device(device)
        super().__init__(batch_size=torch.Size([n_envs]), device=device)
        self.params = p = EnvParams.from_config(scenario, channel)
        self.math = StepMath(p, device)
        self.mode = mode
        self.n_envs = n_envs
        self._check_traces(traces, scenario)
        # planar layout [S, steps, 2, V]: x and y rows stay contiguous per step
        self.register_buffer("veh_pos", traces.positions.transpose(-1, -2).contiguous().to(device))
        self.register_buffer("veh_present", traces.present.to(device))  # [S, steps, V]
        self._windows = self._eval_windows(n_eval_windows) if mode == "eval" else None
        self.rng = torch.Generator(device=device)
        self.rng.manual_seed(0 if seed is None else seed)
        self._state = self._empty_state()
        self._make_specs()
        # torch.compile fuses the step's many small tensor ops: ~7x faster at n_envs = 1
        # on CPU (benchmarks/env_bench.py); costs ~10 s of compilation at the first step
        self._step_math = compiled_or_eager(self.math.step, "the env step") if compile_step \
            else self.math.step

    # ------------------------------------------------------------------ set-up
    def _check_traces(self, traces: TraceSet, scenario: Any) -> None:
        need = self.params.episode_steps + 1
        if traces.steps < need:
            raise ConfigError(
                f"the {traces.meta.get('split', '?')} traces hold {traces.steps} steps but an "
                f"episode needs scenario.episode_steps + 1 = {need}: raise "
                f"traces.<split>.duration_s or lower scenario.episode_steps.")
        if abs(float(traces.meta.get("dt", scenario.dt)) - scenario.dt) > 1e-9:
            raise ConfigError(f"the traces were sampled every {traces.meta['dt']} s but "
                              f"scenario.dt is {scenario.dt}: rebuild the traces.")

    def _eval_windows(self, n: int | None) -> torch.Tensor:
        """[K, 2] (sim, start) of non-overlapping held-out windows, sims interleaved."""
        s, steps = self.veh_pos.shape[:2]
        per_sim = steps // (self.params.episode_steps + 1)
        n = s * per_sim if n is None else n
        if not 1 <= n <= s * per_sim:
            raise ConfigError(
                f"n_eval_windows={n} but the held-out traces hold {s * per_sim} "
                f"non-overlapping windows of {self.params.episode_steps + 1} steps: lower it "
                f"or raise traces.eval.n_sims / traces.eval.duration_s.")
        k = torch.arange(n, device=self.device)
        return torch.stack([k % s, (k // s) * (self.params.episode_steps + 1)], dim=-1)

    def _empty_state(self) -> dict[str, torch.Tensor]:
        e, m, v = self.n_envs, self.params.n_uabs, self.veh_pos.shape[3]
        n, dev = self.params.window_steps, self.device
        z = lambda *s, dt=torch.float32: torch.zeros(*s, dtype=dt, device=dev)  # noqa: E731
        return {
            "pos": z(e, m, 2), "t": z(e, dt=torch.long), "sim": z(e, dt=torch.long),
            "start": z(e, dt=torch.long), "cursor": torch.arange(e, device=dev),
            "priority": z(e, v), "served_count": z(e, v, dt=torch.long),
            "window_full": z(e, v, dt=torch.bool), "prev_present": z(e, v, dt=torch.bool),
            "n_windows": z(e, v), "ns_hist": z(e, v, n + 1), "b": z(e, m, self.params.n_beams),
            **{f"ep_{k}": z(e) for k in ("return", "collisions", "proximity", "fallbacks")},
        }

    def _make_specs(self) -> None:
        e, m, p = self.n_envs, self.params.n_uabs, self.params
        dev = self.device
        agents = Composite(
            observation=Unbounded((e, m, p.obs_dim), device=dev),
            action_mask=Binary(n=N_ACTIONS, shape=(e, m, N_ACTIONS), dtype=torch.bool,
                               device=dev),
            position=Unbounded((e, m, 2), device=dev),  # metres, for the masks
            beam_priority=Unbounded((e, m, p.n_beams), device=dev),  # raw b_t, for ranks
            shape=(e, m), device=dev)
        diag = Composite({k: Unbounded((e,), device=dev) for k in DIAG_KEYS},
                         pg_curve=Unbounded((e, p.window_steps), device=dev),
                         shape=(e,), device=dev)
        self.observation_spec = Composite(agents=agents, diagnostics=diag, shape=(e,),
                                          device=dev)
        self.action_spec = Composite(
            agents=Composite(action=Categorical(N_ACTIONS, shape=(e, m), device=dev),
                             shape=(e, m), device=dev), shape=(e,), device=dev)
        self.reward_spec = Composite(
            agents=Composite(reward=Unbounded((e, m, 1), device=dev), shape=(e, m),
                             device=dev), shape=(e,), device=dev)
        flag = lambda *s: Categorical(2, shape=s, dtype=torch.bool, device=dev)  # noqa: E731
        self.done_spec = Composite(
            done=flag(e, 1), terminated=flag(e, 1), truncated=flag(e, 1),
            agents=Composite(done=flag(e, m, 1), terminated=flag(e, m, 1),
                             truncated=flag(e, m, 1), shape=(e, m), device=dev),
            shape=(e,), device=dev)

    def _set_seed(self, seed: int | None) -> None:
        """Seeds start positions, windows and LoS draws; in eval mode it also rewinds to
        the first held-out windows, so every seeded evaluation sees the same episodes."""
        self.rng.manual_seed(int(seed) if seed is not None else 0)
        self._state["cursor"] = torch.arange(self.n_envs, device=self.device)

    # ------------------------------------------------------------------ traces
    def _draw_windows(self, st: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        if self.mode == "eval":
            w = self._windows[st["cursor"] % self._windows.shape[0]]
            return w[:, 0], w[:, 1]
        s, steps = self.veh_pos.shape[:2]
        sim = torch.randint(0, s, (self.n_envs,), generator=self.rng, device=self.device)
        hi = steps - self.params.episode_steps
        start = torch.randint(0, hi, (self.n_envs,), generator=self.rng, device=self.device)
        return sim, start

    # ------------------------------------------------------------------ reset / step
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        st = self._state
        if tensordict is not None and "_reset" in tensordict.keys():
            mask = tensordict["_reset"].reshape(self.n_envs)
        else:
            mask = torch.ones(self.n_envs, dtype=torch.bool, device=self.device)
        fresh = self._empty_state()
        fresh["sim"], fresh["start"] = self._draw_windows(st)
        fresh["pos"] = self.math.start_positions(self.n_envs, self.rng)
        veh, present = vehicles_at(fresh, self.veh_pos, self.veh_present)
        inside, beam, served = self.math.links(fresh["pos"], veh, present, self.rng)
        self.math.update_service(fresh, served, present)
        fresh["b"] = self.math.beam_sums(inside, beam, fresh["priority"])
        for k, v in fresh.items():
            if k == "cursor":
                continue
            m = mask.view(-1, *([1] * (v.dim() - 1)))
            st[k] = torch.where(m, v, st[k])
        if self.mode == "eval":  # the next reset of env i takes window i + n_envs, ...
            st["cursor"] = st["cursor"] + mask.long() * self.n_envs
        zeros = torch.zeros(self.n_envs, device=self.device)
        return self._pack(self.math.outputs(st, served, present,
                                            {k: zeros for k in DIAG_KEYS}))

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        fb = tensordict.get(FALLBACK, None)
        out = self._step_math(self._state, tensordict.get(ACTION), self.veh_pos,
                              self.veh_present, self.rng, fb)
        return self._pack(out)

    def _pack(self, out: dict[str, torch.Tensor]) -> TensorDict:
        """The step math's flat outputs as the env's TensorDict (see the specs)."""
        e, m = self.n_envs, self.params.n_uabs
        flags = lambda f: f[:, None, :].expand(e, m, 1)  # noqa: E731
        agents = {k: out[k] for k in AGENT_OUT if k in out}
        agents.update(done=flags(out["done"]), terminated=flags(out["terminated"]),
                      truncated=flags(out["truncated"]))
        return TensorDict({
            AGENTS: TensorDict(agents, batch_size=(e, m), device=self.device),
            "done": out["done"], "terminated": out["terminated"], "truncated": out["truncated"],
            DIAG: TensorDict({k: out[k] for k in (*DIAG_KEYS, "pg_curve")}, batch_size=(e,),
                             device=self.device),
        }, batch_size=(e,), device=self.device)
