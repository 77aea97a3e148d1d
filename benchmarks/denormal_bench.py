"""Adam's step with denormal moments, flushed and not, side by side.

    python benchmarks/denormal_bench.py                      # paper net, a quarter dead
    python benchmarks/denormal_bench.py --members 3 --share 0.1
    python benchmarks/denormal_bench.py --checkpoint outputs/<run>/checkpoints/last.pt

A ReLU unit that never fires gets exactly zero gradients, so its Adam moments decay
geometrically (x 0.9 and x 0.999 per update) into the denormal range, where the CPU
computes up to a hundred times slower. ``DQN3.update`` flushes denormals to zero
around Adam's step (``uabs_rl.algorithms.base.flush_denormals``; ``tests/test_algorithms.py`` shows
the parameters stay bit for bit the same). This prints, for Adam over the paper's
network (``--members`` stacked copies, as a population holds them) with ``--share`` of
its moments denormal, the time of one step unflushed and flushed, measured in turns in
one process, and their ratio. ``--checkpoint`` prints the denormal share of a run's
saved moments instead (what a trained network really holds).
"""

from __future__ import annotations

import argparse
import time

import torch

from uabs_rl.algorithms.base import flush_denormals
from uabs_rl.algorithms.model import DuelingQNet


def denormal_share(checkpoint: str) -> None:
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)
    tiny = torch.finfo(torch.float32).tiny
    n = dn = 0
    for s in state["learner"]["optim"]["state"].values():
        for k in ("exp_avg", "exp_avg_sq"):
            t = s[k]
            n += t.numel()
            dn += int(((t != 0) & (t.abs() < tiny)).sum())
    print(f"{checkpoint}: {dn} of {n} Adam moments denormal ({100 * dn / n:.1f} %), "
          f"after {state['learner']['updates']} updates")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--members", type=int, default=1, help="stacked networks (population)")
    ap.add_argument("--share", type=float, default=0.25, help="share of denormal moments")
    ap.add_argument("--obs-dim", type=int, default=18)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--checkpoint", help="print the denormal share of this checkpoint")
    args = ap.parse_args()
    if args.checkpoint:
        denormal_share(args.checkpoint)
        return
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    params = [torch.nn.Parameter(torch.stack([p.detach() for _ in range(args.members)]))
              for p in DuelingQNet(args.obs_dim, 4, [256, 256]).parameters()]
    optim = torch.optim.Adam(params, lr=1e-4, fused=True)
    dead = []
    for p in params:
        p.grad = torch.randn_like(p) * 1e-3
        d = torch.rand(p.shape) < args.share
        p.grad[d] = 0.0  # dead units: zero gradients
        dead.append(d)
    optim.step()

    def make_denormal() -> None:
        for p, d in zip(params, dead, strict=True):
            optim.state[p]["exp_avg"][d] = 1e-39
            optim.state[p]["exp_avg_sq"][d] = 1e-41

    def timed(flush: bool) -> float:
        make_denormal()  # the flushed step zeroes them: set them again each turn
        t0 = time.perf_counter()
        for _ in range(args.steps):
            if flush:
                with flush_denormals():
                    optim.step()
            else:
                optim.step()
        return (time.perf_counter() - t0) / args.steps * 1e3

    runs: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(5):  # in turns
        for flush in (False, True):
            runs[flush].append(timed(flush))
    n = sum(p.numel() for p in params)
    plain, flushed = min(runs[False]), min(runs[True])
    print(f"Adam over {args.members} x the paper's network ({n} parameters), "
          f"{100 * args.share:.0f} % of moments denormal, threads={args.threads}")
    print(f"  unflushed: {plain:.3f} ms per step (best of 5 x {args.steps})")
    print(f"  flushed:   {flushed:.3f} ms per step")
    print(f"  ratio:     {plain / flushed:.1f}x")


if __name__ == "__main__":
    main()
