"""The SUMO trace pipeline, on a small real simulation (20 vehicles, 60 s)."""

from __future__ import annotations

import copy
import logging
import subprocess
import sys

import pytest
import sumolib
import torch
from hydra.errors import ConfigCompositionException
from omegaconf.errors import ConfigKeyError, ValidationError

from tests.conftest import SMALL_TRACES, compose_cfg
from uabs_rl.config import ConfigError, resolve_path
from uabs_rl.traces import build as traces_mod
from uabs_rl.traces.build import build_split, get_traces
from uabs_rl.traces.cache import cache_path, load_traceset


def test_shapes_and_dtypes(train, held_out):
    assert train.positions.shape == (2, 60, 20, 2)
    assert train.present.shape == (2, 60, 20)
    assert train.positions.dtype == torch.float32 and train.present.dtype == torch.bool
    assert held_out.positions.shape == (1, 60, 20, 2)
    assert train.meta["seeds"] == [0, 1] and held_out.meta["seeds"] == [10000]
    assert train.meta["sumo_version"] == "1.28.0" and train.meta["dt"] == 1.0


def test_every_present_vehicle_is_inside_the_area_and_on_a_road(small_traces_cfg, train):
    area = small_traces_cfg.scenario.area
    xy = train.positions[train.present]
    assert len(xy) > 0
    assert (xy[:, 0] >= 0).all() and (xy[:, 0] <= area.width).all()
    assert (xy[:, 1] >= 0).all() and (xy[:, 1] <= area.height).all()
    net = sumolib.net.readNet(
        str(resolve_path(small_traces_cfg.scenario.sumo.net_file, "net")), withInternal=True)
    sample = xy[:: max(1, len(xy) // 300)]
    for x, y in sample.tolist():
        lanes = net.getNeighboringLanes(x + area.x_min, y + area.y_min, r=0.5)
        assert lanes, f"vehicle at ({x:.1f}, {y:.1f}) is more than 0.5 m from every lane"


def test_absent_slots_hold_zeros(train):
    assert (train.positions[~train.present] == 0).all()


def test_presence_never_drops_once_the_fleet_is_in(train, held_out):
    for ts in (train, held_out):
        n = ts.present.sum(-1)  # [sims, steps]
        assert (n[:, -1] == 20).all()
        full = n == 20
        first_full = full.int().argmax(dim=1)
        for s in range(ts.n_sims):
            assert full[s, first_full[s]:].all(), "a fleet vehicle vanished"


def test_same_seed_gives_identical_traces(small_traces_cfg, train):
    again = build_split(small_traces_cfg.scenario, small_traces_cfg.traces.train, "train",
                        workers=1)
    assert torch.equal(again.positions, train.positions)
    assert torch.equal(again.present, train.present)


def test_training_and_held_out_traces_differ(train, held_out):
    assert not torch.allclose(train.positions[0], held_out.positions[0])
    assert set(train.meta["seeds"]).isdisjoint(held_out.meta["seeds"])


def test_vehicles_move(train):
    step = (train.positions[:, 1:] - train.positions[:, :-1]).norm(dim=-1)
    both = train.present[:, 1:] & train.present[:, :-1]
    speeds = step[both]
    assert speeds.mean() > 1.0  # m/s: the fleet is not gridlocked
    assert speeds.max() < 20.0  # no jump beyond the 13.9 m/s speed limit plus slack


def test_cache_hit_does_not_run_sumo(small_traces_cfg, train, monkeypatch):
    def boom(*_a, **_k):
        raise AssertionError("SUMO was started on a cache hit")

    monkeypatch.setattr(traces_mod, "run_simulation", boom)
    monkeypatch.setattr(traces_mod, "build_split", boom)
    again = get_traces(small_traces_cfg.scenario, small_traces_cfg.traces, "train")
    assert again.source == "cache"
    assert torch.equal(again.positions, train.positions)


def test_cache_key_changes_with_parameters(small_traces_cfg):
    scenario, traces = small_traces_cfg.scenario, small_traces_cfg.traces
    base = cache_path(scenario, traces, "train")
    other = copy.deepcopy(scenario)
    other.sumo.fleet_size = 21
    assert cache_path(other, traces, "train") != base
    other_traces = copy.deepcopy(traces)
    other_traces.train.first_seed = 5
    assert cache_path(scenario, other_traces, "train") != base
    other_traces = copy.deepcopy(traces)
    other_traces.eval.n_sims = 3  # the eval split does not change the train file
    assert cache_path(scenario, other_traces, "train") == base


@pytest.mark.parametrize("damage", ["truncate", "flip"])
def test_corrupt_cache_is_detected_and_rebuilt(small_traces_cfg, held_out, damage, caplog):
    path = cache_path(small_traces_cfg.scenario, small_traces_cfg.traces, "eval")
    data = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(data[: len(data) // 2])
    else:  # alter one position value but keep a valid file
        blob = torch.load(path, weights_only=True)
        blob["positions"][0, 5, 3, 0] += 1.0
        torch.save(blob, path)
    with caplog.at_level(logging.WARNING, logger="uabs_rl.traces.cache"):
        rebuilt = get_traces(small_traces_cfg.scenario, small_traces_cfg.traces, "eval")
    assert rebuilt.source == "built"
    assert "damaged" in caplog.text and str(path) in caplog.text
    assert torch.equal(rebuilt.positions, held_out.positions)
    assert load_traceset(path).source == "cache"  # the rebuilt file is sound


def test_missing_network_file_names_the_key(trace_cache):
    cfg = compose_cfg("build_traces", SMALL_TRACES + [f"traces.cache_dir={trace_cache}",
                                                "scenario.sumo.net_file=nowhere.net.xml"])
    with pytest.raises(ConfigError, match=r"scenario\.sumo\.net_file.*not found"):
        get_traces(cfg.scenario, cfg.traces, "train")


def test_area_that_does_not_contain_the_network_names_the_key(trace_cache):
    cfg = compose_cfg("build_traces", SMALL_TRACES + [f"traces.cache_dir={trace_cache}",
                                                "scenario.area.width=200"])
    with pytest.raises(ConfigError, match=r"scenario\.area .*does not contain"):
        get_traces(cfg.scenario, cfg.traces, "train")


def test_fleet_of_zero_names_the_key(trace_cache):
    cfg = compose_cfg("build_traces", SMALL_TRACES + [f"traces.cache_dir={trace_cache}",
                                                "scenario.sumo.fleet_size=0"])
    with pytest.raises(ConfigError, match=r"scenario\.sumo\.fleet_size"):
        get_traces(cfg.scenario, cfg.traces, "train")


def test_overlapping_seeds_are_refused(trace_cache):
    cfg = compose_cfg("build_traces", SMALL_TRACES + [f"traces.cache_dir={trace_cache}",
                                                "traces.eval.first_seed=1"])
    with pytest.raises(ConfigError, match=r"traces\.eval\.first_seed"):
        get_traces(cfg.scenario, cfg.traces, "eval")


@pytest.mark.parametrize("override,key", [
    ("scenario.sumo.fleet_sise=3", "fleet_sise"),
    ("+traces.train.seeds=3", "seeds"),
    ("traces.train.n_sims=many", "n_sims"),
])
def test_unknown_or_mistyped_option_names_the_key(override, key):
    with pytest.raises((ConfigCompositionException, ConfigKeyError, ValidationError,
                        ConfigError)) as e:
        compose_cfg("build_traces", [override])
    assert key in str(e.value) + str(e.value.__cause__)


def test_user_scenario_with_route_file(tmp_path, trace_cache):
    """A user's own routes: vehicles enter and leave, slots are reused after a gap."""
    routes = tmp_path / "flows.rou.xml"
    routes.write_text(
        '<routes>\n'
        '  <flow id="east" begin="0" end="60" period="4" from="A0B0" to="G0H0"/>\n'
        '  <flow id="north" begin="0" end="60" period="6" from="A0A1" to="A3A4"/>\n'
        '</routes>\n')
    cfg = compose_cfg("build_traces", [
        f"traces.cache_dir={trace_cache}", "scenario.sumo.fleet_size=0",
        f"scenario.sumo.route_files=[{routes}]", "traces.train.n_sims=1",
        "traces.train.duration_s=80", "traces.train.warmup_s=0", "traces.workers=1"])
    ts = get_traces(cfg.scenario, cfg.traces, "train")
    n = ts.present[0].sum(-1)
    assert n.max() >= 3 and n[-1] < n.max()  # flows stop at 60 s: the count drains
    # 15 + 10 vehicles: each is one presence run of its own slot, and slots are reused
    p = ts.present[0].int()
    runs = int(p[0].sum() + (p[1:] - p[:-1] == 1).sum())
    assert runs == 25
    assert ts.max_vehicles < 25


def tiny_netgcfg(tmp_path, monkeypatch) -> None:
    """``g/tiny.netgcfg`` (a 3 x 3 grid) under ``tmp_path``, the working folder."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "g").mkdir()
    (tmp_path / "g" / "tiny.netgcfg").write_text(
        '<netgenerateConfiguration><grid_network><grid value="true"/>'
        '<grid.number value="3"/><grid.length value="50"/></grid_network>'
        '</netgenerateConfiguration>')


def test_net_file_is_built_from_its_netgcfg(tmp_path, monkeypatch):
    """A network kept in the repository as its netgenerate config (sumo/city) is built
    on first use, next to the config, and then found as any network."""
    from uabs_rl.traces.inputs import net_file

    tiny_netgcfg(tmp_path, monkeypatch)
    built = net_file("g/tiny.net.xml")
    assert built == (tmp_path / "g" / "tiny.net.xml").resolve() and built.stat().st_size > 1000
    assert [p.name for p in (tmp_path / "g").iterdir() if p.name.startswith(".")] == []
    mtime = built.stat().st_mtime_ns
    assert net_file("g/tiny.net.xml") == built and built.stat().st_mtime_ns == mtime
    (tmp_path / "g" / "bad.netgcfg").write_text("<netgenerateConfiguration><nonsense/>")
    with pytest.raises(ConfigError, match="netgenerate failed"):
        net_file("g/bad.net.xml")
    assert not (tmp_path / "g" / "bad.net.xml").exists()
    with pytest.raises(ConfigError, match="file not found"):
        net_file("g/absent.net.xml")


def test_two_builds_of_a_network_are_byte_identical(tmp_path, monkeypatch):
    """netgenerate writes its start time and the temporary output name into the header:
    both are normalised, so a fresh checkout's build keys the same cached traces."""
    from uabs_rl.traces.inputs import net_file

    tiny_netgcfg(tmp_path, monkeypatch)
    first = net_file("g/tiny.net.xml").read_bytes()
    (tmp_path / "g" / "tiny.net.xml").unlink()
    assert net_file("g/tiny.net.xml").read_bytes() == first
    assert b"generated on" not in first and b".tmp" not in first


def test_city_scenario_holds_its_fleet():
    """scenario=city: 2 km x 1 km, 2000 vehicles, 25 UABS, traces sized for it; the
    recoverable masks' start spacing fits 30 UABS and more."""
    from uabs_rl.env.geometry import lattice_packing
    from uabs_rl.env.params import EnvParams

    cfg = compose_cfg("config", ["scenario=city"])
    sc = cfg.scenario
    assert (sc.name, sc.n_uabs, sc.sumo.fleet_size) == ("city", 25, 2000)
    assert (sc.area.width, sc.area.height) == (2004, 1004)
    assert cfg.traces.train.n_sims == 2 and cfg.traces.train.duration_s == 900
    from uabs_rl.env.uabs_env import window_count

    ev = cfg.traces.eval
    steps = int(ev.duration_s / sc.dt)
    assert window_count(ev.n_sims, steps, sc.episode_steps) >= cfg.train.eval_windows
    p = EnvParams.from_config(sc, cfg.channel)
    assert lattice_packing(p, p.d_th + 2 * sc.speed * sc.dt).shape[0] >= 30


def test_the_package_serves_every_public_name_and_a_worker_starts_without_torch():
    """``uabs_rl.traces`` exports each room's public names (loaded on first use), so a
    SUMO worker, which imports the package, still starts without torch."""
    import uabs_rl.traces as traces
    from uabs_rl.traces import build, cache, inputs

    for name in traces.__all__:
        home = next(m for m in (inputs, cache, build) if hasattr(m, name))
        assert getattr(traces, name) is getattr(home, name), name
    probe = ("import sys, uabs_rl.traces, uabs_rl.traces.sumo_sim; "
             "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"
