"""Everyday faults lose or mix nothing: two runs started together, a resume while the
run still trains, SIGTERM, a re-typed command with ``resume=`` appended, a checkpoint of
another run, a population member without its checkpoint, a save cut between members."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from tests.conftest import Ran, run_command
from tests.test_train import records, smoke
from uabs_rl.runs.checkpoint import CheckpointError, load_checkpoint
from uabs_rl.runs.folder import RunFolderError, RunLock
from uabs_rl.training.members import complete_save
from uabs_rl.training.resume import prepare, run

QUIET = ["train.trajectory_images=false", "train.logger=none", "train.threads=1"]


def uabs_train(cwd: Path, *args: str, env: dict | None = None) -> subprocess.Popen:
    flags = [a for a in args if a.startswith("-")]  # Hydra's flags before the overrides
    return subprocess.Popen([sys.executable, "-m", "uabs_rl.cli.train", *flags,
                             "train.progress=false", *(a for a in args if a not in flags)],
                            cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=None if env is None else {**os.environ, **env})


def uabs_train_here(cwd: Path, *args: str, env: dict | None = None) -> Ran:
    """``uabs_train``'s command run in this process (tests.conftest.run_command): for a
    command that runs to its end (no kill, no signal, no second command beside it)."""
    flags = [a for a in args if a.startswith("-")]
    return run_command("train", *flags, "train.progress=false",
                       *(a for a in args if a not in flags), cwd=cwd, env=env)


def wait_for(path: Path, proc: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        assert time.monotonic() < deadline, f"{path} never appeared"
        time.sleep(0.1)


def episodes(run_dir: Path, kind: str = "train") -> list[int]:
    return [r["episode"] for r in records(run_dir) if r["kind"] == kind]


def error_lines(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if ln.startswith("error:")]


def test_two_identical_commands_started_together_never_share_a_folder(trace_cache, tmp_path):
    # both name their folder from the clock at day resolution, as two commands started
    # in the same second do with the default name
    args = ["experiment=smoke", f"traces.cache_dir={trace_cache}", *QUIET,
            "hydra.run.dir=outputs/${now:%Y-%m-%d}_same"]
    procs = [uabs_train(tmp_path, *args) for _ in range(2)]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err[-2000:]
    folders = sorted((tmp_path / "outputs").iterdir())
    assert [f.name.endswith(("_same", "_same-2")) for f in folders] == [True, True]
    for f in folders:  # every record once, and both runs whole and equal
        assert episodes(f) == [1, 2, 3, 4, 5, 6]
        assert episodes(f, "eval") == [3, 6]
        assert (f / ".hydra" / "config.yaml").is_file()
    assert records(folders[0]) == records(folders[1])
    ids = {json.loads((f / "run.json").read_text())["id"] for f in folders}
    assert len(ids) == 2


def test_resume_of_a_run_that_is_still_training_is_refused(trace_cache, tmp_path):
    run_dir = tmp_path / "busy"
    proc = uabs_train(tmp_path, "experiment=smoke", f"traces.cache_dir={trace_cache}",
                      *QUIET, "train.episodes=200", "train.eval_every=100",
                      f"hydra.run.dir={run_dir}")
    try:
        wait_for(run_dir / "metrics.jsonl", proc)
        second = uabs_train(tmp_path, f"resume={run_dir}", f"traces.cache_dir={trace_cache}")
        _, err = second.communicate(timeout=120)
        assert second.returncode == 2, err[-2000:]
        [line] = error_lines(err)
        assert f"pid {proc.pid}" in line and "being written by another" in line
        assert proc.poll() is None  # the first run goes on untouched
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=120)
    assert proc.returncode == 143
    eps = episodes(run_dir)
    assert eps == list(range(1, len(eps) + 1))  # each episode once, none mixed in


def test_a_stopped_sweep_says_to_re_type_the_sweep_and_continues_so(trace_cache, tmp_path):
    """A job of a sweep stopped by SIGTERM names the sweep's resume (its own folder's
    resume= alone is refused with -m and loses the other jobs): the command re-typed with
    resume=<sweep> finishes every job, the stopped one continued, not restarted."""
    sweep = tmp_path / "sweep"
    args = ["-m", "experiment=smoke", f"traces.cache_dir={trace_cache}", *QUIET,
            "train.episodes=150", "train.eval_every=75", "seed=0,1",
            f"hydra.sweep.dir={sweep}"]
    proc = uabs_train(tmp_path, *args)
    first = sweep / "experiment=smoke,seed=0,train.episodes=150,train.eval_every=75"
    wait_for(first / "metrics.jsonl", proc)
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err[-2000:]
    assert err.strip().splitlines()[-1].endswith(
        f"continue the whole sweep by re-typing its command (with -m) and resume={sweep} "
        f"appended"), err[-2000:]
    stopped = episodes(first)
    assert 0 < len(stopped) < 150
    again = uabs_train(tmp_path, *args, f"resume={sweep}")
    _, err = again.communicate(timeout=600)
    assert again.returncode == 0, err[-2000:]
    assert episodes(first) == list(range(1, 151))  # continued: each episode once
    assert episodes(sweep / "experiment=smoke,seed=1,train.episodes=150,train.eval_every=75"
                    )[-1] == 150


def test_sigterm_saves_a_checkpoint_as_fresh_as_the_last_record(trace_cache, tmp_path):
    run_dir = tmp_path / "preempted"
    proc = uabs_train(tmp_path, "experiment=smoke", f"traces.cache_dir={trace_cache}",
                      *QUIET, "train.episodes=300", "train.eval_every=100",
                      "train.checkpoint_buffer=true", f"hydra.run.dir={run_dir}")
    wait_for(run_dir / "metrics.jsonl", proc)
    time.sleep(1.0)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err[-2000:]
    assert "SIGTERM: stopping after this round" in err
    assert f"continue with resume={run_dir}" in err.strip().splitlines()[-1]
    last = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    train = [r for r in records(run_dir) if r["kind"] == "train"]
    assert 0 < len(train) < 100  # stopped midway, before any evaluation
    assert last["counters"]["episode"] == train[-1]["episode"]
    assert last["counters"]["env_steps"] == train[-1]["env_steps"]
    assert last["replay"] is not None


def test_the_original_command_with_resume_appended_continues_the_run(trace_cache, tmp_path):
    run_dir = tmp_path / "masking=flat,seed=3"
    original = ["experiment=smoke", "masking=flat", "seed=3", f"traces.cache_dir={trace_cache}",
                *QUIET, f"hydra.run.dir='{run_dir}'"]
    first = uabs_train_here(tmp_path, *original, "train.episodes=3")
    assert first.returncode == 0, first.stderr[-2000:]
    again = uabs_train_here(tmp_path, *original, f"resume={run_dir}")  # 6 episodes, as typed
    assert again.returncode == 0, again.stderr[-2000:]
    assert episodes(run_dir) == [1, 2, 3, 4, 5, 6]
    state = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    assert state["config"]["masking"]["mode"] == "flat" and state["config"]["seed"] == 3
    # a group choice, a seed or a preset that would change results is refused (composed
    # in process here, as the command line composes it)
    for old, new in (("masking=flat", "masking=rank"), ("seed=3", "seed=4"),
                     ("experiment=smoke", "experiment=lookahead")):
        wrong = [new if o == old else o for o in original if "hydra" not in o]
        with pytest.raises(CheckpointError, match="would change its results"):
            prepare(smoke(trace_cache, f"resume='{run_dir}'"), Path("unused"),
                    overrides=[*wrong, f"resume={run_dir}"])
    assert episodes(run_dir) == [1, 2, 3, 4, 5, 6]  # nothing written by the refusals


def test_a_checkpoint_of_another_run_is_refused(trace_cache, tmp_path):
    flat, rank = tmp_path / "flat", tmp_path / "rank"
    run(smoke(trace_cache, *QUIET, "masking=flat", "train.episodes=3"), flat)
    run(smoke(trace_cache, *QUIET, "train.episodes=3"), rank)
    before = records(rank)
    shutil.copyfile(flat / "checkpoints" / "last.pt", rank / "checkpoints" / "last.pt")
    cfg = smoke(trace_cache, f"resume={rank}", "train.episodes=6")
    with pytest.raises(RunFolderError, match="belongs to another run"):
        prepare(cfg, Path("unused"), overrides=[f"resume={rank}", "train.episodes=6"])
    # a checkpoint written before runs had identities: its settings give it away
    state = load_checkpoint(rank / "checkpoints" / "last.pt")
    del state["run"]
    torch.save(state, rank / "checkpoints" / "last.pt")
    from omegaconf import OmegaConf

    from uabs_rl.runs.checkpoint import config_dict
    (rank / ".hydra").mkdir()
    OmegaConf.save(OmegaConf.create(config_dict(smoke(trace_cache, *QUIET,
                                                      "train.episodes=3"))),
                   rank / ".hydra" / "config.yaml")
    with pytest.raises(CheckpointError, match=r"does not belong to the run.*masking\.mode"):
        prepare(cfg, Path("unused"), overrides=[f"resume={rank}", "train.episodes=6"])
    assert records(rank) == before  # nothing was truncated or appended


def test_a_population_member_without_its_checkpoint_is_refused_and_nothing_wiped(
        trace_cache, tmp_path):
    run_dir = tmp_path / "pop"
    run(smoke(trace_cache, *QUIET, "train.population=2", "train.episodes=3"), run_dir)
    member0 = records(run_dir / "seed=0")
    (run_dir / "seed=1" / "checkpoints" / "last.pt").unlink()
    cfg = smoke(trace_cache, f"resume={run_dir}", "train.episodes=6")
    with pytest.raises(CheckpointError, match=r"member seed=1 has no checkpoints/last\.pt"):
        prepare(cfg, Path("unused"), overrides=[f"resume={run_dir}", "train.episodes=6"])
    assert records(run_dir / "seed=0") == member0  # the completed member is intact
    assert (run_dir / "seed=0" / "checkpoints" / "last.pt").is_file()


def test_a_population_save_cut_between_members_is_completed_or_dropped(trace_cache, tmp_path):
    run_dir = tmp_path / "pop"
    run(smoke(trace_cache, *QUIET, "train.population=2", "train.episodes=3"), run_dir)
    ck = [run_dir / f"seed={s}" / "checkpoints" for s in (0, 1)]
    old = [load_checkpoint(c / "last.pt") for c in ck]
    newer = [dict(s, counters=dict(s["counters"], episode=99)) for s in old]
    # killed after the staged files and the commit record: the save is finished, also
    # when the population folder was moved since (the record names files relative to it)
    for c, s in zip(ck, newer, strict=True):
        torch.save(s, c / "last.staged.pt")
    (run_dir / ".last.commit").write_text(json.dumps([f"seed={s}/checkpoints/last.staged.pt"
                                                      for s in (0, 1)]))
    moved = tmp_path / "moved"
    run_dir.rename(moved)
    complete_save(moved)
    moved.rename(run_dir)
    assert [load_checkpoint(c / "last.pt")["counters"]["episode"] for c in ck] == [99, 99]
    assert not (run_dir / ".last.commit").exists()
    # killed before the commit record: the staged files are dropped, the old set stays
    torch.save(old[0], ck[0] / "last.staged.pt")
    complete_save(run_dir)
    assert not (ck[0] / "last.staged.pt").exists()
    assert [load_checkpoint(c / "last.pt")["counters"]["episode"] for c in ck] == [99, 99]


def test_a_stale_lock_of_a_dead_process_is_taken_over(tmp_path):
    child = subprocess.Popen([sys.executable, "-c", (
        "import sys, time; from uabs_rl.runs.folder import RunLock; "
        f"lock = RunLock({str(tmp_path)!r}); assert lock.acquire(); print('held', flush=True); "
        "time.sleep(60)")], stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline().strip() == "held"
    assert not RunLock(tmp_path).acquire()
    assert f"pid {child.pid}" in RunLock(tmp_path).holder()
    child.kill()
    child.wait()
    lock = RunLock(tmp_path)
    assert lock.acquire()  # the kernel dropped the dead holder's lock
    lock.release()


def test_the_final_checkpoint_is_written_while_the_run_folder_is_locked(trace_cache, tmp_path,
                                                                        monkeypatch):
    """A second writer cannot take the folder between the last round and the final save."""
    from uabs_rl.training.members import Checkpoints

    save, free_at_save = Checkpoints.save, []

    def checked_save(self, i, name):
        probe = RunLock(self.exp.run_dir)
        free_at_save.append(probe.acquire())
        if free_at_save[-1]:
            probe.release()
        return save(self, i, name)

    monkeypatch.setattr(Checkpoints, "save", checked_save)
    run(smoke(trace_cache, *QUIET, "train.episodes=3", "train.eval_every=3"), tmp_path / "run")
    assert free_at_save and not any(free_at_save)  # every save, the final one included
    assert RunLock(tmp_path / "run").acquire()  # released once the run ended


def test_a_slurm_requeued_job_continues_its_run(trace_cache, tmp_path):
    run_dir = tmp_path / "job"
    args = ["experiment=smoke", f"traces.cache_dir={trace_cache}", *QUIET,
            f"hydra.run.dir={run_dir}"]
    p = uabs_train_here(tmp_path, *args, "train.episodes=3")
    assert p.returncode == 0, p.stderr[-2000:]
    # the same command again, as SLURM requeues it: the run continues in place
    p = uabs_train_here(tmp_path, *args, env={"SLURM_RESTART_COUNT": "1"})
    assert p.returncode == 0, p.stderr[-2000:]
    assert episodes(run_dir) == [1, 2, 3, 4, 5, 6]
    # outside a requeue the same command refuses to overwrite the run
    p = uabs_train_here(tmp_path, *args)
    assert p.returncode == 2 and "already holds a run" in p.stderr


def test_a_full_disk_a_read_only_folder_and_a_removed_folder_are_one_line(
        trace_cache, tmp_path, monkeypatch):
    import errno

    import uabs_rl.training.members as members
    from uabs_rl.training.experiment import Experiment

    def full(state, path):  # what torch.save raises when the disk fills mid-write
        raise RuntimeError("[enforce fail at inline_container.cc:783] . unexpected pos "
                           "9856 vs 9744")

    monkeypatch.setattr(members, "save_checkpoint", full)
    with pytest.raises(RunFolderError, match=r"no space left on the device while writing"):
        run(smoke(trace_cache, *QUIET), tmp_path / "full")
    monkeypatch.undo()

    real_write = Path.write_text

    def read_only(self, *a, **k):
        if self.name.startswith(".probe"):
            raise PermissionError(errno.EROFS, "Read-only file system", str(self))
        return real_write(self, *a, **k)

    monkeypatch.setattr(Path, "write_text", read_only)
    with pytest.raises(RunFolderError, match=r"cannot write into the run folder .*"
                                             r"Read-only file system"):
        prepare(smoke(trace_cache, *QUIET), tmp_path / "ro")
    monkeypatch.undo()

    exp = Experiment(smoke(trace_cache, *QUIET), tmp_path / "gone")
    real = exp.collect

    def removed():
        if exp.episode == 2:
            shutil.rmtree(exp.run_dir)
        return real()

    monkeypatch.setattr(exp, "collect", removed)
    with pytest.raises(RunFolderError, match="was removed or moved while the run"):
        exp.fit()


def test_bad_run_folders_and_ctrl_c_while_loading_are_one_line(trace_cache, tmp_path):
    (tmp_path / "afile").write_text("")
    for args, expected in (
            (["hydra.run.dir=afile/run"], "hydra.run.dir=afile/run: afile is a file"),
            ([f"resume={tmp_path / 'nowhere'}"], "no such folder")):
        p = uabs_train_here(tmp_path, "experiment=smoke", *args)
        err = p.stderr
        assert p.returncode == 2 and error_lines(err) == [err.strip()], err[-2000:]
        assert expected in err
    assert not (tmp_path / "nowhere").exists() and not (tmp_path / "outputs").exists()
    # a garbled .hydra/config.yaml of a run stopped before its first checkpoint
    run_dir = tmp_path / "garbled"
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / ".hydra" / "config.yaml").write_text("scenario: [unclosed\n")
    p = uabs_train_here(tmp_path, f"resume={run_dir}", f"traces.cache_dir={trace_cache}")
    err = p.stderr
    assert p.returncode == 2 and error_lines(err) == [err.strip()], err[-2000:]
    assert ".hydra/config.yaml is damaged" in err
    # Ctrl-C while torch and Hydra load: one line, status 130
    exe = Path(sys.executable).parent / "uabs-train"
    p = subprocess.Popen([str(exe), "experiment=smoke"], cwd=tmp_path, text=True,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    time.sleep(0.5)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 130 and err.strip() == "interrupted", err[-2000:]


def test_a_sweep_retyped_with_resume_continues_every_job(trace_cache, tmp_path):
    sweep = ["-m", "experiment=smoke", "masking=flat,rank", f"traces.cache_dir={trace_cache}",
             *QUIET, "train.episodes=3", "hydra.sweep.dir=sweep"]
    p = uabs_train_here(tmp_path, *sweep)
    assert p.returncode == 0, p.stderr[-2000:]
    jobs = sorted(d for d in (tmp_path / "sweep").iterdir() if d.is_dir())
    assert len(jobs) == 2
    first = {j: load_checkpoint(j / "checkpoints" / "last.pt")["run"]["id"] for j in jobs}
    p = uabs_train_here(tmp_path, *sweep, f"resume={tmp_path / 'sweep'}")
    err = p.stderr
    assert p.returncode == 0, err[-2000:]
    for j in jobs:  # each job continued its own run (finished: nothing appended)
        assert f"resuming {j}" in err
        assert episodes(j) == [1, 2, 3]
        assert load_checkpoint(j / "checkpoints" / "last.pt")["run"]["id"] == first[j]
    assert sorted(d for d in (tmp_path / "sweep").iterdir() if d.is_dir()) == jobs
    # a sweep stopped before its last job: re-typed, that job starts in its own folder
    shutil.rmtree(jobs[1])
    p = uabs_train_here(tmp_path, *sweep, f"resume={tmp_path / 'sweep'}")
    err = p.stderr
    assert p.returncode == 0, err[-2000:]
    assert f"resuming {jobs[0]}" in err and f"run folder: {jobs[1]}" in err
    assert episodes(jobs[0]) == episodes(jobs[1]) == [1, 2, 3]
    assert (jobs[1] / ".hydra" / "config.yaml").is_file()


@pytest.fixture(scope="module")
def three_episodes(trace_cache, tmp_path_factory) -> Path:
    """A finished 3-episode smoke run, trained once for the tests that damage a copy."""
    run_dir = tmp_path_factory.mktemp("three_episodes") / "run"
    run(smoke(trace_cache, *QUIET, "train.episodes=3"), run_dir)
    return run_dir


@pytest.mark.parametrize("damage", [b'{"kind": "train", "epis', b"17", b"\xff\xfe{}",
                                    b'{"kind": "train", "episode": "3", "env_steps": 60}'])
def test_a_damaged_line_before_the_last_is_refused_on_resume(three_episodes, trace_cache,
                                                              tmp_path, damage):
    run_dir = tmp_path / "run"
    shutil.copytree(three_episodes, run_dir, ignore=shutil.ignore_patterns(".lock"))
    original = (run_dir / "metrics.jsonl").read_bytes().splitlines()
    lines = [*original[:1], damage, *original[2:]]
    (run_dir / "metrics.jsonl").write_bytes(b"\n".join(lines) + b"\n")
    before = (run_dir / "metrics.jsonl").read_bytes()
    exp = prepare(smoke(trace_cache, f"resume={run_dir}", "train.episodes=6"), Path("x"),
                  overrides=[f"resume={run_dir}", "train.episodes=6"])
    with pytest.raises(RunFolderError, match=rf"metrics\.jsonl, line 2 of {len(lines)}, is "
                                             r"damaged"):
        exp.fit()
    assert (run_dir / "metrics.jsonl").read_bytes() == before  # nothing dropped
    # the same damage on the last line is a write cut by a crash: repaired
    (run_dir / "metrics.jsonl").write_bytes(b"\n".join([*original, damage]))
    run(smoke(trace_cache, f"resume={run_dir}", "train.episodes=6"), Path("x"),
        overrides=[f"resume={run_dir}", "train.episodes=6"])
    assert episodes(run_dir) == [1, 2, 3, 4, 5, 6]


def test_a_failed_checkpoint_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    from uabs_rl.runs import checkpoint

    path = tmp_path / "checkpoints" / "last.pt"
    checkpoint.save_checkpoint({"format": 1, "x": torch.ones(3)}, path)
    before = path.read_bytes()

    def full(obj, f):  # a write that fills the disk halfway
        f.write(b"PK\x03\x04 half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(checkpoint.torch, "save", full)
    with pytest.raises(OSError, match="No space left"):
        checkpoint.save_checkpoint({"format": 1, "x": torch.zeros(3)}, path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in path.parent.iterdir()) == ["last.pt"]
    shutil.rmtree(tmp_path / "checkpoints")  # the run folder's content removed mid-run
    (tmp_path / "gone").mkdir()
    shutil.rmtree(tmp_path / "gone")
    with pytest.raises(FileNotFoundError):  # not made again behind the user's back
        checkpoint.save_checkpoint({"format": 1}, tmp_path / "gone" / "checkpoints" / "x.pt")
    assert not (tmp_path / "gone").exists()
