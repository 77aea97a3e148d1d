"""Compute per fleet decision of several policies, timed in turns in one process.

    python benchmarks/decision_cost.py outputs/runs/generalist_rank5/seed=0 \
        --policies mpc leaf learned --weight 0.5 --turns 3

Loads the run's ``best.pt`` and its test windows (every one; extra ``key=value``
overrides as ``uabs-eval`` takes them), then flies each policy over all the windows side
by side, ``--turns`` times, the order reversed every other turn so that neither policy
always runs first, at one torch thread (``--threads``). Prints each turn's ms per
decision (the rollout's wall time per step of one window: the whole fleet's move,
amortised over the windows) and served fraction, then the median per policy and each
policy's ratio to the first. ``--weight`` is λ of ``hybrid`` and ``leaf``;
``--mpc-horizon`` the mpc's and theirs; a policy written ``name:H`` (``leaf:3``) searches
H steps instead, so a shorter search with values can be set beside a longer one without;
``name:H:all`` searches over every vehicle instead of those each UABS can reach (the
same moves at the cost of the search before that cut, ``PlannerScore.cut``);
``name:H:bB`` keeps B paths per first move in its beam search (``mpc:5:b4``; default
16, ``uabs-eval --mpc-beam``) and ``name:H:rR`` makes R passes over the fleet
(``mpc:5:b4:r1``; default 2, ``uabs-eval --mpc-rounds``); ``name:H:learned`` (or ``:road``,
``:true``) plans over that predictor's positions (``uabs-eval --predictor``; default cv).

    python benchmarks/decision_cost.py RUN scenario=city scenario.n_uabs=25 \
        --policies mpc:5:all mpc:5 leaf:3:all leaf:3 leaf:2 --turns 2
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import torch

from uabs_rl.cli import one_line_errors
from uabs_rl.cli.evaluate import CHOICES
from uabs_rl.evaluation.baselines import MPC, PLANNER
from uabs_rl.evaluation.hybrid import HYBRID
from uabs_rl.evaluation.leaf import LEAF
from uabs_rl.evaluation.load import evaluate_policies, load_evaluation
from uabs_rl.evaluation.predict import PREDICTORS

SEARCHES = (MPC, PLANNER, HYBRID, LEAF)  # the policies that search: a horizon, beam, rounds


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a run folder (one member)")
    ap.add_argument("overrides", nargs="*", help="world overrides, as uabs-eval takes them")
    ap.add_argument("--policies", nargs="+", default=["mpc", "leaf", "learned"])
    ap.add_argument("--weight", type=float, default=1.0, help="λ of hybrid and leaf")
    ap.add_argument("--mpc-horizon", type=int, default=5)
    ap.add_argument("--turns", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    specs = {}  # name:H[:all][:bB][:rR][:predictor] -> (name, H, cut, beam, rounds, predictor)
    for spec in args.policies:
        name, *rest = spec.split(":")
        if name not in CHOICES:
            ap.error(f"{spec}: {name!r} is not a policy: one of {', '.join(CHOICES)}")
        if rest and name not in SEARCHES:
            ap.error(f"{spec}: {name} searches nothing, so takes no horizon, beam or rounds "
                     f"(those of {', '.join(SEARCHES)})")
        h = rest.pop(0) if rest else ""
        named = [x for x in rest if x in PREDICTORS]
        rest = [x for x in rest if x not in PREDICTORS]
        if named and name == PLANNER:
            ap.error(f"{spec}: the planner plans over the true future; a predictor is the "
                     f"mpc's, the hybrid's or the leaf's")
        if h and not (h.isdigit() and int(h) >= 1):
            ap.error(f"{spec}: the horizon after ':' must be an integer >= 1")
        given = {k: [x[1:] for x in rest if x.startswith(k)] for k in "br"}
        if (any(x != "all" and x[:1] not in given for x in rest)
                or any(len(v) > 1 for v in given.values()) or rest.count("all") > 1
                or len(named) > 1
                or any(not (x.isdigit() and int(x) >= 1) for v in given.values() for x in v)):
            ap.error(f"{spec}: after the horizon only ':all' (every vehicle), ':bB' (a beam "
                     f"of B >= 1 paths), ':rR' (R >= 1 passes over the fleet) and one "
                     f"predictor ({', '.join(PREDICTORS)}) are known")
        beam, rounds = (int(given[k][0]) if given[k] else None for k in "br")
        specs[spec] = (name, int(h) if h else args.mpc_horizon, "all" not in rest, beam,
                       rounds, named[0] if named else "cv")
    ev = load_evaluation(args.run, "best", None, "test", args.overrides)
    ms: dict[str, list[float]] = {p: [] for p in args.policies}
    for turn in range(args.turns):
        order = args.policies if turn % 2 == 0 else args.policies[::-1]
        for spec in order:
            name, h, cut, beam, rounds, predictor = specs[spec]
            rec = evaluate_policies(ev, (name,), mpc_horizon=h, hybrid_weight=args.weight,
                                    cut=cut, beam=beam, rounds=rounds,
                                    predictor=predictor)[name][0]
            ms[spec].append(rec["ms_per_decision"])
            print(f"turn {turn + 1} {spec}: {rec['ms_per_decision']:.2f} ms per decision, "
                  f"served {100 * rec['served_fraction']:.2f} %", flush=True)
    first = statistics.median(ms[args.policies[0]])
    print(f"\nmedians over {args.turns} turns, {rec['windows']} windows side by side, "
          f"{args.threads} torch thread(s):")
    for name, values in ms.items():
        med = statistics.median(values)
        print(f"  {name}: {med:.2f} ms per decision ({med / first:.2f}x {args.policies[0]})")


if __name__ == "__main__":
    one_line_errors(main)
