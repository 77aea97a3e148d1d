"""uabs-train end to end on the smoke preset, checkpoints, resume, config errors, learning."""

from __future__ import annotations

import importlib.util
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra.errors import ConfigCompositionException
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from tests.conftest import compose_cfg, run_command
from uabs_rl.algorithms import ALGORITHMS, Dims, make_algorithm
from uabs_rl.config import CONF_DIR, ConfigError, MaskingMode
from uabs_rl.evaluation.load import load_evaluation
from uabs_rl.runs.checkpoint import (
    CheckpointError,
    Interrupted,
    config_from_checkpoint,
    load_checkpoint,
)
from uabs_rl.safety.make import make_selector
from uabs_rl.traces.cache import TraceSet
from uabs_rl.training.experiment import Experiment
from uabs_rl.training.resume import prepare, run
from uabs_rl.training.startup import validate_run


def smoke(trace_cache, *extra: str):
    return compose_cfg("config", ["experiment=smoke", f"traces.cache_dir={trace_cache}",
                                  "train.progress=false", *extra])


def records(run_dir: Path) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def rank_run(trace_cache, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("rank_run")
    run(smoke(trace_cache), run_dir)
    return run_dir


@pytest.mark.parametrize("mode", ["penalty", "flat"])
def test_smoke_run_per_masking_mode(trace_cache, tmp_path, mode):
    run(smoke(trace_cache, f"masking={mode}", "train.trajectory_images=false"), tmp_path)
    recs = records(tmp_path)
    assert [r["episode"] for r in recs if r["kind"] == "train"] == [1, 2, 3, 4, 5, 6]
    assert [r["episode"] for r in recs if r["kind"] == "eval"] == [3, 6]
    if mode == "flat":
        assert sum(r["collisions"] for r in recs) == 0


@pytest.mark.parametrize("args", [["algo=vdn", "masking=rank"],
                                  ["algo=vdn", "masking=flat", "train.population=2"],
                                  ["algo=qmix", "masking=flat"],
                                  ["algo=qmix", "masking=rank", "train.population=2"],
                                  ["algo.replay=prioritized", "masking=rank"],
                                  ["algo=qmix", "algo.replay=prioritized", "masking=flat"],
                                  ["algo=dqfd", "masking=rank", "train.population=2"]])
def test_each_learner_trains_end_to_end_without_a_collision_or_fallback(trace_cache, tmp_path,
                                                                       args):
    """VDN, QMIX, the teacher-guided 3DQN and prioritized replay through uabs-train's path
    (single runs and populations), evaluated by uabs-eval from the checkpoint."""
    run(smoke(trace_cache, *args, "train.trajectory_images=false", "train.logger=none"),
        tmp_path)
    dirs = sorted(tmp_path.glob("seed=*")) or [tmp_path]
    for d in dirs:
        recs = records(d)
        train = [r for r in recs if r["kind"] == "train"]
        assert train[-1]["updates"] > 0 and math.isfinite(train[-1]["loss"])
        assert sum(r["collisions"] + r["fallbacks"] for r in recs) == 0
        state = load_checkpoint(d / "checkpoints" / "best.pt")
        name = next((x.split("=")[1] for x in args if x.startswith("algo=")), "dqn3")
        assert state["config"]["algo"]["name"] == name
        best = [r for r in recs if r["kind"] == "eval"
                and r["episode"] == state["counters"]["episode"]][0]
        ev = load_evaluation(d, "best", split="eval")
        again, _ = ev.evaluator.evaluate(ev.greedy)
        assert again["return"] == pytest.approx(best["return"])


def test_smoke_run_writes_metrics_tensorboard_and_checkpoints(rank_run):
    recs = records(rank_run)
    train = [r for r in recs if r["kind"] == "train"]
    evals = [r for r in recs if r["kind"] == "eval"]
    assert len(train) == 6 and len(evals) == 2
    assert train[-1]["updates"] > 0 and train[-1]["epsilon"] == pytest.approx(0.05)
    assert train[0]["epsilon"] > train[-1]["epsilon"]
    assert sum(r["collisions"] for r in recs) == 0  # rank masking
    assert len(evals[-1]["pg_curve"]) == 10 and evals[-1]["windows"] == 2
    ea = EventAccumulator(str(rank_run / "tb"), size_guidance={"images": 0, "scalars": 0})
    ea.Reload()
    scalars = set(ea.Tags()["scalars"])
    for tag in ("train/return", "train/collisions", "train/proximity", "train/fallbacks",
                "train/served_fraction", "train/pg", "train/epsilon", "train/loss",
                "train/q_chosen", "eval/return", "eval/collisions", "eval/pg",
                "eval/served_fraction", "eval/closest_approach"):
        assert tag in scalars, tag
    assert [e.value for e in ea.Scalars("train/return")] == pytest.approx(
        [r["return"] for r in train])
    # env steps on the x-axis; counters are not curves; the machine's speed is
    assert [e.step for e in ea.Scalars("eval/return")] == [r["env_steps"] for r in evals]
    assert not {"train/updates", "train/episode", "train/env_steps", "eval/windows",
                "eval/episode"} & scalars
    assert "speed/env_steps_per_s" in scalars
    assert all(e.value > 0 for e in ea.Scalars("speed/env_steps_per_s"))
    assert {"eval/trajectories", "eval/pg_curve"} <= set(ea.Tags()["images"])
    # the hyper-parameters, as TensorBoard's HPARAMS tab reads them, in the run's own
    # event file: no timestamped sub-run, so the run shows once in TensorBoard
    assert not [d for d in (rank_run / "tb").iterdir() if d.is_dir()]
    assert ea.PluginTagToContent("hparams")  # the hparams plugin's records
    for name in ("best", "last"):
        assert (rank_run / "checkpoints" / f"{name}.pt").is_file()
    png = rank_run / "eval" / "last_trajectories.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000


def test_csv_logger_and_missing_optional_loggers(trace_cache, tmp_path):
    run(smoke(trace_cache, "train.logger=csv", "train.trajectory_images=false"),
        tmp_path / "csv_run")
    scalars = tmp_path / "csv_run" / "csv" / "scalars"
    train = [r for r in records(tmp_path / "csv_run") if r["kind"] == "train"]
    rows = [line.split(",") for line in (scalars / "train" / "return.csv").read_text()
            .splitlines()]
    assert [(int(s), float(v)) for s, v in rows] == [
        (r["env_steps"], pytest.approx(r["return"])) for r in train]
    assert not (scalars / "train" / "updates.csv").exists()
    assert "algo.gamma: 0.8" in (tmp_path / "csv_run" / "csv" / "texts" / "hparams0.txt"
                                 ).read_text()
    for kind, pkg in (("wandb", "wandb"), ("mlflow", "mlflow")):
        if importlib.util.find_spec(pkg) is not None:
            continue
        with pytest.raises(ConfigError, match=f"pip install {pkg}"):
            Experiment(smoke(trace_cache, f"train.logger={kind}"), tmp_path / kind)
        assert not (tmp_path / kind).exists()


def test_best_checkpoint_reloads_to_identical_parameters_and_figures(rank_run, trace_cache,
                                                                    tmp_path):
    state = load_checkpoint(rank_run / "checkpoints" / "best.pt")
    exp = Experiment(smoke(trace_cache), tmp_path)
    exp.checkpoints.resume([state], [rank_run / "checkpoints" / "best.pt"])
    for k, v in exp.qnet.state_dict().items():
        assert torch.equal(v, state["learner"]["qnet"][k])
    evals = [r for r in records(rank_run) if r["kind"] == "eval"]
    best = [r for r in evals if r["episode"] == state["counters"]["episode"]][0]
    # evaluation without a trainer (what uabs-eval does) and through the experiment
    ev = load_evaluation(rank_run, "best", split="eval")
    for again, _ in (ev.evaluator.evaluate(ev.greedy), exp.evaluator.evaluate(exp.greedy)):
        for key in ("return", "returns", "collisions", "proximity", "pg_curve",
                    "served_fraction"):
            assert again[key] == pytest.approx(best[key]), key


def test_resume_continues_the_episode_counter(trace_cache, tmp_path):
    run(smoke(trace_cache, "train.episodes=3", "train.checkpoint_buffer=true",
              "train.trajectory_images=false"), tmp_path)
    state = load_checkpoint(tmp_path / "checkpoints" / "last.pt")
    assert state["counters"]["episode"] == 3 and state["replay"] is not None
    run(smoke(trace_cache, "train.episodes=6", f"resume={tmp_path}",
              "train.trajectory_images=false"), Path("unused"))
    eps = [r["episode"] for r in records(tmp_path) if r["kind"] == "train"]
    assert eps == [1, 2, 3, 4, 5, 6]
    state = load_checkpoint(tmp_path / "checkpoints" / "last.pt")
    assert state["counters"]["episode"] == 6
    assert state["learner"]["updates"] > 60  # updates went on from the saved count


def test_a_finished_run_folder_is_not_overwritten(rank_run, trace_cache):
    before = (rank_run / "metrics.jsonl").read_text()
    with pytest.raises(ConfigError, match="already holds a run"):
        run(smoke(trace_cache), rank_run)
    assert (rank_run / "metrics.jsonl").read_text() == before


def test_incompatible_or_damaged_checkpoint_is_refused(rank_run, trace_cache, tmp_path):
    with pytest.raises(CheckpointError, match=r"algo\.hidden: \[32, 32\] in the checkpoint"):
        run(smoke(trace_cache, f"resume={rank_run}", "algo.hidden=[16]"), tmp_path)
    bad = tmp_path / "checkpoints" / "last.pt"
    bad.parent.mkdir(parents=True)
    bad.write_bytes((rank_run / "checkpoints" / "last.pt").read_bytes()[:1000])
    with pytest.raises(CheckpointError, match="damaged"):
        load_checkpoint(bad)
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_checkpoint(tmp_path / "nowhere.pt")
    # resuming from it: the advice is what resume can use (last.pt alone), not "another
    # checkpoint of the run"
    import shutil
    copy = tmp_path / "copy"
    shutil.copytree(rank_run, copy)
    (copy / "checkpoints" / "last.pt").write_bytes(bad.read_bytes())
    with pytest.raises(CheckpointError, match=r"damaged .*: resume continues from "
                                              r"checkpoints/last.pt alone: put back an intact"):
        run(smoke(trace_cache, f"resume={copy}"), copy)


def ctrl_c_in_episode_2(exp: Experiment, monkeypatch) -> None:
    """Fit ``exp`` with Ctrl-C pressed during its second episode: it must stop there
    with Interrupted."""
    import os
    import signal

    real = exp.collect

    def interrupted():
        if exp.episode == 1:
            os.kill(os.getpid(), signal.SIGINT)  # as if Ctrl-C were pressed now
        return real()

    with monkeypatch.context() as m:
        m.setattr(exp, "collect", interrupted)
        with pytest.raises(Interrupted, match="interrupted at episode 2"):
            exp.fit()


def test_ctrl_c_finishes_the_round_saves_last_and_stops(trace_cache, tmp_path, monkeypatch):
    """Ctrl-C during the second episode: that episode ends, is logged and saved, and the
    run stops with Interrupted (one line at the command line), counters consistent."""
    exp = Experiment(smoke(trace_cache, "train.logger=none"), tmp_path)
    ctrl_c_in_episode_2(exp, monkeypatch)
    c = load_checkpoint(tmp_path / "checkpoints" / "last.pt")["counters"]
    assert c["episode"] == 2 and c["env_steps"] == 2 * exp.params.episode_steps
    assert [r["episode"] for r in records(tmp_path) if r["kind"] == "train"] == [1, 2]


RESUMED = [["algo=vdn"], ["algo=vdn", "train.population=2"],
           ["algo=qmix", "algo.replay=prioritized", "train.population=2"],
           ["algo.replay=prioritized"], ["algo=dqfd", "algo.teacher_horizon=3"]]
# and every other registered learner (one of yours: docs/code.md "Extending")
RESUMED += [[f"algo={name}"] for name in sorted(ALGORITHMS) if name != "dqn3"
            and not any(f"algo={name}" in extra for extra in RESUMED)]


@pytest.mark.parametrize("extra", RESUMED)
def test_a_run_of_each_learner_stopped_and_resumed_equals_the_uninterrupted_run(
        trace_cache, tmp_path, monkeypatch, extra):
    """VDN, QMIX, the teacher-guided 3DQN and prioritized replay stopped by Ctrl-C after
    episode 2 and resumed: every record and the final networks (mixers included) as in
    the run that was never stopped (its replay of whole steps, its priorities and its
    teacher's labels included)."""
    args = ["train.checkpoint_buffer=true", "train.logger=none",
            "train.trajectory_images=false", "train.eval_every=2", "train.threads=1", *extra]
    run(smoke(trace_cache, *args), tmp_path / "ref")
    ctrl_c_in_episode_2(prepare(smoke(trace_cache, *args), tmp_path / "run"), monkeypatch)
    # the original command re-typed with resume= appended
    again = ["experiment=smoke", f"traces.cache_dir={trace_cache}", "train.progress=false",
             *args, f"resume={tmp_path / 'run'}"]
    run(compose_cfg("config", again), Path("unused"), overrides=again)
    dirs = sorted((tmp_path / "ref").glob("seed=*")) or [tmp_path / "ref"]
    for ref in dirs:
        got = tmp_path / "run" / ref.relative_to(tmp_path / "ref")
        assert records(got) == records(ref)
        a, b = (load_checkpoint(d / "checkpoints" / "last.pt")["learner"] for d in (got, ref))
        for part in ("qnet", "target", "mixer", "target_mixer"):
            assert (part in a) == (part in b)
            assert all(torch.equal(a[part][k], v) for k, v in b.get(part, {}).items()), part


@pytest.mark.parametrize("override,key", [
    ("scenario.n_uabs=0", "scenario.n_uabs"),
    ("scenario.speed=-5", "scenario.speed"),
    ("scenario.nhat_s=11", "scenario.nhat_s"),
    ("algo.gamma=1.5", "algo.gamma"),
    ("train.eval_windows=0", "train.eval_windows"),
    ("device=tpu", "device"),
    ("algo.n_step=0", "algo.n_step"),
    ("algo.n_step=81", "algo.n_step"),
])
def test_invalid_values_fail_at_start_up_naming_the_key(trace_cache, override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        validate_run(smoke(trace_cache, override))


def test_n_step_returns_need_a_terminal_episode_end(trace_cache):
    validate_run(smoke(trace_cache, "algo.n_step=3"))
    with pytest.raises(ConfigError, match=r"algo\.n_step must be 1 when scenario\.time_is"):
        validate_run(smoke(trace_cache, "algo.n_step=3", "scenario.time_is_terminal=false"))


@pytest.mark.parametrize("mode,recoverable,most", [("flat", "true", 8), ("rank", "true", 8),
                                                   ("rank", "false", 15)])
def test_a_fleet_the_area_cannot_hold_is_refused_with_the_maximum(trace_cache, tmp_path, mode,
                                                                  recoverable, most):
    """30 UABS on the default 350 m x 170 m area: refused before any episode runs."""
    cfg = smoke(trace_cache, "scenario.n_uabs=30", f"masking={mode}",
                f"masking.recoverable={recoverable}")
    with pytest.raises(ConfigError, match=rf"scenario\.n_uabs=30 .* at most {most} UABS"):
        run(cfg, tmp_path / "run")
    assert not (tmp_path / "run" / "metrics.jsonl").exists()


@pytest.mark.parametrize("override,key", [("algo.lrr=1", "lrr"), ("masking=soft", "soft"),
                                          ("scenario.n_uabs=three", "n_uabs")])
def test_misspelt_keys_and_unknown_groups_fail_at_composition(trace_cache, override, key):
    with pytest.raises((ConfigCompositionException, ConfigError, Exception)) as e:
        smoke(trace_cache, override)
    assert key in str(e.value) + str(e.value.__cause__)


# the options of conf/masking/ and of MaskingMode as the messages list them: the package's
# own (flat, penalty, rank) and any a user added (docs/code.md, Extending)
MASKS = ", ".join(sorted(p.stem for p in (CONF_DIR / "masking").glob("*.yaml")))
MODES = ", ".join(m.value for m in MaskingMode)


@pytest.mark.parametrize("args,said", [
    (["masking=rnak"], f"masking=rnak: masking has no option 'rnak'; choose from {MASKS} "
                       f"(the files of conf/masking/; an option of yours is its file, "
                       f"masking/rnak.yaml: docs/code.md, Extending)."),
    (["algo.lrr=1"], "algo.lrr is not a setting (AlgoConfig has no 'lrr'): did you mean "
                     "algo.lr or algo.loss or algo.replay? fix its spelling; uabs-train "
                     "--cfg job prints every setting."),
    (["algo=qmix", "algo.mixing_embed=4"], "algo.mixing_embed is not a setting (QmixConfig "
                                           "has no 'mixing_embed'): did you mean "
                                           "algo.mixing_embed_dim"),
    (["scenario.n_uabs=three"], "scenario.n_uabs=three: Value 'three' of type 'str' could "
                                "not be converted to Integer."),
    (["masking.mode=soft"], f"masking.mode=soft: Invalid value 'soft', expected one of "
                            f"[{MODES}]."),
    (["-m", "masking=penalty,rnak", "seed=0,1"], "masking=rnak: masking has no option"),
    (["masking=masking_schema"], f"masking=masking_schema is the schema the options of "
                                 f"masking build on, not one of them: choose from {MASKS}."),
    (["algo=qmix_schema"], "algo=qmix_schema is the schema the options of algo build on"),
    # a sweep without -m (Hydra: "Ambiguous value", 4 lines, exit 1), a launcher of 0 jobs
    # (a 35-line joblib traceback)
    (["masking=flat,rank"], "masking=flat,rank is a sweep (several values): add -m to run "
                            "one job per value (uabs-train -m ...), or give one value."),
    (["-m", "masking=flat,rank", "hydra/launcher=local_parallel", "hydra.launcher.n_jobs=0"],
     "hydra.launcher.n_jobs=0: the jobs a sweep runs at once must be a whole number >= 1 "
     "(or -1: one per core)."),
    # the SLURM launcher off a SLURM node (before: submitit's traceback, after the sweep's
    # folder was made)
    pytest.param(["-m", "masking=flat,rank", "hydra/launcher=slurm"],
                 "hydra/launcher=slurm submits each job to SLURM, but this machine has no "
                 "srun on its PATH (not a SLURM node): start the sweep on your cluster's "
                 "login node, or run it here with hydra/launcher=local_parallel.",
                 marks=pytest.mark.skipif(bool(shutil.which("srun")), reason="a SLURM node")),
    pytest.param(["-m", "masking=flat,rank", "hydra/launcher='slurm'"],
                 "hydra/launcher=slurm submits each job to SLURM, but this machine has no",
                 marks=pytest.mark.skipif(bool(shutil.which("srun")), reason="a SLURM node")),
    # ... and without -m (before: trained here, one run, without a word)
    (["hydra/launcher=slurm"], "hydra/launcher=slurm submits a sweep's jobs to SLURM, but "
                               "without -m this command trains here, one run: add -m "
                               "(uabs-train -m ...) to submit, or leave the launcher out."),
    # a value one job of a sweep would refuse: before, the jobs before it ran first (the
    # serial launcher), and the sweep stopped there
    (["-m", "algo.lr=0.001,-1", "seed=0,1"], "the job algo.lr=-1 seed=0 of this sweep: "
                                             "algo.lr must be > 0, got -1.0. No job was "
                                             "started."),
    # Hydra's own sweeper named: before, any hydra/sweeper= was taken for a study
    (["-m", "hydra/sweeper=basic", "algo.lr=0.001,-1", "seed=0,1"],
     "the job algo.lr=-1 seed=0 of this sweep: algo.lr must be > 0"),
])
def test_a_command_line_hydra_cannot_compose_is_one_line_before_any_run(trace_cache, tmp_path,
                                                                      args, said):
    """What Hydra answers in 7 to 13 lines and status 1 (a misspelt key, an option no
    group has, a value of the wrong type; in a sweep too) is one line and status 2, and
    a group's typed base (``<group>_schema``, Hydra lists it among the options) is no
    option: before, ``masking=masking_schema`` trained with the schema's defaults."""
    ran = run_command("train", *args, "experiment=smoke", f"traces.cache_dir={trace_cache}",
                      f"hydra.run.dir={tmp_path / 'run'}", f"hydra.sweep.dir={tmp_path / 'sweep'}")
    lines = ran.stderr.strip().splitlines()
    assert ran.returncode == 2 and len(lines) == 1, ran.stderr
    assert lines[0].startswith(f"error: {said}"), lines[0]
    assert not (tmp_path / "run").exists() and not (tmp_path / "sweep").exists()


def test_config_dir_options_are_composed_with_it_and_its_mistakes_are_one_line(tmp_path):
    """``--config-dir D`` adds D's options to the pre-check's composition; a missing D, a
    file of D's that is not YAML, and one named as a package option (which uabs-train
    would ignore: Hydra reads conf/ first) are one line each. ``hydra.searchpath`` is
    left to Hydra."""
    from uabs_rl.cli.hydra import check_composition

    mine = tmp_path / "my conf=a,b'c"  # a path Hydra's override grammar must quote
    (mine / "scenario").mkdir(parents=True)
    (mine / "scenario" / "mine.yaml").write_text("name: mine\n")
    check_composition("config", ["--config-dir", str(mine), "scenario=mine"])
    check_composition("config", [f"-cd={mine}", "scenario=mine"])
    check_composition("config", ["hydra.searchpath=[file://nowhere]", "scenario=mine"])
    # what Hydra itself takes passes: joblib's n_jobs=-1 (a job per core), and a value
    # this check cannot compose (scenario=null) is left to Hydra's own answer
    check_composition("config", ["-m", "hydra/launcher=local_parallel",
                                 "hydra.launcher.n_jobs=-1", "seed=0,1"])
    check_composition("config", ["scenario=null"])
    with pytest.raises(ConfigError, match="scenario has no option 'mine'"):
        check_composition("config", ["scenario=mine"])
    with pytest.raises(ConfigError, match="--config-dir nowhere: no such folder"):
        check_composition("config", ["--config-dir", "nowhere", "scenario=mine"])
    with pytest.raises(ConfigError, match="^-cd nowhere: no such folder"):  # as typed
        check_composition("config", ["-cd", "nowhere", "scenario=mine"])
    (mine / "scenario" / "broken.yaml").write_text("name: [broken\n")
    with pytest.raises(ConfigError, match=r"broken.yaml is not a readable YAML file \("):
        check_composition("config", ["--config-dir", str(mine), "scenario=broken"])
    (mine / "scenario" / "grid6.yaml").write_text("name: grid6\n")
    with pytest.raises(ConfigError, match=r"scenario/grid6.yaml has the name of the "
                                          r"package's conf/scenario/grid6.yaml"):
        check_composition("config", ["--config-dir", str(mine), "scenario=grid6"])
    # a misspelt key in a file of its (before: Hydra's "In 'scenario/typo': ConfigKeyError
    # raised while composing config: Key 'fleetsize' not in 'SumoConfig'", no hint)
    (mine / "scenario" / "typo.yaml").write_text("name: typo\nsumo: {fleetsize: 3}\n")
    with pytest.raises(ConfigError, match=r"^scenario/typo.yaml sets 'fleetsize', which "
                                          r"SumoConfig does not have: did you mean "
                                          r"fleet_size\? fix the file"):
        check_composition("config", ["--config-dir", str(mine), "scenario=typo"])


def test_cli_entry_point(trace_cache, tmp_path):
    """``uabs-train experiment=smoke`` through Hydra: output folder, config, metrics."""
    out = tmp_path / "run"
    proc = subprocess.run(
        [sys.executable, "-m", "uabs_rl.cli.train", "experiment=smoke", "masking=flat",
         f"traces.cache_dir={trace_cache}", "train.progress=false",
         f"hydra.run.dir={out}"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (out / ".hydra" / "config.yaml").is_file()
    assert len(records(out)) == 8
    # the end of a run: its folder and the next commands, ready to copy
    assert f"run folder: {out}" in proc.stdout and f"uabs-eval {out} --policy all" in proc.stdout
    # a refusal, in this process (tests.conftest.run_command: the same entry point)
    bad = run_command("train", "experiment=smoke", "scenario.n_uabs=0",
                      f"traces.cache_dir={trace_cache}", f"hydra.run.dir={tmp_path / 'bad'}")
    assert bad.returncode == 2 and "scenario.n_uabs must be >= 1" in bad.stderr
    assert not (tmp_path / "bad").exists()  # no empty run folder left behind


# ----------------------------------------------------------------------------- learning
def parked_vehicles(steps: int) -> TraceSet:
    """30 vehicles parked in one corner of a 150 m x 90 m area: the best policy flies
    there and stays; a random walk rarely does."""
    g = torch.Generator().manual_seed(0)
    pos = torch.zeros(1, steps, 30, 2)
    pos[..., 0] = 115 + 20 * torch.rand(30, generator=g)
    pos[..., 1] = 60 + 20 * torch.rand(30, generator=g)
    return TraceSet(pos, torch.ones(1, steps, 30, dtype=torch.bool), {"split": "x", "dt": 1.0})


LEARN = ["scenario.n_uabs=1", "scenario.area.width=150", "scenario.area.height=90",
         "channel.los_mode=los", "algo.lr=1e-3", "algo.hidden=[64,64]", "algo.batch_size=64",
         "algo.target_update=50", "train.episodes=60", "train.eval_every=1000",
         "train.eval_windows=4", "train.logger=none", "train.trajectory_images=false"]


def test_greedy_policy_beats_a_random_one_after_training(trace_cache, tmp_path):
    cfg = smoke(trace_cache, *LEARN)
    tr = Experiment(cfg, tmp_path, traces={"train": parked_vehicles(200),
                                           "eval": parked_vehicles(100)})
    while tr.episode < cfg.train.episodes:
        tr.collect()
    greedy, _ = tr.evaluator.evaluate(tr.greedy)
    eval_env = tr.evaluator.env
    rand_sel = make_selector(eval_env, 1.0, torch.Generator().manual_seed(1))
    eval_env.set_seed(cfg.train.eval_seed)
    td = eval_env.rollout(20, rand_sel, break_when_any_done=False)
    random_return = td["next", "diagnostics", "ep_return"][:, -1].mean().item()
    assert greedy["return"] > 3 * random_return > 0


def test_loss_falls_when_fitting_a_fixed_buffer(trace_cache, tmp_path):
    """Regression towards frozen targets: a broken loss or optimiser cannot pass."""
    cfg = smoke(trace_cache, *LEARN, "algo.target_update=1000000")
    tr = Experiment(cfg, tmp_path, traces={"train": parked_vehicles(200),
                                           "eval": parked_vehicles(100)})
    tr.cfg.algo.learning_starts = 10**9  # collect without updating
    for _ in range(5):
        tr.collect()
    lrn = make_algorithm(cfg.algo, Dims(tr.params.obs_dim, 4, tr.params.n_uabs), [0],
                         torch.device("cpu"))
    b = tr.buffer.sample(100)
    first = lrn.update(b)[0].item()
    for _ in range(1000):
        lrn.update(b)
    assert lrn.loss(b)[0].item() < 0.1 * first


def test_checkpoint_of_an_earlier_version_still_loads(rank_run, tmp_path):
    """Checkpoints written before ``train.logger`` stored ``train.tensorboard``."""
    state = load_checkpoint(rank_run / "checkpoints" / "last.pt")
    cfg = dict(state["config"])
    train = dict(cfg["train"])
    train.pop("logger")
    cfg["train"] = {**train, "tensorboard": False}
    state["config"] = cfg
    torch.save(state, tmp_path / "old.pt")
    ev = load_evaluation(tmp_path / "old.pt", split="eval")
    assert ev.cfg.train.logger == "none"


@pytest.mark.parametrize("lookahead,motion,name", [(False, False, "paper"),
                                                   (True, False, "lookahead"),
                                                   (True, True, "lookahead_motion")])
def test_a_config_with_the_observation_in_scenario_still_loads(rank_run, tmp_path,
                                                               lookahead, motion, name):
    """Checkpoints written before the obs group held scenario.lookahead_obs,
    motion_obs and priority_obs_scale: they load with those in obs, and the command the
    run was started with (obs=..., re-typed) finds no difference."""
    from uabs_rl.runs.checkpoint import config_dict, config_differences, upgrade_config

    state = load_checkpoint(rank_run / "checkpoints" / "last.pt")
    cfg = dict(state["config"])
    cfg.pop("obs")
    cfg["scenario"] = {**cfg["scenario"], "lookahead_obs": lookahead, "motion_obs": motion,
                       "priority_obs_scale": 10.0}
    state["config"] = cfg
    if not lookahead:  # the network fits: the whole checkpoint loads
        torch.save(state, tmp_path / "old.pt")
        assert load_evaluation(tmp_path / "old.pt", split="eval").cfg.obs.name == "paper"
    cfg = config_from_checkpoint(state)
    assert (cfg.obs.lookahead, cfg.obs.motion, cfg.obs.name) == (lookahead, motion, name)
    assert cfg.obs.frame == "fleet" and cfg.obs.priority_scale == 10.0
    current = config_dict(cfg)
    assert config_differences(upgrade_config(state["config"]), current) == []
    current["obs"]["motion"] = not motion
    assert config_differences(upgrade_config(state["config"]), current) == [
        f"obs.motion: {motion!r} in the checkpoint, {not motion!r} now"]
