"""Population training (``train.population = P``): P seeds of one configuration trained
together in one process.

    uabs-train train.population=3                         # seeds 0, 1, 2 of rank
    uabs-train -m masking=penalty,flat,rank train.population=3

Member ``p`` has seed ``seed + p``. Its episodes run in block ``p`` of one env
(``P · train.n_envs`` envs), drawn from its own generators (:mod:`uabs_rl.rng`); its
network is member ``p`` of the algorithm's (for the 3DQN slice ``p`` of a
:class:`~uabs_rl.model.StackedQNet`, updated by one batched step per update); its
transitions go to its own replay buffer (block ``p`` of the algorithm's
:class:`~uabs_rl.algorithms.replay.TransitionReplay`); its evaluations are block ``p``
of one batched evaluation.
Each member writes what a solo run writes, in ``<run>/seed=<s>/``: ``metrics.jsonl``,
logger files, ``eval/`` pictures, ``checkpoints/{best,last}.pt`` in the solo format
(so ``uabs-eval`` and ``uabs-report`` read members as runs). Unlike a solo run, a
member draws its evaluation pictures only at a new best and at the end.

What equals a solo run of the same seed, exactly: the initial network, every random
draw (training windows, start positions, LoS states, exploration, replay samples,
evaluation episodes). What differs: the batched matrix products round differently from
the solo ones (float32 rounding, 1e-7 to 1e-6 relative), and DQN training amplifies such
differences, so a member's curve is another sample of the same experiment, not its
solo run's curve bit for bit. ``tests/test_population.py`` checks both: without
updates a member's records equal its solo run's; one population update equals the
members' solo updates to float precision.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import os
from pathlib import Path
from typing import Any

from uabs_rl.algorithms import Dims, make_algorithm
from uabs_rl.checkpoint import (
    CheckpointError,
    check_compatible,
    load_checkpoint,
    save_checkpoint,
)
from uabs_rl.config import ConfigError, RunConfig, validate_run
from uabs_rl.env import N_ACTIONS
from uabs_rl.evaluation import Evaluator, greedy_policy, make_eval_env
from uabs_rl.experiment import (
    NO_REPLAY,
    DeferredInterrupt,
    restore_counters,
    restore_streams,
    run_rounds,
    run_state,
    write_error,
)
from uabs_rl.make import make_env, make_selector, resolve_device
from uabs_rl.rng import Generators
from uabs_rl.rollout import Collector, UpdateSchedule, episode_records, epsilon
from uabs_rl.runfolder import check_identity
from uabs_rl.runlog import RunLog, check_logger
from uabs_rl.threads import setup_threads
from uabs_rl.traces import TraceSet

log = logging.getLogger(__name__)


def member_seeds(cfg: RunConfig) -> list[int]:
    return [cfg.seed + i for i in range(cfg.train.population)]


def member_dir(run_dir: Path, seed: int) -> Path:
    return Path(run_dir) / f"seed={seed}"


def complete_save(run_dir: Path, name: str = "last") -> None:
    """Finish or drop an interrupted :meth:`Population.save_all`: with its commit record,
    the staged checkpoints replace the old ones; without it, they are removed."""
    record = Path(run_dir) / f".{name}.commit"
    if record.is_file():
        for staged in json.loads(record.read_text()):
            staged = Path(run_dir) / staged  # relative to the population folder
            if staged.is_file():
                os.replace(staged, staged.with_name(f"{name}.pt"))
        record.unlink()
    for staged in Path(run_dir).glob(f"seed=*/checkpoints/{name}.staged.pt"):
        staged.unlink()


class Member:
    """One seed of a population: its config (the population's with its own seed), its
    run folder and log, and its best validation return."""

    def __init__(self, cfg: RunConfig, seed: int, run_dir: Path):
        self.cfg = copy.deepcopy(cfg)
        self.cfg.seed = seed
        self.seed, self.run_dir = seed, member_dir(run_dir, seed)
        self.log = RunLog(self.cfg, self.run_dir)
        self.best_eval = -math.inf
        self.last_eval = float("nan")


class Population:
    """A population's collect / optimise / evaluate / checkpoint / log loop: the
    :class:`~uabs_rl.experiment.Experiment` of P members at once."""

    def __init__(self, cfg: RunConfig, run_dir: Path,
                 traces: dict[str, TraceSet] | None = None):
        validate_run(cfg)
        check_logger(cfg.train.logger)
        if cfg.train.population < 2:
            raise ConfigError("Population needs train.population >= 2; a single seed "
                              "trains as a solo run (uabs_rl.experiment.Experiment).")
        self.cfg, self.run_dir = cfg, Path(run_dir)
        dev = self.device = resolve_device(cfg.device)
        tr, seeds = cfg.train, member_seeds(cfg)
        self.n = P = len(seeds)
        self.threads = setup_threads(cfg)
        traces = traces or {}
        env = make_env(cfg.scenario, cfg.channel, cfg.masking, traces.get("train", cfg.traces),
                       "train", n_envs=tr.n_envs * P, device=dev, seed=seeds,
                       compile=tr.compile, spec_mask=False)
        eval_env = make_eval_env(cfg, traces.get("eval"), dev, members=P)
        self.params = p = env.base_env.params
        self.learner = make_algorithm(cfg.algo, Dims(p.obs_dim, N_ACTIONS, p.n_uabs),
                                      seeds, dev)
        self.qnet, self.buffer = self.learner.policy, self.learner.buffer
        self.gen = Generators(seeds, dev)
        selector = make_selector(env, cfg.masking, cfg.algo.eps_start, self.gen,
                                 compile=tr.compile)
        self.collector = Collector(env, self.qnet, selector, self.buffer, members=P,
                                   n_step=cfg.algo.n_step, gamma=cfg.algo.gamma)
        self.updates = UpdateSchedule(self.learner, cfg.algo)
        self.evaluator = Evaluator(eval_env, tr.eval_seed)
        self.greedy = greedy_policy(self.qnet, eval_env, cfg, compile=tr.compile, members=P)
        self.members = [Member(cfg, s, self.run_dir) for s in seeds]
        self.interrupt = DeferredInterrupt()
        self.total_steps = tr.episodes * p.episode_steps
        self.episode = 0  # per member
        self.identity: dict | None = None  # the population folder's (set by train.prepare)
        self.run_lock = None  # the population folder's lock, released when fit ends

    # ------------------------------------------------------------------ steps
    def collect(self) -> list[list[dict[str, Any]]]:
        """One round of ``n_envs`` training episodes per member; their records."""
        last, served, eps, loss, q = self.collector.round(
            lambda s: epsilon(self.cfg.algo, s, self.total_steps), self.updates)
        loss, q = loss.expand(self.n).tolist(), q.expand(self.n).tolist()
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
        """One batched evaluation; each member logs its block, checkpoints ``best`` and
        ``last``, and draws its pictures (``eval/``, the logger's figures) at a new best
        and at the final evaluation only: each member's pictures take longer to draw than
        the batched rollout of all members. Returns the members' returns."""
        td = self.evaluator.rollout(self.greedy)
        w = td.shape[0] // self.n
        returns = []
        for i, m in enumerate(self.members):
            block = td[i * w:(i + 1) * w]
            record = self.evaluator.record(block, self.episode, self.collector.env_steps)
            m.log.record(record)
            is_best = record["return"] >= m.best_eval
            if is_best or self.episode >= self.cfg.train.episodes:
                m.log.eval_figures(record, block, self.evaluator, is_best)
            m.last_eval = record["return"]
            if is_best:
                m.best_eval = record["return"]
                self.save(i, "best")
            returns.append(record["return"])
        self.save_all("last")
        return returns

    # ------------------------------------------------------------------ checkpoints
    def member_state_dict(self, i: int) -> dict:
        """Member ``i``'s checkpoint, in a solo run's format plus ``population``."""
        m = self.members[i]
        state = run_state(self, m.cfg, self.learner.member_state_dict(i), m.best_eval,
                          self.gen.gens[i], self.collector.env.base_env.rng.gens[i],
                          self.buffer, member=i)
        state["population"] = {"seeds": [x.seed for x in self.members], "member": i}
        return state

    def save(self, i: int, name: str) -> Path:
        path = self.members[i].run_dir / "checkpoints" / f"{name}.pt"
        try:
            save_checkpoint(self.member_state_dict(i), path)
        except (OSError, RuntimeError) as e:
            raise write_error(e, self.run_dir) from None
        return path

    def save_all(self, name: str) -> None:
        """Every member's ``<name>.pt`` at this episode, all or none: each is written
        beside its old one (``<name>.staged.pt``), then a commit record in the population
        folder says they are complete, then they replace the old ones. A kill in between
        leaves either the old set (no record: the staged files are dropped on resume) or
        a record that :func:`complete_save` finishes."""
        staged = []
        for i in range(self.n):
            staged.append(self.save(i, f"{name}.staged"))
        record = self.run_dir / f".{name}.commit"
        tmp = record.with_name(record.name + ".tmp")
        # names relative to the population folder: it may be resumed from elsewhere or moved
        tmp.write_text(json.dumps([os.path.relpath(p, self.run_dir) for p in staged]))
        os.replace(tmp, record)
        complete_save(self.run_dir, name)

    def load(self) -> None:
        """Continue every member from its ``last.pt`` (written at the same episode)."""
        states = [load_checkpoint(m.run_dir / "checkpoints" / "last.pt") for m in self.members]
        episodes = {int(s["counters"]["episode"]) for s in states}
        if len(episodes) > 1:
            raise CheckpointError(
                f"the members of {self.run_dir} saved last.pt at different episodes "
                f"({sorted(episodes)}): the run was killed while saving them, and a "
                f"member cannot be rewound. Start the population again in a new folder.")
        env_rng = self.collector.env.base_env.rng
        buffers = True
        seeds = [m.seed for m in self.members]
        for i, (m, st) in enumerate(zip(self.members, states, strict=True)):
            path = m.run_dir / "checkpoints" / "last.pt"
            check_identity(st, self.run_dir, path)
            pop = st.get("population") or {}
            if list(pop.get("seeds", [])) != seeds or pop.get("member") != i:
                raise CheckpointError(
                    f"{path} is not member {i} (seed {m.seed}) of this population of seeds "
                    f"{seeds}: it belongs to another run. Put this member's own last.pt "
                    f"back, or resume the population it came from.")
            check_compatible(st, m.cfg, path)
            self.learner.load_member(i, st["learner"])
            m.best_eval = float(st["counters"]["best_eval"])
            buffers &= restore_streams(st, self.gen.gens[i], env_rng.gens[i],
                                       self.buffer, member=i)
        restore_counters(self, states[0])  # the members' counters are equal
        if not buffers:
            log.warning(NO_REPLAY)

    # ------------------------------------------------------------------ loop
    def rounds(self) -> None:
        tr = self.cfg.train
        while self.episode < tr.episodes:
            per_member = self.collect()
            self.threads.check()
            for member, records in zip(self.members, per_member, strict=True):
                for rec in records:
                    member.log.record(rec)
            for recs in zip(*per_member, strict=True):  # the bar: one step per episode
                self.progress.update({
                    "return": sum(r["return"] for r in recs) / self.n,
                    "epsilon": recs[0]["epsilon"],
                    "collisions": sum(r["collisions"] for r in recs)})
            if self.episode % tr.eval_every == 0 or self.episode >= tr.episodes:
                self.progress.last_eval = sum(self.evaluate()) / self.n
            if self.interrupt.requested:
                self.save_all("last")
                self.interrupt.stop(f"interrupted at episode {self.episode}: saved every "
                                    f"member's last.pt; continue with resume={self.run_dir}")

    def fit(self) -> dict[str, Any]:
        """Train every member to ``train.episodes`` (see :meth:`Experiment.fit`)."""
        minutes = run_rounds(self, [m.log for m in self.members], lambda: self.save_all("last"))
        log.info("done: %d members x %d episodes, %d updates, %.1f min", self.n,
                 self.episode, self.learner.updates, minutes)
        return {"episodes": self.episode, "updates": self.learner.updates,
                "minutes": minutes,
                "members": [{"seed": m.seed, "run_dir": m.run_dir, "best_eval_return":
                             m.best_eval, "last_eval_return": m.last_eval}
                            for m in self.members]}
