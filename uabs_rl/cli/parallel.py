"""Ctrl-C in a sweep of parallel jobs (``hydra/launcher=local_parallel``): every running
job saves after its round, none starts after it, and the sweep ends with one line.

Without this, joblib answered the first Ctrl-C in the launching process by killing its
worker processes at once (SIGKILL), so a job saved only if its own copy of the signal
ran its save first: a job that had logged 309 episodes kept the checkpoint of episode
306. Now:

- the workers leave the terminal's process group as they start and ignore the signals
  between jobs (:func:`worker_start`, loky's initializer): a terminal's Ctrl-C reaches
  the launching process alone, and a signal can no longer end an idle worker (joblib
  would then kill every other one);
- the launching process answers the first signal (SIGINT, SIGTERM, SIGHUP) by writing
  the sweep's stop file; each running job sees it at the end of its round (training's
  :class:`~uabs_rl.training.experiment.DeferredInterrupt` looks, through
  :data:`~uabs_rl.runs.layout.STOP_ENV`), saves and returns; a job that starts
  after it returns at once. When all have returned the launcher raises
  :class:`SweepStopped` (one line, exit 128 + the signal). A second signal stops at once
  (joblib ends the workers; each job keeps its last checkpoint);
- a signal sent to one worker alone (``kill <pid>``, or to every process, as a
  scheduler's ``scancel`` does) stops its job as in a single run; the job writes the
  stop file, so the other jobs stop too, and the sweep ends in the same way. Each
  process acts on one signal once: the launcher hands none on.

The sweep continues when its command is re-typed with ``resume=<sweep folder>``
appended. A worker being spawned (the first seconds of a sweep, before loky's
initializer runs) is still in the terminal's group: a Ctrl-C then ends it (its own error
lines may show), before any job ran on it, and the sweep ends with the same line. A job
checks the stop file as its training starts and at the end of each round, not while it
builds traces. When the launching process ends, even by ``kill -9``, its running jobs
save after their round and end (Linux: :func:`worker_start`)."""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from uabs_rl.paths import detach_terminal
from uabs_rl.runs.layout import STOP_ENV, STOP_FILE, stop_signal

# hydra_plugins.uabs_rl_launcher's class (conf/hydra/launcher/local_parallel.yaml)
LAUNCHER = "hydra_plugins.uabs_rl_launcher.StoppableJoblibLauncher"
SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class SweepStopped(KeyboardInterrupt):
    """A parallel sweep stopped on a signal; ``exit_code`` is 128 + the signal's
    number."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.exit_code = 128 + signum


class JobSignal(KeyboardInterrupt):
    """A signal that reached a job of a parallel sweep outside its training (as it sets
    up, or after it trained): ``signum`` is the signal's number."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _raise_job_signal(signum, frame) -> None:
    raise JobSignal(signum)


_raise_job_signal.chained = False  # training's handling, which takes over, calls it not


_orphaned = False  # in a worker: the launching process has ended


def _parent_gone(signum, frame) -> None:
    """The launching process ended (PR_SET_PDEATHSIG; the kernel may send it once per
    thread of that process): a running job is told through the stop file, which its
    training reads at the end of its round, and ends the worker when it returns
    (:func:`exit_if_orphaned`); an idle worker ends now. Left to loky, orphaned workers
    wait on each other's ends of its pipes for ever."""
    global _orphaned
    _orphaned = True
    stop = os.environ.get(STOP_ENV)
    if stop:
        stop_sweep(Path(stop), signal.SIGTERM)
    else:
        os._exit(0)


def exit_if_orphaned() -> None:
    """In a worker, after its job returned: when the launching process has ended there is
    no one to return the job's result to, so the worker ends here (its output flushed)."""
    if not _orphaned:
        return
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):
            pass
    os._exit(128 + signal.SIGTERM)


def worker_start() -> None:
    """loky's initializer of each worker: out of the terminal's process group, the
    signals ignored until a job runs (:func:`job_signals`), and on Linux told when the
    launching process ends, even by ``kill -9`` (PR_SET_PDEATHSIG, SIGUSR1): a running
    job then saves after its round and lets its folder go, where it would otherwise
    train to its end, holding the folder's lock against the resume (an idle worker
    ends by itself: loky's queue closes)."""
    if hasattr(os, "setpgid"):
        try:
            os.setpgid(0, 0)
        except OSError:
            pass
    job_signals(running=False)
    if sys.platform.startswith("linux"):
        import ctypes

        signal.signal(signal.SIGUSR1, _parent_gone)
        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGUSR1), 0, 0, 0)
        except (OSError, AttributeError):
            pass


def job_signals(running: bool) -> None:
    """In a worker: while a job runs (``running``), each signal raises :class:`JobSignal`
    (training's own handling takes over while it trains); between jobs they are
    ignored."""
    for sig in SIGNALS:
        signal.signal(sig, _raise_job_signal if running else signal.SIG_IGN)


def stop_sweep(stop: Path, signum: int) -> None:
    """Write the stop file of a sweep (the signal's number in it), if not there yet."""
    try:
        with open(stop, "x") as f:
            f.write(str(signum))
    except FileExistsError:
        pass


def launch_stoppable(launch: Callable[[], Sequence[Any]], sweep_dir: Path) -> Sequence[Any]:
    """``launch()`` (the joblib launcher's) stopped by the stop file on a signal (the
    module docstring); its returns, unless a job or this process was stopped."""
    stop = Path(sweep_dir) / STOP_FILE
    stop.unlink(missing_ok=True)  # left by a sweep killed while it stopped
    held: list[int] = []

    def handle(signum, frame) -> None:
        if held:  # joblib ends its workers; each keeps its last checkpoint
            raise SweepStopped("stopped at once: each job keeps its last checkpoint; "
                               f"continue the {_what(sweep_dir)} by re-typing its command "
                               f"(with -m) and resume={sweep_dir} appended", signum)
        held.append(signum)
        if signum == signal.SIGHUP:  # the terminal is gone: later lines go nowhere
            detach_terminal()
        stop.parent.mkdir(parents=True, exist_ok=True)
        stop_sweep(stop, signum)
        name = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        try:
            print(f"\n{name}: the {_what(sweep_dir)} stops: each running job saves after "
                  f"its round, no other starts; again to stop now", file=sys.stderr)
        except OSError:
            pass

    previous = {}
    for sig in SIGNALS:
        if sig == signal.SIGHUP and signal.getsignal(sig) is signal.SIG_IGN:
            continue  # started with nohup: a hang-up stops nothing
        previous[sig] = signal.signal(sig, handle)
    try:
        try:
            returns = launch()
        except Exception as e:  # joblib's TerminatedWorkerError, ...
            if not (held and _ended_by_signals(e)):
                raise
            # a terminal's signal ended workers still being spawned (in its process
            # group until loky's initializer runs): no job had run on them
            returns = []
        stopped = stop_signal(stop)  # this process's, or a job's own
    finally:
        for sig, before in previous.items():
            signal.signal(sig, before)
        stop.unlink(missing_ok=True)
    if held or stopped is not None:
        raise SweepStopped(f"interrupted: every job that was running saved its last "
                           f"checkpoint and none started after the stop; continue the "
                           f"{_what(sweep_dir)} by re-typing its command (with -m) and "
                           f"resume={sweep_dir} appended",
                           held[0] if held else stopped)
    return returns


def _ended_by_signals(e: Exception) -> bool:
    """joblib's error of workers that the signals of :data:`SIGNALS` ended, and none
    else (an out-of-memory kill is SIGKILL: not this)."""
    import re

    codes = re.findall(r"\b(SIG[A-Z]+)\(-\d+\)", str(e))
    return bool(codes) and all(c in {s.name for s in SIGNALS} for c in codes)


def _what(sweep_dir: Path) -> str:
    from uabs_rl.tuning.sweeper import STUDY_FILE

    return "study" if (Path(sweep_dir) / STUDY_FILE).is_file() else "sweep"


def job_stop_file(hydra_cfg: Any) -> Path | None:
    """The sweep's stop file in a job of a sweep run by :data:`LAUNCHER` (a worker
    process); None in any other job, and in a single run."""
    from hydra.types import RunMode

    launcher = hydra_cfg.launcher
    if (hydra_cfg.mode != RunMode.MULTIRUN or launcher is None
            or launcher.get("_target_") != LAUNCHER):
        return None
    return Path(hydra_cfg.runtime.cwd, str(hydra_cfg.sweep.dir)) / STOP_FILE
