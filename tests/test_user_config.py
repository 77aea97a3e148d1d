"""A user's own config folder outside the package (``--config-dir``), presets that do
not override a user's scenario, and ``uabs-eval RUN [overrides]`` on another network
and fleet."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
import yaml

from tests.conftest import run_command
from tests.test_train import smoke
from uabs_rl.cli.evaluate import main as eval_main
from uabs_rl.traces.inputs import netgenerate_path
from uabs_rl.training.resume import run


def _netgenerate() -> str:
    exe = netgenerate_path()
    if not Path(exe).exists():
        pytest.skip("netgenerate not installed (pip install eclipse-sumo)")
    return exe


@pytest.fixture(scope="module")
def user_dir(tmp_path_factory) -> Path:
    """What sumo/README.md tells a user to make: a 4 x 4 grid built with netgenerate,
    a scenario file and a preset of their own, in a folder outside the package."""
    d = tmp_path_factory.mktemp("myconf")
    (d / "scenario").mkdir()
    (d / "experiment").mkdir()
    subprocess.run([_netgenerate(), "--grid", "--grid.number", "4", "--grid.length", "60",
                    "--default.lanenumber", "1", "--default.junctions.type", "allway_stop",
                    "--offset.x", "2", "--offset.y", "2", "--output-file",
                    str(d / "grid4.net.xml")], check=True, capture_output=True)
    (d / "scenario" / "grid4.yaml").write_text(yaml.safe_dump({
        "name": "grid4", "area": {"width": 184, "height": 184},
        "sumo": {"net_file": str(d / "grid4.net.xml"), "fleet_size": 30}}))
    (d / "experiment" / "wide.yaml").write_text(
        "# @package _global_\nalgo:\n  hidden: [48, 48]\n")
    return d


def _composed(*args: str) -> dict:
    """The job config ``uabs-train`` composes for ``args`` (``--cfg job``: nothing runs)."""
    proc = run_command("train", *args, "--cfg", "job")
    assert proc.returncode == 0, proc.stderr
    return yaml.safe_load(proc.stdout)


def test_user_config_folder_composes_and_preset_keeps_user_values(user_dir):
    cfg = _composed("--config-dir", str(user_dir), "scenario=grid4", "experiment=smoke")
    assert cfg["scenario"]["name"] == "grid4"
    # the user's file sets fleet_size: the preset (which sets 20) does not replace it ...
    assert cfg["scenario"]["sumo"]["fleet_size"] == 30
    assert cfg["scenario"]["area"]["width"] == 184
    # ... while what the user's file leaves alone still comes from the preset
    assert cfg["scenario"]["episode_steps"] == 20 and cfg["train"]["episodes"] == 6
    # a preset of the user's own, and the command line still wins over everything
    cfg = _composed("--config-dir", str(user_dir), "scenario=grid4", "experiment=wide",
                    "scenario.sumo.fleet_size=12")
    assert cfg["algo"]["hidden"] == [48, 48] and cfg["scenario"]["sumo"]["fleet_size"] == 12
    # without a user scenario the preset applies in full, as before
    assert _composed("experiment=smoke")["scenario"]["sumo"]["fleet_size"] == 20


def test_uabs_traces_accepts_the_training_groups(user_dir, tmp_path):
    proc = run_command("traces", "--config-dir", str(user_dir), "scenario=grid4",
                       "experiment=smoke", "masking=flat", "split=eval",
                       f"traces.cache_dir={tmp_path}")
    assert proc.returncode == 0, proc.stderr
    assert "built with SUMO" in proc.stdout and "30 slots" in proc.stdout
    assert len(list(tmp_path.glob("grid4-eval-*.pt"))) == 1


@pytest.fixture(scope="module")
def smoke_run(trace_cache, tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("smoke_run")
    run(smoke(trace_cache, "train.logger=none", "train.trajectory_images=false"),
        run_dir)
    return run_dir


def test_uabs_eval_on_another_network_and_fleet(smoke_run, user_dir, capsys):
    test_traces = ["traces.test.n_sims=1", "traces.test.duration_s=170",
                   "traces.test.warmup_s=10"]
    overrides = ["scenario=grid4", "scenario.sumo.fleet_size=12", *test_traces]
    assert eval_main([str(smoke_run), "--config-dir", str(user_dir), *overrides,
                      "--policy", "all", "--checkpoint", "last"]) == 0
    out = smoke_run / "evaluation" / ",".join(overrides)
    res = json.loads((out / "eval.json").read_text())
    assert res["scenario"] == "grid4" and res["overrides"] == overrides
    # the grid's own episode length (the schema's 80 steps): 170 s hold 2 windows
    assert res["windows"] == 2
    assert set(res["policies"]) == {"learned", "random", "greedy", "oracle"}
    assert "scenario grid4" in capsys.readouterr().out
    # the run's own evaluation folder is left alone
    assert not (smoke_run / "evaluation" / "eval.json").exists()


@pytest.mark.parametrize("override, names", [
    ("scenario.n_uabs=4", ["scenario.n_uabs=4", "observations of size", "obs=egocentric"]),
    ("obs=egocentric", ["obs=egocentric", "belongs to the trained policy"]),
    ("scenario.lookahead_obs=true", ["moved to the observation group", "obs=lookahead"]),
    ("channel.n_beams=16", ["channel.n_beams=16", "cannot change at evaluation"]),
    ("algo.lr=0.1", ["algo.lr=0.1", "belongs to the trained policy"]),
    ("train.episodes=3", ["train.episodes=3", "belongs to the trained policy"]),
    ("experiment=smoke", ["presets change how a policy is trained"]),
    ("scenario=nowhere", ["no nowhere.yaml", "--config-dir"]),
    ("scenario.sumo.fleetsize=3", ["fleetsize", "SumoConfig"]),
])
def test_uabs_eval_refuses_what_cannot_change(smoke_run, override, names, capsys):
    assert eval_main([str(smoke_run), override, "--checkpoint", "last"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and len(err.strip().splitlines()) == 1
    for n in names:
        assert n in err


def test_uabs_eval_refuses_a_file_of_yours_named_as_a_package_option(smoke_run, tmp_path,
                                                                      capsys):
    """uabs-eval would read your scenario/grid6.yaml where uabs-train reads the package's:
    refused by both, in the same words (tests/test_train.py has uabs-train's)."""
    (tmp_path / "scenario").mkdir()
    (tmp_path / "scenario" / "grid6.yaml").write_text("name: grid6\n")
    assert eval_main([str(smoke_run), "--config-dir", str(tmp_path), "scenario=grid6",
                      "--checkpoint", "last"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert "scenario/grid6.yaml has the name of the package's conf/scenario/grid6.yaml" in err


@pytest.fixture(scope="module")
def egocentric_run(trace_cache, tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("egocentric_run")
    run(smoke(trace_cache, "obs=egocentric", "masking=rank", "train.logger=none",
              "train.trajectory_images=false"), run_dir)
    return run_dir


def test_an_egocentric_policy_flies_other_fleets_and_cities(egocentric_run, user_dir,
                                                           capsys):
    """Trained at M = 3 over the default grid: evaluated at M = 6 there, and at M = 2
    over a user's 4 x 4 grid, with its own observation (the scenario files hold none)."""
    test_traces = ["traces.test.n_sims=1", "traces.test.duration_s=170",
                   "traces.test.warmup_s=10"]
    assert eval_main([str(egocentric_run), "scenario.n_uabs=6", *test_traces,
                      "--checkpoint", "last"]) == 0
    res = json.loads((egocentric_run / "evaluation" / ",".join(
        ["scenario.n_uabs=6", *test_traces]) / "eval.json").read_text())
    learned = res["policies"]["learned"]
    assert learned["collisions"] == 0 and learned["fallbacks"] == 0
    other = ["scenario=grid4", "scenario.n_uabs=2", *test_traces]
    assert eval_main([str(egocentric_run), "--config-dir", str(user_dir), *other,
                      "--checkpoint", "last"]) == 0
    res = json.loads((egocentric_run / "evaluation" / ",".join(other) / "eval.json")
                     .read_text())
    assert res["scenario"] == "grid4" and res["policies"]["learned"]["collisions"] == 0


def test_old_observation_keys_on_the_command_line_say_what_to_type():
    proc = run_command("train", "scenario.lookahead_obs=true", "scenario.motion_obs=true")
    assert proc.returncode == 2
    assert proc.stderr.strip() == (
        "error: scenario.lookahead_obs moved to the observation group: type obs=lookahead "
        "(obs=lookahead_motion with the motion features) instead of "
        "scenario.lookahead_obs=true (conf/obs holds the observations).")


def test_training_over_a_family_of_cities(trace_cache, user_dir, tmp_path, caplog):
    """experiment=smoke over the default grid and the user's 4 x 4 grid at once (the
    family given on the command line): both cities' training traces are read and the
    run trains to its end without a collision (tests/test_family.py checks the envs)."""
    import logging

    grid4 = (f"{{name:grid4,area:{{width:184,height:184}},"
             f"sumo:{{net_file:'{user_dir / 'grid4.net.xml'}',fleet_size:30}}}}")
    cfg = smoke(trace_cache, "obs=egocentric", f"family=[{{}},{grid4}]",
                "train.logger=none", "train.trajectory_images=false")
    with caplog.at_level(logging.INFO, logger="uabs_rl.traces.build"):
        run(cfg, tmp_path)
    assert "family city grid4" in caplog.text and "family city manhattan" in caplog.text
    recs = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    train = [r for r in recs if r["kind"] == "train"]
    assert len(train) == 6 and all(r["collisions"] == 0 for r in train)


def test_uabs_eval_takes_the_city_preset_with_its_traces():
    """scenario=city is a global-package file (it sizes the traces too): uabs-eval takes
    its scenario and its test traces, not its training settings."""
    from uabs_rl.config import RunConfig
    from uabs_rl.evaluation.load import with_overrides

    cfg = with_overrides(RunConfig(), ["scenario=city", "scenario.n_uabs=30"])
    assert (cfg.scenario.name, cfg.scenario.n_uabs, cfg.scenario.sumo.fleet_size) == (
        "city", 30, 2000)
    assert (cfg.traces.test.n_sims, cfg.traces.test.duration_s) == (2, 600.0)
    assert cfg.train.eval_windows == RunConfig().train.eval_windows
