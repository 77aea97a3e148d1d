"""``uabs-train``: 3DQN training with periodic held-out evaluation (SPEC §7, §8).

    uabs-train                                    # paper protocol, masking=rank
    uabs-train masking=flat seed=3
    uabs-train -m masking=penalty,flat,rank seed=0,1,2
    uabs-train experiment=smoke                   # the whole pipeline in seconds
    uabs-train resume=outputs/runs/<run dir>      # continue a stopped run

Every run writes under its Hydra output directory: ``metrics.jsonl`` (one line per
training episode and per evaluation), ``tb/`` (TensorBoard), ``checkpoints/last.pt``
and ``checkpoints/best.pt`` (by evaluation return), ``eval/*.png``. The run itself is
:class:`uabs_rl.experiment.Experiment`.

``resume=<run dir>`` takes the run's own configuration (from its last checkpoint, or
from its ``.hydra/config.yaml`` if it stopped before one) and writes into that folder;
overrides typed beside it may change only what does not change results
(``train.episodes``, ``device``, ``train.progress``, ...).
"""

from __future__ import annotations

import logging
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
)
from uabs_rl.cli import hydra_main
from uabs_rl.config import ConfigError, RunConfig, to_container
from uabs_rl.experiment import Experiment

log = logging.getLogger(__name__)


def saved_config(run_dir: Path) -> tuple[RunConfig, dict | None]:
    """The configuration a run was started with, and its last checkpoint if it has one."""
    ckpt = run_dir / "checkpoints" / "last.pt"
    if ckpt.is_file():
        state = load_checkpoint(ckpt)
        return config_from_checkpoint(state), state
    hydra_cfg = run_dir / ".hydra" / "config.yaml"
    if not hydra_cfg.is_file():
        raise CheckpointError(f"resume={run_dir}: no checkpoints/last.pt and no "
                              f".hydra/config.yaml there: pass the folder of a uabs-train "
                              f"run (the one printed when it started).")
    merged = OmegaConf.merge(OmegaConf.structured(RunConfig), OmegaConf.load(hydra_cfg))
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


def run(cfg: RunConfig, run_dir: Path, overrides: list[str] | None = None) -> dict[str, Any]:
    """Train (or resume) one run; the Hydra entry point's body. With ``resume`` and
    ``overrides`` (the command line's), the run's own config is used."""
    if not cfg.resume:
        if (Path(run_dir) / "metrics.jsonl").exists():
            raise ConfigError(f"{run_dir} already holds a run (metrics.jsonl): continue it "
                              f"with resume={run_dir}, or choose another hydra.run.dir.")
        return Experiment(cfg, run_dir).fit()
    run_dir = Path(cfg.resume)
    if run_dir.suffix == ".pt" or run_dir.is_file():
        raise ConfigError(f"resume={cfg.resume} is a file: pass the run folder that holds "
                          f"checkpoints/last.pt, e.g. resume={run_dir.parent.parent}.")
    saved, state = saved_config(run_dir)
    if overrides is not None:
        cfg = resumed_config(saved, overrides)
    exp = Experiment(cfg, run_dir)
    if state is None:  # stopped before its first checkpoint: start it again, in place
        log.info("%s has no checkpoint yet: starting it again from episode 0", run_dir)
        exp.log.truncate(0)
    else:
        exp.load_state_dict(state, run_dir / "checkpoints" / "last.pt")
        log.info("resuming %s at episode %d", run_dir, exp.episode)
    return exp.fit()


def print_summary(summary: dict[str, Any], run_dir: Path) -> None:
    """The end of a run: where it is, its headline figures, and what to run next."""
    print(f"\nrun folder: {run_dir}\n"
          f"  episodes {summary['episodes']}, updates {summary['updates']}, "
          f"{summary['minutes']:.1f} min\n"
          f"  validation return: best {summary['best_eval_return']:.0f}, last "
          f"{summary['last_eval_return']:.0f}\n"
          f"next:\n"
          f"  uabs-eval {run_dir} --policy all   # test-set figures beside the baselines\n"
          f"  tensorboard --logdir {run_dir / 'tb'}\n"
          f"  uabs-report {run_dir.parent}   # tables and figures of a sweep's runs")


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
    summary = run(cfg, run_dir, overrides)
    print_summary(summary, Path(cfg.resume) if cfg.resume else run_dir)


def main() -> None:
    """Entry point of ``uabs-train``."""
    sys.argv = [sys.argv[0], *_quote_resume(sys.argv[1:])]
    hydra_main("config", _run_and_report, pass_overrides=True)


if __name__ == "__main__":
    main()
