"""The road-aware predictor (``--predictor road``): lanes found from position and heading,
motion along the lane and straight on at junctions, by hand on a small network written
here; constant velocity where no lane fits; it never reads a position after step t; the
mpc with it flies only legal moves."""

from __future__ import annotations

import subprocess

import pytest
import torch

from tests.test_mpc import eval_env, poisoned, rollout
from uabs_rl.config import ConfigError
from uabs_rl.env.uabs_env import ACTION
from uabs_rl.evaluation.predict import Predictor, make_predictor
from uabs_rl.evaluation.roads import RoadAware, RoadNetwork, network_file, straightest
from uabs_rl.traces.inputs import netgenerate_path, read_net


@pytest.fixture(scope="module")
def cross(tmp_path_factory):
    """A plus-shaped network: junction C at (0, 0) with arms 100 m long to W (-100, 0),
    E (100, 0), S (0, -100) and N (0, 100), two-way, one lane each way, no lights."""
    d = tmp_path_factory.mktemp("cross")
    nodes = d / "x.nod.xml"
    nodes.write_text(
        '<nodes><node id="C" x="0" y="0" type="priority"/>'
        '<node id="W" x="-100" y="0"/><node id="E" x="100" y="0"/>'
        '<node id="S" x="0" y="-100"/><node id="N" x="0" y="100"/></nodes>')
    edges = d / "x.edg.xml"
    edges.write_text(
        "<edges>" + "".join(
            f'<edge id="{a}{b}" from="{a}" to="{b}" numLanes="1" speed="13.9"/>'
            for a, b in (("W", "C"), ("C", "W"), ("E", "C"), ("C", "E"),
                         ("S", "C"), ("C", "S"), ("N", "C"), ("C", "N"))) + "</edges>")
    net = d / "x.net.xml"
    netconvert = netgenerate_path().replace("netgenerate", "netconvert")
    subprocess.run([netconvert, "-n", str(nodes), "-e", str(edges), "-o", str(net),
                    "--no-turnarounds", "true", "--offset.disable-normalization", "true"],
                   check=True, capture_output=True)
    return read_net(net)


def test_straight_on_at_a_junction(cross):
    east = [c.getToLane().getEdge().getID() for c in cross.getLane("WC_0").getOutgoing()]
    assert sorted(east) == ["CE", "CN", "CS"]  # three ways out, no turning back
    nxt = straightest(cross.getLane("WC_0"), cross)
    assert nxt[-1].getID() == "CE_0"  # straight on, through the junction's internal lane
    assert all(lane.getEdge().getFunction() == "internal" for lane in nxt[:-1])
    assert straightest(cross.getLane("CE_0"), cross) == []  # a dead end


def test_snap_by_position_and_heading_and_move_along(cross):
    net = RoadNetwork(cross, (0.0, 0.0), reach_m=300.0)
    we = cross.getLane("WC_0").getShape()  # westbound-to-east lane, y < 0 (right-hand)
    y = we[0][1]
    pos = torch.tensor([[-50.0, y], [-50.0, y], [-50.0, y + 40.0]])
    heading = torch.tensor([[1.0, 0.0], [-1.0, 0.0], [1.0, 0.0]])
    lane, offset = net.snap(pos, heading)
    # heading east: the WC lane, 50 m from W's end of it; heading west: the lane of CW
    # (the other side of the street); 40 m off any lane: none
    assert lane[0] == net.index["WC_0"] and lane[1] == net.index["CW_0"] and lane[2] == -1
    assert offset[0] == pytest.approx(-50.0 - we[0][0], abs=1e-3)
    # 10 m on: still on WC; past the junction: on CE, straight on, at the same y
    ahead = offset[0] + torch.tensor([[10.0, 200.0]])
    pts = net.along(lane[:1], ahead)[0]
    assert pts[0].tolist() == pytest.approx([-40.0, y], abs=1e-3)
    ce = cross.getLane("CE_0").getShape()
    assert pts[1, 1].item() == pytest.approx(ce[0][1], abs=0.5)
    assert pts[1, 0].item() > 50.0  # past the junction, heading east
    # beyond the chain's end (the dead end at E): held at its last point
    far = net.along(lane[:1], offset[:1, None] + 1000.0)[0, 0]
    assert far.tolist() == pytest.approx(list(ce[-1][:2]), abs=1e-3)


def test_road_predictions_by_hand_beside_constant_velocity(cross, monkeypatch):
    """Three vehicles: one driving east on WC at 10 m/s, one standing, one driving north
    off the network (constant velocity for it); 3 steps ahead."""
    import uabs_rl.evaluation.roads as roads

    y = cross.getLane("WC_0").getShape()[0][1]
    prev = torch.tensor([[[-60.0, -30.0, 300.0], [y, y, 300.0]]])  # [E, 2, V]
    now = torch.tensor([[[-50.0, -30.0, 300.0], [y, y, 310.0]]])
    present = torch.ones(1, 3, dtype=torch.bool)
    monkeypatch.setattr(roads, "observed",
                        lambda env, back=0: ((prev if back else now), present))
    monkeypatch.setattr(roads, "schedule", lambda env, h: {})

    class Env:
        state = {"prev_present": present}

    w = RoadAware(RoadNetwork(cross, (0.0, 0.0), reach_m=300.0))(Env(), 3)
    veh = w["veh"]  # [H, E, 2, V]
    for k in range(3):
        assert veh[k, 0, :, 0].tolist() == pytest.approx([-50.0 + 10.0 * (k + 1), y], abs=1e-3)
        assert veh[k, 0, :, 1].tolist() == pytest.approx([-30.0, y], abs=1e-6)
        assert veh[k, 0, :, 2].tolist() == pytest.approx([300.0, 310.0 + 10.0 * (k + 1)])
    assert torch.equal(w["present"], present[None].expand(4, -1, -1))


def test_the_grid_network_and_refusals(trace_cache):
    cfg, env = eval_env(trace_cache, "masking=rank", windows=2)
    assert network_file(cfg.scenario).name == "manhattan.net.xml"
    pred = make_predictor("road", "all", cfg.scenario)
    assert isinstance(pred, RoadAware) and pred.network.chain_pts.shape[0] > 0
    with pytest.raises(ValueError, match="needs the scenario"):
        make_predictor("road")


def test_a_sumocfg_scenario_reads_the_network_it_names(tmp_path):
    from uabs_rl.config import compose

    cfg = compose("config", ["scenario=bologna"])
    assert ".net.xml" in network_file(cfg.scenario).name
    empty = tmp_path / "empty.sumocfg"
    empty.write_text("<configuration><input/></configuration>")
    cfg.scenario.sumo.sumocfg = str(empty)
    with pytest.raises(ConfigError, match="names no network file"):
        network_file(cfg.scenario)


def test_road_never_reads_after_step_t_and_flies_legal_moves(trace_cache):
    """The mpc with the road predictor on the grid's windows: the same actions when every
    trace row after step t is garbage while it predicts; no collision, no proximity event,
    no fallback."""
    cfg, env = eval_env(trace_cache, "masking=rank", windows=2)
    road = make_predictor("road", "all", cfg.scenario)

    class PoisonedRoad(Predictor):
        def __call__(self, env, horizon):
            return poisoned(road, env, horizon)

    rec, td = rollout(cfg, env, "mpc", horizon=3, predictor=road)
    _, td_p = rollout(cfg, env, "mpc", horizon=3, predictor=PoisonedRoad())
    assert torch.equal(td_p.get(ACTION), td.get(ACTION))
    assert rec["collisions"] == rec["proximity"] == rec["fallbacks"] == 0
