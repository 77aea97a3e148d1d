"""Ctrl-C in a sweep of parallel jobs (``hydra/launcher=local_parallel``): every running
job saves after its round, none starts after it, and the sweep ends with one line.

Without this, joblib answered the first Ctrl-C in the launching process by killing its
worker processes at once (SIGKILL), so a job saved only if its own copy of the signal
ran its save first: a job that had logged 309 episodes kept the checkpoint of episode
306. Now the jobs leave the terminal's process group (a Ctrl-C reaches the launching
process alone), which hands each signal on to its workers once: each running job saves
at the end of its round and returns, jobs not yet started return at once (the sweep's
stop file says so), and the launcher raises :class:`SweepStopped` when all have
returned. A second signal stops at once, as in a single run (each job keeps its last
checkpoint). The sweep continues when its command is re-typed with ``resume=<sweep
folder>`` appended."""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from uabs_rl.paths import detach_terminal

STOP_FILE = ".stopping"  # in the sweep folder while a stopped sweep's jobs return
# hydra_plugins.uabs_rl_launcher's class (conf/hydra/launcher/local_parallel.yaml)
LAUNCHER = "hydra_plugins.uabs_rl_launcher.StoppableJoblibLauncher"
SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class SweepStopped(KeyboardInterrupt):
    """A parallel sweep stopped on a signal after its running jobs saved; ``exit_code``
    is 128 + the signal's number."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.exit_code = 128 + signum


def workers() -> list[int]:
    """The process ids of this process's children but loky's resource tracker (which
    ignores SIGINT and SIGTERM and would end on SIGHUP, leaving tracebacks); Linux's
    /proc, elsewhere none (and only a terminal's own Ctrl-C reaches the workers)."""
    pids: list[int] = []
    try:
        for task in os.listdir("/proc/self/task"):
            with open(f"/proc/self/task/{task}/children") as f:
                pids += [int(p) for p in f.read().split()]
    except OSError:
        return []
    out = []
    for pid in pids:
        try:
            with open(f"/proc/{pid}/cmdline", "rb") as f:
                if b"resource_tracker" in f.read():
                    continue
        except OSError:  # ended meanwhile
            continue
        out.append(pid)
    return out


def launch_stoppable(launch: Callable[[], Sequence[Any]], sweep_dir: Path) -> Sequence[Any]:
    """``launch()`` (the joblib launcher's) with the signals of :data:`SIGNALS` handed
    on to the workers: the first one writes the stop file and lets the jobs return; a
    second one stops at once (KeyboardInterrupt here, the jobs' own second signal)."""
    stop = Path(sweep_dir) / STOP_FILE
    stop.unlink(missing_ok=True)  # left by a sweep killed while it stopped
    held: list[int] = []

    def handle(signum, frame) -> None:
        for pid in workers():
            try:
                os.kill(pid, signum)
            except OSError:
                pass
        if held:
            raise KeyboardInterrupt("stopped at once: each job keeps its last checkpoint")
        held.append(signum)
        if signum == signal.SIGHUP:  # the terminal is gone: later lines go nowhere
            detach_terminal()
        stop.parent.mkdir(parents=True, exist_ok=True)
        stop.touch()
        name = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        try:
            print(f"\n{name}: the sweep stops: each running job saves after its round, "
                  f"no other starts; again to stop now", file=sys.stderr)
        except OSError:  # the terminal is gone (SIGHUP)
            pass

    previous = {}
    for sig in SIGNALS:
        if sig == signal.SIGHUP and signal.getsignal(sig) is signal.SIG_IGN:
            continue  # started with nohup: a hang-up stops nothing
        previous[sig] = signal.signal(sig, handle)
    try:
        returns = launch()
    finally:
        for sig, before in previous.items():
            signal.signal(sig, before)
        stop.unlink(missing_ok=True)
    if held:
        from uabs_rl.tuning.sweeper import STUDY_FILE

        what = "study" if (Path(sweep_dir) / STUDY_FILE).is_file() else "sweep"
        raise SweepStopped(f"interrupted: every job that was running saved its last "
                           f"checkpoint; continue the {what} by re-typing its command "
                           f"(with -m) and resume={sweep_dir} appended", held[0])
    return returns


def job_stop_file(hydra_cfg: Any) -> Path | None:
    """In a job of a sweep run by :data:`LAUNCHER` (a worker process): leave the
    terminal's process group (the launching process hands signals on, once), and
    return the sweep's stop file; None in any other job."""
    launcher = hydra_cfg.launcher
    if launcher is None or launcher.get("_target_") != LAUNCHER:
        return None
    if hasattr(os, "setpgid") and os.getpgrp() != os.getpid():
        try:
            os.setpgid(0, 0)
        except OSError:
            pass
    return Path(hydra_cfg.runtime.cwd, str(hydra_cfg.sweep.dir)) / STOP_FILE


def job_signals(running: bool) -> None:
    """In a worker of :data:`LAUNCHER`: while a job runs (``running``), each signal
    raises KeyboardInterrupt as Ctrl-C does (training's own handling takes over while it
    trains, and chains to none of these); between jobs they are ignored: one that
    reached loky's idle loop would end the worker, and joblib would then kill every
    other one before they save."""
    for sig in SIGNALS:
        signal.signal(sig, signal.default_int_handler if running else signal.SIG_IGN)
