"""Learner against learner under each mask: each run's best.pt on the test traces, the
difference of the group means (QMIX or VDN minus the 3DQN) of the served fraction and
P_g(N̂_s), with a 95 % bootstrap CI resampling each group's seeds independently.

    python benchmarks/learners.py outputs/multirun/algorithms \
        > docs/results/algorithms/learners.md
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from uabs_rl.cli.evaluate import evaluate_policies, load_evaluation


def test_means(run: Path) -> dict[str, float]:
    rec = evaluate_policies(load_evaluation(run, "best", split="test"), ("learned",))
    rec = rec["learned"][0]
    return {"served": float(np.mean(rec["served_fractions"])), "pg": float(np.mean(rec["pgs"]))}


def difference(a: list[float], b: list[float], n_boot: int = 10_000) -> tuple[float, ...]:
    """mean(a) − mean(b) and its percentile bootstrap interval (seeds resampled per group)."""
    a, b = np.asarray(a), np.asarray(b)
    rng = np.random.default_rng(0)
    boot = (a[rng.integers(0, a.size, (n_boot, a.size))].mean(1)
            - b[rng.integers(0, b.size, (n_boot, b.size))].mean(1))
    return a.mean() - b.mean(), *np.quantile(boot, [0.025, 0.975])


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


if __name__ == "__main__":
    main(Path(sys.argv[1]))
