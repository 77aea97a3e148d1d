"""Torch CPU threads of a run: how many CPUs this process may use, how many threads its
update's size warrants, and a governor that uses fewer while other processes keep those
CPUs busy (OpenMP threads spin-wait for a sibling that a busy core holds off, so two
threads beside one busy process train several times slower than one:
``benchmarks/train_bench.py --busy``)."""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Mapping
from pathlib import Path

import torch

from uabs_rl.config import RunConfig

log = logging.getLogger(__name__)

# clock ticks per second of /proc's CPU times
TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


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
    from uabs_rl.algorithms import Dims, algorithm_class
    from uabs_rl.env.params import EnvParams
    from uabs_rl.env.uabs_env import N_ACTIONS

    obs_dim = EnvParams.from_config(cfg.scenario, cfg.channel, cfg.obs).obs_dim
    dims = Dims(obs_dim, N_ACTIONS, cfg.scenario.n_uabs)
    per_row = algorithm_class(cfg.algo.name).network_size(cfg.algo, dims).multiply_adds
    return cfg.algo.batch_size * cfg.scenario.n_uabs * cfg.train.population * per_row


# update work per thread of the default's most threads: below it one thread. On a quiet
# 2-core machine two threads train faster from about this size up (the paper network,
# 27M, gets two; see benchmarks/train_bench.py --threads with algo.hidden=[...]); beside a
# busy process the ThreadGovernor takes the count down
WORK_PER_THREAD = 10_000_000


def resolve_threads(cfg: RunConfig, environ: Mapping[str, str] | None = None) -> tuple[int, str]:
    """``(n, why)``: the torch CPU threads a run starts with and the reason, for its log.

    ``train.threads`` when set. Else the most the default uses (:class:`ThreadGovernor`
    takes it down while other processes keep the CPUs busy): one thread, unless an
    update's products reach :data:`WORK_PER_THREAD` multiply-adds, then one per that
    much, at most the CPUs this process may use (:func:`usable_cpus`)."""
    cpus, what = usable_cpus(environ)
    allowed = f"{cpus} CPU{'s' * (cpus != 1)} allowed by {what}"
    if cfg.train.threads is not None:
        return cfg.train.threads, f"{cfg.train.threads} (train.threads; {allowed})"
    work = update_work(cfg)
    n = min(cpus, max(1, work // WORK_PER_THREAD))
    rule = "one thread below" if work < WORK_PER_THREAD else "a thread per"
    return n, (f"{n} ({work / 1e6:,.1f}M multiply-adds per update: {rule} "
               f"{WORK_PER_THREAD / 1e6:.0f}M; {allowed})")


class ThreadGovernor:
    """The default thread count (``train.threads`` unset) at run time: :func:`resolve_threads`'s
    count while the CPUs this process may use are free, fewer while other processes keep
    them busy. :meth:`check`, called once a round, looks every ``period_s`` at the busy
    time of those CPUs (``/proc/stat``) less the CPU time of this process and its
    children (torch.compile's workers): ``other`` cores in use by others. Above ``NOISE``
    of a core it uses the CPUs they leave whole, ``floor(cpus - other + NOISE)``, at
    least one; at or below, the full count again. A new count is taken only when two
    looks in a row agree on it, so a burst of a second changes nothing.

    The thread count changes the rounding of some products (a reduction split in two), so
    a default run is bit-reproducible only under the same load: a run that must be so
    whatever the load sets ``train.threads``. With a fixed count, or one thread at most,
    or no ``/proc/stat``, it does nothing."""

    NOISE = 0.25  # cores of others' use ignored (kernel threads, a shell, a monitor)

    def __init__(self, most: int, fixed: bool, period_s: float = 1.0,
                 stat: Path = Path("/proc/stat")) -> None:
        self.most = self.n = most
        self.period_s, self.stat = period_s, stat
        try:
            self.cpus = sorted(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            self.cpus = []
        self.active = not fixed and most > 1 and self._busy() is not None
        self.changes = 0
        self._proposed: int | None = None
        self._last = self._sample() if self.active else None

    def _busy(self) -> float | None:
        """Busy seconds of this process's CPUs since boot, or None without /proc/stat."""
        try:
            lines = self.stat.read_text().splitlines()
        except OSError:
            return None
        wanted = {f"cpu{c}" for c in self.cpus}
        busy = 0
        for line in lines:
            name, *fields = line.split()
            if name in wanted:
                vals = [int(v) for v in fields[:8]]
                busy += sum(vals) - vals[3] - vals[4]  # all but idle and iowait
        return busy / TICKS

    def _sample(self) -> tuple[float, float, float]:
        return time.monotonic(), self._busy() or 0.0, time.process_time() + _children_cpu()

    def others(self, before: tuple[float, float, float],
               after: tuple[float, float, float]) -> float:
        """Cores that other processes kept busy between two samples."""
        wall = after[0] - before[0]
        return max(0.0, (after[1] - before[1]) - (after[2] - before[2])) / wall

    def threads_for(self, others: float) -> int:
        """The thread count beside ``others`` busy cores."""
        if others <= self.NOISE:
            return self.most
        free = math.floor(len(self.cpus) - others + self.NOISE)
        return max(1, min(self.most, free))

    def check(self) -> int:
        """Look again if ``period_s`` passed; set and return the thread count."""
        if not self.active:
            return self.n
        now = self._sample()
        if now[0] - self._last[0] < self.period_s:
            return self.n
        others = self.others(self._last, now)
        self._last = now
        n = self.threads_for(others)
        n, self._proposed = (n, None) if n == self._proposed else (self.n, n)
        if n != self.n:
            log.info("threads: %d -> %d (other processes kept %.1f of %d CPUs busy)",
                     self.n, n, others, len(self.cpus))
            torch.set_num_threads(n)
            self.n, self.changes = n, self.changes + 1
        return n


def _children_cpu(pid: int | None = None) -> float:
    """CPU seconds of the descendants of ``pid`` (this process), running or finished:
    each running descendant's own time and that of its children it has waited for,
    and this process's waited-for children's (``/proc/<pid>/stat`` utime, stime,
    cutime, cstime; 0 where /proc lists none). torch.compile's compile workers are
    children that start compilers as children of their own, each running a second or
    two between two looks: counted only while running, a compile would read as other
    processes keeping the CPUs busy."""
    root = os.getpid() if pid is None else pid
    total, todo = 0, [root]
    while todo:
        parent = todo.pop()
        for task in Path(f"/proc/{parent}/task").glob("*/children"):
            try:
                todo += [int(c) for c in task.read_text().split()]
            except OSError:
                continue
        try:  # utime, stime, cutime, cstime: fields 14-17, after the command in parentheses
            fields = Path(f"/proc/{parent}/stat").read_text().rsplit(")", 1)[1].split()
            own, waited = int(fields[11]) + int(fields[12]), int(fields[13]) + int(fields[14])
        except (OSError, IndexError, ValueError):
            continue
        total += waited if parent == root else own + waited
    return total / TICKS


def setup_threads(cfg: RunConfig) -> ThreadGovernor:
    """Set a run's torch threads (:func:`resolve_threads`), log why, and return the
    governor its training loop checks once a round."""
    n, why = resolve_threads(cfg)
    torch.set_num_threads(n)
    governor = ThreadGovernor(n, fixed=cfg.train.threads is not None)
    log.info("threads: %s%s", why, "; fewer while other processes keep these CPUs busy"
             if governor.active else "")
    return governor
