"""One training run (docs/model.md §7, §8): wires the env, the Q-network, the learner, the replay
buffer, collection, evaluation, checkpoints and the run log, and runs the fit loop."""

from __future__ import annotations

import errno
import logging
import math
import shutil
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from uabs_rl.algorithms import Dims, make_algorithm
from uabs_rl.algorithms.replay import TransitionReplay
from uabs_rl.checkpoint import (
    CKPT_FORMAT,
    Interrupted,
    check_compatible,
    config_dict,
    save_checkpoint,
)
from uabs_rl.config import RunConfig, TrainConfig, validate_run
from uabs_rl.env import N_ACTIONS
from uabs_rl.evaluation import Evaluator, greedy_policy, make_eval_env
from uabs_rl.make import make_env, make_selector, resolve_device
from uabs_rl.rollout import Collector, UpdateSchedule, episode_records, epsilon
from uabs_rl.runfolder import RunFolderError
from uabs_rl.runlog import RunLog, check_logger
from uabs_rl.threads import setup_threads
from uabs_rl.traces import TraceSet

log = logging.getLogger(__name__)


class Stopped(Interrupted):
    """Training stopped on a signal after saving ``last``; the process exits with
    ``exit_code`` (130 for Ctrl-C, 143 for SIGTERM, as a shell reports them)."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.exit_code = 128 + signum


class DeferredInterrupt:
    """While active, Ctrl-C (SIGINT) and SIGTERM (a scheduler's preemption) only set
    :attr:`requested`: the loop saves at the end of the round and stops with one line
    (:meth:`stop`); a second one raises KeyboardInterrupt at once. A handler installed
    before for SIGTERM or SIGUSR2 (the submitit launcher's, which requeues a preempted
    SLURM job) runs after the save. Outside the main thread it does nothing."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGUSR2)

    def __init__(self):
        self.requested: int | None = None  # the signal received
        self._previous: dict[int, Any] = {}

    def _handle(self, signum, frame) -> None:
        if self.requested is not None:
            raise KeyboardInterrupt
        self.requested = signum
        name = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        print(f"\n{name}: stopping after this round (again to stop now, keeping the last "
              f"checkpoint)", file=sys.stderr)

    def __enter__(self) -> DeferredInterrupt:
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                before = signal.getsignal(sig)
                if sig == signal.SIGUSR2 and not callable(before):
                    continue  # only chained where someone (submitit) listens
                self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, before in self._previous.items():
            signal.signal(sig, before)
        self._previous = {}

    def stop(self, message: str) -> None:
        """After the save: run a chained handler of the signal (submitit's requeue),
        then raise :class:`Stopped` with ``message``."""
        signum = self.requested
        before = self._previous.get(signum)
        self.__exit__()
        if callable(before) and before is not signal.default_int_handler:
            before(signum, None)
        raise Stopped(message, signum)


class Progress:
    """The progress bar of a run: episodes, last return, ε, collisions, last eval R."""

    def __init__(self, train: TrainConfig, episode: int):
        # a thread lock: tqdm's default creates a multiprocessing semaphore, which a run
        # killed with kill -9 leaves to Python's resource tracker to warn about
        tqdm.set_lock(threading.RLock())
        self.bar = tqdm(total=train.episodes, initial=episode, unit="ep",
                        disable=not train.progress, dynamic_ncols=True)
        self.collisions, self.last_eval = 0.0, float("nan")

    def update(self, rec: dict[str, Any]) -> None:
        self.collisions += rec["collisions"]
        self.bar.update()
        shown = {"R": f"{rec['return']:.0f}", "eps": f"{rec['epsilon']:.2f}",
                 "coll": int(self.collisions)}
        if not math.isnan(self.last_eval):  # none yet in this session (a resume)
            shown["eval_R"] = f"{self.last_eval:.0f}"
        self.bar.set_postfix(shown)

    def close(self) -> None:
        self.bar.close()


NO_REPLAY = ("the checkpoint holds no replay buffer (train.checkpoint_buffer=false): "
             "learning restarts after algo.learning_starts transitions")


def run_state(exp, cfg: RunConfig, learner: dict, best_eval: float,
              selector_gen: torch.Generator, env_gen: torch.Generator,
              buffer: TransitionReplay, member: int = 0) -> dict:
    """The checkpoint of a run (or of one member of a population, ``exp`` being the
    population): its config, the run's identity (``uabs_rl.runfolder``; None outside
    ``uabs_rl.train.prepare``), learner state, ``exp``'s counters, the global RNG,
    the selector's and env's generators and, with ``train.checkpoint_buffer``, the
    replay buffer (member ``member``'s)."""
    return {
        "format": CKPT_FORMAT, "config": config_dict(cfg), "run": exp.identity,
        "learner": learner,
        "counters": {"episode": exp.episode, "env_steps": exp.collector.env_steps,
                     "update_credit": exp.updates.credit, "best_eval": best_eval,
                     "total_steps": exp.total_steps},
        "rng": {"torch": torch.get_rng_state(), "selector": selector_gen.get_state(),
                "env": env_gen.get_state()},
        "replay": buffer.member_state_dict(member) if cfg.train.checkpoint_buffer else None,
    }


def restore_counters(exp, state: dict) -> None:
    """``exp``'s episode, env-step and update counters and the global RNG from a
    checkpoint written by :func:`run_state`."""
    c = state["counters"]
    exp.episode, exp.collector.env_steps = int(c["episode"]), int(c["env_steps"])
    exp.updates.credit = float(c["update_credit"])
    # the ε schedule as the run planned it, whatever train.episodes says now
    planned = int(c.get("total_steps", exp.total_steps))
    if planned != exp.total_steps:
        log.info("train.episodes changed on resume: the ε schedule keeps the run's "
                 "original length (%d env steps)", planned)
    exp.total_steps = planned
    torch.set_rng_state(state["rng"]["torch"])


def restore_streams(state: dict, selector_gen: torch.Generator, env_gen: torch.Generator,
                    buffer: TransitionReplay, member: int = 0) -> bool:
    """The generators and the replay buffer (member ``member``'s) of a checkpoint written
    by :func:`run_state`; False when it holds no buffer (``train.checkpoint_buffer=false``)."""
    selector_gen.set_state(state["rng"]["selector"])
    env_gen.set_state(state["rng"]["env"])
    if state.get("replay") is None:
        return False
    buffer.load_member(member, state["replay"])
    return True


def run_rounds(exp, logs: list[RunLog], save_last) -> float:
    """``exp.rounds()`` with its logs open, a progress bar and Ctrl-C / SIGTERM deferred
    to the end of a round (see :meth:`Experiment.fit`), then ``save_last()``; returns the
    minutes the rounds took. The run folder's lock (``exp.run_lock``) is released when
    it ends, however it ends, and only after the last save."""
    try:
        for lg in logs:
            lg.open(resume_episode=exp.episode if exp.episode else None)
        exp.progress = Progress(exp.cfg.train, exp.episode)
        t0 = time.perf_counter()
        try:
            with exp.interrupt:
                exp.rounds()
        finally:
            exp.progress.close()
            for lg in logs:
                lg.close()
        minutes = (time.perf_counter() - t0) / 60
        save_last()
    except OSError as e:
        raise write_error(e, exp.run_dir) from None
    finally:
        if exp.run_lock is not None:
            exp.run_lock.release()
    return minutes


def write_error(e: OSError | RuntimeError, run_dir: Path) -> Exception:
    """A failed write of a run's files as one line saying why and what to do; ``e``
    itself when it is not about the run folder."""
    if not run_dir.is_dir():
        return RunFolderError(f"the run folder {run_dir} was removed or moved while the "
                              f"run was writing it: the run stopped; nothing more was "
                              f"written.")
    where = getattr(e, "filename", None) or run_dir
    if getattr(e, "errno", None) == errno.ENOSPC or "unexpected pos" in str(e):
        free = shutil.disk_usage(run_dir).free / 2**20
        return RunFolderError(f"no space left on the device while writing {where} "
                              f"({free:.0f} MiB free): free some space, then continue with "
                              f"resume={run_dir} (the last complete checkpoint is kept).")
    if getattr(e, "errno", None) in (errno.EACCES, errno.EROFS, errno.EPERM):
        return RunFolderError(f"cannot write {where} ({e.strerror}): make the run folder "
                              f"writable, then continue with resume={run_dir}.")
    return e


class Experiment:
    """Collect / optimise / evaluate / checkpoint / log, each in its own object."""

    def __init__(self, cfg: RunConfig, run_dir: Path,
                 traces: dict[str, TraceSet] | None = None):
        """``traces`` may hold ready TraceSets per split ("train", "eval"); by default
        they come from the trace cache (built with SUMO if missing)."""
        validate_run(cfg)
        check_logger(cfg.train.logger)
        self.cfg, self.run_dir = cfg, Path(run_dir)
        dev = self.device = resolve_device(cfg.device)
        tr = cfg.train
        self.threads = setup_threads(cfg)
        torch.manual_seed(cfg.seed)
        traces = traces or {}
        env = make_env(cfg.scenario, cfg.channel, cfg.masking, traces.get("train", cfg.traces),
                       "train", n_envs=tr.n_envs, device=dev, seed=cfg.seed,
                       compile=tr.compile, spec_mask=False)
        eval_env = make_eval_env(cfg, traces.get("eval"), dev)
        self.params = p = env.base_env.params
        self.learner = make_algorithm(cfg.algo, Dims(p.obs_dim, N_ACTIONS, p.n_uabs),
                                      [cfg.seed], dev)
        self.qnet, self.buffer = self.learner.policy, self.learner.buffer
        self.gen = torch.Generator(device=dev)
        self.gen.manual_seed(cfg.seed)
        selector = make_selector(env, cfg.masking, cfg.algo.eps_start, self.gen,
                                 compile=tr.compile)
        self.collector = Collector(env, self.qnet, selector, self.buffer,
                                   n_step=cfg.algo.n_step, gamma=cfg.algo.gamma)
        self.updates = UpdateSchedule(self.learner, cfg.algo)
        self.evaluator = Evaluator(eval_env, tr.eval_seed)
        self.greedy = greedy_policy(self.qnet, eval_env, cfg, compile=tr.compile)
        self.log = RunLog(cfg, self.run_dir)
        self.interrupt = DeferredInterrupt()
        self.total_steps = tr.episodes * p.episode_steps  # per-env steps of the protocol
        self.episode, self.best_eval = 0, -math.inf
        self.identity: dict | None = None  # the run folder's (set by train.prepare)
        self.run_lock = None  # the run folder's lock, released when fit ends

    # ------------------------------------------------------------------ steps
    def collect(self) -> list[dict[str, Any]]:
        """One round of ``n_envs`` training episodes with their updates; one record each."""
        last, served, eps, loss, q = self.collector.round(
            lambda s: epsilon(self.cfg.algo, s, self.total_steps), self.updates)
        records = episode_records(
            last, served, self.params.episode_steps, self.episode + 1,
            self.collector.env_steps,
            {"epsilon": eps, "loss": loss.item(), "q_chosen": q.item(),
             "updates": self.learner.updates})
        self.episode += len(records)
        return records

    def evaluate(self) -> float:
        """Evaluate the greedy policy, log it with its figures, checkpoint ``best`` (by
        evaluation return) and ``last``. Returns the evaluation return."""
        record, td = self.evaluator.evaluate(self.greedy, self.episode,
                                             self.collector.env_steps)
        self.log.record(record)
        is_best = record["return"] >= self.best_eval
        self.log.eval_figures(record, td, self.evaluator, is_best)
        if is_best:
            self.best_eval = record["return"]
            self.save("best")
        self.save("last")
        return record["return"]

    # ------------------------------------------------------------------ checkpoint
    def state_dict(self) -> dict:
        return run_state(self, self.cfg, self.learner.state_dict(), self.best_eval, self.gen,
                         self.collector.env.base_env.rng, self.buffer)

    def load_state_dict(self, state: dict, source: Path) -> None:
        """Continue from a checkpoint written under compatible settings."""
        check_compatible(state, self.cfg, source)
        self.learner.load_state_dict(state["learner"])
        self.best_eval = float(state["counters"]["best_eval"])
        restore_counters(self, state)
        if not restore_streams(state, self.gen, self.collector.env.base_env.rng, self.buffer):
            log.warning(NO_REPLAY)

    def save(self, name: str) -> Path:
        path = self.run_dir / "checkpoints" / f"{name}.pt"
        try:
            save_checkpoint(self.state_dict(), path)
        except (OSError, RuntimeError) as e:
            raise write_error(e, self.run_dir) from None
        return path

    def rounds(self) -> None:
        """Collect and evaluate until ``train.episodes``, stopping early (after a whole
        round, so the saved state is consistent) when Ctrl-C was pressed."""
        tr = self.cfg.train
        while self.episode < tr.episodes:
            for rec in self.collect():
                self.log.record(rec)
                self.progress.update(rec)
            self.threads.check()
            if self.episode % tr.eval_every == 0 or self.episode >= tr.episodes:
                self.progress.last_eval = self.evaluate()
            if self.interrupt.requested:
                path = self.save("last")
                self.interrupt.stop(f"interrupted at episode {self.episode}: saved {path}; "
                                    f"continue with resume={self.run_dir}")

    # ------------------------------------------------------------------ loop
    def fit(self) -> dict[str, Any]:
        """Train to ``train.episodes``, evaluating every ``train.eval_every`` episodes.
        Ctrl-C or SIGTERM finishes the current round, saves ``last`` and raises
        :class:`Stopped` (a second one stops at once, keeping the last checkpoint)."""
        minutes = run_rounds(self, [self.log], lambda: self.save("last"))
        summary = {"episodes": self.episode, "updates": self.learner.updates,
                   "best_eval_return": self.best_eval, "last_eval_return": self.progress.last_eval,
                   "minutes": minutes}
        log.info("done: %d episodes, %d updates, best validation return %.0f, %.1f min",
                 self.episode, self.learner.updates, self.best_eval, summary["minutes"])
        return summary
