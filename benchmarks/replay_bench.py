"""Replay cost per training step: one push of an env step's transitions plus one sample.

    python benchmarks/replay_bench.py                # paper sizes: 3 agents, batch 128
    python benchmarks/replay_bench.py --n-envs 4 --batch 256

Times, in turns in one process, the project's ``TransitionReplay`` (plain tensors in
env-step slots, uniform per-agent sampling) and TorchRL's
``TensorDictReplayBuffer(LazyTensorStorage)`` holding the same per-agent transitions,
each doing what a training step does once per env step: push ``n_envs`` env steps of
M agents, then sample a batch. Prints µs per push + sample and the ratio.
"""

from __future__ import annotations

import argparse
import time

import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from uabs_rl.algorithms.replay import TransitionReplay


def step_transitions(n: int, m: int, obs_dim: int) -> dict[str, torch.Tensor]:
    return {"obs": torch.randn(n, m, obs_dim), "action": torch.randint(0, 4, (n, m)),
            "mask": torch.ones(n, m, 4, dtype=torch.bool), "reward": torch.randn(n, m),
            "next_obs": torch.randn(n, m, obs_dim),
            "next_mask": torch.ones(n, m, 4, dtype=torch.bool),
            "terminated": torch.zeros(n, m, dtype=torch.bool)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--agents", type=int, default=3)
    ap.add_argument("--obs-dim", type=int, default=18)
    ap.add_argument("--n-envs", type=int, default=1)
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--capacity", type=int, default=100_000)
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--turns", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(1)
    m, n = args.agents, args.n_envs
    data = step_transitions(n, m, args.obs_dim)
    mine = TransitionReplay(args.capacity, args.obs_dim, 4, m, [0], args.batch)
    flat = TensorDict({k: v.reshape(n * m, *v.shape[2:]) for k, v in data.items()},
                      batch_size=[n * m])
    theirs = TensorDictReplayBuffer(storage=LazyTensorStorage(args.capacity),
                                    batch_size=args.batch)

    def ours() -> None:
        mine.extend(TensorDict(data, batch_size=[n, m]))
        mine.sample()

    def torchrl() -> None:
        theirs.extend(flat)
        theirs.sample()

    for f in (ours, torchrl):  # fill past the batch size, warm up
        for _ in range(args.batch):
            f()
    best = {"TransitionReplay": float("inf"), "TorchRL": float("inf")}
    for _ in range(args.turns):
        for name, f in (("TransitionReplay", ours), ("TorchRL", torchrl)):
            t0 = time.perf_counter()
            for _ in range(args.steps):
                f()
            best[name] = min(best[name], (time.perf_counter() - t0) / args.steps * 1e6)
    print(f"push {n} env step(s) of {m} agents + sample {args.batch}, best of "
          f"{args.turns} turns of {args.steps}:")
    for name, us in best.items():
        print(f"  {name:>16}: {us:7.1f} µs")
    print(f"  TorchRL / TransitionReplay: {best['TorchRL'] / best['TransitionReplay']:.1f}x")


if __name__ == "__main__":
    main()
