"""Statistics for reported figures: bootstrap confidence intervals of paired
differences (learned − baseline on the same windows) and across seeds, and the
interquartile mean (IQM) as rliable reports it."""

from __future__ import annotations

import numpy as np


def bootstrap_ci(x: np.ndarray | list[float], level: float = 0.95, n_boot: int = 10_000,
                 seed: int = 0) -> tuple[float, float, float]:
    """``(mean, low, high)``: the mean of ``x`` and its percentile bootstrap interval
    (resampling the entries of ``x`` with replacement, ``n_boot`` times, seeded)."""
    x = np.asarray(x, dtype=float)
    if x.size == 0:
        return float("nan"), float("nan"), float("nan")
    if x.size == 1:
        return float(x[0]), float(x[0]), float(x[0])
    rng = np.random.default_rng(seed)
    means = x[rng.integers(0, x.size, size=(n_boot, x.size))].mean(-1)
    a = (1.0 - level) / 2.0
    return float(x.mean()), float(np.quantile(means, a)), float(np.quantile(means, 1 - a))


def paired_difference(a: list[float], b: list[float], **kw) -> dict[str, float]:
    """Mean of ``a − b`` entry by entry (the same windows) with its bootstrap CI, over
    the pairs where both are defined (``n`` of them)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.shape != b.shape:
        raise ValueError(f"paired samples need equal shapes, got {a.shape} and {b.shape}")
    kept = ~(np.isnan(a) | np.isnan(b))  # a window without a vehicle: no served fraction
    a, b = a[kept], b[kept]
    mean, lo, hi = bootstrap_ci(a - b, **kw)
    return {"diff": mean, "ci_low": lo, "ci_high": hi, "n": int(a.size)}


def iqm(x: np.ndarray | list[float]) -> float:
    """Interquartile mean: the mean of the middle 50 % of the sorted values."""
    x = np.sort(np.asarray(x, dtype=float))
    n = x.size
    if n == 0:
        return float("nan")
    lo, hi = int(np.floor(0.25 * n)), int(np.ceil(0.75 * n))
    return float(x[lo:hi].mean()) if hi > lo else float(x.mean())


def spread_over_seeds(values: np.ndarray | list[list[float]], n_boot: int = 2000
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per column of ``values [seeds, columns]``: the mean over seeds and its spread, a
    95 % bootstrap CI with 3 seeds or more, the min-max range with 2 (what a bootstrap
    of 2 values gives too), nothing (low = high = mean) with 1. See :func:`spread_name`."""
    values = np.asarray(values, dtype=float)
    if values.ndim != 2 or values.shape[1] == 0:  # no common column (nothing evaluated)
        return np.zeros(0), np.zeros(0), np.zeros(0)
    if values.shape[0] < 3:
        return values.mean(0), values.min(0), values.max(0)
    cols = [bootstrap_ci(values[:, j], n_boot=n_boot) for j in range(values.shape[1])]
    return tuple(np.array(c) for c in zip(*cols, strict=True))


def spread_name(seeds: int) -> str:
    """What :func:`spread_over_seeds` gives for ``seeds`` seeds, in words ("" for 1)."""
    return ("95 % bootstrap CI over seeds" if seeds >= 3 else
            "min-max range of the 2 seeds" if seeds == 2 else "")
