"""Sweeps through Hydra launchers: a local-parallel multirun, the submitit launcher run
for real through its local executor (slow), and the SLURM config."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import get_class

from tests.test_train import records
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


def _train_episodes(run_dir: Path) -> list[int]:
    if not (run_dir / "metrics.jsonl").is_file():
        return []
    return [r["episode"] for r in records(run_dir) if r["kind"] == "train"]


def _endless_sweep(trace_cache: Path, sweep: Path, seeds: tuple[int, ...], *extra: str,
                   out=subprocess.PIPE) -> tuple[subprocess.Popen, list[Path]]:
    """A parallel sweep of smoke runs too long to end by themselves, started in its own
    process group (as a terminal's foreground job is), and its jobs' folders."""
    p = subprocess.Popen(
        [sys.executable, "-m", "uabs_rl.cli.train", "-m", "hydra/launcher=local_parallel",
         *extra, "experiment=smoke", "train.threads=1", "train.logger=none",
         "train.trajectory_images=false", f"traces.cache_dir={trace_cache}",
         "train.progress=false", "train.episodes=100000",
         f"seed={','.join(map(str, seeds))}", f"hydra.sweep.dir={sweep}"],
        stdout=out, stderr=out, text=True, start_new_session=True)
    return p, [sweep / f"experiment=smoke,seed={s},train.episodes=100000" for s in seeds]


def _wait_until(proc: subprocess.Popen, ready, timeout: float = 300) -> None:
    deadline = time.monotonic() + timeout
    while not ready():
        assert proc.poll() is None, (proc.communicate()[1] or "")[-3000:]
        assert time.monotonic() < deadline, "the sweep never got that far"
        time.sleep(0.2)


def _saved_each_episode_once(job: Path, err: str = "") -> int:
    """The episodes a stopped job logged, each once, its last.pt at the last of them."""
    episodes = _train_episodes(job)
    assert episodes == list(range(1, len(episodes) + 1)), err
    last = torch.load(job / "checkpoints" / "last.pt", weights_only=False)
    assert last["counters"]["episode"] == len(episodes), err
    return len(episodes)


def test_ctrl_c_stops_a_parallel_sweep_with_every_running_job_saved(trace_cache, tmp_path):
    """Before, joblib killed the workers at the first Ctrl-C: a job kept the checkpoint
    of episode 306 after logging 309. Now each running job saves after its round, the
    job not yet started never starts, and the command re-typed with resume= continues
    every job from its own last episode, each episode once."""
    sweep = tmp_path / "sweep"
    saved = {}
    for resume in ([], [f"resume={sweep}"]):
        p, jobs = _endless_sweep(trace_cache, sweep, (0, 1, 2), "hydra.launcher.n_jobs=2",
                                 *resume)
        _wait_until(p, lambda jobs=jobs: all(
            len(_train_episodes(j)) >= saved.get(j, 0) + 3 for j in jobs[:2]))
        os.killpg(p.pid, signal.SIGINT)  # Ctrl-C as a terminal sends it: the whole group
        _, err = p.communicate(timeout=300)
        for j in jobs[:2]:
            n = _saved_each_episode_once(j, err[-3000:])  # none lost
            assert n > saved.get(j, 0)
            saved[j] = n
        assert p.returncode == 130, err[-3000:]
        assert err.rstrip().splitlines()[-1] == (
            f"interrupted: every job that was running saved its last checkpoint and none "
            f"started after the stop; continue the sweep by re-typing its command (with "
            f"-m) and resume={sweep} appended")
        assert not jobs[2].exists()  # dispatched after the stop: it never started
        assert not (sweep / ".stopping").exists()


def _process_tree(pid: int) -> list[int]:
    out = [pid]
    for task in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{task}/children") as f:
            for child in map(int, f.read().split()):
                out += _process_tree(child)
    return out


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux's /proc")
def test_sigterm_to_every_process_of_a_parallel_sweep_saves_each_job_once(trace_cache,
                                                                          tmp_path):
    """A scheduler's scancel (SIGTERM to every process) with a worker more than jobs:
    the idle worker must not die of it (joblib would kill the others), and a job that
    gets the signal from the scheduler must not take the launcher's stop for a second
    signal (it would stop at once, without saving)."""
    p, jobs = _endless_sweep(trace_cache, tmp_path / "sweep", (0, 1), "hydra.launcher.n_jobs=3")
    _wait_until(p, lambda: all(len(_train_episodes(j)) >= 3 for j in jobs))
    for pid in _process_tree(p.pid):
        try:
            os.kill(pid, signal.SIGTERM)
        except OSError:
            pass
    _, err = p.communicate(timeout=300)
    # the whole of stderr on a failure: which process printed what, in which order (a
    # second signal reached a job or the launcher once in a CI run, from no known sender)
    for j in jobs:
        assert _saved_each_episode_once(j, err[-20000:]) >= 3
    assert p.returncode == 143, err[-20000:]
    assert "stopped at once" not in err, err[-20000:]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_parallel_sweep_whose_launcher_is_killed_saves_its_jobs_and_frees_them(
        trace_cache, tmp_path):
    """``kill -9`` of the launching process: before, its jobs (out of its reach) trained
    on to their ends holding their folders' locks, so a resume was refused; now each
    saves after its round and its worker ends."""
    from uabs_rl.runs.folder import RunLock

    # nothing reads its output once it is killed
    p, jobs = _endless_sweep(trace_cache, tmp_path / "sweep", (0, 1), out=subprocess.DEVNULL)
    _wait_until(p, lambda: all(len(_train_episodes(j)) >= 3 for j in jobs))
    tree = _process_tree(p.pid)
    p.kill()
    p.wait()
    deadline = time.monotonic() + 120
    while any(Path(f"/proc/{pid}").exists() for pid in tree[1:]):
        assert time.monotonic() < deadline, "the workers outlived their launcher"
        time.sleep(0.2)
    for j in jobs:
        assert _saved_each_episode_once(j) >= 3
        lock = RunLock(j)
        assert lock.acquire(record=False)  # what a resume takes first
        lock.release()


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
