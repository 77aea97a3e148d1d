"""How much the fleet's footprints overlap under each policy: the share of the covered
vehicles that lie under the footprints of two UABS or more, on every test window.

    python benchmarks/overlap.py outputs/runs/lookahead_motion5

A fleet that splits the traffic covers each vehicle once; two UABS over the same
vehicles serve no more of them than one (a vehicle is served by one link). The
coordinated planners (the mpc, the clairvoyant planner) search each UABS's path given
the others' plans, so their overlap shows what coordination buys; the same mpc with
each UABS planning alone (``PlannerScore(coordinated=False)``) and the learned policies
are measured beside it. At every step of every window, after the fleet has moved: the
present vehicles under at least one UABS's footprints and under two or more, summed
over steps and windows; the share is their ratio. Learned: each member of the
population's ``best.pt`` (mean and Student-t 95 % CI over the members); greedy, the
oracle and the mpc are deterministic on these windows and flown once. One process,
one torch thread.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from uabs_rl.cli import one_line_errors
from uabs_rl.env.service import vehicles_at
from uabs_rl.evaluation.baselines import MPC, baseline_policy, policy_label
from uabs_rl.evaluation.load import load_evaluation
from uabs_rl.evaluation.planner import footprint
from uabs_rl.evaluation.predict import ConstantVelocity
from uabs_rl.evaluation.stats import t_interval
from uabs_rl.runs.layout import RunFolder
from uabs_rl.safety.make import make_selector


def flown(ev, policy) -> tuple[float, float]:
    """(served fraction, overlap share) of ``policy`` on ``ev``'s windows."""
    base = ev.evaluator.env.base_env
    p = base.params
    counts = torch.zeros(2, dtype=torch.float64)

    def count() -> None:
        st = base.state
        veh, present = vehicles_at(st, base.veh_pos, base.veh_present)
        under = (footprint(st["pos"], veh, p.r_b, p.n_beams) & present[:, None, :]).sum(1)
        counts[0] += (under >= 1).sum()
        counts[1] += (under >= 2).sum()

    ev.evaluator.on_step = count
    try:
        rec, _ = ev.evaluator.evaluate(policy)
    finally:
        ev.evaluator.on_step = None
    return float(np.nanmean(rec["served_fractions"])), float(counts[1] / counts[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a population's folder (or one run folder)")
    ap.add_argument("--mpc-horizon", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    runs = RunFolder(args.run).members()
    rows = []
    first = load_evaluation(runs[0], "best", None, "test")
    env = first.evaluator.env
    for name, coordinated in (("greedy", True), ("oracle", True), (MPC, True), (MPC, False)):
        policy = baseline_policy(name, env, make_selector(env), 0, horizon=args.mpc_horizon,
                                 predictor=ConstantVelocity() if name == MPC else None,
                                 coordinated=coordinated)
        served, share = flown(first, policy)
        label = policy_label(name, args.mpc_horizon, "cv", coordinated=coordinated)
        rows.append((label, f"{100 * served:.2f}", f"{100 * share:.2f}"))
    learned = [flown(ev, ev.greedy) for ev in
               [first, *(load_evaluation(r, "best", None, "test") for r in runs[1:])]]
    served, share = (t_interval([100 * x[i] for x in learned]) for i in (0, 1))
    rows.append((f"learned ({len(runs)} member(s))",
                 f"{served[0]:.2f} [{served[1]:.2f}, {served[2]:.2f}]",
                 f"{share[0]:.2f} [{share[1]:.2f}, {share[2]:.2f}]"))
    cfg = first.cfg
    print(f"{args.run}: test split, every window; masking={cfg.masking.mode}, "
          f"M = {cfg.scenario.n_uabs}")
    print("| policy | served % | covered vehicles under 2+ UABS, % |")
    print("|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    print(f"{time.perf_counter() - t0:.0f} s (1 torch thread)")


if __name__ == "__main__":
    one_line_errors(main)
