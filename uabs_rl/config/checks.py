"""The per-section checks that run at start-up, each naming the offending key in a
:class:`~uabs_rl.config.base.ConfigError`: value checks a type cannot express (a fleet of
0, disjoint trace seeds, a NaN, ...). The checks that need the env or a learner run above
them (:func:`uabs_rl.env.params.validate_world`, :mod:`uabs_rl.training.startup`)."""

from __future__ import annotations

import math
from collections.abc import Collection
from dataclasses import is_dataclass, replace
from typing import Any

from omegaconf import DictConfig, OmegaConf

import uabs_rl.config.memory as memory
from uabs_rl.config.base import (
    RANGES,
    SEED_END,
    SEED_MIN,
    SUMO_SEED_MAX,
    ConfigError,
    LoggerKind,
    LosMode,
    LossKind,
    MaskingMode,
    ObsFrame,
    RankNextMask,
    ReplayKind,
    _raise_first,
    check_finite,
    check_ranges,
    enum_value,
)
from uabs_rl.config.schema import (
    FAMILY_KEYS,
    TRACE_SPLITS,
    AlgoConfig,
    ChannelConfig,
    DqfdConfig,
    MaskingConfig,
    ObsConfig,
    QmixConfig,
    RunConfig,
    ScenarioConfig,
    SplitConfig,
    TracesConfig,
    algo_schema,
)


def validate_masking(masking: MaskingConfig) -> None:
    """Value checks for the masking settings, each naming the offending key."""
    check_finite(masking, "masking.")
    enum_value(MaskingMode, masking.mode, "masking.mode (select it with masking=...)")
    enum_value(RankNextMask, masking.rank_next_mask, "masking.rank_next_mask")
    for key in ("flat_margin", "collider_margin"):
        v = getattr(masking, key)
        if v is not None and v < 0:
            raise ConfigError(f"masking.{key} must be null or >= 0, got {v}.")
    check_ranges(masking, "masking.")


def validate_obs(obs: ObsConfig) -> None:
    """Value checks for the observation, each naming the offending key."""
    check_finite(obs, "obs.")
    ego = enum_value(ObsFrame, obs.frame, "obs.frame") == ObsFrame.egocentric
    _raise_first([
        (obs.priority_scale > 0, "obs.priority_scale", "must be > 0", obs.priority_scale),
        (not (ego and obs.lookahead), "obs.lookahead", "must be false with "
         "obs.frame=egocentric (its local map holds the lookahead scores)", obs.lookahead),
        (obs.lookahead or ego or not obs.motion, "obs.motion", "needs obs.lookahead=true "
         "or obs.frame=egocentric (it extends their scores)", obs.motion),
        (obs.motion_steps == 1 or (obs.motion and not ego), "obs.motion_steps",
         "must be 1 unless obs.motion=true with obs.frame=fleet (it extends the fleet "
         "frame's motion scores)", obs.motion_steps),
        (obs.map_radius >= 0, "obs.map_radius", "must be >= 0 (lattice steps)",
         obs.map_radius),
        (obs.neighbours >= 0, "obs.neighbours", "must be >= 0", obs.neighbours),
        (obs.neighbour_range > 0, "obs.neighbour_range", "must be > 0 (lattice steps)",
         obs.neighbour_range),
        (obs.edge_range > 0, "obs.edge_range", "must be > 0 (lattice steps)",
         obs.edge_range),
    ])
    check_ranges(obs, "obs.")


# settings that moved: (section, old key) -> (section, new key); stored configs are


def validate_env(scenario: ScenarioConfig, channel: ChannelConfig,
                 channels: Collection[str] | None = None) -> None:
    """Value checks for the environment, each naming the offending key; ``channels``:
    the channel models ``channel.name`` must be one of (the env's ``CHANNELS``, passed
    by the env, which owns them; None: not checked here)."""
    check_finite(scenario, "scenario.")
    check_finite(channel, "channel.")
    checks = [
        (scenario.n_uabs >= 1, "scenario.n_uabs", "must be >= 1", scenario.n_uabs),
        (scenario.altitude > channel.ue_height, "scenario.altitude",
         "must exceed channel.ue_height", scenario.altitude),
        (scenario.speed > 0, "scenario.speed", "must be > 0", scenario.speed),
        (scenario.episode_steps >= 1, "scenario.episode_steps", "must be >= 1",
         scenario.episode_steps),
        (1 <= scenario.window_steps <= scenario.episode_steps, "scenario.window_steps",
         "must be in 1..scenario.episode_steps (a longer window never completes in an "
         "episode, so P_g would be 0)", scenario.window_steps),
        (1 <= scenario.nhat_s <= scenario.window_steps, "scenario.nhat_s",
         "must be in 1..scenario.window_steps", scenario.nhat_s),
        (scenario.lambda_s >= 0, "scenario.lambda_s", "must be >= 0 (the proximity "
         "penalty's size)", scenario.lambda_s),
        (scenario.lambda_c >= 0, "scenario.lambda_c", "must be >= 0 (the collision "
         "penalty's size)", scenario.lambda_c),
        (scenario.collision_distance > 0, "scenario.collision_distance", "must be > 0",
         scenario.collision_distance),
        (scenario.safety_distance is None or scenario.safety_distance
         >= scenario.collision_distance, "scenario.safety_distance",
         "must be null or >= scenario.collision_distance", scenario.safety_distance),
        (min(scenario.area.width, scenario.area.height) >= scenario.speed * scenario.dt,
         "scenario.area", f"must be at least v·δt (scenario.speed x scenario.dt = "
         f"{scenario.speed * scenario.dt:g} m) wide and high so every UABS can move",
         (scenario.area.width, scenario.area.height)),
        (channel.carrier_ghz > 0, "channel.carrier_ghz", "must be > 0", channel.carrier_ghz),
        (channel.ue_height >= 0, "channel.ue_height", "must be >= 0 (m above ground)",
         channel.ue_height),
        (channel.shadow_sigma_los_db >= 0, "channel.shadow_sigma_los_db",
         "must be >= 0 (a standard deviation)", channel.shadow_sigma_los_db),
        (channel.shadow_sigma_nlos_db >= 0, "channel.shadow_sigma_nlos_db",
         "must be >= 0 (a standard deviation)", channel.shadow_sigma_nlos_db),
        (0 < channel.fov_deg < 180, "channel.fov_deg", "must be in (0, 180)", channel.fov_deg),
        (channel.n_beams >= 1 and round(channel.n_beams ** 0.5) ** 2 == channel.n_beams,
         "channel.n_beams", "must be a square number (k x k beam grid)", channel.n_beams),
    ]
    _raise_first(checks)
    enum_value(LosMode, channel.los_mode, "channel.los_mode")
    if channels is not None and channel.name not in channels:
        raise ConfigError(f"channel.name={channel.name!r} is not a channel model: use one of "
                          f"{', '.join(sorted(channels))} (uabs_rl.env.channel.CHANNELS).")
    check_ranges(scenario, "scenario.")
    check_ranges(channel, "channel.")
    points = lattice_points(scenario)
    if points > MAX_LATTICE_POINTS:
        shown = points if points < 1e6 else format(points, ".3g")
        raise ConfigError(
            f"scenario.area / (scenario.speed x scenario.dt) must give at most "
            f"{MAX_LATTICE_POINTS} lattice points (the start positions compare every pair "
            f"of them), got {shown} ({scenario.area.width:g} m x {scenario.area.height:g} m "
            f"at a pitch of {scenario.speed * scenario.dt:g} m): raise scenario.speed or "
            f"scenario.dt, or shrink scenario.area.")


# the lattice of pitch v·δt over the area: the start-position packing
# (uabs_rl.env.geometry.lattice_packing) compares every pair of its points
MAX_LATTICE_POINTS = 20_000


def lattice_points(scenario: ScenarioConfig) -> int:
    """Points of the lattice of pitch v·δt over the area (``Geometry.lattice_n``)."""
    step = scenario.speed * scenario.dt
    return ((math.floor(scenario.area.width / step) + 1)
            * (math.floor(scenario.area.height / step) + 1))


def validate_scenario_traces(scenario: ScenarioConfig, traces: TracesConfig) -> None:
    """Value checks for the trace pipeline, each naming the offending key."""
    check_finite(scenario, "scenario.")
    check_finite(traces, "traces.")
    sumo = scenario.sumo
    if scenario.dt <= 0:
        raise ConfigError(f"scenario.dt must be > 0 seconds, got {scenario.dt}.")
    if scenario.area.width <= 0 or scenario.area.height <= 0:
        raise ConfigError(
            f"scenario.area.width/height must be > 0, got {scenario.area.width} x "
            f"{scenario.area.height}.")
    if sumo.fleet_size < 0:
        raise ConfigError(f"scenario.sumo.fleet_size must be >= 0, got {sumo.fleet_size}.")
    if sumo.fleet_size == 0 and not sumo.route_files and not sumo.sumocfg:
        raise ConfigError(
            "scenario.sumo.fleet_size is 0 and no scenario.sumo.route_files or "
            "scenario.sumo.sumocfg is given: there would be no vehicle. Set "
            "scenario.sumo.fleet_size >= 1 or give routes.")
    for key in ("dt", "area", "sumo"):  # what sizes the traces
        _check_field(scenario, key, "scenario.")
    host = memory.available_memory("cpu")  # traces are built and cached on the host
    for name in TRACE_SPLITS:
        _validate_split(name, getattr(traces, name), scenario, host)
    _check_disjoint_seeds(traces)
    _check_disjoint_times(scenario, traces)
    if traces.workers < 0:
        raise ConfigError(f"traces.workers must be >= 0, got {traces.workers}.")
    check_ranges(traces, "traces.")


def _check_field(obj: Any, name: str, prefix: str) -> None:
    """:func:`check_ranges` of the one field ``name`` of ``obj``."""
    value = getattr(obj, name)
    if is_dataclass(value):
        check_ranges(value, f"{prefix}{name}.")
        return
    rng = RANGES[type(obj)][name]
    if value is not None and not rng.holds(value):
        raise ConfigError(f"{prefix}{name} must be in {rng}, got {value!r}.")


def _validate_split(name: str, split: SplitConfig, scenario: ScenarioConfig,
                    host: tuple[int, str] | None) -> None:
    key = f"traces.{name}"
    _raise_first([
        (split.n_sims >= 1, f"{key}.n_sims", "must be >= 1", split.n_sims),
        (split.duration_s >= scenario.dt, f"{key}.duration_s", "must be >= scenario.dt",
         split.duration_s),
        (split.warmup_s >= 0, f"{key}.warmup_s", "must be >= 0", split.warmup_s),
        (split.first_seed >= 0, f"{key}.first_seed",
         "must be >= 0 (SUMO and numpy take non-negative seeds)", split.first_seed),
        (split.first_seed + split.n_sims - 1 <= SUMO_SEED_MAX,
         f"{key}.first_seed + {key}.n_sims - 1", f"(the last SUMO seed) must be <= "
         f"{SUMO_SEED_MAX} (SUMO's --seed is a 32-bit integer)",
         split.first_seed + split.n_sims - 1),
    ])
    check_ranges(split, f"{key}.")  # before sizing them: a huge size is no float
    memory.check_fits(f"{key}.n_sims x {key}.duration_s", memory.trace_bytes(scenario, split),
                f"the {name} traces", host, f"lower {key}.n_sims or {key}.duration_s")


def _check_disjoint_seeds(traces: TracesConfig) -> None:
    """Training, validation and test traces come from disjoint SUMO seed ranges."""
    ranges = {n: (getattr(traces, n).first_seed,
                  getattr(traces, n).first_seed + getattr(traces, n).n_sims - 1)
              for n in TRACE_SPLITS}
    for i, a in enumerate(TRACE_SPLITS):
        for b in TRACE_SPLITS[i + 1:]:
            (a0, a1), (b0, b1) = ranges[a], ranges[b]
            if a0 <= b1 and b0 <= a1:
                raise ConfigError(
                    f"traces.{b}.first_seed={b0} makes the {b} SUMO seeds overlap the {a} "
                    f"seeds {a0}..{a1}: training, validation (eval) and test traces must "
                    f"come from disjoint seeds. Move traces.{b}.first_seed past them.")


def fixed_demand(scenario: ScenarioConfig) -> bool:
    """Whether the scenario's vehicles (some of them) come from route files or a
    .sumocfg: a demand every SUMO seed replays, the same vehicles departing at the same
    times, so only disjoint time ranges make its splits independent."""
    return bool(scenario.sumo.route_files or scenario.sumo.sumocfg)


def demand_setting(scenario: ScenarioConfig) -> str:
    """The setting that holds a fixed demand (:func:`fixed_demand`), for messages."""
    return "scenario.sumo.sumocfg" if scenario.sumo.sumocfg else "scenario.sumo.route_files"


def split_begin(scenario: ScenarioConfig, traces: TracesConfig, name: str) -> float:
    """``traces.<name>.begin_s``, or where null: 0 for a fleet scenario, and for a
    fixed-demand one the end of the previous split's recorded range (train, eval, test
    in that order; train at 0), so the default splits are disjoint in time."""
    split = getattr(traces, name)
    if split.begin_s is not None:
        return float(split.begin_s)
    i = TRACE_SPLITS.index(name)
    if not fixed_demand(scenario) or i == 0:
        return 0.0
    prev = TRACE_SPLITS[i - 1]
    _, end = split_time_range(scenario, traces, prev)
    return max(0.0, end - split.warmup_s)


def split_time_range(scenario: ScenarioConfig, traces: TracesConfig,
                     name: str) -> tuple[float, float]:
    """The simulated seconds the split records: [warmup_s + begin, + duration_s)."""
    split = getattr(traces, name)
    start = split.warmup_s + split_begin(scenario, traces, name)
    return start, start + split.duration_s


def resolved_split(scenario: ScenarioConfig, traces: TracesConfig, name: str) -> SplitConfig:
    """``traces.<name>`` with ``begin_s`` set to :func:`split_begin`."""
    return replace(getattr(traces, name), begin_s=split_begin(scenario, traces, name))


def _check_disjoint_times(scenario: ScenarioConfig, traces: TracesConfig) -> None:
    """A fixed demand's training, validation and test traces record disjoint time
    ranges: under every seed they would otherwise hold the same vehicles at the same
    times. The refusal names a begin_s that was set (the later split's if both were)."""
    if not fixed_demand(scenario):
        return
    ranges = {n: split_time_range(scenario, traces, n) for n in TRACE_SPLITS}
    source = demand_setting(scenario)
    for i, a in enumerate(TRACE_SPLITS):
        for b in TRACE_SPLITS[i + 1:]:
            (a0, a1), (b0, b1) = ranges[a], ranges[b]
            if not (a0 < b1 and b0 < a1):
                continue
            moved, other = ((b, a) if getattr(traces, b).begin_s is not None
                            or getattr(traces, a).begin_s is None else (a, b))
            (m0, m1), (o0, o1) = ranges[moved], ranges[other]
            begin = split_begin(scenario, traces, moved)
            after = max(0.0, o1 - getattr(traces, moved).warmup_s)  # past the other's
            clear = _first_clear_begin(scenario, traces, moved)
            past = (f"Move traces.{moved}.begin_s past the {other} range (begin_s >= "
                    f"{after:g})")
            if clear is not None and clear != after:
                past = (f"Move traces.{moved}.begin_s to {clear:g} (the first start from "
                        f"which the {moved} range overlaps no other split's)")
            raise ConfigError(
                f"traces.{moved}.begin_s={begin:g} makes the {moved} time range "
                f"{m0:g}..{m1:g} s (warm-up {getattr(traces, moved).warmup_s:g} s "
                f"included) overlap the {other} range {o0:g}..{o1:g} s: the vehicles of "
                f"{source} depart at the same times under every SUMO seed, so training, "
                f"validation (eval) and test traces must come from disjoint time ranges. "
                f"{past}, or leave the begin_s settings null (the splits then follow one "
                f"another).")


def _first_clear_begin(scenario: ScenarioConfig, traces: TracesConfig,
                       moved: str) -> float | None:
    """The smallest ``traces.<moved>.begin_s`` at or after its own whose time range
    overlaps no other split's (the splits that follow it with a null begin_s move with
    it); None where none is found within a few steps."""
    split = getattr(traces, moved)
    begin = split_begin(scenario, traces, moved)
    for _ in range(2 * len(TRACE_SPLITS)):
        trial = replace(traces, **{moved: replace(split, begin_s=begin)})
        ranges = {n: split_time_range(scenario, trial, n) for n in TRACE_SPLITS}
        m0, m1 = ranges[moved]
        clash = [o1 for n, (o0, o1) in ranges.items() if n != moved and m0 < o1 and o0 < m1]
        if not clash:
            return begin
        begin = max(begin, max(clash) - split.warmup_s)
    return None


def family_scenarios(cfg: RunConfig) -> list[ScenarioConfig]:
    """The training cities of ``cfg.family``, each ``cfg.scenario`` with the entry's
    ``name``, ``area`` and ``sumo`` (checked, naming ``family[i]``); empty without a
    family."""
    out: list[ScenarioConfig] = []
    for i, entry in enumerate(cfg.family):
        key = f"family[{i}]"
        if not isinstance(entry, dict | DictConfig):
            raise ConfigError(f"{key} must be a mapping of {', '.join(FAMILY_KEYS)}, got "
                              f"{entry!r}.")
        other = sorted(set(entry) - set(FAMILY_KEYS))
        if other:
            raise ConfigError(
                f"{key}.{other[0]}: a family's cities share scenario's fleet, altitude and "
                f"episodes; a city sets only {', '.join(FAMILY_KEYS)}.")
        try:
            merged = OmegaConf.merge(OmegaConf.structured(cfg.scenario), entry)
        except Exception as e:  # OmegaConf's type and key errors: one line, the entry named
            raise ConfigError(f"{key}: {str(e).splitlines()[0]}") from None
        out.append(OmegaConf.to_object(merged))
    names = [s.name for s in out]
    dup = next((n for n in names if names.count(n) > 1), None)
    if dup is not None:
        raise ConfigError(f"family: two cities are named {dup!r}; give each its own name "
                          f"(it names its trace cache files).")
    return out


def validate_family(cfg: RunConfig, channels: Collection[str] | None = None) -> None:
    """The checks of each city of ``cfg.family`` (``channels``: as :func:`validate_env`),
    naming what a city sets as the family entry's (``family[i].area``)."""
    for i, city in enumerate(family_scenarios(cfg)):
        try:
            validate_scenario_traces(city, cfg.traces)
            validate_env(city, cfg.channel, channels)
        except ConfigError as e:  # what a city sets: name it as the family entry's
            raise ConfigError(str(e).replace("scenario.area", f"family[{i}].area")
                              .replace("scenario.sumo", f"family[{i}].sumo")) from None


def check_algo_schema(algo: AlgoConfig) -> None:
    """``algo`` holds the settings of the learner it names: ``algo=<name>`` selects both,
    ``algo.name=<name>`` alone would leave another learner's settings."""
    want = algo_schema(algo.name)
    if type(algo) is not want:
        raise ConfigError(f"algo.name={algo.name} with the settings of {type(algo).__name__}: "
                          f"select the learner with algo={algo.name} (conf/algo), not "
                          f"algo.name={algo.name}.")


def validate_learning(cfg: RunConfig) -> None:
    """The ``algo`` and ``train`` settings and the seed, then every number's range."""
    enum_value(LossKind, cfg.algo.loss, "algo.loss")
    enum_value(ReplayKind, cfg.algo.replay, "algo.replay")
    enum_value(LoggerKind, cfg.train.logger, "train.logger")
    _raise_first(_algo_checks(cfg) + _train_checks(cfg))
    check_ranges(cfg)


def validate_device(device: str) -> None:
    if not (device in ("cpu", "cuda", "auto") or device.startswith("cuda:")):
        raise ConfigError(f"device must be cpu, cuda, cuda:N or auto, got {device!r}.")


def _algo_checks(cfg: RunConfig) -> list[tuple[bool, str, str, Any]]:
    a, t, s = cfg.algo, cfg.train, cfg.scenario
    return [
        (a.lr > 0, "algo.lr", "must be > 0", a.lr),
        (0 <= a.gamma <= 1, "algo.gamma", "must be in [0, 1]", a.gamma),
        (a.batch_size >= 1, "algo.batch_size", "must be >= 1", a.batch_size),
        (a.buffer_size >= a.batch_size, "algo.buffer_size", "must be >= algo.batch_size",
         a.buffer_size),
        (a.buffer_size >= t.n_envs * s.n_uabs, "algo.buffer_size",
         f"must be >= train.n_envs x scenario.n_uabs = {t.n_envs * s.n_uabs} (the "
         "transitions one env step stores)", a.buffer_size),
        (a.learning_starts >= a.batch_size, "algo.learning_starts",
         "must be >= algo.batch_size", a.learning_starts),
        (a.learning_starts <= a.buffer_size, "algo.learning_starts",
         "must be <= algo.buffer_size (the buffer never holds more, so no update would "
         "ever run)", a.learning_starts),
        (a.update_every >= 1, "algo.update_every", "must be >= 1", a.update_every),
        (a.target_update >= 1, "algo.target_update", "must be >= 1", a.target_update),
        (0 <= a.eps_end <= a.eps_start <= 1, "algo.eps_start/eps_end",
         "must satisfy 0 <= eps_end <= eps_start <= 1", (a.eps_start, a.eps_end)),
        (0 < a.eps_fraction <= 1, "algo.eps_fraction", "must be in (0, 1]", a.eps_fraction),
        (a.grad_clip is None or a.grad_clip > 0, "algo.grad_clip",
         "must be null (no clipping) or > 0 (a gradient norm)", a.grad_clip),
        (all(h >= 1 for h in a.hidden) and len(a.hidden) >= 1, "algo.hidden",
         "must be a non-empty list of positive widths", a.hidden),
        (1 <= a.n_step <= s.episode_steps, "algo.n_step",
         "must be in [1, scenario.episode_steps]", a.n_step),
        (a.n_step == 1 or s.time_is_terminal, "algo.n_step",
         "must be 1 when scenario.time_is_terminal=false (a cut return would need its "
         "own discount)", a.n_step),
        (a.priority_alpha >= 0, "algo.priority_alpha", "must be >= 0", a.priority_alpha),
        (0 <= a.priority_beta <= 1, "algo.priority_beta", "must be in [0, 1]",
         a.priority_beta),
        *([(a.mixing_embed_dim >= 1, "algo.mixing_embed_dim", "must be >= 1",
            a.mixing_embed_dim)] if isinstance(a, QmixConfig) else []),
        *([(1 <= a.teacher_horizon <= s.episode_steps, "algo.teacher_horizon",
            "must be in [1, scenario.episode_steps] (a longer look cannot change a move)",
            a.teacher_horizon),
           (a.teacher_margin >= 0, "algo.teacher_margin", "must be >= 0", a.teacher_margin),
           (a.imitation_weight >= 0, "algo.imitation_weight", "must be >= 0",
            a.imitation_weight),
           # the teacher plans in one area (the planner's lattice and bounds): a family's
           # rows each have their own
           (not cfg.family, "family", "must be empty with algo=dqfd (its teacher, the "
            "planner, plans over one city's area); train on one scenario",
            f"{len(cfg.family)} cities")] if isinstance(a, DqfdConfig) else []),
        (t.population == 1 or a.loss == LossKind.fused, "algo.loss",
         "must be fused when train.population > 1 (torchrl is the solo reference loss)",
         str(a.loss)),
    ]


def _train_checks(cfg: RunConfig) -> list[tuple[bool, str, str, Any]]:
    t = cfg.train
    seeds = "in [-2^63, 2^64) (the seeds torch.Generator.manual_seed accepts)"
    return [
        (t.episodes >= 1, "train.episodes", "must be >= 1", t.episodes),
        (t.eval_every >= 1, "train.eval_every", "must be >= 1", t.eval_every),
        (t.eval_windows >= 1, "train.eval_windows", "must be >= 1", t.eval_windows),
        (t.n_envs >= 1, "train.n_envs", "must be >= 1", t.n_envs),
        (t.population >= 1, "train.population", "must be >= 1", t.population),
        (t.episodes % max(t.n_envs, 1) == 0, "train.episodes",
         "must be a multiple of train.n_envs", (t.episodes, t.n_envs)),
        (t.threads is None or t.threads >= 1, "train.threads",
         "must be null (chosen for the machine) or >= 1", t.threads),
        (0 <= t.eval_seed < SEED_END, "train.eval_seed", "must be in [0, 2^64) (TorchRL's "
         "env.set_seed hands it to numpy, which takes no negative seed)", t.eval_seed),
        (SEED_MIN <= cfg.seed < SEED_END, "seed", f"must be {seeds}", cfg.seed),
        (cfg.seed + t.population - 1 < SEED_END, "seed",
         f"+ train.population - 1 (the last member's seed) must be {seeds}",
         cfg.seed + t.population - 1),
    ]
