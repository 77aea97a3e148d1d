"""Sweeps through Hydra launchers: a local-parallel multirun, the submitit launcher run
for real through its local executor (slow), and the SLURM config."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import get_class

from uabs_rl.config import CONF_DIR, register_configs


def test_two_job_local_parallel_multirun(trace_cache, tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "uabs_rl.cli.train", "-m", "hydra/launcher=local_parallel",
         "hydra.launcher.n_jobs=2", "experiment=smoke", "train.threads=1",
         "train.logger=none", "train.trajectory_images=false",
         f"traces.cache_dir={trace_cache}", "train.progress=false", "seed=0,1",
         f"hydra.sweep.dir={tmp_path}"], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for seed in (0, 1):
        run_dir = tmp_path / f"experiment=smoke,seed={seed}"  # named by its overrides
        lines = (run_dir / "metrics.jsonl").read_text().splitlines()
        assert [json.loads(x)["kind"] for x in lines].count("train") == 6
        assert (run_dir / "checkpoints" / "last.pt").is_file()


def test_slurm_launcher_config_composes():
    register_configs()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", ["hydra/launcher=slurm", "hydra.launcher.partition=gpu",
                                 "hydra.launcher.gpus_per_node=1"], return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert get_class(launcher._target_).__name__ == "SlurmLauncher"
    assert launcher.partition == "gpu" and launcher.gpus_per_node == 1
    assert launcher.cpus_per_task == 2 and launcher.timeout_min == 120
    assert launcher.submitit_folder.endswith(".submitit/%j")


@pytest.mark.slow
def test_submitit_local_multirun(trace_cache, tmp_path):
    """The cluster path for real: Hydra's submitit launcher with its local executor
    (``hydra/launcher=submitit_local``) submits, runs and collects two jobs; SLURM
    (``hydra/launcher=slurm``) differs from it only by the executor."""
    proc = subprocess.run(
        [sys.executable, "-m", "uabs_rl.cli.train", "-m", "hydra/launcher=submitit_local",
         "hydra.launcher.timeout_min=10", "hydra.launcher.cpus_per_task=1",
         "experiment=smoke", "train.threads=1", "train.logger=none",
         "train.trajectory_images=false", f"traces.cache_dir={trace_cache}",
         "train.progress=false", "seed=0,1", f"hydra.sweep.dir={tmp_path}"],
        capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    for seed in (0, 1):
        run_dir = tmp_path / f"experiment=smoke,seed={seed}"
        recs = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
        assert [r["kind"] for r in recs].count("train") == 6
        assert (run_dir / "checkpoints" / "best.pt").is_file()
    # submitit's own records of the jobs: one result pickle per job
    assert len(list((tmp_path / ".submitit").rglob("*_result.pkl"))) == 2
