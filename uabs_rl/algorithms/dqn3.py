"""3DQN (``algo=dqn3``): the paper's shared double dueling DQN (docs/model.md §7).

One dueling Q-network shared by every agent; each agent's step is one transition of a
shared replay (``unit="agent"``); the double-DQN target maximises over the target mask
at o'; a target network copied every ``algo.target_update`` updates; Huber loss; Adam.
A population (P members) stacks the members' networks (:class:`StackedQNet`) and steps
them in one batched update with one fused Adam; each member's state is saved in a single
run's format.

Two implementations of the same loss, selected by ``algo.loss``:

* ``fused`` (default, :class:`DQN3Loss`): plain tensors: online net on o (with gradient)
  and on o' (without), target net on o', Huber loss.
* ``torchrl`` (:class:`TorchRLDQN3Loss`): TorchRL's ``DQNLoss(double_dqn=True)`` over the
  same batch, kept as the tested reference (single runs only).

Why a hand-written loss: measured on the 2-core development CPU (batch 128 × 3 agents,
2 × 256 MLP), one update takes 6.9 ms fused against 13.9 ms with ``DQNLoss``, which
builds TensorDicts, runs the value network through functional calls and masks via
``QValueModule`` on every call. ``tests/test_algorithms.py`` checks that both give the
same loss and gradients.
"""

from __future__ import annotations

import copy
import logging
import warnings

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictParams
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.modules import QValueModule
from torchrl.objectives import DQNLoss, LossModule

from uabs_rl.algorithms.base import (
    Algorithm,
    Dims,
    PeriodicHardUpdate,
    flush_denormals,
    register,
)
from uabs_rl.algorithms.compiled_update import LossProgram, UpdateProgram, covered
from uabs_rl.algorithms.model import DuelingQNet, StackedQNet
from uabs_rl.algorithms.replay import TransitionReplay
from uabs_rl.config import AlgoConfig, ConfigError, LossKind, ReplayKind

TARGET_WARNING = "No target network updater has been associated"
log = logging.getLogger(__name__)


def huber(pred: torch.Tensor, y: torch.Tensor,
          weight: torch.Tensor | None = None) -> torch.Tensor:
    """The mean Huber loss over the last dim: 0-d for ``[B]``, one per member for ``[P, B]``;
    with ``weight`` (a prioritized sample's importance weights) the weighted mean."""
    if weight is not None:
        return (weight * F.smooth_l1_loss(pred, y, reduction="none")).mean(-1)
    if pred.dim() == 1:
        return F.smooth_l1_loss(pred, y)
    return F.smooth_l1_loss(pred, y, reduction="none").mean(-1)


class DQN3Loss(LossModule):
    """Huber(Q(o, a), r + γ (1 − terminated) Q_target(o', argmax_{a' ∈ mask'} Q(o', a')))
    on batches of agent transitions ``[B, ...]`` (a population's ``[P, B, ...]``, one
    loss per member ``[P]``); ``gamma`` is γ^n with n-step returns. The target network
    reads ``target_value_network_params``, which TorchRL's target updaters write."""

    value_network: nn.Module
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams

    def __init__(self, qnet: nn.Module, gamma: float):
        super().__init__()
        self.convert_to_functional(qnet, "value_network", create_target_params=True)
        self.target_network = copy.deepcopy(qnet)
        with warnings.catch_warnings():  # read before the algorithm attaches its updater
            warnings.filterwarnings("ignore", message=TARGET_WARNING)
            self.target_value_network_params.to_module(self.target_network)  # shares them
        self.gamma = gamma

    def forward(self, b: TensorDict) -> TensorDict:
        return self.td_outputs(*self.agent_values(b), b)

    def td_outputs(self, q_taken: torch.Tensor, q_next: torch.Tensor,
                   b: TensorDict) -> TensorDict:
        """:meth:`outputs` of the TD loss of ``q_taken`` against the target
        r + γ (1 − terminated) ``q_next``."""
        with torch.no_grad():
            y = b.get("reward") + self.gamma * (~b.get("terminated")).float() * q_next
        return self.outputs(q_taken, y, b, q_taken.detach().mean(-1))

    @staticmethod
    def outputs(pred: torch.Tensor, y: torch.Tensor, b: TensorDict,
                q_chosen: torch.Tensor) -> TensorDict:
        """``loss`` (Huber of ``pred`` against ``y``, weighted when the sample is
        prioritized), ``q_chosen``, and for a prioritized sample ``td_error`` |pred − y|,
        the sampled items' new priorities."""
        weight = b.get("weight", None)
        out = {"loss": huber(pred, y, weight), "q_chosen": q_chosen}
        if weight is not None:
            out["td_error"] = (pred.detach() - y).abs()
        return TensorDict(out, batch_size=[])

    def agent_values(self, b: TensorDict) -> tuple[torch.Tensor, torch.Tensor]:
        """Q(o, a) (with gradient) and Q_target(o', argmax_{a' ∈ mask'} Q(o', a')) (without),
        per transition: the fields' shape without the feature dim."""
        q_taken = self.value_network(b.get("obs")).gather(
            -1, b.get("action")[..., None]).squeeze(-1)
        return q_taken, self.next_values(b)

    @torch.no_grad()  # o' outside the graph: the backward pass covers o only
    def next_values(self, b: TensorDict) -> torch.Tensor:
        """Q_target(o', argmax_{a' ∈ mask'} Q(o', a')) per transition, without gradient."""
        next_obs = b.get("next_obs")
        best = self.value_network(next_obs).masked_fill(
            ~b.get("next_mask"), -torch.inf).argmax(-1, keepdim=True)
        return self.target_network(next_obs).gather(-1, best).squeeze(-1)

    def target_state(self, member: int | None = None) -> dict[str, torch.Tensor]:
        """The target network's state dict, or member ``member``'s of a population."""
        if member is None:
            return self.target_network.state_dict()
        return self.target_network.member_state_dict(member)

    def load_target_state(self, state: dict, member: int | None = None) -> None:
        if member is None:
            self.target_network.load_state_dict(state)
        else:
            self.target_network.load_member(member, state)


def value_network(qnet: DuelingQNet) -> TensorDictSequential:
    """``qnet`` as TorchRL's Q-value actor on flat per-agent batches, masked by
    ``action_mask``."""
    return TensorDictSequential(
        TensorDictModule(qnet, in_keys=["observation"], out_keys=["action_value"]),
        QValueModule(action_space="categorical", action_mask_key="action_mask"))


def batch_to_td(b: TensorDict) -> TensorDict:
    """A batch of agent transitions in the keys of TorchRL's losses."""
    n = b.get("obs").shape[0]
    done = b.get("terminated")[:, None]
    return TensorDict({
        "observation": b.get("obs"), "action": b.get("action"), "action_mask": b.get("mask"),
        "next": {"observation": b.get("next_obs"), "action_mask": b.get("next_mask"),
                 "reward": b.get("reward")[:, None], "done": done, "terminated": done},
    }, batch_size=[n])


class TorchRLDQN3Loss(DQNLoss):
    """TorchRL's double-DQN loss on the batches of :class:`DQN3Loss` (single runs)."""

    def __init__(self, qnet: DuelingQNet, gamma: float):
        super().__init__(value_network(qnet), action_space="categorical", double_dqn=True,
                         delay_value=True, loss_function="smooth_l1")
        self.make_value_estimator(gamma=gamma)
        self.qnet = qnet
        # the parameters' keys in the loss's layout, by the net's own names
        names = {p.data_ptr(): k for k, p in qnet.named_parameters()}
        self.names = {k: names[v.data_ptr()] for k, v in
                      self.value_network_params.flatten_keys(".").items(True, True)}

    def forward(self, b: TensorDict) -> TensorDict:
        loss = super().forward(batch_to_td(b))["loss"]
        with torch.no_grad():
            q_taken = self.qnet(b.get("obs")).gather(1, b.get("action")[:, None]).squeeze(1)
        return TensorDict({"loss": loss, "q_chosen": q_taken.mean(-1)}, batch_size=[])

    def target_state(self, member: int | None = None) -> dict[str, torch.Tensor]:
        flat = self.target_value_network_params.flatten_keys(".")
        return {self.names[k]: flat.get(k).detach().clone() for k in self.names}

    def load_target_state(self, state: dict, member: int | None = None) -> None:
        flat = self.target_value_network_params.flatten_keys(".")
        for k, name in self.names.items():
            flat.get(k).data.copy_(state[name])


@register
class DQN3(Algorithm):
    """The 3DQN of the paper for P >= 1 members (see the module docstring)."""

    name = "dqn3"
    acting_key = "qnet"
    unit = "agent"  # its replay samples per-agent transitions

    def __init__(self, algo: AlgoConfig, dims: Dims, seeds: list[int], device: torch.device):
        super().__init__(algo, dims, seeds, device)
        nets, self.extras = [], []
        for s in self.seeds:  # each member's initial network is its single run's
            torch.manual_seed(s)
            nets.append(self.acting_network(algo, dims))
            self.extras.append(self.member_extra())
        self.policy = (nets[0] if self.members == 1 else StackedQNet(nets)).to(device)
        gamma = float(algo.gamma) ** algo.n_step  # bootstraps n steps on
        self.loss_module = self.make_loss(gamma)
        self.target_updater = PeriodicHardUpdate(self.loss_module, int(algo.target_update))
        # fused Adam: one kernel for all parameters (3x faster than foreach on CPU here)
        self.optim = torch.optim.Adam(self.policy.parameters(), lr=algo.lr, fused=True)
        self.optims = [self.optim]  # every optimiser an update steps
        self.program = LossProgram(self.loss_module)  # the eager loss and backward
        self.whole: UpdateProgram | None = None  # the compiled update (compile_update)
        prioritized = algo.replay == ReplayKind.prioritized
        self.buffer = TransitionReplay(algo.buffer_size, dims.obs_dim, dims.n_actions,
                                       dims.n_agents, self.seeds, self.sample_size(),
                                       unit=self.unit, device=device,
                                       priority_alpha=algo.priority_alpha if prioritized
                                       else None, priority_beta=algo.priority_beta,
                                       extra=self.extra_fields())

    @classmethod
    def check_config(cls, algo: AlgoConfig) -> None:
        if algo.loss == LossKind.torchrl and algo.replay != ReplayKind.uniform:
            raise ConfigError(f"algo.replay={algo.replay} needs the fused loss (it weights "
                              f"each sample); algo.loss=torchrl, the reference loss, takes "
                              f"uniform samples only: drop algo.loss.")

    def member_extra(self) -> nn.Module | None:
        """A module of each member built right after its network, from the same seeded
        draws (QMIX's mixer); the 3DQN has none."""
        return None

    def extra_fields(self) -> dict[str, tuple[tuple[int, ...], torch.dtype]]:
        """The learner's own per-agent replay fields beside the transitions' (``algo=dqfd``'s
        teacher labels); the 3DQN has none."""
        return {}

    def make_loss(self, gamma: float) -> LossModule:
        """The loss module on ``self.policy`` (``algo.loss`` picks the implementation)."""
        cls = TorchRLDQN3Loss if self.algo.loss == LossKind.torchrl else DQN3Loss
        return cls(self.policy, gamma)

    def sample_size(self) -> int:
        """Replay samples per update (``algo.batch_size`` per-agent transitions)."""
        return int(self.algo.batch_size)

    @classmethod
    def acting_network(cls, algo: AlgoConfig, dims: Dims) -> nn.Module:
        return DuelingQNet(dims.obs_dim, dims.n_actions, list(algo.hidden))

    # ------------------------------------------------------------------ update
    def loss(self, batch: TensorDict) -> tuple[torch.Tensor, torch.Tensor]:
        """(loss, mean chosen Q) of ``batch``, with gradient."""
        out = self.loss_module(batch)
        return out.get("loss"), out.get("q_chosen")

    def compile_update(self, compile: bool = True) -> None:
        """Run the whole update (loss, gradient, clipping, Adam) as one compiled program
        (``train.compile_update``; :mod:`uabs_rl.algorithms.compiled_update`), or eager
        again with ``False``. TorchRL's reference loss (``algo.loss=torchrl``) and an
        optimiser the program does not compute stay eager, said in the log."""
        self.whole = None
        if not compile:
            return
        why = ("algo.loss=torchrl is the eager reference loss"
               if self.algo.loss == LossKind.torchrl else
               next((w for w in map(covered, self.optims) if w), None))
        if why:
            log.info("the update runs eagerly: %s", why)
            return
        extras = [m for m in self.extras if m is not None]
        clip = self.clipped if self.algo.grad_clip is not None else None
        self.whole = UpdateProgram(self.loss_module, [self.policy, *extras], self.optims,
                                   clip, self.device)

    @property
    def compiled(self) -> bool:
        """Whether updates run as the compiled program (not eagerly)."""
        return self.whole is not None

    def zero_grad(self) -> None:
        for optim in self.optims:
            optim.zero_grad(set_to_none=True)

    def update(self, batch: TensorDict) -> tuple[torch.Tensor, torch.Tensor]:
        if self.whole is not None:
            try:
                loss, q_chosen, td_error = self.whole(batch)
            except Exception as e:  # compilation errors surface at the first call
                log.warning("torch.compile failed for the update (%s: %s); running it "
                            "eagerly. Set train.compile_update=false to skip compiling it.",
                            type(e).__name__,
                            str(e).splitlines()[0][:200] if str(e) else "")
                self.whole = None
                return self.update(batch)
        else:
            loss, q_chosen, td_error = self.program(batch, self.zero_grad)
            if self.algo.grad_clip is not None:
                self.clip_gradients()
            with flush_denormals():
                for optim in self.optims:
                    optim.step()
        self.updates += 1
        self.target_updater.step()
        if td_error is not None:  # a prioritized sample: its new priorities
            self.buffer.update_priority(batch.get("index"), td_error)
        return loss.detach(), q_chosen

    def clipped(self, grads: list[torch.Tensor]) -> list[torch.Tensor]:
        """:meth:`clip_gradients` as a function of the gradients (in the optimisers'
        order: the network's, then each member's extra module's), for the compiled
        update: each member's gradients scaled by max_norm / (their norm + 1e-6), at
        most 1, the norm computed as ``clip_grad_norm_`` computes it."""
        clip = float(self.algo.grad_clip)
        if self.members == 1:
            norm = torch.linalg.vector_norm(
                torch.stack([torch.linalg.vector_norm(g) for g in grads]))
            scale = (clip / (norm + 1e-6)).clamp(max=1.0)
            return [g * scale for g in grads]
        n = len(self.policy.weight) + len(self.policy.bias)
        net, rest = grads[:n], grads[n:]
        sizes = [0 if m is None else len(list(m.parameters())) for m in self.extras]
        extra, at = [], 0
        for size in sizes:
            extra.append(rest[at:at + size])
            at += size
        sq = torch.stack([g.pow(2).flatten(1).sum(1) for g in net]).sum(0)  # [P]
        if all(extra):
            sq = sq + torch.stack([torch.stack([g.pow(2).sum() for g in gs]).sum()
                                   for gs in extra])
        scale = (clip / (sq.sqrt() + 1e-6)).clamp(max=1.0)
        out = [g * scale.view(-1, *([1] * (g.dim() - 1))) for g in net]
        for p, gs in enumerate(extra):
            out += [g * scale[p] for g in gs]
        return out

    def clip_gradients(self) -> None:
        """Each member's gradient (its network's and its :meth:`member_extra`'s) clipped
        by its own norm, as ``clip_grad_norm_`` over both does in a single run."""
        extras = [[] if m is None else list(m.parameters()) for m in self.extras]
        if self.members == 1:
            torch.nn.utils.clip_grad_norm_([*self.policy.parameters(), *extras[0]],
                                           self.algo.grad_clip)
            return
        grads = [p.grad for p in self.policy.parameters()]
        sq = torch.stack([g.pow(2).flatten(1).sum(1) for g in grads]).sum(0)  # [P]
        extra = [[q.grad for q in ps if q.grad is not None] for ps in extras]
        if all(extra):
            sq = sq + torch.stack([torch.stack([g.pow(2).sum() for g in gs]).sum()
                                   for gs in extra])
        scale = (self.algo.grad_clip / (sq.sqrt() + 1e-6)).clamp(max=1.0)
        for g in grads:
            g.mul_(scale.view(-1, *([1] * (g.dim() - 1))))
        for p, gs in enumerate(extra):
            for g in gs:
                g.mul_(scale[p])

    # ------------------------------------------------------------------ state
    def member_state_dict(self, p: int) -> dict:
        """Member ``p``'s learner state: ``qnet``, ``target`` (``DuelingQNet`` state
        dicts), ``optim`` (Adam's, over a ``DuelingQNet``'s parameters), ``updates``."""
        if self.members == 1:
            return {"qnet": self.policy.state_dict(), "target": self.loss_module.target_state(),
                    "optim": self.optim.state_dict(), "updates": self.updates}
        params = list(self.policy.parameters())
        st, keys = self.optim.state, self.policy.keys
        optim = {"state": {}, "param_groups": [dict(self.optim.param_groups[0],
                                                    params=list(range(len(keys))))]}
        if st:
            avg, avg_sq = (self.policy.member_tensors([st[q][name] for q in params], p)
                           for name in ("exp_avg", "exp_avg_sq"))
            step = st[params[0]]["step"]
            optim["state"] = {i: {"step": step.clone(), "exp_avg": avg[k], "exp_avg_sq":
                                  avg_sq[k]} for i, k in enumerate(keys)}
        return {"qnet": self.policy.member_state_dict(p),
                "target": self.loss_module.target_state(member=p),
                "optim": optim, "updates": self.updates}

    def load_member(self, p: int, state: dict) -> None:
        self.updates = int(state["updates"])
        self.target_updater.set_calls(self.updates)
        if self.members == 1:
            self.policy.load_state_dict(state["qnet"])
            self.loss_module.load_target_state(state["target"])
            self.optim.load_state_dict(state["optim"])
            return
        self.policy.load_member(p, state["qnet"])
        self.loss_module.load_target_state(state["target"], member=p)
        params, keys = list(self.policy.parameters()), self.policy.keys
        saved = state["optim"]["state"]
        if saved:
            for name in ("exp_avg", "exp_avg_sq"):
                tensors = [self.optim.state[q].get(name) for q in params]
                tensors = [torch.zeros_like(q) if t is None else t
                           for q, t in zip(params, tensors, strict=True)]
                self.policy.write_member(tensors, p, {k: saved[i][name]
                                                      for i, k in enumerate(keys)})
                for q, t in zip(params, tensors, strict=True):
                    self.optim.state[q][name] = t
            for q in params:
                self.optim.state[q]["step"] = saved[0]["step"].clone()
