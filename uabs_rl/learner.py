"""3DQN updates: double DQN with a target network, Huber loss, Adam (docs/model.md §7).

Two implementations of the same loss, selected by ``algo.loss``:

* ``fused`` (default): a hand-written update on plain tensors: online net on o (with
  gradient) and on o' (without), target net on o', Huber loss, fused Adam.
* ``torchrl``: TorchRL's ``DQNLoss(double_dqn=True)`` over the same batch, kept as the
  tested reference.

Why a hand-written loss: measured on the 2-core development CPU (batch 128 × 3 agents,
2 × 256 MLP), one update takes 6.9 ms fused against 13.9 ms with ``DQNLoss``, which
builds TensorDicts, runs the value network through functional calls and masks via
``QValueModule`` on every call; the update is half of a training step's time.
``tests/test_learner.py`` checks that both give the same loss and gradients.
"""

from __future__ import annotations

import contextlib
import copy
import warnings

import torch
import torch.nn.functional as F
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.modules import QValueModule
from torchrl.objectives import DQNLoss

from uabs_rl.config import AlgoConfig, LossKind
from uabs_rl.model import DuelingQNet, StackedQNet

TARGET_WARNING = "No target network updater has been associated"


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
    (``tests/test_learner.py``)."""
    torch.set_flush_denormal(True)
    try:
        yield
    finally:
        torch.set_flush_denormal(False)


class DQNLearner:
    """The online Q-network, its target copy (copied every ``algo.target_update``
    updates), Adam, and one double-DQN update per :meth:`update` call."""

    def __init__(self, qnet: DuelingQNet, algo: AlgoConfig, n_actions: int):
        self.qnet = qnet
        self.target = copy.deepcopy(qnet).requires_grad_(False)
        self.gamma = float(algo.gamma) ** algo.n_step  # bootstraps n steps on
        self.target_update = int(algo.target_update)
        self.grad_clip = algo.grad_clip
        self.kind = algo.loss
        # fused Adam: one kernel for all parameters (3x faster than foreach on CPU here)
        self.optim = torch.optim.Adam(qnet.parameters(), lr=algo.lr, fused=True)
        self.updates = 0
        if self.kind == LossKind.torchrl:
            self.dqn_loss = make_dqn_loss(qnet, n_actions, self.gamma)
            # the loss's target parameters mirror ``self.target``, whose layout differs
            # (the loss wraps the net): a wrapper of the target with the loss's layout
            self.target_value_net = value_network(self.target)
            self._sync_torchrl_target()

    # ------------------------------------------------------------------ losses
    def fused_loss(self, b: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Huber(Q(o, a), r + γ (1 − terminated) Q_target(o', argmax_{a' ∈ mask'} Q(o', a')))
        (γ^n with n-step returns). Batch fields ``[B, ...]``; for a population
        ``[P, B, ...]``, with one loss per member ``[P]``."""
        q_taken = self.qnet(b["obs"]).gather(-1, b["action"][..., None]).squeeze(-1)
        with torch.no_grad():  # o' outside the graph: the backward pass covers o only
            best = self.qnet(b["next_obs"]).masked_fill(~b["next_mask"], -torch.inf).argmax(
                -1, keepdim=True)
            q_next = self.target(b["next_obs"]).gather(-1, best).squeeze(-1)
            y = b["reward"] + self.gamma * (~b["terminated"]).float() * q_next
        if q_taken.dim() == 1:
            return F.smooth_l1_loss(q_taken, y), q_taken.detach()
        return F.smooth_l1_loss(q_taken, y, reduction="none").mean(-1), q_taken.detach()

    def torchrl_loss(self, b: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        td = batch_to_td(b)
        with warnings.catch_warnings():  # the target is copied by sync_target, on purpose
            warnings.filterwarnings("ignore", message=TARGET_WARNING)
            loss = self.dqn_loss(td)["loss"]
        with torch.no_grad():
            q_taken = self.qnet(b["obs"]).gather(1, b["action"][:, None]).squeeze(1)
        return loss, q_taken

    # ------------------------------------------------------------------ update
    def update(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """One gradient step; returns (loss, mean chosen Q) as 0-d tensors (no sync);
        ``[P]`` tensors, one per member, for a population."""
        loss, q_taken = (self.fused_loss if self.kind == LossKind.fused
                         else self.torchrl_loss)(batch)
        self.optim.zero_grad(set_to_none=True)
        (loss if loss.dim() == 0 else loss.sum()).backward()
        if self.grad_clip is not None:
            self.clip_gradients()
        with flush_denormals():
            self.optim.step()
        self.updates += 1
        if self.updates % self.target_update == 0:
            self.sync_target()
        return loss.detach(), q_taken.mean(-1)

    def clip_gradients(self) -> None:
        torch.nn.utils.clip_grad_norm_(self.qnet.parameters(), self.grad_clip)

    def sync_target(self) -> None:
        self.target.load_state_dict(self.qnet.state_dict())
        if self.kind == LossKind.torchrl:
            self._sync_torchrl_target()

    def _sync_torchrl_target(self) -> None:
        """Copy ``self.target`` into the TorchRL loss's target parameters."""
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=TARGET_WARNING)
            self.dqn_loss.target_value_network_params.update_(
                TensorDict.from_module(self.target_value_net).data)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        return {"qnet": self.qnet.state_dict(), "target": self.target.state_dict(),
                "optim": self.optim.state_dict(), "updates": self.updates}

    def load_state_dict(self, state: dict) -> None:
        self.qnet.load_state_dict(state["qnet"])
        self.target.load_state_dict(state["target"])
        self.optim.load_state_dict(state["optim"])
        self.updates = int(state["updates"])
        if self.kind == LossKind.torchrl:
            self._sync_torchrl_target()


class PopulationLearner(DQNLearner):
    """:class:`DQNLearner`'s fused update for the P members of a population at once, on
    a :class:`~uabs_rl.model.StackedQNet` with one fused Adam over the stacked
    parameters. The loss is the sum of the members' mean Huber losses; members share
    no parameter, so each slice's gradient is its member's own, and Adam is
    element-wise, so each slice steps as its member's solo run would (up to the
    rounding of batched products). ``algo.grad_clip`` clips each member's gradient by
    its own norm, as ``clip_grad_norm_`` does in a solo run."""

    def __init__(self, qnet: StackedQNet, algo: AlgoConfig):
        super().__init__(qnet, algo, n_actions=0)  # algo.loss is fused (validate_run)

    def clip_gradients(self) -> None:
        grads = [p.grad for p in self.qnet.parameters()]
        norm = torch.stack([g.pow(2).flatten(1).sum(1) for g in grads]).sum(0).sqrt()  # [P]
        scale = (self.grad_clip / (norm + 1e-6)).clamp(max=1.0)
        for g in grads:
            g.mul_(scale.view(-1, *([1] * (g.dim() - 1))))

    # ------------------------------------------------------------------ members
    def member_state_dict(self, p: int) -> dict:
        """Member ``p``'s learner state in the solo format (:meth:`DQNLearner.state_dict`),
        so its checkpoint is a solo run's checkpoint."""
        params = list(self.qnet.parameters())
        st, keys = self.optim.state, self.qnet.keys
        optim = {"state": {}, "param_groups": [dict(self.optim.param_groups[0],
                                                    params=list(range(len(keys))))]}
        if st:
            avg, avg_sq = (self.qnet.member_tensors([st[q][name] for q in params], p)
                           for name in ("exp_avg", "exp_avg_sq"))
            step = st[params[0]]["step"]
            optim["state"] = {i: {"step": step.clone(), "exp_avg": avg[k], "exp_avg_sq":
                                  avg_sq[k]} for i, k in enumerate(keys)}
        return {"qnet": self.qnet.member_state_dict(p),
                "target": self.target.member_state_dict(p),
                "optim": optim, "updates": self.updates}

    def load_member(self, p: int, state: dict) -> None:
        """Set member ``p`` from a solo learner state (a member checkpoint)."""
        self.qnet.load_member(p, state["qnet"])
        self.target.load_member(p, state["target"])
        params, keys = list(self.qnet.parameters()), self.qnet.keys
        saved = state["optim"]["state"]
        if saved:
            for name in ("exp_avg", "exp_avg_sq"):
                tensors = [self.optim.state[q].get(name) for q in params]
                tensors = [torch.zeros_like(q) if t is None else t
                           for q, t in zip(params, tensors, strict=True)]
                self.qnet.write_member(tensors, p, {k: saved[i][name]
                                                    for i, k in enumerate(keys)})
                for q, t in zip(params, tensors, strict=True):
                    self.optim.state[q][name] = t
            for q in params:
                self.optim.state[q]["step"] = saved[0]["step"].clone()
        self.updates = int(state["updates"])


def value_network(qnet: DuelingQNet) -> TensorDictSequential:
    """``qnet`` as TorchRL's Q-value actor on flat per-agent batches (keys as in
    :func:`batch_to_td`), masked by ``action_mask``."""
    return TensorDictSequential(
        TensorDictModule(qnet, in_keys=["observation"], out_keys=["action_value"]),
        QValueModule(action_space="categorical", action_mask_key="action_mask"))


def make_dqn_loss(qnet: DuelingQNet, n_actions: int, gamma: float) -> DQNLoss:
    """TorchRL's double-DQN loss on flat per-agent batches (keys as in batch_to_td).
    Its target parameters are copied by :meth:`DQNLearner.sync_target`, not by a
    TorchRL updater, so both losses share one target schedule."""
    loss = DQNLoss(value_network(qnet), action_space="categorical", double_dqn=True,
                   delay_value=True, loss_function="smooth_l1")
    loss.make_value_estimator(gamma=gamma)
    return loss


def batch_to_td(b: dict[str, torch.Tensor]) -> TensorDict:
    n = b["obs"].shape[0]
    done = b["terminated"][:, None]
    return TensorDict({
        "observation": b["obs"], "action": b["action"], "action_mask": b["mask"],
        "next": {"observation": b["next_obs"], "action_mask": b["next_mask"],
                 "reward": b["reward"][:, None], "done": done, "terminated": done},
    }, batch_size=[n])
