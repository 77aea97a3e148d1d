"""The coverage at 95 % of every interval method the project reports
(``uabs_rl/evaluation/stats.py``), measured on simulated seeds of known mean: normal,
and log-normal with σ = 0.25 (skewness 0.78), 0.5 (1.75) and 1 (6.2), at 3, 5 and 10
seeds; Welch's with two groups of n seeds, standard deviations 1 and 3; the IQM's
stratified bootstrap over 9 tasks. Prints a markdown table (docs/evaluation.md).

    python benchmarks/coverage.py --trials 20000     # about 2 minutes on one core
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from uabs_rl.evaluation.stats import (
    coverage,
    iqm_runs,
    percentile_bootstrap,
    stratified_bootstrap,
    t_interval,
    welch_difference,
)

SIGMAS = (0.25, 0.5, 1.0)
TASKS = np.linspace(-1.0, 1.0, 9)


def draw(dist: float | None, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """Normal (``dist`` None) or log-normal of σ = ``dist`` values."""
    return rng.normal(0.0, 1.0, shape) if dist is None else rng.lognormal(0.0, dist, shape)


def mean_of(dist: float | None) -> float:
    return 0.0 if dist is None else math.exp(dist ** 2 / 2)


def row(name: str, dist: float | None, trials: int) -> list[float]:
    """Coverage of method ``name`` at 3, 5 and 10 seeds."""
    def welch(x):
        d = welch_difference(x[0], x[1])
        return d["ci_low"], d["ci_high"]

    intervals = {"Student-t": lambda x: t_interval(x)[1:],
                 "percentile bootstrap (before)": lambda x: percentile_bootstrap(
                     x, n_boot=1000)[1:]}
    out = []
    for n in (3, 5, 10):
        if name in intervals:
            cov = coverage(intervals[name], lambda rng, t, n=n: draw(dist, (t, n), rng),
                           mean_of(dist), trials, n)
        else:  # Welch, sd 1 against 3
            cov = coverage(welch, lambda rng, t, n=n: np.stack(
                [draw(dist, (t, n), rng), 3.0 * draw(dist, (t, n), rng)], 1),
                -2.0 * mean_of(dist), trials, n)
        out.append(cov)
    return out


def iqm_row(trials: int) -> list[float]:
    big = np.random.default_rng(99).normal(0.0, 1.0, size=(200_000, TASKS.size)) + TASKS
    truth = float(iqm_runs(big))
    return [coverage(lambda s: stratified_bootstrap([s], iqm_runs, n_boot=1000)[1:],
                     lambda rng, t, n=n: rng.normal(0.0, 1.0, (t, n, TASKS.size)) + TASKS,
                     truth, trials, n) for n in (3, 5, 10)]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=2000)
    args = ap.parse_args(argv)
    print(f"Coverage of the 95 % intervals, {args.trials} simulated experiments each "
          f"(binomial s.e. {100 * math.sqrt(0.95 * 0.05 / args.trials):.1f} points).\n")
    print("| method | seeds' distribution | 3 seeds | 5 seeds | 10 seeds |")
    print("|---|---|---|---|---|")
    for name in ("Student-t", "Welch (sd 1 and 3, n per group)",
                 "percentile bootstrap (before)"):
        for dist in (None, *SIGMAS):
            cells = " | ".join(f"{100 * c:.1f} %" for c in row(name, dist, args.trials))
            what = "normal" if dist is None else f"log-normal σ = {dist}"
            print(f"| {name} | {what} | {cells} |", flush=True)
    cells = " | ".join(f"{100 * c:.1f} %" for c in iqm_row(args.trials))
    print(f"| IQM, stratified bootstrap (9 tasks) | normal | {cells} |")


if __name__ == "__main__":
    main()
