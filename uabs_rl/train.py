"""``uabs-train``: 3DQN training with periodic held-out evaluation (SPEC §7, §8).

    uabs-train                                    # paper protocol, masking=rank
    uabs-train masking=flat seed=3
    uabs-train -m masking=penalty,flat,rank seed=0,1,2
    uabs-train experiment=smoke                   # the whole pipeline in seconds
    uabs-train resume=outputs/runs/<run dir>      # continue a stopped run

Every run writes under its Hydra output directory: ``metrics.jsonl`` (one line per
training episode and per evaluation), ``tb/`` (TensorBoard; ``train.logger`` picks
another TorchRL logger), ``checkpoints/last.pt``
and ``checkpoints/best.pt`` (by evaluation return), ``eval/*.png``. The run itself is
:class:`uabs_rl.experiment.Experiment`.

``resume=<run dir>`` takes the run's own configuration (from its last checkpoint, or
from its ``.hydra/config.yaml`` if it stopped before one) and writes into that folder;
overrides typed beside it may change only what does not change results
(``train.episodes``, ``device``, ``train.progress``, ...).
"""

from __future__ import annotations

import logging
import shlex
import sys
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from uabs_rl.checkpoint import (
    CheckpointError,
    config_dict,
    config_differences,
    config_from_checkpoint,
    load_checkpoint,
    upgrade_config,
)
from uabs_rl.cli import hydra_main
from uabs_rl.config import ConfigError, LoggerKind, RunConfig, to_container
from uabs_rl.experiment import Experiment
from uabs_rl.population import Population, member_dir, member_seeds
from uabs_rl.runlog import read_metrics

log = logging.getLogger(__name__)


def saved_config(run_dir: Path) -> tuple[RunConfig, dict | None]:
    """The configuration a run was started with, and its last checkpoint if it has one."""
    ckpt = run_dir / "checkpoints" / "last.pt"
    if ckpt.is_file():
        state = load_checkpoint(ckpt)
        if "population" in state:
            raise CheckpointError(f"{run_dir} is one member of a population trained "
                                  f"together: resume the population, "
                                  f"resume={run_dir.parent}.")
        return config_from_checkpoint(state), state
    for member in sorted(run_dir.glob("seed=*/checkpoints/last.pt")):  # a population
        state = load_checkpoint(member)
        if "population" in state:
            cfg = config_from_checkpoint(state)
            cfg.seed = int(state["population"]["seeds"][0])
            return cfg, None  # the population loads its members' checkpoints itself
    hydra_cfg = run_dir / ".hydra" / "config.yaml"
    if not hydra_cfg.is_file():
        raise CheckpointError(f"resume={run_dir}: no checkpoints/last.pt and no "
                              f".hydra/config.yaml there: pass the folder of a uabs-train "
                              f"run (the one printed when it started).")
    stored = OmegaConf.to_container(OmegaConf.load(hydra_cfg))
    merged = OmegaConf.merge(OmegaConf.structured(RunConfig), upgrade_config(stored))
    return to_container(merged), None


def resumed_config(saved: RunConfig, overrides: list[str]) -> RunConfig:
    """``saved`` with the command line's overrides, refused if one changes results."""
    keep = [o for o in overrides if not o.split("=", 1)[0].lstrip("+~").startswith(
        ("resume", "hydra"))]
    cfg = to_container(OmegaConf.merge(OmegaConf.structured(saved),
                                       OmegaConf.from_dotlist(keep)))
    diffs = config_differences(config_dict(saved), config_dict(cfg))
    if diffs:
        raise CheckpointError("resume continues a run with its own settings; these "
                              "overrides would change its results:\n  " + "\n  ".join(diffs)
                              + "\nStart a new run to use them.")
    cfg.resume = saved.resume
    return cfg


def prepare(cfg: RunConfig, run_dir: Path,
            overrides: list[str] | None = None) -> Experiment | Population:
    """The experiment of one run, or of a population (``train.population`` > 1), new or
    resumed. With ``resume`` and ``overrides`` (the command line's), the run's own
    config is used."""
    if not cfg.resume:
        held = [d for d in [Path(run_dir), *(member_dir(run_dir, s) for s in
                                              member_seeds(cfg))]
                if (d / "metrics.jsonl").exists()]
        if held:
            raise ConfigError(f"{held[0]} already holds a run (metrics.jsonl): continue it "
                              f"with resume={run_dir}, or choose another hydra.run.dir.")
        if cfg.train.population > 1:
            return Population(cfg, run_dir)
        return Experiment(cfg, run_dir)
    run_dir = Path(cfg.resume)
    if run_dir.suffix == ".pt" or run_dir.is_file():
        raise ConfigError(f"resume={cfg.resume} is a file: pass the run folder that holds "
                          f"checkpoints/last.pt, e.g. resume={run_dir.parent.parent}.")
    saved, state = saved_config(run_dir)
    if overrides is not None:
        cfg = resumed_config(saved, overrides)
    if cfg.train.population > 1:
        return _resume_population(cfg, run_dir)
    exp = Experiment(cfg, run_dir)
    if state is None:  # stopped before its first checkpoint: start it again, in place
        log.info("%s has no checkpoint yet: starting it again from episode 0", run_dir)
        exp.log.truncate(0)
    else:
        exp.load_state_dict(state, run_dir / "checkpoints" / "last.pt")
        log.info("resuming %s at episode %d", run_dir, exp.episode)
    return exp


def _resume_population(cfg: RunConfig, run_dir: Path) -> Population:
    pop = Population(cfg, run_dir)
    if all((m.run_dir / "checkpoints" / "last.pt").is_file() for m in pop.members):
        pop.load()
        log.info("resuming the population %s at episode %d", run_dir, pop.episode)
    else:  # stopped before every member's first checkpoint: start again, in place
        log.info("%s has no checkpoint of every member yet: starting it again from "
                 "episode 0", run_dir)
        for m in pop.members:
            m.log.truncate(0)
    return pop


def run(cfg: RunConfig, run_dir: Path, overrides: list[str] | None = None) -> dict[str, Any]:
    """Train (or resume) one run to its end; returns the fit's summary."""
    return prepare(cfg, run_dir, overrides).fit()


def summary_text(cfg: RunConfig, summary: dict[str, Any], run_dir: Path) -> str:
    """The end of a run: where it is, a table of its headline figures (from its whole
    ``metrics.jsonl``, so a resumed run counts every episode), and the next commands,
    ready to copy."""
    metrics = run_dir / "metrics.jsonl"
    recs = read_metrics(metrics) if metrics.is_file() else []
    train = [r for r in recs if r["kind"] == "train"]
    evals = [r for r in recs if r["kind"] == "eval"]
    steps = train[-1]["env_steps"] if train else 0
    lines = [f"\nrun folder: {run_dir}",
             f"  {summary['episodes']} episodes, {steps} env steps, {summary['updates']} "
             f"updates; this session {summary['minutes']:.1f} min"]
    if evals:
        best = max(evals, key=lambda r: r["return"])  # the checkpoint best.pt holds
        last = evals[-1]
        nhat = cfg.scenario.nhat_s
        rows = [("return R", "{:.0f}", "return"),
                ("served fraction", "{:.1%}", "served_fraction"),
                (f"P_g(N̂s={nhat})", "{:.1%}", "pg"),
                ("collisions", "{:.0f}", "collisions"),
                ("proximity events", "{:.0f}", "proximity"),
                ("mask fallbacks", "{:.0f}", "fallbacks")]
        head_b, head_l = f"best (ep {best['episode']})", f"last (ep {last['episode']})"
        title = f"validation ({best['windows']} windows)"
        lines.append(f"  {title:<24} {head_b:>16} {head_l:>16}")
        for name, fmt, key in rows:
            lines.append(f"  {name:<24} {fmt.format(best[key]):>16} {fmt.format(last[key]):>16}")
    if train:
        lines.append("  training: " + ", ".join(
            f"{sum(r[k] for r in train):.0f} {name}" for k, name in (
                ("collisions", "collisions"), ("proximity", "proximity events"),
                ("fallbacks", "mask fallbacks"))) + f" in {len(train)} episodes")
    q = shlex.quote(str(run_dir))
    lines += ["next:",
              f"  uabs-eval {q} --policy all   # test traces, beside the baselines, with CIs",
              f"  uabs-report {shlex.quote(str(run_dir.parent))}   # tables and figures of "
              f"the runs in that folder"]
    logger = LoggerKind(cfg.train.logger)
    if logger is LoggerKind.tensorboard:
        lines.append(f"  tensorboard --logdir {shlex.quote(str(run_dir / 'tb'))}")
    elif logger is LoggerKind.csv:
        lines.append(f"  ls {shlex.quote(str(run_dir / 'csv' / 'scalars'))}   # one CSV per "
                     f"curve")
    return "\n".join(lines)


def population_summary_text(cfg: RunConfig, summary: dict[str, Any], run_dir: Path) -> str:
    """The end of a population: one row per member (validation R at its best and last
    evaluation, served fraction and P_g at its best, training collisions), then the
    next commands."""
    nhat = cfg.scenario.nhat_s
    lines = [f"\npopulation folder: {run_dir}",
             f"  {len(summary['members'])} members x {summary['episodes']} episodes, "
             f"{summary['updates']} batched updates; this session {summary['minutes']:.1f} min",
             f"  {'member':<22} {'best R (ep)':>14} {'last R':>8} {'served':>8} "
             f"{f'P_g({nhat})':>8} {'train coll.':>11}"]
    for m in summary["members"]:
        path = Path(m["run_dir"]) / "metrics.jsonl"
        recs = read_metrics(path) if path.is_file() else []
        evals = [r for r in recs if r["kind"] == "eval"]
        coll = sum(r["collisions"] for r in recs if r["kind"] == "train")
        if evals:
            best = max(evals, key=lambda r: r["return"])
            lines.append(f"  {Path(m['run_dir']).name:<22} "
                         f"{best['return']:>8.0f} ({best['episode']:>3}) "
                         f"{evals[-1]['return']:>8.0f} {best['served_fraction']:>8.1%} "
                         f"{best['pg']:>8.1%} {coll:>11.0f}")
    q = shlex.quote(str(run_dir))
    first = shlex.quote(str(summary["members"][0]["run_dir"]))
    lines += ["next:",
              f"  uabs-eval {first} --policy all   # a member on the test traces, beside "
              f"the baselines",
              f"  uabs-report {q}   # tables and figures over the members"]
    if LoggerKind(cfg.train.logger) is LoggerKind.tensorboard:
        lines.append(f"  tensorboard --logdir {q}")
    return "\n".join(lines)


def _quote_resume(argv: list[str]) -> list[str]:
    """``resume=<dir>`` as Hydra would not parse it: a run folder named after overrides
    holds '=' and ','. Quote it, and make the resumed job log into that folder without
    writing a new .hydra/ there."""
    out = []
    for a in argv:
        if a.startswith("resume=") and a[7:] and a[7] not in "'\"":
            path = a[7:].replace("\\", "\\\\").replace("'", "\\'")
            out += [f"resume='{path}'", f"hydra.run.dir='{path}'", "hydra.output_subdir=null"]
        else:
            out.append(a)
    return out


def _run_and_report(cfg: RunConfig, run_dir: Path, overrides: list[str]) -> None:
    exp = prepare(cfg, run_dir, overrides)
    text = population_summary_text if isinstance(exp, Population) else summary_text
    print(text(exp.cfg, exp.fit(), exp.run_dir))


def main() -> None:
    """Entry point of ``uabs-train``."""
    sys.argv = [sys.argv[0], *_quote_resume(sys.argv[1:])]
    hydra_main("config", _run_and_report, pass_overrides=True)


if __name__ == "__main__":
    main()
