"""``EnvParams``: every number the environment's physics needs, derived once from the
scenario and channel configs (docs/model.md §1, §3-§5)."""

from __future__ import annotations

from dataclasses import dataclass

from uabs_rl.config import (
    ChannelConfig,
    LosMode,
    ObsConfig,
    ObsFrame,
    RunConfig,
    ScenarioConfig,
    validate_env,
    validate_masking,
    validate_obs,
    validate_scenario_traces,
)
from uabs_rl.env import channel as ch


def validate_world(cfg: RunConfig) -> None:
    """The start-up checks of the world a policy acts in (scenario, traces, channel,
    masking; and the observation), each naming the key: what ``uabs-eval`` checks, and
    part of :func:`uabs_rl.training.startup.validate_run`. (:class:`EnvParams` checks the
    env settings again, so an env built from the library is guarded too.)"""
    validate_scenario_traces(cfg.scenario, cfg.traces)
    validate_env(cfg.scenario, cfg.channel, ch.CHANNELS)
    validate_obs(cfg.obs)
    validate_masking(cfg.masking)


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
    # the observation (ObsConfig)
    obs_scale: float
    lookahead_obs: bool
    motion_obs: bool
    motion_steps: int
    egocentric: bool
    map_radius: int
    neighbours: int
    neighbour_range: float  # lattice steps
    edge_range: float  # lattice steps
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
    los_mode: LosMode
    shadow: bool
    sigma_los: float
    sigma_nlos: float
    channel: str  # channel.name: the model of uabs_rl.env.channel.CHANNELS

    @classmethod
    def from_config(cls, scenario: ScenarioConfig, channel: ChannelConfig,
                    obs: ObsConfig | None = None) -> EnvParams:
        """``obs`` None: the paper's observation."""
        obs = ObsConfig() if obs is None else obs
        validate_env(scenario, channel, ch.CHANNELS)
        validate_obs(obs)
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
            obs_scale=obs.priority_scale, lookahead_obs=obs.lookahead, motion_obs=obs.motion,
            motion_steps=obs.motion_steps,
            egocentric=obs.frame == ObsFrame.egocentric, map_radius=obs.map_radius,
            neighbours=obs.neighbours, neighbour_range=obs.neighbour_range,
            edge_range=obs.edge_range,
            time_is_terminal=scenario.time_is_terminal,
            fc_ghz=channel.carrier_ghz, h_ut=channel.ue_height, tx_dbm=channel.tx_power_dbm,
            tx_gain_db=channel.tx_gain_db, noise_dbm=channel.noise_dbm,
            snr_th_db=channel.snr_threshold_db, n_beams=channel.n_beams,
            r_b=ch.beam_footprint_radius(scenario.altitude, channel.fov_deg, channel.n_beams),
            gain_db=ch.beam_gain_db(channel.fov_deg, channel.n_beams),
            outside_gain_db=channel.outside_beam_gain_db, los_mode=LosMode(channel.los_mode),
            shadow=channel.shadow_fading, sigma_los=channel.shadow_sigma_los_db,
            sigma_nlos=channel.shadow_sigma_nlos_db, channel=channel.name,
        )

    @property
    def obs_dim(self) -> int:
        """One agent's observation size (``uabs_rl.env.observe``): the egocentric one's
        depends on neither the fleet size nor the area."""
        if self.egocentric:
            return 1 + self.n_beams + self.n_lookahead + 3 * self.neighbours + 4
        return 3 + 2 * self.n_uabs + self.n_beams + self.n_lookahead

    @property
    def n_lookahead(self) -> int:
        """Priority scores per agent: egocentric, the local map's (2r + 1)^2 lattice
        points (twice with ``motion_obs``); else 4 moves and 4 double moves (and, with
        ``motion_obs``, 4 moves at the vehicle positions extrapolated one step, then 4 per
        k = 2 .. ``motion_steps``: k moves along each direction at those extrapolated k
        steps), or none."""
        if self.egocentric:
            return (2 * self.map_radius + 1) ** 2 * (1 + self.motion_obs)
        if not self.lookahead_obs:
            return 0
        return 8 + 4 * self.motion_obs * self.motion_steps
