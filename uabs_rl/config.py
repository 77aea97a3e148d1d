"""Typed config schemas (Hydra ConfigStore) and the checks that run at start-up.

Every yaml under ``conf/`` is validated against these dataclasses, so a misspelt key
or a value of the wrong type fails when the config is composed. Value checks that a
type cannot express (a fleet of 0, a NaN or infinite number, a replay buffer larger
than the machine's memory, ...) live in ``validate_*`` functions and raise
:class:`ConfigError` naming the key, before anything is built or written.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields, is_dataclass, replace
from enum import StrEnum
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

PROJECT_ROOT = Path(__file__).resolve().parents[1]


class ConfigError(ValueError):
    """A config value is invalid; the message names the key and the fix."""


# run seeds (seed, seed + 1, ... of a population, train.eval_seed): the range that
# torch.Generator.manual_seed accepts, [-2^63, 2^64)
SEED_MIN, SEED_END = -(2 ** 63), 2 ** 64
# SUMO seeds (traces.<split>.first_seed + i): SUMO's --seed is a 32-bit signed integer
# and numpy's default_rng (the fleet's routes) refuses negative seeds
SUMO_SEED_MAX = 2 ** 31 - 1
N_MOVES = 4  # the actions: up, right, down, left (uabs_rl.env.uabs_env.N_ACTIONS)


# Closed sets. Member names equal their values because OmegaConf converts yaml strings
# to members by name: ``masking.mode: flat`` -> ``MaskingMode.flat``; Hydra rejects
# any other value when the config is composed.
class MaskingMode(StrEnum):
    """The anti-collision mechanism (docs/model.md §6); its rules live in
    ``uabs_rl.safety.masking``."""

    penalty = "penalty"
    flat = "flat"
    rank = "rank"


class RankNextMask(StrEnum):
    """Rank mode's double-DQN target mask at s' (see ``uabs_rl.safety.masking.RankRule``)."""

    greedy = "greedy"
    boundary = "boundary"


class LosMode(StrEnum):
    """How a link's LoS state is decided (docs/model.md §3)."""

    sample = "sample"
    expected = "expected"
    los = "los"


class LoggerKind(StrEnum):
    """Where a run's scalars go besides ``metrics.jsonl`` (TorchRL's loggers)."""

    tensorboard = "tensorboard"
    csv = "csv"
    wandb = "wandb"
    mlflow = "mlflow"
    none = "none"


class ReplayKind(StrEnum):
    """How a learner's replay draws its samples (``uabs_rl.algorithms.replay``)."""

    uniform = "uniform"
    prioritized = "prioritized"


class LossKind(StrEnum):
    """Which implementation of the 3DQN loss (``uabs_rl.algorithms.dqn3``)."""

    fused = "fused"
    torchrl = "torchrl"


def enum_value(enum: type[StrEnum], value: object, key: str) -> StrEnum:
    """``value`` as a member of ``enum``, or a ConfigError naming ``key`` and the choices."""
    try:
        return enum(value)
    except ValueError:
        choices = "|".join(m.value for m in enum)
        raise ConfigError(f"{key} must be one of {choices}, got {value!r}.") from None


@dataclass
class AreaConfig:
    """Service-area rectangle in SUMO network coordinates (metres)."""

    x_min: float = 0.0  # lower-left corner, x (east)
    y_min: float = 0.0  # lower-left corner, y (north)
    width: float = 350.0  # W
    height: float = 170.0  # H


@dataclass
class SumoConfig:
    """Where the vehicles come from: a network plus a fleet and/or routes."""

    net_file: str = "sumo/manhattan/manhattan.net.xml"  # relative to cwd or the project root
    fleet_size: int = 80  # |G|: vehicles that get a new random destination at each route's end
    # extra .rou.xml files: vehicles that enter and leave
    route_files: list[str] = field(default_factory=list)
    sumocfg: str | None = None  # a .sumocfg; replaces net_file/route_files when set
    extra_args: list[str] = field(default_factory=list)  # passed verbatim to sumo


@dataclass
class SplitConfig:
    """One set of traces: simulations with seeds first_seed .. first_seed + n_sims - 1,
    each recording simulated seconds warmup_s + begin_s .. warmup_s + begin_s + duration_s."""

    first_seed: int = 0
    n_sims: int = 8
    duration_s: float = 3600.0  # recorded seconds per simulation (after warm-up)
    warmup_s: float = 60.0  # simulated seconds skipped before recording
    # start of the recorded time range, in seconds after the warm-up. null: 0 for a
    # fleet scenario; for a fixed-demand scenario (route files or a .sumocfg: the same
    # vehicles depart at the same times under every seed) the splits follow one another
    # in time, train first, then eval, then test (:func:`split_begin`)
    begin_s: float | None = None


# trace splits: training, validation ("eval": periodic evaluation and checkpoint
# selection) and test (every reported figure)
TRACE_SPLITS = ("train", "eval", "test")


@dataclass
class TracesConfig:
    """Training and held-out evaluation traces, and where they are cached."""

    # 8 h of training traces: 1000 random 80 s windows rarely overlap much.
    train: SplitConfig = field(default_factory=SplitConfig)
    # validation traces (other SUMO seeds): the periodic evaluation during training, the
    # Fig. 3 curve and the choice of the best checkpoint [decision]
    eval: SplitConfig = field(
        default_factory=lambda: SplitConfig(first_seed=10_000, n_sims=2, duration_s=600.0)
    )
    # test traces (yet other seeds): every reported figure (uabs-eval, uabs-report); never
    # read by training or checkpoint selection. 8 x 600 s hold 56 windows of 81 steps
    test: SplitConfig = field(
        default_factory=lambda: SplitConfig(first_seed=20_000, n_sims=8, duration_s=600.0)
    )
    cache_dir: str | None = None  # null = $UABS_RL_CACHE/traces, default ~/.cache/uabs_rl/traces
    workers: int = 0  # SUMO processes in parallel; 0 = one per core


@dataclass
class ScenarioConfig:
    """The city, its vehicles, and the UABS fleet flying over it (docs/model.md §1, §4, §5)."""

    name: str = "manhattan"
    area: AreaConfig = field(default_factory=AreaConfig)
    dt: float = 1.0  # δt, seconds per step (SUMO step length and sampling period)
    sumo: SumoConfig = field(default_factory=SumoConfig)
    n_uabs: int = 3  # M, the agents
    altitude: float = 100.0  # h (m), all UABS
    speed: float = 20.0  # v (m/s): each action moves v·δt
    episode_steps: int = 80  # T
    window_steps: int = 10  # N, service window length [decision: the paper gives none]
    nhat_s: int = 5  # N̂_s, served steps per window to be satisfied [decision]
    lambda_s: float = 10.0  # λ_s, proximity penalty
    lambda_c: float = 1000.0  # λ_c, collision penalty
    collision_distance: float = 1.0  # closer than this is a collision (m)
    safety_distance: float | None = None  # d_th (m); null = 2·h·tan(φ/2) ≈ 72.8 m [decision]
    lattice: bool = True  # positions on a lattice of pitch v·δt [decision]; false = continuous
    safe_start: bool = True  # the inner UABS starts ≥ d_th from the others [decision]
    time_is_terminal: bool = True  # t/T is observed: t = T ends the MDP, no bootstrap [decision]


class ObsFrame(StrEnum):
    """Which frame each UABS's observation is written in (``uabs_rl.env.observe``)."""

    fleet = "fleet"
    egocentric = "egocentric"


@dataclass
class ObsConfig:
    """What each UABS observes: the network's input (docs/model.md §5). Its own group,
    apart from ``scenario``, so a policy evaluated in another city keeps the observation
    it was trained on. ``obs=paper`` (default), ``lookahead``, ``lookahead_motion``,
    ``egocentric``."""

    name: str = "paper"  # a label for reports; the fields below decide the observation
    # fleet: the paper's (x/W, y/H, t/T, every UABS's position, b_t): its size grows
    # with M. egocentric: a size fixed whatever M and the area (below)
    frame: ObsFrame = ObsFrame.fleet
    priority_scale: float = 10.0  # priorities (b_t, lookahead, map) are divided by this
    # fleet frame, beyond the paper: for each of the 4 moves and for 2 steps in each
    # direction, the priority the UABS's footprints would cover there at the vehicles'
    # current positions (what the greedy baseline looks at); false = the paper's
    lookahead: bool = False
    # beyond the paper, with lookahead (fleet) or egocentric: the same scores at the
    # vehicles' positions extrapolated one step from their last move (x_t + (x_t -
    # x_{t-1}), past positions only): an estimate of what the oracle baseline sees
    # (fleet: the 4 moves; egocentric: the whole local map)
    motion: bool = False
    # egocentric: the priority the footprints would cover at each lattice point within
    # this many steps in x and y of the UABS, (2r + 1)^2 numbers
    map_radius: int = 2
    neighbours: int = 4  # egocentric: K nearest other UABS (offset and a present flag)
    # egocentric: neighbours' offsets, in lattice steps, divided by this and clipped
    # to [-1, 1]
    neighbour_range: float = 10.0
    # egocentric: the distance to each of the area's 4 edges, in lattice steps, divided
    # by this and clipped to [0, 1]
    edge_range: float = 4.0


@dataclass
class ChannelConfig:
    """3GPP TR 38.901 UMa uplink, GUE to UABS, with a k×k beam grid (docs/model.md §3)."""

    name: str = "uma"  # the channel model: a key of uabs_rl.env.channel.CHANNELS
    carrier_ghz: float = 30.0  # f_c
    ue_height: float = 1.5  # h_UT (m)
    tx_power_dbm: float = 14.0  # P_tx
    tx_gain_db: float = 0.0  # G_tx
    noise_dbm: float = -106.4  # P_n
    snr_threshold_db: float = -13.7  # SNR_th
    fov_deg: float = 40.0  # φ
    n_beams: int = 9  # B, a square number (3×3 grid)
    # [decision] sample: Bernoulli(ρ_L) per link per step | expected | los
    los_mode: LosMode = LosMode.sample
    shadow_fading: bool = False  # log-normal shadowing, σ below [decision: off]
    shadow_sigma_los_db: float = 4.0
    shadow_sigma_nlos_db: float = 6.0
    outside_beam_gain_db: float | None = None  # null = ideal beams, no service outside [decision]



@dataclass
class MaskingConfig:
    """Anti-collision mechanism (docs/model.md §6)."""

    mode: MaskingMode = MaskingMode.rank  # penalty | flat | rank
    flat_margin: float | None = None  # flat: unsafe below d_th + this; null = v·δt (paper)
    collider_margin: float | None = None  # rank: colliders below d_th + this; null = 2·v·δt
    # [decision] next-state mask of the double-DQN target in rank mode: "greedy" = the
    # masks a greedy rank selection would apply at s'; "boundary" = boundary mask only
    rank_next_mask: RankNextMask = RankNextMask.greedy
    # [decision] recoverable flat and rank masks (docs/model.md §6): every UABS always keeps a
    # legal move that is safe, so no fallback is ever needed; false = the paper's
    # literal rules (fallbacks possible, pairs may end closer than d_th)
    recoverable: bool = True


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


@dataclass
class AlgoConfig:
    """3DQN: shared dueling double DQN (docs/model.md §7). Defaults follow the authors' single-UABS
    3DQN where the paper is silent (see docs/configuration.md, "Learning hyper-parameters")."""

    name: str = "dqn3"  # the learner: a key of uabs_rl.algorithms.ALGORITHMS (dqn3, vdn, qmix)
    hidden: list[int] = field(default_factory=lambda: [256, 256])  # MLP trunk widths
    lr: float = 1e-4  # Adam learning rate
    gamma: float = 0.8  # discount γ
    batch_size: int = 128  # per-agent transitions per update
    buffer_size: int = 100_000  # replay capacity, per-agent transitions
    learning_starts: int = 1_000  # transitions stored before the first update
    update_every: int = 1  # T_u: env steps (per env) between updates
    target_update: int = 250  # updates between copies of the online net to the target
    eps_start: float = 1.0  # ε-greedy schedule: linear from eps_start ...
    eps_end: float = 0.05  # ... to eps_end ...
    eps_fraction: float = 0.6  # ... over this share of the training env steps
    grad_clip: float | None = None  # max gradient norm; null = no clipping
    # beyond the paper: n-step returns, target r_t + γ r_{t+1} + ... + γ^{n-1} r_{t+n-1}
    # + γ^n Q(s_{t+n}) (cut at the episode's end); 1 = the paper's one-step target
    n_step: int = 1
    loss: LossKind = LossKind.fused  # fused (hand-written, same maths) | torchrl (DQNLoss)
    # beyond the paper: uniform | prioritized (proportional, as TorchRL's
    # PrioritizedSampler: draws in proportion to (|TD error| + 1e-8)^priority_alpha, new
    # transitions at the highest priority so far, the loss weighted by
    # (p_i / p_min)^-priority_beta; uabs_rl.algorithms.replay.Priorities)
    replay: ReplayKind = ReplayKind.uniform
    priority_alpha: float = 0.6  # prioritization exponent α (0: uniform draws)
    priority_beta: float = 0.4  # importance-weight exponent β (1: the bias fully corrected)
    mixing_embed_dim: int = 32  # algo=qmix: width of the mixing network (its hypernetworks)


@dataclass
class TrainConfig:
    """Training protocol (docs/model.md §7, §8)."""

    episodes: int = 1000  # N_t
    eval_every: int = 20  # N_e: greedy evaluation on held-out traces every N_e episodes
    eval_windows: int = 10  # held-out windows per evaluation (the paper evaluates 1)
    eval_seed: int = 12345  # start positions of every evaluation (the same each time)
    # episodes in parallel; updates per collector step = n_envs / algo.update_every
    n_envs: int = 1
    # seeds trained together in one process: seed, seed + 1, ..., seed + population - 1,
    # their episodes side by side in one env and their networks stacked (batched
    # products); each member writes a solo run's folder, <run>/seed=<s>/ (docs/scaling.md,
    # "Population training", says what differs from training each alone)
    population: int = 1
    checkpoint_buffer: bool = False  # also store the replay buffer in checkpoints (~20 MB)
    # TorchRL logger: tensorboard (<run>/tb) | csv (<run>/csv) | wandb | mlflow
    # (<run>/mlruns) | none; wandb and mlflow need their package installed
    logger: LoggerKind = LoggerKind.tensorboard
    trajectory_images: bool = True  # held-out trajectory picture at each evaluation
    progress: bool = True  # progress bar
    # torch.compile the env step and the action selection: ~2x faster training, ~20 s to
    # compile (eager if compilation fails)
    compile: bool = True
    # also run the update's loss and backward as one compiled program (any learner, solo
    # or population; uabs_rl/algorithms/compiled_update.py): about 0.9x the update's time,
    # results equal to float32 rounding, not bit for bit; off by default: over the main
    # job its compile (10-60 s, again at each change of threads) costs about what it
    # saves (see that module)
    compile_update: bool = False
    # torch CPU threads; null = by the update's size, at most the CPUs this process may use,
    # fewer while other processes keep them busy (uabs_rl/training/threads.py); set it for runs
    # that must be bit-reproducible whatever the load, and to cores / n_jobs in sweeps
    threads: int | None = None


@dataclass
class RunConfig:
    """Top-level config of ``uabs-train``."""

    scenario: ScenarioConfig = field(default_factory=ScenarioConfig)
    obs: ObsConfig = field(default_factory=ObsConfig)
    channel: ChannelConfig = field(default_factory=ChannelConfig)
    masking: MaskingConfig = field(default_factory=MaskingConfig)
    algo: AlgoConfig = field(default_factory=AlgoConfig)
    traces: TracesConfig = field(default_factory=TracesConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    # beyond the paper: train over several cities at once. Each entry is a city given by
    # what differs from `scenario` (name, area, sumo: its network and vehicles; {} is
    # `scenario` itself); each training env draws its city per episode among them.
    # Empty: `scenario` only. Validation and the default evaluation stay on `scenario`.
    family: list[Any] = field(default_factory=list)
    seed: int = 0  # network init, exploration, training windows and start positions
    device: str = "cpu"  # cpu | cuda | cuda:N | auto
    resume: str | None = None  # a run directory (outputs/runs/...) to continue


@dataclass
class TracesAppConfig(RunConfig):
    """Top-level config of ``uabs-traces``: the same groups and presets as ``uabs-train``
    (only ``scenario`` and ``traces`` decide the traces), plus which split to build."""

    split: str = "all"  # which traces to build: train, eval, test or all (uabs-traces split=test)


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
# upgraded (uabs_rl.training.checkpoint.upgrade_config), command lines refused by
# check_moved_overrides
MOVED = {("scenario", "lookahead_obs"): ("obs", "lookahead"),
         ("scenario", "motion_obs"): ("obs", "motion"),
         ("scenario", "priority_obs_scale"): ("obs", "priority_scale")}


def check_moved_overrides(overrides: list[str]) -> None:
    """Refuse a command-line override of a setting that moved, saying what to type."""
    for o in overrides:
        key, _, value = o.lstrip("+~").partition("=")
        for (sec, old), (new_sec, new) in MOVED.items():
            if key == f"{sec}.{old}":
                hint = {"lookahead": "obs=lookahead (obs=lookahead_motion with the motion "
                                     "features)", "motion": "obs=lookahead_motion"}.get(
                    new, f"{new_sec}.{new}={value}")
                raise ConfigError(f"{key} moved to the observation group: type {hint} "
                                  f"instead of {o} (conf/obs holds the observations).")


# Hydra's flags that take the next word as their value (``--cfg job``, ``-cn config``)
_FLAGS_WITH_VALUE = {"-c", "--cfg", "-p", "--package", "-cn", "--config-name", "-cp",
                     "--config-path", "-cd", "--config-dir", "--experimental-rerun"}
_INFO_TOPICS = {"all", "config", "defaults", "defaults-tree", "plugins", "searchpath"}
# keys a command appends to what the user typed (uabs-train's resume= names the run's
# folder again as hydra.run.dir, or hydra.sweep.dir with -m): typed once, they appear twice
APPENDED_KEYS = ("hydra.run.dir", "hydra.sweep.dir", "hydra.output_subdir")


def override_key(word: str) -> str | None:
    """The setting a command-line word overrides (``+a.b=1``, ``~a.b``, ``a.b=1`` ->
    ``a.b``; a group with a package, ``a@p=x``, stays whole), None for a flag."""
    if word.startswith("-"):
        return None
    key, eq, _ = word.lstrip("+~").partition("=")
    return key.strip() if (eq or word.startswith("~")) and key.strip() else None


def command_line_overrides(argv: list[str]) -> list[str]:
    """The overrides of a command line: its words that are neither flags nor a flag's
    value."""
    out, skip = [], False
    for i, word in enumerate(argv):
        if skip:
            skip = False
            continue
        if word in _FLAGS_WITH_VALUE or (word == "--info" and i + 1 < len(argv)
                                         and argv[i + 1] in _INFO_TOPICS):
            skip = True
            continue
        if not word.startswith("-"):
            out.append(word)
    return out


def check_duplicate_overrides(argv: list[str]) -> None:
    """Refuse a setting given twice on the command line (``masking=flat
    masking=penalty``, ``seed=1 seed=2``; with ``-m`` too): Hydra would keep the last
    one silently, and the run folder would be named after both."""
    seen: dict[str, list[str]] = {}
    for word in command_line_overrides(argv):
        key = override_key(word)
        if key is not None:
            seen.setdefault(key, []).append(word)
    resumed = "resume" in seen
    for key, words in seen.items():
        allowed = 2 if key in APPENDED_KEYS and resumed else 1
        if len(words) > allowed:
            n = len(words) - allowed + 1
            values = ",".join(w.partition("=")[2] for w in words[:n])
            raise ConfigError(f"{key} is given {'twice' if n == 2 else f'{n} times'} on the "
                              f"command line ({', '.join(words[:n])}): give it once (a "
                              f"sweep over several values: -m {key}={values}).")


def validate_world(cfg: RunConfig) -> None:
    """The start-up checks of the world a policy acts in (scenario, traces, channel,
    masking), each naming the key: what ``uabs-eval`` checks, and part of
    :func:`validate_run`. (:class:`~uabs_rl.env.params.EnvParams` checks the env settings
    again, so an env built from the library is guarded too.)"""
    validate_scenario_traces(cfg.scenario, cfg.traces)
    validate_env(cfg.scenario, cfg.channel)
    validate_obs(cfg.obs)
    validate_masking(cfg.masking)


FAMILY_KEYS = ("name", "area", "sumo")  # what a family's cities may set


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


def validate_run(cfg: RunConfig) -> None:
    """Every start-up check of ``uabs-train``, each naming the offending key: nothing is
    built or written before they pass."""
    check_finite(cfg)
    validate_world(cfg)
    for i, city in enumerate(family_scenarios(cfg)):
        try:
            validate_scenario_traces(city, cfg.traces)
            validate_env(city, cfg.channel)
        except ConfigError as e:  # what a city sets: name it as the family entry's
            raise ConfigError(str(e).replace("scenario.area", f"family[{i}].area")
                              .replace("scenario.sumo", f"family[{i}].sumo")) from None
    validate_algo_name(cfg.algo)
    enum_value(LossKind, cfg.algo.loss, "algo.loss")
    enum_value(ReplayKind, cfg.algo.replay, "algo.replay")
    enum_value(LoggerKind, cfg.train.logger, "train.logger")
    _raise_first(_algo_checks(cfg) + _train_checks(cfg))
    check_ranges(cfg)
    _check_eval_windows(cfg)
    if not (cfg.device in ("cpu", "cuda", "auto") or cfg.device.startswith("cuda:")):
        raise ConfigError(f"device must be cpu, cuda, cuda:N or auto, got {cfg.device!r}.")
    check_memory(cfg)


def _check_eval_windows(cfg: RunConfig) -> None:
    """Training and validation traces long enough for an episode, and
    ``train.eval_windows`` against the windows the validation traces will hold
    (n_sims x duration_s / dt steps, as they are built), before any trace is built:
    the refusals the env and :func:`~uabs_rl.evaluation.evaluator.eval_window_count`
    give once they are."""
    from types import SimpleNamespace

    from uabs_rl.evaluation.evaluator import eval_window_count

    need = cfg.scenario.episode_steps + 1
    for name in ("train", "eval"):  # as uabs_rl.env.uabs_env refuses them once built
        split = getattr(cfg.traces, name)
        steps = int(round(split.duration_s / cfg.scenario.dt))
        if steps < need:
            raise ConfigError(
                f"the {name} traces hold {steps} steps but an episode needs "
                f"scenario.episode_steps + 1 = {need}: raise traces.{name}.duration_s "
                f"(now {split.duration_s:g} s at scenario.dt={cfg.scenario.dt:g} s) or "
                f"lower scenario.episode_steps.")
    split = cfg.traces.eval
    shape = SimpleNamespace(n_sims=split.n_sims,
                            steps=int(round(split.duration_s / cfg.scenario.dt)))
    eval_window_count(cfg, shape, "eval")


def validate_algo_name(algo: AlgoConfig) -> None:
    """``algo.name`` names a registered algorithm (``uabs_rl.algorithms``), and it
    accepts the other ``algo`` settings."""
    from uabs_rl.algorithms import algorithm_class  # here: it imports this module

    algorithm_class(algo.name).check_config(algo)


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
        (a.mixing_embed_dim >= 1, "algo.mixing_embed_dim", "must be >= 1",
         a.mixing_embed_dim),
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


def register_configs() -> None:
    cs = ConfigStore.instance()
    cs.store(group="scenario", name="scenario_schema", node=ScenarioConfig)
    cs.store(group="obs", name="obs_schema", node=ObsConfig)
    cs.store(group="channel", name="channel_schema", node=ChannelConfig)
    cs.store(group="masking", name="masking_schema", node=MaskingConfig)
    cs.store(name="traces_app_schema", node=TracesAppConfig)
    cs.store(group="traces", name="traces_schema", node=TracesConfig)
    cs.store(group="algo", name="algo_schema", node=AlgoConfig)
    cs.store(name="run_schema", node=RunConfig)


CONF_DIR = PROJECT_ROOT / "conf"


def compose(config_name: str = "config", overrides: list[str] | None = None) -> Any:
    """Compose a config as the CLI would (``config`` for uabs-train, ``build_traces``
    for uabs-traces) and return it as checked dataclasses: for notebooks and scripts."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = hydra_compose(config_name=config_name, overrides=list(overrides or []))
    return to_container(cfg)


def resolve_path(value: str, key: str) -> Path:
    """Resolve a config path against the cwd, then the project root; fail naming ``key``."""
    p = Path(value).expanduser()
    candidates = [p] if p.is_absolute() else [Path.cwd() / p, PROJECT_ROOT / p]
    for c in candidates:
        if c.is_file():
            return c.resolve()
    tried = ", ".join(str(c) for c in candidates)
    raise ConfigError(f"{key}: file not found: {value!r} (looked at {tried}). "
                      f"Set {key} to an existing file.")


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
    host = available_memory("cpu")  # traces are built and cached on the host
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
    _check_fits(f"{key}.n_sims x {key}.duration_s", trace_bytes(scenario, split),
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
    source = ("scenario.sumo.sumocfg" if scenario.sumo.sumocfg
              else "scenario.sumo.route_files")
    for i, a in enumerate(TRACE_SPLITS):
        for b in TRACE_SPLITS[i + 1:]:
            (a0, a1), (b0, b1) = ranges[a], ranges[b]
            if not (a0 < b1 and b0 < a1):
                continue
            moved, other = ((b, a) if getattr(traces, b).begin_s is not None
                            or getattr(traces, a).begin_s is None else (a, b))
            (m0, m1), (o0, o1) = ranges[moved], ranges[other]
            begin = split_begin(scenario, traces, moved)
            raise ConfigError(
                f"traces.{moved}.begin_s={begin:g} makes the {moved} time range "
                f"{m0:g}..{m1:g} s (warm-up {getattr(traces, moved).warmup_s:g} s "
                f"included) overlap the {other} range {o0:g}..{o1:g} s: the vehicles of "
                f"{source} depart at the same times under every SUMO seed, so training, "
                f"validation (eval) and test traces must come from disjoint time ranges. "
                f"Move traces.{moved}.begin_s past the {other} range (begin_s >= "
                f"{max(0.0, o1 - getattr(traces, moved).warmup_s):g}), or leave the begin_s "
                f"settings null (the splits then follow one another).")


def _check_known_keys(obj: Any, node: Any, prefix: str) -> None:
    """Refuse keys a dataclass does not have (``+key=...`` would otherwise vanish)."""
    if not (is_dataclass(obj) and isinstance(node, DictConfig)):
        return
    known = {f.name for f in fields(obj)}
    for key in node.keys():
        if key not in known:
            raise ConfigError(f"unknown config key {prefix}{key}: {type(obj).__name__} has "
                              f"{sorted(known)}. Remove it or fix its spelling.")
        _check_known_keys(getattr(obj, key), node._get_node(key), f"{prefix}{key}.")


def to_container(cfg: Any) -> Any:
    """Resolved dataclasses from a composed DictConfig; unknown keys are an error."""
    if isinstance(cfg, DictConfig):
        obj = OmegaConf.to_object(cfg)
        _check_known_keys(obj, cfg, "")
        return obj
    return cfg


def validate_env(scenario: ScenarioConfig, channel: ChannelConfig) -> None:
    """Value checks for the environment, each naming the offending key."""
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
    from uabs_rl.env.channel import CHANNELS

    if channel.name not in CHANNELS:
        raise ConfigError(f"channel.name={channel.name!r} is not a channel model: use one of "
                          f"{', '.join(sorted(CHANNELS))} (uabs_rl.env.channel.CHANNELS).")
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


def check_finite(obj: Any, prefix: str = "") -> None:
    """Refuse a NaN or infinite float anywhere in the dataclass ``obj`` (nested configs
    and lists included), naming its key: ``prefix`` + the field's path. A NaN passes
    every ``<``/``>`` range check and trains (or caches traces) on nonsense."""
    for f in fields(obj):
        key, value = f"{prefix}{f.name}", getattr(obj, f.name)
        if is_dataclass(value):
            check_finite(value, f"{key}.")
            continue
        for v in value if isinstance(value, list | tuple) else [value]:
            if isinstance(v, float) and not math.isfinite(v):
                null = " (or null)" if "None" in str(f.type) else ""
                raise ConfigError(f"{key} must be a finite number{null}, got {value!r}. "
                                  f"Set {key} to a finite value.")


def _raise_first(checks: list[tuple[bool, str, str, Any]]) -> None:
    """Raise a ConfigError for the first failed ``(ok, key, rule, value)`` check."""
    for ok, key, rule, value in checks:
        if not ok:
            raise ConfigError(f"{key} {rule}, got {value!r}.")


# ----------------------------------------------------------------------------- ranges
@dataclass(frozen=True)
class Range:
    """The values a numeric setting may take: ``lo`` to ``hi`` (``lo_open`` /
    ``hi_open``: the bound itself excluded), in ``unit``; ``text`` shows a bound that
    reads better as a power (2^64)."""

    lo: float
    hi: float
    unit: str = ""
    lo_open: bool = False
    hi_open: bool = False
    text: tuple[str, str] | None = None

    def holds(self, v: float) -> bool:
        above = v > self.lo if self.lo_open else v >= self.lo
        below = v < self.hi if self.hi_open else v <= self.hi
        return above and below

    def __str__(self) -> str:
        lo, hi = self.text or (_num(self.lo), _num(self.hi))
        unit = f" {self.unit}" if self.unit else ""
        return f"{'(' if self.lo_open else '['}{lo}, {hi}{')' if self.hi_open else ']'}{unit}"


def _num(x: float) -> str:
    """A bound as people write it: 3600, 0.001, 10^9, -1e+08."""
    if float(x).is_integer() and abs(x) < 1e7:
        return str(int(x))
    k = math.log10(abs(x)) if x else 0.0
    return f"{'-' if x < 0 else ''}10^{round(k)}" if k.is_integer() and k > 0 else f"{x:g}"


def _r(lo: float, hi: float, unit: str = "", **kw: Any) -> Range:
    return Range(lo, hi, unit, **kw)


def _pos(hi: float, unit: str = "") -> Range:  # (0, hi]
    return Range(0, hi, unit, lo_open=True)


# Every number a config holds, by dataclass and field: finite, physically meaningful
# ranges, wide enough for every preset and documented experiment (a list: each entry).
# Checked at start-up after the checks that relate settings to each other, so a value
# those explain better (scenario.dt=-1: "must be > 0 seconds") keeps their message.
SEED_RANGE = Range(SEED_MIN, SEED_END, hi_open=True, text=("-2^63", "2^64"))
RANGES: dict[type, dict[str, Range]] = {}  # filled below, once every dataclass exists


def check_ranges(obj: Any, prefix: str = "") -> None:
    """Refuse a number of the dataclass ``obj`` (nested configs and lists included)
    outside its :data:`RANGES` entry, naming its key (``prefix`` + the field's path)."""
    table = RANGES.get(type(obj), {})
    for f in fields(obj):
        key, value = f"{prefix}{f.name}", getattr(obj, f.name)
        if is_dataclass(value):
            check_ranges(value, f"{key}.")
            continue
        rng = table.get(f.name)
        if rng is None or value is None:
            continue
        for v in value if isinstance(value, list | tuple) else [value]:
            if isinstance(v, bool) or not isinstance(v, int | float):
                continue
            if not rng.holds(v):
                each = " (each entry)" if isinstance(value, list | tuple) else ""
                raise ConfigError(f"{key}{each} must be in {rng}, got {v!r}.")


_UNIT = Range(0, 1)  # a probability, a share, a discount
RANGES.update({
    AreaConfig: {"x_min": _r(-1e8, 1e8, "m"), "y_min": _r(-1e8, 1e8, "m"),
                 "width": _pos(1e5, "m"), "height": _pos(1e5, "m")},
    SumoConfig: {"fleet_size": _r(0, 100_000, "vehicles")},
    SplitConfig: {"first_seed": Range(0, SUMO_SEED_MAX, text=("0", "2^31 - 1")),
                  "n_sims": _r(1, 100_000),
                  "duration_s": _pos(1e7, "s"), "warmup_s": _r(0, 1e7, "s"),
                  "begin_s": _r(0, 1e7, "s")},
    TracesConfig: {"workers": _r(0, 1024)},
    ScenarioConfig: {
        "dt": _r(0.001, 3600, "s"), "n_uabs": _r(1, 1000), "altitude": _pos(10_000, "m"),
        "speed": _r(0.01, 1000, "m/s"), "episode_steps": _r(1, 1_000_000),
        "window_steps": _r(1, 1_000_000), "nhat_s": _r(1, 1_000_000),
        "lambda_s": _r(0, 1e6), "lambda_c": _r(0, 1e6),
        "collision_distance": _pos(10_000, "m"), "safety_distance": _r(0, 1e5, "m")},
    ObsConfig: {"priority_scale": _pos(1e6), "map_radius": _r(0, 100, "lattice steps"),
                "neighbours": _r(0, 1000), "neighbour_range": _pos(1e6, "lattice steps"),
                "edge_range": _pos(1e6, "lattice steps")},
    ChannelConfig: {
        "carrier_ghz": _pos(300, "GHz"), "ue_height": _r(0, 1000, "m"),
        "tx_power_dbm": _r(-100, 100, "dBm"), "tx_gain_db": _r(-100, 100, "dB"),
        "noise_dbm": _r(-200, 100, "dBm"), "snr_threshold_db": _r(-100, 100, "dB"),
        "fov_deg": Range(0, 180, "degrees", lo_open=True, hi_open=True),
        "n_beams": _r(1, 10_000), "shadow_sigma_los_db": _r(0, 50, "dB"),
        "shadow_sigma_nlos_db": _r(0, 50, "dB"), "outside_beam_gain_db": _r(-200, 100, "dB")},
    MaskingConfig: {"flat_margin": _r(0, 1e5, "m"), "collider_margin": _r(0, 1e5, "m")},
    AlgoConfig: {
        "hidden": _r(1, 65_536), "lr": _pos(1), "gamma": _UNIT, "batch_size": _r(1, 1_000_000),
        "buffer_size": _r(1, 1e12, "transitions"), "learning_starts": _r(1, 1e12, "transitions"),
        "update_every": _r(1, 1_000_000, "env steps"), "target_update": _r(1, 1e9, "updates"),
        "eps_start": _UNIT, "eps_end": _UNIT, "eps_fraction": _pos(1), "grad_clip": _pos(1e6),
        "n_step": _r(1, 1_000_000), "priority_alpha": _r(0, 10), "priority_beta": _UNIT,
        "mixing_embed_dim": _r(1, 65_536)},
    TrainConfig: {
        "episodes": _r(1, 1e9), "eval_every": _r(1, 1e9, "episodes"),
        "eval_windows": _r(1, 1_000_000),
        # torchrl's env.set_seed hands the seed to numpy, which takes no negative seed
        "eval_seed": Range(0, SEED_END, hi_open=True, text=("0", "2^64")),
        "n_envs": _r(1, 1_000_000), "population": _r(1, 1000), "threads": _r(1, 1024)},
    RunConfig: {"seed": SEED_RANGE},
})
RANGES[TracesAppConfig] = RANGES[RunConfig]

# the lattice of pitch v·δt over the area: the start-position packing
# (uabs_rl.env.geometry.lattice_packing) compares every pair of its points
MAX_LATTICE_POINTS = 20_000


def lattice_points(scenario: ScenarioConfig) -> int:
    """Points of the lattice of pitch v·δt over the area (``Geometry.lattice_n``)."""
    step = scenario.speed * scenario.dt
    return ((math.floor(scenario.area.width / step) + 1)
            * (math.floor(scenario.area.height / step) + 1))


# ----------------------------------------------------------------------------- memory
def score_size(obs: ObsConfig) -> int:
    """Priority scores one agent's observation holds (the env state's ``look``;
    ``uabs_rl.env.params.EnvParams.n_lookahead``)."""
    if obs.frame == ObsFrame.egocentric:
        return (2 * obs.map_radius + 1) ** 2 * (1 + obs.motion)
    return (8 + 4 * obs.motion) if obs.lookahead else 0


def observation_size(scenario: ScenarioConfig, channel: ChannelConfig,
                     obs: ObsConfig | None = None) -> int:
    """Features of one agent's observation (``uabs_rl.env.params.EnvParams.obs_dim``)."""
    obs = ObsConfig() if obs is None else obs
    if obs.frame == ObsFrame.egocentric:
        return 1 + channel.n_beams + score_size(obs) + 3 * obs.neighbours + 4
    return 3 + 2 * scenario.n_uabs + channel.n_beams + score_size(obs)


def transition_bytes(obs_dim: int) -> int:
    """Bytes of one stored transition (``uabs_rl.algorithms.replay.storage``): obs and next_obs
    float32, action int64, mask and next_mask bool per move, reward float32,
    terminated bool."""
    return 2 * 4 * obs_dim + 8 + 2 * N_MOVES + 4 + 1


def env_bytes(scenario: ScenarioConfig, channel: ChannelConfig,
              obs: ObsConfig | None = None) -> int:
    """A lower bound on one training env's memory: its episode state
    (``uabs_rl.env.uabs_env.empty_state``) over the fleet's vehicles only, plus one step's two
    float32 beam-grid coordinates per UABS-vehicle link (``uabs_rl.env.links``)."""
    m, v, b = scenario.n_uabs, scenario.sumo.fleet_size, channel.n_beams
    look = score_size(ObsConfig() if obs is None else obs)
    # priority, served_count, window_full, prev_present, n_windows, ns_hist [N + 1]
    per_vehicle = 4 + 8 + 1 + 1 + 4 + 4 * (scenario.window_steps + 1)
    per_uabs = 4 * 2 + 8 + 4 * b + 4 * look  # pos, backup, b, look
    counters = 4 * 8 + 4 * 4  # t, sim, start, cursor (int64); ep_* (float32)
    return v * per_vehicle + m * per_uabs + counters + 2 * 4 * m * v


def trace_bytes(scenario: ScenarioConfig, split: SplitConfig) -> int:
    """A lower bound on one split's traces (``uabs_rl.traces.store.TraceSet``: float32 x, y
    and a bool per vehicle slot and step), counting the fleet's vehicles only."""
    steps = int(split.duration_s // scenario.dt)
    return split.n_sims * steps * scenario.sumo.fleet_size * (2 * 4 + 1)


def network_bytes(obs_dim: int, hidden: list[int]) -> int:
    """One member's Q-network in training: parameters, target copy, gradients and
    Adam's two moments, float32 (``uabs_rl.algorithms.model.DuelingQNet``)."""
    widths = [obs_dim, *hidden]
    params = sum((i + 1) * o for i, o in zip(widths, widths[1:], strict=False))
    params += (widths[-1] + 1) * (1 + N_MOVES)  # value and advantage heads
    return 5 * 4 * params


def available_memory(device: str) -> tuple[int, str] | None:
    """``(bytes, where)``: the memory a run on ``device`` can use (a CUDA device's free
    memory, else the machine's MemAvailable from /proc/meminfo, else os.sysconf), or
    None where it cannot be read (then nothing is refused)."""
    if device != "cpu":
        import torch

        if torch.cuda.is_available():
            try:
                dev = torch.device("cuda" if device == "auto" else device)
                return torch.cuda.mem_get_info(dev)[0], f"{dev} has"
            except (RuntimeError, AssertionError, ValueError):
                return None  # no such device: refused where the device is resolved
        if device != "auto":
            return None  # cuda without CUDA: refused where the device is resolved
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "this machine has"
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"), "this machine has"
    except (ValueError, OSError, AttributeError):
        return None


def _size(n: int) -> str:
    """``n`` bytes for a reader: 512 bytes, 1.5 GiB, ..."""
    x, unit = float(n), "bytes"
    for bigger in ("KiB", "MiB", "GiB", "TiB"):
        if x < 1024:
            break
        x, unit = x / 1024, bigger
    return f"{n} bytes" if unit == "bytes" else f"{x:.4g} {unit}"


def _check_fits(setting: str, need: int, what: str, have: tuple[int, str] | None,
                fix: str) -> None:
    """Refuse ``setting`` when ``what`` needs more than ``have`` (``available_memory``)."""
    if have is not None and need > have[0]:
        raise ConfigError(f"{setting}: {what} would need at least {_size(need)}, but "
                          f"{have[1]} {_size(have[0])} available: {fix}.")


def check_memory(cfg: RunConfig) -> None:
    """Refuse a run whose replay buffer, training envs, Q-networks or traces cannot fit
    in the memory of ``cfg.device``, before any of them is allocated. Every size is a
    lower bound (the envs and traces count the fleet's vehicles only), so a run that
    fits is never refused."""
    a, t, s, P = cfg.algo, cfg.train, cfg.scenario, cfg.train.population
    obs = observation_size(s, cfg.channel, cfg.obs)
    per_env = env_bytes(s, cfg.channel, cfg.obs)
    have = available_memory(cfg.device)
    parts = [
        ("algo.buffer_size", a.buffer_size * transition_bytes(obs) * P,
         f"the replay buffer ({a.buffer_size} transitions of {transition_bytes(obs)} bytes "
         f"x train.population={P})", "lower algo.buffer_size or train.population"),
        ("train.n_envs", per_env * t.n_envs * P,
         f"{t.n_envs} x train.population={P} training envs ({_size(per_env)} each)",
         "lower train.n_envs or train.population"),
        ("algo.hidden", network_bytes(obs, a.hidden) * P,
         f"the Q-network{f's of {P} members' if P > 1 else ''} (with target copy, "
         "gradients and Adam's moments)",
         "narrow algo.hidden or lower train.population"),
        ("traces.train/eval", sum(trace_bytes(c, cfg.traces.train)
                                  for c in family_scenarios(cfg) or [s])
         + trace_bytes(s, cfg.traces.eval),
         "the training and validation traces", "lower their n_sims or duration_s"),
    ]
    for key, need, what, fix in parts:
        _check_fits(key, need, what, have, fix)
    _check_fits(", ".join(p[0] for p in parts), sum(p[1] for p in parts),
                "the replay buffer, envs, Q-networks and traces together", have,
                "lower algo.buffer_size, train.n_envs or train.population")
