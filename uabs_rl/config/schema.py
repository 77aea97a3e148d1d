"""The config schemas: one dataclass per section, every default written once with its
comment, and each setting's :class:`~uabs_rl.config.base.Role` (``setting(Role...)``; a
section's role holds for its fields that declare none). Hydra validates every yaml under
``conf/`` against them (registered by :func:`uabs_rl.config.store.register_configs`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from uabs_rl.config.base import (
    RANGES,
    SEED_END,
    SEED_RANGE,
    SUMO_SEED_MAX,
    LoggerKind,
    LosMode,
    LossKind,
    MaskingMode,
    ObsFrame,
    Range,
    RankNextMask,
    ReplayKind,
    Role,
    _pos,
    _r,
    setting,
)


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
    test: SplitConfig = setting(Role.test, default_factory=lambda: SplitConfig(
        first_seed=20_000, n_sims=8, duration_s=600.0))
    # null = $UABS_RL_CACHE/traces, default ~/.cache/uabs_rl/traces
    cache_dir: str | None = setting(Role.runtime, None)
    workers: int = setting(Role.runtime, 0)  # SUMO processes in parallel; 0 = one per core


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




@dataclass
class ObsConfig:
    """What each UABS observes: the network's input (docs/model.md §5). Its own group,
    apart from ``scenario``, so a policy evaluated in another city keeps the observation
    it was trained on. ``obs=paper`` (default), ``lookahead``, ``lookahead_motion``,
    ``egocentric``."""

    # a label for reports; the fields below decide the observation
    name: str = setting(Role.label, "paper")
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
    # fleet frame with motion, beyond the paper: also, for k = 2 .. motion_steps, the
    # priority the footprints would cover k moves along each direction at the vehicles'
    # positions extrapolated k steps (x_t + k (x_t - x_{t-1})), 4 numbers per k: where
    # the traffic will be over the horizon the mpc plans (1 = the 4 one-step scores only)
    motion_steps: int = 1
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



@dataclass
class AlgoConfig:
    """3DQN: shared dueling double DQN (docs/model.md §7). Defaults follow the authors' single-UABS
    3DQN where the paper is silent (see docs/configuration.md, "Learning hyper-parameters")."""

    name: str = "dqn3"  # the learner: a key of uabs_rl.algorithms.ALGORITHMS (dqn3, vdn, qmix, ...)
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
    # fused (hand-written, same maths) | torchrl (DQNLoss)
    loss: LossKind = setting(Role.method, LossKind.fused)
    # beyond the paper: uniform | prioritized (proportional, as TorchRL's
    # PrioritizedSampler: draws in proportion to (|TD error| + 1e-8)^priority_alpha, new
    # transitions at the highest priority so far, the loss weighted by
    # (p_i / p_min)^-priority_beta; uabs_rl.algorithms.replay.Priorities)
    replay: ReplayKind = ReplayKind.uniform
    priority_alpha: float = 0.6  # prioritization exponent α (0: uniform draws)
    priority_beta: float = 0.4  # importance-weight exponent β (1: the bias fully corrected)


@dataclass
class QmixConfig(AlgoConfig):
    """QMIX's own settings beside the shared ones (``algo=qmix``: conf/algo/qmix.yaml
    selects this schema, so ``algo.mixing_embed_dim`` is a key of that learner only)."""

    name: str = "qmix"
    mixing_embed_dim: int = 32  # width of the mixing network (its hypernetworks)


@dataclass
class DqfdConfig(AlgoConfig):
    """The teacher-guided 3DQN's own settings (``algo=dqfd``: conf/algo/dqfd.yaml;
    uabs_rl/algorithms/dqfd.py). At every training step a privileged teacher, the
    clairvoyant receding-horizon planner, labels the states the learner's own ε-greedy
    policy visits (DAgger); the loss adds to the 3DQN's TD loss a large-margin term
    (DQfD) that pulls the teacher's move above every other legal move by a margin."""

    name: str = "dqfd"
    teacher_horizon: int = 5  # the teacher planner's horizon H (uabs-eval --horizon)
    # J_E = max_{a legal} [Q(o, a) + margin · (a != a_E)] − Q(o, a_E), in the reward's
    # units: about the gap between a trained network's two best moves (5.8, measured on
    # experiment=lookahead_motion)
    teacher_margin: float = 5.0
    imitation_weight: float = 1.0  # λ_E: the loss is TD + λ_E · J_E (0: the 3DQN's loss)


# the learners with settings of their own, by algo.name; the others take AlgoConfig
LEARNER_SCHEMAS: dict[str, type[AlgoConfig]] = {"qmix": QmixConfig, "dqfd": DqfdConfig}


def algo_schema(name: object) -> type[AlgoConfig]:
    """The schema of the learner ``algo.name = name`` (AlgoConfig unless it has settings
    of its own)."""
    return LEARNER_SCHEMAS.get(str(name), AlgoConfig)


@dataclass
class TrainConfig:
    """Training protocol (docs/model.md §7, §8)."""

    episodes: int = setting(Role.protocol, 1000)  # N_t
    # N_e: greedy evaluation on held-out traces every N_e episodes (after the round of
    # n_envs episodes that reaches each multiple of N_e)
    eval_every: int = setting(Role.protocol, 20)
    # held-out windows per evaluation (the paper evaluates 1)
    eval_windows: int = setting(Role.protocol, 10)
    # start positions of every evaluation (the same each time)
    eval_seed: int = setting(Role.evaluation, 12345)
    # episodes in parallel; updates per collector step = n_envs / algo.update_every;
    # train.episodes must be a multiple of it
    n_envs: int = setting(Role.policy, 1)
    # seeds trained together in one process: seed, seed + 1, ..., seed + population - 1,
    # their episodes side by side in one env and their networks stacked (batched
    # products); each member writes a solo run's folder, <run>/seed=<s>/ (docs/scaling.md,
    # "Population training", says what differs from training each alone)
    population: int = setting(Role.method, 1)
    # also store the replay buffer in checkpoints (~20 MB)
    checkpoint_buffer: bool = setting(Role.runtime, False)
    # TorchRL logger: tensorboard (<run>/tb) | csv (<run>/csv) | wandb | mlflow
    # (<run>/mlruns) | none; wandb and mlflow need their package installed
    logger: LoggerKind = setting(Role.runtime, LoggerKind.tensorboard)
    # held-out trajectory picture at each evaluation
    trajectory_images: bool = setting(Role.runtime, True)
    progress: bool = setting(Role.runtime, True)  # training's progress bar (SUMO's: a tty's)
    # torch.compile the env step (with the masking rule) and the decision (Q forward,
    # target mask, masked choice): ~2x faster training, ~20 s to compile (eager if
    # compilation fails)
    compile: bool = setting(Role.runtime, True)
    # run each update (loss, gradient, Adam) as one compiled program, any learner, solo or
    # population (uabs_rl/algorithms/compiled_update.py): results equal to the eager
    # update's to float32 rounding, not bit for bit; ~15 s to compile; null = as
    # train.compile
    compile_update: bool | None = setting(Role.runtime, None)
    # torch CPU threads; null = by the update's size, at most the CPUs this process may use,
    # fewer while other processes keep them busy (uabs_rl/training/threads.py); set it for runs
    # that must be bit-reproducible whatever the load, and to cores / n_jobs in sweeps
    threads: int | None = setting(Role.runtime, None)


@dataclass
class RunConfig:
    """Top-level config of ``uabs-train``."""

    scenario: ScenarioConfig = setting(Role.world, default_factory=ScenarioConfig)
    obs: ObsConfig = setting(Role.policy, default_factory=ObsConfig)
    channel: ChannelConfig = setting(Role.world, default_factory=ChannelConfig)
    masking: MaskingConfig = setting(Role.world, default_factory=MaskingConfig)
    algo: AlgoConfig = setting(Role.policy, default_factory=AlgoConfig)
    traces: TracesConfig = setting(Role.world, default_factory=TracesConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    # beyond the paper: train over several cities at once. Each entry is a city given by
    # what differs from `scenario` (name, area, sumo: its network and vehicles; {} is
    # `scenario` itself); each training env draws its city per episode among them.
    # Empty: `scenario` only. Validation and the default evaluation stay on `scenario`.
    family: list[Any] = setting(Role.policy, default_factory=list)
    # network init, exploration, training windows and start positions
    seed: int = setting(Role.seed, 0)
    device: str = setting(Role.runtime, "cpu")  # cpu | cuda | cuda:N | auto
    # a run directory (outputs/runs/...) to continue
    resume: str | None = setting(Role.runtime, None)


@dataclass
class TracesAppConfig(RunConfig):
    """Top-level config of ``uabs-traces``: the same groups and presets as ``uabs-train``
    (only ``scenario`` and ``traces`` decide the traces), plus which split to build."""

    # which traces to build: train, eval, test or all (uabs-traces split=test)
    split: str = setting(Role.runtime, "all")


# settings that moved: (section, old key) -> (section, new key); stored configs are
# upgraded (uabs_rl.runs.checkpoint.upgrade_config), command lines refused by
# uabs_rl.config.overrides.check_moved_overrides
MOVED = {("scenario", "lookahead_obs"): ("obs", "lookahead"),
         ("scenario", "motion_obs"): ("obs", "motion"),
         ("scenario", "priority_obs_scale"): ("obs", "priority_scale")}

FAMILY_KEYS = ("name", "area", "sumo")  # what a family's cities may set


# Every number a config holds, by dataclass and field: finite, physically meaningful
# ranges, wide enough for every preset and documented experiment (a list: each entry).
# Checked at start-up after the checks that relate settings to each other, so a value
# those explain better (scenario.dt=-1: "must be > 0 seconds") keeps their message.
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
                "motion_steps": _r(1, 1000, "steps"),
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
        "n_step": _r(1, 1_000_000), "priority_alpha": _r(0, 10), "priority_beta": _UNIT},
    TrainConfig: {
        "episodes": _r(1, 1e9), "eval_every": _r(1, 1e9, "episodes"),
        "eval_windows": _r(1, 1_000_000),
        # torchrl's env.set_seed hands the seed to numpy, which takes no negative seed
        "eval_seed": Range(0, SEED_END, hi_open=True, text=("0", "2^64")),
        "n_envs": _r(1, 1_000_000), "population": _r(1, 1000), "threads": _r(1, 1024)},
    RunConfig: {"seed": SEED_RANGE},
})
RANGES[TracesAppConfig] = RANGES[RunConfig]
RANGES[QmixConfig] = {**RANGES[AlgoConfig], "mixing_embed_dim": _r(1, 65_536)}
RANGES[DqfdConfig] = {**RANGES[AlgoConfig], "teacher_horizon": _r(1, 1_000_000),
                      "teacher_margin": _r(0, 1e9), "imitation_weight": _r(0, 1e9)}
