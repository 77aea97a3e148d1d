"""The interface between the trainer and a learner (an algorithm), and its registry.

An :class:`Algorithm` supplies, for the P >= 1 members of a run (P = 1 a single run,
P > 1 a population, ``train.population``):

* ``policy``: the network the masked ε-greedy selector and the greedy evaluation act
  with, ``[rows, M, obs_dim] -> [rows, M, n_actions]`` action values (member ``p``'s
  rows are block ``p`` of the env's rows);
* ``loss_module``: its loss, a TorchRL :class:`~torchrl.objectives.LossModule` taking
  the TensorDict batches its replay samples;
* ``buffer``: its replay, with TorchRL's ``ReplayBuffer`` API
  (:class:`~uabs_rl.algorithms.replay.TransitionReplay`);
* ``target_updater``: TorchRL's target-network updater over ``loss_module``;
* :meth:`update`: one gradient step on a sampled batch;
* its checkpoint state per member (:meth:`member_state_dict`, :meth:`load_member`), in
  the format of a single run, so a member's checkpoint is a run's checkpoint.

The trainer (:class:`uabs_rl.training.experiment.Experiment`, one class for any P) owns
the env, the masking rule's selector, collection, evaluation, checkpoints and logs, and
talks to learners through this interface only. A new learner is one module that subclasses
:class:`Algorithm` with ``@register``, and one ``conf/algo/<name>.yaml`` (see
docs/code.md, "Adding an algorithm").
"""

from __future__ import annotations

import contextlib
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import nn
from torchrl.objectives import HardUpdate

from uabs_rl.config import AlgoConfig, ConfigError, check_algo_schema


@dataclass(frozen=True)
class Dims:
    """The sizes a learner is built for: observation, actions, agents."""

    obs_dim: int
    n_actions: int
    n_agents: int


@dataclass(frozen=True)
class NetworkSize:
    """The acting network's size: its parameters' bytes, and the multiply-adds of its
    forward pass for one row (one agent's observation)."""

    parameter_bytes: int
    multiply_adds: int


class PeriodicHardUpdate(HardUpdate):
    """TorchRL's :class:`~torchrl.objectives.HardUpdate` that copies the online
    parameters into the target every ``every`` calls of :meth:`step` (the first copy at
    call ``every``), and does nothing else on the other calls. ``HardUpdate`` walks
    every parameter pair on every call (50 µs for the paper's network, measured on the
    development CPU: 3 % of a training step) and copies on call ``interval + 1``."""

    def __init__(self, loss_module, every: int):
        super().__init__(loss_module, value_network_update_interval=every - 1)

    def step(self) -> None:
        if self.counter == self.value_network_update_interval:
            super().step()  # copies, then restarts the count
        else:
            self.counter += 1

    def set_calls(self, calls: int) -> None:
        """The count after ``calls`` calls since the start (a resumed run)."""
        self.counter = calls % (self.value_network_update_interval + 1)


@contextlib.contextmanager
def flush_denormals():
    """Denormal floats read and written as zero inside the block (``torch.set_flush_denormal``).

    Around Adam's step: a unit whose ReLU stays off gets exactly zero gradients, so its
    Adam moments decay geometrically into the denormal range (below 1.2e-38), where the
    CPU computes them many times slower. Measured on the 2-core development CPU
    (``benchmarks/denormal_bench.py``), one fused Adam step over the paper's network
    with a quarter of its moments denormal took 1.7 ms against 0.13 ms flushed (5.0 ms
    against 0.27 ms for a population of three), and the main job ends with 23 % of its
    moments denormal; its full run took 5.4 min instead of 5.8 min, side by side, with
    a byte-identical ``metrics.jsonl``. Flushing changes the moments of dead units (0
    instead of about 1e-39), not the parameters: such a moment moves a weight by at most
    lr x 1.2e-38 / eps ~ 1e-34, far below the rounding step of any weight above 1e-26,
    so the parameters, and everything computed from them, stay bit for bit the same
    (``tests/test_algorithms.py``)."""
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)


class Algorithm(ABC):
    """A learner for P members with seeds ``seeds`` (see the module docstring)."""

    name: ClassVar[str]
    acting_key: ClassVar[str]  # the learner-state entry that holds the acting network
    policy: nn.Module
    buffer: object  # TransitionReplay
    updates: int  # gradient steps so far (every member steps together)
    # a learner that imitates a planner: the horizon of the clairvoyant planner that
    # labels its training states (uabs_rl.training.teacher; algo=dqfd); None: no teacher
    teacher_horizon: int | None = None

    def __init__(self, algo: AlgoConfig, dims: Dims, seeds: list[int],
                 device: torch.device):
        self.algo, self.dims, self.seeds, self.device = algo, dims, list(seeds), device
        self.members = len(self.seeds)
        self.updates = 0

    @abstractmethod
    def update(self, batch) -> tuple[torch.Tensor, torch.Tensor]:
        """One gradient step on ``batch`` (a :meth:`buffer` sample); returns (loss, mean
        chosen Q) as tensors, 0-d for a single run, ``[P]`` for a population, without a
        device sync."""

    def compile_update(self, compile: bool = True) -> None:
        """Run :meth:`update` through ``torch.compile`` where the learner has a compiled
        path (``train.compile_update``), eager otherwise; the default has none."""
        return None

    @abstractmethod
    def member_state_dict(self, p: int) -> dict:
        """Member ``p``'s learner state (networks, optimiser, counters) as a single run's."""

    @abstractmethod
    def load_member(self, p: int, state: dict) -> None:
        """Set member ``p`` from :meth:`member_state_dict`'s format."""

    @classmethod
    @abstractmethod
    def acting_network(cls, algo: AlgoConfig, dims: Dims) -> nn.Module:
        """A single run's acting network, freshly built: ``uabs-eval`` loads the learner
        state's ``acting_key`` entry into it and flies it."""

    @classmethod
    def network_size(cls, algo: AlgoConfig, dims: Dims) -> NetworkSize:
        """:meth:`acting_network`'s size, built on the meta device (shapes only): its
        affine layers' weights are the multiply-adds of one row."""
        with torch.device("meta"):
            net = cls.acting_network(algo, dims)
        return NetworkSize(
            sum(p.numel() * p.element_size() for p in net.parameters()),
            sum(m.weight.numel() for m in net.modules() if isinstance(m, nn.Linear)))

    @classmethod
    def network_bytes(cls, algo: AlgoConfig, dims: Dims) -> int:
        """One member's acting network in training: its parameters, the target copy,
        the gradients and Adam's two moments."""
        return 5 * cls.network_size(algo, dims).parameter_bytes

    @classmethod
    def check_config(cls, algo: AlgoConfig) -> None:
        """Refuse, with a :class:`ConfigError` naming the key, ``algo`` settings this
        algorithm cannot honour (checked at start-up, before anything is built). The
        default accepts every setting."""
        return None

    def state_dict(self) -> dict:
        return self.member_state_dict(0)

    def load_state_dict(self, state: dict) -> None:
        self.load_member(0, state)


ALGORITHMS: dict[str, type[Algorithm]] = {}


def register(cls: type[Algorithm]) -> type[Algorithm]:
    """Class decorator: make ``cls`` the algorithm ``algo.name = cls.name``."""
    ALGORITHMS[cls.name] = cls
    return cls


def algorithm_class(name: str) -> type[Algorithm]:
    if name not in ALGORITHMS:
        raise ConfigError(f"algo.name={name!r} is not a registered algorithm; choose one of "
                          f"{', '.join(sorted(ALGORITHMS))} (algo=<name>; uabs_rl.algorithms).")
    return ALGORITHMS[name]


def make_algorithm(algo: AlgoConfig, dims: Dims, seeds: list[int],
                   device: torch.device) -> Algorithm:
    """The algorithm ``algo.name`` for members of seeds ``seeds`` (``algo`` of its own
    schema: :func:`uabs_rl.config.algo_schema`)."""
    cls = algorithm_class(algo.name)
    check_algo_schema(algo)
    return cls(algo, dims, seeds, device)
