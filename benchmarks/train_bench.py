"""Training-loop throughput of the paper protocol on this machine.

    python benchmarks/train_bench.py                 # 30 episodes, paper defaults, rank
    python benchmarks/train_bench.py --episodes 50 masking=flat algo.loss=torchrl
    python benchmarks/train_bench.py train.population=3   # 3 seeds in one process

Trains ``--episodes`` episodes with the paper's defaults (overrides as for uabs-train),
after filling the replay to ``algo.learning_starts`` and two warm-up rounds (the first
updates compile the update program, seconds once a run: the figures exclude it, the
whole-run figures of docs/performance.md include it), then prints episodes per minute,
the projected time of the full protocol (1000 episodes of 80 steps, one update per
step) and the share of the time spent in the decision and env step (the Q forward, the
target mask where the rule needs the Q-values, the masked choice, the direct step and the
masking rule's write: ``DirectEnv.act_and_step``, one compiled program with
``train.compile``), replay (push + sample) and the update (loss, backward, Adam).
Evaluation is excluded.
With ``train.population=P`` the figures are per member: a member's episodes per minute
and ms per member env step, so they compare with a solo run's directly.

The update's line gives its µs per update and its achieved GFLOP/s (the loss's forward
and backward, counted by torch's FLOP formulas for the products, Adam not counted)
beside a measured matrix-product peak of this machine: one plain ``torch.mm`` of about
the same FLOPs (square, n = (FLOPs / 2)^(1/3)), at the same threads.

    python benchmarks/train_bench.py --update --turns 15   # the update alone: eager vs compiled

``--update`` times the update alone, eager and compiled (``train.compile_update``,
:mod:`uabs_rl.algorithms.compiled_update`), on the same sampled batches of a filled
replay, in turns, and prints the median µs per update of each, their ratio and the
compile's one-off seconds.

    python benchmarks/train_bench.py --update --profile train.population=3

``--profile`` adds where the compiled update's time goes: its program compiled once more
with Inductor's kernel profiling, one turn under ``torch.profiler``, and the share of the
matrix products (the library calls ``mm``, ``addmm``, ``bmm``, ``baddbmm``) with their
GFLOP/s beside the ``torch.mm`` rate; the rest is the fused loops between them (Adam,
the loss's elementwise work) and the program's call. The profiler's own cost makes
this turn a little slower than the timed ones.

    python benchmarks/train_bench.py --threads        # default vs train.threads=1, 2
    python benchmarks/train_bench.py --busy --turns 2 # the same beside a busy core

``--threads`` measures the default thread count (``uabs_rl.training.threads``: resolve_threads and
the ThreadGovernor that takes it down beside busy CPUs) and
``train.threads=1``, ``2`` (and all CPUs, if more), each in its own process, in turn,
and prints ms per env step with the ratio to the best; ``--busy`` does it beside one
other process keeping a core busy (a Python busy loop), as on a shared machine.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from contextlib import contextmanager

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils.flop_counter import flop_registry

from uabs_rl.algorithms import Dims, make_algorithm
from uabs_rl.config import compose
from uabs_rl.env.params import EnvParams
from uabs_rl.env.uabs_env import N_ACTIONS
from uabs_rl.training.experiment import Experiment
from uabs_rl.training.threads import resolve_threads, usable_cpus

SPENT: dict[str, float] = defaultdict(float)


@contextmanager
def timed(name: str):
    t0 = time.perf_counter()
    yield
    SPENT[name] += time.perf_counter() - t0


def wrap(obj, attr: str, name: str) -> None:
    fn = getattr(obj, attr)

    def inner(*a, **k):
        with timed(name):
            return fn(*a, **k)
    setattr(obj, attr, inner)


def measure(overrides: list[str], n_episodes: int) -> None:
    """Train ``n_episodes`` after filling the buffer; print the figures."""
    cfg = compose("config", ["train.progress=false", "train.logger=none", *overrides])
    _, why = resolve_threads(cfg)  # the run sets its threads (and governor) as uabs-train
    tr = Experiment(cfg, tempfile.mkdtemp(prefix="uabs_bench_"))
    # the decision (Q-values, target mask, choice) and the env step: one compiled program
    wrap(tr.collector.direct, "act_and_step", "decision + env step")
    wrap(tr.collector.direct, "reset", "decision + env step")
    wrap(tr.buffer, "extend", "replay")
    wrap(tr.buffer, "sample", "replay")
    wrap(tr.learner, "update", "update")
    # fill the buffer past learning_starts first, so every timed step updates
    while len(tr.buffer) < cfg.algo.learning_starts:
        tr.collect()
        tr.threads.check()
    # then warm up: the first updates compile the update program (seconds, once a run;
    # the whole-run figures of docs/performance.md include it, a step's shares must not)
    for _ in range(2):
        tr.collect()
        tr.threads.check()
    SPENT.clear()
    start_updates, t0 = tr.learner.updates, time.perf_counter()
    for _ in range(n_episodes // cfg.train.n_envs):
        tr.collect()
        tr.threads.check()  # once a round, as the training loop does
    wall = time.perf_counter() - t0
    updates = tr.learner.updates - start_updates
    episodes = n_episodes // cfg.train.n_envs * cfg.train.n_envs
    per_ep = wall / episodes
    full = cfg.train.episodes * per_ep
    print(f"scenario={cfg.scenario.name} M={cfg.scenario.n_uabs} "
          f"vehicles={tr.collector.env.base_env.veh_present.shape[-1]} "
          f"masking={cfg.masking.mode} loss={cfg.algo.loss} n_envs={cfg.train.n_envs} "
          f"threads={torch.get_num_threads()} hidden={list(cfg.algo.hidden)} "
          f"batch={cfg.algo.batch_size} population={cfg.train.population}")
    print(f"threads: {why}" + (f"; the governor ended at {tr.threads.n} after "
                               f"{tr.threads.changes} change(s)" if tr.threads.active else ""))
    each = " per member" if cfg.train.population > 1 else ""
    print(f"{episodes} episodes{each}, {updates} updates in {wall:.1f} s: "
          f"{60 / per_ep:.1f} episodes/min{each}, "
          f"{1000 * wall / (episodes * cfg.scenario.episode_steps):.2f} "
          f"ms per env step{each} (incl. its update); "
          f"{1000 * wall / (episodes * cfg.scenario.episode_steps * cfg.train.population):.2f}"
          f" ms per env step of one run")
    print(f"projected full protocol ({cfg.train.episodes} episodes x "
          f"{cfg.scenario.episode_steps} steps, {cfg.train.episodes * cfg.scenario.episode_steps} "
          f"updates): {full / 60:.1f} min (+ {cfg.train.episodes // cfg.train.eval_every} "
          f"evaluations and the compile)")
    other = wall - sum(SPENT.values())
    for name in ("decision + env step", "replay", "update"):
        print(f"  {name:>17}: {SPENT[name]:6.2f} s  {100 * SPENT[name] / wall:5.1f} %")
    print(f"  {'other (loop)':>17}: {other:6.2f} s  {100 * other / wall:5.1f} %")
    print(update_line(tr.learner, SPENT["update"], updates, wall))


class FlopCount(TorchDispatchMode):
    """FLOPs of the ops run inside (torch's own formulas: the products and
    convolutions; elementwise ops count none)."""

    def __init__(self):
        super().__init__()
        self.total = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        count = flop_registry.get(func._overloadpacket)
        if count is not None:
            self.total += count(*args, **kwargs, out_val=out)
        return out


def update_flops(learner) -> int:
    """FLOPs of one update's loss, forward and backward, on a sample of its replay
    (the gradients it leaves are cleared; no parameter moves)."""
    batch = learner.buffer.sample()
    with FlopCount() as count:
        learner.program(batch, learner.zero_grad)
    learner.zero_grad()
    return count.total


def matmul_peak(flops: int, repeats: int = 20) -> float:
    """GFLOP/s of one plain ``torch.mm`` of square float32 matrices with about ``flops``
    FLOPs (the best of ``repeats``), at the current thread count."""
    n = max(8, round((flops / 2) ** (1 / 3)))
    a, b = torch.randn(n, n), torch.randn(n, n)
    best = math.inf
    for _ in range(repeats + 3):
        t0 = time.perf_counter()
        torch.mm(a, b)
        best = min(best, time.perf_counter() - t0)
    return 2 * n ** 3 / best / 1e9


def update_line(learner, spent_s: float, updates: int, wall: float) -> str:
    """The update's µs per update and GFLOP/s, beside the machine's matrix-product peak."""
    if not updates:
        return "  no update in the timed episodes"
    flops = update_flops(learner)
    us = 1e6 * spent_s / updates
    return (f"  update: {100 * spent_s / wall:.1f} % of the step, {us:.0f} µs per update, "
            f"{flops / 1e6:.1f} MFLOP (loss forward + backward) at {flops / us / 1e3:.1f} "
            f"GFLOP/s; a torch.mm of the same FLOPs: {matmul_peak(flops):.1f} GFLOP/s "
            f"({torch.get_num_threads()} thread(s))")


def filled_learner(overrides: list[str]):
    """The run's learner (as uabs-train builds it, eager, at the run's threads) with a
    replay of random transitions, and its config."""
    cfg = compose("config", ["train.progress=false", "train.logger=none", *overrides])
    torch.set_num_threads(resolve_threads(cfg)[0])
    p = EnvParams.from_config(cfg.scenario, cfg.channel, cfg.obs)
    m, d = p.n_uabs, p.obs_dim
    seeds = [cfg.seed + i for i in range(cfg.train.population)]
    learner = make_algorithm(cfg.algo, Dims(d, N_ACTIONS, m), seeds, torch.device("cpu"))
    g = torch.Generator().manual_seed(0)
    n = len(seeds) * max(400, cfg.algo.batch_size)
    steps = {
        "obs": torch.randn(n, m, d, generator=g),
        "action": torch.randint(0, N_ACTIONS, (n, m), generator=g),
        "mask": torch.ones(n, m, N_ACTIONS, dtype=torch.bool),
        "reward": torch.randn(n, m, generator=g), "next_obs": torch.randn(n, m, d, generator=g),
        "next_mask": torch.rand(n, m, N_ACTIONS, generator=g) < 0.7,
        "terminated": torch.rand(n, m, generator=g) < 0.05}
    for k in learner.buffer.data.keys() - steps.keys():  # a learner's own (dqfd's labels)
        steps[k] = torch.randint(0, N_ACTIONS, (n, m), generator=g)
    learner.buffer.extend(steps)
    return learner, cfg


def compare_update(overrides: list[str], turns: int, per_turn: int = 50,
                   profile: bool = False) -> None:
    """The update alone, eager and compiled, on the same batches, in turns."""
    learners = {}
    for name, compiled in (("eager", False), ("compiled", True)):
        learner, cfg = filled_learner(overrides)
        learner.compile_update(compiled)
        t0 = time.perf_counter()
        learner.update(learner.buffer.sample())
        print(f"{name}: first update {time.perf_counter() - t0:.2f} s"
              + " (the compile included)" * compiled, flush=True)
        learners[name] = learner
    batches = [learners["eager"].buffer.sample() for _ in range(per_turn)]
    us: dict[str, list[float]] = {name: [] for name in learners}
    for _ in range(turns):
        for name, learner in learners.items():
            t0 = time.perf_counter()
            for b in batches:
                learner.update(b)
            us[name].append(1e6 * (time.perf_counter() - t0) / per_turn)
    flops = update_flops(learners["eager"])
    print(f"algo={cfg.algo.name} hidden={list(cfg.algo.hidden)} batch={cfg.algo.batch_size} "
          f"population={cfg.train.population} threads={torch.get_num_threads()}; "
          f"{turns} turns of {per_turn} updates; {flops / 1e6:.1f} MFLOP per update; "
          f"a torch.mm of the same FLOPs: {matmul_peak(flops):.1f} GFLOP/s")
    base = statistics.median(us["eager"])
    for name, times in us.items():
        med = statistics.median(times)
        print(f"  {name:>8}: {med:7.0f} µs per update (min {min(times):.0f}), "
              f"{flops / med / 1e3:6.1f} GFLOP/s, {med / base:.3f}x eager")
    print(json.dumps({"overrides": overrides, "us_per_update": {
        name: statistics.median(times) for name, times in us.items()}}))
    if profile:
        products_line(overrides, batches, flops)


PRODUCTS = ("mm_out", "addmm_out", "bmm_out", "baddbmm_out")  # the compiled program's calls


def products_line(overrides: list[str], batches: list, flops: int) -> None:
    """The compiled update's matrix products: their share of its time and their rate
    (``--profile``: a program compiled with Inductor's kernel profiling, so that its
    library calls show in ``torch.profiler``)."""
    import torch._inductor.config as inductor
    from torch.profiler import ProfilerActivity, profile

    with inductor.patch({"cpp.enable_kernel_profile": True}):
        learner, _ = filled_learner(overrides)
        learner.compile_update(True)
        learner.update(learner.buffer.sample())
        for b in batches:  # warm
            learner.update(b)
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for b in batches:
                learner.update(b)
    events = prof.key_averages()
    total = sum(e.self_cpu_time_total for e in events)
    mm = sum(e.self_cpu_time_total for e in events if e.key.endswith(PRODUCTS))
    if not mm:
        print("  --profile: no matrix product showed in the profile (another backend?)")
        return
    n = len(batches)
    peak = matmul_peak(flops)
    rate = flops / (mm / n) / 1e3
    print(f"  compiled, profiled: {total / n:.0f} µs per update, of which the matrix "
          f"products {mm / n:.0f} µs ({100 * mm / total:.0f} %) at {rate:.1f} GFLOP/s, "
          f"{100 * rate / peak:.0f} % of a torch.mm of the same FLOPs ({peak:.1f} GFLOP/s); "
          f"the rest {(total - mm) / n:.0f} µs")


BUSY_LOOP = "while True: pass"


def one_setting(threads: int | None, overrides: list[str], n_episodes: int,
                busy: bool) -> tuple[float, str]:
    """ms per env step of one run of this script in its own process at ``threads``
    (None: the default), beside a busy loop with ``busy``; and its thread line."""
    setting = [] if threads is None else [f"train.threads={threads}"]
    cmd = [sys.executable, __file__, "--episodes", str(n_episodes), *overrides, *setting]
    hog = subprocess.Popen([sys.executable, "-c", BUSY_LOOP]) if busy else None
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()
    ms = float(re.search(r"([\d.]+) ms per env step of one run", out).group(1))
    return ms, re.search(r"^threads: (.*)$", out, re.M).group(1)


def compare_threads(overrides: list[str], n_episodes: int, busy: bool, turns: int) -> None:
    """The default thread count against each fixed one, in turns; the best time of each
    and its ratio to the best setting's."""
    cpus, what = usable_cpus()
    settings: list[int | None] = [None, *sorted({1, 2, cpus})]
    label = {None: "default", **{n: f"threads={n}" for n in settings if n is not None}}
    print(f"{cpus} CPUs allowed by {what}; " + ("beside one busy process (a Python busy "
          "loop)" if busy else "no other load started") + f"; {turns} turn(s)")
    best: dict[int | None, float] = {}
    for turn in range(turns):
        for n in settings:
            ms, why = one_setting(n, overrides, n_episodes, busy)
            best[n] = min(ms, best.get(n, ms))
            print(f"  turn {turn + 1} {label[n]:>10}: {ms:7.2f} ms per env step  ({why})",
                  flush=True)
    top = min(best.values())
    print(json.dumps({"busy": busy, "overrides": overrides,
                      "ms_per_env_step": {label[n]: best[n] for n in settings}}))
    for n in settings:
        print(f"{label[n]:>10}: {best[n]:7.2f} ms per env step, {best[n] / top:5.2f}x the best")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=30)
    ap.add_argument("--threads", action="store_true",
                    help="compare the default thread count with train.threads=1, 2, ...")
    ap.add_argument("--busy", action="store_true",
                    help="--threads beside one other process keeping a core busy")
    ap.add_argument("--turns", type=int, default=1,
                    help="rounds of --threads / --busy / --update")
    ap.add_argument("--update", action="store_true",
                    help="time the update alone, eager against compiled, in turns")
    ap.add_argument("--profile", action="store_true",
                    help="with --update: the compiled update's matrix products' share and rate")
    ap.add_argument("overrides", nargs="*", help="uabs-train overrides")
    args = ap.parse_args()
    if args.profile and not args.update:
        ap.error("--profile goes with --update")
    if args.threads or args.busy:
        if any(o.startswith("train.threads=") for o in args.overrides):
            ap.error("--threads and --busy set train.threads themselves")
        compare_threads(args.overrides, args.episodes, args.busy, args.turns)
    elif args.update:
        compare_update(args.overrides, args.turns, profile=args.profile)
    else:
        measure(args.overrides, args.episodes)


if __name__ == "__main__":
    main()
