"""The layout of a run folder, in one place: what ``uabs-train`` writes there and where
``uabs-eval``, ``uabs-report`` and ``resume=`` look for it.

    <run>/metrics.jsonl            one JSON line per training episode and evaluation
    <run>/checkpoints/last.pt      the latest checkpoint (best.pt: the best evaluation)
    <run>/eval/                    the evaluation pictures
    <run>/tb/                      TensorBoard (train.logger picks another TorchRL logger)
    <run>/.hydra/config.yaml       the settings of record (Hydra's layout)
    <run>/run.json                 the run's identity; <run>/.lock: who writes it now
    <run>/evaluation/              uabs-eval's output
    <run>/seed=<s>/                a member of a population, laid out as a single run
    <sweep>/multirun.yaml          a sweep's record (Hydra's), beside its jobs' folders
"""

from __future__ import annotations

import signal
from pathlib import Path

CHECKPOINTS = "checkpoints"
METRICS = "metrics.jsonl"
EVAL = "eval"
TB = "tb"
HYDRA = ".hydra"
IDENTITY = "run.json"
LOCK = ".lock"
EVALUATION = "evaluation"
MULTIRUN = "multirun.yaml"
# a parallel sweep's stop file (uabs_rl.cli.parallel), in its folder while its jobs stop,
# and the environment variable that names it to a job's training
STOP_FILE = ".stopping"
STOP_ENV = "UABS_RL_SWEEP_STOP"
MEMBER_PREFIX = "seed="


class RunFolder:
    """The paths of one run folder (a single run, a population, or one member of it)."""

    def __init__(self, path: Path | str):
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"RunFolder({str(self.path)!r})"

    @property
    def checkpoints(self) -> Path:
        return self.path / CHECKPOINTS

    def checkpoint(self, name: str = "last") -> Path:
        """``checkpoints/<name>.pt`` (``last``, ``best``, or a staged ``last.staged``)."""
        return self.checkpoints / f"{name}.pt"

    @property
    def last(self) -> Path:
        return self.checkpoint("last")

    @property
    def best(self) -> Path:
        return self.checkpoint("best")

    @property
    def metrics(self) -> Path:
        return self.path / METRICS

    @property
    def eval(self) -> Path:
        return self.path / EVAL

    @property
    def tb(self) -> Path:
        return self.path / TB

    @property
    def hydra(self) -> Path:
        return self.path / HYDRA

    @property
    def hydra_config(self) -> Path:
        return self.hydra / "config.yaml"

    @property
    def identity(self) -> Path:
        return self.path / IDENTITY

    @property
    def lock(self) -> Path:
        return self.path / LOCK

    @property
    def evaluation(self) -> Path:
        return self.path / EVALUATION

    @property
    def sweep_record(self) -> Path:
        """``multirun.yaml`` of a sweep whose folder this is."""
        return self.path / MULTIRUN

    def member(self, seed: int) -> RunFolder:
        """The folder of a population's member of seed ``seed``."""
        return RunFolder(self.path / f"{MEMBER_PREFIX}{seed}")

    @property
    def is_member(self) -> bool:
        """Named as a population's member (``seed=<s>``)."""
        return self.path.name.startswith(MEMBER_PREFIX)

    def members(self) -> list[Path]:
        """A population's member folders by seed (``seed=<s>``), or this folder alone
        when it holds none (a single run): the runs a benchmark flies."""
        found = sorted(self.path.glob(f"{MEMBER_PREFIX}*"),
                       key=lambda p: int(p.name[len(MEMBER_PREFIX):]))
        return found or [self.path]

    def member_checkpoints(self, name: str = "last") -> list[Path]:
        """Every member's ``checkpoints/<name>.pt`` that exists, by path."""
        return sorted(self.path.glob(f"{MEMBER_PREFIX}*/{CHECKPOINTS}/{name}.pt"))


def run_of_checkpoint(ckpt: Path) -> Path | None:
    """The run folder a checkpoint file lies in (``<run>/checkpoints/x.pt``), else None."""
    return ckpt.parent.parent if ckpt.parent.name == CHECKPOINTS else None


def stop_signal(stop: Path) -> int | None:
    """The signal a parallel sweep's stop file holds (``STOP_FILE``; SIGINT if its text
    is not a number); None while there is no such file."""
    try:
        text = stop.read_text().strip()
    except FileNotFoundError:
        return None
    except OSError:  # there, but unreadable: the sweep stopped all the same
        text = ""
    return int(text) if text.isdigit() else int(signal.SIGINT)
