"""Training over a family of cities (``family``): traces stacked side by side, each env
drawing its city per episode and keeping its UABS inside that city's own area."""

from __future__ import annotations

import pytest
import torch

from tests.test_observation import EGO, ego_size
from uabs_rl.config import (
    AreaConfig,
    ChannelConfig,
    ConfigError,
    RunConfig,
    ScenarioConfig,
    family_scenarios,
)
from uabs_rl.env.uabs_env import UABSEnv
from uabs_rl.traces.build import stack_cities
from uabs_rl.traces.cache import TraceSet


def parked(n_sims: int, v: int, w: float, h: float, steps: int = 40, seed: int = 0) -> TraceSet:
    g = torch.Generator().manual_seed(seed)
    pos = torch.rand(n_sims, 1, v, 2, generator=g) * torch.tensor([w, h])
    pos = pos.expand(n_sims, steps, v, 2).contiguous()
    return TraceSet(pos, torch.ones(n_sims, steps, v, dtype=torch.bool),
                    {"split": "train", "dt": 1.0})


def family_traces() -> TraceSet:
    """A small city (184 m x 184 m, 30 vehicles, 2 sims) and the default area (350 m x
    170 m, 50 vehicles, 3 sims)."""
    return stack_cities([parked(2, 30, 184, 184), parked(3, 50, 350, 170, steps=45, seed=1)],
                        [(184.0, 184.0), (350.0, 170.0)], ["small", "default"])


def test_stacked_traces_pad_the_smaller_fleet_and_cut_to_the_shorter():
    ts = family_traces()
    assert ts.positions.shape == (5, 40, 50, 2) and ts.meta["city_of_sim"] == [0, 0, 1, 1, 1]
    assert not ts.present[:2, :, 30:].any() and ts.present[:2, :, :30].all()
    assert ts.present[2:].all()
    assert ts.meta["city_area"] == [[184.0, 184.0], [350.0, 170.0]]


def test_each_env_draws_its_city_and_stays_in_its_area():
    """16 envs over 4 episodes of random legal moves: the envs draw their cities anew
    each episode, both cities are flown at once, and no UABS leaves its env's own city
    (the small city's boundary mask, not the large one's)."""
    env = UABSEnv(ScenarioConfig(n_uabs=3, episode_steps=20), ChannelConfig(),
                  family_traces(), n_envs=16, seed=0, obs=EGO)
    env.require_start_spacing(40.0)
    seen = torch.zeros(16, 2, dtype=torch.bool)
    small_left_default = False
    for _ in range(4):
        out = env.reset_direct()
        city = env.city_of_sim[env.state["sim"]]
        assert 0 < int(city.sum()) < 16  # both cities in one batch
        seen[torch.arange(16), city] = True
        for _ in range(20):
            bounds = env.city_bounds[city][:, None, :]
            pos = env.state["pos"]
            assert ((pos >= 0) & (pos <= bounds)).all()
            small_left_default |= bool((pos[city == 0] > 184).any())
            mask = out["agents", "action_mask"]
            a = torch.multinomial(mask.flatten(0, 1).float(), 1).view(16, 3)
            out = env.step_direct(a)
        assert out["agents", "observation"].shape == (16, 3, ego_size())
    assert seen.all(-1).sum() >= 12  # (1 - 0.6^4 - 0.4^4) of the 16 envs expected: 13.6
    assert not small_left_default


def test_the_start_spacing_holds_in_every_city():
    env = UABSEnv(ScenarioConfig(n_uabs=3, episode_steps=20), ChannelConfig(),
                  family_traces(), n_envs=32, seed=1, obs=EGO)
    env.require_start_spacing(40.0)
    env.reset_direct()
    d = torch.cdist(env.state["pos"], env.state["pos"])
    d = d + torch.eye(3) * 1e9
    assert d.amin() >= env.params.d_th + 40.0 - 1e-4


@pytest.mark.parametrize("family,message", [
    ([{"n_uabs": 4}], "family[0].n_uabs: a family's cities share scenario's fleet"),
    ([{"name": "a"}, {"name": "a"}], "two cities are named 'a'"),
    ([{"area": {"width": "wide"}}], "family[0]"),
    (["grid"], "family[0] must be a mapping"),
])
def test_bad_family_entries_are_refused_naming_the_entry(family, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        family_scenarios(RunConfig(family=family))


def test_family_cities_take_scenario_for_what_they_leave_out():
    cfg = RunConfig(scenario=ScenarioConfig(n_uabs=4, episode_steps=30), family=[
        {}, {"name": "b", "area": {"width": 200.0}, "sumo": {"fleet_size": 10}}])
    a, b = family_scenarios(cfg)
    assert a == cfg.scenario
    assert (b.name, b.area, b.sumo.fleet_size, b.n_uabs, b.episode_steps) == (
        "b", AreaConfig(width=200.0), 10, 4, 30)
