"""Training (docs/model.md §7, §8): wires the env, the algorithm (networks, loss, replay),
collection, evaluation, checkpoints and the run logs of P >= 1 members (a single run, or
a population: :mod:`uabs_rl.training.members`), and runs the fit loop."""

from __future__ import annotations

import logging
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from uabs_rl.algorithms import Dims, make_algorithm
from uabs_rl.config import RunConfig, TrainConfig
from uabs_rl.env.uabs_env import N_ACTIONS
from uabs_rl.evaluation.evaluator import Evaluator, greedy_policy, make_eval_env
from uabs_rl.paths import detach_terminal
from uabs_rl.rng import Generators, make_generator
from uabs_rl.runs.checkpoint import Interrupted
from uabs_rl.runs.folder import write_error
from uabs_rl.runs.layout import STOP_ENV, RunFolder, stop_signal
from uabs_rl.safety.make import make_env, make_selector, resolve_device
from uabs_rl.traces.build import training_traces
from uabs_rl.traces.cache import TraceSet
from uabs_rl.training.members import Checkpoints, Member, member_dir, member_seeds
from uabs_rl.training.rollout import Collector, UpdateSchedule, episode_records, epsilon
from uabs_rl.training.runlog import check_logger
from uabs_rl.training.startup import validate_run
from uabs_rl.training.teacher import Teacher
from uabs_rl.training.threads import setup_threads

log = logging.getLogger(__name__)


class Stopped(Interrupted):
    """Training stopped on a signal after saving ``last``; the process exits with
    ``exit_code`` (130 for Ctrl-C, 143 for SIGTERM, as a shell reports them)."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.exit_code = 128 + signum


class NotFinite(Interrupted):
    """Training stopped because a loss or a network weight is not a finite number
    (a diverging run): nothing is logged or saved from that round on, the checkpoints
    saved before it are kept. One line on stderr (``error: ...``) and exit status 2."""

    exit_code = 2

    def __init__(self, message: str):
        super().__init__(f"error: {message}")


class StoppedNow(KeyboardInterrupt):
    """A second signal stopped training at once; ``str()`` says what was kept,
    ``exit_code`` is 128 + the signal's number (130 Ctrl-C, 143 SIGTERM, 129 SIGHUP)."""

    def __init__(self, message: str, signum: int):
        super().__init__(message)
        self.exit_code = 128 + signum


class DeferredInterrupt:
    """While active, Ctrl-C (SIGINT), SIGTERM (a scheduler's preemption) and SIGHUP (a
    closed terminal, a dropped SSH connection) only set :attr:`requested`: the loop
    saves at the end of the round and stops with one line (:meth:`stop`); a second one
    stops at once (:class:`StoppedNow`, saying what ``kept()`` reports was kept). A
    handler installed before for SIGTERM or SIGUSR2 (the submitit launcher's, which
    requeues a preempted SLURM job) runs after the save. After SIGHUP, output to the
    terminal that is gone goes nowhere instead of failing. Outside the main thread it
    does nothing."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGUSR2)

    def __init__(self, kept: Any = None, round_s: Any = None):
        self.requested: int | None = None  # the signal received
        # in a job of a parallel sweep (uabs_rl.cli.parallel): the sweep's stop file, which
        # its launching process writes on a signal; the job then stops as on its own
        self._stop_file = os.environ.get(STOP_ENV)
        self._previous: dict[int, Any] = {}
        self._kept = kept or (lambda: "the last checkpoint, if any, is kept")
        self._round_s = round_s or (lambda: None)  # seconds a round takes, if known

    def _handle(self, signum, frame) -> None:
        if signum == signal.SIGHUP:
            detach_terminal()
        if self.requested is not None:
            raise StoppedNow(f"stopped at once: {self._kept()}", signum)
        self.requested = signum
        name = "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name
        secs = self._round_s()
        within = f" (a round takes about {secs:.0f} s)" if secs and secs >= 1 else ""
        try:
            print(f"\n{name}: stopping after this round{within}; again to stop now, "
                  f"keeping the last checkpoint", file=sys.stderr)
        except OSError:
            pass

    def asked(self, more: bool = True) -> bool:
        """A signal came, or (with ``more`` episodes to train) the parallel sweep this job
        belongs to stopped: its stop file, holding the signal (after SIGHUP the
        terminal the job writes to is gone too)."""
        if more and self.requested is None and self._stop_file:
            self.requested = stop_signal(Path(self._stop_file))
            if self.requested == signal.SIGHUP:
                detach_terminal()
        return self.requested is not None

    def __enter__(self) -> DeferredInterrupt:
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                before = signal.getsignal(sig)
                if sig == signal.SIGUSR2 and not callable(before):
                    continue  # only chained where someone (submitit) listens
                if sig == signal.SIGHUP and before is signal.SIG_IGN:
                    continue  # started with nohup: a hang-up does not stop it
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
        if (callable(before) and before is not signal.default_int_handler
                and getattr(before, "chained", True)):  # uabs_rl.cli.parallel's: not
            before(signum, None)
        raise Stopped(message, signum)




def member_generator(gen: torch.Generator | Generators, i: int) -> torch.Generator:
    """Member ``i``'s generator of ``gen`` (a single run's generator is its own)."""
    return gen.gens[i] if isinstance(gen, Generators) else gen


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


class Experiment:
    """Collect / optimise / evaluate / checkpoint / log, each in its own object, for the
    P = ``train.population`` members of a run (P = 1: a single run)."""

    def __init__(self, cfg: RunConfig, run_dir: Path,
                 traces: dict[str, TraceSet] | None = None):
        """``traces`` may hold ready TraceSets per split ("train", "eval"); by default
        they come from the trace cache (built with SUMO if missing)."""
        validate_run(cfg)
        check_logger(cfg.train.logger)
        self.cfg, self.run_dir = cfg, Path(run_dir)
        dev = self.device = resolve_device(cfg.device)
        tr, seeds = cfg.train, member_seeds(cfg)
        self.n, self.solo = len(seeds), len(seeds) == 1
        seed = cfg.seed if self.solo else seeds  # an int: one generator, not a list of one
        self.threads = setup_threads(cfg)
        torch.manual_seed(cfg.seed)
        traces = traces or {}
        train = traces["train"] if "train" in traces else training_traces(cfg)
        env = make_env(cfg.scenario, cfg.channel, cfg.masking, train,
                       "train", n_envs=tr.n_envs * self.n, device=dev, seed=seed,
                       compile=tr.compile, spec_mask=False, obs=cfg.obs)
        # eager, as every evaluation (make_eval_env): 50 evaluations take ~8 s; the
        # figures are the compiled rollout's bit for bit (tests/test_masking.py; P_g's
        # sum: tests/test_env.py)
        eval_env = make_eval_env(cfg, traces.get("eval"), dev, members=self.n)
        self.params = p = env.base_env.params
        self.learner = make_algorithm(cfg.algo, Dims(p.obs_dim, N_ACTIONS, p.n_uabs), seeds, dev)
        self.learner.compile_update(tr.compile if tr.compile_update is None
                                    else tr.compile_update)
        self.qnet, self.buffer = self.learner.policy, self.learner.buffer
        self.gen = make_generator(seed, dev)
        selector = make_selector(env, cfg.algo.eps_start, self.gen,
                                 compile=tr.compile)
        horizon = self.learner.teacher_horizon  # a learner that imitates a planner
        self.collector = Collector(env, self.qnet, selector, self.buffer, members=self.n,
                                   n_step=cfg.algo.n_step, gamma=cfg.algo.gamma,
                                   teacher=None if horizon is None else
                                   Teacher(env.base_env, horizon))
        self.updates = UpdateSchedule(self.learner, cfg.algo)
        self.evaluator = Evaluator(eval_env, tr.eval_seed)
        self.greedy = greedy_policy(self.qnet, eval_env, cfg, members=self.n)
        self.members = [Member(cfg, s, self.run_dir if self.solo else
                               member_dir(self.run_dir, s)) for s in seeds]
        self.checkpoints = Checkpoints(self)
        self.interrupt = DeferredInterrupt(self.kept, lambda: self.round_s)
        self.round_s: float | None = None  # how long the last training round took
        self.total_steps = tr.episodes * p.episode_steps  # per-env steps of the protocol
        self.episode = 0  # per member
        self.saved_episode: int | None = None  # the episode of the last ``last`` saved
        self.identity: dict | None = None  # the run folder's (set by resume.prepare)
        self.run_lock = None  # the run folder's lock, released when fit ends
        # called after each evaluation with the episode, the members' validation
        # returns and whether it is the run's last; True stops training there, the
        # checkpoint saved (a tuning study's pruner, uabs_rl.tuning)
        self.on_eval: Callable[[int, list[float], bool], bool] | None = None
        # how a stopped run continues, as its stop line says it (a sweep's job: the
        # sweep re-typed, set by uabs-train; None: resume= of this run's folder)
        self.continue_hint: str | None = None

    # ------------------------------------------------------------------ state
    def generators(self, i: int) -> tuple[torch.Generator, torch.Generator]:
        """Member ``i``'s selector and env generators."""
        return (member_generator(self.gen, i),
                member_generator(self.collector.env.base_env.rng, i))

    def member_state(self, i: int) -> dict:
        """Member ``i``'s state, as a single run's checkpoint holds it: its config, the
        run's identity, its learner state, the run's counters, the global RNG, its
        selector's and env's generators and, with ``train.checkpoint_buffer``, its
        replay buffer; ``population`` (the seeds, and which member) for a member of a
        population."""
        m = self.members[i]
        selector, env = self.generators(i)
        state = {
            "config": m.config, "run": self.identity,
            "learner": self.learner.member_state_dict(i),
            "counters": {"episode": self.episode, "env_steps": self.collector.env_steps,
                         "update_credit": self.updates.credit, "best_eval": m.best_eval,
                         "total_steps": self.total_steps},
            "rng": {"torch": torch.get_rng_state(), "selector": selector.get_state(),
                    "env": env.get_state()},
            "replay": (self.buffer.member_state_dict(i) if m.cfg.train.checkpoint_buffer
                       else None),
        }
        if not self.solo:
            state["population"] = {"seeds": [x.seed for x in self.members], "member": i}
        return state

    def load_member_state(self, i: int, state: dict) -> bool:
        """Continue member ``i`` from ``state`` (:meth:`member_state`): its learner, best
        evaluation, generators and replay buffer; False when ``state`` holds no buffer
        (``train.checkpoint_buffer=false``)."""
        self.learner.load_member(i, state["learner"])
        self.members[i].best_eval = float(state["counters"]["best_eval"])
        selector, env = self.generators(i)
        selector.set_state(state["rng"]["selector"])
        env.set_state(state["rng"]["env"])
        if state.get("replay") is None:
            return False
        self.buffer.load_member(i, state["replay"])
        return True

    def load_counters(self, state: dict) -> None:
        """The run's episode, env-step and update counters and the global RNG, from a
        member's state (the members' are equal)."""
        c = state["counters"]
        self.episode, self.collector.env_steps = int(c["episode"]), int(c["env_steps"])
        self.updates.credit = float(c["update_credit"])
        # the ε schedule as the run planned it, whatever train.episodes says now
        planned = int(c.get("total_steps", self.total_steps))
        if planned != self.total_steps:
            log.info("train.episodes changed on resume: the ε schedule keeps the run's "
                     "original length (%d env steps)", planned)
        self.total_steps = planned
        torch.set_rng_state(state["rng"]["torch"])

    # ------------------------------------------------------------------ steps
    def collect(self) -> list[list[dict[str, Any]]]:
        """One round of ``n_envs`` training episodes per member with their updates; the
        records of each member's episodes. A loss that is not finite stops training
        (:class:`NotFinite`) before anything of the round is logged."""
        updates = self.learner.updates
        last, served, eps, loss, q = self.collector.round(
            lambda s: epsilon(self.cfg.algo, s, self.total_steps), self.updates)
        loss, q = loss.expand(self.n).tolist(), q.expand(self.n).tolist()
        if self.learner.updates > updates:  # NaN stands for "no update" otherwise
            for i, (x, y) in enumerate(zip(loss, q, strict=True)):
                if not (math.isfinite(x) and math.isfinite(y)):
                    k = self.cfg.train.n_envs
                    at = (f"episode {self.episode + 1}" if k == 1 else
                          f"episodes {self.episode + 1}..{self.episode + k}")
                    what = f"the loss is {x}" if not math.isfinite(x) else f"the mean Q is {y}"
                    self.stop_not_finite(at, what, i)
        k = self.cfg.train.n_envs
        out = []
        for i in range(self.n):
            sl = slice(i * k, (i + 1) * k)
            out.append(episode_records(
                last[sl], served[sl], self.params.episode_steps, self.episode + 1,
                self.collector.env_steps,
                {"epsilon": eps, "loss": loss[i], "q_chosen": q[i],
                 "updates": self.learner.updates}))
        self.episode += k
        return out

    def evaluate(self) -> list[float]:
        """One batched evaluation of the greedy policy; each member logs its block,
        checkpoints ``best`` (by evaluation return) and ``last``, and draws its pictures
        (``eval/``, the logger's figures): a single run at every evaluation, a
        population's members at a new best and at the end only (each member's first
        pictures take longer to make than the batched rollout of all). Returns their
        returns.
        Weights that are not all finite stop training first (:class:`NotFinite`)."""
        self.check_weights()
        td = self.evaluator.rollout(self.greedy)
        w = td.shape[0] // self.n
        final = self.episode >= self.cfg.train.episodes
        returns = []
        for i, m in enumerate(self.members):
            block = td[i * w:(i + 1) * w]
            record = self.evaluator.record(block, self.episode, self.collector.env_steps)
            m.log.record(record)
            is_best = record["return"] >= m.best_eval
            if self.solo or is_best or final:
                m.log.eval_figures(record, block, self.evaluator, is_best)
            m.last_eval = record["return"]
            if is_best:
                m.best_eval = record["return"]
                self.checkpoints.save(i, "best")
            returns.append(record["return"])
        self.checkpoints.save_all("last")
        self.saved_episode = self.episode
        return returns

    def how_to_continue(self) -> str:
        """The words a stopped run ends its line with."""
        return self.continue_hint or f"continue with resume={self.run_dir}"

    def kept(self) -> str:
        """What a run stopped at once keeps, in words."""
        last = [RunFolder(m.run_dir).last for m in self.members]
        if all(p.is_file() for p in last):
            return f"the last checkpoint is kept; {self.how_to_continue()}"
        return ("no checkpoint had been written yet: nothing to resume, start the run "
                "again")

    def check_weights(self) -> None:
        """Stop (:class:`NotFinite`) when a weight of a member's networks (Q-network,
        QMIX's mixer) is not finite: checked before anything is evaluated or saved, in
        one device sync."""
        params = [p for m in (self.learner.policy, *getattr(self.learner, "extras", []))
                  if m is not None for p in m.parameters()]
        if params and not bool(torch.stack([p.isfinite().all() for p in params]).all()):
            self.stop_not_finite(f"episode {self.episode}", "a network weight is not finite")

    def stop_not_finite(self, at: str, what: str, member: int | None = None) -> None:
        """Raise :class:`NotFinite`: ``what`` happened (to ``member``) ``at`` an episode;
        the last checkpoint is kept."""
        who = "" if self.solo or member is None else f" (member seed={self.members[member].seed})"
        if self.saved_episode:
            kept = (f"the checkpoints of episode {self.saved_episode} and before are kept "
                    f"(resume={self.run_dir} continues from it)")
        else:
            kept = "no checkpoint had been saved yet"
        raise NotFinite(f"training stopped at {at}: {what}{who} (after "
                        f"{self.learner.updates} updates); nothing later is saved, {kept}. "
                        f"Lower algo.lr or set algo.grad_clip.")

    # ------------------------------------------------------------------ loop
    def rounds(self) -> None:
        """Collect and evaluate until ``train.episodes``, stopping early (after a whole
        round, so the saved state is consistent) when Ctrl-C or SIGTERM came."""
        tr = self.cfg.train
        while self.episode < tr.episodes:
            t0 = time.perf_counter()
            per_member = self.collect()
            self.round_s = time.perf_counter() - t0
            self.threads.check()
            for member, records in zip(self.members, per_member, strict=True):
                for rec in records:
                    member.log.record(rec)
            for recs in zip(*per_member, strict=True):  # the bar: one step per episode
                self.progress.update({
                    "return": sum(r["return"] for r in recs) / self.n,
                    "epsilon": recs[0]["epsilon"],
                    "collisions": sum(r["collisions"] for r in recs)})
            # after the round that reaches a multiple of eval_every (rounds of n_envs
            # episodes: with n_envs not dividing it, up to n_envs - 1 episodes past it)
            reached = self.episode // tr.eval_every > (self.episode - tr.n_envs) // tr.eval_every
            if reached or self.episode >= tr.episodes:
                returns = self.evaluate()
                self.progress.last_eval = sum(returns) / self.n
                if self.on_eval is not None and self.on_eval(
                        self.episode, returns, self.episode >= tr.episodes):
                    break  # stopped early: fit saves last.pt
            if self.interrupt.asked(more=self.episode < tr.episodes):
                self.check_weights()
                path = self.checkpoints.save_all("last")
                saved = path if self.solo else "every member's last.pt"
                self.interrupt.stop(f"interrupted at episode {self.episode}: saved {saved}; "
                                    f"{self.how_to_continue()}")

    def fit(self) -> dict[str, Any]:
        """Train every member to ``train.episodes``, evaluating every
        ``train.eval_every`` episodes. Ctrl-C or SIGTERM finishes the current round,
        saves ``last`` and raises :class:`Stopped` (a second one stops at once, keeping
        the last checkpoint). The run folder's lock (``run_lock``) is released when it
        ends, however it ends, and only after the last save. The summary's ``members``
        hold each member's returns; a single run's are also at its top level."""
        try:
            if self.interrupt.asked():  # a parallel sweep stopped while this job set up
                raise KeyboardInterrupt("the sweep stopped before this job trained")
            self.saved_episode = self.episode or None  # a resume: the checkpoint it loaded
            for m in self.members:
                m.log.open(resume_episode=self.episode if self.episode else None)
            self.progress = Progress(self.cfg.train, self.episode)
            t0 = time.perf_counter()
            try:
                with self.interrupt:
                    self.rounds()
            finally:
                self.progress.close()
                for m in self.members:
                    m.log.close()
            minutes = (time.perf_counter() - t0) / 60
            self.check_weights()
            self.checkpoints.save_all("last")
        except OSError as e:
            raise write_error(e, self.run_dir) from None
        finally:
            if self.run_lock is not None:
                self.run_lock.release()
        members = [{"seed": m.seed, "run_dir": m.run_dir, "best_eval_return": m.best_eval,
                    "last_eval_return": m.last_eval} for m in self.members]
        summary = {"episodes": self.episode, "updates": self.learner.updates,
                   "minutes": minutes, "members": members}
        if self.solo:
            summary.update({k: members[0][k] for k in ("best_eval_return",
                                                       "last_eval_return")})
        log.info("done: %d member(s) x %d episodes, %d updates, best validation return "
                 "%s, %.1f min", self.n, self.episode, self.learner.updates,
                 ", ".join(f"{m.best_eval:.0f}" for m in self.members), minutes)
        return summary
