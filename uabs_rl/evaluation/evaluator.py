"""Greedy evaluation on fixed held-out windows (docs/model.md §8): needs only an eval env and a
policy (a Q-network with the masking rule's selector, or a baseline); no trainer,
replay buffer or optimiser."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.envs import TransformedEnv

from uabs_rl.config import ConfigError, RunConfig
from uabs_rl.env.channel import coverage_fraction
from uabs_rl.env.uabs_env import AGENTS, DIAG, OBS, POSITION, REWARD, Outputs, window_count
from uabs_rl.rng import make_generator
from uabs_rl.safety.make import make_env, make_selector
from uabs_rl.safety.modules import DirectEnv, MaskedActionSelector, SafetyTransform
from uabs_rl.safety.rules import ACTION_VALUE
from uabs_rl.traces.build import get_traces
from uabs_rl.traces.cache import TraceSet

log = logging.getLogger(__name__)


class GreedyPolicy(TensorDictSequential):
    """A Q-network's policy: its Q-values under ``("agents", "action_value")``, then a
    masking rule's selector (a TorchRL policy module like any other). :class:`Evaluator`
    flies it without TorchRL's per-step TensorDicts (:meth:`Evaluator.rollout`)."""

    def __init__(self, qnet: nn.Module, selector: MaskedActionSelector):
        super().__init__(TensorDictModule(qnet, in_keys=[OBS], out_keys=[ACTION_VALUE]),
                         selector)

    @property
    def qnet(self) -> nn.Module:
        return self.module[0].module

    @property
    def selector(self) -> MaskedActionSelector:
        return self.module[1]


def greedy_policy(qnet: nn.Module, env: TransformedEnv, cfg: RunConfig,
                  compile: bool = False, members: int = 1) -> GreedyPolicy:
    """The greedy learned policy: Q-values, then the masking rule's choice with ε = 0.
    Its generator (one per population member) is seeded with ``train.eval_seed``: no
    draw decides anything when greedy, but evaluation stays off the global RNG."""
    gen = make_generator([cfg.train.eval_seed] * members if members > 1
                         else cfg.train.eval_seed, env.base_env.device)
    return GreedyPolicy(qnet, make_selector(env, 0.0, gen, compile=compile))


def make_eval_env(cfg: RunConfig, traces: TraceSet | None = None,
                  device: str | torch.device = "cpu", windows: int | None = None,
                  compile: bool = False, split: str = "eval",
                  members: int = 1, windows_name: str = "windows") -> TransformedEnv:
    """The held-out env of ``split`` ("eval": the validation traces that training
    evaluates on; "test": the traces every reported figure comes from) with ``windows``
    fixed windows, one env each (default: ``train.eval_windows`` for validation, every
    window of the test traces for test); eager unless ``compile``: an evaluation is a few
    rollouts, and compiling its shape (20-36 s for the main job's 10 windows) costs more
    than it saves (60-90 ms a rollout). With ``members`` > 1, the windows once per
    member of a population, side by side, each block with its own generator seeded
    alike.
    ``windows_name`` is how the caller's user gave ``windows`` (``--windows``)."""
    tr = cfg.train
    traces = get_traces(cfg.scenario, cfg.traces, split) if traces is None else traces
    n = eval_window_count(cfg, traces, split, windows, windows_name)
    seed = [tr.eval_seed] * members if members > 1 else tr.eval_seed
    return make_env(cfg.scenario, cfg.channel, cfg.masking, traces, split,
                    n_envs=n * members, device=device, n_eval_windows=n, seed=seed,
                    compile=compile, spec_mask=False, obs=cfg.obs)


def eval_window_count(cfg: RunConfig, traces: TraceSet, split: str,
                      windows: int | None = None, windows_name: str = "windows") -> int:
    """How many fixed windows ``make_eval_env`` evaluates: ``windows``, else
    ``train.eval_windows`` on "eval", else every window of ``traces``. Refuses
    (naming the setting to change) traces too short for one episode and more windows
    than they hold."""
    t, key = cfg.scenario.episode_steps, f"traces.{split}"
    most = window_count(traces.n_sims, traces.steps, t)
    if most == 0:
        raise ConfigError(
            f"scenario.episode_steps={t} needs windows of {t + 1} steps but the {split} "
            f"traces hold {traces.steps} steps ({key}.duration_s="
            f"{getattr(cfg.traces, split).duration_s:g} s at scenario.dt={cfg.scenario.dt:g} s): "
            f"lower scenario.episode_steps or raise {key}.duration_s.")
    if windows is not None:
        n, setting = windows, windows_name
    elif split == "eval":
        n, setting = cfg.train.eval_windows, "train.eval_windows"
    else:
        return most
    if not 1 <= n <= most:
        given = f"{setting} {n}" if setting.startswith("--") else f"{setting}={n}"
        raise ConfigError(
            f"{given} but the {split} traces hold {most} non-overlapping windows of {t} "
            f"steps ({t + 1} recorded instants each; {traces.n_sims} x {traces.steps} "
            f"instants): lower {setting} or "
            f"raise {key}.n_sims / {key}.duration_s.")
    return n


def _stacked(steps: list[Outputs], m: int) -> TensorDict:
    """Per-step outputs ``[E, ...]`` stacked along time, as the TensorDict ``[E, T]``
    of ``env.rollout`` (the agents' entries ``[E, T, M]``)."""
    e = steps[0][OBS].shape[0]
    shape, device = [e, len(steps)], steps[0][OBS].device
    groups: dict[str, dict[str, torch.Tensor]] = {}
    root: dict[str, torch.Tensor] = {}
    for key in steps[0]:
        value = torch.stack([s[key] for s in steps], 1)
        if isinstance(key, tuple):
            groups.setdefault(key[0], {})[key[1]] = value
        else:
            root[key] = value
    for name, entries in groups.items():
        root[name] = TensorDict(entries, batch_size=shape + ([m] if name == AGENTS else []),
                                device=device)
    return TensorDict(root, batch_size=shape, device=device)


def vehicle_windows(base) -> torch.Tensor | None:
    """``[n]`` (CPU) whether each fixed window of the eval-mode env ``base`` holds a
    vehicle at one of its T + 1 steps, or None when every one does (or ``base`` draws
    random windows: training)."""
    windows = getattr(base, "eval_windows", None)
    if windows is None:
        return None
    sim, start = windows[:, 0].cpu(), windows[:, 1].cpu()
    steps = start[:, None] + torch.arange(base.params.episode_steps + 1)  # [n, T+1]
    present = base.veh_present.cpu()[sim[:, None], steps]  # [n, T+1, V]
    has = present.flatten(1).any(-1)
    return None if bool(has.all()) else has


class Evaluator:
    """Runs a policy on every fixed held-out window of ``env``, seeded with ``seed`` so
    every call sees the same episodes and start positions."""

    def __init__(self, env: TransformedEnv, seed: int):
        self.env, self.seed = env, seed
        self.params = env.base_env.params
        # called after every step of a rollout but its last when set (uabs-eval: the
        # thread governor's look at the CPUs, training.threads.ThreadGovernor.check)
        self.on_step: Callable[[], object] | None = None
        self._direct: DirectEnv | None = None  # the env without TensorDicts, once built
        # which fixed windows hold a vehicle at some step; in one without any, the served
        # fraction and P_g are undefined: NaN, left out of the means (None: all hold one)
        self.has_vehicles = vehicle_windows(env.base_env)
        if self.has_vehicles is not None:
            empty = int((~self.has_vehicles).sum())
            log.warning("%d of %d evaluation windows had no vehicle: their served fraction "
                        "and P_g are undefined (NaN) and left out of the means", empty,
                        self.has_vehicles.numel())

    @torch.no_grad()
    def evaluate(self, policy: TensorDictModuleBase, episode: int = 0,
                 env_steps: int = 0) -> tuple[dict[str, Any], TensorDictBase]:
        """The record (R, safety counters, served fraction, P_g and its curve, closest
        approach, coverage) and the rollout of ``policy``."""
        td = self.rollout(policy)
        return self.record(td, episode, env_steps), td

    @torch.no_grad()
    def rollout(self, policy: TensorDictModuleBase) -> TensorDictBase:
        """One seeded episode of ``policy`` in every env: ``[E, T]``, as
        ``env.rollout`` returns it. A :class:`GreedyPolicy` flies through
        :meth:`direct_rollout`, every other policy through ``env.rollout``."""
        self.env.set_seed(self.seed)
        if isinstance(policy, GreedyPolicy) and isinstance(self.env.transform,
                                                           SafetyTransform):
            return self.direct_rollout(policy)
        hook = self.on_step
        return self.env.rollout(self.params.episode_steps, policy, break_when_any_done=False,
                                callback=None if hook is None else lambda env, td: hook())

    @torch.no_grad()
    def direct_rollout(self, policy: GreedyPolicy) -> TensorDictBase:
        """``env.rollout`` of ``policy`` from the env's current seed, entry for entry
        (``tests/test_masking.py``): the same modules and the same compiled programs
        (the selector's choice, the env's step math), stepped through
        :class:`~uabs_rl.safety.modules.DirectEnv` without TorchRL's TensorDicts and
        checks at every step (most of an evaluation's rollout time). ``on_step`` is
        called as ``env.rollout``'s callback would be."""
        if self._direct is None:
            self._direct = DirectEnv(self.env, one_program=False)
        direct, selector, qnet = self._direct, policy.selector, policy.qnet
        steps, hook = self.params.episode_steps, self.on_step
        td, roots, nexts = direct.reset(), [], []
        for t in range(steps):
            selector(td.set(ACTION_VALUE, qnet(td.get(OBS))))
            nxt = direct.step(td)
            roots.append(td)
            nexts.append(nxt)
            if hook is not None and t < steps - 1:
                hook()
            # the next root: what TorchRL's step_mdp keeps of the step's outputs
            td = Outputs({k: v for k, v in nxt.items() if k != REWARD})
        out = _stacked(roots, self.params.n_uabs)
        out["next"] = _stacked(nexts, self.params.n_uabs)
        return out

    def record(self, td: TensorDictBase, episode: int = 0, env_steps: int = 0) -> dict[str, Any]:
        """The evaluation record of the rollout ``td`` (or of a block of its envs: a
        population member's)."""
        last = td["next", DIAG][:, -1]
        ret = last["ep_return"]
        record = {
            "kind": "eval", "episode": episode, "env_steps": env_steps,
            "return": ret.mean().item(),
            "return_std": ret.std().item() if ret.numel() > 1 else 0.0,
            "returns": ret.tolist(),
            "collisions": last["ep_collisions"].sum().item(),
            "episodes_with_collision": int((last["ep_collisions"] > 0).sum().item()),
            "proximity": last["ep_proximity"].sum().item(),
            "fallbacks": last["ep_fallbacks"].sum().item(),
            "served_fraction": td["next", DIAG, "served_fraction"].mean().item(),
            "served_fractions": td["next", DIAG, "served_fraction"].mean(-1).tolist(),
            "pg": last["pg"].mean().item(),
            "pgs": last["pg"].tolist(),
            "pg_curve": last["pg_curve"].mean(0).tolist(),
            "closest_approach": td["next", DIAG, "closest_approach"].min().item(),
            "coverage": self.coverage(td["next", POSITION]),
            "windows": int(ret.numel())}
        if self.has_vehicles is not None:
            record.update(self.without_empty_windows(td, last))
        return record

    def without_empty_windows(self, td: TensorDictBase, last: TensorDictBase) -> dict[str, Any]:
        """The served fraction and P_g entries of a record over the windows that hold a
        vehicle (NaN per window for the others, NaN overall when none does), and
        ``no_vehicle_windows``, their count. Rows are windows ``row % n`` (a
        population's block of ``n`` rows each)."""
        rows = torch.arange(td.shape[0]) % self.has_vehicles.numel()
        keep = self.has_vehicles[rows].to(td.device)
        nan = torch.full((), float("nan"), device=td.device)
        sf, pg = td["next", DIAG, "served_fraction"], last["pg"]
        return {
            "served_fraction": sf[keep].mean().item(),
            "served_fractions": torch.where(keep, sf.mean(-1), nan).tolist(),
            "pg": pg[keep].mean().item(),
            "pgs": torch.where(keep, pg, nan).tolist(),
            "pg_curve": last["pg_curve"][keep].mean(0).tolist(),
            "no_vehicle_windows": int((~keep).sum())}

    def coverage(self, pos: torch.Tensor) -> float:
        """Mean share of the area under footprints over the evaluated steps (10 m grid)."""
        p = self.params
        return coverage_fraction(pos, p.r_b, p.n_beams, p.width, p.height, 10.0).mean().item()

    def trajectory_of(self, td: TensorDictBase, window: int = 0):
        """UABS path [T+1, M, 2], vehicles [T+1, 2, V] and presence of one eval window."""
        path = torch.cat([td[POSITION][window, :1], td["next", POSITION][window]])
        return (path, *self.env.base_env.window_trace(window))
