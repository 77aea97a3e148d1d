"""Environment throughput: ``UABSEnv.step`` against the same step math as raw tensors,
and the cost of each anti-collision mode.

    python benchmarks/env_bench.py                 # n_envs 1, 64, 1024 on CPU
    python benchmarks/env_bench.py --n-envs 64 --device cuda

Table 1: env steps/s and agent-steps/s for each n_envs, for the raw step math
(``StepMath.step`` on plain tensors, no TensorDict) and for ``env.step`` (TensorDict,
TorchRL's checks), and the ratio of their costs.
Table 2: per masking mode, one decision + step of the masked env (transform, masked
ε-greedy selector over random Q-values, env.step) at n_envs 64 and 1024.
Default scenario, traces and channel. Each figure is the fastest of a few episodes.
"""

from __future__ import annotations

import argparse
import time

import torch

from uabs_rl.config import ChannelConfig, MaskingConfig, ScenarioConfig, TracesConfig
from uabs_rl.env.uabs_env import ACTION, UABSEnv
from uabs_rl.safety.make import make_env, make_selector
from uabs_rl.safety.rules import ACTION_VALUE
from uabs_rl.traces.build import get_traces


def _time(fn, steps: int, episodes: int) -> float:
    """Seconds per step: the fastest of ``episodes`` episodes of ``steps`` steps (resets
    excluded; the minimum is the figure least disturbed by other load on the machine)."""
    best = float("inf")
    for _ in range(episodes):
        run = fn()
        t0 = time.perf_counter()
        for _ in range(steps):
            run()
        best = min(best, time.perf_counter() - t0)
    return best / steps


def bench(n_envs: int, device: str, episodes: int, scenario, channel, traces) -> dict:
    env = UABSEnv(scenario, channel, traces, n_envs=n_envs, device=device, seed=0)
    m, steps = scenario.n_uabs, scenario.episode_steps
    actions = torch.randint(0, 4, (steps, n_envs, m), device=device)

    def raw():
        env.reset()
        st, i = env.state, iter(range(steps))
        return lambda: env.math.step(st, actions[next(i)], env.veh_pos, env.veh_present,
                                     env.rng)

    def wrapped():
        td = env.reset()
        i = iter(range(steps))

        def one():
            nonlocal td
            td = env.step(td.set(ACTION, actions[next(i)]))["next"]
        return one

    for fn in (raw, wrapped):  # warm-up
        _time(fn, steps, 1)
    t_raw = _time(raw, steps, episodes)
    t_env = _time(wrapped, steps, episodes)
    return {"n_envs": n_envs, "raw_sps": 1 / t_raw, "env_sps": 1 / t_env,
            "raw_asps": n_envs * m / t_raw, "env_asps": n_envs * m / t_env,
            "ratio": t_env / t_raw}


def bench_mode(mode: str, n_envs: int, episodes: int, scenario, channel, traces,
               recoverable: bool = True) -> float:
    """Agent-steps/s of decide (masked selector) + step for one masking mode."""
    mk = MaskingConfig(mode=mode, recoverable=recoverable)
    env = make_env(scenario, channel, mk, traces, n_envs=n_envs, seed=0)
    sel = make_selector(env, eps=0.1, generator=torch.Generator().manual_seed(0))
    steps, m = scenario.episode_steps, scenario.n_uabs
    q = torch.randn(steps, n_envs, m, 4)

    def episode():
        td = env.reset()
        i = iter(range(steps))

        def one():
            nonlocal td
            td = env.step(sel(td.set(ACTION_VALUE, q[next(i)])))["next"]
        return one

    _time(episode, steps, 1)
    return n_envs * m / _time(episode, steps, episodes)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n-envs", type=int, nargs="+", default=[1, 64, 1024])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--episodes", type=int, default=5)
    ap.add_argument("--no-modes", dest="modes", action="store_false",
                    help="skip the per-masking-mode tables")
    ap.add_argument("--fleets", type=int, nargs="+", default=[3, 6, 8],
                    help="fleet sizes of the recoverable-vs-literal table")
    args = ap.parse_args()
    scenario, channel, traces_cfg = ScenarioConfig(), ChannelConfig(), TracesConfig()
    traces = get_traces(scenario, traces_cfg, "train")
    print(f"device={args.device} threads={torch.get_num_threads()} M={scenario.n_uabs} "
          f"vehicles={traces.max_vehicles} T={scenario.episode_steps}")
    print(f"{'n_envs':>7} {'raw steps/s':>12} {'env steps/s':>12} {'raw agent-steps/s':>18} "
          f"{'env agent-steps/s':>18} {'env/raw cost':>13}")
    for n in args.n_envs:
        r = bench(n, args.device, args.episodes, scenario, channel, traces)
        print(f"{r['n_envs']:>7} {r['raw_sps']:>12.0f} {r['env_sps']:>12.0f} "
              f"{r['raw_asps']:>18,.0f} {r['env_asps']:>18,.0f} {r['ratio']:>13.2f}")
    if args.modes:
        print("\nmasking modes: agent-steps/s of select (masked ε-greedy) + env.step")
        sizes = [n for n in args.n_envs if n > 1] or args.n_envs
        print(f"{'mode':>8} " + " ".join(f"{f'n_envs={n}':>14}" for n in sizes))
        for mode in ("penalty", "flat", "rank"):
            figs = [bench_mode(mode, n, args.episodes, scenario, channel, traces) for n in sizes]
            print(f"{mode:>8} " + " ".join(f"{f:>14,.0f}" for f in figs))
        recoverable_table(args, sizes, channel, traces)


def recoverable_table(args, sizes: list[int], channel, traces) -> None:
    """Cost of the recoverable masks against the paper's literal rules, measured side by
    side (alternating, best of two each), per fleet size."""
    print("\nrecoverable vs literal masks: agent-steps/s of select + env.step, and the cost "
          "ratio (time per step, recoverable / literal)")
    print(f"{'M':>3} {'mode':>6} {'n_envs':>7} {'literal':>12} {'recoverable':>12} {'cost':>6}")
    for m in args.fleets:
        sc = ScenarioConfig(n_uabs=m)
        for mode in ("flat", "rank"):
            for n in sizes:
                lit, rec = 0.0, 0.0
                for _ in range(2):
                    lit = max(lit, bench_mode(mode, n, args.episodes, sc, channel, traces, False))
                    rec = max(rec, bench_mode(mode, n, args.episodes, sc, channel, traces, True))
                print(f"{m:>3} {mode:>6} {n:>7} {lit:>12,.0f} {rec:>12,.0f} {lit / rec:>6.2f}")


if __name__ == "__main__":
    main()
