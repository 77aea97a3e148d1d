"""A real district and fixed-demand scenarios: the Bologna preset (sumo/bologna_acosta),
time-split traces for route-file demand, the masks over a sparse street network at
M = 25, and the OpenStreetMap walkthrough of sumo/README.md run offline."""

from __future__ import annotations

import copy
import hashlib
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.conftest import compose_cfg
from tests.test_masking import assert_never_below_d_th
from uabs_rl.config import (
    PROJECT_ROOT,
    ChannelConfig,
    ConfigError,
    MaskingConfig,
    ObsConfig,
    split_time_range,
    validate_scenario_traces,
)
from uabs_rl.env.uabs_env import OBS
from uabs_rl.safety.make import make_env, make_selector
from uabs_rl.traces.build import get_traces, thinning
from uabs_rl.traces.cache import TraceSet, cache_path, split_key

FOLDER = PROJECT_ROOT / "sumo" / "bologna_acosta"
SPLITS = ("train", "eval", "test")
# Bologna at small durations: 2.5 min of warm-up (~350 vehicles present), 45 s of
# training, 10 s of validation and test, one simulation each
SMALL = ["traces.workers=1", *(f"traces.{s}.{k}={v}" for s in SPLITS
                               for k, v in [("n_sims", 1), ("warmup_s", 150)]),
         "traces.train.duration_s=45", "traces.eval.duration_s=10", "traces.test.duration_s=10"]


def bologna(*overrides: str):
    return compose_cfg("build_traces", ["scenario=bologna", *overrides])


def ranges(cfg) -> list[tuple[float, float]]:
    return [split_time_range(cfg.scenario, cfg.traces, s) for s in SPLITS]


def test_fixed_demand_default_splits_are_disjoint_in_time(tmp_path):
    """Bologna's preset: 10-40, 40-45 and 45-60 min. Any route-file scenario left at the
    defaults: one split after another. A fleet scenario records from its warm-up on, as
    before, and its cache key does not hold a time range."""
    assert ranges(bologna()) == [(600, 2400), (2400, 2700), (2700, 3600)]
    routes = tmp_path / "r.rou.xml"
    routes.write_text("<routes/>")
    cfg = compose_cfg("build_traces", ["scenario.sumo.fleet_size=0",
                                       f"scenario.sumo.route_files=[{routes}]"])
    (a0, a1), (b0, b1), (c0, c1) = ranges(cfg)
    assert a0 == 60 and a1 <= b0 and b1 <= c0  # warm-up 60 s, train 8 x 3600 s, ...
    validate_scenario_traces(cfg.scenario, cfg.traces)
    fleet = compose_cfg("build_traces", [])
    assert ranges(fleet) == [(60, 3660), (60, 660), (60, 660)]  # seeds keep them apart
    for s in SPLITS:
        assert "begin_s" not in split_key(fleet.scenario, getattr(fleet.traces, s), s)[1]


@pytest.mark.parametrize("overrides,named", [
    (["traces.eval.begin_s=0"], "eval"),  # validation on the training range
    (["traces.test.begin_s=1000"], "test"),  # test inside the training range
    # training over the test range (test left null, after the validation range)
    (["traces.eval.begin_s=1800", "traces.train.begin_s=2500"], "train"),
    (["traces.test.begin_s=1700", "traces.train.begin_s=0"], "test"),  # both set: the later
    (["traces.eval.begin_s=1800", "traces.eval.warmup_s=300"], "eval"),  # warm-up counts
])
def test_overlapping_time_ranges_of_a_fixed_demand_are_refused(overrides, named):
    """Refused naming the split's setting, with a begin_s that clears every split: the
    command line with that value is accepted."""
    cfg = bologna(*overrides)
    with pytest.raises(ConfigError, match=rf"^traces\.{named}\.begin_s=\S+ makes the {named} "
                                          rf"time range .* disjoint time ranges") as e:
        validate_scenario_traces(cfg.scenario, cfg.traces)
    advised = re.search(rf"Move traces\.{named}\.begin_s (?:to |past the \w+ range "
                        rf"\(begin_s >= )([0-9.]+)", str(e.value)).group(1)
    fixed = [o for o in overrides if not o.startswith(f"traces.{named}.begin_s=")]
    cfg = bologna(*fixed, f"traces.{named}.begin_s={advised}")
    validate_scenario_traces(cfg.scenario, cfg.traces)


def test_a_fixed_demand_recorded_while_it_drains_is_named():
    """Traces whose vehicles thin out to under half within the range (a begin_s past the
    demand's hour) get a warning naming begin_s; a steady count and a fleet get none."""
    def traces(counts):
        present = torch.zeros(2, len(counts), 700, dtype=torch.bool)
        for t, c in enumerate(counts):
            present[:, t, :c] = True
        return TraceSet(torch.zeros(2, len(counts), 700, 2), present, {"split": "test"})

    fixed = bologna().scenario
    fleet = compose_cfg("build_traces", []).scenario
    draining = traces([600] * 50 + [130] * 50)
    assert thinning(draining, fixed, "test") == (
        "the test traces' vehicles thin out within the recorded range, from 600 present per "
        "step in its first tenth to 130 in its last: the demand of scenario.sumo.sumocfg "
        "ends or drains there. Move traces.test.begin_s earlier (or leave it null) to "
        "record while it lasts.")
    assert thinning(draining, fixed, "test", begin_given=False).endswith(
        "traces.test.begin_s is null, so the test range follows the earlier splits': "
        "shorten their duration_s to record it while the demand lasts.")
    assert thinning(traces([600] * 50 + [310] * 50), fixed, "test") is None  # over half
    assert thinning(draining, fleet, "test") is None


def test_fleet_scenarios_take_any_time_range():
    """Seeds keep a fleet scenario's splits apart: begin_s may overlap there."""
    cfg = compose_cfg("build_traces", ["traces.eval.begin_s=0", "traces.test.begin_s=30"])
    validate_scenario_traces(cfg.scenario, cfg.traces)


def test_the_time_range_is_part_of_the_cache_key(trace_cache):
    at = {b: cache_path(c.scenario, c.traces, "test").name for b, c in [
        ("null", bologna(f"traces.cache_dir={trace_cache}")),
        ("2100", bologna(f"traces.cache_dir={trace_cache}", "traces.test.begin_s=2100")),
        ("2200", bologna(f"traces.cache_dir={trace_cache}", "traces.test.begin_s=2200"))]}
    assert at["null"] == at["2100"] != at["2200"]
    fleet = [compose_cfg("build_traces", [f"traces.cache_dir={trace_cache}", *o])
             for o in ([], ["traces.train.begin_s=0"])]
    assert len({cache_path(c.scenario, c.traces, "train") for c in fleet}) == 1


def snapshot(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def git_status(*paths: Path) -> str:
    out = subprocess.run(["git", "status", "--porcelain", "--ignored", "--", *map(str, paths)],
                         cwd=PROJECT_ROOT, capture_output=True, text=True)
    return out.stdout if out.returncode == 0 else "(not a git checkout)"


@pytest.fixture(scope="module")
def bologna_traces(tmp_path_factory):
    """The preset's three splits at small durations, built in a fresh cache from a
    scratch working folder, and the folder's files and git status before and after."""
    work, cache = tmp_path_factory.mktemp("work"), tmp_path_factory.mktemp("cache")
    before = snapshot(FOLDER), git_status(FOLDER)
    cwd = Path.cwd()
    os.chdir(work)
    try:
        cfg = bologna(f"traces.cache_dir={cache}", *SMALL)
        sets = {s: get_traces(cfg.scenario, cfg.traces, s, verbose=False) for s in SPLITS}
    finally:
        os.chdir(cwd)
    return cfg, sets, before, (snapshot(FOLDER), git_status(FOLDER)), work


def test_bologna_builds_its_traces_without_writing_into_the_repository(bologna_traces):
    cfg, sets, before, after, work = bologna_traces
    assert after == before  # no detector output, trip info or log in sumo/bologna_acosta
    assert list(work.iterdir()) == []  # nor in the working folder
    assert all(ts.source == "built" for ts in sets.values())
    for s, ts in sets.items():
        n = ts.present.sum(-1)
        assert n.min() > 250, s  # the district has filled for 2.5 min
        x, y = ts.positions[..., 0][ts.present], ts.positions[..., 1][ts.present]
        assert x.min() >= 0 and y.min() >= 0 and x.max() <= cfg.scenario.area.width \
            and y.max() <= cfg.scenario.area.height
    assert [sets[s].meta.get("begin_s") for s in SPLITS] == [None, 45.0, 55.0]
    assert ranges(cfg) == [(150, 195), (195, 205), (205, 215)]


@pytest.mark.parametrize("mode,frame", [("flat", "fleet"), ("rank", "egocentric")])
def test_masks_keep_every_pair_apart_over_bologna_at_m25(bologna_traces, mode, frame):
    """M = 25 over 1820 m x 1358 m where the streets cover a small part of the area:
    start positions, the recoverable masks under the random legal policy (ε = 1) over
    two episodes, and the observations (the egocentric one scores every move against
    ~350 vehicles: 4 envs x 40 steps cost seconds); no pair ever closer than d_th."""
    cfg, sets, *_ = bologna_traces
    sc = copy.deepcopy(cfg.scenario)
    assert sc.n_uabs == 25
    sc.episode_steps = 20
    env = make_env(sc, ChannelConfig(), MaskingConfig(mode=mode, recoverable=True),
                   sets["train"], n_envs=4, seed=1, obs=ObsConfig(frame=frame))
    sel = make_selector(env, eps=1.0, generator=torch.Generator().manual_seed(1))
    env.set_seed(1)
    td = env.rollout(40, policy=sel, break_when_any_done=False)
    assert_never_below_d_th(td, env.base_env.params)
    assert td[OBS].shape[:3] == (4, 40, 25) and torch.isfinite(td[OBS]).all()


def walkthrough_block() -> str:
    """The bash block of sumo/README.md's OpenStreetMap walkthrough."""
    text = (PROJECT_ROOT / "sumo" / "README.md").read_text()
    m = re.search(r"<!-- osm-walkthrough -->\n```bash\n(.*?)```", text, flags=re.S)
    assert m, "sumo/README.md lost its osm-walkthrough block"
    return m.group(1)


def test_osm_walkthrough_builds_traces_offline(tmp_path):
    """sumo/README.md's walkthrough as written, on the OpenStreetMap extract the
    eclipse-sumo wheel ships (no network access), then uabs-traces at small durations."""
    import sumo

    osm = Path(sumo.__file__).parent / "tools" / "game" / "racing" / "spreewaldring.osm"
    env = dict(os.environ, OSM=str(osm),
               PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    proc = subprocess.run(["bash", "-euo", "pipefail", "-c", walkthrough_block()], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    preset = (tmp_path / "myconf" / "scenario" / "mycity.yaml").read_text()
    assert re.search(r"area: \{x_min: -?\d+, y_min: -?\d+, width: \d+, height: \d+\}", preset)
    small = [f"traces.{s}.{k}={v}" for s in SPLITS
             for k, v in [("n_sims", 1), ("warmup_s", 120), ("duration_s", 30)]]
    proc = subprocess.run(
        [str(Path(sys.executable).parent / "uabs-traces"), "--config-dir", "myconf",
         "scenario=mycity", f"traces.cache_dir={tmp_path / 'cache'}", "traces.workers=1",
         *small], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    built = re.findall(r"^mycity built with SUMO .*: (\w+): 1 sims x 30 steps x \d+ slots, "
                       r"vehicles present per step ([\d.]+)", proc.stdout, flags=re.M)
    assert [s for s, _ in built] == list(SPLITS), proc.stdout
    assert all(float(n) >= 5 for _, n in built)


def test_a_negative_begin_is_refused():
    cfg = compose_cfg("build_traces", ["traces.train.begin_s=-5"])
    with pytest.raises(ConfigError, match=r"^traces\.train\.begin_s must be in \[0, 10\^7\] s, "
                                          r"got -5\.0\.$"):
        validate_scenario_traces(cfg.scenario, cfg.traces)
