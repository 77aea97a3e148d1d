"""Safety of the masks under a uniformly random legal policy (the hardest case for a
mask): per fleet size and masking mode, agent-steps, steps with a pair closer than d_th
(at the end of a step or on the straight paths between steps), collisions and mask
fallbacks, on the default area.

    python benchmarks/safety_table.py                       # M = 3, 6, 8; recoverable
    python benchmarks/safety_table.py --literal             # the paper's literal rules
    python benchmarks/safety_table.py --envs 128 --steps 80 --fleets 3 6 8 10
"""

from __future__ import annotations

import argparse

import torch

from uabs_rl.cli import one_line_errors
from uabs_rl.config import ConfigError, compose
from uabs_rl.safety.make import make_env, make_selector
from uabs_rl.traces.build import get_traces


def run(m: int, mode: str, recoverable: bool, envs: int, steps: int,
        seed: int = 0) -> dict[str, float] | str:
    cfg = compose("config", [f"masking={mode}", f"scenario.n_uabs={m}",
                             f"masking.recoverable={str(recoverable).lower()}"])
    traces = get_traces(cfg.scenario, cfg.traces, "train", verbose=False)
    try:
        env = make_env(cfg.scenario, cfg.channel, cfg.masking, traces, "train",
                       n_envs=envs, seed=seed)
    except ConfigError as e:
        return f"refused: {e}"
    policy = make_selector(env, eps=1.0,
                           generator=torch.Generator().manual_seed(seed))
    td = env.rollout(steps, policy, break_when_any_done=False)
    d = td["next", "diagnostics"]
    d_th = env.base_env.params.d_th
    close = (d["min_pair_distance"] < d_th) | (d["closest_approach"] < d_th)
    return {"agent_steps": envs * steps * m, "steps_below_d_th": int(close.sum()),
            "collisions": int(d["collisions"].sum()), "fallbacks": int(d["fallbacks"].sum()),
            "min_distance": float(torch.minimum(d["min_pair_distance"],
                                                d["closest_approach"]).min())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fleets", type=int, nargs="+", default=[3, 6, 8])
    ap.add_argument("--modes", nargs="+", default=["flat", "rank"])
    ap.add_argument("--envs", type=int, default=128)
    ap.add_argument("--steps", type=int, default=80)
    ap.add_argument("--literal", action="store_true", help="masking.recoverable=false")
    args = ap.parse_args()
    print(f"recoverable={not args.literal}, {args.envs} episodes x {args.steps} steps, "
          f"uniformly random legal policy, default area")
    print("| M | mode | agent-steps | steps with a pair < d_th | collisions | mask fallbacks "
          "| closest (m) |")
    print("|---|---|---|---|---|---|---|")
    for m in args.fleets:
        for mode in args.modes:
            r = run(m, mode, not args.literal, args.envs, args.steps)
            if isinstance(r, str):
                print(f"| {m} | {mode} | {r} |")
                continue
            print(f"| {m} | {mode} | {r['agent_steps']} | {r['steps_below_d_th']} | "
                  f"{r['collisions']} | {r['fallbacks']} | {r['min_distance']:.1f} |")


if __name__ == "__main__":
    one_line_errors(main)
