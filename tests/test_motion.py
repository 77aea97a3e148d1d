"""The learned motion predictor (``--predictor learned``): it never reads a position
after step t, falls back to constant velocity where a vehicle's past is short, learns
constant velocity from traces that hold nothing else, and is fit once per training
traces and cached (a damaged cache file is fit again)."""

from __future__ import annotations

import logging

import pytest
import torch

from tests.test_mpc import eval_env, poisoned, rollout
from uabs_rl.env.uabs_env import ACTION
from uabs_rl.evaluation import motion
from uabs_rl.evaluation.motion import (
    AHEAD,
    HISTORY,
    LearnedMotion,
    MotionModel,
    fit_motion,
    learned_motion,
    motion_samples,
)
from uabs_rl.evaluation.predict import ConstantVelocity, make_predictor


def straight_traces(n_veh: int = 64, steps: int = 200, seed: int = 0):
    """Vehicles at constant velocity, each its own speed and heading, some absent."""
    g = torch.Generator().manual_seed(seed)
    start = 500 * torch.rand(1, 1, n_veh, 2, generator=g)
    vel = 8 * torch.rand(1, 1, n_veh, 2, generator=g) - 4
    t = torch.arange(steps, dtype=torch.float32)[None, :, None, None]
    present = torch.rand(1, steps, n_veh, generator=g) < 0.97
    return start + t * vel, present


def test_samples_are_the_moves_before_and_the_displacements_after_a_step():
    pos, present = straight_traces()
    moves, future = motion_samples(pos, present, 500, torch.Generator().manual_seed(1))
    assert moves.shape[1:] == (HISTORY, 2) and future.shape[1:] == (AHEAD, 2)
    assert 0 < len(moves) < 500  # spans with an absent step are left out
    # at constant velocity every move is the same, and step k is k moves on
    k = torch.arange(1, AHEAD + 1, dtype=torch.float32)[None, :, None]
    assert torch.allclose(future, k * moves[:, -1:], atol=1e-3)
    assert torch.allclose(moves, moves[:, -1:].expand_as(moves), atol=1e-4)


def test_a_fit_on_constant_velocity_traces_predicts_constant_velocity():
    pos, present = straight_traces(256, 400)
    model = fit_motion([(pos, present)], samples=10_000, steps=800, batch=256, lr=3e-3)
    test_pos, test_present = straight_traces(64, 200, seed=7)  # other vehicles
    moves, future = motion_samples(test_pos, test_present, 2000, torch.Generator())
    with torch.no_grad():
        err = (model(moves) - future).norm(dim=-1)  # [N, AHEAD]
    span = future.norm(dim=-1)
    # within a few percent of how far the vehicles go, at every step ahead
    assert float(err.mean() / span.mean()) < 0.05


def cv_model() -> MotionModel:
    """A model that predicts constant velocity exactly (by hand, no fit): its output is
    k times the last move."""
    m = MotionModel()
    with torch.no_grad():
        for layer in m.net:
            if isinstance(layer, torch.nn.Linear):
                layer.weight.zero_()
                layer.bias.zero_()
    m.net = torch.nn.Sequential(torch.nn.Identity())
    m.x_scale.fill_(1.0)
    m.y_scale.fill_(1.0)

    class Last(torch.nn.Module):
        def forward(self, x):  # x [N, 2·HISTORY] -> [N, 2·AHEAD]
            last = x[:, -2:]
            k = torch.arange(1, AHEAD + 1, dtype=x.dtype)
            return (k[:, None] * last[:, None, :]).reshape(len(x), -1)

    m.net = Last()
    return m


class PoisonedLearned(LearnedMotion):
    def __call__(self, env, horizon):
        return poisoned(super().__call__, env, horizon)


def test_the_learned_predictor_never_reads_after_step_t(trace_cache):
    cfg, env = eval_env(trace_cache, "masking=rank")
    model = fit_motion([straight_traces(64, 300)], samples=5000, steps=50, batch=256)
    rec, good = rollout(cfg, env, "mpc", horizon=3, predictor=LearnedMotion(model))
    bad_rec, bad = rollout(cfg, env, "mpc", horizon=3, predictor=PoisonedLearned(model))
    assert torch.equal(bad[ACTION], good[ACTION])
    assert bad_rec["returns"] == rec["returns"]


def test_a_constant_velocity_model_gives_constant_velocitys_world(trace_cache):
    """Where the network predicts k times the last move, the learned world is constant
    velocity's at every step (short pasts fall back to it; long horizons continue by the
    last predicted move), and so are the mpc's moves."""
    cfg, env = eval_env(trace_cache, "masking=rank")
    base = env.base_env
    env.reset()
    learned, cv = LearnedMotion(cv_model()), ConstantVelocity()
    for t in range(0, cfg.scenario.episode_steps, 3):  # before and after HISTORY steps
        base.state["t"] = torch.full_like(base.state["t"], t)
        for h in (3, AHEAD + 4):
            a, b = learned(base, h), cv(base, h)
            assert torch.allclose(a["veh"], b["veh"], atol=1e-3), (t, h)
            assert torch.equal(a["present"], b["present"])
    _, want = rollout(cfg, env, "mpc", horizon=3, predictor=cv)
    _, got = rollout(cfg, env, "mpc", horizon=3, predictor=learned)
    assert torch.equal(got[ACTION], want[ACTION])


def test_the_model_is_fit_once_per_training_traces_and_cached(trace_cache, monkeypatch,
                                                              caplog):
    from uabs_rl.traces.cache import cache_dir

    cfg, env = eval_env(trace_cache, "masking=rank")
    fits = []
    real = motion.fit_motion

    def counted(*a, **k):
        fits.append(1)
        return real(*a, **{**k, "samples": 5000, "steps": 20, "batch": 256})

    monkeypatch.setattr(motion, "fit_motion", counted)
    first = make_predictor("learned", "all", cfg.scenario, traces=cfg.traces)
    files = list(cache_dir(cfg.traces).glob(f"{cfg.scenario.name}-motion-*.pt"))
    assert len(fits) == 1 and len(files) == 1
    second = learned_motion(cfg.scenario, cfg.traces)
    assert len(fits) == 1  # read back, not fit again
    for a, b in zip(first.model.state_dict().values(), second.model.state_dict().values(),
                    strict=True):
        assert torch.equal(a, b)
    files[0].write_bytes(b"not a model")  # a damaged cache file: fit again, with a warning
    with caplog.at_level(logging.WARNING):
        learned_motion(cfg.scenario, cfg.traces)
    assert len(fits) == 2 and "fitting it again" in caplog.text
    with pytest.raises(ValueError, match="needs the scenario"):
        make_predictor("learned")
