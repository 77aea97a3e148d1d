"""Learner against learner under each mask: each run's best.pt on the test traces, the
difference of the group means (QMIX or VDN minus the 3DQN) of the served fraction and
P_g(N̂_s), with Welch's 95 % CI (two independent groups of seeds), and rliable's
probability of improvement over the two masks (the tasks) with its stratified bootstrap
interval.

    python benchmarks/learners.py outputs/multirun/algorithms \
        > docs/results/algorithms/learners.md
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from uabs_rl.evaluation.load import evaluate_policies, load_evaluation
from uabs_rl.evaluation.stats import (
    AGGREGATE_METHOD,
    probability_of_improvement,
    stratified_bootstrap,
    welch_difference,
)


def test_means(run: Path) -> dict[str, float]:
    rec = evaluate_policies(load_evaluation(run, "best", split="test"), ("learned",))
    rec = rec["learned"][0]
    return {"served": float(np.mean(rec["served_fractions"])), "pg": float(np.mean(rec["pgs"]))}


def difference(a: list[float], b: list[float]) -> tuple[float, float, float]:
    """mean(a) − mean(b) and Welch's 95 % interval (two independent groups of seeds)."""
    d = welch_difference(a, b)
    return d["diff"], d["ci_low"], d["ci_high"]


def main(root: Path) -> None:
    values: dict[tuple[str, str], list[dict[str, float]]] = {}
    for group in sorted(root.glob("algo=*")):
        keys = dict(kv.split("=", 1) for kv in group.name.split(","))
        algo, mode = keys["algo"], keys["masking"]
        values[algo, mode] = [test_means(run) for run in sorted(group.glob("seed=*"))]
    print("| mask | learner | seeds | served fraction | − 3DQN [95 % CI] | P_g(N̂_s=5) "
          "| − 3DQN [95 % CI] |")
    print("|---|---|---|---|---|---|---|")
    for mode in ("flat", "rank"):
        for algo in ("dqn3", "vdn", "qmix"):
            runs = values.get((algo, mode))
            if not runs:
                continue
            cells = [mode, algo, str(len(runs))]
            for k in ("served", "pg"):
                x = [r[k] for r in runs]
                cells.append(f"{100 * np.mean(x):.2f} %")
                if algo == "dqn3":
                    cells.append("")
                else:
                    d, lo, hi = difference(x, [r[k] for r in values["dqn3", mode]])
                    cells.append(f"{100 * d:+.2f} pt [{100 * lo:+.2f}, {100 * hi:+.2f}]")
            print("| " + " | ".join(cells) + " |")
    print("\nDifferences: 95 % CI, Welch over the two groups' seeds.")
    print_improvement(values)


def print_improvement(values: dict[tuple[str, str], list[dict[str, float]]]) -> None:
    """P(learner > 3DQN) over the masks run by both (runs [seeds, masks]), served fraction."""
    for algo in ("vdn", "qmix"):
        modes = [m for m in ("flat", "rank") if (algo, m) in values and ("dqn3", m) in values]
        if not modes:
            continue
        x, y = (np.array([[r["served"] for r in values[a, m]] for m in modes]).T
                for a in (algo, "dqn3"))
        p, lo, hi = stratified_bootstrap([x, y], probability_of_improvement)
        print(f"P({algo} > dqn3), served fraction over {', '.join(modes)} masks: {p:.2f} "
              f"[{lo:.2f}, {hi:.2f}] ({AGGREGATE_METHOD})")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
