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


class Scripted(torch.nn.Module):
    """In place of the fit network: k times the oldest (``oldest``) or the last move."""

    def __init__(self, oldest: bool):
        super().__init__()
        self.oldest = oldest

    def forward(self, x):  # x [N, 2·HISTORY] (moves oldest first) -> [N, 2·AHEAD]
        move = x[:, :2] if self.oldest else x[:, -2:]
        k = torch.arange(1, AHEAD + 1, dtype=x.dtype)
        return (k[:, None] * move[:, None, :]).reshape(len(x), -1)


def scripted_model(oldest: bool) -> MotionModel:
    m = MotionModel()
    m.net = Scripted(oldest)  # scales stay 1
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
    learned, cv = LearnedMotion(scripted_model(oldest=False)), ConstantVelocity()
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
    for f in cache_dir(cfg.traces).glob(f"{cfg.scenario.name}-motion-*.pt"):
        f.unlink()  # a 20-step fit: no later test of this session should read it
    with pytest.raises(ValueError, match="needs the scenario"):
        make_predictor("learned")


def test_the_network_moves_vehicles_with_a_whole_past_and_cv_the_others(trace_cache):
    """By hand (tests.test_mpc.hand_traces: vehicle 0 at 2 m per step, vehicle 1 at
    x = 10 + t², vehicle 2 absent until step 3; here vehicle 2 at x = 50 + t²), with a
    network that predicts k times the *oldest* of the 4 moves it reads: a vehicle
    present at each of the last 5 steps (t >= 4) moves so, past AHEAD steps too; the
    others move at constant velocity (one move) or stand (none)."""
    from tests.test_mpc import hand_traces
    from tests.test_train import smoke
    from uabs_rl.env.params import EnvParams
    from uabs_rl.safety.make import make_env

    cfg = smoke(trace_cache, "masking=penalty", "scenario.n_uabs=1")
    p = EnvParams.from_config(cfg.scenario, cfg.channel)
    traces = hand_traces(p, cfg.scenario.episode_steps + 1)
    steps = torch.arange(traces.steps, dtype=torch.float32)
    traces.positions[0, :, 2, 0] = 50 + steps * steps  # its past before step 3: unseen
    env = make_env(cfg.scenario, cfg.channel, cfg.masking, traces, "test", n_envs=1,
                   n_eval_windows=1, seed=0, spec_mask=False)
    env.set_seed(0)
    env.reset()
    base = env.base_env
    pred = LearnedMotion(scripted_model(oldest=True))
    h = AHEAD + 3
    k = torch.arange(1, h + 1, dtype=torch.float32)
    for t in range(9):
        base.state["t"] = torch.full_like(base.state["t"], t)
        x = pred(base, h)["veh"][:, 0, 0, :]  # [H, V] along x
        pos = lambda v, s: {0: 5 + 2 * s, 1: 10 + s * s, 2: 50 + s * s}[v]  # noqa: E731
        for v in range(3):
            first = 3 if v == 2 else 0  # the first step it is present
            if t >= 4 and t - 4 >= first:  # a whole past: k x its oldest move
                move = pos(v, t - 3) - pos(v, t - 4)
            elif t - 1 >= first:  # one move at least: constant velocity
                move = pos(v, t) - pos(v, t - 1)
            else:
                move = 0.0
            want = pos(v, t) + k * move
            assert torch.allclose(x[:, v], want, atol=1e-4), (t, v, x[:, v], want)


def test_traces_too_small_are_a_config_error_and_an_unwritable_cache_only_a_warning(
        trace_cache, monkeypatch, caplog):
    import uabs_rl.paths
    from uabs_rl.config import ConfigError
    from uabs_rl.traces.cache import cache_dir

    cfg, _ = eval_env(trace_cache, "masking=rank")
    for f in cache_dir(cfg.traces).glob(f"{cfg.scenario.name}-motion-*.pt"):
        f.unlink()

    def too_small(*a, **k):
        raise ValueError("the traces hold 3 spans")

    monkeypatch.setattr(motion, "fit_motion", too_small)
    with pytest.raises(ConfigError, match=r"traces.train.n_sims, traces.train.duration_s"):
        learned_motion(cfg.scenario, cfg.traces)
    real = fit_motion
    monkeypatch.setattr(motion, "fit_motion", lambda traces: real(
        traces, samples=2000, steps=5, batch=256))

    def unwritable(path, mode="wb"):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(uabs_rl.paths, "atomic_file", unwritable)
    with caplog.at_level(logging.WARNING):
        pred = learned_motion(cfg.scenario, cfg.traces)
    assert isinstance(pred, LearnedMotion) and "not cached" in caplog.text
    assert not list(cache_dir(cfg.traces).glob(f"{cfg.scenario.name}-motion-*.pt"))
