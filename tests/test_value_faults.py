"""Bad values and runs that go wrong (issue #35): every number has a finite range checked
at start-up, a value that would fail late is refused before any work, a setting typed
twice is refused before Hydra runs, a diverging run stops keeping its last good
checkpoint, and a window without a vehicle has no served fraction or P_g."""

from __future__ import annotations

import copy
import json
import math
import typing
from dataclasses import fields, is_dataclass, replace
from pathlib import Path

import pytest
import torch

from tests.conftest import Ran, run_command
from tests.test_train import smoke
from uabs_rl import config
from uabs_rl.config import (
    RANGES,
    ConfigError,
    RunConfig,
    check_duplicate_overrides,
)
from uabs_rl.training.startup import validate_run

NUMBER = (int, float)


def numeric_fields(cls: type = RunConfig, prefix: str = "") -> list[tuple[str, type, type]]:
    """``(key, owning dataclass, number type)`` of every int / float setting (lists of
    them and ``| None`` included) under ``cls``."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in fields(cls):
        t = hints[f.name]
        if is_dataclass(t):
            out += numeric_fields(t, f"{prefix}{f.name}.")
            continue
        args = [a for a in typing.get_args(t) if a is not type(None)] or [t]
        inner = [b for a in args for b in (typing.get_args(a) or [a])]
        kind = next((a for a in inner if a in NUMBER and a is not bool), None)
        if kind is not None:
            out.append((f"{prefix}{f.name}", cls, kind))
    return out


NUMERIC = numeric_fields()


def test_every_number_of_every_config_has_a_range():
    assert len(NUMERIC) > 60
    missing = [key for key, cls, _ in NUMERIC if key.rsplit(".", 1)[-1] not in RANGES.get(cls, {})]
    assert missing == []
    assert RANGES[config.TracesAppConfig] == RANGES[RunConfig]


@pytest.fixture(scope="module")
def base(trace_cache):
    return smoke(trace_cache)


def _set(cfg: RunConfig, key: str, value) -> RunConfig:
    cfg = copy.deepcopy(cfg)
    *path, name = key.split(".")
    obj = cfg
    for p in path:
        obj = getattr(obj, p)
    setattr(obj, name, [value] if isinstance(getattr(obj, name), list) else value)
    return cfg


def _extremes(kind: type) -> list:
    if kind is int:
        return [10 ** 30, -10 ** 30]
    return [math.nan, math.inf, -math.inf, 1e308, -1e308]


@pytest.mark.parametrize("key,kind", [(k, t) for k, _, t in NUMERIC])
def test_nan_inf_and_extreme_numbers_are_refused_naming_the_setting(base, key, kind):
    section, _, name = key.rpartition(".")
    for value in _extremes(kind):
        with pytest.raises(ConfigError) as e:
            validate_run(_set(base, key, value))
        msg = str(e.value)
        assert "\n" not in msg
        assert key in msg or (msg.startswith(section) and name in msg), (value, msg)


@pytest.mark.parametrize("override,message", [
    ("algo.lr=1e308", "algo.lr must be in (0, 1], got 1e+308."),
    ("scenario.altitude=1e308", "scenario.altitude must be in (0, 10000] m, got 1e+308."),
    ("scenario.speed=1e-300", "scenario.speed must be in [0.01, 1000] m/s, got 1e-300."),
    ("scenario.area.width=1e308", "scenario.area.width must be in (0, 100000] m, got 1e+308."),
    ("scenario.lambda_c=1e308", "scenario.lambda_c must be in [0, 1000000], got 1e+308."),
    ("train.episodes=99999999999999999999999",
     "train.episodes must be in [1, 10^9], got 99999999999999999999999."),
    ("train.eval_seed=-1", "train.eval_seed must be in [0, 2^64) (TorchRL's env.set_seed "
     "hands it to numpy, which takes no negative seed), got -1."),
    ("scenario.dt=1e-9", "scenario.dt must be in [0.001, 3600] s, got 1e-09."),
    ("channel.fov_deg=180", "channel.fov_deg must be in (0, 180), got 180.0."),
    ("algo.hidden=[32,100000]", "algo.hidden (each entry) must be in [1, 65536], got 100000."),
    ("train.eval_windows=5", "train.eval_windows=5 but the eval traces hold 4 non-overlapping "
     "windows of 20 steps (21 recorded instants each; 1 x 100 instants): lower "
     "train.eval_windows or raise "
     "traces.eval.n_sims / traces.eval.duration_s."),
    ("scenario.speed=0.05", "scenario.area / (scenario.speed x scenario.dt) must give at most "
     "20000 lattice points (the start positions compare every pair of them), got 2.38e+07 "
     "(350 m x 170 m at a pitch of 0.05 m): raise scenario.speed or scenario.dt, or shrink "
     "scenario.area."),
    ("family=[{},{name:wide,area:{width:1e308}}]",
     "family[1].area.width must be in (0, 100000] m, got 1e+308."),
])
def test_the_issue_values_are_refused_at_start_up(trace_cache, override, message):
    with pytest.raises(ConfigError) as e:
        validate_run(smoke(trace_cache, override))
    assert str(e.value) == message


def test_the_bounds_hold_every_preset():
    """The largest preset (scenario=city: 25 UABS, 2000 vehicles, 5151 lattice points)
    sits inside every range; tests/test_validation.py validates every preset."""
    cfg = config.compose("config", ["scenario=city"])
    assert config.lattice_points(cfg.scenario) == 101 * 51
    validate_run(cfg)


# ----------------------------------------------------------------------------- twice
@pytest.mark.parametrize("argv,message", [
    (["masking=flat", "masking=penalty"], "masking is given twice on the command line "
     "(masking=flat, masking=penalty): give it once (a sweep over several values: -m "
     "masking=flat,penalty)."),
    (["seed=1", "train.episodes=3", "seed=2"], "seed is given twice"),
    (["-m", "seed=1,2", "seed=3"], "seed is given twice"),
    (["+algo.lr=1e-3", "algo.lr=1e-4"], "algo.lr is given twice"),
    (["hydra.run.dir=a", "hydra.run.dir=b"], "hydra.run.dir is given twice"),
    # resume= appends hydra.run.dir=<the same folder>: typed twice it is three
    (["hydra.run.dir=x", "hydra.run.dir=y", "resume='x'", "hydra.run.dir='x'"],
     "hydra.run.dir is given twice"),
])
def test_a_setting_typed_twice_is_refused(argv, message):
    with pytest.raises(ConfigError, match=f"^{message.replace('(', '.').replace(')', '.')}"):
        check_duplicate_overrides(argv)


@pytest.mark.parametrize("argv", [
    ["masking=flat", "masking.mode=rank"],  # a group and a field of it
    ["hydra.run.dir=x", "resume='x'", "hydra.run.dir='x'"],  # typed once, appended once
    ["--cfg", "job", "seed=1"], ["-cn", "config", "seed=1"], ["--info", "all", "seed=1"],
    ["-m", "seed=1,2,3", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2"],
])
def test_settings_typed_once_pass(argv):
    check_duplicate_overrides(argv)


def _one_line_error(proc: Ran) -> str:
    """The one line of stderr (besides a run's "run folder: ..."), "error: ..."."""
    lines = [line for line in proc.stderr.splitlines() if line.strip()
             and not line.startswith("run folder: ")]
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    return lines[0]


@pytest.mark.parametrize("module", ["train", "traces"])
def test_the_commands_refuse_a_setting_typed_twice_before_hydra(tmp_path, module):
    proc = run_command(module, "experiment=smoke", "masking=flat", "masking=penalty",
                       f"traces.cache_dir={tmp_path / 'cache'}",
                       f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert _one_line_error(proc).startswith("error: masking is given twice")
    assert list(tmp_path.iterdir()) == []


def test_a_negative_eval_seed_fails_before_training(tmp_path, trace_cache):
    """It used to train 3 episodes, then fail with a traceback at the first evaluation."""
    proc = run_command("train", "experiment=smoke", "train.eval_seed=-1", "train.threads=1",
                       f"traces.cache_dir={trace_cache}", f"hydra.run.dir={tmp_path / 'run'}",
                       cwd=tmp_path)
    assert _one_line_error(proc).startswith("error: train.eval_seed must be in [0, 2^64)")
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- NaN
# a run that diverges: after update `at`, the Q-network's weights are NaN (what a
# learning rate far too large does), then the command runs as uabs-train
def diverge_after(monkeypatch, at: int) -> None:
    from uabs_rl.algorithms.dqn3 import DQN3

    update = DQN3.update

    def diverging(self, batch):
        out = update(self, batch)
        if self.updates >= at:
            with torch.no_grad():
                next(self.policy.parameters()).fill_(float("nan"))
        return out

    monkeypatch.setattr(DQN3, "update", diverging)


@pytest.fixture(scope="module")
def smoke_cache(trace_cache) -> Path:
    """``trace_cache`` holding the smoke preset's traces (their build prints progress)."""
    from uabs_rl.traces.build import get_traces

    cfg = smoke(trace_cache)
    for split in ("train", "eval"):
        get_traces(cfg.scenario, cfg.traces, split, verbose=False)
    return trace_cache


def _finite_checkpoint(path: Path) -> int:
    """The episode of the checkpoint at ``path``, whose weights must all be finite."""
    state = torch.load(path, weights_only=False, map_location="cpu")
    for part in ("qnet", "target"):
        assert all(t.isfinite().all() for t in state["learner"][part].values())
    return state["counters"]["episode"]


@pytest.mark.parametrize("at,where", [
    (50, "at episode 4: the loss is nan"),  # during episode 4: its loss
    # the last update of episode 6 (1 update per step after the buffer holds 64 agent
    # transitions, 22 steps in): the loss of the round is finite, the weights are not
    (98, "at episode 6: a network weight is not finite"),
])
def test_a_diverging_run_stops_keeping_its_last_good_checkpoint(tmp_path, smoke_cache, at,
                                                                where, monkeypatch):
    run = tmp_path / "run"
    diverge_after(monkeypatch, at)
    proc = run_command("train", "experiment=smoke", "train.threads=1", "train.progress=false",
                       "train.trajectory_images=false", f"traces.cache_dir={smoke_cache}",
                       f"hydra.run.dir={run}", cwd=tmp_path)
    line = _one_line_error(proc)
    assert line.startswith(f"error: training stopped {where}"), line
    assert "the checkpoints of episode 3 and before are kept" in line
    ckpt = run / "checkpoints"
    assert _finite_checkpoint(ckpt / "last.pt") == 3
    assert _finite_checkpoint(ckpt / "best.pt") == 3
    recs = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    train = [r["episode"] for r in recs if r["kind"] == "train"]
    assert train == ([1, 2, 3] if at == 50 else [1, 2, 3, 4, 5, 6])
    assert [r["episode"] for r in recs if r["kind"] == "eval"] == [3]
    assert all(math.isfinite(r["loss"]) for r in recs if r["kind"] == "train"
               and r["updates"] > 0)
    assert (run / ".hydra" / "config.yaml").is_file()  # the run's record stays


# ----------------------------------------------------------------------------- empty
def test_a_window_without_a_vehicle_has_no_served_fraction_or_pg(trace_cache, held_out):
    """Window 0 of the held-out traces emptied: its served fraction and P_g are NaN and
    left out of the means; window 1's figures are those it has with window 0 full."""
    from uabs_rl.algorithms.model import DuelingQNet
    from uabs_rl.evaluation.evaluator import Evaluator, greedy_policy, make_eval_env

    cfg = smoke(trace_cache)
    t = cfg.scenario.episode_steps
    present = held_out.present.clone()
    present[0, :t + 1] = False  # window 0: steps 0..T of sim 0
    empty = replace(held_out, present=present)
    out = {}
    for name, traces in (("full", held_out), ("empty", empty)):
        env = make_eval_env(cfg, traces, windows=2)
        torch.manual_seed(0)
        qnet = DuelingQNet(env.base_env.params.obs_dim, 4, [8])
        out[name], _ = Evaluator(env, 7).evaluate(greedy_policy(qnet, env, cfg))
    full, emp = out["full"], out["empty"]
    assert "no_vehicle_windows" not in full and emp["no_vehicle_windows"] == 1
    assert math.isnan(emp["served_fractions"][0]) and math.isnan(emp["pgs"][0])
    assert emp["served_fractions"][1] == full["served_fractions"][1]
    assert emp["pgs"][1] == full["pgs"][1]
    assert emp["pg"] == pytest.approx(full["pgs"][1])
    assert emp["served_fraction"] == pytest.approx(full["served_fractions"][1])


def test_paired_figures_leave_out_the_windows_without_a_vehicle():
    from uabs_rl.evaluation.planner import gap_share
    from uabs_rl.evaluation.stats import paired_difference

    a, b, c = [0.5, 0.25, 0.75], [0.25, 0.0, 0.25], [1.0, 0.5, 1.0]
    nan = math.nan
    assert paired_difference([nan, *a], [nan, *b]) == paired_difference(a, b)
    assert paired_difference(a, b)["n"] == 3
    assert gap_share([*a, nan], [*b, nan], [*c, nan]) == gap_share(a, b, c)
