"""Anti-collision: the safety guarantee over random states, masks, exploration, ranks."""

from __future__ import annotations

import copy
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from tests.conftest import another_thread_count
from tests.test_algorithms import learner_config
from uabs_rl.algorithms import ALGORITHMS
from uabs_rl.config import ChannelConfig, ConfigError, MaskingConfig, MaskingMode, ScenarioConfig
from uabs_rl.env.params import EnvParams
from uabs_rl.env.uabs_env import (
    ACTION,
    BEAM_PRIORITY,
    DIAG,
    FALLBACK,
    MASK,
    POSITION,
    REWARD,
    StepMath,
)
from uabs_rl.safety.make import make_env, make_selector
from uabs_rl.safety.modules import DirectEnv
from uabs_rl.safety.rules import (
    ACTION_VALUE,
    COLLIDERS,
    RANK_ORDER,
    RULES,
    SAFETY_TOLERANCE,
    apply_fallback,
    epsilon_greedy,
    flat_unsafe,
    make_rule,
    potential_colliders,
    rank_order,
    rank_select,
    uniforms,
)

E = 64  # random states per hypothesis example
# every registered masking mode (a rule of yours among them, docs/code.md "Extending"),
# and those that mask collisions: the safety tests below run each
MODES = sorted(m.value for m in RULES)
COLLISION_MODES = sorted(m.value for m, rule in RULES.items() if rule.masks_collisions)


def step_math(width: float, height: float, m: int) -> StepMath:
    sc = ScenarioConfig(n_uabs=m)
    sc.area.width, sc.area.height = width, height
    return StepMath(EnvParams.from_config(sc, ChannelConfig()), torch.device("cpu"))


def random_state(mth: StepMath, gen: torch.Generator, lattice: bool):
    """Positions anywhere in the area (safe or not), Q-values and beam scores."""
    m = mth.p.n_uabs
    if lattice:
        ix = torch.randint(0, int(mth.geometry.lattice_n[0]), (E, m), generator=gen)
        iy = torch.randint(0, int(mth.geometry.lattice_n[1]), (E, m), generator=gen)
        pos = mth.geometry.lattice_point(ix.float(), iy.float())
    else:
        pos = torch.rand(E, m, 2, generator=gen) * mth.geometry.area
    q = torch.randn(E, m, 4, generator=gen)
    b = torch.rand(E, m, 9, generator=gen).round() * torch.randint(0, 5, (E, m, 1), generator=gen)
    return pos, q, b


def select(mode: str, mth: StepMath, pos, q, b, eps, gen):
    """One decision of the whole pipeline: transform rules + selector. Returns the
    action, the stored mask and the fallback flags."""
    p = mth.p
    boundary = mth.geometry.boundary_mask(pos)
    if mode == "flat":
        unsafe, dist = flat_unsafe(pos, mth.moves, p.d_th + p.step_m)
        mask, fb = apply_fallback(boundary & ~unsafe, boundary, dist)
        return epsilon_greedy(q, mask, eps, draws(mask, gen)), mask, fb
    order = rank_order(b)
    coll = potential_colliders(pos, p.d_th + 2 * p.step_m)
    return rank_select(q, boundary, pos, order, coll, mth.moves, p.d_th, eps, draws(boundary, gen))


def draws(mask, gen):
    return uniforms(mask.shape[:-1], gen, mask.device)


AREAS = st.sampled_from([(350.0, 170.0), (200.0, 120.0), (160.0, 100.0)])


@settings(max_examples=60, deadline=None)
@given(mode=st.sampled_from(["flat", "rank"]), m=st.integers(2, 6), area=AREAS,
       lattice=st.booleans(), eps=st.floats(0.0, 1.0), seed=st.integers(0, 2**31 - 1))
def test_literal_masks_fall_back_only_where_they_must(mode, m, area, lattice, eps, seed):
    """The paper's literal rules (masking.recoverable=false) carry no guarantee: from an
    arbitrary state a pair may end closer than d_th, but only with a counted fallback.
    The guarantee of the recoverable rules is tested below."""
    mth = step_math(*area, m)
    gen = torch.Generator().manual_seed(seed)
    pos, q, b = random_state(mth, gen, lattice)
    action, mask, fb = select(mode, mth, pos, q, b, eps, gen)
    assert mask.any(-1).all(), "a mask row is all False"
    assert mask.gather(-1, action[..., None]).all(), "an executed action is illegal"
    assert mth.geometry.boundary_mask(pos).gather(-1, action[..., None]).all()
    new = pos + mth.moves[action]
    close = mth.geometry.pair_distances(new).flatten(1).amin(-1) < mth.p.d_th  # [E]
    assert not (close & ~fb.any(-1)).any(), "closer than d_th without a counted fallback"


@settings(max_examples=40, deadline=None)
@given(mode=st.sampled_from(["penalty", "flat", "rank"]), m=st.integers(1, 5),
       seed=st.integers(0, 2**31 - 1))
def test_exploration_is_uniform_over_legal_actions_and_greedy_is_best_legal(mode, m, seed):
    mth = step_math(350.0, 170.0, m)
    gen = torch.Generator().manual_seed(seed)
    pos, q, b = random_state(mth, gen, True)
    if mode == "penalty":
        mask = mth.geometry.boundary_mask(pos)
        greedy = epsilon_greedy(q, mask, 0.0, draws(mask, gen))
    else:
        greedy, mask, _ = select(mode, mth, pos, q, b, 0.0, gen)
    best = q.masked_fill(~mask, -math.inf).argmax(-1)
    assert torch.equal(greedy, best)


def test_random_choice_is_uniform_over_the_legal_actions():
    mask = torch.tensor([[True, False, True, True]]).expand(30000, 4)
    u = draws(mask, torch.Generator().manual_seed(0))
    a = epsilon_greedy(torch.zeros(30000, 4), mask, 1.0, u)
    counts = torch.bincount(a, minlength=4).float() / 30000
    assert counts[1] == 0
    assert torch.allclose(counts[[0, 2, 3]], torch.full((3,), 1 / 3), atol=0.015)


def test_top_ranked_agent_takes_its_unmasked_greedy_action():
    mth = step_math(350.0, 170.0, 4)
    gen = torch.Generator().manual_seed(0)
    pos, q, b = random_state(mth, gen, True)
    action, mask, _ = select("rank", mth, pos, q, b, 0.0, gen)
    top = rank_order(b)[:, 0]
    rows = torch.arange(E)
    boundary = mth.geometry.boundary_mask(pos)
    expected = q[rows, top].masked_fill(~boundary[rows, top], -math.inf).argmax(-1)
    assert torch.equal(action[rows, top], expected)
    assert torch.equal(mask[rows, top], boundary[rows, top])


def test_swapping_scores_swaps_who_yields():
    """Two UABS 80 m apart both want to move towards each other: the higher-ranked one
    does, the other may not (it would end 40 m away) and moves elsewhere."""
    mth = step_math(350.0, 170.0, 2)
    pos = torch.tensor([[[125.0, 85.0], [205.0, 85.0]]])
    q = torch.tensor([[[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]])  # right, left
    hi0 = torch.tensor([[[5.0] * 9, [1.0] * 9]])
    a, mask, fb = select("rank", mth, pos, q, hi0, 0.0, None)
    assert a.tolist() == [[1, 1]] and mask[0, 1, 3].item() is False and not fb.any()
    a, mask, fb = select("rank", mth, pos, q, hi0.flip(1), 0.0, None)
    assert a.tolist() == [[3, 3]] and mask[0, 0, 1].item() is False and not fb.any()


def test_ties_rank_the_lower_index_first():
    b = torch.tensor([[[1.0] * 9, [2.0] * 9, [1.0] * 9, [2.0] * 9]])
    assert rank_order(b).tolist() == [[1, 3, 0, 2]]


def test_fallback_takes_the_boundary_legal_action_farthest_from_the_others():
    # agent 0 boxed in the lower-left corner, agent 1 right next to it
    mth = step_math(350.0, 170.0, 2)
    pos = torch.tensor([[[5.0, 5.0], [45.0, 25.0]]])
    boundary = mth.geometry.boundary_mask(pos)
    unsafe, dist = flat_unsafe(pos, mth.moves, mth.p.d_th + mth.p.step_m)
    mask, fb = apply_fallback(boundary & ~unsafe, boundary, dist)
    assert fb.tolist() == [[True, True]]
    # agent 0 can go up (to (5, 25): 40 m from agent 1) or right ((25, 5): 28.3 m): up
    assert mask[0, 0].tolist() == [True, False, False, False]


def scenario(small_traces_cfg, n_uabs=3) -> ScenarioConfig:
    sc = copy.deepcopy(small_traces_cfg.scenario)
    sc.episode_steps = 20
    sc.n_uabs = n_uabs
    return sc


def random_rollout(small_traces_cfg, train, mode, steps=160, n_envs=32, recoverable=True,
                   sc=None, eps=1.0, seed=0):
    mk = MaskingConfig(mode=mode, recoverable=recoverable)
    env = make_env(sc or scenario(small_traces_cfg), ChannelConfig(), mk, train,
                   n_envs=n_envs, seed=seed)
    sel = make_selector(env, eps=eps, generator=torch.Generator().manual_seed(seed))
    env.set_seed(seed)
    return env.rollout(steps, policy=sel, break_when_any_done=False), env.base_env.params


def assert_never_below_d_th(td, p):
    """The guarantee of the recoverable masks, asserted whole: no fallback, no
    collision, no proximity event, and no pair closer than d_th at the end of any step
    or anywhere on the straight paths between steps (to SAFETY_TOLERANCE)."""
    diag = td["next", DIAG]
    assert diag["fallbacks"].sum() == 0
    assert diag["collisions"].sum() == 0
    assert diag["proximity"].sum() == 0
    assert diag["min_pair_distance"].min() >= p.d_th - SAFETY_TOLERANCE
    assert diag["closest_approach"].min() >= p.d_th - SAFETY_TOLERANCE
    assert td[MASK].gather(-1, td[ACTION][..., None]).all()


@settings(max_examples=16, deadline=None)
@given(mode=st.sampled_from(COLLISION_MODES), area=AREAS, lattice=st.booleans(),
       eps=st.floats(0.0, 1.0), seed=st.integers(0, 2**31 - 1), crowd=st.integers(0, 3))
def test_recoverable_masks_keep_every_pair_apart(small_traces_cfg, train, mode, area,
                                                 lattice, eps, seed, crowd):
    """From M = 2 up to the largest fleet the area takes (crowded and boundary-heavy),
    ε-greedy over random Q-values (ε = 1: the random legal policy): zero violations."""
    sc = scenario(small_traces_cfg)
    sc.area.width, sc.area.height = area
    sc.lattice = lattice
    max_m = EnvParams.from_config(sc, ChannelConfig())  # the fleet the area holds
    from uabs_rl.env.geometry import Geometry
    fits = Geometry(max_m, torch.device("cpu")).packing(max_m.d_th + 2 * max_m.step_m).shape[0]
    sc.n_uabs = max(2, fits - crowd)
    td, p = random_rollout(small_traces_cfg, train, mode, steps=60, n_envs=8, sc=sc, eps=eps,
                           seed=seed % 1000)
    assert_never_below_d_th(td, p)


@pytest.mark.parametrize("mode", COLLISION_MODES)
def test_random_legal_policy_never_comes_closer_than_d_th(small_traces_cfg, train, mode):
    td, p = random_rollout(small_traces_cfg, train, mode)  # 32 envs x 160 steps, M = 3
    assert_never_below_d_th(td, p)
    assert torch.equal(td["next", DIAG, "fallbacks"], td[FALLBACK].float().sum(-1))


@pytest.mark.slow
@pytest.mark.parametrize("mode", COLLISION_MODES)
@pytest.mark.parametrize("lattice", [True, False])
def test_a_million_random_agent_steps_never_come_closer_than_d_th(small_traces_cfg, train,
                                                                  mode, lattice):
    """4 x 3 fleet sizes x 256 envs x 80 steps x M: 1.4 million agent-steps in all."""
    for m in (3, 6, 8):
        sc = scenario(small_traces_cfg, m)
        sc.lattice = lattice
        td, p = random_rollout(small_traces_cfg, train, mode, steps=80, n_envs=256, sc=sc)
        assert_never_below_d_th(td, p)


@pytest.mark.parametrize("mode", ["flat", "rank"])
def test_literal_masks_fall_back_but_never_collide_at_m3(small_traces_cfg, train, mode):
    td, _ = random_rollout(small_traces_cfg, train, mode, recoverable=False)
    diag = td["next", DIAG]
    assert diag["collisions"].sum() == 0
    # proximity only on steps that counted a fallback
    assert not ((diag["proximity"] > 0) & (diag["fallbacks"] == 0)).any()
    # the stored mask allows the stored (executed) action, and is never all False
    assert td[MASK].any(-1).all()
    assert td[MASK].gather(-1, td[ACTION][..., None]).all()
    assert torch.equal(diag["fallbacks"], td[FALLBACK].float().sum(-1))


def test_random_policy_collides_under_penalty(small_traces_cfg, train):
    """The check that the counters can fail: without masks, random UABS collide."""
    diag = random_rollout(small_traces_cfg, train, "penalty")[0]["next", DIAG]
    assert diag["collisions"].sum() > 0 and diag["proximity"].sum() > 0
    assert diag["fallbacks"].sum() == 0


def test_transform_specs_and_unknown_mode(small_traces_cfg, train):
    from torchrl.envs.utils import check_env_specs

    for mode in ("penalty", "flat", "rank"):
        env = make_env(scenario(small_traces_cfg), ChannelConfig(), MaskingConfig(mode=mode),
                       train, n_envs=4)
        check_env_specs(env, seed=0)
    with pytest.raises(ConfigError, match="masking.mode"):
        make_env(scenario(small_traces_cfg), ChannelConfig(), MaskingConfig(mode="soft"),
                 train)
    p = EnvParams.from_config(scenario(small_traces_cfg), ChannelConfig())
    with pytest.raises(ConfigError, match="masking.mode"):
        make_rule(MaskingConfig(mode="soft"), p)
    with pytest.raises(ConfigError, match="masking.rank_next_mask"):
        make_rule(MaskingConfig(rank_next_mask="soft"), p)
    assert set(RULES) == set(MaskingMode)  # every mode has exactly one rule class


def test_a_mode_without_a_registered_rule_is_refused_in_one_line(small_traces_cfg, train,
                                                                  trace_cache, monkeypatch):
    """A MaskingMode member whose rule class lacks @register (a user's new mode) is a
    ConfigError naming the mode and the decorator, at start-up and wherever a rule is
    made, not a KeyError traceback."""
    from tests.test_train import smoke
    from uabs_rl.training.startup import validate_settings

    monkeypatch.delitem(RULES, MaskingMode.flat)
    msg = r"masking.mode=flat has no rule: .*MaskingMode.flat, decorated with @register"
    with pytest.raises(ConfigError, match=msg):
        make_env(scenario(small_traces_cfg), ChannelConfig(), MaskingConfig(mode="flat"),
                 train)
    with pytest.raises(ConfigError, match=msg):
        validate_settings(smoke(trace_cache, "masking=flat"))


def test_flat_mask_keeps_random_warmup_actions_legal(small_traces_cfg, train):
    """ActionMask keeps the action spec in sync: env.rand_action respects the flat mask."""
    env = make_env(scenario(small_traces_cfg), ChannelConfig(), MaskingConfig(mode="flat"),
                   train, n_envs=16, seed=0)
    td = env.reset()
    for _ in range(40):
        td = env.rand_action(td)
        assert td[MASK].gather(-1, td[ACTION][..., None]).all()
        _, td = env.step_and_maybe_reset(td)


def test_next_state_masks_for_the_double_dqn_target():
    mth = step_math(350.0, 170.0, 2)
    pos = torch.tensor([[[125.0, 85.0], [205.0, 85.0]]])
    boundary = mth.geometry.boundary_mask(pos)
    b = torch.tensor([[[5.0] * 9, [1.0] * 9]])
    td = TensorDict({MASK: boundary, POSITION: pos, BEAM_PRIORITY: b,
                     RANK_ORDER: rank_order(b),
                     COLLIDERS: potential_colliders(pos, mth.p.d_th + 2 * mth.p.step_m)},
                    batch_size=[1])
    q = torch.tensor([[[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]])
    td.set(ACTION_VALUE, q)
    # flat / penalty / rank-boundary: the mask the transform wrote at s'
    for mode, nxt in [("flat", "greedy"), ("penalty", "greedy"), ("rank", "boundary")]:
        rule = make_rule(MaskingConfig(mode=mode, rank_next_mask=nxt), mth.p)
        assert not rule.target_needs_q
        assert torch.equal(rule.target_mask(td), boundary)
    # rank-greedy: agent 0 (top) greedily goes right to (145, 85); from (205, 85) agent 1
    # may then only go right (80 m); up/down end 63.2 m away, left 40 m (< d_th = 72.8)
    rule = make_rule(MaskingConfig(mode="rank", recoverable=False), mth.p)
    assert rule.target_needs_q
    m = rule.target_mask(td)
    assert torch.equal(m[0, 0], boundary[0, 0])
    assert m[0, 1].tolist() == [False, True, False, False]


def test_compiled_env_and_selector_match_eager(small_traces_cfg, train):
    """train.compile: the compiled step math and selection give identical rollouts."""
    out = {}
    for comp in (False, True):
        mk = MaskingConfig(mode="rank")
        env = make_env(scenario(small_traces_cfg), ChannelConfig(), mk, train, n_envs=4,
                       seed=0, compile=comp)
        sel = make_selector(env, eps=0.3, generator=torch.Generator().manual_seed(0),
                            compile=comp)
        env.set_seed(0)
        q = torch.randn(4, 3, 4, generator=torch.Generator().manual_seed(1))
        out[comp] = env.rollout(50, fixed_q_policy(sel, q), break_when_any_done=False)
    assert out[True]["next", DIAG, "ep_return"].abs().sum() > 0
    assert (out[False] == out[True]).all()


@pytest.mark.parametrize("mode,recoverable,next_mask", [("rank", True, "greedy"),
                                                         ("flat", False, "greedy"),
                                                         ("penalty", True, "greedy")])
def test_compiled_act_equals_the_eager_decision(small_traces_cfg, train, mode, recoverable,
                                                next_mask):
    """The training loop's decision and step, compiled as train.compile compiles them:
    MaskedActionSelector.act as one program (Q forward, the target mask, the ε-greedy
    choice) and DirectEnv's step as one (the step math and the rule's write), and both as
    one program (DirectEnv.act_and_step, what the training loop calls). They give the
    eager sequence's Q-values, target masks, actions, applied masks, fallback flags and
    every env output bit for bit over an episode (flat literal masks: fallbacks
    happen)."""
    from uabs_rl.algorithms.model import DuelingQNet

    mk = MaskingConfig(mode=mode, recoverable=recoverable, rank_next_mask=next_mask)
    compiled = (False, True, True)  # eager; two compiled programs; one
    envs = [make_env(scenario(small_traces_cfg), ChannelConfig(), mk, train, n_envs=4,
                     seed=0, spec_mask=False, compile=comp) for comp in compiled]
    sels = [make_selector(env, eps=0.3, generator=torch.Generator().manual_seed(0),
                          compile=comp) for env, comp in zip(envs, compiled, strict=True)]
    p = envs[0].base_env.params
    torch.manual_seed(0)
    qnet = DuelingQNet(p.obs_dim, 4, [16, 16])
    directs = [DirectEnv(env) for env in envs]
    tds = [d.reset() for d in directs]
    target = sels[0].rule.target_needs_q
    for _ in range(p.episode_steps):
        masks = [sel.act(qnet, td, target=target) for sel, td in
                 zip(sels[:2], tds[:2], strict=True)]
        mask, nxt = directs[2].act_and_step(sels[2], qnet, tds[2], target=target)
        masks.append(mask)
        assert all((m is None) == (not target) for m in masks)
        for key in (ACTION_VALUE, ACTION, MASK, FALLBACK):
            for td in tds[1:]:
                assert torch.equal(tds[0].get(key), td.get(key)), key
        if target:
            for m in masks[1:]:
                assert torch.equal(masks[0], m)
        tds = [d.step(td) for d, td in zip(directs[:2], tds[:2], strict=True)] + [nxt]
        for td in tds[1:]:
            assert set(tds[0]) == set(td)
            for key, value in tds[0].items():
                assert torch.equal(value, td[key]), key
    assert tds[0].get((DIAG, "ep_return")).abs().sum() > 0
    if mode == "flat":
        assert tds[0].get((DIAG, "ep_fallbacks")).sum() > 0
    # the one program ran compiled ahead of time (AheadOfTime), not through its fallback;
    # so does its second program, for another thread count (the thread governor's, on a
    # busy machine; one mode suffices: it is a compile)
    if mode == "rank":
        with another_thread_count():
            directs[2].act_and_step(sels[2], qnet, tds[2], target=target)
    (program,) = directs[2]._decided.values()
    assert len(program.fn.programs) == (2 if mode == "rank" else 1)
    assert all(p is not program.fn.fallback for p in program.fn.programs.values())


@pytest.mark.parametrize("mode,recoverable,compiled", [("rank", True, True),
                                                       ("rank", True, False),
                                                       ("flat", False, False),
                                                       ("penalty", True, True)])
def test_evaluator_rollout_equals_torchrl_rollout(small_traces_cfg, train, mode, recoverable,
                                                  compiled):
    """Evaluation flies a Q-network's greedy policy through DirectEnv (Evaluator.rollout
    of a GreedyPolicy): the TensorDict it returns equals env.rollout's of the same
    modules, entry for entry, shapes and dtypes too, so every record drawn from it is
    the same (flat literal masks: fallbacks happen)."""
    from tensordict.nn import TensorDictSequential

    from uabs_rl.algorithms.model import DuelingQNet
    from uabs_rl.evaluation.evaluator import Evaluator, GreedyPolicy

    mk = MaskingConfig(mode=mode, recoverable=recoverable)
    out = []
    for direct in (True, False):
        env = make_env(scenario(small_traces_cfg), ChannelConfig(), mk, train, n_envs=4,
                       seed=0, spec_mask=False, compile=compiled)
        torch.manual_seed(0)
        qnet = DuelingQNet(env.base_env.params.obs_dim, 4, [16, 16])
        # ε = 0.3: exploring, literal flat masks meet dead ends (fallbacks)
        sel = make_selector(env, eps=0.3, generator=torch.Generator().manual_seed(0),
                            compile=compiled)
        policy = GreedyPolicy(qnet, sel)
        if not direct:  # the same modules, as a plain TorchRL policy: env.rollout
            policy = TensorDictSequential(*policy.module)
        ev = Evaluator(env, 0)
        out.append((ev.rollout(policy), ev))
    (a, ev), (b, _) = out
    assert a.batch_size == b.batch_size and a["agents"].batch_size == b["agents"].batch_size
    keys = set(a.keys(True, True))
    assert keys == set(b.keys(True, True)) and ("next", *REWARD) in keys
    for k in keys:
        assert a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]), k
    assert ev.record(a) == ev.record(b)
    if mode == "flat":
        assert a["next", DIAG, "ep_fallbacks"].sum() > 0


def assert_same_entries(td, out):
    """A TensorDict and a DirectEnv output hold the same keys and equal tensors."""
    keys = set(td.keys(include_nested=True, leaves_only=True))
    assert keys == set(out.keys())
    for k in keys:
        assert td[k].shape == out[k].shape and torch.equal(td[k], out[k]), k


@pytest.mark.parametrize("mode,recoverable", [*((m, True) for m in MODES),
                                              ("flat", False), ("rank", False)])
def test_direct_env_equals_the_torchrl_env_entry_for_entry(small_traces_cfg, train, mode,
                                                           recoverable):
    """The training loop steps through DirectEnv: every reset and step gives what
    env.reset() and env.step(td)["next"] give, key for key, through episode ends."""
    mk = MaskingConfig(mode=mode, recoverable=recoverable)
    envs = [make_env(scenario(small_traces_cfg), ChannelConfig(), mk, train, n_envs=4,
                     seed=0, spec_mask=False) for _ in range(2)]
    sels = [make_selector(env, eps=0.5, generator=torch.Generator().manual_seed(0))
            for env in envs]
    direct = DirectEnv(envs[1])
    qs = torch.randn(2, 20, 4, 3, 4, generator=torch.Generator().manual_seed(1))
    for episode in range(2):
        td, out = envs[0].reset(), direct.reset()
        for t in range(20):
            assert_same_entries(td, out)
            sels[0](td.set(ACTION_VALUE, qs[episode, t]))
            sels[1](out.set(ACTION_VALUE, qs[episode, t]))
            td, out = envs[0].step(td)["next"], direct.step(out)
        assert td["done"].all()
        assert_same_entries(td, out)
    assert td[DIAG, "ep_return"].abs().sum() > 0
    with pytest.raises(TypeError, match="spec_mask=False"):
        DirectEnv(make_env(scenario(small_traces_cfg), ChannelConfig(), mk, train))


def fixed_q_policy(sel, q):
    def policy(td):
        return sel(td.set(ACTION_VALUE, q))
    return policy


@settings(max_examples=12, deadline=None)
@given(name=st.sampled_from(sorted(ALGORITHMS)), mode=st.sampled_from(MODES),
       eps=st.floats(0.0, 0.5),
       seed=st.integers(0, 2**31 - 1))
def test_every_learners_policy_acts_only_within_the_mask(small_traces_cfg, train, name, mode,
                                                         eps, seed):
    """Each algorithm's acting network (randomly initialised) behind the masking rule's
    selector, ε-greedy from random states: every chosen action is legal under the mask
    that applied to it, and the collision masks keep every pair apart."""
    from tensordict.nn import TensorDictModule, TensorDictSequential

    from uabs_rl.algorithms import Dims, make_algorithm
    from uabs_rl.env.uabs_env import N_ACTIONS, OBS

    mk = MaskingConfig(mode=mode)
    env = make_env(scenario(small_traces_cfg), ChannelConfig(), mk, train, n_envs=8,
                   seed=seed % 1000)
    p = env.base_env.params
    lrn = make_algorithm(learner_config(name, hidden=[32]),
                         Dims(p.obs_dim, N_ACTIONS, p.n_uabs), [seed % 1000],
                         torch.device("cpu"))
    policy = TensorDictSequential(
        TensorDictModule(lrn.policy, in_keys=[OBS], out_keys=[ACTION_VALUE]),
        make_selector(env, eps=eps, generator=torch.Generator().manual_seed(seed)))
    env.set_seed(seed % 1000)
    td = env.rollout(40, policy=policy, break_when_any_done=False)
    assert td[MASK].gather(-1, td[ACTION][..., None]).all()
    if mode != "penalty":
        assert_never_below_d_th(td, p)
