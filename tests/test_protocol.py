"""The evaluation protocol: three disjoint trace splits, selection on validation only,
and the statistics every reported figure comes with."""

from __future__ import annotations

import numpy as np
import pytest

from tests.test_train import smoke
from uabs_rl.config import ConfigError
from uabs_rl.evaluation.stats import iqm, paired_difference, t_interval
from uabs_rl.traces import build as traces_mod
from uabs_rl.training.resume import run
from uabs_rl.training.startup import validate_run


@pytest.mark.parametrize("override,split", [
    ("traces.test.first_seed=0", "test"),  # test on training seeds
    ("traces.test.first_seed=10000", "test"),  # test on validation seeds
    ("traces.eval.first_seed=0", "eval"),  # validation on training seeds
])
def test_the_three_trace_sets_never_share_a_sumo_seed(trace_cache, override, split):
    with pytest.raises(ConfigError, match=rf"traces\.{split}\.first_seed.*disjoint"):
        validate_run(smoke(trace_cache, override))


def test_training_and_checkpoint_selection_never_read_test_traces(trace_cache, tmp_path,
                                                                  monkeypatch):
    """Every trace a training run loads passes through get_traces: not one is a test
    split, and uabs-eval's default is the one that reads it."""
    asked = []
    real = traces_mod.get_traces

    def spy(scenario, traces_cfg, split, verbose=True):
        asked.append(split)
        return real(scenario, traces_cfg, split, verbose)

    for mod in ("uabs_rl.traces.build", "uabs_rl.safety.make", "uabs_rl.evaluation.evaluator"):
        monkeypatch.setattr(f"{mod}.get_traces", spy)
    run(smoke(trace_cache, "train.logger=none", "train.trajectory_images=false"),
        tmp_path / "run")
    assert "test" not in asked and {"train", "eval"} <= set(asked)
    from uabs_rl.cli.evaluate import main as eval_main
    assert eval_main([str(tmp_path / "run")]) == 0
    assert asked[-1] == "test"


def test_paired_interval_covers_a_known_difference():
    """Paired samples whose true mean difference is 2.0: the 95 % interval covers it in
    about 95 % of repeated experiments, and narrows with more windows (coverage at few
    seeds: tests/test_stats.py)."""
    rng = np.random.default_rng(1)
    hits, widths = 0, {}
    for _ in range(200):
        base = rng.normal(100.0, 10.0, size=56)
        learned = base + 2.0 + rng.normal(0.0, 3.0, size=56)
        d = paired_difference(learned, base)
        hits += d["ci_low"] <= 2.0 <= d["ci_high"]
        widths.setdefault(56, []).append(d["ci_high"] - d["ci_low"])
    assert 0.90 <= hits / 200 <= 0.99
    mean, lo, hi = t_interval(rng.normal(2.0, 3.0, size=5000))
    assert lo < 2.0 < hi and hi - lo < np.mean(widths[56]) / 5
    assert iqm([1, 2, 3, 4, 100, -100, 2.5, 3.5]) == pytest.approx(np.mean([2, 2.5, 3, 3.5]))
