"""A learner's whole update as one compiled program (``train.compile_update``).

An update is: the loss of a replay batch, its gradient, the optional gradient clipping,
and Adam's step over every parameter. Eager, that is a hundred small kernels (each dense
layer's product, bias, ReLU, their backward, the dueling head, the masked argmax, the
gathers, the Huber loss, the autograd engine's bookkeeping, Adam's Python), most of them
tens of microseconds on 128 x 256 matrices. :class:`UpdateProgram` traces the same
update once through ``torch.compile`` (Inductor, whole graph, static shapes: a replay
batch has the same shapes at every update): the gradient by ``torch.func.grad`` of the
learner's own loss module (called through ``torch.func.functional_call`` on the modules
that hold the trained parameters), then Adam's arithmetic written out, so the matrix
products stay library calls and everything between them becomes a few fused C++ loops,
with one Python call per update.

It serves every learner built on :class:`~uabs_rl.algorithms.dqn3.DQN3` (the 3DQN, VDN,
QMIX), a single run and a population (the stacked members' batched products; QMIX's
per-member mixer optimisers), uniform and prioritized replay (the TD errors come out of
the program), with or without ``algo.grad_clip``. State stays where eager training keeps
it: the parameters are updated in place, Adam's moments and step counts live in the
optimisers' own ``state`` (initialised as ``torch.optim.Adam`` initialises them), so
checkpoints, resume and ``load_state_dict`` are unchanged and a run can switch between
compiled and eager updates at any checkpoint. ``p.grad`` is not written.

Adam is the update ``torch.optim.Adam(fused=True)`` computes (betas, eps and lr read
from the optimiser when the program is built; weight decay, AMSGrad, ``maximize`` and
the other options are not covered: such an optimiser keeps the eager update). The
program runs with denormal floats flushed (:func:`~uabs_rl.algorithms.base.flush_denormals`),
as eager training runs Adam: Adam's moments of dead ReLU units decay into the denormal
range, where the CPU computes many times slower.

Compiled and eager updates agree to float32 rounding, not bit for bit (the fused loops
add in another order; Adam's bias corrections are computed in float64 from the float32
step as the fused kernel does): ``tests/test_compiled_update.py`` bounds the difference
and checks that a compiled run learns within the eager runs' seed spread. A failure to
compile (no C++ compiler, an unsupported op) falls back to the eager update with one
warning, as the env step's compilation does (:func:`~uabs_rl.env._compile.compiled_or_eager`).
The program is compiled ahead of its calls and called without Dynamo's per-call guard
evaluation (:class:`~uabs_rl.env._compile.AheadOfTime`); each change of torch's thread
count or of the batch's fields compiles it again once.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict
from torch import nn

from uabs_rl.algorithms.base import flush_denormals
from uabs_rl.env._compile import AheadOfTime, compile_options, signature

log = logging.getLogger(__name__)

# (loss [] or [P], mean chosen Q, |TD error| of a prioritized sample or None)
LossOutputs = tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]
# the gradients of the trained parameters (in the optimisers' order) -> clipped ones
Clip = Callable[[list[torch.Tensor]], list[torch.Tensor]]


def outputs(out: TensorDict) -> LossOutputs:
    return out.get("loss"), out.get("q_chosen"), out.get("td_error", None)


class LossProgram:
    """The eager loss of ``loss_module`` on a batch and its backward pass: :meth:`__call__`
    sets the parameters' gradients (after ``zero_grad``) and returns the loss module's
    outputs. The eager update steps the optimisers on these gradients."""

    def __init__(self, loss_module: Callable[[TensorDict], TensorDict]):
        self.loss_module = loss_module

    def __call__(self, batch: TensorDict, zero_grad: Callable[[], None]) -> LossOutputs:
        loss, q_chosen, td_error = outputs(self.loss_module(batch))
        zero_grad()
        (loss if loss.dim() == 0 else loss.sum()).backward()
        return loss, q_chosen, td_error


def covered(optim: torch.optim.Optimizer) -> str | None:
    """Why ``optim`` is not an Adam the compiled program computes, or None if it is."""
    if type(optim) is not torch.optim.Adam:
        return f"{type(optim).__name__} is not torch.optim.Adam"
    for group in optim.param_groups:
        for key, plain in (("weight_decay", 0), ("amsgrad", False), ("maximize", False),
                           ("differentiable", False), ("decoupled_weight_decay", False)):
            if group.get(key, plain) != plain:
                return f"Adam with {key}={group[key]}"
    return None


class _Trained(nn.Module):
    """The modules that hold the trained parameters, under one root, so that
    ``functional_call`` can put traced tensors in their place for one loss call; the
    loss module reads the same module objects."""

    def __init__(self, loss_module: nn.Module, modules: Sequence[nn.Module]):
        super().__init__()
        self.held = nn.ModuleList(modules)
        self.__dict__["loss_module"] = loss_module  # not a submodule: its names stay out

    def forward(self, batch: dict[str, torch.Tensor]) -> LossOutputs:
        return outputs(self.loss_module(TensorDict(batch, batch_size=[])))


class UpdateProgram:
    """The loss, gradient, clipping and Adam step of a learner as one compiled function
    (see the module docstring). ``modules`` hold every parameter of ``optims`` (and the
    loss module reads them); ``clip`` maps the gradients, in the optimisers' parameter
    order, to clipped ones (None: no clipping).

    :meth:`__call__` updates the parameters and the optimisers' state in place and returns
    the loss module's outputs, detached."""

    def __init__(self, loss_module: nn.Module, modules: Sequence[nn.Module],
                 optims: Sequence[torch.optim.Adam], clip: Clip | None = None,
                 device: torch.device | str = "cpu"):
        self.optims = list(optims)
        # per parameter, in the optimisers' order: it, its (β1, β2, eps), lr, optimiser
        self.params, self.hyper, self.rates, self.owner = [], [], [], []
        for i, o in enumerate(self.optims):
            for g in o.param_groups:
                for p in g["params"]:
                    self.params.append(p)
                    self.hyper.append((*map(float, g["betas"]), float(g["eps"])))
                    self.rates.append(float(g["lr"]))
                    self.owner.append(i)
        trained = _Trained(loss_module, modules)
        names = {id(p): n for n, p in trained.named_parameters()}
        missing = [i for i, p in enumerate(self.params) if id(p) not in names]
        if missing:
            raise ValueError(f"parameters {missing} of the optimisers are in none of the "
                             f"modules given to UpdateProgram")
        self.names = [names[id(p)] for p in self.params]
        # the parameters' storage without their autograd identity: the program reads them
        # as plain inputs and writes the new values into them
        self.data = [p.detach() for p in self.params]
        self.clip = clip

        def loss_of(values: list[torch.Tensor], batch: dict[str, torch.Tensor]):
            loss, q_chosen, td_error = torch.func.functional_call(
                trained, dict(zip(self.names, values, strict=True)), (batch,))
            total = loss if loss.dim() == 0 else loss.sum()  # members' grads are apart
            aux = [loss.detach(), q_chosen.detach()]  # (the aux holds tensors only)
            if td_error is not None:
                aux.append(td_error.detach())
            return total, aux

        gradient = torch.func.grad(loss_of, has_aux=True)

        def update(values, avgs, sqs, steps, corrections, batch):
            grads, aux = gradient(values, batch)
            if self.clip is not None:
                grads = self.clip(grads)
            for p, g, m, v, step, hyper, c in zip(values, grads, avgs, sqs, steps, self.hyper,
                                                  corrections, strict=True):
                adam_(p, g, m, v, step, *hyper, *c)
            return (*aux, None) if len(aux) == 2 else tuple(aux)

        compiled = torch.compile(update, fullgraph=True, dynamic=False,
                                 options=compile_options(device))
        # compiled ahead per thread count and batch signature, called without Dynamo's
        # per-call guards: their ~1 300 checks (the modules the loss reads, every
        # tensor's shape and aliasing) took 0.2-0.4 ms a call, a tenth of the update, and
        # what they check cannot change between two calls with the same key: the
        # parameters, moments and step counts are the same tensors, updated in place (or
        # replaced by ``load_state_dict`` with tensors of their parameters' layout), the
        # settings are fixed when the program is built
        def key(args: tuple) -> tuple:
            return torch.get_num_threads(), signature(args[-1])

        checked = None  # where it is not: the key of the last fully guarded Dynamo call

        def guarded_once(*args):
            nonlocal checked
            k = key(args)
            if k == checked:
                with torch.compiler.set_stance(skip_guard_eval_unsafe=True):
                    return compiled(*args)
            out = compiled(*args)
            checked = k
            return out

        self.compiled = AheadOfTime(compiled, guarded_once, "the update", key=key)

    def state(self) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
        """Adam's moments and step counts of every parameter, from the optimisers' own
        state (initialised as ``torch.optim.Adam(fused=True)`` does at its first step;
        read at every call, since ``load_state_dict`` replaces them)."""
        avgs, sqs, steps = [], [], []
        for o in self.optims:
            for p in (p for g in o.param_groups for p in g["params"]):
                st = o.state[p]
                if not st:
                    st["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                    st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                avgs.append(st["exp_avg"])
                sqs.append(st["exp_avg_sq"])
                steps.append(st["step"])
        return avgs, sqs, steps

    def corrections(self, steps: list[torch.Tensor]) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Each parameter's Adam step size lr / (1 − β1^t) and sqrt(1 − β2^t) at this
        update's step t, as 0-d float64 tensors on its device (computed here, once per
        update: written in the program, Inductor would compute the powers again for every
        8 elements of the parameter, a third of the update's time). An optimiser steps
        all its parameters together, so t is read once per optimiser."""
        out, memo, counts = [], {}, {}
        for step, owner, lr, (beta1, beta2, _) in zip(steps, self.owner, self.rates,
                                                       self.hyper, strict=True):
            if owner not in counts:
                counts[owner] = float(step) + 1
            key = (counts[owner], lr, beta1, beta2, step.device)
            if key not in memo:
                t = key[0]
                memo[key] = tuple(torch.tensor(x, dtype=torch.float64, device=step.device)
                                  for x in (lr / (1 - beta1 ** t), math.sqrt(1 - beta2 ** t)))
            out.append(memo[key])
        return out

    def __call__(self, batch: TensorDict) -> LossOutputs:
        avgs, sqs, steps = self.state()
        with flush_denormals():
            return self.compiled(self.data, avgs, sqs, steps, self.corrections(steps),
                                 dict(batch.items()))


def adam_(p: torch.Tensor, g: torch.Tensor, m: torch.Tensor, v: torch.Tensor,
          step: torch.Tensor, beta1: float, beta2: float, eps: float,
          step_size: torch.Tensor, bias2_sqrt: torch.Tensor) -> None:
    """One Adam step of ``p`` in place (moments ``m``, ``v`` and ``step`` too), as
    ``torch.optim.Adam(fused=True)``'s CPU kernel computes it: m = lerp(m, g, 1 − β1),
    v = β2 v + (1 − β2) g², p −= step_size · m / (sqrt(v) / bias2_sqrt + eps), with
    step_size = lr / (1 − β1^t) and bias2_sqrt = sqrt(1 − β2^t) in float64 at the
    incremented step t (:meth:`UpdateProgram.corrections`)."""
    step.add_(1)
    m.lerp_(g, 1 - beta1)
    v.mul_(beta2).addcmul_(g, g, value=1 - beta2)
    denom = v.sqrt() / bias2_sqrt.float() + eps
    p.sub_(step_size.float() * m / denom)
