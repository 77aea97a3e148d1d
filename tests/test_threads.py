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
from uabs_rl.safety.make import resolve_device
from uabs_rl.training.threads import (
    WORK_PER_THREAD,
    ThreadGovernor,
    cgroup_cpus,
    resolve_threads,
    setup_threads,
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
    monkeypatch.setattr("uabs_rl.training.threads.cgroup_cpus", lambda *a: None)
    paper = smoke(trace_cache, "algo.hidden=[256,256]", "algo.batch_size=128")
    assert update_work(paper) == 128 * 3 * (18 * 256 + 256 * 256 + 256 * 5)
    assert resolve_threads(paper, env) == (
        2, "2 (27.4M multiply-adds per update: a thread per 10M; 8 CPUs allowed "
           "by affinity)")
    assert resolve_threads(paper, {"SLURM_CPUS_PER_TASK": "1"})[0] == 1  # capped
    small = smoke(trace_cache)  # the smoke network: one thread
    assert update_work(small) < WORK_PER_THREAD
    assert resolve_threads(small, env) == (
        1, "1 (0.2M multiply-adds per update: one thread below 10M; 8 CPUs allowed by "
           "affinity)")
    big = smoke(trace_cache, "algo.hidden=[512,512]", "algo.batch_size=128")
    work = update_work(big)
    assert work == 128 * 3 * (18 * 512 + 512 * 512 + 512 * 5) == 105_185_280
    assert work // WORK_PER_THREAD == 10 and resolve_threads(big, env)[0] == 8
    pop = smoke(trace_cache, "train.population=4")
    assert update_work(pop) == 4 * update_work(small)
    # an explicit count wins, even above the CPUs allowed (said in the reason)
    assert resolve_threads(smoke(trace_cache, "train.threads=12"), env) == (
        12, "12 (train.threads; 8 CPUs allowed by affinity)")


def test_device_auto_says_what_it_chose(monkeypatch, caplog):
    caplog.set_level(logging.INFO, logger="uabs_rl.safety.make")
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


def proc_stat(tmp_path: Path, busy: dict[int, int], idle: int = 0) -> Path:
    """A /proc/stat whose cpuN lines hold ``busy[N]`` user ticks and ``idle`` idle ticks."""
    lines = ["cpu  0 0 0 0 0 0 0 0 0 0"] + [
        f"cpu{c} {b} 0 0 {idle} 0 0 0 0 0 0" for c, b in busy.items()]
    path = tmp_path / "stat"
    path.write_text("\n".join(lines) + "\nintr 1 2 3\n")
    return path


def test_governor_uses_the_cpus_others_leave_free(tmp_path, monkeypatch):
    """Two CPUs: the full count while others use at most NOISE of a core, one thread
    while another process keeps a core busy (whether or not its own threads took part of
    that core), and the full count again once it stops; the count is set in torch."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1}, raising=False)
    set_to = []
    monkeypatch.setattr(torch, "set_num_threads", set_to.append)
    gov = ThreadGovernor(2, fixed=False, period_s=0.0, stat=proc_stat(tmp_path, {0: 0, 1: 0}))
    assert gov.active and gov.cpus == [0, 1]
    assert [gov.threads_for(o) for o in (0.0, 0.25, 0.3, 0.5, 1.0, 1.9, 2.0)] == [
        2, 2, 1, 1, 1, 1, 1]
    tick = 1 / os.sysconf("SC_CLK_TCK")
    before = (0.0, 0.0, 0.0)
    # 1 s: both CPUs fully busy, this process used 1.0 of them -> another core is busy
    assert gov.others(before, (1.0, 2.0, 1.0)) == pytest.approx(1.0)
    assert gov.others(before, (1.0, 2.0, 1.5)) == pytest.approx(0.5)  # our spinning threads
    assert gov.others(before, (1.0, 1.0, 1.2)) == 0.0  # never negative
    # check() through the file: ticks of busy time, this process's CPU time faked
    # (children's CPU time counts as this process's: torch.compile's workers are not others)
    monkeypatch.setattr("uabs_rl.training.threads._children_cpu", lambda: 0.0)
    own = iter([0.0, 0.1, 0.2, 0.3, 1.3, 2.3, 3.3])
    monkeypatch.setattr("uabs_rl.training.threads.time.process_time", lambda: next(own))
    clock = iter(range(10))
    monkeypatch.setattr("uabs_rl.training.threads.time.monotonic", lambda: float(next(clock)))
    gov = ThreadGovernor(2, fixed=False, period_s=0.5, stat=tmp_path / "stat")
    t = round(1 / tick)
    # busy CPU-seconds of both CPUs so far, and the thread count after each look
    for busy, threads in [(2.0, 2), (2.1, 2),  # a second of a busy core changes nothing;
                          (4.1, 2), (6.1, 1),  # two in a row do (ours: 0.1, then 1.0);
                          (7.1, 1), (8.1, 2)]:  # then two quiet seconds (all ours)
        ticks = round(busy * t)
        proc_stat(tmp_path, {0: ticks // 2, 1: ticks - ticks // 2})
        assert gov.check() == threads, busy
    assert set_to == [1, 2] and gov.changes == 2


def test_governor_is_off_with_a_fixed_count_one_thread_or_no_proc_stat(tmp_path):
    stat = proc_stat(tmp_path, {0: 0})
    assert not ThreadGovernor(2, fixed=True, stat=stat).active
    assert not ThreadGovernor(1, fixed=False, stat=stat).active
    assert not ThreadGovernor(2, fixed=False, stat=tmp_path / "missing").active
    assert ThreadGovernor(2, fixed=True, stat=stat).check() == 2


def test_a_run_logs_its_threads_and_why(trace_cache, caplog, monkeypatch):
    monkeypatch.setattr(torch, "set_num_threads", lambda n: None)
    caplog.set_level(logging.INFO, logger="uabs_rl.training.threads")
    gov = setup_threads(smoke(trace_cache, "train.threads=3"))
    assert not gov.active and gov.n == 3
    assert caplog.messages[-1].startswith("threads: 3 (train.threads; ")
    gov = setup_threads(smoke(trace_cache))
    assert gov.n == 1 and "one thread below 10M" in caplog.messages[-1]


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")
def test_a_finished_child_and_a_grandchild_count_as_this_process():
    """torch.compile's workers start compilers that run a second or two and exit between
    two of the governor's looks: their CPU time is this process's, not other processes'
    (else a compile in training reads as a busy machine and the count drops)."""
    import subprocess
    import sys

    from uabs_rl.training.threads import _children_cpu

    burn = "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.5: pass"
    before = _children_cpu()
    subprocess.run([sys.executable, "-c", burn], check=True)  # a child, finished
    middle = _children_cpu()
    subprocess.run(["sh", "-c", f"{sys.executable} -c '{burn}'"], check=True)  # a grandchild
    after = _children_cpu()
    assert middle - before >= 0.45 and after - middle >= 0.45, (before, middle, after)
