"""Interrupted runs resume exactly: kill -9 at random moments, resume by re-typing the
original command with ``resume=<folder>`` appended (the folder's name as printed), and
end with the metrics and parameters of an uninterrupted run."""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from tests.test_train import records, smoke
from uabs_rl.cli.train import summary_text
from uabs_rl.runs.checkpoint import CheckpointError, load_checkpoint
from uabs_rl.training.resume import prepare, run

RUN = ["experiment=smoke", "train.episodes=60", "train.eval_every=5",
       "train.checkpoint_buffer=true", "train.logger=none",
       "train.trajectory_images=false", "train.threads=1"]


def train_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "uabs_rl.cli.train", "train.progress=false", *args]


def test_kill_9_and_resume_gives_the_uninterrupted_run(trace_cache, tmp_path):
    cache = f"traces.cache_dir={trace_cache}"
    ref = tmp_path / "ref"
    run(smoke(trace_cache, *RUN[1:]), ref)
    # a folder named like a sweep's: '=' and ',' in it, passed to resume= unquoted
    run_dir = tmp_path / "masking=rank,seed=0"
    rng = random.Random(7)
    original = train_cmd(*RUN, cache, f"hydra.run.dir='{run_dir}'")
    proc = subprocess.Popen(original, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            cwd=tmp_path)
    kills = 0
    deadline = time.monotonic() + 120
    while not (run_dir / ".hydra" / "config.yaml").exists() and time.monotonic() < deadline:
        time.sleep(0.2)  # a kill before Hydra wrote the config leaves nothing to resume
    for _ in range(4):
        time.sleep(rng.uniform(2.0, 6.0))
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            kills += 1
        proc.wait()
        # what users type: the original command again, with resume= appended
        proc = subprocess.Popen([*original, f"resume={run_dir}"], stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, cwd=tmp_path)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err.decode()[-2000:]
    assert kills >= 2  # the run really was killed midway, more than once
    recs = records(run_dir)
    assert [r["episode"] for r in recs if r["kind"] == "train"] == list(range(1, 61))
    assert [r["episode"] for r in recs if r["kind"] == "eval"] == list(range(5, 61, 5))
    assert recs == records(ref)  # every number as in the uninterrupted run
    a = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    b = load_checkpoint(ref / "checkpoints" / "last.pt")
    for k in b["learner"]["qnet"]:
        assert torch.equal(a["learner"]["qnet"][k], b["learner"]["qnet"][k]), k
    assert a["counters"] == b["counters"]
    assert not list((run_dir / "checkpoints").glob(".*.tmp"))
    assert not (tmp_path / "outputs").exists()  # no stray run folder in the cwd


def test_resume_without_a_replay_buffer_warns_only_where_learning_goes_on(
        trace_cache, tmp_path, caplog):
    """A checkpoint without its buffer (the default): resuming a stopped run warns that
    learning restarts after algo.learning_starts; a finished one, with nothing left to
    learn, said so too."""
    import logging

    run_dir = tmp_path / "run"
    run(smoke(trace_cache, "train.episodes=3", "train.trajectory_images=false"), run_dir)
    for episodes, warned in ((3, False), (4, True)):
        caplog.clear()
        args = [f"resume={run_dir}", f"train.episodes={episodes}"]
        with caplog.at_level(logging.WARNING, logger="uabs_rl.training.members"):
            prepare(smoke(trace_cache, *args), Path("unused"), overrides=args).fit()
        assert ("learning restarts after algo.learning_starts" in caplog.text) == warned


def test_resume_takes_the_runs_own_config_and_refuses_result_changes(trace_cache, tmp_path):
    run_dir = tmp_path / "run"
    run(smoke(trace_cache, "train.episodes=3", "train.trajectory_images=false",
              "masking=flat", "seed=4"), run_dir)
    # composed defaults (rank, seed 0) + resume: the run's own flat / seed 4 are used
    cfg = smoke(trace_cache, f"resume={run_dir}", "train.episodes=6")
    exp = prepare(cfg, Path("unused"), overrides=[f"resume={run_dir}", "train.episodes=6"])
    # the experiment (and the end-of-run summary drawn from it) has the run's own config
    assert exp.cfg.masking.mode == "flat" and exp.cfg.seed == 4 and exp.run_dir == run_dir
    summary = exp.fit()
    assert summary["episodes"] == 6
    text = summary_text(exp.cfg, summary, exp.run_dir)
    assert f"run folder: {run_dir}" in text and "6 episodes" in text
    state = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    assert state["config"]["masking"]["mode"] == "flat" and state["config"]["seed"] == 4
    with pytest.raises(CheckpointError, match=r"algo\.lr"):
        run(smoke(trace_cache, f"resume={run_dir}"), Path("unused"),
            overrides=[f"resume={run_dir}", "algo.lr=0.5"])
    with pytest.raises(Exception, match="is a file"):
        run(smoke(trace_cache, f"resume={run_dir / 'checkpoints' / 'last.pt'}"), Path("x"))


def test_a_run_killed_before_its_first_checkpoint_restarts_in_place(trace_cache, tmp_path):
    done = tmp_path / "done"
    run(smoke(trace_cache, "train.trajectory_images=false"), done)
    # what a kill before the first checkpoint leaves: .hydra/, a partial metrics file
    stuck = tmp_path / "stuck"
    shutil.copytree(done / ".hydra", stuck / ".hydra") if (done / ".hydra").exists() else \
        (stuck / ".hydra").mkdir(parents=True)
    from omegaconf import OmegaConf

    from uabs_rl.runs.checkpoint import config_dict
    cfg = smoke(trace_cache, "train.trajectory_images=false")
    OmegaConf.save(OmegaConf.create(config_dict(cfg)), stuck / ".hydra" / "config.yaml")
    (stuck / "metrics.jsonl").write_text(
        json.dumps(records(done)[0]) + "\n" + '{"kind": "train", "epis')
    run(smoke(trace_cache, f"resume={stuck}"), Path("unused"), overrides=[f"resume={stuck}"])
    assert [r["episode"] for r in records(stuck) if r["kind"] == "train"] == [1, 2, 3, 4, 5, 6]
    assert records(stuck) == records(done)
    assert os.path.isfile(stuck / "checkpoints" / "last.pt")
