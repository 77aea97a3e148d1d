"""``uabs-train``'s start-up checks: every setting checked, each refusal naming the key,
before anything is built or written. The per-section checks are the config layer's
(:mod:`uabs_rl.config.checks`); here are those that ask the env, the learner or the
evaluator: a channel model's name, a masking mode's rule, the learner's own refusals,
the validation windows, and whether the replay, the envs, the networks and the traces
fit in memory, each size given by its owner."""

from __future__ import annotations

from types import SimpleNamespace

from uabs_rl.algorithms import Dims, algorithm_class
from uabs_rl.algorithms.replay import transition_bytes
from uabs_rl.config import (
    AlgoConfig,
    ConfigError,
    RunConfig,
    check_algo_schema,
    check_finite,
    family_scenarios,
    memory,
    validate_device,
    validate_family,
    validate_learning,
)
from uabs_rl.env.channel import CHANNELS
from uabs_rl.env.params import EnvParams, validate_world
from uabs_rl.env.state import state_bytes
from uabs_rl.env.uabs_env import N_ACTIONS
from uabs_rl.evaluation.evaluator import eval_window_count
from uabs_rl.safety.rules import rule_class


def registered_names() -> dict[str, set[str]]:
    """The names the registries hold, per config group: the learners, the channel models
    and the masking modes (an option so named must select it:
    :func:`uabs_rl.config.check_group_choices`)."""
    from uabs_rl.algorithms import ALGORITHMS
    from uabs_rl.config import MaskingMode

    return {"algo": set(ALGORITHMS), "channel": set(CHANNELS),
            "masking": {m.value for m in MaskingMode}}


def validate_run(cfg: RunConfig) -> None:
    """Every start-up check of ``uabs-train``, each naming the offending key: nothing is
    built or written before they pass."""
    validate_settings(cfg)
    validate_device(cfg.device)
    check_memory(cfg)


def validate_settings(cfg: RunConfig) -> None:
    """The start-up checks of the settings alone, not of the machine (its device and
    memory): what a sweep checks for each of its jobs before any starts, where a job
    may run on another machine (a SLURM node)."""
    check_finite(cfg)
    validate_world(cfg)
    validate_family(cfg, CHANNELS)
    rule_class(cfg.masking.mode)  # a masking mode without a registered rule
    validate_algo_name(cfg.algo)
    validate_learning(cfg)
    check_eval_windows(cfg)


def validate_algo_name(algo: AlgoConfig) -> None:
    """``algo.name`` names a registered algorithm (``uabs_rl.algorithms``), ``algo``
    holds that learner's settings, and it accepts them."""
    cls = algorithm_class(algo.name)
    check_algo_schema(algo)
    cls.check_config(algo)


def check_eval_windows(cfg: RunConfig) -> None:
    """Training and validation traces long enough for an episode, and
    ``train.eval_windows`` against the windows the validation traces will hold
    (n_sims x duration_s / dt steps, as they are built), before any trace is built:
    the refusals the env and :func:`~uabs_rl.evaluation.evaluator.eval_window_count`
    give once they are."""
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


def check_memory(cfg: RunConfig) -> None:
    """Refuse a run whose replay buffer, training envs, Q-networks or traces cannot fit
    in the memory of ``cfg.device``, before any of them is allocated. Every size is a
    lower bound (the envs and traces count the fleet's vehicles only), so a run that
    fits is never refused."""
    a, t, s, P = cfg.algo, cfg.train, cfg.scenario, cfg.train.population
    params = EnvParams.from_config(s, cfg.channel, cfg.obs)
    per_step = transition_bytes(params.obs_dim, N_ACTIONS)
    per_env = state_bytes(params, s.sumo.fleet_size)
    net = algorithm_class(a.name).network_bytes(a, Dims(params.obs_dim, N_ACTIONS, s.n_uabs))
    have = memory.available_memory(cfg.device)
    size = memory.size_text
    parts = [
        ("algo.buffer_size", a.buffer_size * per_step * P,
         f"the replay buffer ({a.buffer_size} transitions of {per_step} bytes "
         f"x train.population={P})", "lower algo.buffer_size or train.population"),
        ("train.n_envs", per_env * t.n_envs * P,
         f"{t.n_envs} x train.population={P} training envs ({size(per_env)} each)",
         "lower train.n_envs or train.population"),
        ("algo.hidden", net * P,
         f"the Q-network{f's of {P} members' if P > 1 else ''} (with target copy, "
         "gradients and Adam's moments)",
         "narrow algo.hidden or lower train.population"),
        ("traces.train/eval", sum(memory.trace_bytes(c, cfg.traces.train)
                                  for c in family_scenarios(cfg) or [s])
         + memory.trace_bytes(s, cfg.traces.eval),
         "the training and validation traces", "lower their n_sims or duration_s"),
    ]
    for key, need, what, fix in parts:
        memory.check_fits(key, need, what, have, fix)
    memory.check_fits(", ".join(p[0] for p in parts), sum(p[1] for p in parts),
                      "the replay buffer, envs, Q-networks and traces together", have,
                      "lower algo.buffer_size, train.n_envs or train.population")
