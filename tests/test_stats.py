"""The project's intervals: hand-computed values, and their coverage at 95 % measured
on simulated seeds of known mean (docs/evaluation.md gives the figures;
``python benchmarks/coverage.py`` prints them)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uabs_rl.evaluation.stats import (
    coverage,
    iqm,
    iqm_runs,
    paired_over_seeds,
    percentile_bootstrap,
    performance_profile,
    probability_of_improvement,
    stratified_bootstrap,
    t_interval,
    t_quantile,
    welch_difference,
)

SEEDS = [3, pytest.param(5, marks=pytest.mark.slow), pytest.param(10, marks=pytest.mark.slow)]
TRIALS = 4000  # binomial s.e. 0.34 points at 95 %
NOMINAL = (0.93, 0.97)  # 95 % within ±2 points
SIGMA = 0.25  # the log-normal the Student-t interval covers (skewness 0.78)


def normal(n: int):
    return lambda rng, trials: rng.normal(0.0, 1.0, size=(trials, n))


def lognormal(n: int, sigma: float = SIGMA):
    return lambda rng, trials: rng.lognormal(0.0, sigma, size=(trials, n))


def lognormal_mean(sigma: float = SIGMA) -> float:
    return math.exp(sigma ** 2 / 2)


def t_lohi(x):
    return t_interval(x)[1:]


# ----------------------------------------------------------------------------- values
def test_t_quantiles_and_intervals_match_hand_computed_values():
    """Tables' t_{0.975, df}; the interval of 1, 2, 3 is 2 ± 4.3027 / √3; Welch's of
    two groups with equal variances and sizes has 2n − 2 degrees of freedom."""
    for df, q in ((1, 12.7062047), (2, 4.3026527), (4, 2.7764451), (9, 2.2621572),
                  (30, 2.0422725)):
        assert t_quantile(0.975, df) == pytest.approx(q, abs=1e-6)
    assert t_quantile(0.025, 4) == pytest.approx(-2.7764451, abs=1e-6)
    m, lo, hi = t_interval([1.0, 2.0, 3.0])
    assert (m, lo, hi) == pytest.approx((2.0, 2 - 4.3026527 / math.sqrt(3),
                                         2 + 4.3026527 / math.sqrt(3)))
    assert t_interval([5.0]) == (5.0, 5.0, 5.0)
    d = welch_difference([1.0, 2.0, 3.0], [0.0, 1.0, 2.0])
    assert d["df"] == pytest.approx(4.0) and d["diff"] == pytest.approx(1.0)
    assert d["ci_high"] - 1.0 == pytest.approx(2.7764451 * math.sqrt(2 / 3), abs=1e-6)
    assert d["method"] == "95 % CI, Welch over 3 and 3 seeds"
    with pytest.raises(ValueError, match="2 seeds or more"):
        welch_difference([1.0], [0.0, 1.0])


def test_paired_differences_over_seeds_and_over_the_windows_of_one_seed():
    """Per seed the mean over windows of learned − baseline, then Student-t over seeds;
    one seed: Student-t over its windows, and the method says so."""
    base = [[1.0, 2.0, 3.0, 4.0]] * 3
    learned = [[2.0, 3.0, 4.0, 5.0], [1.5, 2.5, 3.5, 4.5], [3.0, 4.0, 5.0, 6.0]]
    d = paired_over_seeds(learned, base)
    assert (d["diff"], d["ci_low"], d["ci_high"]) == pytest.approx(t_interval([1.0, 0.5, 2.0]))
    assert d["n"] == 3 and d["method"] == "95 % CI, Student-t over 3 seeds"
    one = paired_over_seeds([[2.0, 2.5, 4.0, 5.0]], [[1.0, 2.0, 3.0, 4.0]])
    assert (one["diff"], one["ci_low"], one["ci_high"]) == pytest.approx(
        t_interval([1.0, 0.5, 1.0, 1.0]))
    assert one["n"] == 1 and "4 windows of the one seed" in one["method"]


def test_rliable_aggregates_match_hand_computed_values():
    """IQM of every run and task together; P(X > Y) per task with ties a half, averaged
    over tasks; the performance profile is the share of runs above τ; the stratified
    bootstrap resamples runs within a task only (a task whose runs agree never moves)."""
    assert iqm([1, 2, 3, 4, 100, -100, 2.5, 3.5]) == pytest.approx(np.mean([2, 2.5, 3, 3.5]))
    s = np.array([[1.0, 10.0], [2.0, 20.0], [3.0, 30.0], [4.0, 40.0]])  # [runs, tasks]
    assert iqm_runs(s) == pytest.approx(np.mean([3.0, 4.0, 10.0, 20.0]))
    x, y = np.array([[1.0, 5.0], [3.0, 5.0]]), np.array([[2.0, 5.0], [2.0, 6.0]])
    # task 0: x>y in 2 of 4 pairs; task 1: ties in 2, below in 2 -> 0.25
    assert probability_of_improvement(x, y) == pytest.approx((0.5 + 0.25) / 2)
    share, lo, hi = performance_profile(s, [2.5, 25.0], n_boot=200)
    assert list(share) == [0.75, 0.25]
    same = np.array([[1.0, 7.0], [2.0, 7.0], [3.0, 7.0]])
    v, lo, hi = stratified_bootstrap([same], lambda a: a[..., 1].mean(-1), n_boot=200)
    assert v == lo == hi == 7.0


# ----------------------------------------------------------------------------- coverage
@pytest.mark.parametrize("n", SEEDS)  # 5 and 10: -m slow
def test_student_t_over_seeds_covers_at_95_percent(n):
    """Student-t on n seed means covers within [93, 97] % at 95 % over 2000 simulated
    experiments, normal and log-normal (σ = 0.25) seeds of known mean."""
    assert NOMINAL[0] <= coverage(t_lohi, normal(n), 0.0, TRIALS, seed=n) <= NOMINAL[1]
    assert NOMINAL[0] <= coverage(t_lohi, lognormal(n), lognormal_mean(), TRIALS,
                                  seed=n) <= NOMINAL[1]


@pytest.mark.parametrize("n", SEEDS)  # 5 and 10: -m slow
def test_paired_difference_over_seeds_covers_at_95_percent(n):
    """learned − baseline over 56 shared windows per seed, seeds differing by a normal
    or log-normal effect of known mean: the interval over seeds covers within [93, 97] %."""
    windows = 56

    def seeds(effect):
        def sample(rng, trials):
            base = rng.normal(0.3, 0.05, size=(trials, 1, windows))
            eff = effect(rng, trials)[..., None]
            noise = rng.normal(0.0, 0.02, size=(trials, n, windows))
            return np.stack(np.broadcast_arrays(base + eff + noise, base), axis=1)
        return sample

    def interval(x):
        d = paired_over_seeds(x[0], x[1])
        return d["ci_low"], d["ci_high"]

    assert NOMINAL[0] <= coverage(interval, seeds(normal(n)), 0.0, TRIALS, seed=n) \
        <= NOMINAL[1]
    assert NOMINAL[0] <= coverage(interval, seeds(lognormal(n)), lognormal_mean(), TRIALS,
                                  seed=n) <= NOMINAL[1]


@pytest.mark.parametrize("n", SEEDS)  # 5 and 10: -m slow
@pytest.mark.parametrize("sd_b", [pytest.param(1.0, marks=pytest.mark.slow), 3.0])
def test_welch_between_two_groups_of_seeds_covers_at_95_percent(n, sd_b):
    """Two groups of n seeds (learned − learned), standard deviations 1 and ``sd_b``:
    Welch's interval covers the true difference within [93, 97] %, normal and log-normal."""
    def lohi(x):
        d = welch_difference(x[0], x[1])
        return d["ci_low"], d["ci_high"]

    def pair(gen, scale):
        return lambda rng, trials: np.stack([gen(rng, trials), scale * gen(rng, trials)], 1)

    assert NOMINAL[0] <= coverage(lohi, pair(normal(n), sd_b), 0.0, TRIALS, seed=n) \
        <= NOMINAL[1]
    truth = (1.0 - sd_b) * lognormal_mean()
    assert NOMINAL[0] <= coverage(lohi, pair(lognormal(n), sd_b), truth, TRIALS, seed=n) \
        <= NOMINAL[1]


def test_the_coverage_test_fails_the_old_percentile_bootstrap():
    """The same bounded check rejects the percentile bootstrap over 3 seeds (what every
    interval over seeds was before): it covers about 75 %."""
    def boot(x):
        return percentile_bootstrap(x, n_boot=500)[1:]

    cov = coverage(boot, normal(3), 0.0, 2000, seed=3)
    assert cov < NOMINAL[0] and cov == pytest.approx(0.75, abs=0.03)


def test_stated_limit_student_t_undercovers_strongly_skewed_seeds():
    """docs/evaluation.md's stated limit: on log-normal seeds with σ = 1 (skewness 6.2)
    the Student-t interval covers about 83 %, below the bound, at 3, 5 and 10 seeds."""
    for n in (3, 5, 10):
        cov = coverage(t_lohi, lognormal(n, 1.0), lognormal_mean(1.0), TRIALS, seed=n)
        assert 0.78 <= cov < NOMINAL[0]


TASKS = np.linspace(-1.0, 1.0, 9)  # 9 tasks of different means, as the generalization's


def iqm_truth() -> float:
    big = np.random.default_rng(99).normal(0.0, 1.0, size=(200_000, TASKS.size)) + TASKS
    return float(iqm_runs(big))


def iqm_coverage(n: int, trials: int, n_boot: int = 1000) -> float:
    def lohi(s):
        return stratified_bootstrap([s], iqm_runs, n_boot=n_boot)[1:]

    return coverage(lohi, lambda rng, t: rng.normal(0.0, 1.0, (t, n, TASKS.size)) + TASKS,
                    iqm_truth(), trials, seed=n)


def test_stated_limit_iqm_bootstrap_undercovers_at_3_seeds():
    """The stratified bootstrap of the IQM over 9 tasks covers about 88 % at 3 seeds (so
    the reports name it and base no verdict on it below 10 seeds)."""
    assert iqm_coverage(3, 400, n_boot=500) < NOMINAL[0]


@pytest.mark.slow
def test_iqm_stratified_bootstrap_covers_at_10_seeds():
    """At 10 seeds over 9 tasks the stratified bootstrap of the IQM covers within
    [93, 97] %."""
    assert NOMINAL[0] <= iqm_coverage(10, TRIALS) <= NOMINAL[1]


def test_differences_never_print_minus_zero():
    """A bound that rounds to zero prints +0.0 in uabs-eval and uabs-report alike (the
    report printed -0.0 where uabs-eval printed +0.0 for the same interval)."""
    from uabs_rl.cli.evaluate import points
    from uabs_rl.evaluation.stats import signed
    from uabs_rl.report.tables import fmt_diff

    assert [signed(-0.04), signed(0.04), signed(-0.06), signed(-0.4, 0)] == [
        "+0.0", "+0.0", "-0.1", "+0"]
    d = {"diff": 0.012, "ci_low": -0.0004, "ci_high": 0.032}
    assert fmt_diff("served_fraction", d["diff"], d["ci_low"], d["ci_high"]) == points(d) \
        == "+1.2 pt [+0.0, +3.2]"
