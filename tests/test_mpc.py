"""The deployable planner (``mpc``): the planner's search fed by a predictor. With a
predictor that returns the true future it is the clairvoyant planner action for action
(and at H = 1 the oracle); the constant-velocity predictor never reads a position after
step t; its error k steps ahead by hand; the mpc flies only legal moves."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest
import torch

from tests.test_planner import eval_env as planner_env
from tests.test_train import smoke
from uabs_rl.cli.evaluate import main as eval_main
from uabs_rl.env.params import EnvParams
from uabs_rl.env.uabs_env import ACTION, MASK, UABSEnv
from uabs_rl.evaluation.baselines import baseline_policy
from uabs_rl.evaluation.evaluator import Evaluator
from uabs_rl.evaluation.predict import (
    ConstantVelocity,
    Predictor,
    TrueFuture,
    Within,
    make_predictor,
    parse_sees,
    prediction_error,
    schedule,
)
from uabs_rl.report.build import build_report
from uabs_rl.safety.make import make_env, make_selector
from uabs_rl.traces.cache import TraceSet
from uabs_rl.training.resume import run


def eval_env(trace_cache, *overrides: str, windows: int = 2):
    return planner_env(trace_cache, *overrides, windows=windows)


def rollout(cfg, env, name: str, horizon: int = 1, predictor: Predictor | None = None):
    policy = baseline_policy(name, env, make_selector(env), seed=0, horizon=horizon,
                             predictor=predictor)
    return Evaluator(env, cfg.train.eval_seed).evaluate(policy)


class Replay(Predictor):
    """The true future read straight from the traces' rows (not through env.vehicles):
    a predictor that happens to be right."""

    name = "replay"

    def __call__(self, env: UABSEnv, horizon: int) -> dict[str, torch.Tensor]:
        st, steps = env.state, env.veh_pos.shape[1]
        rows = [(st["start"] + st["t"] + k).clamp_max(steps - 1) for k in range(1, horizon + 1)]
        return {"veh": torch.stack([env.veh_pos[st["sim"], r] for r in rows]),
                "present": torch.stack([st["prev_present"],
                                        *(env.veh_present[st["sim"], r] for r in rows)]),
                **schedule(env, horizon)}


class Poisoned(ConstantVelocity):
    """Constant velocity with every trace row after each env's step t (to its window's
    end) replaced by garbage while it predicts (the env steps on the true traces)."""

    def __call__(self, env: UABSEnv, horizon: int) -> dict[str, torch.Tensor]:
        st, pos, present = env.state, env.veh_pos, env.veh_present
        t = int(st["t"][0])
        assert (st["t"] == t).all()  # the windows run in lock step: no window's rows are
        # another's future
        gen = torch.Generator().manual_seed(t)
        kept = []
        for sim, start in zip(st["sim"].tolist(), st["start"].tolist(), strict=True):
            sl = slice(start + t + 1, start + env.params.episode_steps + 1)
            kept.append((sim, sl, pos[sim, sl].clone(), present[sim, sl].clone()))
            n = pos[sim, sl].shape
            pos[sim, sl] = 1e4 * torch.rand(n, generator=gen) - 5e3
            present[sim, sl] = torch.rand(n[:1] + n[2:], generator=gen) < 0.5
        try:
            return super().__call__(env, horizon)
        finally:
            for sim, sl, p, q in kept:
                pos[sim, sl], present[sim, sl] = p, q


@pytest.mark.parametrize("overrides", [("masking=flat",), ("masking=rank",)])
def test_mpc_with_the_true_future_is_the_planner_action_for_action(trace_cache, overrides):
    cfg, env = eval_env(trace_cache, *overrides)
    planner_rec, planner = rollout(cfg, env, "planner", horizon=3)
    mpc_rec, mpc = rollout(cfg, env, "mpc", horizon=3, predictor=Replay())
    assert torch.equal(mpc[ACTION], planner[ACTION])
    assert mpc_rec["returns"] == planner_rec["returns"]
    # and a predictor is what makes the difference: constant velocity plans otherwise
    _, cv = rollout(cfg, env, "mpc", horizon=3)
    assert not torch.equal(cv[ACTION], planner[ACTION])


@pytest.mark.parametrize("overrides", [("masking=flat",), ("masking=rank",)])
def test_mpc_with_horizon_1_and_the_true_future_is_the_oracle(trace_cache, overrides):
    cfg, env = eval_env(trace_cache, *overrides)
    oracle_rec, oracle = rollout(cfg, env, "oracle")
    for pred in (TrueFuture(), Replay()):
        rec, mpc = rollout(cfg, env, "mpc", horizon=1, predictor=pred)
        assert torch.equal(mpc[ACTION], oracle[ACTION]), pred.name
        assert rec["returns"] == oracle_rec["returns"]


def test_constant_velocity_never_reads_after_step_t(trace_cache):
    cfg, env = eval_env(trace_cache, "masking=rank")
    rec, cv = rollout(cfg, env, "mpc", horizon=3, predictor=ConstantVelocity())
    bad_rec, bad = rollout(cfg, env, "mpc", horizon=3, predictor=Poisoned())
    assert torch.equal(bad[ACTION], cv[ACTION])
    assert bad_rec["returns"] == rec["returns"]
    # the poison is real: the clairvoyant planner given the same garbage plans otherwise

    class PoisonedTruth(Poisoned):
        def __call__(self, env, horizon):
            saved = ConstantVelocity.__call__
            try:
                ConstantVelocity.__call__ = lambda s, e, h: TrueFuture()(e, h)
                return super().__call__(env, horizon)
            finally:
                ConstantVelocity.__call__ = saved

    _, truth = rollout(cfg, env, "mpc", horizon=3, predictor=TrueFuture())
    _, fooled = rollout(cfg, env, "mpc", horizon=3, predictor=PoisonedTruth())
    assert not torch.equal(fooled[ACTION], truth[ACTION])


@pytest.mark.parametrize("overrides", [("masking=flat",), ("masking=rank",),
                                       ("masking=rank", "scenario.n_uabs=6")])
def test_mpc_flies_only_legal_moves(trace_cache, overrides):
    cfg, env = eval_env(trace_cache, *overrides)
    d_th = env.base_env.params.d_th
    h = 2 if cfg.scenario.n_uabs > 3 else 3
    preds = [ConstantVelocity()] + ([Within(ConstantVelocity(), 60.0)]
                                    if cfg.masking.mode == "rank" else [])
    for pred in preds:
        rec, td = rollout(cfg, env, "mpc", horizon=h, predictor=pred)
        assert td[MASK].gather(-1, td[ACTION][..., None]).all(), pred.name
        diag = td["next", "diagnostics"]
        assert diag["illegal_moves"].sum() == 0 and diag["collisions"].sum() == 0
        assert rec["collisions"] == 0 and rec["proximity"] == 0 and rec["fallbacks"] == 0
        assert rec["closest_approach"] >= d_th - 1e-3


def hand_traces(p: EnvParams, steps: int) -> TraceSet:
    """Vehicle 0 drives at 2 m per step, vehicle 1 accelerates (x = 10 + t² m), vehicle
    2 is absent until step 3."""
    t = torch.arange(steps, dtype=torch.float32)
    pos = torch.zeros(1, steps, 3, 2)
    pos[0, :, 0, 0], pos[0, :, 1, 0], pos[0, :, 2, 0] = 5 + 2 * t, 10 + t * t, 50.0
    pos[..., 1] = 40.0
    present = torch.ones(1, steps, 3, dtype=torch.bool)
    present[0, :3, 2] = False
    return TraceSet(pos, present, {"dt": p.dt, "split": "test"})


def test_prediction_error_by_hand(trace_cache):
    cfg = smoke(trace_cache, "masking=penalty", "scenario.n_uabs=1")
    t_steps = cfg.scenario.episode_steps
    p = EnvParams.from_config(cfg.scenario, cfg.channel)
    env = make_env(cfg.scenario, cfg.channel, cfg.masking, hand_traces(p, t_steps + 1),
                   "test", n_envs=1, n_eval_windows=1, seed=0, spec_mask=False)
    env.set_seed(0)
    env.reset()
    base = env.base_env
    # constant velocity predicts x_t + k (x_t − x_{t−1}); at t = 0 there is no past
    # (no motion). Vehicle 0: error 2k at t = 0, 0 after. Vehicle 1: the truth is
    # 10 + (t + k)², the prediction 10 + t² + k (2t − 1): error k² + k, k² at t = 0.
    # Vehicle 2 (present from step 3) stands still the step it appears, then is exact.
    for k, got in prediction_error(base, ConstantVelocity(), (1, 2, 5)).items():
        n_t = t_steps - k + 1  # t = 0 .. T − k
        errors = [2 * k, k * k] + [k * k + k] * (n_t - 1)  # vehicles 0 and 1
        errors += [0.0] * (n_t - 1)  # vehicle 0 after t = 0
        # vehicle 2: predicted present at t >= 3 only; at t = 3 it stands still, 0 m off
        errors += [0.0] * (n_t - 3)
        assert got["n"] == len(errors), k
        assert got["mean_m"] == pytest.approx(sum(errors) / len(errors), rel=1e-5), k
        assert got["rmse_m"] == pytest.approx((sum(e * e for e in errors) / len(errors)) ** 0.5,
                                              rel=1e-5)
    # the true future is never off; the step counter is put back
    assert all(e["mean_m"] == 0 for e in prediction_error(base, TrueFuture(), (1, 3)).values())
    assert int(base.state["t"][0]) == 0


def test_within_sees_only_the_vehicles_near_a_uabs_and_options(trace_cache):
    cfg, env = eval_env(trace_cache, "masking=rank", windows=2)
    env.set_seed(0)
    env.reset()
    base = env.base_env
    full = ConstantVelocity()(base, 3)
    near = Within(ConstantVelocity(), 40.0)(base, 3)
    veh, present = base.vehicles(0)
    d = (veh[:, None] - base.state["pos"][..., None]).norm(dim=2).amin(1)  # [E, V]
    assert torch.equal(near["present"][1:], full["present"][1:] & (d <= 40.0)[None])
    assert torch.equal(near["present"][0], full["present"][0])
    assert torch.equal(near["veh"], full["veh"])
    assert isinstance(make_predictor("cv", 40.0), Within)
    assert isinstance(make_predictor("true"), TrueFuture)
    assert parse_sees("all") == "all" and parse_sees("150") == 150.0
    for bad in ("-1", "far", "nan", "inf"):
        with pytest.raises(ValueError, match="--sees must be 'all' or a distance"):
            parse_sees(bad)
    with pytest.raises(ValueError, match="unknown predictor 'road'"):
        make_predictor("road")


@pytest.fixture(scope="module")
def smoke_run(trace_cache, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("mpc") / "run"
    run(smoke(trace_cache, "train.episodes=2", "train.trajectory_images=false"), run_dir)
    return run_dir


def test_uabs_eval_mpc_reports_its_settings_and_compute(smoke_run, tmp_path, capsys):
    run_dir = smoke_run
    out = tmp_path / "ev"
    assert eval_main([str(run_dir), "--checkpoint", "last", "--policy", "greedy",
                      "--policy", "mpc", "--mpc-horizon", "3", "--sees", "150",
                      "--windows", "2", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    res = json.loads((out / "eval.json").read_text())
    mpc = res["policies"]["mpc"]
    assert (mpc["horizon"], mpc["predictor"], mpc["sees"]) == (3, "cv", 150.0)
    assert mpc["ms_per_decision"] > 0 and res["policies"]["greedy"]["ms_per_decision"] > 0
    assert "mpc: horizon 3, predictor cv, sees the vehicles within 150 m; " in text
    assert "compute per decision (the whole fleet, ms per step" in text
    # the whole evaluation's time and this process's peak memory, as a number of MiB
    assert re.search(r"^evaluated 2 policies in \d+\.\d s, peak memory [1-9]\d* MiB$", text,
                     re.M), text
    with pytest.raises(SystemExit) as e:
        eval_main([str(run_dir), "--policy", "mpc", "--sees", "near"])
    assert e.value.code == 2
    assert "--sees must be 'all' or a distance >= 0 in metres, got 'near'" in \
        capsys.readouterr().err


def test_uabs_report_mpc_sits_beside_greedy_and_the_oracle(smoke_run, tmp_path):
    out = tmp_path / "report"
    res = build_report(smoke_run, out, mpc=2)
    mode = next(iter(res["grouping"].groups.values()))[0].mode
    names = ("random", "greedy", "oracle", "mpc")
    assert list(res["baselines"]) == [f"{b} ({mode} masks)" for b in names]
    with open(out / "baselines.csv") as f:
        assert [r["policy"].split()[0] for r in csv.DictReader(f)] == list(names)
    lvb = res["learned_vs_baselines"]
    assert {r["baseline"] for r in lvb} == set(names)
    row = next(r for r in lvb if r["baseline"] == "mpc" and r["metric"] == "served_fraction")
    mpc = res["baselines"][f"mpc ({mode} masks)"]
    assert mpc["horizon"] == 2 and mpc["predictor"] == "cv"
    assert row["baseline_value"] == pytest.approx(float(np.mean(mpc["served_fractions"])))
    assert (out / "fig4_pg.png").stat().st_size > 10_000
    # without --mpc nothing of it
    plain = build_report(smoke_run, tmp_path / "plain")
    assert list(plain["baselines"]) == [f"{b} ({mode} masks)" for b in names[:3]]


@pytest.mark.parametrize("module, args, says", [
    ("evaluate", ["RUN", "--policy", "mpc", "--mpc-horizon", "0"], "--mpc-horizon must be >= 1"),
    ("report", ["DIR", "--mpc", "0"], "--mpc H needs H >= 1"),
    ("report", ["DIR", "--mpc", "5", "--no-baselines"], "--mpc H needs H >= 1")])
def test_mpc_option_errors_are_one_line(module, args, says, capsys):
    import importlib

    main = importlib.import_module(f"uabs_rl.cli.{module}").main
    with pytest.raises(SystemExit) as e:
        main(args)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0]
