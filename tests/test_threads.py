"""CPU threads of a run: the CPUs a process may use (affinity, cgroup quotas, SLURM,
OMP_NUM_THREADS), the default count from the network's size, the override; and what
device=auto chose."""

from __future__ import annotations

import logging
import os
from pathlib import Path

import pytest
import torch

from tests.test_train import smoke
from uabs_rl.make import (
    WORK_PER_THREAD,
    cgroup_cpus,
    resolve_device,
    resolve_threads,
    update_work,
    usable_cpus,
)


@pytest.fixture
def eight_cores(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)), raising=False)


def cgroup_v2(tmp_path: Path, quotas: dict[str, str]) -> tuple[Path, Path]:
    """A cgroup v2 tree with ``cpu.max`` per folder and this process in the deepest."""
    root = tmp_path / "cgroup"
    for path, text in quotas.items():
        (root / path).mkdir(parents=True, exist_ok=True)
        (root / path / "cpu.max").write_text(text + "\n")
    proc = tmp_path / "proc_cgroup"
    proc.write_text(f"0::/{max(quotas, key=len)}\n")
    return root, proc


def test_cgroup_v2_quota_is_the_tightest_on_the_way_up(tmp_path):
    root, proc = cgroup_v2(tmp_path, {"": "max 100000", "job": "250000 100000",
                                      "job/step": "max 100000"})
    assert cgroup_cpus(root, proc) == 2  # 2.5 CPUs of time: two whole threads
    root, proc = cgroup_v2(tmp_path / "b", {"": "max 100000", "a/b": "400000 100000",
                                            "a": "300000 100000"})
    assert cgroup_cpus(root, proc) == 3
    root, proc = cgroup_v2(tmp_path / "c", {"": "max 100000", "x": "50000 100000"})
    assert cgroup_cpus(root, proc) == 1  # half a CPU: still one thread
    root, proc = cgroup_v2(tmp_path / "d", {"": "max 100000"})
    assert cgroup_cpus(root, proc) is None


def test_cgroup_v1_quota_and_a_container_that_sees_host_paths(tmp_path):
    root = tmp_path / "cgroup"
    cpu = root / "cpu,cpuacct"
    cpu.mkdir(parents=True)
    (cpu / "cpu.cfs_quota_us").write_text("300000\n")
    (cpu / "cpu.cfs_period_us").write_text("100000\n")
    proc = tmp_path / "proc_cgroup"
    # the host's path of this container's cgroup, not below the mount: the mount's own
    proc.write_text("4:memory:/x\n3:cpu,cpuacct:/docker/abc123\n0::/\n")
    assert cgroup_cpus(root, proc) == 3
    (cpu / "cpu.cfs_quota_us").write_text("-1\n")
    assert cgroup_cpus(root, proc) is None
    assert cgroup_cpus(root, tmp_path / "missing") is None


def test_usable_cpus_is_the_least_limit_and_names_it(tmp_path, eight_cores):
    none = tmp_path / "missing"
    assert usable_cpus({}, proc_cgroup=none) == (8, "affinity")
    assert usable_cpus({"SLURM_CPUS_PER_TASK": "3"}, proc_cgroup=none) == (
        3, "SLURM_CPUS_PER_TASK")
    assert usable_cpus({"SLURM_CPUS_PER_TASK": "3", "OMP_NUM_THREADS": "2"},
                       proc_cgroup=none) == (2, "OMP_NUM_THREADS")
    assert usable_cpus({"OMP_NUM_THREADS": "4,2", "SLURM_CPUS_PER_TASK": ""},
                       proc_cgroup=none) == (8, "affinity")  # unparsable: ignored
    root, proc = cgroup_v2(tmp_path, {"": "200000 100000"})
    assert usable_cpus({"SLURM_CPUS_PER_TASK": "4"}, root, proc) == (
        2, "the cgroup CPU quota")


def test_default_threads_follow_the_network_size(trace_cache, monkeypatch, eight_cores):
    env = {}
    monkeypatch.setattr("uabs_rl.make.cgroup_cpus", lambda *a: None)
    paper = smoke(trace_cache, "algo.hidden=[256,256]", "algo.batch_size=128")
    assert update_work(paper) == 128 * 3 * (18 * 256 + 256 * 256 + 256 * 5)
    assert resolve_threads(paper, env) == (
        1, "1 (27.4M multiply-adds per update: one thread below 440M; 8 CPUs allowed "
           "by affinity)")
    big = smoke(trace_cache, "algo.hidden=[1024,1024]", "algo.batch_size=512",
                "algo.learning_starts=512")
    work = update_work(big)
    assert work == 512 * 3 * (18 * 1024 + 1024 * 1024 + 1024 * 5) == 1_646_788_608
    assert work // WORK_PER_THREAD == 3
    assert resolve_threads(big, env) == (
        3, "3 (1,646.8M multiply-adds per update: a thread per 440M; 8 CPUs allowed by "
           "affinity)")
    assert resolve_threads(big, {"SLURM_CPUS_PER_TASK": "2"})[0] == 2  # capped
    pop = smoke(trace_cache, "algo.hidden=[1024,1024]", "algo.batch_size=512",
                "algo.learning_starts=512", "train.population=4")
    assert update_work(pop) == 4 * work and resolve_threads(pop, env)[0] == 8
    # an explicit count wins, even above the CPUs allowed (said in the reason)
    assert resolve_threads(smoke(trace_cache, "train.threads=12"), env) == (
        12, "12 (train.threads; 8 CPUs allowed by affinity)")


def test_device_auto_says_what_it_chose(monkeypatch, caplog):
    caplog.set_level(logging.INFO, logger="uabs_rl.make")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    assert "device=auto: using cpu (no CUDA)" in caplog.messages
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 1)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda i: f"Fake GPU {i}")
    assert resolve_device("auto") == torch.device("cuda")
    assert "device=auto: using cuda:1 (Fake GPU 1)" in caplog.messages
    caplog.clear()
    assert resolve_device("cpu") == torch.device("cpu") and not caplog.messages
