"""A refused command never deletes or rewrites what was there, and a run's history is
never replaced or mixed: a bad value aimed at a user's folder, a re-typed command aimed
at a finished run, a second sweep into a sweep's folder, a resume of a run whose
checkpoint was removed, a lock file deleted under its holder, metrics.jsonl or tb/
removed while the run writes them, and signals (SIGHUP, a second SIGTERM)."""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import Ran, run_command
from tests.test_faults import QUIET, error_lines, uabs_train, uabs_train_here, wait_for
from tests.test_train import records, smoke
from uabs_rl.runs.folder import Before, RunFolderError, RunLock
from uabs_rl.runs.metrics import MetricsError, read_metrics
from uabs_rl.training.resume import run
from uabs_rl.training.runlog import RunLog


def tree(root: Path, skip: tuple[str, ...] = ()) -> dict[str, str]:
    """Every file under ``root`` (relative path -> md5), and every folder (-> "dir")."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        if p.name in skip:
            continue
        out[rel] = "dir" if p.is_dir() else hashlib.md5(p.read_bytes()).hexdigest()
    return out


def one_error(proc: subprocess.Popen | Ran, timeout: float = 300) -> str:
    """The one line a refused command prints; asserts exit 2 and no traceback."""
    err = proc.stderr if isinstance(proc, Ran) else proc.communicate(timeout=timeout)[1]
    assert proc.returncode == 2, err[-2000:]
    assert "Traceback" not in err, err[-2000:]
    lines = error_lines(err)
    assert len(lines) == 1, err[-2000:]
    return lines[0]


@pytest.fixture(scope="module")
def finished_run(trace_cache, tmp_path_factory) -> tuple[Path, list[str]]:
    """A finished smoke run trained by the command line (in this process), and that
    command's overrides."""
    where = tmp_path_factory.mktemp("finished")
    args = ["experiment=smoke", f"traces.cache_dir={trace_cache}", "train.threads=1",
            "train.trajectory_images=false", "train.eval_every=2"]
    p = uabs_train_here(where, *args, "train.episodes=4", f"hydra.run.dir={where / 'run'}")
    assert p.returncode == 0, p.stderr[-2000:]
    return where / "run", args


def wait_until(ready, proc: subprocess.Popen, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while not ready():
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        assert time.monotonic() < deadline, "never ready"
        time.sleep(0.05)


def copy_of(run_dir: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "copy"
    shutil.copytree(run_dir, dst, ignore=shutil.ignore_patterns(".lock"))
    return dst


def test_a_bad_value_aimed_at_a_users_folder_leaves_it_as_it_was(trace_cache, tmp_path):
    mine = tmp_path / "mylogs"
    mine.mkdir()
    (mine / "important.log").write_text("precious\n")
    (mine / "hydra.log").write_text("the user's own hydra.log\n")
    before = tree(mine)
    err = one_error(uabs_train_here(tmp_path, "experiment=smoke", f"traces.cache_dir={trace_cache}",
                                    f"hydra.run.dir={mine}", "scenario.n_uabs=0"))
    assert "scenario.n_uabs" in err
    assert tree(mine) == before  # nothing removed, nothing added (.lock, .hydra)
    # a folder the command made (with its parents) goes with the refused start
    err = one_error(uabs_train_here(tmp_path, "experiment=smoke", f"traces.cache_dir={trace_cache}",
                                    f"hydra.run.dir={tmp_path / 'new' / 'deep' / 'run'}",
                                    "scenario.n_uabs=0"))
    assert not (tmp_path / "new").exists()


def test_before_tells_made_from_found(tmp_path):
    (tmp_path / "old").mkdir()
    before = Before([tmp_path / "old" / "run", tmp_path / "x" / "y"])
    assert not before.created(tmp_path / "old")
    assert before.created(tmp_path / "old" / "run")
    assert before.created(tmp_path / "x") and before.created(tmp_path / "x" / "y" / "z")
    assert not before.created(Path("/tmp"))  # there before, though not named


def test_a_refused_command_leaves_a_finished_runs_record_and_history(finished_run, tmp_path):
    run_dir, args = finished_run
    run_dir = copy_of(run_dir, tmp_path)
    (run_dir / ".lock").write_text("the last holder's record\n")
    before = tree(run_dir)
    err = one_error(uabs_train_here(tmp_path, *args, "train.episodes=4", "algo.lr=0.5",
                                    f"hydra.run.dir={run_dir}"))
    assert "already holds a run" in err
    assert tree(run_dir) == before  # .hydra/ and .lock included
    # so the run's own command, re-typed with resume= appended, still continues it
    p = uabs_train_here(tmp_path, *args, "train.episodes=6", f"resume={run_dir}")
    assert p.returncode == 0, p.stderr[-2000:]
    assert [r["episode"] for r in read_metrics(run_dir / "metrics.jsonl")
            if r["kind"] == "train"] == list(range(1, 7))


def test_a_second_sweep_into_a_sweeps_folder_is_refused(trace_cache, tmp_path):
    sweep = tmp_path / "sweep"
    job = sweep / "masking=flat"
    (job / ".hydra").mkdir(parents=True)
    (sweep / "multirun.yaml").write_text("the first sweep's record\n")
    (job / ".hydra" / "config.yaml").write_text("seed: 0\n")
    before = tree(sweep)
    err = one_error(uabs_train_here(tmp_path, "-m", "experiment=smoke", "masking=flat,rank",
                                    f"traces.cache_dir={trace_cache}", f"hydra.sweep.dir={sweep}"))
    assert "holds another sweep" in err and f"resume={sweep}" in err
    assert tree(sweep) == before


def test_what_existed_before_survives_the_trip_to_a_parallel_worker(tmp_path):
    """A local_parallel sweep's jobs get the parent's :class:`Before` pickled: a folder
    that did not exist must still read as absent there (its sentinel compared by identity
    once, and a refused job ended in a TypeError traceback instead of its one line)."""
    import pickle

    sweep = tmp_path / "sweep"
    there = pickle.loads(pickle.dumps(Before([sweep])))
    (sweep / "job").mkdir(parents=True)
    assert there.created(sweep) and there.created(sweep / "job")
    assert not there.created(tmp_path)


def test_a_sweep_resumed_with_another_command_is_refused(trace_cache, tmp_path):
    """``-m ... resume=<sweep folder>`` continues the sweep its multirun.yaml records only
    when re-typed as that sweep (values in any order, settings that cannot change results
    free): without its overrides it started one run in the sweep folder itself; with one
    left out, new runs beside its own; and Hydra overwrote the record. Without ``-m`` it
    names what to type."""
    sweep = tmp_path / "sweep"
    job = sweep / "experiment=smoke,masking=flat,seed=0"
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "config.yaml").write_text("seed: 0\n")
    (sweep / "multirun.yaml").write_text(
        "hydra:\n  overrides:\n    task:\n    - experiment=smoke\n    - masking=flat,rank\n"
        "    - seed=0\n    - train.progress=false\n")
    before = tree(sweep)
    common = [f"traces.cache_dir={trace_cache}", f"resume={sweep}"]
    for args, says in ((["-m"], "lacks experiment, masking, seed"),
                       (["-m", "masking=flat,rank", "seed=0"], "lacks experiment"),
                       (["-m", "experiment=smoke", "masking=flat,rank", "seed=0,1"],
                        "changes seed"),
                       (["-m", "experiment=smoke", "masking=flat,rank", "seed=0",
                         "train.episodes=12"], "adds train.episodes")):
        err = one_error(run_command("train", *args, *common))
        assert err.startswith(f"error: resume={sweep} continues the sweep typed as `uabs-train "
                              f"-m experiment=smoke masking=flat,rank seed=0 "
                              f"train.progress=false`; this command {says}: re-type"), err
        assert tree(sweep) == before
    err = one_error(run_command("train", *common))
    assert f"resume={sweep} is a sweep's folder (multirun.yaml): re-type the sweep's" in err
    assert tree(sweep) == before


def test_resume_refuses_a_run_whose_checkpoint_was_removed(finished_run, tmp_path):
    run_dir, args = finished_run
    run_dir = copy_of(run_dir, tmp_path)
    shutil.rmtree(run_dir / "checkpoints")
    before = tree(run_dir, skip=(".lock",))
    err = one_error(uabs_train_here(tmp_path, *args, "train.episodes=4", f"resume={run_dir}"))
    assert "no checkpoints/last.pt" in err and "history" in err
    assert tree(run_dir, skip=(".lock",)) == before  # metrics.jsonl and tb/ untouched
    (run_dir / "checkpoints").write_text("not a folder")  # a file in its place
    before = tree(run_dir, skip=(".lock",))
    err = one_error(uabs_train_here(tmp_path, *args, "train.episodes=4", f"resume={run_dir}"))
    assert "is not a folder" in err
    assert tree(run_dir, skip=(".lock",)) == before


def test_resume_refuses_a_history_with_a_hole(finished_run, tmp_path):
    run_dir, args = finished_run
    run_dir = copy_of(run_dir, tmp_path)
    lines = (run_dir / "metrics.jsonl").read_text().splitlines(keepends=True)
    (run_dir / "metrics.jsonl").write_text("".join(lines[2:]))  # episodes 1-2 gone
    before = tree(run_dir, skip=(".lock",))
    err = one_error(uabs_train_here(tmp_path, *args, "train.episodes=6", f"resume={run_dir}"))
    assert "starts at episode 3" in err
    assert tree(run_dir, skip=(".lock",)) == before
    with pytest.raises(MetricsError, match="starts at episode 3"):  # uabs-report's reader
        read_metrics(run_dir / "metrics.jsonl")


def test_an_empty_hydra_config_is_not_read_as_the_paper_defaults(finished_run, tmp_path):
    """A full disk at start-up once left .hydra/config.yaml empty; a resume of that
    folder must not train the defaults in place of the original command."""
    run_dir, _ = finished_run
    run_dir = copy_of(run_dir, tmp_path)
    shutil.rmtree(run_dir / "checkpoints")
    (run_dir / "metrics.jsonl").write_text("")
    (run_dir / ".hydra" / "config.yaml").write_text("")
    err = one_error(uabs_train_here(tmp_path, f"resume={run_dir}"))
    assert "config.yaml is damaged" in err


def test_deleting_the_lock_file_does_not_free_the_folder(tmp_path):
    held = RunLock(tmp_path)
    assert held.acquire()
    (tmp_path / ".lock").unlink()
    second = RunLock(tmp_path)
    assert not second.acquire()
    held.release()
    assert second.acquire()
    second.release()


def test_metrics_removed_while_the_run_writes_it_stops_the_run(trace_cache, tmp_path):
    cfg = smoke(trace_cache, *QUIET)
    log = RunLog(cfg, tmp_path)
    log.open()
    rec = {"kind": "train", "episode": 1, "env_steps": 80}
    log.record(rec)
    (tmp_path / "metrics.jsonl").unlink()
    with pytest.raises(RunFolderError, match="removed, replaced or changed"):
        log.record({**rec, "episode": 2})
    assert not (tmp_path / "metrics.jsonl").exists()  # no history restarting at episode 2
    log.close()


def test_tensorboard_removed_mid_run_is_one_line_and_resumes(trace_cache, tmp_path):
    run_dir = tmp_path / "run"
    args = ["experiment=smoke", f"traces.cache_dir={trace_cache}", "train.threads=1",
            "train.trajectory_images=false", "train.eval_every=2"]
    p = uabs_train(tmp_path, *args, "train.episodes=400", f"hydra.run.dir={run_dir}")
    wait_for(run_dir / "checkpoints" / "last.pt", p)
    shutil.rmtree(run_dir / "tb")
    err = one_error(p)
    assert "was removed while the run wrote it" in err and "resume=" in err
    p = uabs_train(tmp_path, *args, "train.episodes=4", f"resume={run_dir}")
    _, err = p.communicate(timeout=300)
    assert p.returncode == 0, err[-2000:]
    assert list((run_dir / "tb").glob("events.out.tfevents.*"))


@pytest.mark.parametrize("sig, code", [(signal.SIGHUP, 129), (signal.SIGTERM, 143)])
def test_a_signal_saves_and_a_second_stops_at_once_saying_what_was_kept(trace_cache,
                                                                       tmp_path, sig, code):
    run_dir = tmp_path / "run"
    args = ["experiment=smoke", f"traces.cache_dir={trace_cache}", *QUIET,
            "train.episodes=400", "train.eval_every=2", f"hydra.run.dir={run_dir}"]
    p = uabs_train(tmp_path, *args)
    wait_for(run_dir / "checkpoints" / "last.pt", p)
    p.send_signal(sig)
    _, err = p.communicate(timeout=300)
    assert p.returncode == code, err[-2000:]
    assert "Traceback" not in err
    assert (run_dir / "checkpoints" / "last.pt").is_file()
    if sig != signal.SIGTERM:
        return
    # two in a row: at once, with the signal's own status and a true account
    lines = len((run_dir / "metrics.jsonl").read_text().splitlines())
    p = uabs_train(tmp_path, *args, f"resume={run_dir}")
    wait_until(lambda: len((run_dir / "metrics.jsonl").read_text().splitlines()) > lines, p)
    # two of one kind sent together may arrive as one: a SIGTERM and a SIGHUP do not
    p.send_signal(signal.SIGTERM)
    p.send_signal(signal.SIGHUP)
    _, err = p.communicate(timeout=300)
    assert p.returncode in (129, 143), err[-2000:]  # the status of the second handled
    assert "Traceback" not in err
    assert "stopped at once: the last checkpoint is kept" in err


def test_a_second_sigterm_before_any_checkpoint_says_there_is_none(trace_cache, tmp_path):
    from uabs_rl.training.experiment import DeferredInterrupt, StoppedNow

    with DeferredInterrupt(lambda: "no checkpoint had been written yet") as interrupt:
        os.kill(os.getpid(), signal.SIGTERM)
        assert interrupt.requested == signal.SIGTERM
        with pytest.raises(StoppedNow, match="no checkpoint had been written yet") as e:
            os.kill(os.getpid(), signal.SIGTERM)
    assert e.value.exit_code == 143


def test_a_nohup_run_is_not_stopped_by_a_hang_up():
    from uabs_rl.training.experiment import DeferredInterrupt

    before = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with DeferredInterrupt() as interrupt:
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGHUP)
            assert interrupt.requested is None
    finally:
        signal.signal(signal.SIGHUP, before)


@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a pseudo-terminal")
def test_a_run_whose_terminal_hangs_up_saves_and_exits_129(trace_cache, tmp_path):
    """A closed terminal window: the kernel sends SIGHUP, and the terminal is no longer
    one to ``isatty``. Before, the run saved and then died writing its last line to it
    (exit 1); now its output goes to /dev/null and it exits 129."""
    import fcntl
    import select
    import sys
    import termios

    import torch

    run = tmp_path / "run"
    master, slave = os.openpty()
    p = subprocess.Popen(
        [sys.executable, "-m", "uabs_rl.cli.train", "experiment=smoke", *QUIET,
         f"traces.cache_dir={trace_cache}", "train.episodes=100000",
         f"hydra.run.dir={run}"], stdin=slave, stdout=slave, stderr=slave,
        start_new_session=True, preexec_fn=lambda: fcntl.ioctl(0, termios.TIOCSCTTY, 0))
    os.close(slave)
    metrics, deadline = run / "metrics.jsonl", time.monotonic() + 300
    while not (metrics.is_file() and metrics.read_text().count('"train"') >= 3):
        assert p.poll() is None and time.monotonic() < deadline
        if select.select([master], [], [], 0.2)[0]:  # the terminal shows what it writes
            try:
                os.read(master, 65536)
            except OSError:
                break
    os.close(master)  # the window closes
    assert p.wait(timeout=120) == 129
    episodes = [r["episode"] for r in records(run) if r["kind"] == "train"]
    last = torch.load(run / "checkpoints" / "last.pt", weights_only=False)
    assert last["counters"]["episode"] == len(episodes) >= 3


@pytest.mark.parametrize("override", ["hydra.run.dir", "resume"])
def test_a_folder_name_too_long_for_the_file_system_is_one_line(tmp_path, override):
    err = one_error(uabs_train_here(tmp_path, "experiment=smoke",
                                    f"{override}={tmp_path / ('x' * 300)}"), timeout=120)
    assert "300 bytes long" in err


def test_a_run_folder_named_after_too_many_overrides_is_one_line(tmp_path):
    err = one_error(uabs_train_here(tmp_path, "experiment=smoke", "algo.lr=0.0001" + "0" * 300),
                    timeout=120)
    assert "name it with hydra.run.dir=" in err
    assert not (tmp_path / "outputs").exists()


def test_a_run_started_in_a_folder_that_moved_writes_its_own_record(trace_cache, tmp_path):
    """Two identical commands in the same second: the second writes beside the first,
    and the first run's record stays its own."""
    args = ["experiment=smoke", f"traces.cache_dir={trace_cache}", *QUIET,
            "train.episodes=2", "train.eval_every=2",
            "hydra.run.dir=outputs/${now:%Y-%m-%d}_same"]
    first = uabs_train_here(tmp_path, *args, "seed=1")
    assert first.returncode == 0, first.stderr[-2000:]
    runs = list((tmp_path / "outputs").iterdir())
    record = tree(runs[0] / ".hydra")
    second = uabs_train_here(tmp_path, *args, "seed=2")
    assert second.returncode == 0, second.stderr[-2000:]
    assert tree(runs[0] / ".hydra") == record
    moved = [d for d in (tmp_path / "outputs").iterdir() if d != runs[0]]
    assert len(moved) == 1 and moved[0].name.endswith("-2")
    assert "seed: 2" in (moved[0] / ".hydra" / "config.yaml").read_text()
    assert json.loads((moved[0] / "run.json").read_text())["id"] != json.loads(
        (runs[0] / "run.json").read_text())["id"]


def test_a_name_with_a_slash_neither_nests_nor_leads_a_run_folder_out(trace_cache, tmp_path):
    cwd = tmp_path / "a" / "b"
    cwd.mkdir(parents=True)
    err = one_error(uabs_train_here(cwd, "experiment=smoke", f"traces.cache_dir={trace_cache}",
                                    "scenario.name=../../../elsewhere/ESCAPED"))
    assert "scenario.name" in err
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a", "b"]  # nothing made
    # a value that is a path (a network file) names one folder under outputs/runs
    net = Path(__file__).parents[1] / "sumo" / "manhattan" / "manhattan.net.xml"
    p = uabs_train_here(cwd, "experiment=smoke", f"traces.cache_dir={trace_cache}", *QUIET,
                        "train.episodes=2", "train.eval_every=2",
                        f"scenario.sumo.net_file={net}")
    assert p.returncode == 0, p.stderr[-2000:]
    (run,) = (cwd / "outputs" / "runs").iterdir()
    assert "%2F" in run.name and (run / "metrics.jsonl").is_file()


def test_a_full_disk_under_tensorboard_is_one_line_without_a_thread_trace(
        trace_cache, tmp_path, monkeypatch, capfd):
    import errno

    from tensorboard.compat.tensorflow_stub.io import gfile

    def full(self, filename, file_content, binary_mode=False):
        raise OSError(errno.ENOSPC, "No space left on device", filename)

    monkeypatch.setattr(gfile.LocalFileSystem, "append", full)
    cfg = smoke(trace_cache, "train.threads=1", "train.trajectory_images=false",
                "train.episodes=4", "train.eval_every=2")
    with pytest.raises(RunFolderError, match="no space left on the device"):
        run(cfg, tmp_path / "run")
    err = capfd.readouterr().err
    assert "Traceback" not in err and "Exception in thread" not in err


@pytest.mark.parametrize("value, says", [("", "names no folder"),
                                         ("notes.txt", "is a file")])
def test_resume_of_nothing_or_of_a_file_is_one_line(tmp_path, value, says):
    """An empty shell variable (``resume=$RUN``) once started a new run silently; a
    file once ended in Hydra's traceback."""
    (tmp_path / "notes.txt").write_text("mine\n")
    err = one_error(uabs_train_here(tmp_path, "experiment=smoke", f"resume={value}"), timeout=120)
    assert says in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_resume_takes_a_setting_that_changes_no_result(finished_run, tmp_path):
    """traces.workers (how many SUMO processes build traces) groups runs alike in a
    sweep; a resume that types it is no change of results either."""
    run_dir, args = finished_run
    run_dir = copy_of(run_dir, tmp_path)
    p = uabs_train_here(tmp_path, *args, "train.episodes=4", "traces.workers=4",
                        f"resume={run_dir}")
    assert p.returncode == 0, p.stderr[-2000:]


def test_a_members_checkpoint_is_checked_against_its_population(trace_cache, tmp_path,
                                                               capsys):
    """A population's members have no run.json of their own: a checkpoint copied into a
    member folder from another run is refused by uabs-report (and uabs-eval) all the
    same, against the population's identity."""
    from uabs_rl.cli.report import main as report_main

    pop, other = tmp_path / "pop", tmp_path / "other"
    run(smoke(trace_cache, *QUIET, "train.episodes=2", "train.eval_every=2",
              "train.population=2"), pop)
    run(smoke(trace_cache, *QUIET, "train.episodes=2", "train.eval_every=2"), other)
    assert report_main([str(pop), "--no-baselines", "--out", str(tmp_path / "r1")]) == 0
    shutil.copyfile(other / "checkpoints" / "last.pt", pop / "seed=1" / "checkpoints" / "last.pt")
    capsys.readouterr()
    assert report_main([str(pop), "--no-baselines", "--out", str(tmp_path / "r2")]) == 2
    assert "belongs to another run" in capsys.readouterr().err


def test_hydra_settings_the_project_owns_are_refused(finished_run, tmp_path):
    """hydra.output_subdir=.hydra would let Hydra rewrite a finished run's record before
    the refusal; hydra.job.name=../x would put the log outside the run folder."""
    run_dir, args = finished_run
    run_dir = copy_of(run_dir, tmp_path)
    before = tree(run_dir)
    err = one_error(uabs_train_here(tmp_path, *args, "train.episodes=4", "algo.lr=0.5",
                                    "hydra.output_subdir=.hydra", f"hydra.run.dir={run_dir}"))
    assert "hydra.output_subdir is set by uabs_rl itself" in err
    assert tree(run_dir) == before
    from uabs_rl.cli.hydra import check_command_line
    from uabs_rl.config import ConfigError

    for words, says in [(["hydra.job.name=../../ESC"], "hydra.job.name is set"),
                        (["hydra/job_logging=none"], "is set by uabs_rl"),
                        (["scenario=../algo/dqn3"], "scenario='../algo/dqn3' cannot name"),
                        (["-m", "scenario=city,../x"], "scenario='../x' cannot name"),
                        (["seed=["], "does not parse"),
                        (["train={episodes:2}", "train.episodes=1"], "given twice"),
                        (["scenario.area={width:360}", "scenario.area.width=400"],
                         "given twice")]:
        with pytest.raises(ConfigError, match=re.escape(says)):
            check_command_line(words)
    check_command_line(["scenario=city", "scenario.n_uabs=5", "masking=flat",
                        "masking.flat_margin=10"])  # a group, then its settings


def test_folders_a_run_must_not_take_are_refused_before_hydra(finished_run, tmp_path):
    from uabs_rl.cli.train import _check_paths
    from uabs_rl.config import ConfigError

    run_dir, _ = finished_run
    for argv, says in [(["hydra.run.dir="], "names no folder"),
                       (["-m", "hydra.sweep.dir="], "names no folder"),
                       ([f"hydra.run.dir={run_dir / 'eval'}"], "holds a run"),
                       ([f"resume={run_dir}", f"hydra.run.dir={tmp_path}"], "drop hydra.run.dir")]:
        with pytest.raises(ConfigError, match=says):
            _check_paths(argv)
    _check_paths([f"resume={run_dir}", f"hydra.run.dir={run_dir}"])  # the same: its own
    refused = tmp_path / "sweep"  # a sweep refused before its first job left this only
    refused.mkdir()
    (refused / "multirun.yaml").write_text("a refused sweep\n")
    _check_paths(["-m", f"hydra.sweep.dir={refused}"])


def test_resume_refuses_a_run_whose_checkpoints_and_metrics_were_removed(finished_run,
                                                                         tmp_path):
    run_dir, args = finished_run
    run_dir = copy_of(run_dir, tmp_path)
    shutil.rmtree(run_dir / "checkpoints")
    (run_dir / "metrics.jsonl").unlink()
    before = tree(run_dir)
    err = one_error(uabs_train_here(tmp_path, *args, "train.episodes=4", f"resume={run_dir}"))
    assert "evaluation pictures in eval/" in err
    assert tree(run_dir) == before


def test_checkpoints_removed_while_the_run_writes_them_stop_the_run(trace_cache, tmp_path,
                                                                    monkeypatch):
    from uabs_rl.training.experiment import Experiment

    evaluate, calls = Experiment.evaluate, []

    def evaluate_then_remove(self):
        out = evaluate(self)
        calls.append(1)
        if len(calls) == 1:
            shutil.rmtree(self.run_dir / "checkpoints")
        return out

    monkeypatch.setattr(Experiment, "evaluate", evaluate_then_remove)
    with pytest.raises(RunFolderError, match="best.pt was removed while the run wrote it"):
        run(smoke(trace_cache, *QUIET, "train.episodes=6", "train.eval_every=2"),
            tmp_path / "run")
    assert not (tmp_path / "run" / "checkpoints").exists()  # not half made again


def test_a_path_the_file_system_refuses_is_one_line_and_leaves_nothing(trace_cache, tmp_path):
    run_dir = tmp_path / "run"
    net = tmp_path / ("y" * 300) / "x.net.xml"
    err = one_error(uabs_train_here(tmp_path, "experiment=smoke", f"traces.cache_dir={trace_cache}",
                                    f"hydra.run.dir={run_dir}", f"scenario.sumo.net_file={net}"))
    assert "File name too long" in err
    assert not run_dir.exists()


def test_one_window_gives_no_interval_and_names_are_bounded_in_bytes():
    from uabs_rl.config import ConfigError
    from uabs_rl.evaluation.stats import paired_difference
    from uabs_rl.paths import safe_component

    d = paired_difference([3.0], [1.0])
    assert d["diff"] == 2.0 and np.isnan(d["ci_low"]) and np.isnan(d["ci_high"])
    assert d["method"] == "no interval: 1 window"
    with pytest.raises(ConfigError, match="280 bytes long"):
        safe_component("\U0001F600" * 70, "scenario.name")
