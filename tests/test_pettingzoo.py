"""The PettingZoo door (uabs_rl.interop.pettingzoo): PettingZoo's own API test under
every masking mode, the safety guarantee under random legal actions from the masks
given, the parallel rank mask against the sequential rank rule, and a TorchRL learner
trained through ``torchrl.envs.PettingZooWrapper`` (docs/interop.md)."""

from __future__ import annotations

import copy
import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("pettingzoo", reason='needs the interop extra: pip install -e ".[interop]"')

from pettingzoo.test import parallel_api_test, parallel_seed_test  # noqa: E402

from tests.conftest import load_benchmark  # noqa: E402
from uabs_rl.config import ChannelConfig, ConfigError, MaskingConfig  # noqa: E402
from uabs_rl.env.geometry import UNIT_MOVES, path_distance  # noqa: E402
from uabs_rl.env.uabs_env import MASK  # noqa: E402
from uabs_rl.interop.pettingzoo import make_parallel_env, parallel_rank_mask  # noqa: E402
from uabs_rl.safety.rules import (  # noqa: E402
    SAFETY_TOLERANCE,
    flat_recoverable_mask,
    potential_colliders,
    rank_order,
    rank_select_recoverable,
)

STEPS = 20  # episode length of the small case


def scenario(small_traces_cfg, n_uabs=4):
    sc = copy.deepcopy(small_traces_cfg.scenario)
    sc.episode_steps = STEPS
    sc.n_uabs = n_uabs
    return sc


def penv(small_traces_cfg, train, mode, n_uabs=4, seed=0, recoverable=True):
    return make_parallel_env(scenario(small_traces_cfg, n_uabs), ChannelConfig(),
                             MaskingConfig(mode=mode, recoverable=recoverable), train,
                             seed=seed)


@pytest.mark.parametrize("mode", ["penalty", "flat", "rank"])
def test_parallel_api_test_passes(small_traces_cfg, train, mode):
    env = penv(small_traces_cfg, train, mode)
    parallel_api_test(env, num_cycles=3 * STEPS)
    obs, _ = env.reset(seed=1)
    assert set(obs) == set(env.possible_agents) and len(env.possible_agents) == 4
    for o in obs.values():
        assert env.observation_space("uabs_0").contains(o)
        assert o["action_mask"].any()


def test_seeded_resets_repeat_the_episode(small_traces_cfg, train):
    """PettingZoo's seed test: two envs reset with the same seed give the same
    observations, masks and rewards under the same actions."""
    parallel_seed_test(lambda: penv(small_traces_cfg, train, "rank"))


@pytest.mark.parametrize("mode", ["flat", "rank"])
def test_random_legal_actions_never_bring_two_uabs_closer_than_d_th(small_traces_cfg,
                                                                    train, mode):
    """The guarantee across the door: 200 steps (10 episodes) of uniformly random
    actions among those the action_mask allows, with 6 UABS crowded by the random
    starts; every action is executed as asked (no repair) and no pair comes closer
    than d_th at the end of a step or on the paths between steps."""
    env = penv(small_traces_cfg, train, mode, n_uabs=6, seed=3)
    d_th = env.params.d_th
    rng = np.random.default_rng(0)
    steps = repaired = 0
    closest = np.inf
    for episode in range(10):
        obs, _ = env.reset(seed=episode)
        while env.agents:
            actions = {a: int(rng.choice(np.flatnonzero(obs[a]["action_mask"])))
                       for a in env.agents}
            obs, _, _, _, _ = env.step(actions)
            s = env.last_step
            steps += 1
            repaired += s["repaired"]
            closest = min(closest, s["closest_approach"], s["min_pair_distance"])
            assert s["collisions"] == 0 and s["proximity"] == 0 and s["fallbacks"] == 0
    assert steps == 10 * STEPS
    assert repaired == 0
    assert closest >= d_th - SAFETY_TOLERANCE


def test_actions_outside_the_mask_are_repaired_safely(small_traces_cfg, train):
    """A learner that ignores the mask: the rank rule, applied in rank order, replaces
    its illegal moves and the fleet still keeps d_th."""
    env = penv(small_traces_cfg, train, "rank", n_uabs=6, seed=5)
    rng = np.random.default_rng(1)
    repaired = 0
    for episode in range(5):
        env.reset(seed=100 + episode)
        while env.agents:
            env.step({a: int(rng.integers(4)) for a in env.agents})
            s = env.last_step
            repaired += s["repaired"]
            assert s["proximity"] == 0 and s["collisions"] == 0
            assert s["closest_approach"] >= env.params.d_th - SAFETY_TOLERANCE
    assert repaired > 0


def test_literal_rank_gives_the_boundary_mask_and_repairs(small_traces_cfg, train):
    """The paper's literal rank rule has no backup to build a parallel mask on: the
    agents get the boundary mask (what the rule writes) and the rank rule repairs."""
    env = penv(small_traces_cfg, train, "rank", recoverable=False)
    parallel_api_test(env, num_cycles=STEPS + 2)
    obs, _ = env.reset(seed=0)
    boundary = env._out.get(MASK)[0].numpy()
    for i, a in enumerate(env.possible_agents):
        assert (obs[a]["action_mask"] == boundary[i]).all()
    _, _, _, _, info = env.step({a: 0 for a in env.agents})
    assert all(0 <= info[a]["executed_action"] < 4 for a in env.possible_agents)


def test_parallel_rank_mask_lies_between_flat_and_sequential_rank():
    """Over random crowded states: recoverable flat mask <= parallel rank mask <= the
    sequential rank mask of the same order; every joint choice from it passes the rank
    rule unchanged; every mask holds the agent's backup."""
    g = torch.Generator().manual_seed(0)
    e, m, step, d_th = 4096, 5, 10.0, 25.0
    moves = UNIT_MOVES * step
    # states the rules reach: the last joint move kept d_th along its paths, so the
    # backups (retracing it) are pairwise safe
    prev = torch.rand(e, m, 2, generator=g) * 110.0
    last = torch.randint(0, 4, (e, m), generator=g)
    pos = prev + moves[last]
    backup = (last + 2) % 4
    r0 = prev[:, :, None] - prev[:, None]
    dv = moves[last][:, :, None] - moves[last][:, None]
    d = path_distance(r0, dv) + torch.eye(m) * 1e9
    ok = d.flatten(1).amin(-1) >= d_th
    pos, backup = pos[ok], backup[ok]
    e = pos.shape[0]
    assert e > 100
    boundary = torch.ones(e, m, 4, dtype=torch.bool)
    order = rank_order(torch.rand(e, m, 3, generator=g))
    coll = potential_colliders(pos, d_th + 2 * step)
    par = parallel_rank_mask(pos, boundary, backup, order, coll, moves, d_th)
    flat = flat_recoverable_mask(pos, boundary, backup, moves, d_th)
    assert (flat <= par).all()
    assert par.gather(-1, backup[..., None]).all()
    for _ in range(20):
        want = (torch.rand(e, m, 4, generator=g) + 2.0 * par).argmax(-1)  # legal picks
        q = torch.nn.functional.one_hot(want, 4).float()
        got, applied, fb = rank_select_recoverable(q, boundary, pos, order, coll, backup,
                                                   moves, d_th, 0.0, None)
        assert (got == want).all() and not fb.any()
        assert (par <= applied).all()


def load_example():
    """benchmarks/pettingzoo_dqn.py, the example docs/interop.md runs."""
    return load_benchmark("pettingzoo_dqn")


@pytest.mark.parametrize("mode", ["flat", "rank"])
def test_torchrl_learner_trains_through_the_door(small_traces_cfg, train, mode):
    """The round trip: torchrl.envs.PettingZooWrapper over the ParallelEnv, a collector
    and TorchRL's DQNLoss for 300 frames (15 episodes): the network's parameters move,
    the loss stays finite, and the masked learner never brings two UABS within d_th."""
    penv_ = penv(small_traces_cfg, train, mode)
    out = load_example().train(penv_, frames=300, frames_per_batch=20, seed=0)
    assert out["frames"] == 300 and out["updates"] >= 100
    assert math.isfinite(out["mean_loss"]) and out["parameter_change"] > 0
    assert penv_.totals["steps"] >= 300
    assert out["collisions"] == 0 and out["repaired"] == 0
    assert penv_.totals["proximity"] == 0
    assert out["closest_approach"] >= out["d_th"] - SAFETY_TOLERANCE


def test_interop_page_links_and_commands_resolve():
    """docs/interop.md: every relative link and anchor resolves, and every flag of
    ``python benchmarks/pettingzoo_dqn.py`` it writes exists."""
    root = Path(__file__).resolve().parents[1]
    page = root / "docs" / "interop.md"
    text = page.read_text()
    prose = re.sub(r"```.*?```", "", text, flags=re.S)
    for target in re.findall(r"\]\(([^)\s]+)\)", prose):
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        assert dest.exists(), target
        if anchor:
            headings = re.findall(r"^#+ (.+)$", re.sub(r"```.*?```", "", dest.read_text(),
                                                        flags=re.S), flags=re.M)
            slugs = {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
                     for h in headings}
            assert anchor in slugs, target
    source = (root / "benchmarks" / "pettingzoo_dqn.py").read_text()
    for args in re.findall(r"python benchmarks/pettingzoo_dqn\.py([^`\n]*)", text):
        for flag in re.findall(r"(?<!\S)(--[a-z-]+)", args):
            assert f'"{flag}"' in source, flag


def test_a_split_the_door_does_not_know_or_traces_of_another_split_are_refused(
        small_traces_cfg, train, held_out):
    """split names the traces' own split: a misspelt one, or test traces walked as
    training traces (training on held-out data by a slip), is refused with the fix."""
    sc, mk = scenario(small_traces_cfg), MaskingConfig(mode="rank")
    with pytest.raises(ConfigError, match=r"split must be one of train, eval, test "
                                          r"\(eval: the validation traces\), got 'valid'\."):
        make_parallel_env(sc, ChannelConfig(), mk, train, split="valid")
    with pytest.raises(ConfigError, match=r"split='train' but the traces given are the "
                                          r"eval split: pass get_traces\(scenario, "
                                          r"traces_cfg, 'train'\) for them, or split='eval'"):
        make_parallel_env(sc, ChannelConfig(), mk, held_out, split="train")
    with pytest.raises(ConfigError, match=r"split='test' but the traces given are the "
                                          r"train split"):
        make_parallel_env(sc, ChannelConfig(), mk, train, split="test")
    env = make_parallel_env(sc, ChannelConfig(), mk, held_out, split="eval")
    obs, _ = env.reset(seed=0)
    assert set(obs) == set(env.possible_agents)
    # the traces config: the split named is the one loaded
    env = make_parallel_env(sc, ChannelConfig(), mk, small_traces_cfg.traces, split="eval")
    assert env.reset(seed=0)[0].keys() == obs.keys()
