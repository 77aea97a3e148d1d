"""The planning reference and the classic heuristics: the planner at H = 1 is the oracle
action for action, its moves are legal under every mask, a longer horizon finds a detour
that one step of greed misses; k-means, junction sites and the gap share by hand."""

from __future__ import annotations

import json
import math

import pytest
import torch

from tests.test_train import smoke
from uabs_rl.cli.evaluate import main as eval_main
from uabs_rl.config import ConfigError
from uabs_rl.env.geometry import Geometry
from uabs_rl.env.params import EnvParams
from uabs_rl.env.uabs_env import ACTION, MASK, POSITION
from uabs_rl.evaluation.baselines import baseline_policy
from uabs_rl.evaluation.evaluator import Evaluator, make_eval_env
from uabs_rl.evaluation.planner import (
    busiest_sites,
    gap_share,
    junction_sites,
    junctions,
    nearest_assignment,
    next_priority,
    scale_to_gap,
    weighted_kmeans,
)
from uabs_rl.safety.make import make_env, make_selector
from uabs_rl.traces.cache import TraceSet
from uabs_rl.training.resume import run


def eval_env(trace_cache, *overrides: str, windows: int = 4):
    cfg = smoke(trace_cache, *overrides)
    return cfg, make_eval_env(cfg, split="test", windows=windows)


def rollout(cfg, env, name: str, horizon: int = 1):
    policy = baseline_policy(name, env, make_selector(env), seed=0,
                             horizon=horizon, sites=junction_sites(cfg, env.base_env))
    return Evaluator(env, cfg.train.eval_seed).evaluate(policy)


@pytest.mark.parametrize("overrides", [("masking=flat",), ("masking=rank",),
                                       ("masking=rank", "scenario.n_uabs=6")])
def test_planner_with_horizon_1_is_the_oracle_action_for_action(trace_cache, overrides):
    cfg, env = eval_env(trace_cache, *overrides)
    oracle_rec, oracle = rollout(cfg, env, "oracle")
    planner_rec, planner = rollout(cfg, env, "planner", horizon=1)
    assert oracle[ACTION].shape == (4, cfg.scenario.episode_steps, cfg.scenario.n_uabs)
    assert torch.equal(planner[ACTION], oracle[ACTION])
    assert planner_rec["returns"] == oracle_rec["returns"]


@pytest.mark.parametrize("overrides", [("masking=flat",), ("masking=rank",),
                                       ("masking=flat", "scenario.n_uabs=6"),
                                       ("masking=rank", "scenario.n_uabs=6"),
                                       ("masking=rank", "masking.recoverable=false")])
def test_planner_and_heuristics_fly_only_legal_moves(trace_cache, overrides):
    cfg, env = eval_env(trace_cache, *overrides)
    d_th = env.base_env.params.d_th
    for name, h in (("planner", 4), ("kmeans", 1), ("junctions", 1)):
        rec, td = rollout(cfg, env, name, h)
        # the mask that applied to each executed move (the rank selector's, in rank
        # order) allows it
        assert td[MASK].gather(-1, td[ACTION][..., None]).all(), name
        diag = td["next", "diagnostics"]
        assert diag["illegal_moves"].sum() == 0 and diag["collisions"].sum() == 0, name
        if cfg.masking.recoverable:
            assert rec["fallbacks"] == 0 and rec["proximity"] == 0, name
            assert rec["closest_approach"] >= d_th - 1e-3, name


def test_next_priority_follows_service_windows_and_arrivals():
    p = torch.tensor([[3.0, 0.0, 2.0, 5.0]])
    served = torch.tensor([[True, True, False, True]])
    present = torch.tensor([[True, True, True, False]])
    prev = torch.tensor([[True, False, True, True]])
    # served +1, a vehicle that appears starts at 1, absent is 0
    assert next_priority(p, served, present, prev, torch.tensor([False])).tolist() == \
        [[4.0, 1.0, 2.0, 0.0]]
    # a window starts: every present vehicle back to 1
    assert next_priority(p, served, present, prev, torch.tensor([True])).tolist() == \
        [[1.0, 1.0, 1.0, 0.0]]


def detour_traces(p: EnvParams, start: torch.Tensor, steps: int) -> TraceSet:
    """A lone vehicle one move to the right of ``start`` driving right at the UABS's
    speed (one step of greed follows it) and a queue of 10 standing vehicles five moves
    to the left (out of sight of one step's look, served from the fourth step on)."""
    pos = torch.zeros(1, steps, 11, 2)
    pos[0, :, :10] = start - torch.tensor([5 * p.step_m, 0.0])
    t = torch.arange(steps, dtype=torch.float32)
    x = (start[0] + p.step_m * (1 + t)).clamp_max(p.width - 1.0)
    pos[0, :, 10] = torch.stack([x, torch.full_like(x, float(start[1]))], -1)
    present = torch.ones(1, steps, 11, dtype=torch.bool)
    return TraceSet(pos, present, {"dt": p.dt, "split": "test"})


def test_a_longer_horizon_takes_the_detour_to_a_queue(trace_cache):
    cfg = smoke(trace_cache, "masking=penalty", "scenario.n_uabs=1")
    t_steps = cfg.scenario.episode_steps
    p = EnvParams.from_config(cfg.scenario, cfg.channel)
    start = Geometry(p, torch.device("cpu")).lattice_point(torch.tensor(9.0), torch.tensor(4.0))
    env = make_env(cfg.scenario, cfg.channel, cfg.masking,
                   detour_traces(p, start, t_steps + 1), "test", n_envs=1, n_eval_windows=1,
                   seed=0, spec_mask=False)
    returns, first = {}, {}
    for h in (1, 5):
        policy = baseline_policy("planner", env, make_selector(env), horizon=h)
        env.set_seed(0)
        td = env.reset()
        env.base_env.state["pos"][:] = start  # the UABS starts between the two
        td[POSITION][:] = start
        td.set(MASK, env.base_env.math.geometry.boundary_mask(td[POSITION]))
        for t in range(t_steps):
            td = policy(td)
            if t == 0:
                first[h] = int(td[ACTION][0, 0])
            td = env.step(td)["next"]
        returns[h] = float(env.base_env.state["ep_return"][0])
    assert (first[1], first[5]) == (1, 3)  # greed follows the lone car right, H = 5 turns left
    # the planner serves the queue from step 4 on: 10 vehicles with growing priority
    assert returns[5] > 3 * returns[1] > 0


def test_weighted_kmeans_and_nearest_assignment_by_hand():
    x = torch.tensor([[[0.0, 0.0], [2.0, 0.0], [100.0, 0.0], [104.0, 0.0], [50.0, 50.0]]])
    w = torch.tensor([[1.0, 3.0, 1.0, 1.0, 0.0]])  # the last point does not count
    centres = weighted_kmeans(x, w, torch.tensor([[[10.0, 0.0], [90.0, 0.0]]]))
    assert centres.tolist() == [[[1.5, 0.0], [102.0, 0.0]]]
    sites = torch.tensor([[0.0, 0.0], [100.0, 0.0]])
    pos = torch.tensor([[[90.0, 0.0], [10.0, 0.0]], [[5.0, 0.0], [50.0, 0.0]]])
    assert nearest_assignment(pos, sites).tolist() == [[[100.0, 0.0], [0.0, 0.0]],
                                                       [[0.0, 0.0], [100.0, 0.0]]]


def test_busiest_sites_by_hand_and_manhattan_junctions(trace_cache):
    cand = torch.tensor([[0.0, 0.0], [30.0, 0.0], [200.0, 0.0], [400.0, 0.0]])
    veh = torch.tensor([[[0.0, 60.0, 60.0, 200.0, 200.0], [0.0] * 5]])  # [1, 2, V]
    present = torch.ones(1, 5, dtype=torch.bool)
    # footprints reach 3 r_b = 34.9 m along an axis: the site at 30 sees 3 vehicles, 200
    # sees 2, 0 sees 1 but is too close to 30, 400 none
    assert busiest_sites(cand, veh, present, 2, 11.64, 9, 100.0).tolist() == \
        [[30.0, 0.0], [200.0, 0.0]]
    # no 3 sites 1000 m apart: the spacing halves (62.5 m) until 3 fit
    assert busiest_sites(cand, veh, present, 3, 11.64, 9, 1000.0).tolist() == \
        [[30.0, 0.0], [200.0, 0.0], [400.0, 0.0]]
    # two sites on one point: they fit once the spacing is gone; fewer sites than UABS: refused
    twin = torch.tensor([[30.0, 0.0], [30.0, 0.0]])
    assert busiest_sites(twin, veh, present, 2, 11.64, 9, 100.0).tolist() == [[30.0, 0.0]] * 2
    with pytest.raises(ConfigError, match="at least as many junctions inside the area as "
                                          "UABS: 4 for scenario.n_uabs=5"):
        busiest_sites(cand, veh, present, 5, 11.64, 9, 100.0)
    cfg = smoke(trace_cache)
    p = EnvParams.from_config(cfg.scenario, cfg.channel)
    geo = Geometry(p, torch.device("cpu"))
    sites = junctions(cfg.scenario, geo)
    # the manhattan grid's junctions, on lattice points inside the area
    assert len(sites) >= 20
    assert torch.allclose((sites - geo.lattice_lo) / p.step_m,
                          torch.round((sites - geo.lattice_lo) / p.step_m))
    assert (sites >= 0).all() and (sites <= geo.area).all()


def test_gap_share_by_hand():
    d = gap_share([1.0, 2.0, 3.0], [0.0, 0.0, 1.0], [2.0, 4.0, 5.0])
    assert d["share"] == pytest.approx(5.0 / 10.0) and d["n"] == 3
    assert d["ci_low"] <= 0.5 <= d["ci_high"]
    assert math.isnan(gap_share([1.0, 2.0], [1.0, 1.0], [1.0, 1.0])["share"])  # no gap
    # the planner below greedy: no gap either (not a share with its sign flipped), and
    # uabs-report's scaling of a difference and its interval agrees
    assert math.isnan(gap_share([1.0, 2.0], [2.0, 2.0], [1.0, 1.0])["share"])
    assert scale_to_gap(0.5, 0.2, 0.8, 2.0) == {"share": 0.25, "ci_low": 0.1, "ci_high": 0.4}
    assert all(math.isnan(v) for v in scale_to_gap(0.5, 0.2, 0.8, -1.0).values())


def test_uabs_eval_planner_prints_its_cost_and_the_gap_share(trace_cache, tmp_path, capsys):
    run_dir = tmp_path / "run"
    run(smoke(trace_cache, "train.episodes=3", "train.trajectory_images=false"), run_dir)
    out = tmp_path / "ev"
    assert eval_main([str(run_dir), "--checkpoint", "last", "--policy", "learned",
                      "--policy", "greedy", "--policy", "planner", "--horizon", "3",
                      "--policy", "kmeans", "--policy", "junctions", "--windows", "3",
                      "--out", str(out)]) == 0
    text = capsys.readouterr().out
    res = json.loads((out / "eval.json").read_text())
    assert list(res["policies"]) == ["learned", "greedy", "planner", "kmeans", "junctions"]
    planner = res["policies"]["planner"]
    assert planner["horizon"] == 3 and planner["seconds"] > 0
    assert "planner: horizon 3, " in text and " s per window (3 windows side by side" in text
    pol = res["policies"]
    for metric, key in (("served_fraction", "served_fractions"), ("pg", "pgs")):
        share = res["gap_share"][metric]
        gained = sum(pol["learned"][key]) - sum(pol["greedy"][key])
        assert share["n"] == 3
        assert share["share"] == pytest.approx(gained / (sum(planner[key]) -
                                                         sum(pol["greedy"][key])))
    assert "learned share of the greedy-to-planner gap, served:" in text


def test_uabs_eval_horizon_must_be_positive(capsys):
    with pytest.raises(SystemExit) as e:
        eval_main(["nowhere", "--policy", "planner", "--horizon", "0"])
    assert e.value.code == 2
    assert "--horizon must be >= 1, got 0" in capsys.readouterr().err


def test_an_uncoordinated_planner_plans_each_uabs_alone(trace_cache):
    """coordinated=False: a UABS's scores do not depend on where the others are (no
    other plan takes its vehicles), while the coordinated planner's do (the others'
    plans cover vehicles it would serve)."""
    from uabs_rl.evaluation.planner import PlannerScore

    cfg, env = eval_env(trace_cache, "masking=rank")
    base = env.base_env
    td, select = env.reset(), make_selector(env)
    for _ in range(5):  # a few steps in, so that vehicles are about
        td = env.step(select(td))["next"]
    pos = td.get(POSITION).clone()
    moved = pos.clone()
    moved[:, 1:] = pos[:, :1]  # every other UABS where UABS 0 is
    scores = {}
    for coordinated in (True, False):
        for name, where in (("as flown", pos), ("moved", moved)):
            td.set(POSITION, where)
            planner = PlannerScore(base, 4, torch.Generator().manual_seed(0),
                                   coordinated=coordinated)
            scores[coordinated, name] = planner.scores(td)[:, 0]
    td.set(POSITION, pos)
    assert torch.equal(scores[False, "as flown"], scores[False, "moved"])
    assert not torch.equal(scores[True, "as flown"], scores[True, "moved"])
