"""Starting a run: a new run's checks and folder, or a stopped run resumed in its own
folder (``resume=<run dir>``: the run's own configuration, from its last checkpoint or,
if it stopped before one, from its ``.hydra/config.yaml``; overrides typed beside it may
change only what does not change results), and a population's members resumed together.
:func:`prepare` returns the :class:`~uabs_rl.training.experiment.Experiment`, holding its
run folder's lock."""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from uabs_rl.config import ConfigError, RunConfig, compose, structured_run, to_container
from uabs_rl.runs import folder as runfolder
from uabs_rl.runs.checkpoint import (
    ANOTHER,
    CheckpointError,
    check_own,
    config_dict,
    config_differences,
    config_from_checkpoint,
    flatten,
    load_checkpoint,
    load_hydra_config,
)
from uabs_rl.runs.layout import RunFolder
from uabs_rl.runs.metrics import check_history, count_evaluations
from uabs_rl.traces.build import check_names
from uabs_rl.training.experiment import Experiment
from uabs_rl.training.members import complete_save, member_dir, member_seeds
from uabs_rl.training.startup import validate_run

log = logging.getLogger(__name__)


def saved_config(run_dir: Path) -> tuple[RunConfig, dict | None]:
    """The configuration a run was started with, and its last checkpoint if it has one.
    A checkpoint must be this run's own: its run id (``run.json``) and its settings
    (``.hydra/config.yaml``) are checked."""
    check_checkpoints_folder(run_dir)
    folder = RunFolder(run_dir)
    ckpt = folder.last
    if ckpt.is_file():
        state = load_checkpoint(ckpt)
        if "population" in state:
            raise CheckpointError(f"{run_dir} is one member of a population trained "
                                  f"together: resume the population, "
                                  f"resume={run_dir.parent}.")
        check_own(state, run_dir, ckpt)
        return config_from_checkpoint(state), state
    if folder.member_checkpoints():  # a population
        return population_config(run_dir), None
    hydra_cfg = load_hydra_config(run_dir)
    if hydra_cfg is None:
        raise CheckpointError(f"resume={run_dir}: no checkpoints/last.pt and no "
                              f".hydra/config.yaml there: pass the folder of a uabs-train "
                              f"run (the one printed when it started).")
    return to_container(OmegaConf.merge(structured_run(hydra_cfg), hydra_cfg)), None


def check_checkpoints_folder(run_dir: Path) -> None:
    """Refuse a run folder whose ``checkpoints`` is not a folder (a file, a dangling
    link) before anything in it is written or truncated."""
    ckpts = RunFolder(run_dir).checkpoints
    if (ckpts.exists() or ckpts.is_symlink()) and not ckpts.is_dir():
        raise CheckpointError(f"{ckpts} is not a folder: a run keeps its checkpoints "
                              f"there. Move that file away (nothing was changed), then "
                              f"run the command again.")


def check_lost_checkpoint(members: list[Path]) -> None:
    """A run (or population) with no ``last.pt`` may start again in place only when it
    stopped before its first evaluation (the first checkpoint is written with it): a
    member folder that logged an evaluation or holds ``best.pt`` lost its checkpoint,
    and starting again would replace its history. Refused, naming what is missing."""
    for folder in members:
        f = RunFolder(folder)
        evals = count_evaluations(f.metrics)
        best = f.best.is_file()
        pictures = list(f.eval.glob("*.png")) if f.eval.is_dir() else []
        if evals or best or pictures:
            held = (f"{evals} evaluations in metrics.jsonl" if evals else
                    "checkpoints/best.pt" if best else "evaluation pictures in eval/")
            raise CheckpointError(
                f"{folder} holds a run's history ({held}) but no checkpoints/last.pt: "
                f"its checkpoint was removed or moved, and starting again would replace "
                f"that history. Put checkpoints/last.pt back to continue (nothing was "
                f"changed), or start a new run in another folder.")


def population_config(run_dir: Path) -> RunConfig:
    """The config of the population in ``run_dir``, from a member's checkpoint (the
    population's seed is its first member's)."""
    for member in RunFolder(run_dir).member_checkpoints():
        state = load_checkpoint(member)
        if "population" in state:
            cfg = config_from_checkpoint(state)
            cfg.seed = int(state["population"]["seeds"][0])
            return cfg
    raise CheckpointError(f"{run_dir} holds seed=*/ folders whose checkpoints are not a "
                          f"population's: resume each run folder on its own.")


def _flat_config(cfg: RunConfig) -> dict[str, Any]:
    return flatten(config_dict(cfg))


def _composer():
    """``compose(overrides) -> RunConfig`` as ``uabs-train`` composes its command line:
    inside the running app (so ``--config-dir`` and the app's search path apply), else
    from the package's ``conf/``."""
    from hydra.core.global_hydra import GlobalHydra

    gh = GlobalHydra.instance()
    if not gh.is_initialized():
        return lambda ovs: compose("config", ovs)
    from hydra.types import RunMode
    from omegaconf import open_dict

    def comp(ovs: list[str]) -> RunConfig:
        c = gh.hydra.compose_config("config", ovs, run_mode=RunMode.RUN)
        with open_dict(c):
            del c["hydra"]
        return to_container(c)
    return comp


def typed_settings(overrides: list[str]) -> tuple[dict[str, Any], set[str]]:
    """What the command line sets: the flat config it composes to, and the keys its
    overrides touch (those they change, and every key under a group or key they name, so
    ``masking=rank`` speaks for all of ``masking`` even where rank is the default). A
    group choice is compared with the defaults; a setting with the group choices typed
    beside it (``algo=dqfd algo.teacher_horizon=3``: a learner's own setting exists under
    its group only)."""
    comp = _composer()
    base = _flat_config(comp([]))
    typed = _flat_config(comp(overrides)) if overrides else base

    def name(o: str) -> str:
        return o.split("=", 1)[0].lstrip("+~").split("@", 1)[0].replace("/", ".")

    # a setting is composed with the group choices typed beside it: a learner's own
    # setting (algo.teacher_horizon) exists only under its group (algo=dqfd)
    groups = [o for o in overrides if "." not in name(o)]
    grouped = _flat_config(comp(groups)) if groups else base
    touched: set[str] = set()
    for o in overrides:
        ref, alone = ((base, _flat_config(comp([o]))) if o in groups
                      else (grouped, _flat_config(comp([*groups, o]))))
        touched |= {k for k in alone if alone[k] != ref.get(k)}
        touched |= {k for k in typed if k == name(o) or k.startswith(name(o) + ".")}
    return typed, touched


def resumed_config(saved: RunConfig, overrides: list[str]) -> RunConfig:
    """``saved`` with what the command line sets, refused if that would change results.
    The command line may be the run's original command with ``resume=`` appended:
    group choices, presets and settings equal to the run's own are accepted."""
    keep = [o for o in overrides if not o.split("=", 1)[0].lstrip("+~").startswith(
        ("resume", "hydra"))]
    try:
        typed, touched = typed_settings(keep)
    except Exception as e:  # Hydra's own composition errors: one line
        if isinstance(e, ConfigError):
            raise
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise ConfigError(f"resume: the overrides typed beside it do not compose: "
                          f"{first}") from None
    own = _flat_config(saved)
    changed = {k: typed[k] for k in touched if k in typed and typed[k] != own.get(k)}
    # a setting the run's config lacks (added since) compares as its default
    diffs = config_differences({k: own[k] for k in changed if k in own}, changed)
    if diffs:
        raise CheckpointError("resume continues a run with its own settings; these "
                              "overrides would change its results:\n  " + "\n  ".join(diffs)
                              + "\nStart a new run to use them.")
    nested: dict[str, Any] = {}
    for key, value in changed.items():  # what may change: train.episodes, device, ...
        *path, leaf = key.split(".")
        node = nested
        for part in path:
            node = node.setdefault(part, {})
        node[leaf] = value
    return to_container(OmegaConf.merge(OmegaConf.structured(saved), nested))


# what a resume refused for a damaged or foreign last.pt can do instead
RESUME_FIX = ("resume continues from checkpoints/last.pt alone: put back an intact copy of "
              "it, or start a new run (uabs-eval can still evaluate the run's best.pt)")


def requeued() -> bool:
    """True in a SLURM job that the scheduler requeued (after a preemption or a
    time-out, e.g. by the submitit launcher's ``max_num_timeout``)."""
    return int(os.environ.get("SLURM_RESTART_COUNT", "0") or 0) > 0


def prepare(cfg: RunConfig, run_dir: Path, overrides: list[str] | None = None,
            auto_named: bool = False, sweep_dir: Path | None = None,
            on_move: Callable[[Path], None] | None = None,
            record: Callable[[Path], None] | None = None) -> Experiment:
    """The experiment of one run, or of a population (``train.population`` > 1), new or
    resumed, holding its run folder's lock (released when its fit ends). With
    ``resume`` and ``overrides`` (the command line's), the run's own config is used.
    ``record(run_dir)`` writes a new run's settings of record (``.hydra/``) once every
    check has passed, so a refused start never changes a folder's record.
    A new run whose automatically named folder another process took writes beside it
    (:func:`uabs_rl.runs.folder.claim`, which ``auto_named``, ``sweep_dir`` and
    ``on_move`` are passed to)."""
    if not cfg.resume:
        validate_run(cfg)  # before anything is sized from it (member folders, ...)
        check_names(cfg)  # names of trace files: before anything is built or logged
    if not cfg.resume and requeued() and runfolder.holds_run(Path(run_dir)):
        log.info("SLURM requeued this job: continuing the run in %s", run_dir)
        cfg.resume = str(run_dir)
    if cfg.resume:
        run_dir = Path(cfg.resume)
        if run_dir.suffix == ".pt" or run_dir.is_file():
            raise ConfigError(f"resume={cfg.resume} is a file: pass the run folder that "
                              f"holds checkpoints/last.pt, e.g. "
                              f"resume={run_dir.parent.parent}.")
        if not run_dir.is_dir():
            raise ConfigError(f"resume={cfg.resume}: no such folder. Pass the folder of a "
                              f"uabs-train run (the one printed when it started).")
        lk = runfolder.lock(run_dir)
    else:
        run_dir, lk = runfolder.claim(Path(run_dir), auto_named, sweep_dir, on_move)
    try:
        exp = _prepare_locked(cfg, run_dir, overrides, record)
        exp.identity = dict(runfolder.identity(run_dir), folder=run_dir.name)
        lk.record()  # who writes the folder, now that every check has passed
    except OSError as e:  # a full disk or a read-only folder at start-up: one line
        lk.release()
        raise runfolder.write_error(e, run_dir) from None
    except CheckpointError as e:  # resume reads last.pt alone: "another checkpoint" is
        lk.release()  # no advice for it
        if not cfg.resume or ANOTHER not in str(e):
            raise
        raise CheckpointError(str(e).replace(ANOTHER, RESUME_FIX)) from None
    except BaseException:
        lk.release()
        raise
    exp.run_lock = lk
    return exp


def _prepare_locked(cfg: RunConfig, run_dir: Path, overrides: list[str] | None,
                    record: Callable[[Path], None] | None = None) -> Experiment:
    if not cfg.resume:
        folders = [run_dir, *(member_dir(run_dir, s) for s in member_seeds(cfg))]
        held = [d for d in folders if RunFolder(d).metrics.exists()]
        if held:
            raise ConfigError(f"{held[0]} already holds a run (metrics.jsonl): continue it "
                              f"with resume={run_dir}, or choose another hydra.run.dir.")
        for folder in folders:
            check_checkpoints_folder(folder)
        if record is not None:  # the run's settings of record, once every check passed
            record(run_dir)
        return Experiment(cfg, run_dir)
    saved, state = saved_config(run_dir)
    if overrides is not None:
        cfg = resumed_config(saved, overrides)
    cfg.resume = str(run_dir)
    if cfg.train.population > 1:
        return _resume_population(cfg, run_dir)
    if state is None:
        check_lost_checkpoint([run_dir])
    else:  # before anything is built, logged or truncated
        check_history(RunFolder(run_dir).metrics, int(state["counters"]["episode"]))
    exp = Experiment(cfg, run_dir)
    if state is None:  # stopped before its first checkpoint: start it again, in place
        log.info("%s has no checkpoint yet: starting it again from episode 0", run_dir)
        exp.members[0].log.truncate(0)
    else:
        exp.checkpoints.resume([state], [RunFolder(run_dir).last])
        log.info("resuming %s at episode %d", run_dir, exp.episode)
    return exp


def _resume_population(cfg: RunConfig, run_dir: Path) -> Experiment:
    """Every member continues from its ``last.pt``; a population none of whose members
    has checkpointed yet starts again in place. A member without a checkpoint beside
    members with one is refused by name: a member cannot be restarted alone (its updates
    are batched with the others'), and no completed member is ever wiped."""
    complete_save(run_dir)  # a save_all that a kill interrupted
    folders = [member_dir(run_dir, s) for s in member_seeds(cfg)]
    for folder in folders:
        check_checkpoints_folder(folder)
    if not any(RunFolder(f).last.is_file() for f in folders):
        check_lost_checkpoint(folders)
    pop = Experiment(cfg, run_dir)
    have = [RunFolder(m.run_dir).last.is_file() for m in pop.members]
    if all(have):
        pop.checkpoints.load()
        for m in pop.members:  # every member's history, before any is truncated
            m.log.check_history(pop.episode)
        log.info("resuming the population %s at episode %d", run_dir, pop.episode)
    elif not any(have):  # stopped before its first checkpoint: start again, in place
        log.info("%s has no checkpoint of any member yet: starting it again from "
                 "episode 0", run_dir)
        for m in pop.members:
            m.log.truncate(0)
    else:
        missing = [m.run_dir.name for m, h in zip(pop.members, have, strict=True) if not h]
        present = [m.run_dir.name for m, h in zip(pop.members, have, strict=True) if h]
        raise CheckpointError(
            f"the population in {run_dir} cannot continue: member {', '.join(missing)} has "
            f"no checkpoints/last.pt while {', '.join(present)} have theirs (members train "
            f"together, so one cannot restart alone). Put its last.pt back (nothing was "
            f"changed), or start a new population.")
    return pop


def run(cfg: RunConfig, run_dir: Path, overrides: list[str] | None = None) -> dict[str, Any]:
    """Train (or resume) one run to its end; returns the fit's summary."""
    return prepare(cfg, run_dir, overrides).fit()
