"""Factories: build the environment (with its masking transform) and the action
selector from configs. Entry points only wire these."""

from __future__ import annotations

import logging

import torch
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.transforms import ActionMask

from uabs_rl.config import (
    ChannelConfig,
    ConfigError,
    MaskingConfig,
    ObsConfig,
    ScenarioConfig,
    TracesConfig,
)
from uabs_rl.env.uabs_env import ACTION, MASK, UABSEnv
from uabs_rl.safety.modules import MaskedActionSelector, SafetyTransform, env_rule
from uabs_rl.safety.rules import make_rule
from uabs_rl.traces.build import get_traces
from uabs_rl.traces.cache import TraceSet

log = logging.getLogger(__name__)


def make_env(scenario: ScenarioConfig, channel: ChannelConfig, masking: MaskingConfig,
             traces: TraceSet | TracesConfig, split: str = "train", n_envs: int = 1,
             device: str | torch.device = "cpu", n_eval_windows: int | None = None,
             seed: int | None = None, compile: bool = False,
             spec_mask: bool = True, obs: ObsConfig | None = None) -> TransformedEnv:
    """``UABSEnv`` over the ``split`` traces ("train": random windows; "eval"
    (validation) or "test": fixed windows), wrapped with the masking transform and,
    with ``spec_mask``, TorchRL's ``ActionMask`` (so ``env.rand_action()`` respects the
    written mask; the trainer acts through the selector and skips it).

    ``traces`` is a :class:`TraceSet` or the ``traces`` config (then loaded or built);
    ``obs`` the observation (None: the paper's)."""
    if not isinstance(traces, TraceSet):
        traces = get_traces(scenario, traces, split)
    mode = "train" if split == "train" else "eval"
    base = UABSEnv(scenario, channel, traces, n_envs=n_envs, mode=mode, device=device,
                   n_eval_windows=n_eval_windows, seed=seed, compile_step=compile, obs=obs)
    rule = make_rule(masking, base.params).to(base.device)
    base.require_start_spacing(rule.start_margin)
    safety = SafetyTransform(rule)
    return TransformedEnv(base, Compose(safety, ActionMask(ACTION, MASK)) if spec_mask
                          else safety)


def make_selector(env: TransformedEnv, eps: float = 0.0,
                  generator: torch.Generator | None = None,
                  compile: bool = False) -> MaskedActionSelector:
    """The ε-greedy masked selector of ``env``'s masking rule: the rule :func:`make_env`
    built once for the env, handed on (not built again from the config)."""
    return MaskedActionSelector(env_rule(env), eps=eps, generator=generator,
                                compile=compile).to(env.base_env.device)


def resolve_device(name: str) -> torch.device:
    """The torch device of the ``device`` setting (cpu, cuda, cuda:N or auto)."""
    if name == "auto":
        if not torch.cuda.is_available():
            log.info("device=auto: using cpu (no CUDA)")
            return torch.device("cpu")
        index = torch.cuda.current_device()
        log.info("device=auto: using cuda:%d (%s)", index, torch.cuda.get_device_name(index))
        return torch.device("cuda")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device={name} but CUDA is not available here: use device=cpu "
                          f"or device=auto.")
    return torch.device(name)
