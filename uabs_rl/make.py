"""Factories: build the environment (with its masking transform) and the action
selector from configs. Entry points only wire these."""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Mapping
from pathlib import Path

import torch
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.transforms import ActionMask

from uabs_rl.config import (
    ChannelConfig,
    ConfigError,
    MaskingConfig,
    RunConfig,
    ScenarioConfig,
    TracesConfig,
)
from uabs_rl.env import ACTION, MASK, UABSEnv
from uabs_rl.masking import MaskedActionSelector, SafetyTransform, make_rule
from uabs_rl.traces import TraceSet, get_traces

log = logging.getLogger(__name__)


def make_env(scenario: ScenarioConfig, channel: ChannelConfig, masking: MaskingConfig,
             traces: TraceSet | TracesConfig, split: str = "train", n_envs: int = 1,
             device: str | torch.device = "cpu", n_eval_windows: int | None = None,
             seed: int | None = None, compile: bool = False,
             spec_mask: bool = True) -> TransformedEnv:
    """``UABSEnv`` over the ``split`` traces ("train": random windows; "eval"
    (validation) or "test": fixed windows), wrapped with the masking transform and,
    with ``spec_mask``, TorchRL's ``ActionMask`` (so ``env.rand_action()`` respects the
    written mask; the trainer acts through the selector and skips it).

    ``traces`` is a :class:`TraceSet` or the ``traces`` config (then loaded or built)."""
    if not isinstance(traces, TraceSet):
        traces = get_traces(scenario, traces, split)
    mode = "train" if split == "train" else "eval"
    base = UABSEnv(scenario, channel, traces, n_envs=n_envs, mode=mode, device=device,
                   n_eval_windows=n_eval_windows, seed=seed, compile_step=compile)
    rule = make_rule(masking, base.params).to(base.device)
    base.require_start_spacing(rule.start_margin)
    safety = SafetyTransform(rule)
    return TransformedEnv(base, Compose(safety, ActionMask(ACTION, MASK)) if spec_mask
                          else safety)


def make_selector(env: TransformedEnv, masking: MaskingConfig, eps: float = 0.0,
                  generator: torch.Generator | None = None,
                  compile: bool = False) -> MaskedActionSelector:
    """The ε-greedy masked selector of ``masking``'s rule for ``env``."""
    base = env.base_env
    rule = make_rule(masking, base.params).to(base.device)
    return MaskedActionSelector(rule, eps=eps, generator=generator, compile=compile).to(
        base.device)


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


# ----------------------------------------------------------------------------- threads
def cgroup_cpus(root: Path = Path("/sys/fs/cgroup"),
                proc_cgroup: Path = Path("/proc/self/cgroup")) -> int | None:
    """Whole CPUs of this process's cgroup CPU quota (cgroup v2 ``cpu.max``, v1
    ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``; the tightest on the way up to the
    root, at least 1), or None without a quota."""
    try:
        lines = proc_cgroup.read_text().splitlines()
    except OSError:
        return None
    quotas = []
    for line in lines:
        _, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if controllers == "":  # v2: one unified hierarchy
            files = [(root, "cpu.max", None)]
        elif "cpu" in controllers.split(","):  # v1: the cpu controller's own mount
            mount = root / controllers if (root / controllers).is_dir() else root / "cpu"
            files = [(mount, "cpu.cfs_quota_us", "cpu.cfs_period_us")]
        else:
            continue
        for mount, quota_file, period_file in files:
            quotas += [q for d in _up_to(mount, path) if (q := _quota(d, quota_file,
                                                                      period_file))]
    return max(1, math.floor(min(quotas))) if quotas else None


def _up_to(mount: Path, path: str) -> list[Path]:
    """``mount/path`` and its parents up to ``mount`` (only ``mount`` when ``path``
    is not below it, as in a container that sees the host's paths)."""
    d = mount / path.strip("/")
    if not d.is_dir():
        return [mount]
    out = [d]
    while d != mount:
        d = d.parent
        out.append(d)
    return out


def _quota(d: Path, quota_file: str, period_file: str | None) -> float | None:
    """The CPUs of one cgroup's quota, or None (no file, no limit)."""
    try:
        if period_file is None:  # v2: "max 100000" or "<quota> <period>"
            quota, period = (d / quota_file).read_text().split()[:2]
        else:
            quota = (d / quota_file).read_text().strip()
            period = (d / period_file).read_text().strip()
        if quota == "max" or int(quota) <= 0:
            return None
        return int(quota) / int(period)
    except (OSError, ValueError):
        return None


def usable_cpus(environ: Mapping[str, str] | None = None,
                cgroup_root: Path = Path("/sys/fs/cgroup"),
                proc_cgroup: Path = Path("/proc/self/cgroup")) -> tuple[int, str]:
    """``(n, what)``: the CPUs this process may use, the least of its CPU affinity, its
    cgroup CPU quota, ``SLURM_CPUS_PER_TASK`` and ``OMP_NUM_THREADS``, and which one
    sets it."""
    environ = os.environ if environ is None else environ
    try:
        limits = [(len(os.sched_getaffinity(0)), "affinity")]
    except AttributeError:  # not on Linux
        limits = [(os.cpu_count() or 1, "CPU count")]
    quota = cgroup_cpus(cgroup_root, proc_cgroup)
    if quota is not None:
        limits.append((quota, "the cgroup CPU quota"))
    for var in ("SLURM_CPUS_PER_TASK", "OMP_NUM_THREADS"):
        try:
            n = int(environ.get(var, ""))
        except ValueError:
            continue
        if n >= 1:
            limits.append((n, var))
    return min(limits, key=lambda lim: lim[0])


def update_work(cfg: RunConfig) -> int:
    """Multiply-adds of one forward pass of the Q-network over an update's batch
    (``algo.batch_size`` transitions of each of the M agents, of each member): the size
    of the products that more CPU threads split."""
    from uabs_rl.env import N_ACTIONS
    from uabs_rl.params import EnvParams

    widths = [EnvParams.from_config(cfg.scenario, cfg.channel).obs_dim, *cfg.algo.hidden]
    per_row = sum(i * o for i, o in zip(widths, widths[1:], strict=False))
    per_row += widths[-1] * (1 + N_ACTIONS)  # value and advantage heads
    return cfg.algo.batch_size * cfg.scenario.n_uabs * cfg.train.population * per_row


# update work from which the default uses a second thread, and one more per as much
# again: 16x the paper network's (hidden 256x256, batch 128 x 3 agents: 27M). Below it one
# thread: two were 1.3x faster on a quiet 2-core machine at 1x-8x the paper network, but
# 2-50x slower beside one busy process, OpenMP threads spinning for a sibling the busy
# process holds off its core (benchmarks/train_bench.py --threads, --busy)
WORK_PER_THREAD = 440_000_000


def resolve_threads(cfg: RunConfig, environ: Mapping[str, str] | None = None) -> tuple[int, str]:
    """``(n, why)``: the torch CPU threads of a run and the reason, for its log.

    ``train.threads`` when set. Else from the configuration alone, so that a run's
    thread count (and any rounding that depends on it) does not depend on the load it
    meets: one thread, unless an update's products reach :data:`WORK_PER_THREAD`
    multiply-adds, then one per that much, at most the CPUs this process may use
    (:func:`usable_cpus`)."""
    cpus, what = usable_cpus(environ)
    allowed = f"{cpus} CPU{'s' * (cpus != 1)} allowed by {what}"
    if cfg.train.threads is not None:
        return cfg.train.threads, f"{cfg.train.threads} (train.threads; {allowed})"
    work = update_work(cfg)
    n = min(cpus, max(1, work // WORK_PER_THREAD))
    rule = "one thread below" if work < WORK_PER_THREAD else "a thread per"
    return n, (f"{n} ({work / 1e6:,.1f}M multiply-adds per update: {rule} "
               f"{WORK_PER_THREAD / 1e6:.0f}M; {allowed})")
