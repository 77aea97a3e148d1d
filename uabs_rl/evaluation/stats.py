"""Statistics for every reported interval, each with its method named and its coverage
measured (``tests/test_stats.py``, figures in docs/evaluation.md):

- across seeds (the unit of replication of a training run): a Student-t interval on the
  seed means (:func:`t_interval`); with 2 seeds, figures draw the min-max range instead
  (:func:`spread_over_seeds`);
- learned − baseline on the same windows: per seed the mean over windows of the paired
  differences, then the Student-t interval over seeds; with one seed, the windows are the
  unit (:func:`paired_over_seeds`, :func:`paired_difference`);
- learned − learned between two groups of seeds: Welch's interval (:func:`welch_difference`);
- over several tasks (cities, fleet sizes, masking modes): rliable's aggregates, the
  interquartile mean with a stratified bootstrap interval, the probability of improvement
  and performance profiles (:func:`stratified_bootstrap`, :func:`iqm`,
  :func:`probability_of_improvement`, :func:`performance_profile`).

The percentile bootstrap of a mean (:func:`percentile_bootstrap`) is kept for the
aggregates over tasks only: over 3 to 10 seeds its "95 %" interval covers 75 to 90 % of
the time (measured in the tests), so no interval over seeds uses it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import lru_cache

import numpy as np

LEVEL = 0.95


# ----------------------------------------------------------------------------- Student-t
def _betacf(a: float, b: float, x: float) -> float:
    """Continued fraction of the regularised incomplete beta function (modified Lentz)."""
    tiny, c, d = 1e-300, 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 300):
        for num in (m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),
                    -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))):
            d = 1.0 + num * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + num / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h


def _betainc(a: float, b: float, x: float) -> float:
    """The regularised incomplete beta function I_x(a, b)."""
    if x <= 0.0 or x >= 1.0:
        return 0.0 if x <= 0.0 else 1.0
    front = math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b)
                     + a * math.log(x) + b * math.log1p(-x))
    if x < (a + 1.0) / (a + b + 2.0):
        return front * _betacf(a, b, x) / a
    return 1.0 - front * _betacf(b, a, 1.0 - x) / b


def t_cdf(t: float, df: float) -> float:
    """P(T <= t) for Student's t with ``df`` degrees of freedom (df > 0, not an integer
    only: Welch's)."""
    tail = 0.5 * _betainc(df / 2.0, 0.5, df / (df + t * t))
    return 1.0 - tail if t > 0 else tail


def t_pdf(t: float, df: float) -> float:
    """The density of Student's t with ``df`` degrees of freedom."""
    return math.exp(math.lgamma((df + 1) / 2) - math.lgamma(df / 2)
                    - 0.5 * math.log(df * math.pi) - (df + 1) / 2 * math.log1p(t * t / df))


@lru_cache(maxsize=4096)
def t_quantile(p: float, df: float) -> float:
    """The ``p`` quantile of Student's t with ``df`` degrees of freedom (not only whole:
    Welch's), by Newton's method on :func:`t_cdf` from the normal quantile, which lies
    below it: the upper half of the cdf is concave, so the steps climb to the root
    without overshooting (scipy is not a dependency)."""
    if not 0.0 < p < 1.0 or df <= 0:
        raise ValueError(f"t_quantile needs 0 < p < 1 and df > 0, got p={p}, df={df}")
    if p < 0.5:
        return -t_quantile(1.0 - p, df)
    t = math.sqrt(2.0) * _erfinv(2.0 * p - 1.0)
    for _ in range(100):
        step = (p - t_cdf(t, df)) / t_pdf(t, df)
        t += step
        if abs(step) < 1e-12 * max(1.0, t):
            break
    return t


def _erfinv(y: float) -> float:
    """The inverse error function (Newton from Winitzki's approximation)."""
    a = 0.147
    ln = math.log1p(-y * y)
    x = math.copysign(math.sqrt(math.sqrt((2 / (math.pi * a) + ln / 2) ** 2 - ln / a)
                                - (2 / (math.pi * a) + ln / 2)), y)
    for _ in range(3):
        x -= (math.erf(x) - y) / (2 / math.sqrt(math.pi) * math.exp(-x * x))
    return x


def t_interval(x: np.ndarray | Sequence[float], level: float = LEVEL
               ) -> tuple[float, float, float]:
    """``(mean, low, high)``: the mean of ``x`` and its Student-t interval, mean ±
    t_{(1+level)/2, n-1} · s / √n; low = high = mean for one value, NaN for none."""
    x = np.asarray(x, dtype=float)
    if x.size == 0:
        return float("nan"), float("nan"), float("nan")
    mean = float(x.mean())
    if x.size == 1:
        return mean, mean, mean
    half = t_quantile((1.0 + level) / 2.0, x.size - 1) * float(x.std(ddof=1)) / math.sqrt(x.size)
    return mean, mean - half, mean + half


# ----------------------------------------------------------------------------- intervals
def signed(x: float, digits: int = 1) -> str:
    """``x`` with its sign and ``digits`` decimals, a value that rounds to zero as
    ``+0.0`` (never ``-0.0``): how every difference and interval bound is printed."""
    return f"{round(x, digits) + 0.0:+.{digits}f}"


def across_seeds_name(n: int, unit: str = "seeds") -> str:
    """The words for the interval of :func:`t_interval` over ``n`` ``unit`` ("" for 1)."""
    return f"95 % CI, Student-t over {n} {unit}" if n > 1 else ""


def paired_difference(a: Sequence[float], b: Sequence[float], level: float = LEVEL,
                      unit: str = "windows") -> dict[str, float | int | str]:
    """Mean of ``a − b`` entry by entry (the same windows, or the same seeds) with its
    Student-t interval, over the pairs where both are defined (a window without a
    vehicle has no served fraction): ``{diff, ci_low, ci_high, n, method}``."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.shape != b.shape:
        raise ValueError(f"paired samples need equal shapes, got {a.shape} and {b.shape}")
    kept = ~(np.isnan(a) | np.isnan(b))
    a, b = a[kept], b[kept]
    mean, lo, hi = t_interval(a - b, level)
    if a.size < 2:  # one pair gives no interval (not one of width zero)
        lo = hi = float("nan")
    return {"diff": mean, "ci_low": lo, "ci_high": hi, "n": int(a.size),
            "method": across_seeds_name(int(a.size), unit) or f"no interval: {a.size} "
            f"{unit[:-1] if a.size == 1 and unit.endswith('s') else unit}"}


def paired_over_seeds(learned: Sequence[Sequence[float]], baseline: Sequence[Sequence[float]],
                      level: float = LEVEL) -> dict[str, float | int | str]:
    """learned − baseline over the same windows, per seed (``learned[seed][window]``):
    each seed's mean over windows of the paired differences, then the mean over seeds and
    its Student-t interval over seeds. With one seed the windows are the unit, and
    ``method`` says so. ``{diff, ci_low, ci_high, n, method}`` (``n``: seeds)."""
    diffs = [np.subtract(np.asarray(a, dtype=float), np.asarray(b, dtype=float))
             for a, b in zip(learned, baseline, strict=True)]
    if len(diffs) == 1:
        d = paired_difference(diffs[0], np.zeros_like(diffs[0]), level)
        d["method"] = f"95 % CI, Student-t over the {diffs[0].size} windows of the one seed"
        return {**d, "n": 1}
    mean, lo, hi = t_interval([float(np.nanmean(d)) for d in diffs], level)
    return {"diff": mean, "ci_low": lo, "ci_high": hi, "n": len(diffs),
            "method": across_seeds_name(len(diffs))}


def welch_difference(a: Sequence[float], b: Sequence[float], level: float = LEVEL
                     ) -> dict[str, float | int | str]:
    """mean(a) − mean(b) of two independent groups of seeds (learned − learned) with
    Welch's interval (Welch–Satterthwaite degrees of freedom): ``{diff, ci_low, ci_high,
    df, n_a, n_b, method}``. Each group needs 2 seeds or more."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if a.size < 2 or b.size < 2:
        raise ValueError(f"Welch's interval needs 2 seeds or more per group, got {a.size} "
                         f"and {b.size}")
    va, vb = a.var(ddof=1) / a.size, b.var(ddof=1) / b.size
    diff = float(a.mean() - b.mean())
    se = math.sqrt(va + vb)
    if se == 0.0:
        df, half = float(a.size + b.size - 2), 0.0
    else:
        df = (va + vb) ** 2 / (va ** 2 / (a.size - 1) + vb ** 2 / (b.size - 1))
        half = t_quantile((1.0 + level) / 2.0, df) * se
    return {"diff": diff, "ci_low": diff - half, "ci_high": diff + half, "df": float(df),
            "n_a": int(a.size), "n_b": int(b.size),
            "method": f"95 % CI, Welch over {a.size} and {b.size} seeds"}


def spread_over_seeds(values: np.ndarray | list[list[float]]
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per column of ``values [seeds, columns]``: the mean over seeds and its spread, the
    Student-t 95 % CI with 3 seeds or more, the min-max range with 2 (a figure's band;
    the t interval of 2 values is 12.7 times their half-range), nothing (low = high =
    mean) with 1. See :func:`spread_name`."""
    values = np.asarray(values, dtype=float)
    if values.ndim != 2 or values.shape[1] == 0:  # no common column (nothing evaluated)
        return np.zeros(0), np.zeros(0), np.zeros(0)
    if values.shape[0] < 3:
        return values.mean(0), values.min(0), values.max(0)
    cols = [t_interval(values[:, j]) for j in range(values.shape[1])]
    return tuple(np.array(c) for c in zip(*cols, strict=True))


def spread_name(seeds: int) -> str:
    """What :func:`spread_over_seeds` gives for ``seeds`` seeds, in words ("" for 1)."""
    return (across_seeds_name(seeds) if seeds >= 3 else
            "min-max range of the 2 seeds" if seeds == 2 else "")


# ----------------------------------------------------------------------------- over tasks
def percentile_bootstrap(x: np.ndarray | Sequence[float], level: float = LEVEL,
                         n_boot: int = 10_000, seed: int = 0) -> tuple[float, float, float]:
    """``(mean, low, high)``: the mean of ``x`` and its percentile bootstrap interval.
    Too narrow over few values (75 % coverage at 3, 84 % at 5): not for seeds."""
    x = np.asarray(x, dtype=float)
    if x.size == 0:
        return float("nan"), float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    means = x[rng.integers(0, x.size, size=(n_boot, x.size))].mean(-1)
    a = (1.0 - level) / 2.0
    return float(x.mean()), float(np.quantile(means, a)), float(np.quantile(means, 1 - a))


def iqm(x: np.ndarray | Sequence[float]) -> float:
    """Interquartile mean: the mean of the middle 50 % of the sorted values (of every
    run and task together, as rliable's)."""
    x = np.asarray(x, dtype=float)
    return float(iqm_runs(x.reshape(-1, 1))) if x.size else float("nan")


def iqm_runs(scores: np.ndarray) -> np.ndarray:
    """The interquartile mean of ``scores [..., runs, tasks]`` over its runs and tasks
    together (the leading axes kept: bootstrap resamples)."""
    flat = np.sort(scores.reshape(*scores.shape[:-2], -1), axis=-1)
    n = flat.shape[-1]
    lo, hi = int(np.floor(0.25 * n)), int(np.ceil(0.75 * n))
    return flat[..., lo:hi].mean(-1) if hi > lo else flat.mean(-1)


def stratified_bootstrap(scores: Sequence[np.ndarray], statistic: Callable[..., np.ndarray],
                         level: float = LEVEL, n_boot: int = 2000, seed: int = 0
                         ) -> tuple[float, float, float]:
    """``(value, low, high)`` of ``statistic(*scores)`` with rliable's stratified
    percentile bootstrap: each array of ``scores`` is ``[runs, tasks]`` and its runs are
    resampled within each task, independently per array and task. ``statistic`` takes
    arrays ``[..., runs, tasks]`` and keeps the leading axes (all resamples at once)."""
    arrays = [np.asarray(s, dtype=float) for s in scores]
    rng = np.random.default_rng(seed)
    resampled = [np.take_along_axis(s[None], rng.integers(0, s.shape[0], (n_boot, *s.shape)),
                                    axis=1) for s in arrays]
    boots = np.asarray(statistic(*resampled), dtype=float)
    a = (1.0 - level) / 2.0
    return (float(statistic(*arrays)), float(np.quantile(boots, a)),
            float(np.quantile(boots, 1 - a)))


def probability_of_improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """rliable's P(X > Y): per task, the share of (run of x, run of y) pairs where x's
    score is higher (ties count a half), averaged over tasks; ``x``, ``y``: ``[..., runs,
    tasks]`` (the leading axes kept)."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if x.shape[-1] != y.shape[-1]:
        raise ValueError(f"probability of improvement needs the same tasks, got "
                         f"{x.shape[-1]} and {y.shape[-1]}")
    xs, ys = x[..., :, None, :], y[..., None, :, :]
    return ((xs > ys).mean((-3, -2)) + 0.5 * (xs == ys).mean((-3, -2))).mean(-1)


def performance_profile(scores: np.ndarray, taus: Sequence[float], n_boot: int = 2000,
                        seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """rliable's run-score distribution: for each threshold τ the share of runs (over all
    tasks) scoring above τ, with its stratified bootstrap 95 % band: ``(share, low,
    high)``, one entry per τ."""
    out = [stratified_bootstrap([scores], lambda s, t=t: (s > t).mean((-2, -1)),
                                n_boot=n_boot, seed=seed) for t in np.asarray(taus, float)]
    return tuple(np.array(c) for c in zip(*out, strict=True))


AGGREGATE_METHOD = "95 % CI, stratified percentile bootstrap over runs within each task"


# ----------------------------------------------------------------------------- coverage
def coverage(interval: Callable[[np.ndarray], tuple[float, float]],
             sample: Callable[[np.random.Generator, int], np.ndarray], truth: float,
             trials: int = 2000, seed: int = 0) -> float:
    """The share of ``trials`` simulated experiments (``sample(rng, trials)``: one
    experiment per leading entry) whose ``interval(experiment) -> (low, high)`` holds
    ``truth``: how the tests and ``benchmarks/coverage.py`` measure each method."""
    data = sample(np.random.default_rng(seed), trials)
    hits = 0
    for x in data:
        lo, hi = interval(x)
        hits += lo <= truth <= hi
    return hits / trials
