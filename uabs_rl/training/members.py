"""The members of a run and their checkpoints.

A run trains P >= 1 seeds of one configuration in one process (``train.population = P``;
P = 1, the default, is a single run):

    uabs-train train.population=3                         # seeds 0, 1, 2 of rank
    uabs-train -m masking=penalty,flat,rank train.population=3

Member ``p`` has seed ``seed + p``. Its episodes run in block ``p`` of one env
(``P · train.n_envs`` envs), drawn from its own generators (:mod:`uabs_rl.rng`); its
network is member ``p`` of the algorithm's (for the 3DQN slice ``p`` of a
:class:`~uabs_rl.algorithms.model.StackedQNet`, updated by one batched step per update); its
transitions go to its own replay buffer (block ``p`` of the algorithm's
:class:`~uabs_rl.algorithms.replay.TransitionReplay`); its evaluations are block ``p``
of one batched evaluation. A single run writes into its run folder; each member of a
population writes what a single run writes, in ``<run>/seed=<s>/``: ``metrics.jsonl``,
logger files, ``eval/`` pictures, ``checkpoints/{best,last}.pt`` in a single run's
format (so ``uabs-eval`` and ``uabs-report`` read members as runs). Unlike a single run,
a member draws its evaluation pictures only at a new best and at the end.

What equals a single run of the same seed, exactly: the initial network, every random
draw (training windows, start positions, LoS states, exploration, replay samples,
evaluation episodes). What differs: the batched matrix products round differently from
the single ones (float32 rounding, 1e-7 to 1e-6 relative), and DQN training amplifies
such differences, so a member's curve is another sample of the same experiment, not its
single run's curve bit for bit. ``tests/test_population.py`` checks both: without
updates a member's records equal its single run's; one population update equals the
members' single updates to float precision.
"""

from __future__ import annotations

import copy
import functools
import json
import logging
import math
import os
from pathlib import Path
from typing import Protocol

from uabs_rl.config import RunConfig
from uabs_rl.paths import atomic_write
from uabs_rl.runs.checkpoint import (
    CKPT_FORMAT,
    CheckpointError,
    check_compatible,
    config_dict,
    load_checkpoint,
    save_checkpoint,
)
from uabs_rl.runs.folder import RunFolderError, check_identity, write_error
from uabs_rl.runs.layout import RunFolder
from uabs_rl.training.runlog import RunLog

log = logging.getLogger(__name__)

NO_REPLAY = ("the checkpoint holds no replay buffer (train.checkpoint_buffer=false): "
             "learning restarts after algo.learning_starts transitions")


def member_seeds(cfg: RunConfig) -> list[int]:
    return [cfg.seed + i for i in range(cfg.train.population)]


def member_dir(run_dir: Path, seed: int) -> Path:
    return RunFolder(run_dir).member(seed).path


def complete_save(run_dir: Path, name: str = "last") -> None:
    """Finish or drop an interrupted :meth:`Checkpoints.save_all` of a population: with
    its commit record, the staged checkpoints replace the old ones; without it, they
    are removed."""
    record = Path(run_dir) / f".{name}.commit"
    if record.is_file():
        for staged in json.loads(record.read_text()):
            staged = Path(run_dir) / staged  # relative to the population folder
            if staged.is_file():
                os.replace(staged, staged.with_name(f"{name}.pt"))
        record.unlink()
    for staged in RunFolder(run_dir).member_checkpoints(f"{name}.staged"):
        staged.unlink()


class Member:
    """One seed of a run: its config (the run's with its own seed), its folder and log,
    and its validation returns."""

    def __init__(self, cfg: RunConfig, seed: int, run_dir: Path):
        self.cfg = copy.deepcopy(cfg)
        self.cfg.seed = seed
        self.seed, self.run_dir = seed, Path(run_dir)
        self.log = RunLog(self.cfg, self.run_dir)
        self.best_eval = -math.inf
        self.last_eval = float("nan")

    @functools.cached_property
    def config(self) -> dict:
        """The member's config as its checkpoints store it (:func:`config_dict`), made
        once: it does not change during a run, and making it took 85 ms, half of each
        checkpoint's save."""
        return config_dict(self.cfg)


class Trainer(Protocol):
    """What :class:`Checkpoints` needs of the trainer whose members it saves
    (:class:`~uabs_rl.training.experiment.Experiment`): the members, and each member's
    state in and out."""

    run_dir: Path
    solo: bool
    members: list[Member]

    def member_state(self, i: int) -> dict: ...

    def load_member_state(self, i: int, state: dict) -> bool: ...

    def load_counters(self, state: dict) -> None: ...


class Checkpoints:
    """The checkpoint files of a trainer's members: each member's ``best.pt`` and
    ``last.pt`` (the trainer's :meth:`~Trainer.member_state` in the checkpoint format),
    a population's saved all or none, and a resume's checks that each file is its
    member's own and fits the run's settings."""

    def __init__(self, exp: Trainer):
        self.exp = exp
        self.written: set[Path] = set()  # the checkpoints this session wrote

    def check_written(self) -> None:
        """Every checkpoint this session wrote is still there: one removed by another
        process (``rm -rf <run>/checkpoints``) stops the run in one line instead of
        being half made again (a removed ``best.pt`` would come back only at a new
        best)."""
        gone = sorted(p for p in self.written if not p.is_file())
        if gone:
            raise RunFolderError(
                f"{gone[0]} was removed while the run wrote it: the run stopped so that "
                f"its checkpoints stay its own. Put it back and continue with "
                f"resume={self.exp.run_dir}, or start the run again.")

    def save(self, i: int, name: str) -> Path:
        path = RunFolder(self.exp.members[i].run_dir).checkpoint(name)
        self.check_written()
        try:
            save_checkpoint({"format": CKPT_FORMAT, **self.exp.member_state(i)}, path)
        except (OSError, RuntimeError) as e:
            raise write_error(e, self.exp.run_dir) from None
        if not name.endswith(".staged"):
            self.written.add(path)
        return path

    def save_all(self, name: str) -> Path:
        """Every member's ``<name>.pt`` at this episode, all or none; returns the folder
        or file saved. A population's are each written beside its old one
        (``<name>.staged.pt``), then a commit record in the population folder says they
        are complete, then they replace the old ones. A kill in between leaves either
        the old set (no record: the staged files are dropped on resume) or a record that
        :func:`complete_save` finishes."""
        run_dir = self.exp.run_dir
        if self.exp.solo:
            return self.save(0, name)
        staged = [self.save(i, f"{name}.staged") for i in range(len(self.exp.members))]
        record = run_dir / f".{name}.commit"
        # names relative to the population folder: it may be resumed from elsewhere or moved
        atomic_write(record, json.dumps([os.path.relpath(p, run_dir) for p in staged]))
        complete_save(run_dir, name)
        self.written |= {RunFolder(m.run_dir).checkpoint(name) for m in self.exp.members}
        return run_dir

    def resume(self, states: list[dict], sources: list[Path]) -> None:
        """Continue every member from its checkpoint (written at the same episode)."""
        exp = self.exp
        episodes = {int(s["counters"]["episode"]) for s in states}
        if len(episodes) > 1:
            raise CheckpointError(
                f"the members of {exp.run_dir} saved last.pt at different episodes "
                f"({sorted(episodes)}): the run was killed while saving them, and a "
                f"member cannot be rewound. Start the population again in a new folder.")
        buffers = True
        for i, (st, path) in enumerate(zip(states, sources, strict=True)):
            m = exp.members[i]
            if not exp.solo:
                self.check_member(st, i, path)
            check_compatible(st, m.cfg, path)
            buffers &= exp.load_member_state(i, st)
        exp.load_counters(states[0])  # the members' counters are equal
        if not buffers and exp.episode < exp.cfg.train.episodes:  # learning goes on
            log.warning(NO_REPLAY)

    def check_member(self, state: dict, i: int, path: Path) -> None:
        """``state`` is member ``i`` of this population, written in its folder."""
        exp, m = self.exp, self.exp.members[i]
        check_identity(state, exp.run_dir, path)
        pop = state.get("population") or {}
        seeds = [x.seed for x in exp.members]
        if list(pop.get("seeds", [])) != seeds or pop.get("member") != i:
            raise CheckpointError(
                f"{path} is not member {i} (seed {m.seed}) of this population of seeds "
                f"{seeds}: it belongs to another run. Put this member's own last.pt "
                f"back, or resume the population it came from.")

    def load(self) -> None:
        """Continue every member from its ``last.pt``."""
        paths = [RunFolder(m.run_dir).last for m in self.exp.members]
        self.resume([load_checkpoint(p) for p in paths], paths)
