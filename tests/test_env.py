"""UABSEnv: specs, determinism, resets, masks, rewards and the P_g bookkeeping."""

from __future__ import annotations

import copy

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from uabs_rl.config import ChannelConfig, ConfigError, ObsConfig, ScenarioConfig
from uabs_rl.env import service
from uabs_rl.env.channel import los_probability
from uabs_rl.env.params import EnvParams
from uabs_rl.env.uabs_env import ACTION, DIAG, MASK, POSITION, REWARD, StepMath, UABSEnv

EP = 20  # episode length for the small traces (60 s)


def scenario(small_traces_cfg, **kw) -> ScenarioConfig:
    sc = copy.deepcopy(small_traces_cfg.scenario)
    sc.episode_steps = EP
    for k, v in kw.items():
        setattr(sc, k, v)
    return sc


def random_legal(td):
    mask = td[MASK]
    flat = mask.reshape(-1, mask.shape[-1]).float()
    a = torch.multinomial(flat, 1).reshape(mask.shape[:-1])
    td.set(ACTION, a)
    return td


def rollout(env, steps, seed):
    env.set_seed(seed)
    torch.manual_seed(seed)
    return env.rollout(steps, policy=random_legal, break_when_any_done=False)


@pytest.mark.parametrize("n_envs", [1, 8])
@pytest.mark.parametrize("m", [1, 3, 5])
def test_check_env_specs(small_traces_cfg, train, n_envs, m):
    env = UABSEnv(scenario(small_traces_cfg, n_uabs=m), ChannelConfig(), train, n_envs=n_envs)
    check_env_specs(env, seed=0)
    assert env.observation_spec["agents", "observation"].shape == (n_envs, m, 3 + 2 * m + 9)


def test_seeded_rollouts_are_identical(small_traces_cfg, train):
    env = UABSEnv(scenario(small_traces_cfg), ChannelConfig(), train, n_envs=4)
    a, b = rollout(env, 2 * EP, seed=3), rollout(env, 2 * EP, seed=3)
    assert (a == b).all()
    c = rollout(env, 2 * EP, seed=4)
    assert not torch.equal(a["next", "agents", "reward"], c["next", "agents", "reward"])


def test_boundary_mask_keeps_every_uabs_inside(small_traces_cfg, train):
    sc = scenario(small_traces_cfg)
    env = UABSEnv(sc, ChannelConfig(), train, n_envs=16)
    td = rollout(env, 3 * EP, seed=0)
    pos = td["next", POSITION]
    assert (pos[..., 0] >= 0).all() and (pos[..., 0] <= sc.area.width).all()
    assert (pos[..., 1] >= 0).all() and (pos[..., 1] <= sc.area.height).all()
    assert (td["next", DIAG, "illegal_moves"] == 0).all()
    assert td[MASK].any(-1).all()  # never an all-False row
    # on the lattice: pitch 20 m, centred (5 m from the edges in 350 x 170)
    assert torch.allclose(torch.remainder(pos - 5.0, 20.0), torch.zeros_like(pos), atol=1e-4)


def test_an_illegal_move_is_refused_and_counted(small_traces_cfg, train):
    env = UABSEnv(scenario(small_traces_cfg, n_uabs=1), ChannelConfig(), train, n_envs=1)
    td = env.reset()
    env.state["pos"][:] = torch.tensor([[[5.0, 5.0]]])  # lower-left lattice corner
    td.set(ACTION, torch.tensor([[3]]))  # left: out of the area
    out = env.step(td)
    assert out["next", POSITION].tolist() == [[[5.0, 5.0]]]
    assert out["next", DIAG, "illegal_moves"].item() == 1
    assert out["next", MASK].tolist() == [[[True, True, False, False]]]


def test_partial_reset_resets_only_flagged_envs(small_traces_cfg, train):
    env = UABSEnv(scenario(small_traces_cfg), ChannelConfig(), train, n_envs=4)
    env.set_seed(0)
    td = env.reset()
    for _ in range(5):
        td = env.step(random_legal(td))["next"]
    before = {k: v.clone() for k, v in env.state.items()}
    flag = torch.tensor([True, False, True, False])
    out = env.reset(td.set("_reset", flag[:, None]))
    st = env.state
    assert st["t"].tolist() == [0, 5, 0, 5]
    for k in ("pos", "priority", "ep_return", "sim", "start"):
        assert torch.equal(st[k][~flag], before[k][~flag]), k
    assert (st["ep_return"][flag] == 0).all()
    assert torch.equal(out[POSITION][~flag], before["pos"][~flag])


def test_start_positions(small_traces_cfg, train):
    sc = scenario(small_traces_cfg, n_uabs=4)
    p = EnvParams.from_config(sc, ChannelConfig())
    mth = StepMath(p, torch.device("cpu"))
    pos = mth.geometry.start_positions(500, torch.Generator().manual_seed(0))
    ring = pos[:, 1:]
    on_edge = (ring[..., 0] == 5) | (ring[..., 0] == 345) | (ring[..., 1] == 5) \
        | (ring[..., 1] == 165)
    assert on_edge.all()  # the others on the perimeter (lattice ring)
    d_inner = (pos[:, :1] - ring).norm(dim=-1).amin(-1)
    assert (d_inner >= p.d_th).float().mean() > 0.99  # safe start (best of 32 draws)
    assert pos[:, 0].std(0).min() > 30  # the inner one is spread over the area


def test_reward_cases_from_constructed_positions(small_traces_cfg):
    p = EnvParams.from_config(scenario(small_traces_cfg), ChannelConfig())
    mth = StepMath(p, torch.device("cpu"))
    b = torch.tensor([[[1.0] * 9, [2.0] * 9, [3.0] * 9]])  # ||b||_1 = 9, 18, 27
    far = torch.tensor([[[0.0, 0.0], [200.0, 0.0], [0.0, 150.0]]])
    near = torch.tensor([[[0.0, 0.0], [50.0, 0.0], [300.0, 150.0]]])  # 50 m < d_th
    hit = torch.tensor([[[0.0, 0.0], [0.5, 0.0], [300.0, 150.0]]])  # 0.5 m < 1 m
    r, coll, prox = mth.rewards(b, mth.geometry.pair_distances(far))  # (a)
    assert r.tolist() == [[9.0, 18.0, 27.0]] and coll.item() == 0 and prox.item() == 0
    r, coll, prox = mth.rewards(b, mth.geometry.pair_distances(near))  # (b)
    assert r.tolist() == [[-10.0, -10.0, 27.0]] and coll.item() == 0 and prox.item() == 1
    r, coll, prox = mth.rewards(b, mth.geometry.pair_distances(hit))  # (c): collision wins
    assert r.tolist() == [[-1000.0, -1000.0, 27.0]] and coll.item() == 1 and prox.item() == 1


def test_collision_through_the_env(small_traces_cfg, train):
    """Two UABS moved into the same cell: −λ_c for both, one collision event."""
    env = UABSEnv(scenario(small_traces_cfg, n_uabs=2), ChannelConfig(), train, n_envs=1)
    td = env.reset()
    env.state["pos"][:] = torch.tensor([[[105.0, 85.0], [145.0, 85.0]]])
    td.set(ACTION, torch.tensor([[1, 3]]))  # right, left: both end at (125, 85)
    out = env.step(td)["next"]
    assert out[REWARD].squeeze(-1).tolist() == [[-1000.0, -1000.0]]
    assert out[DIAG, "collisions"].item() == 1 and out[DIAG, "ep_collisions"].item() == 1
    assert out[DIAG, "min_pair_distance"].item() == 0.0


def test_swap_is_seen_by_the_closest_approach(small_traces_cfg, train):
    """Two UABS swapping cells never share a sampled position but cross on the way."""
    env = UABSEnv(scenario(small_traces_cfg, n_uabs=2), ChannelConfig(), train, n_envs=1)
    td = env.reset()
    env.state["pos"][:] = torch.tensor([[[105.0, 85.0], [125.0, 85.0]]])
    out = env.step(td.set(ACTION, torch.tensor([[1, 3]])))["next"]
    assert out[DIAG, "min_pair_distance"].item() == 20.0
    assert out[DIAG, "closest_approach"].item() == 0.0


def _service_state(n_veh: int, n: int) -> dict[str, torch.Tensor]:
    return {"t": torch.zeros(1, dtype=torch.long), "priority": torch.zeros(1, n_veh),
            "served_count": torch.zeros(1, n_veh, dtype=torch.long),
            "window_full": torch.zeros(1, n_veh, dtype=torch.bool),
            "prev_present": torch.zeros(1, n_veh, dtype=torch.bool),
            "n_windows": torch.zeros(1, n_veh), "ns_hist": torch.zeros(1, n_veh, n + 1)}


def test_priorities_and_pg_over_a_known_served_pattern(small_traces_cfg):
    sc = scenario(small_traces_cfg, window_steps=4, nhat_s=2)
    mth = StepMath(EnvParams.from_config(sc, ChannelConfig()), torch.device("cpu"))
    st = _service_state(3, 4)
    served = torch.tensor([  # t = 0..7, vehicles 0, 1, 2
        [1, 0, 1], [1, 0, 1], [0, 0, 1], [1, 0, 0],
        [1, 0, 1], [1, 1, 1], [1, 0, 1], [1, 0, 1]], dtype=torch.bool)
    present = torch.ones(8, 3, dtype=torch.bool)
    present[1, 2] = False  # vehicle 2 misses a step of window 1: that window does not count
    priorities = []
    for t in range(8):
        st["t"] = torch.tensor([t])
        service.update_service(st, served[t][None] & present[t][None], present[t][None],
                               mth.p.window_steps)
        priorities.append(st["priority"][0].tolist())
    # vehicle 0: p = 1 at t = 0 (window start), +1 when served: 2, 2, 3; new window: 1, 2, 3, 4
    assert [p[0] for p in priorities] == [1, 2, 2, 3, 1, 2, 3, 4]
    assert [p[1] for p in priorities] == [1, 1, 1, 1, 1, 2, 2, 2]
    # vehicle 2: absent at t = 1 (p = 0), back at t = 2 (p = 1 again)
    assert [p[2] for p in priorities] == [1, 0, 1, 1, 1, 2, 3, 4]
    # N_s per window: v0 = 3, 4; v1 = 0, 1; v2 = (not counted), 4
    assert st["n_windows"][0].tolist() == [2, 2, 1]
    curve = service.pg_curve(st["n_windows"], st["ns_hist"])[0]
    # N̂_s = 1: (2/2 + 1/2 + 1/1) / 3 = 0.8333; 2: (1 + 0 + 1)/3; 3: (1 + 0 + 1)/3;
    # 4: (1/2 + 0 + 1)/3 = 0.5
    assert curve.tolist() == pytest.approx([2.5 / 3, 2 / 3, 2 / 3, 0.5])


def test_pg_curve_of_a_constructed_served_matrix(small_traces_cfg):
    sc = scenario(small_traces_cfg, window_steps=2, nhat_s=1)
    mth = StepMath(EnvParams.from_config(sc, ChannelConfig()), torch.device("cpu"))
    st = _service_state(2, 2)
    served = torch.tensor([[1, 1], [1, 0], [0, 0], [1, 1]], dtype=torch.bool)
    for t in range(4):
        st["t"] = torch.tensor([t])
        service.update_service(st, served[t][None], torch.ones(1, 2, dtype=torch.bool),
                               mth.p.window_steps)
    # v0: N_s = 2, 1 -> share(≥1) = 1, share(≥2) = 0.5 ; v1: N_s = 1, 1 -> 1, 0
    assert service.pg_curve(st["n_windows"], st["ns_hist"])[0].tolist() == [1.0, 0.25]


def test_pg_curve_is_its_exact_value_rounded_once_whatever_the_vehicles_order():
    """P_g is a mean of per-GUE shares with different denominators: summed in float32,
    the order of the sum (the compiled evaluation's kernels against eager ones) showed in
    the last bit. Summed in float64 and rounded once, it is the exact fraction rounded
    to float32, for any order of the vehicles."""
    from fractions import Fraction

    gen = torch.Generator().manual_seed(0)
    e, v, n = 6, 300, 10
    n_windows = torch.randint(0, 9, (e, v), generator=gen)
    ns_hist = torch.zeros(e, v, n + 1)
    for w in range(8):  # up to 8 windows, each a served count in 0..n
        ns = torch.randint(0, n + 1, (e, v, 1), generator=gen)
        ns_hist.scatter_add_(2, ns, (n_windows > w).float()[..., None])
    n_windows = n_windows.float()
    curve = service.pg_curve(n_windows, ns_hist)
    assert curve.dtype == torch.float32
    for perm in (torch.randperm(v, generator=gen) for _ in range(5)):
        assert torch.equal(curve, service.pg_curve(n_windows[:, perm], ns_hist[:, perm]))
    for i in range(e):
        counted = [g for g in range(v) if n_windows[i, g] > 0]
        for k in range(1, n + 1):
            exact = sum(Fraction(int(ns_hist[i, g, k:].sum()), int(n_windows[i, g]))
                        for g in counted) / len(counted)
            assert curve[i, k - 1].item() == torch.tensor(float(exact)).item()


def test_episode_ends_at_T_and_tallies(small_traces_cfg, train):
    env = UABSEnv(scenario(small_traces_cfg), ChannelConfig(), train, n_envs=2)
    td = rollout(env, EP, seed=1)
    done = td["next", "done"].squeeze(-1)
    assert not done[:, :-1].any() and done[:, -1].all()
    assert torch.equal(td["next", "agents", "terminated"][:, -1],
                       torch.ones(2, 3, 1, dtype=torch.bool))
    ret = td["next", REWARD].sum((1, 2, 3))
    assert torch.allclose(td["next", DIAG, "ep_return"][:, -1], ret)
    # b_t (the reward's source) sums the priorities of present vehicles under the beams
    assert (td["next", "agents", "beam_priority"] >= 0).all()
    assert td["next", DIAG, "served_fraction"].max() <= 1.0


def test_eval_mode_walks_fixed_windows(small_traces_cfg, held_out):
    env = UABSEnv(scenario(small_traces_cfg), ChannelConfig(), held_out, n_envs=2,
                  mode="eval", n_eval_windows=2)
    a = rollout(env, EP, seed=0)
    b = rollout(env, EP, seed=0)
    assert (a == b).all()
    assert env.eval_windows.tolist() == [[0, 0], [0, EP + 1]]
    with pytest.raises(ConfigError, match="n_eval_windows"):
        UABSEnv(scenario(small_traces_cfg), ChannelConfig(), held_out, n_envs=2,
                mode="eval", n_eval_windows=3)


def test_traces_too_short_for_an_episode(small_traces_cfg, train):
    with pytest.raises(ConfigError, match="episode_steps"):
        UABSEnv(scenario(small_traces_cfg, episode_steps=80), ChannelConfig(), train)


@pytest.mark.parametrize("key,value", [("n_uabs", 0), ("speed", -1.0), ("nhat_s", 11)])
def test_invalid_env_values_name_the_key(small_traces_cfg, train, key, value):
    with pytest.raises(ConfigError, match=f"scenario.{key}"):
        UABSEnv(scenario(small_traces_cfg, **{key: value}), ChannelConfig(), train)


def test_los_modes_and_outside_gain(small_traces_cfg, train):
    served = {}
    for mode, outside in [("los", None), ("expected", None), ("sample", None),
                          ("sample", 0.0)]:
        chn = ChannelConfig(los_mode=mode, outside_beam_gain_db=outside)
        env = UABSEnv(scenario(small_traces_cfg), chn, train, n_envs=4)
        served[(mode, outside)] = rollout(env, EP, 0)["next", DIAG, "served_fraction"].mean()
    # ideal beams at these powers: everyone inside a footprint is served whatever the LoS
    assert served[("los", None)] == served[("expected", None)] == served[("sample", None)]
    # the literal "0 dB outside the beam" reading serves far more vehicles
    assert served[("sample", 0.0)] > 3 * served[("sample", None)]


@pytest.mark.parametrize("los_mode", ["los", "expected"])
@pytest.mark.parametrize("threshold", [-13.7, 30.0, 45.0])
def test_service_radius_equals_the_snr_rule(small_traces_cfg, los_mode, threshold):
    """The distance-threshold shortcut gives exactly the SNR >= SNR_th decisions."""
    chn = ChannelConfig(los_mode=los_mode, snr_threshold_db=threshold)
    mth = StepMath(EnvParams.from_config(scenario(small_traces_cfg), chn), torch.device("cpu"))
    radii = mth.links.radii[mth.p.gain_db]
    d2 = torch.linspace(0.0, 400.0, 20001) ** 2
    gen = torch.Generator().manual_seed(0)
    by_snr = mth.links.snr(d2, gen) + mth.p.gain_db >= threshold
    by_radius = radii.served(d2, gen)
    assert torch.equal(by_snr, by_radius)
    if threshold == 45.0:  # a real cut inside the range: both rules see it
        assert by_snr.any() and not by_snr.all()


def test_sampled_los_draws_only_where_they_matter(small_traces_cfg):
    defaults = StepMath(EnvParams.from_config(scenario(small_traces_cfg), ChannelConfig()),
                        torch.device("cpu"))
    assert defaults.links.always_served  # ideal beams at Table 1 powers: footprint = service
    chn = ChannelConfig(snr_threshold_db=45.0)  # LoS reaches farther than NLoS now
    mth = StepMath(EnvParams.from_config(scenario(small_traces_cfg), chn), torch.device("cpu"))
    radii = mth.links.radii[mth.p.gain_db]
    assert radii.needs_draw and radii.r_nlos < radii.r_los
    d = torch.tensor([radii.r_nlos * 0.99, (radii.r_nlos + radii.r_los) / 2,
                      radii.r_los * 1.01]).repeat(4000)
    served = radii.served(d ** 2, torch.Generator().manual_seed(0)).view(4000, 3).float()
    rho = los_probability(d[1:2]).item()
    assert served[:, 0].all() and not served[:, 2].any()
    assert abs(served[:, 1].mean().item() - rho) < 0.03  # Bernoulli(ρ_L) in between


def test_lookahead_observation_scores_each_candidate_move(small_traces_cfg):
    """obs.lookahead: one vehicle 40 m east of the UABS is under its footprints
    after a move right (20 m off) and after two (0 m), and nowhere else."""
    from uabs_rl.traces.cache import TraceSet

    steps = 30
    pos = torch.zeros(1, steps, 1, 2)
    pos[..., 0], pos[..., 1] = 145.0, 85.0
    traces = TraceSet(pos, torch.ones(1, steps, 1, dtype=torch.bool), {"split": "x", "dt": 1.0})
    sc = scenario(small_traces_cfg, n_uabs=1)
    env = UABSEnv(sc, ChannelConfig(), traces, n_envs=1, seed=0, obs=ObsConfig(lookahead=True))
    assert env.params.obs_dim == 3 + 2 + 9 + 8
    env.reset()
    st = env.state
    st["pos"][:] = torch.tensor([[[105.0, 85.0]]])
    env.math.observe(st, env.veh_pos, env.veh_present, env.rng)
    look = st["look"][0, 0]
    prio = max(1.0, float(st["priority"][0, 0]))
    # order: up, right, down, left, then 2 x up, 2 x right, 2 x down, 2 x left
    assert look.tolist() == [0.0, prio, 0.0, 0.0, 0.0, prio, 0.0, 0.0]
    obs = env.math.observation(st["pos"], st["t"], st["b"], st["look"])
    assert torch.allclose(obs[0, 0, -8:], look / ObsConfig().priority_scale)


def observed_at(env: UABSEnv, uabs: list[float], t: int) -> dict[str, torch.Tensor]:
    """The state of ``env`` (one env, one UABS) after observing step ``t`` of its window
    starting at 0 with the UABS at ``uabs``."""
    env.reset()
    st = env.state
    st["pos"][:] = torch.tensor([[uabs]])
    st["start"][:], st["t"][:] = 0, t
    env.math.observe(st, env.veh_pos, env.veh_present, env.rng)
    return st


def test_motion_observation_scores_moves_at_extrapolated_positions(small_traces_cfg):
    """obs.motion: a vehicle that moved 40 m east in the last step is scored
    where it will be if it keeps moving (40 m east of the UABS: only the move right
    reaches it), while the plain lookahead scores it where it is (under the UABS: every
    move reaches it). At the window's first step there is no last move."""
    from uabs_rl.traces.cache import TraceSet

    steps = 30
    pos = torch.zeros(1, steps, 1, 2)
    pos[..., 1] = 85.0
    pos[0, :5, 0, 0], pos[0, 5:, 0, 0] = 65.0, 105.0
    traces = TraceSet(pos, torch.ones(1, steps, 1, dtype=torch.bool), {"split": "x", "dt": 1.0})
    sc = scenario(small_traces_cfg, n_uabs=1)
    with pytest.raises(ConfigError, match="obs.motion needs obs.lookahead=true"):
        UABSEnv(sc, ChannelConfig(), traces, n_envs=1, seed=0, obs=ObsConfig(motion=True))
    env = UABSEnv(sc, ChannelConfig(), traces, n_envs=1, seed=0,
                  obs=ObsConfig(lookahead=True, motion=True))
    assert env.params.obs_dim == 3 + 2 + 9 + 8 + 4
    st = observed_at(env, [105.0, 85.0], 5)
    p = max(1.0, float(st["priority"][0, 0]))
    # up, right, down, left (then 2 steps each); then the extrapolated up, right, down, left
    assert st["look"][0, 0].tolist() == [p, p, p, p, 0.0, 0.0, 0.0, 0.0, 0.0, p, 0.0, 0.0]
    st["start"][:], st["t"][:] = 5, 0  # the window's first step: no last move
    env.math.observe(st, env.veh_pos, env.veh_present, env.rng)
    look = st["look"][0, 0]
    assert torch.equal(look[8:], look[:4])


def test_motion_steps_score_k_moves_at_k_steps_ahead(small_traces_cfg):
    """obs.motion_steps = 3: a vehicle 60 m west of the UABS, moving 40 m east per step,
    is under its footprints after k moves right at its position extrapolated k steps
    (45 + 40k m against 105 + 20k m: 20 m off, then 0), and nowhere else (extrapolated
    k − 1 steps it would be under the left moves' footprints at k = 2 and under none at
    k = 3); a vehicle standing under the UABS is under none of them (the k moves leave it
    20k m behind)."""
    from uabs_rl.traces.cache import TraceSet

    steps = 30
    pos = torch.zeros(1, steps, 1, 2)
    pos[..., 1] = 85.0
    pos[0, :, 0, 0] = 45.0 + 40.0 * (torch.arange(steps) - 5)  # at t = 5: 45 m, 40 m/s
    traces = TraceSet(pos, torch.ones(1, steps, 1, dtype=torch.bool), {"split": "x", "dt": 1.0})
    sc = scenario(small_traces_cfg, n_uabs=1)
    obs = ObsConfig(lookahead=True, motion=True, motion_steps=3)
    env = UABSEnv(sc, ChannelConfig(), traces, n_envs=1, seed=0, obs=obs)
    assert env.params.obs_dim == 3 + 2 + 9 + 8 + 4 + 2 * 4
    st = observed_at(env, [105.0, 85.0], 5)
    p = max(1.0, float(st["priority"][0, 0]))
    # k = 2 then k = 3: up, right, down, left
    assert st["look"][0, 0, 12:].tolist() == [0.0, p, 0.0, 0.0] * 2
    obs_vec = env.math.observation(st["pos"], st["t"], st["b"], st["look"])
    assert torch.equal(obs_vec[0, 0, -8:], st["look"][0, 0, 12:] / obs.priority_scale)
    pos[0, :, 0, 0] = 105.0  # the same vehicle standing still
    still = TraceSet(pos, torch.ones(1, steps, 1, dtype=torch.bool), {"split": "x", "dt": 1.0})
    env = UABSEnv(sc, ChannelConfig(), still, n_envs=1, seed=0, obs=obs)
    st = observed_at(env, [105.0, 85.0], 5)
    assert st["look"][0, 0, 12:].tolist() == [0.0] * 8


def test_motion_steps_see_what_the_mpc_predicts(small_traces_cfg, train):
    """The k-step scores are the move scores at the vehicles the mpc's constant-velocity
    predictor puts k steps ahead (the same extrapolation, bit for bit), on SUMO traces
    at every step of an episode; motion_steps = 1 is obs.motion's observation."""
    from uabs_rl.evaluation.predict import ConstantVelocity

    sc = scenario(small_traces_cfg, n_uabs=2)
    k_max = 4
    env = UABSEnv(sc, ChannelConfig(), train, n_envs=3, seed=1,
                  obs=ObsConfig(lookahead=True, motion=True, motion_steps=k_max))
    one = UABSEnv(sc, ChannelConfig(), train, n_envs=3, seed=1,
                  obs=ObsConfig(lookahead=True, motion=True))
    td, td1 = env.reset(), one.reset()
    for _ in range(EP - 1):
        assert torch.equal(td[("agents", "observation")][..., :-4 * (k_max - 1)],
                           td1[("agents", "observation")])
        st = env.state
        veh = ConstantVelocity()(env, k_max)["veh"]  # [H, E, 2, V]
        present = service.vehicles_at(st, env.veh_pos, env.veh_present)[1]
        for k in range(2, k_max + 1):
            cand = st["pos"][:, :, None, :] + k * env.math.moves
            want = service.move_scores(cand, veh[k - 1], present, st["priority"],
                                       env.params.r_b, env.params.n_beams)
            assert torch.equal(st["look"][..., 12 + 4 * (k - 2): 16 + 4 * (k - 2)], want)
        td1.set(ACTION, random_legal(td).get(ACTION).clone())
        td = env.step(td)["next"]
        td1 = one.step(td1)["next"]
    assert not (env.state["look"][..., 12:] == 0).all()  # something was scored


@pytest.mark.parametrize("obs,why", [
    (ObsConfig(lookahead=True, motion_steps=3), "must be 1 unless obs.motion=true"),
    (ObsConfig(frame="egocentric", motion=True, motion_steps=2), "with obs.frame=fleet"),
    (ObsConfig(lookahead=True, motion=True, motion_steps=0), "must be in \\[1, 1000\\]")])
def test_motion_steps_refused_where_they_mean_nothing(small_traces_cfg, train, obs, why):
    with pytest.raises(ConfigError, match=f"obs.motion_steps .*{why}"):
        UABSEnv(scenario(small_traces_cfg), ChannelConfig(), train, n_envs=1, seed=0, obs=obs)
