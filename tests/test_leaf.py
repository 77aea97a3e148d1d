"""Learned leaf values for the mpc (``uabs-eval --policy leaf``): the observation at a
path's end is the env's own observation where the path ends at the current state; with
λ = 0 the policy is the mpc action for action; with a weight it changes the moves and
keeps every guarantee; a fleet-frame network is refused with the fix."""

from __future__ import annotations

import json

import pytest
import torch

from tests.conftest import load_benchmark
from tests.test_observation import AREA, EGO, FLEET, MOVES, traces
from tests.test_train import smoke
from uabs_rl.cli.evaluate import main as eval_main
from uabs_rl.config import ChannelConfig, ConfigError, ScenarioConfig
from uabs_rl.env.uabs_env import ACTION, UABSEnv
from uabs_rl.evaluation.baselines import MPC, baseline_policy
from uabs_rl.evaluation.leaf import LeafValue
from uabs_rl.evaluation.load import evaluate_policies, load_evaluation
from uabs_rl.evaluation.predict import ConstantVelocity, observed
from uabs_rl.safety.make import make_selector
from uabs_rl.training.resume import run


def test_the_observation_at_the_current_state_is_the_envs():
    """Each UABS placed at its own position, the fleet where it is, the vehicles and
    priorities of now: the leaf observation equals the env's, bit for bit, after steps
    that served vehicles (priorities above 1) and moved them (the motion half), its
    local maps tested point by point or read from a table around another point."""
    env = UABSEnv(ScenarioConfig(n_uabs=6, area=AREA, episode_steps=20),
                  ChannelConfig(los_mode="los"), traces(AREA), n_envs=2, seed=3, obs=EGO)
    env.reset()
    st = env.state
    st["pos"][:] = FLEET
    for a in MOVES:
        out = env.math.step(st, torch.stack([a, a.flip(0)]), env.veh_pos, env.veh_present,
                            env.rng)
    leaf = LeafValue(env, qnet=None, weight=1.0)
    now, present = observed(env, 0)
    prev, prev_present = observed(env, 1)
    assert (st["priority"] > 1).any() and not torch.equal(now, prev)
    for u in range(6):
        args = (st["pos"][:, u:u + 1], torch.full((2,), u), st["pos"], st["t"], now, present,
                prev, prev_present, st["priority"][:, None])
        want = out["observation"][:, u:u + 1]
        assert torch.equal(leaf.observation(*args), want)  # each map point tested
        # read from the table of a point two steps west and one north (the same numbers)
        origin = st["pos"][:, u] + torch.tensor([-40.0, 20.0])
        assert torch.equal(leaf.observation(*args, origin=origin, reach=2), want)


@pytest.fixture(scope="module")
def ego_run(trace_cache, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("leaf") / "run"
    run(smoke(trace_cache, "obs=egocentric", "train.episodes=6",
              "train.trajectory_images=false"), run_dir)
    return run_dir


def test_leaf_with_weight_0_is_the_mpc_action_for_action(ego_run):
    """The leaf values are added (λ = 0) and the best beam taken by value: the mpc's moves."""
    ev = load_evaluation(ego_run, "last", 3, "test")
    mpc = evaluate_policies(ev, (MPC,), mpc_horizon=3)[MPC][1].get(ACTION)
    env = ev.evaluator.env
    policy = baseline_policy(MPC, env, make_selector(env), 0, horizon=3,
                             predictor=ConstantVelocity())
    policy[0].leaf = LeafValue(env.base_env, ev.greedy[0].module, 0.0)
    rec, td = ev.evaluator.evaluate(policy, ev.episode, ev.env_steps)
    assert torch.equal(td.get(ACTION), mpc)
    assert rec["served_fraction"] > 0


def test_leaf_values_change_the_moves_and_keep_the_guarantees(ego_run):
    ev = load_evaluation(ego_run, "last", 3, "test")
    out = evaluate_policies(ev, (MPC, "leaf"), mpc_horizon=3, hybrid_weight=100.0)
    for rec, _ in out.values():
        assert rec["collisions"] == rec["proximity"] == rec["fallbacks"] == 0
    assert not torch.equal(out["leaf"][1].get(ACTION), out[MPC][1].get(ACTION))
    assert out["leaf"][0]["weight"] == 100.0 and out["leaf"][0]["horizon"] == 3


def test_the_value_counts_only_inside_the_episode(ego_run):
    """A path ending at the episode's last step or after it earns no learned value."""
    ev = load_evaluation(ego_run, "last", 2, "test")
    env = ev.evaluator.env.base_env
    env.reset()
    leaf = LeafValue(env, ev.greedy[0].module, 1.0)
    w = ConstantVelocity()(env, 2)
    e, m = env.state["pos"].shape[:2]
    ends = env.state["pos"][:, :1, None, :].expand(e, 4, 3, 2)
    prio = env.priority[:, None, None, :].expand(e, 4, 3, -1)
    u = torch.zeros(e, dtype=torch.long)
    assert leaf(ends, prio, env.state["pos"], u, w).abs().sum() > 0
    env.state["t"][:] = env.params.episode_steps - 2  # t + H = T: the episode is over
    assert torch.equal(leaf(ends, prio, env.state["pos"], u, w), torch.zeros(e, 4, 3))


def test_uabs_eval_leaf_reports_its_settings(ego_run, tmp_path, capsys):
    out = tmp_path / "ev"
    assert eval_main([str(ego_run), "--checkpoint", "last", "--policy", "leaf",
                      "--hybrid-weight", "0.5", "--mpc-horizon", "2", "--windows", "2",
                      "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rec = json.loads((out / "eval.json").read_text())["policies"]["leaf"]
    assert (rec["horizon"], rec["predictor"], rec["weight"]) == (2, "cv", 0.5)
    assert "leaf: horizon 2, predictor cv, sees every vehicle, weight 0.5 of the learned " \
           "leaf values; " in text


def test_a_fleet_frame_network_is_refused_with_the_fix(trace_cache, tmp_path, capsys):
    run_dir = tmp_path / "run"
    run(smoke(trace_cache, "train.episodes=2", "train.trajectory_images=false"), run_dir)
    assert eval_main([str(run_dir), "--checkpoint", "last", "--policy", "leaf",
                      "--windows", "1", "--out", str(tmp_path / "ev")]) == 2
    err = capsys.readouterr().err
    assert "obs=egocentric" in err and "--policy hybrid" in err
    with pytest.raises(ConfigError, match="egocentric"):
        LeafValue(load_evaluation(run_dir, "last", 1, "test").evaluator.env.base_env,
                  None, 1.0)


def test_the_benchmark_chooses_lambda_on_validation_and_names_the_leaf(ego_run, tmp_path):
    """``benchmarks/hybrid.py --leaf``: λ* from the validation sweep (λ = 0 the mpc's
    figure), the test rows as for the hybrid, the kind of hybrid in hybrid.json."""
    bench = load_benchmark("hybrid")
    bench.main([str(ego_run), "--leaf", "--weights", "0", "100", "--eval-windows", "2",
                "--out", str(tmp_path)])
    out = json.loads((tmp_path / "hybrid.json").read_text())
    assert out["hybrid"] == "leaf" and set(out["weights"]) == {"0.0", "100.0"}
    sweep = {float(w): v[0] for w, v in out["weights"].items()}
    assert out["best_weight"] == max(sweep, key=sweep.get)
    mpc = evaluate_policies(load_evaluation(ego_run, "best", 2, "eval"), (MPC,))[MPC][0]
    assert sweep[0.0] == pytest.approx(sum(mpc["served_fractions"]) / 2)
    assert set(out["policies"]) == {"greedy", "mpc", "learned", "hybrid"}
    assert "hybrid (the learned values at the paths' ends)" in (tmp_path / "log.txt").read_text()
