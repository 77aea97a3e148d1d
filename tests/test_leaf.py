"""Learned leaf values for the mpc (``uabs-eval --policy leaf``): the observation at a
path's end is the env's own observation where the path ends at the current state; with
λ = 0 the policy is the mpc action for action; with a weight it changes the moves and
keeps every guarantee; a fleet-frame network is refused with the fix."""

from __future__ import annotations

import json
import re
import shutil

import pytest
import torch
from tensordict.nn import TensorDictSequential

from tests.conftest import load_benchmark
from tests.test_observation import AREA, EGO, FLEET, MOVES, traces
from tests.test_train import smoke
from uabs_rl.cli.evaluate import main as eval_main
from uabs_rl.config import ChannelConfig, ConfigError, ScenarioConfig
from uabs_rl.env.service import move_scores, near_sets
from uabs_rl.env.uabs_env import ACTION, UABSEnv
from uabs_rl.evaluation.baselines import MPC, baseline_policy
from uabs_rl.evaluation.leaf import LeafValue
from uabs_rl.evaluation.load import evaluate_policies, load_evaluation
from uabs_rl.evaluation.planner import PlannerScore, on_lattice, one_uabs, sub_world
from uabs_rl.evaluation.predict import ConstantVelocity, TrueFuture, observed
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
    assert on_lattice(st["pos"], 20.0, 2 + env.params.map_radius)  # the table path is taken
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


class Recorder(torch.nn.Module):
    """A stand-in Q-network: records the observations it is given, returns ``q``."""

    def __init__(self, q: list[float]):
        super().__init__()
        self.q, self.seen = torch.tensor(q), []

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        self.seen.append(obs)
        return self.q.expand(*obs.shape[:-1], 4)


@pytest.mark.parametrize("h", [1, 2, 3])
def test_the_value_is_taken_at_the_observation_the_env_reaches_h_steps_on(h):
    """With the true future as the world, the observation at the end of the path the
    fleet then flies (UABS u's position after h moves, the env's own priorities and fleet
    there) is the env's own observation h steps on, bit for bit: the world's positions,
    presence, the step before (the motion half) and t + h, as LeafValue reads them."""
    env = UABSEnv(ScenarioConfig(n_uabs=6, area=AREA, episode_steps=20),
                  ChannelConfig(los_mode="los"), traces(AREA), n_envs=2, seed=3, obs=EGO)
    env.reset()
    st = env.state
    st["pos"][:] = FLEET
    for a in MOVES[:2]:
        env.math.step(st, torch.stack([a, a.flip(0)]), env.veh_pos, env.veh_present, env.rng)
    snap = {k: v.clone() for k, v in st.items()}
    w = TrueFuture()(env, h)
    for i in range(h):
        a = MOVES[(2 + i) % len(MOVES)]
        out = env.math.step(st, torch.stack([a, a.flip(0)]), env.veh_pos, env.veh_present,
                            env.rng)
    after = {k: st[k].clone() for k in ("pos", "priority")}
    for k, v in snap.items():
        st[k] = v
    u = 2
    qnet = Recorder([0.0, 1.0, 2.0, 3.0])
    value = LeafValue(env, qnet, 0.5)(after["pos"][:, u, None, None, :],
                                      after["priority"][:, None, None, :], after["pos"],
                                      torch.full((2,), u), w, snap["pos"][:, u])
    assert torch.equal(qnet.seen[0], out["observation"][:, u:u + 1])
    assert torch.equal(value, torch.full((2, 1, 1), 0.5 * 3.0))  # λ · max Q


def test_the_value_is_the_best_q_over_the_moves_legal_at_the_edges():
    """A path ending at the area's west edge: the move west (index 3) is not counted,
    however high its Q."""
    env = UABSEnv(ScenarioConfig(n_uabs=6, area=AREA, episode_steps=20),
                  ChannelConfig(los_mode="los"), traces(AREA), n_envs=2, seed=3, obs=EGO)
    env.reset()
    west = env.math.geometry.boundary_mask(torch.tensor([[[0.0, 400.0]]]))[0, 0]
    assert west.tolist() == [True, True, True, False]
    ends = torch.tensor([[[0.0, 400.0], [40.0, 400.0]]]).expand(2, 2, 2)[:, None]  # [E,1,2,2]
    prio = env.priority[:, None, None, :].expand(2, 1, 2, -1)
    w = ConstantVelocity()(env, 1)
    value = LeafValue(env, Recorder([1.0, 2.0, 3.0, 100.0]), 1.0)(
        ends, prio, env.state["pos"], torch.zeros(2, dtype=torch.long), w,
        torch.tensor([[20.0, 400.0], [20.0, 400.0]]))
    assert value[:, 0].tolist() == [[3.0, 100.0], [3.0, 100.0]]


def test_the_search_takes_the_path_whose_end_is_worth_most():
    """A leaf value of 1e6 per metre east: for each first move the path kept is the one
    ending furthest east, the first move east then straight on, and its value carries
    that end's worth (the search's own gains are a few hundred at most)."""
    env = UABSEnv(ScenarioConfig(n_uabs=6, area=AREA, episode_steps=20),
                  ChannelConfig(los_mode="los"), traces(AREA), n_envs=2, seed=3, obs=EGO)
    env.reset()
    env.state["pos"][:] = FLEET
    h = 3
    planner = PlannerScore(env, h, torch.Generator().manual_seed(0),
                           predictor=ConstantVelocity())
    planner.leaf = lambda leaf, *_: 1e6 * leaf[..., 0]
    e, m = 2, 6
    w = planner.world()
    plan = env.state["pos"][:, :, None, :].expand(e, m, h, 2).clone()
    none = torch.zeros(e, m, dtype=torch.bool)
    cover = torch.zeros(e, h, w["veh"].shape[-1], dtype=torch.bool)
    u = torch.zeros(e, dtype=torch.long)
    value, path = planner.search(env.state["pos"][:, 0], plan, none, cover, w, None, u)
    x0 = float(FLEET[0, 0])
    east = env.math.moves[:, 0].argmax()  # the move east
    assert path[:, east, -1, 0].tolist() == [x0 + 20.0 * h] * e
    assert (value[:, east] // 1e6).tolist() == [x0 + 20.0 * h] * e
    assert (path[:, :, -1, 0] == path[:, :, -1, 0].amax(-1, keepdim=True)).sum() == e


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


@pytest.mark.parametrize("h", [1, 3])
def test_leaf_values_change_the_moves_and_keep_the_guarantees(ego_run, h):
    """At H = 1 too (the search is then the first move and its leaf value)."""
    ev = load_evaluation(ego_run, "last", 3, "test")
    out = evaluate_policies(ev, (MPC, "leaf"), mpc_horizon=h, hybrid_weight=100.0)
    for rec, _ in out.values():
        assert rec["collisions"] == rec["proximity"] == rec["fallbacks"] == 0
    assert not torch.equal(out["leaf"][1].get(ACTION), out[MPC][1].get(ACTION))
    assert out["leaf"][0]["weight"] == 100.0 and out["leaf"][0]["horizon"] == h


def test_the_value_counts_only_inside_the_episode(ego_run):
    """A path ending before the episode's last step earns its value; one ending at that
    step (the episode is over there) earns none."""
    ev = load_evaluation(ego_run, "last", 2, "test")
    env = ev.evaluator.env.base_env
    env.reset()
    leaf = LeafValue(env, ev.greedy[0].module, 1.0)
    w = ConstantVelocity()(env, 2)
    e, m = env.state["pos"].shape[:2]
    ends = env.state["pos"][:, :1, None, :].expand(e, 4, 3, 2)
    prio = env.priority[:, None, None, :].expand(e, 4, 3, -1)
    u = torch.zeros(e, dtype=torch.long)
    here = env.state["pos"][:, 0]
    env.state["t"][:] = env.params.episode_steps - 3  # t + H = T - 1: one step left
    assert (leaf(ends, prio, env.state["pos"], u, w, here) != 0).all()
    env.state["t"][:] = env.params.episode_steps - 2  # t + H = T: the episode is over
    assert torch.equal(leaf(ends, prio, env.state["pos"], u, w, here), torch.zeros(e, 4, 3))


def test_uabs_eval_leaf_reports_its_settings(ego_run, tmp_path, capsys):
    out = tmp_path / "ev"
    assert eval_main([str(ego_run), "--checkpoint", "last", "--policy", "leaf",
                      "--hybrid-weight", "0.5", "--mpc-horizon", "2", "--windows", "2",
                      "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rec = json.loads((out / "eval.json").read_text())["policies"]["leaf"]
    assert (rec["horizon"], rec["predictor"], rec["weight"]) == (2, "cv", 0.5)
    assert "leaf: horizon 2, beam 16, 2 rounds, predictor cv, sees every vehicle, weight 0.5 " \
           "of the learned leaf values; " in text


def test_a_fleet_frame_network_is_refused_with_the_fix(trace_cache, tmp_path, capsys):
    run_dir = tmp_path / "run"
    run(smoke(trace_cache, "train.episodes=2", "train.trajectory_images=false"), run_dir)
    for weight in ("1", "0"):  # λ = 0 flies the mpc alone, and is refused alike
        assert eval_main([str(run_dir), "--checkpoint", "last", "--policy", "leaf",
                          "--hybrid-weight", weight, "--windows", "1",
                          "--out", str(tmp_path / "ev")]) == 2
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
    log = (tmp_path / "log.txt").read_text()
    assert "hybrid (the learned values at the paths' ends)" in log
    # its row named as what it is; one member's intervals over its windows, not zero wide
    row = next(ln for ln in log.splitlines() if ln.startswith("| leaf |"))
    low, high = map(float, row.split(" | ")[1].split("[")[1].rstrip("]").split(", "))
    assert low < high
    # a world setting the run cannot take: a ConfigError (one line, status 2, as a
    # script), before --out is made
    with pytest.raises(ConfigError, match=r"scenario=nosuch"):
        bench.main([str(ego_run), "scenario=nosuch", "--out", str(tmp_path / "no")])
    assert not (tmp_path / "no").exists()


def test_the_benchmark_flies_a_shorter_leaf_beside_the_mpc(ego_run, tmp_path):
    """``--hybrid-horizon 2``: the leaf searches 2 steps (at λ = 0 the mpc at H = 2, on
    validation and test), the mpc beside it keeps its 5."""
    bench = load_benchmark("hybrid")
    bench.main([str(ego_run), "--leaf", "--weights", "0", "--hybrid-horizon", "2",
                "--eval-windows", "2", "--out", str(tmp_path)])
    out = json.loads((tmp_path / "hybrid.json").read_text())
    assert (out["mpc_horizon"], out["hybrid_horizon"]) == (5, 2)
    fly = lambda split, windows, h: evaluate_policies(  # noqa: E731
        load_evaluation(ego_run, "best", windows, split), (MPC,), mpc_horizon=h)[MPC][0]
    short, long = fly("test", None, 2), fly("test", None, 5)
    assert short["served_fractions"] != long["served_fractions"]  # the two differ here
    assert out["weights"]["0.0"][0] == pytest.approx(
        sum(fly("eval", 2, 2)["served_fractions"]) / 2)
    assert out["policies"]["hybrid"]["served"][0] == short["served_fractions"]
    assert out["policies"]["mpc"]["served"] == long["served_fractions"]
    assert "hybrid (the learned values at the paths' ends) λ* = 0, H = 2" in (
        tmp_path / "log.txt").read_text()


def test_the_benchmark_flies_a_narrower_mpc_beside_the_leaf(ego_run, tmp_path):
    """``--mpc-beam 1 --mpc-rounds 1 --hybrid-beam 16 --hybrid-rounds 2``: the mpc beside
    the leaf keeps 1 path per first move in one pass over the fleet, the leaf (λ = 0: the
    mpc at 16 paths in two passes, on validation and test) the defaults; all recorded and
    printed."""
    bench = load_benchmark("hybrid")
    bench.main([str(ego_run), "--leaf", "--weights", "0", "--mpc-beam", "1",
                "--hybrid-beam", "16", "--mpc-rounds", "1", "--hybrid-rounds", "2",
                "--eval-windows", "2", "--out", str(tmp_path)])
    out = json.loads((tmp_path / "hybrid.json").read_text())
    assert (out["mpc_beam"], out["hybrid_beam"], out["mpc_rounds"], out["hybrid_rounds"]) == (
        1, 16, 1, 2)
    fly = lambda split, windows, b, r: evaluate_policies(  # noqa: E731
        load_evaluation(ego_run, "best", windows, split), (MPC,), beam=b, rounds=r)[MPC][0]
    narrow, wide = fly("test", None, 1, 1), fly("test", None, 16, 2)
    # the settings differ here: each one left out would show
    assert len({str(x["served_fractions"]) for x in (
        narrow, wide, fly("test", None, 1, 2), fly("test", None, 16, 1))}) == 4
    assert out["weights"]["0.0"][0] == pytest.approx(
        sum(fly("eval", 2, 16, 2)["served_fractions"]) / 2)
    assert out["policies"]["hybrid"]["served"][0] == wide["served_fractions"]
    assert out["policies"]["mpc"]["served"] == narrow["served_fractions"]
    assert "mpc H = 5 (cv, sees all, beam 1, 1 round); hybrid (the learned values at the " \
           "paths' ends) λ* = 0, beam 16, 2 rounds" in (tmp_path / "log.txt").read_text()


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("altitude", [100.0, 80.0])
def test_the_table_of_footprint_tests_gives_move_scores_own_numbers(seed, altitude):
    """Candidates up to 3 steps from the table's origin, vehicles anywhere around them
    (fractional metres, some just inside or outside a footprint's reach of a lattice
    point): each local map read from the table equals move_scores' at its points. At
    80 m a footprint spans 1.4 lattice steps from its centre (1.75 at 100 m)."""
    env = UABSEnv(ScenarioConfig(n_uabs=6, area=AREA, episode_steps=20, altitude=altitude),
                  ChannelConfig(los_mode="los"), traces(AREA), n_envs=2, seed=3, obs=EGO)
    leaf = LeafValue(env, None, 1.0)
    g = torch.Generator().manual_seed(seed)
    e, n, v, h = 2, 7, 300, 3
    origin = torch.tensor([[400.0, 400.0], [380.0, 420.0]])
    pos = origin[:, None, :] + torch.randint(-h, h + 1, (e, n, 2), generator=g) * 20.0
    veh = origin[:, :, None] + (torch.rand(e, 2, v, generator=g) - 0.5) * 240.0
    veh[:, :, :40] = origin[:, :, None] + torch.tensor([31.49, 31.51, 51.5, 50.0]).repeat(10)
    # a city's: most vehicles far from the table (left out of its sums), the windows
    # keeping different numbers (the fewer padded)
    veh[0, :, 200:] = origin[0, :, None] + (torch.rand(2, 100, generator=g) - 0.5) * 4000.0
    veh[1, :, 100:] = origin[1, :, None] + (torch.rand(2, 200, generator=g) - 0.5) * 4000.0
    present = torch.rand(e, v, generator=g) < 0.9
    prio = torch.randint(0, 30, (e, n, v), generator=g).float()
    radius = h + env.params.map_radius
    got = leaf.map_scores(pos, origin, radius, veh, present, prio)
    cand = pos[:, :, None, :] + env.math.look_offsets
    for i in range(n):
        want = move_scores(cand[:, i:i + 1], veh, present, prio[:, i], env.params.r_b,
                           env.params.n_beams)[:, 0]
        assert torch.equal(got[:, i], want)
    assert got.sum() > 0


@pytest.mark.parametrize("reach", [0, 3])
@pytest.mark.parametrize("altitude", [100.0, 80.0])
def test_the_observation_from_a_table_over_the_near_vehicles_is_the_full_ones(reach,
                                                                             altitude):
    """Vehicles over a city (most far from the UABS, the two windows keeping different
    numbers near it): the observation read from a table over the vehicles near its
    origin equals the one tested point by point over every vehicle (at 80 m a footprint
    spans 1.4 lattice steps from its centre, 1.75 at 100 m)."""
    env = UABSEnv(ScenarioConfig(n_uabs=6, area=AREA, episode_steps=20, altitude=altitude),
                  ChannelConfig(los_mode="los"), traces(AREA), n_envs=2, seed=3, obs=EGO)
    env.reset()
    leaf = LeafValue(env, None, 1.0)
    g = torch.Generator().manual_seed(reach)
    e, n, v = 2, 9, 600
    origin = FLEET[:2] + torch.tensor([[0.0, 0.0], [20.0, -40.0]])
    pos = origin[:, None, :] + torch.randint(-reach, reach + 1, (e, n, 2), generator=g) * 20.0
    spread = torch.full((v,), 3000.0)
    spread[: v // 3] = 300.0  # a third within 150 m of the UABS, the rest over 3 km
    veh = origin[:, :, None] + (torch.rand(e, 2, v, generator=g) - 0.5) * spread
    veh[1, :, : v // 3] += 1500.0  # window 1: fewer vehicles near its UABS
    prev = veh + (torch.rand(e, 2, v, generator=g) - 0.5) * 60.0
    present, prev_present = (torch.rand(2, e, v, generator=g) < 0.9).unbind(0)
    prio = torch.randint(0, 30, (e, n, v), generator=g).float()
    args = (pos, torch.tensor([0, 3]), FLEET[None].expand(e, 6, 2), torch.tensor([4, 7]),
            veh, present, prev, prev_present, prio)
    want = leaf.observation(*args)
    got = leaf.observation(*args, origin=origin, reach=reach)
    assert torch.equal(got, want)
    assert want[..., 1:10].sum() > 0  # some vehicles under the beams


def test_the_cost_benchmark_sets_a_horizon_per_policy(ego_run, capsys, monkeypatch):
    """``benchmarks/decision_cost.py --policies mpc:1 leaf:2``: each entry flown at its own
    horizon (mpc:1 serves what the 1-step mpc serves), search (``:all``), beam
    (``:b4``) and predictor (``:true``), a bad horizon refused before any loading."""
    bench = load_benchmark("decision_cost")
    asked = []

    def spy(*args, **kwargs):
        asked.append((kwargs["mpc_horizon"], kwargs["cut"], kwargs["beam"], kwargs["rounds"],
                      kwargs["predictor"]))
        return evaluate_policies(*args, **kwargs)

    monkeypatch.setattr(bench, "evaluate_policies", spy)
    bench.main([str(ego_run / "checkpoints" / "last.pt"), "--policies", "mpc:1", "leaf:2",
                "leaf:2:all", "mpc:2:b4", "leaf:2:all:b3", "mpc:2:r1:b4", "mpc:2:true:b4",
                "--weight", "1", "--turns", "1"])
    assert asked == [(1, True, None, None, "cv"), (2, True, None, None, "cv"),
                     (2, False, None, None, "cv"), (2, True, 4, None, "cv"),
                     (2, False, 3, None, "cv"), (2, True, 4, 1, "cv"), (2, True, 4, None, "true")]
    out = capsys.readouterr().out
    ev = load_evaluation(ego_run, "last", None, "test")
    one = evaluate_policies(ev, (MPC,), mpc_horizon=1)[MPC][0]["served_fraction"]
    assert "turn 1 mpc:1: " in out and f"served {100 * one:.2f} %" in out.split("\n")[0]
    assert "leaf:2:" in out and "x mpc:1)" in out
    served = re.findall(r"turn 1 leaf:2(?::all)?: .* served ([0-9.]+) %", out)
    assert len(served) == 2 and served[0] == served[1]  # every vehicle: the same moves
    for bad, says in (("mpc:0", "the horizon after ':' must be an integer >= 1"),
                      ("mpc:2:some", "only ':all' (every vehicle), ':bB'"),
                      ("mpc:2:b0", "(a beam of B >= 1 paths), ':rR'"),
                      ("mpc:2:r1:r2", "(R >= 1 passes over the fleet) and one predictor"),
                      ("mpc:2:cv:road", "and one predictor (cv, road, true, learned)"),
                      ("planner:2:learned", "the planner plans over the true future")):
        with pytest.raises(SystemExit):
            bench.main([str(ego_run), "--policies", bad])
        assert says in capsys.readouterr().err


@pytest.mark.parametrize("h", [1, 3])
def test_the_vehicles_a_value_reads_are_all_the_planner_keeps_for_it(h):
    """A city's spread (a third of the vehicles near the UABS, the rest over 4 km, the
    windows keeping different numbers): the observations at the ends of a UABS's paths
    over the vehicles ``reads`` marks (cut as the planner cuts each search's world) are
    those over every vehicle, bit for bit, and the cut leaves most vehicles out."""
    env = UABSEnv(ScenarioConfig(n_uabs=6, area=AREA, episode_steps=20),
                  ChannelConfig(los_mode="los"), traces(AREA), n_envs=2, seed=3, obs=EGO)
    env.reset()
    g = torch.Generator().manual_seed(h)
    e, a, b, v = 2, 4, 5, 400
    origin = FLEET[:2] + torch.tensor([[0.0, 0.0], [20.0, -40.0]])
    ends = origin[:, None, None, :] + torch.randint(-h, h + 1, (e, a, b, 2), generator=g) * 20.0
    spread = torch.full((v,), 4000.0)
    spread[: v // 3] = 500.0
    start = origin[:, :, None] + (torch.rand(e, 2, v, generator=g) - 0.5) * spread
    start[1, :, : v // 3] += 150.0  # window 1: fewer near
    speed = (torch.rand(e, 2, v, generator=g) - 0.5) * 30.0
    steps = [start + k * speed for k in range(h + 1)]
    w = {"veh": torch.stack(steps[1:]), "now": steps[0],
         "present": torch.rand(h + 1, e, v, generator=g) < 0.9}
    prio = torch.randint(0, 30, (e, a, b, v), generator=g).float()
    u = torch.tensor([0, 3])
    fleet = FLEET[None].expand(e, 6, 2)
    full, cut = Recorder([0.0, 1.0, 2.0, 3.0]), Recorder([0.0, 1.0, 2.0, 3.0])
    LeafValue(env, full, 1.0)(ends, prio, fleet, u, w, origin)
    leaf = LeafValue(env, cut, 1.0)
    sel, valid = near_sets(leaf.reads(origin[:, None], w))  # one UABS per window
    rows = torch.arange(e)
    wu = one_uabs(sub_world(w, sel, valid), rows, torch.zeros(e, dtype=torch.long))
    idx = sel[:, 0]
    leaf(ends, prio.gather(-1, idx[:, None, None].expand(e, a, b, -1)), fleet, u, wu, origin)
    assert torch.equal(cut.seen[0], full.seen[0])
    assert full.seen[0][..., 1:10].sum() > 0  # some vehicles under the beams
    assert idx.shape[-1] < v // 2 and not bool(valid.all())  # most left out; one padded


def test_the_tables_kept_through_a_planning_step_score_as_tables_made_anew(ego_run):
    """Inside a planning step each UABS's local-map tables are made once and read again
    in the second round (the same origin, the same world): every move scored as by a
    leaf that makes every table anew, at every step, bit for bit, with half the tables
    made; outside a step nothing is kept."""
    from tests.test_mpc import Checked

    made = []

    class Counted(LeafValue):
        def map_table(self, *args):
            made.append(self.tag)
            return super().map_table(*args)

    class Anew(Counted):
        def map_scores(self, *args, key=None):
            return super().map_scores(*args)

    ev = load_evaluation(ego_run, "last", 3, "test")
    env = ev.evaluator.env
    scores = []
    for kind, tag in ((Counted, "kept"), (Anew, "anew")):
        score = PlannerScore(env.base_env, 3, torch.Generator().manual_seed(0),
                             predictor=ConstantVelocity())
        score.leaf = kind(env.base_env, ev.greedy[0].module, 100.0)
        score.leaf.tag = tag
        scores.append(score)
    checked = Checked(*scores)
    rec, _ = ev.evaluator.evaluate(TensorDictSequential(checked, make_selector(env)),
                                   ev.episode, ev.env_steps)
    assert checked.steps == env.base_env.params.episode_steps and rec["collisions"] == 0
    assert 2 * made.count("kept") == made.count("anew") > 0
    assert scores[0].leaf.tables is None


@pytest.mark.parametrize("h", [1, 3])
def test_the_leaf_searching_the_vehicles_in_reach_scores_as_over_every_vehicle(
        ego_run, monkeypatch, h):
    """The mpc with leaf values (λ = 100: the values decide), each UABS's search cut to
    the vehicles in its reach and those its values read, scores every move as the
    search over every vehicle does, at every step, bit for bit (at H = 1 the values'
    motion half reads the vehicles at step t), with the cut made at most steps."""
    from tests.test_mpc import Checked, spy_on_the_cut

    sizes = spy_on_the_cut(monkeypatch)
    ev = load_evaluation(ego_run, "last", 3, "test")
    env = ev.evaluator.env
    scores = []
    for cut in (True, False):
        score = PlannerScore(env.base_env, h, torch.Generator().manual_seed(0),
                             predictor=ConstantVelocity())
        score.leaf, score.cut = LeafValue(env.base_env, ev.greedy[0].module, 100.0), cut
        scores.append(score)
    checked = Checked(*scores)
    rec, _ = ev.evaluator.evaluate(TensorDictSequential(checked, make_selector(env)),
                                   ev.episode, ev.env_steps)
    steps = env.base_env.params.episode_steps
    assert checked.steps == steps and rec["collisions"] == rec["proximity"] == 0
    assert len(sizes) == steps and sum(k < v for k, v in sizes) > steps // 2


def test_mpc_value_returns_are_discounted_to_the_episodes_end():
    """``benchmarks/mpc_value.py``: G_t = r_t + γ G_{t+1}, nothing after the last step."""
    bench = load_benchmark("mpc_value")
    r = torch.tensor([[[1.0], [2.0], [3.0]]])  # [E=1, T=3, M=1]
    assert bench.returns(r, 0.5)[0, :, 0].tolist() == [1 + 0.5 * 2 + 0.25 * 3, 2 + 0.5 * 3, 3]


def test_mpc_value_fit_gives_every_output_the_return_in_its_units():
    """The fit regresses the return scaled to unit spread and scales the heads back: the
    network's outputs are the return itself, each move alike."""
    from uabs_rl.algorithms.model import DuelingQNet

    bench = load_benchmark("mpc_value")
    g = torch.Generator().manual_seed(0)
    x = torch.randn(4000, 6, generator=g)
    y = 200 + 60 * x[:, 0] - 30 * x[:, 1]
    torch.manual_seed(0)
    net, r2 = bench.fit(DuelingQNet(6, 4, [32]), x, y, seed=0, steps=1500, lr=3e-3, batch=256)
    assert r2 > 0.97
    with torch.no_grad():
        q = net(x[:500])
    assert (q.mean(-1) - y[:500]).abs().mean() < 0.1 * y.std()
    assert (q.amax(-1) - q.amin(-1)).mean() < 0.05 * y.std()


def test_mpc_value_writes_members_that_fly_as_runs(ego_run, tmp_path, capsys):
    """Each member a copy of the template run whose best.pt holds the fitted network;
    the template's own files untouched; uabs-eval's loader takes a member; an --out
    inside the template, or one holding files the script did not write, is refused."""
    bench = load_benchmark("mpc_value")
    before = (ego_run / "checkpoints" / "best.pt").read_bytes()
    out = tmp_path / "values"
    bench.main([str(ego_run), "--out", str(out), "--members", "2", "--fleets", "3",
                "--windows", "2", "--steps", "20", "--batch", "64"])
    assert (ego_run / "checkpoints" / "best.pt").read_bytes() == before
    fit = json.loads((out / "fit.json").read_text())
    assert [m["seed"] for m in fit["members"]] == [0, 1] and fit["samples"] > 0
    template = torch.load(ego_run / "checkpoints" / "best.pt", weights_only=False)
    for s in (0, 1):
        member = out / f"seed={s}"
        state = torch.load(member / "checkpoints" / "best.pt", weights_only=False)
        assert state["counters"] == template["counters"]
        assert not torch.equal(state["learner"]["qnet"]["value.weight"],
                               template["learner"]["qnet"]["value.weight"])
        ev = load_evaluation(member, "best", 1, "test")
        assert ev.cfg.obs.name == "egocentric"
    for m in fit["members"]:  # R² <= 1 on the windows left out (NaN where none was)
        r2 = m["r2_windows_left_out"]
        assert r2 <= 1 if r2 == r2 else m["windows_left_out"] == 0
    with pytest.raises(SystemExit):
        bench.main([str(ego_run), "--out", str(ego_run / "values"), "--members", "1"])
    assert "lies inside the template run" in capsys.readouterr().err
    # a folder it did not write (a trained population): refused, its members kept
    other = tmp_path / "population"
    shutil.copytree(ego_run, other / "seed=0")
    with pytest.raises(SystemExit):
        bench.main([str(ego_run), "--out", str(other), "--members", "1"])
    assert "holds files this script did not write" in capsys.readouterr().err
    assert (other / "seed=0" / "checkpoints" / "best.pt").read_bytes() == before
