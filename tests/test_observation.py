"""The egocentric observation (obs=egocentric): its size depends on neither the fleet size
nor the area, it is unchanged when the whole scene is translated by a lattice step or
the UABS are renumbered, and its parts are what docs/model.md §5 says."""

from __future__ import annotations

import pytest
import torch

from uabs_rl.config import AreaConfig, ChannelConfig, ObsConfig, ScenarioConfig
from uabs_rl.env.observe import map_offsets, nearest_neighbours
from uabs_rl.env.params import EnvParams
from uabs_rl.env.uabs_env import UABSEnv
from uabs_rl.traces.cache import TraceSet

EGO = ObsConfig(name="egocentric", frame="egocentric", motion=True)
STEP = 20.0  # the lattice pitch v·δt of the defaults
CITY = AreaConfig(width=2004, height=1004)  # conf/scenario/city.yaml


def ego_size(obs: ObsConfig = EGO, beams: int = 9) -> int:
    r, k = obs.map_radius, obs.neighbours
    return 1 + beams + (2 * r + 1) ** 2 * (1 + obs.motion) + 3 * k + 4


@pytest.mark.parametrize("m", [2, 3, 6, 25])
@pytest.mark.parametrize("area", [AreaConfig(), CITY])
def test_the_size_depends_on_neither_the_fleet_nor_the_area(m, area):
    p = EnvParams.from_config(ScenarioConfig(n_uabs=m, area=area), ChannelConfig(), EGO)
    assert p.obs_dim == ego_size() == 1 + 9 + 50 + 12 + 4
    paper = EnvParams.from_config(ScenarioConfig(n_uabs=m, area=area), ChannelConfig())
    assert paper.obs_dim == 3 + 2 * m + 9  # the paper's grows with the fleet


def traces(area: AreaConfig, v: int = 60, steps: int = 30, shift: float = 0.0,
           seed: int = 0) -> TraceSet:
    """``v`` vehicles on a random walk of 10 m steps inside the middle of ``area``,
    every coordinate a whole number, all of them moved by ``shift`` metres east."""
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor([area.width, area.height]) * 0.3
    hi = torch.tensor([area.width, area.height]) * 0.7
    start = (lo + torch.rand(v, 2, generator=g) * (hi - lo)).round()
    walk = torch.randint(-1, 2, (steps, v, 2), generator=g).float() * 10.0
    pos = (start + walk.cumsum(0))[None] + torch.tensor([shift, 0.0])
    return TraceSet(pos, torch.ones(1, steps, v, dtype=torch.bool), {"split": "x", "dt": 1.0})


def run_scene(m: int, uabs: torch.Tensor, actions: torch.Tensor, tr: TraceSet,
              area: AreaConfig, los: str = "sample") -> list[torch.Tensor]:
    """Observations [M, obs_dim] at reset and after each row of ``actions`` [K, M], the
    fleet placed at ``uabs`` [M, 2] and the window starting at step 0."""
    env = UABSEnv(ScenarioConfig(n_uabs=m, area=area, episode_steps=20),
                  ChannelConfig(los_mode=los), tr, n_envs=1, seed=3, obs=EGO)
    env.reset()
    st = env.state
    st["pos"][0], st["start"][:], st["t"][:] = uabs, 0, 0
    st["priority"].zero_()
    st["prev_present"].zero_()
    env.math.observe(st, env.veh_pos, env.veh_present, env.rng)
    seen = [env.math.observation(st["pos"], st["t"], st["b"], st["look"])[0]]
    for a in actions:
        out = env.math.step(st, a[None], env.veh_pos, env.veh_present, env.rng)
        seen.append(out["observation"][0])
    return seen


AREA = AreaConfig(width=800, height=800)
FLEET = torch.tensor([[400.0, 400.0], [500.0, 400.0], [400.0, 300.0], [300.0, 400.0],
                      [400.0, 500.0], [520.0, 520.0]])  # 3 at 100 m: ties in distance
MOVES = torch.tensor([[1, 0, 2, 3, 1, 0], [1, 1, 3, 3, 0, 2], [0, 1, 2, 2, 1, 3],
                      [3, 1, 0, 2, 0, 0]])


def test_unchanged_when_the_whole_scene_moves_a_lattice_step():
    """Vehicles and UABS 20 m further east, far from every edge: every UABS observes
    exactly what it did, step after step (LoS sampled, same draws); the paper's
    observation does not."""
    here = run_scene(6, FLEET, MOVES, traces(AREA), AREA)
    east = run_scene(6, FLEET + torch.tensor([STEP, 0.0]), MOVES,
                     traces(AREA, shift=STEP), AREA)
    for a, b in zip(here, east, strict=True):
        assert torch.equal(a, b)
    assert here[-1][:, 1:10].sum() > 0  # vehicles were served: the test compares something
    p = EnvParams.from_config(ScenarioConfig(n_uabs=6, area=AREA), ChannelConfig())
    assert p.obs_dim != here[0].shape[-1]


def test_unchanged_when_the_uabs_are_renumbered():
    """UABS i of the renumbered fleet is UABS perm[i] of the first: it observes what
    that one observed, including with neighbours tied in distance."""
    perm = torch.tensor([4, 2, 5, 0, 3, 1])
    tr = traces(AREA)
    first = run_scene(6, FLEET, MOVES, tr, AREA, los="los")
    renumbered = run_scene(6, FLEET[perm], MOVES[:, perm], tr, AREA, los="los")
    for a, b in zip(first, renumbered, strict=True):
        assert torch.equal(a[perm], b)


def test_neighbours_are_the_nearest_others_padded_when_fewer():
    pos = torch.tensor([[[0.0, 0.0], [100.0, 0.0], [0.0, -300.0]]])
    near = nearest_neighbours(pos, 4, scale=200.0).view(1, 3, 4, 3)
    # UABS 0: UABS 1 at (+100, 0), then UABS 2 at (0, -300) clipped to -1; two missing
    assert near[0, 0].tolist() == [[0.5, 0.0, 1.0], [0.0, -1.0, 1.0], [0.0, 0.0, 0.0],
                                   [0.0, 0.0, 0.0]]
    assert near[0, 2, 0].tolist() == [0.0, 1.0, 1.0]  # UABS 0, 300 m north (clipped)
    assert nearest_neighbours(pos[:, :1], 2, 200.0).abs().sum() == 0  # alone: all padding


def test_the_neighbours_of_some_uabs_are_their_rows_among_all():
    """``of``: the rows of the UABS asked for, each window its own, the same numbers as
    every UABS's (ties in distance included: a fleet on a lattice)."""
    g = torch.Generator().manual_seed(0)
    pos = torch.randint(0, 6, (3, 7, 2), generator=g).float() * 20.0
    every = nearest_neighbours(pos, 4, 60.0)
    of = torch.tensor([[6, 0], [2, 2], [5, 1]])
    assert torch.equal(nearest_neighbours(pos, 4, 60.0, of=of),
                       every.gather(1, of[..., None].expand(-1, -1, every.shape[-1])))


def test_the_parts_are_time_beams_map_neighbours_and_edges():
    """One vehicle 40 m east of a lone UABS: the map scores it from the lattice points
    whose 3 x 3 beam grid (about 31.5 m either way) covers it, the edges say how far the
    UABS is from each (clipped at 4 steps)."""
    veh = torch.zeros(1, 30, 1, 2)
    veh[..., 0], veh[..., 1] = 145.0, 85.0
    tr = TraceSet(veh, torch.ones(1, 30, 1, dtype=torch.bool), {"split": "x", "dt": 1.0})
    seen = run_scene(1, torch.tensor([[105.0, 85.0]]), torch.zeros(0, 1), tr, AreaConfig())
    o = seen[0][0]
    assert o.shape == (ego_size(),)
    assert o[0] == 0.0  # t / T at reset
    grid = map_offsets(2, STEP, torch.device("cpu"))
    scored = o[10:35] > 0
    # 20 m and 40 m east, a step south to a step north; the extrapolated copy alike
    # (the vehicle has not moved)
    assert grid[scored].tolist() == [[20.0, -20.0], [40.0, -20.0], [20.0, 0.0], [40.0, 0.0],
                                     [20.0, 20.0], [40.0, 20.0]]
    assert torch.equal(o[35:60], o[10:35])
    assert o[60:72].abs().sum() == 0  # no other UABS
    # west 105 m, south 85 m, east 245 m, north 85 m: all beyond 4 steps = 80 m
    assert o[72:].tolist() == [1.0, 1.0, 1.0, 1.0]
    near_edge = run_scene(1, torch.tensor([[25.0, 85.0]]), torch.zeros(0, 1), tr,
                          AreaConfig())[0][0]
    assert near_edge[72].item() == pytest.approx(25.0 / 80.0)


@pytest.mark.parametrize("block", [1, 37, 1000])
def test_scores_in_blocks_equal_the_scores_in_one_block(monkeypatch, block):
    """The local map is scored in blocks of candidates to bound memory; every block size
    gives the same numbers as one block, and each equals its footprint count by hand."""
    from uabs_rl.env import service
    from uabs_rl.env.channel import assign_beams

    g = torch.Generator().manual_seed(3)
    e, m, v = 3, 5, 120
    cand = ((torch.rand(e, m, 1, 2, generator=g) * 300).round()
            + map_offsets(2, 20.0, torch.device("cpu")))
    veh = torch.rand(e, 2, v, generator=g) * 300
    present = torch.rand(e, v, generator=g) < 0.8
    priority = torch.randint(0, 40, (e, v), generator=g).float()
    monkeypatch.setattr(service, "SCORE_BLOCK", 1 << 30)
    whole = service.move_scores(cand, veh, present, priority, 25.0, 9)
    monkeypatch.setattr(service, "SCORE_BLOCK", block)
    assert torch.equal(service.move_scores(cand, veh, present, priority, 25.0, 9), whole)
    i, j, k = 1, 3, 12
    inside, _ = assign_beams(veh[i, 0] - cand[i, j, k, 0], veh[i, 1] - cand[i, j, k, 1], 25.0)
    by_hand = sum(max(1.0, float(priority[i, n])) for n in range(v)
                  if inside[n] and present[i, n])
    assert whole[i, j, k].item() == by_hand
    assert whole.sum() > 0


def test_compiled_scores_take_every_vehicle_in_one_graph():
    """Inside a compiled program (train.compile's env step) the scores skip the choice
    of near vehicles, whose count would be a shape read from the data (a graph break and
    a recompile per value): one graph, the same numbers as eager."""
    from uabs_rl.env import service

    g = torch.Generator().manual_seed(7)
    cand = ((torch.rand(2, 6, 1, 2, generator=g) * 1800).round()
            + map_offsets(2, 20.0, torch.device("cpu")))
    veh = torch.rand(2, 2, 400, generator=g) * 1800
    present = torch.rand(2, 400, generator=g) < 0.9
    priority = torch.randint(0, 40, (2, 400), generator=g).float()
    args = (cand, veh, present, priority, 25.0, 9)
    groups = cand.reshape(2, -1, cand.shape[-2], 2)
    assert service.near_vehicles(groups, veh, priority + 1, 75.0) is not None  # eager: chosen
    compiled = torch.compile(service.move_scores, fullgraph=True, backend="eager")
    assert torch.equal(compiled(*args), service.move_scores(*args))


def test_the_near_sets_are_ascending_padded_and_declined_where_most_are_kept():
    """One selection serves the env's scores, the planner's cut and the leaf's maps:
    each set's vehicles in ascending order, padded to the largest set with vehicles it
    does not keep (flagged invalid); none made where a set keeps every vehicle, or more
    than the share ``most``."""
    from uabs_rl.env.service import near_sets

    keep = torch.tensor([[0, 1, 0, 1, 0, 0, 0, 0], [1, 0, 1, 0, 0, 0, 0, 1]], dtype=torch.bool)
    sel, valid = near_sets(keep)
    assert sel.tolist() == [[1, 3, 0], [0, 2, 7]]
    assert valid.tolist() == [[True, True, False], [True, True, True]]
    assert near_sets(keep, most=0.5) is not None  # 3 of 8
    keep[1, 3:5] = True  # 5 of 8
    assert near_sets(keep, most=0.5) is None and near_sets(keep) is not None
    keep[0] = True
    assert near_sets(keep) is None
    assert near_sets(torch.zeros(2, 3, 0, dtype=torch.bool)) is None


@pytest.mark.parametrize("block", [1, 37, 1 << 30])
def test_scores_from_the_near_vehicles_equal_the_scores_over_all(monkeypatch, block):
    """Over a district (vehicles spread far beyond the footprints' reach) each UABS's
    candidates are tested against its near vehicles only: the same numbers as against
    every vehicle, in any block size, with vehicles at the very edge of the reach."""
    from uabs_rl.env import service

    g = torch.Generator().manual_seed(5)
    e, m, r_b = 2, 6, 25.0
    cand = ((torch.rand(e, m, 1, 2, generator=g) * 1800).round()
            + map_offsets(2, 20.0, torch.device("cpu")))  # [E, M, 25, 2]
    spread = torch.rand(e, 2, 400, generator=g) * 1800
    # just inside the reach (3 x 25 m) of the map's outer candidates (40 m from its
    # centre), just beyond it, and at a corner
    edge = torch.tensor([[114.99, 0.0], [-114.99, 0.0], [0.0, 114.99], [0.0, -114.99],
                         [115.01, 0.0], [90.0, 89.0]])
    at_edge = (cand[:, :, 12, None, :] + edge).reshape(e, -1, 2).transpose(1, 2)
    veh = torch.cat([spread, at_edge], dim=-1)
    v = veh.shape[-1]
    present = torch.rand(e, v, generator=g) < 0.9
    priority = torch.randint(0, 40, (e, v), generator=g).float()
    groups = cand.reshape(e, -1, cand.shape[-2], 2)
    weight = torch.where(present, priority.clamp_min(1.0), 0.0)
    assert service.near_vehicles(groups, veh, weight, 3 * r_b) is not None  # chosen here
    monkeypatch.setattr(service, "SCORE_BLOCK", block)
    near = service.move_scores(cand, veh, present, priority, r_b, 9)
    monkeypatch.setattr(service, "near_vehicles", lambda *args: None)
    every = service.move_scores(cand, veh, present, priority, r_b, 9)
    assert torch.equal(near, every)
    outer = (map_offsets(2, 20.0, torch.device("cpu")).abs().amax(-1) == 40.0)
    assert (every[..., outer] > 0).float().mean() > 0.3  # the edge vehicles are scored
