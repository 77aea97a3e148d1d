"""Start-up validation of every setting: each wrong value is refused before anything is
built or written, in one line that names the setting (docs/bad_inputs.md)."""

from __future__ import annotations

import itertools
import math
import re
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from tests.conftest import run_command
from tests.test_train import smoke
from uabs_rl import config
from uabs_rl.algorithms import Dims, algorithm_class
from uabs_rl.algorithms.replay import transition_bytes
from uabs_rl.config import (
    CONF_DIR,
    AlgoConfig,
    ChannelConfig,
    ConfigError,
    MaskingConfig,
    ObsConfig,
    ScenarioConfig,
    SplitConfig,
    TracesConfig,
    compose,
    memory,
    validate_env,
    validate_masking,
    validate_scenario_traces,
)
from uabs_rl.env.params import EnvParams
from uabs_rl.env.state import state_bytes
from uabs_rl.env.uabs_env import N_ACTIONS
from uabs_rl.training.startup import validate_run

BAD = [  # (override on the smoke preset, the setting its message must name)
    ("algo.lr=inf", "algo.lr"),
    ("algo.lr=nan", "algo.lr"),
    ("algo.grad_clip=-1", "algo.grad_clip"),
    ("algo.grad_clip=0", "algo.grad_clip"),
    ("algo.grad_clip=nan", "algo.grad_clip"),
    ("algo.eps_start=nan", "algo.eps_start"),
    ("algo.eps_end=-inf", "algo.eps_end"),
    ("algo.eps_fraction=nan", "algo.eps_fraction"),
    ("algo.gamma=nan", "algo.gamma"),
    ("algo.buffer_size=0", "algo.buffer_size"),
    ("algo.learning_starts=5000", "algo.learning_starts"),  # more than the buffer holds
    ("scenario.lambda_s=nan", "scenario.lambda_s"),
    ("scenario.lambda_s=-1", "scenario.lambda_s"),
    ("scenario.lambda_c=nan", "scenario.lambda_c"),
    ("scenario.lambda_c=-1000", "scenario.lambda_c"),
    ("scenario.area.x_min=nan", "scenario.area.x_min"),
    ("scenario.area.y_min=inf", "scenario.area.y_min"),
    ("scenario.window_steps=21", "scenario.window_steps"),  # longer than episode_steps=20
    ("scenario.dt=nan", "scenario.dt"),
    ("scenario.dt=inf", "scenario.dt"),
    ("scenario.altitude=inf", "scenario.altitude"),
    ("scenario.safety_distance=nan", "scenario.safety_distance"),
    ("channel.tx_power_dbm=nan", "channel.tx_power_dbm"),
    ("channel.noise_dbm=-inf", "channel.noise_dbm"),
    ("channel.snr_threshold_db=nan", "channel.snr_threshold_db"),
    ("channel.tx_gain_db=inf", "channel.tx_gain_db"),
    ("channel.ue_height=-1", "channel.ue_height"),
    ("channel.shadow_sigma_los_db=-4", "channel.shadow_sigma_los_db"),
    ("channel.shadow_sigma_nlos_db=nan", "channel.shadow_sigma_nlos_db"),
    ("channel.outside_beam_gain_db=nan", "channel.outside_beam_gain_db"),
    ("obs.priority_scale=0", "obs.priority_scale"),
    ("obs.priority_scale=nan", "obs.priority_scale"),
    ("obs.motion=true", "obs.motion"),  # on the paper's observation: nothing to extend
    ("obs.map_radius=-1", "obs.map_radius"),
    ("obs.neighbours=-1", "obs.neighbours"),
    ("obs.edge_range=0", "obs.edge_range"),
    ("masking.flat_margin=nan", "masking.flat_margin"),
    ("masking.collider_margin=-1", "masking.collider_margin"),
    ("train.threads=0", "train.threads"),
    ("train.threads=-2", "train.threads"),
    ("seed=18446744073709551616", "seed"),  # 2^64
    ("seed=-9223372036854775809", "seed"),  # -2^63 - 1
    ("train.eval_seed=18446744073709551616", "train.eval_seed"),
    ("traces.train.duration_s=inf", "traces.train.duration_s"),
    ("traces.eval.duration_s=nan", "traces.eval.duration_s"),
    ("traces.test.warmup_s=inf", "traces.test.warmup_s"),
    ("traces.train.warmup_s=nan", "traces.train.warmup_s"),
    ("traces.train.first_seed=-1", "traces.train.first_seed"),
    ("traces.test.first_seed=2147483648", "traces.test.first_seed"),
    ("traces.train.n_sims=1000000000000", "traces.train.n_sims"),  # no 10^12 seed set built
]


@pytest.mark.parametrize("override,key", BAD)
def test_bad_values_are_refused_naming_the_setting(trace_cache, override, key):
    with pytest.raises(ConfigError, match=re.escape(key)) as e:
        validate_run(smoke(trace_cache, override))
    assert "\n" not in str(e.value)


def test_the_egocentric_map_replaces_the_lookahead_scores(trace_cache):
    with pytest.raises(ConfigError, match=r"obs\.lookahead must be false with "
                                          r"obs\.frame=egocentric"):
        validate_run(smoke(trace_cache, "obs=egocentric", "obs.lookahead=true"))
    validate_run(smoke(trace_cache, "obs=egocentric"))


def test_the_last_population_seed_must_be_a_generator_seed(trace_cache):
    top = 2 ** 64 - 1
    validate_run(smoke(trace_cache, f"seed={top}"))  # the largest seed torch takes
    validate_run(smoke(trace_cache, f"seed={-2 ** 63}"))  # and the smallest
    with pytest.raises(ConfigError, match=r"seed \+ train\.population - 1 .* got "
                                          rf"{top + 1}\."):
        validate_run(smoke(trace_cache, f"seed={top}", "train.population=2"))


def test_a_nan_step_length_is_blamed_on_the_step_length(trace_cache):
    """A NaN fails every comparison, so the area check used to take the blame."""
    with pytest.raises(ConfigError) as e:
        validate_run(smoke(trace_cache, "scenario.dt=nan"))
    assert str(e.value) == ("scenario.dt must be a finite number, got nan. Set scenario.dt "
                            "to a finite value.")


def test_the_buffer_must_hold_one_env_step_and_learning_starts(trace_cache):
    with pytest.raises(ConfigError, match=r"algo\.buffer_size must be >= train\.n_envs x "
                                          r"scenario\.n_uabs = 48 .*got 40\."):
        validate_run(smoke(trace_cache, "train.n_envs=16", "train.episodes=16",
                           "algo.batch_size=8", "algo.learning_starts=8",
                           "algo.buffer_size=40"))
    validate_run(smoke(trace_cache, "algo.learning_starts=2000"))  # = algo.buffer_size


@pytest.mark.parametrize("check,args,key", [
    (validate_scenario_traces, (ScenarioConfig(dt=math.nan), TracesConfig()), "scenario.dt"),
    (validate_scenario_traces,
     (ScenarioConfig(), TracesConfig(eval=SplitConfig(first_seed=10_000, warmup_s=math.inf))),
     "traces.eval.warmup_s"),
    (validate_env, (ScenarioConfig(lambda_c=math.nan), ChannelConfig()), "scenario.lambda_c"),
    (validate_env, (ScenarioConfig(), ChannelConfig(noise_dbm=math.inf)), "channel.noise_dbm"),
    (validate_masking, (MaskingConfig(collider_margin=math.nan),), "masking.collider_margin"),
    (EnvParams.from_config, (ScenarioConfig(), ChannelConfig(tx_power_dbm=math.nan)),
     "channel.tx_power_dbm"),
])
def test_uabs_traces_and_uabs_eval_checks_refuse_non_finite_numbers(check, args, key):
    """uabs-traces calls validate_scenario_traces; uabs-eval calls it with
    validate_masking and builds EnvParams (validate_env)."""
    with pytest.raises(ConfigError, match=rf"^{re.escape(key)} must be a finite number"):
        check(*args)


def test_every_default_and_preset_validates():
    """Every experiment x scenario x masking preset (and the defaults) passes validate_run;
    every experiment x scenario pair passes the uabs-traces checks; every option of the
    other groups (a learner, channel model or observation of yours in conf/ among them)
    passes validate_run; and every option's file names itself (its name or mode)."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    names = lambda group: [p.stem for p in (CONF_DIR / group).glob("*.yaml")]  # noqa: E731
    experiments = [[]] + [[f"experiment={e}"] for e in names("experiment")]
    combos = list(itertools.product(experiments, names("scenario"), names("masking")))
    # the package's own presets, scenarios and masks are among them (a user's own files
    # in conf/ are validated too)
    assert {"smoke", "generalist"} <= set(names("experiment"))
    assert {"manhattan", "city", "bologna", "grid6", "lights60", "lanes75"} <= set(
        names("scenario"))
    assert {"penalty", "flat", "rank"} <= set(names("masking"))
    config.register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        validate_run(config.to_container(hydra_compose("config")))
        for experiment, scenario, masking in combos:
            overrides = [*experiment, f"scenario={scenario}"]
            validate_run(config.to_container(hydra_compose(
                "config", [*overrides, f"masking={masking}"])))
            if masking == "rank":
                t = config.to_container(hydra_compose("build_traces", overrides))
                validate_scenario_traces(t.scenario, t.traces)
        for group in config.SELF_NAMES:
            for option in names(group):
                assert config.names_itself([CONF_DIR], group, option,
                                           config.SELF_NAMES[group]), f"{group}={option}"
                if group not in ("scenario", "masking"):  # those: above
                    validate_run(config.to_container(hydra_compose("config", [
                        f"{group}={option}"])))


def test_a_group_option_whose_file_does_not_name_itself_is_refused(tmp_path, trace_cache,
                                                                     monkeypatch):
    """An option named as a registered channel model (mode, learner) whose file sets no
    name (nor does an option it builds on) would run uma under that model's name:
    uabs-train refuses it before any folder (a sweep: before any job), uabs-eval
    likewise. An option of another name is a variant of what it composes, as it always
    was (a file with settings alone, or one that sets the key, or builds on an option
    that does); the key typed on the command line is the user's choice; a resumed run's
    settings are its own."""
    from uabs_rl.env import channel as ch

    mine = tmp_path / "myconf"
    for group in ("masking", "scenario", "channel"):
        (mine / group).mkdir(parents=True)
    (mine / "channel" / "umi.yaml").write_text("snr_threshold_db: 20\n")
    (mine / "masking" / "careful.yaml").write_text("recoverable: true\n")
    (mine / "masking" / "rank_boundary.yaml").write_text("mode: rank\n"
                                                         "rank_next_mask: boundary\n")
    (mine / "masking" / "careful_rank.yaml").write_text("defaults: [rank]\n")
    (mine / "scenario" / "mygrid.yaml").write_text("name: mygrid\n")
    (mine / "scenario" / "dense.yaml").write_text("defaults: [mygrid]\n"
                                                  "sumo: {fleet_size: 120}\n")
    (mine / "scenario" / "hdr.yaml").write_text("# my variant\n# @package _global_\n"
                                                "name: hdr\n")  # not Hydra's header
    from uabs_rl.cli.hydra import check_composition

    # not registered: a variant of uma (as at every earlier version)
    check_composition("config", ["--config-dir", str(mine), "channel=umi"])
    monkeypatch.setitem(ch.CHANNELS, "umi", ch.UMa)  # the user's new model, registered
    out = tmp_path / "runs"
    base = ["--config-dir", str(mine), f"traces.cache_dir={trace_cache}",
            "train.progress=false", "experiment=smoke"]
    said = (f"channel=umi: its file ({mine / 'channel' / 'umi.yaml'}) sets no name, nor "
            f"does an option it builds on, so it would run uma under the name of the "
            f"registered umi. Add the line 'name: umi' to it.")
    for extra in (["channel=umi", f"hydra.run.dir={out / 'one'}"],
                  ["channel=umi", "seed=0,1", f"hydra.sweep.dir={out / 'sweep'}"],
                  ["channel=uma,umi", f"hydra.sweep.dir={out / 's'}"]):
        sweep = ["-m"] if any("," in e for e in extra) else []
        r = run_command("train", *sweep, *base, *extra)
        assert r.returncode == 2 and said in r.stderr, r.stderr
        assert not out.exists()  # no folder: nothing written
        # the job named where a sweep's value is at fault, not where a fixed one is
        assert ("the job channel=umi of this sweep" in r.stderr) == ("channel=uma,umi" in extra)
    for extra in (["masking=careful"], ["masking=rank_boundary"], ["masking=careful_rank"],
                  ["scenario=dense"], ["scenario=hdr"], ["channel=umi", "channel.name=uma"],
                  ["channel=umi", f"resume={tmp_path / 'old_run'}"]):
        check_composition("config", ["--config-dir", str(mine), *extra])
    assert config.names_itself([CONF_DIR, mine], "scenario", "dense", "name")
    assert config.names_itself([CONF_DIR, mine], "channel", "umi", "name") is False
    assert not config.global_package((mine / "scenario" / "hdr.yaml").read_text())
    assert config.global_package((CONF_DIR / "scenario" / "city.yaml").read_text())
    # uabs-eval's group options compose the same files (the options they build on too)
    from uabs_rl.evaluation.load import with_overrides

    cfg = smoke(trace_cache)
    with pytest.raises(config.ConfigError, match=re.escape(said)):
        with_overrides(cfg, ["channel=umi"], [mine])
    assert with_overrides(cfg, ["channel=umi", "channel.name=uma"],
                          [mine]).channel.snr_threshold_db == 20
    dense = with_overrides(cfg, ["scenario=dense"], [mine]).scenario
    assert (dense.name, dense.sumo.fleet_size) == ("mygrid", 120)
    assert with_overrides(cfg, ["masking=rank_boundary"],
                          [mine]).masking.rank_next_mask == "boundary"
    assert with_overrides(cfg, ["masking=careful"], [mine]).masking.mode == "rank"


# ----------------------------------------------------------------------------- memory
@pytest.mark.parametrize("obs", [ObsConfig(), ObsConfig(lookahead=True),
                                 ObsConfig(lookahead=True, motion=True),
                                 ObsConfig(frame="egocentric", motion=True),
                                 ObsConfig(frame="egocentric", map_radius=1, neighbours=2)])
@pytest.mark.parametrize("n_uabs,n_beams", [(3, 9), (25, 16)])
def test_memory_sizes_are_the_owners_tensors(obs, n_uabs, n_beams):
    """The byte counts of the memory check, each given by its owner (the replay's
    storage, the env's state, the learner's network), are what those allocate, counted
    by hand: a transition is obs and next_obs (float32), the action (int64), both masks
    (a bool per move), the reward (float32) and a flag; an env's state is per vehicle
    18 + 4·(N + 1) bytes, per UABS 16 + 4·B + 4·(its priority scores) bytes, 48 bytes of
    counters and one step's link coordinates, 8 bytes per UABS-vehicle pair."""
    sc = ScenarioConfig(n_uabs=n_uabs)
    ch = ChannelConfig(n_beams=n_beams)
    p = EnvParams.from_config(sc, ch, obs)
    assert transition_bytes(p.obs_dim, N_ACTIONS) == 2 * 4 * p.obs_dim + 8 + 2 * 4 + 4 + 1
    assert transition_bytes(18, N_ACTIONS) == 165  # the paper's observation: 3 + 2·3 + 9
    v, n = sc.sumo.fleet_size, sc.window_steps
    assert state_bytes(p, v) == (v * (18 + 4 * (n + 1)) + n_uabs * (16 + 4 * n_beams
                                                                     + 4 * p.n_lookahead)
                                 + 48 + 8 * n_uabs * v)
    widths = [p.obs_dim, 256, 256]
    weights = p.obs_dim * 256 + 256 * 256 + 256 * (1 + N_ACTIONS)
    size = algorithm_class("dqn3").network_size(AlgoConfig(), Dims(p.obs_dim, N_ACTIONS,
                                                                     n_uabs))
    assert size.multiply_adds == weights
    assert size.parameter_bytes == 4 * (weights + sum(widths[1:]) + 1 + N_ACTIONS)


@pytest.fixture
def one_mib(monkeypatch):
    """A machine with 1 MiB available; the smoke preset needs about 0.4 MiB."""
    monkeypatch.setattr(memory, "available_memory", lambda device: (2 ** 20,
                                                                    "this machine has"))


@pytest.mark.parametrize("overrides,message", [
    (["algo.buffer_size=10000"], "algo.buffer_size: the replay buffer (10000 transitions "
     "of 165 bytes x train.population=1) would need at least 1.574 MiB, but this machine "
     "has 1 MiB available: lower algo.buffer_size or train.population."),
    (["train.population=4"], "algo.buffer_size: the replay buffer (2000 transitions of 165 "
     "bytes x train.population=4) would need at least 1.259 MiB, but this machine has "
     "1 MiB available: lower algo.buffer_size or train.population."),
    (["train.n_envs=1000", "train.episodes=1000", "algo.buffer_size=3000"],
     "train.n_envs: 1000 x train.population=1 training envs (1.879 KiB each) would need at "
     "least 1.835 MiB, but this machine has 1 MiB available: lower train.n_envs or "
     "train.population."),
    (["algo.hidden=[512,512]"], "algo.hidden: the Q-network (with target copy, gradients "
     "and Adam's moments) would need at least 5.244 MiB, but this machine has 1 MiB "
     "available: narrow algo.hidden or lower train.population."),
    (["traces.train.duration_s=10000"], "traces.train.n_sims x traces.train.duration_s: the "
     "train traces would need at least 1.717 MiB, but this machine has 1 MiB available: "
     "lower traces.train.n_sims or traces.train.duration_s."),
    (["algo.buffer_size=6000"], "algo.buffer_size, train.n_envs, algo.hidden, "
     "traces.train/eval: the replay buffer, envs, Q-networks and traces together would need "
     "at least 1.05 MiB, but this machine has 1 MiB available: lower algo.buffer_size, "
     "train.n_envs or train.population."),
])
def test_what_cannot_fit_in_memory_is_refused_before_allocating(trace_cache, one_mib,
                                                                 overrides, message):
    """Replay: 10000 x 165 B = 1.574 MiB. Envs: 20 vehicles x (18 + 4·11) B + 3 UABS x
    (16 + 4·9) B + 48 B + 8·3·20 B = 1924 B each. Network 19-512-512-(1+4): 274949
    parameters x 4 B x 5 copies. Traces: 10000 steps x 20 vehicles x 9 B. Together:
    990000 + 1924 + 36580 (the 32-32 network) + 54000 + 18000 B (the traces)."""
    validate_run(smoke(trace_cache))
    with pytest.raises(ConfigError) as e:
        validate_run(smoke(trace_cache, *overrides))
    assert str(e.value) == message


def test_available_memory_reads_meminfo_then_sysconf(monkeypatch):
    if Path("/proc/meminfo").is_file():  # Linux
        meminfo = Path("/proc/meminfo").read_text()
        kib = int(re.search(r"^MemAvailable:\s+(\d+) kB", meminfo, re.M).group(1))
        have, where = memory.available_memory("cpu")
        assert abs(have - kib * 1024) < 2 ** 30 and where == "this machine has"

    def no_file(*args, **kwargs):
        raise OSError("no /proc here")

    monkeypatch.setattr(memory, "open", no_file, raising=False)
    monkeypatch.setattr(memory.os, "sysconf", lambda name: {"SC_AVPHYS_PAGES": 3,
                                                            "SC_PAGE_SIZE": 4096}[name])
    assert memory.available_memory("cpu") == (3 * 4096, "this machine has")

    def unknown(name):
        raise ValueError(name)

    monkeypatch.setattr(memory.os, "sysconf", unknown)
    assert memory.available_memory("cpu") is None
    cfg = replace(compose("config"), algo=replace(compose("config").algo,
                                                  buffer_size=10 ** 12))
    validate_run(cfg)  # nothing to compare with: nothing refused


def test_a_cuda_device_is_checked_against_its_free_memory(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda dev: (5 * 2 ** 30, 8 * 2 ** 30))
    assert memory.available_memory("cuda:0") == (5 * 2 ** 30, "cuda:0 has")
    assert memory.available_memory("auto") == (5 * 2 ** 30, "cuda has")
    cfg = compose("config", ["device=cuda", "algo.buffer_size=50000000"])
    with pytest.raises(ConfigError, match=r"^algo\.buffer_size: .* 7\.683 GiB, but cuda has "
                                          r"5 GiB available"):
        validate_run(cfg)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert memory.available_memory("cuda") is None  # refused by make.resolve_device
    assert memory.available_memory("auto")[1] == "this machine has"


# ----------------------------------------------------------------------------- commands
def test_uabs_train_refuses_an_infinite_learning_rate_in_one_line(tmp_path):
    proc = run_command("train", "experiment=smoke", "algo.lr=inf", "train.threads=1",
                       f"traces.cache_dir={tmp_path / 'cache'}",
                       f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path)
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert lines == ["error: algo.lr must be a finite number, got inf. Set algo.lr to a "
                     "finite value."]
    assert list(tmp_path.iterdir()) == []  # no run folder, no trace cache, nothing


def test_uabs_traces_blames_a_nan_step_length_on_it(tmp_path):
    proc = run_command("traces", "scenario.dt=nan", f"traces.cache_dir={tmp_path / 'cache'}",
                       cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "error: scenario.dt must be a finite number, got nan. Set scenario.dt to a finite "
        "value."]
    assert list(tmp_path.iterdir()) == []
