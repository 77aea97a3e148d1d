"""The learner's loss and its backward as one compiled program (``train.compile_update``).

:class:`LossProgram` runs a learner's loss module on a replay batch and back-propagates
it. Compiled, the loss goes through ``torch.compile`` (Inductor, whole graph, static
shapes: a replay batch has the same shapes at every update) and AOTAutograd compiles
its backward with it: the forward's bias adds, ReLUs, dueling head, masked argmax,
gathers and Huber loss become a few fused C++ loops around the matrix products, and the
backward likewise. The same program serves the 3DQN, VDN and QMIX, a single run and a
population (the stacked members' batched products): each loss module traces as one
graph, TensorDict batch included. Adam stays outside: it is already one fused kernel,
and ``torch.compile(optim.step)`` measured no faster (see below), so the denormal
flushing around it (:func:`~uabs_rl.algorithms.base.flush_denormals`) stays as it is.

What it gains, measured on the 2-core development CPU while other processes kept it
busy (ratios of runs in turns; absolute times there mean little):
``benchmarks/train_bench.py --update train.threads=1`` put a paper-network update at
0.91x the eager one's time (0.74x to 0.92x over several such runs; a population of three
0.88x), and a compiled ``optim.step`` on top at 0.99x eager's fused step, so Adam stays
eager. The update's matrix products are most of its arithmetic and stay the same
library calls, so the gain is in the elementwise work and the kernels around them.

Over a whole run the one-off compile (forward and backward graphs: 10 to 60 s with an
empty Inductor cache, the more the busier the machine) weighs against about 0.1 ms
saved per update, and torch.compile compiles again whenever the thread count changes
(its guards include it): once per change of the thread governor's count
(:mod:`uabs_rl.training.threads`) beside busy CPUs, as for the env step. Two
100-episode runs of the paper protocol (7666 updates, an empty cache each), in turns
with eager ones on the busy machine, each with one change of threads, took 1.05x the
eager runs' CPU time (the training process's; the compile workers' not counted) and
1.45x to 1.85x their wall time (other processes' load drifted between the runs). At a
steady thread count the main job (80 000 updates) would save about what one compile
costs. Hence ``train.compile_update=false`` by default, which also keeps the default's
results bit for bit.

Compiled and eager updates agree to float32 rounding, not bit for bit (the fused loops
add in another order): ``tests/test_compiled_update.py`` bounds the difference. A
failure to compile (no C++ compiler, an unsupported op) falls back to the eager loss
with a warning, as the env step's compilation does
(:func:`~uabs_rl.env._compile.compiled_or_eager`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import torch
from tensordict import TensorDict
from torch import nn

log = logging.getLogger(__name__)

# (loss [] or [P], mean chosen Q, |TD error| of a prioritized sample or None)
LossOutputs = tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]


def outputs(out: TensorDict) -> LossOutputs:
    return out.get("loss"), out.get("q_chosen"), out.get("td_error", None)


def compiled_loss(loss_module: nn.Module,
                  device: torch.device | str) -> Callable[[TensorDict], LossOutputs]:
    """``loss_module`` through ``torch.compile``. The compiled function takes the batch
    as a plain dict of tensors, because compiled code is reused only where the dict's
    keys are the same (a prioritized sample adds ``weight`` and ``index``), which a
    TensorDict's contents are not guarded on."""

    def run(batch: dict[str, torch.Tensor]) -> LossOutputs:
        return outputs(loss_module(TensorDict(batch, batch_size=[])))

    # Inductor's C++ wrapper on CPU, as for the env step (less Python per call)
    options = {"cpp_wrapper": True} if torch.device(device).type == "cpu" else None
    compiled = torch.compile(run, fullgraph=True, dynamic=False, options=options)
    return lambda batch: compiled(dict(batch.items()))


class LossProgram:
    """The loss of ``loss_module`` on a batch and its backward pass, eager or compiled
    (``compile``). :meth:`__call__` sets the parameters' gradients (after ``zero_grad``)
    and returns the loss module's outputs."""

    def __init__(self, loss_module: nn.Module, compile: bool = False,
                 device: torch.device | str = "cpu"):
        self.eager = lambda batch: outputs(loss_module(batch))
        self.compiled = compile
        self.run = compiled_loss(loss_module, device) if compile else self.eager

    def __call__(self, batch: TensorDict, zero_grad: Callable[[], None]) -> LossOutputs:
        try:
            return self.step(self.run, batch, zero_grad)
        except Exception as e:  # compilation errors surface at the first calls
            if not self.compiled:
                raise
            log.warning("torch.compile failed for the update (%s: %s); running it "
                        "eagerly. Set train.compile_update=false to skip compiling it.",
                        type(e).__name__, str(e).splitlines()[0][:200] if str(e) else "")
            self.run, self.compiled = self.eager, False
            return self.step(self.run, batch, zero_grad)

    @staticmethod
    def step(run: Callable[[TensorDict], LossOutputs], batch: TensorDict,
             zero_grad: Callable[[], None]) -> LossOutputs:
        loss, q_chosen, td_error = run(batch)
        zero_grad()
        (loss if loss.dim() == 0 else loss.sum()).backward()
        return loss, q_chosen, td_error
