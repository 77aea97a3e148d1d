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
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from uabs_rl.checkpoint import load_checkpoint
from uabs_rl.cli import hydra_main
from uabs_rl.config import ConfigError, RunConfig
from uabs_rl.experiment import Experiment

log = logging.getLogger(__name__)


def run(cfg: RunConfig, run_dir: Path) -> dict[str, Any]:
    """Train (or resume) one run; the Hydra entry point's body."""
    if cfg.resume:
        run_dir = Path(cfg.resume)
        exp = Experiment(cfg, run_dir)
        source = run_dir / "checkpoints" / "last.pt"
        exp.load_state_dict(load_checkpoint(source), source)
        log.info("resuming %s at episode %d", run_dir, exp.episode)
    else:
        if (Path(run_dir) / "metrics.jsonl").exists():
            raise ConfigError(f"{run_dir} already holds a run (metrics.jsonl): continue it "
                              f"with resume={run_dir}, or choose another hydra.run.dir.")
        exp = Experiment(cfg, run_dir)
    return exp.fit()


def main() -> None:
    """Entry point of ``uabs-train``."""
    hydra_main("config", run)


if __name__ == "__main__":
    main()
