"""Replay of env-step transitions with the agent dimension kept, for P >= 1 members.

Storage ``[P, S, M, ...]``: member ``p``'s ring of S env-step slots, each one step's
transitions of the M agents (o, a, mask, r, o', mask', terminated'), where mask' is the
mask the double-DQN target maximises over at o'. ``algo.buffer_size`` counts per-agent
transitions, as the paper's shared buffer does: the newest ``buffer_size`` of them are
held (S = ceil(buffer_size / M) step slots hold them, whole steps at a time).

The API is TorchRL's ``ReplayBuffer``'s: :meth:`extend` with a TensorDict,
:meth:`sample` with ``return_info`` giving the sampled indices, :meth:`update_priority`,
:meth:`state_dict` / :meth:`load_state_dict` (per member: :meth:`member_state_dict`).
What a sample is depends on the learner (``unit``):

* ``"agent"``: per-agent transitions drawn uniformly among the newest ``buffer_size``,
  fields ``[B, ...]`` (an independent learner such as the 3DQN);
* ``"step"``: whole env steps, fields ``[B, M, ...]`` (a learner of the team reward).

A population's sample is ``[P, B, ...]``, each member's indices drawn from its own
generator, seeded as its single run seeds its own (``tests/test_algorithms.py``).

Prioritized replay (``algo.replay=prioritized``, ``priority_alpha`` given): each member
draws through a :class:`Priorities` table over its storage positions (``slot · M +
agent``, or step slots), with its own generator: TorchRL's ``PrioritizedSampler``
semantics (priorities (p + 1e-8)^α, new items at the highest priority so far, weights
(p_i / p_min)^-β), in plain torch, because TorchRL's sampler needs its C++ extension,
which does not load with the CPU torch this project pins. A sample carries ``index`` and
the importance ``weight``, and :meth:`update_priority` sets the sampled items'
priorities from the learner's TD errors. It draws among the held step slots'
transitions, which, when M does not divide ``algo.buffer_size``, are up to M − 1 more
than ``buffer_size`` (uniform sampling keeps exactly the newest ``buffer_size``).

Why not TorchRL's ``ReplayBuffer(LazyTensorStorage)``: measured on the 2-core
development CPU (``benchmarks/replay_bench.py``, one thread, in turns), one push of an
env step's transitions (3 agents) plus one sample of 128 takes 105 µs here against
219 µs with ``TensorDictReplayBuffer(LazyTensorStorage)`` holding the same per-agent
transitions (2.1x); a training step does both once per env step, and the difference is
7 % of the main job's 1.6 ms step.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from tensordict import TensorDict, TensorDictBase

FIELDS = ("obs", "action", "mask", "reward", "next_obs", "next_mask", "terminated")
UNITS = ("agent", "step")


# a learner's own per-agent fields beside FIELDS: name -> (shape, dtype)
ExtraFields = Mapping[str, tuple[tuple[int, ...], torch.dtype]]


def storage(lead: tuple[int, ...], capacity: int, obs_dim: int, n_actions: int,
            device: torch.device, extra: ExtraFields | None = None) -> dict[str, torch.Tensor]:
    """Zeroed tensors for every field of :data:`FIELDS` and of ``extra`` (a learner's
    own, such as ``algo=dqfd``'s teacher labels), shaped ``[*lead, capacity, ...]``."""
    shapes = {"obs": ((obs_dim,), torch.float32), "action": ((), torch.long),
              "mask": ((n_actions,), torch.bool), "reward": ((), torch.float32),
              "next_obs": ((obs_dim,), torch.float32),
              "next_mask": ((n_actions,), torch.bool), "terminated": ((), torch.bool),
              **(extra or {})}
    return {k: torch.zeros(*lead, capacity, *shape, dtype=dtype, device=device)
            for k, (shape, dtype) in shapes.items()}


def transition_bytes(obs_dim: int, n_actions: int) -> int:
    """Bytes of one stored transition: every field of :func:`storage` (sized on the meta
    device)."""
    one = storage((), 1, obs_dim, n_actions, torch.device("meta"))
    return sum(t.numel() * t.element_size() for t in one.values())


class Priorities:
    """Proportional prioritized sampling over ``capacity`` items (Schaul et al., 2016),
    as TorchRL's ``PrioritizedSampler`` does it: item i is drawn with probability
    (p_i + eps)^α / Σ_j (p_j + eps)^α and weighted (p_i / p_min)^-β; an item written
    anew gets the highest priority given so far (1 before any).

    The stored (p + eps)^α in one float64 tensor; a draw searches their cumulative sum.
    Measured on the development CPU (one thread, 100 002 items, batch 128): a draw takes
    108 µs and setting 128 priorities 2 µs, against about 250 µs each (and 250 µs to
    mark three new items) for a sum tree in plain torch, whose log2(capacity) levels
    each cost a few small tensor ops."""

    def __init__(self, capacity: int, alpha: float, beta: float, generator: torch.Generator,
                 eps: float = 1e-8):
        self.alpha, self.beta, self.eps, self.generator = alpha, beta, eps, generator
        self.stored = torch.zeros(capacity, dtype=torch.float64)
        self.max_priority: float | None = None  # the highest priority given so far

    def update_priority(self, index: torch.Tensor, priority: torch.Tensor) -> None:
        """Items ``index`` get priorities ``priority`` (raw: stored as (p + eps)^α)."""
        priority = priority.detach().to("cpu", torch.float64).reshape(-1)
        if priority.numel():
            top = float(priority.max())
            self.max_priority = top if self.max_priority is None else max(self.max_priority, top)
        self.stored[index.cpu().reshape(-1)] = (priority + self.eps) ** self.alpha

    def mark_update(self, index: torch.Tensor) -> None:
        """Items written anew: the highest priority so far."""
        index = index.cpu().reshape(-1)
        first = 1.0 if self.max_priority is None else self.max_priority
        self.update_priority(index, torch.full(index.shape, first))

    def sample(self, held: int, batch_size: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``batch_size`` items among ``0..held-1`` in proportion to their stored
        priorities, and their importance weights (p_i / p_min)^-β (float32)."""
        p = self.stored[:held]
        total = torch.cumsum(p, 0)
        mass = torch.rand(batch_size, generator=self.generator, dtype=torch.float64)
        index = torch.searchsorted(total, mass * total[-1]).clamp(max=held - 1)
        weight = (p[index] / p.min()) ** -self.beta
        return index, weight.float()

    def state_dict(self, held: int) -> dict:
        top = -1.0 if self.max_priority is None else self.max_priority
        return {"priority": self.stored[:held].clone(), "max_priority": top}

    def load_state_dict(self, state: dict) -> None:
        self.stored.zero_()
        leaves = state["priority"].to(torch.float64)
        self.stored[:leaves.shape[0]] = leaves
        top = float(state["max_priority"])
        self.max_priority = None if top < 0 else top


def prioritized_draw(samplers: list[Priorities], held: int, batch_size: int,
                     device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """``[P, batch_size]`` positions among the ``held`` drawn in proportion to priority^α,
    and their importance weights, each member's from its own table."""
    drawn = [s.sample(held, batch_size) for s in samplers]
    return (torch.stack([i for i, _ in drawn]).to(device),
            torch.stack([w for _, w in drawn]).to(device))


def flat_ring_position(slot: torch.Tensor, total: int, capacity: int,
                       ring: int) -> torch.Tensor:
    """Where slot ``slot`` of the paper's flat ring of ``capacity`` per-agent transitions
    lies in the step slots (``ring`` = S · M positions), after ``total`` were written.
    The slot holds the newest transition g with g = slot mod capacity; it lies at the
    slot itself until the ring wraps, or when the step slots are that ring (capacity a
    multiple of M), else at g mod ring."""
    if total <= capacity or ring == capacity:
        return slot
    g = slot + capacity * torch.div(total - 1 - slot, capacity, rounding_mode="floor")
    return g % ring


class TransitionReplay:
    """The replay buffers of P members (see the module docstring): ``capacity`` per-agent
    transitions each, ``n_agents`` agents a step, sampled in ``unit`` by ``batch_size``."""

    def __init__(self, capacity: int, obs_dim: int, n_actions: int, n_agents: int,
                 seeds: list[int], batch_size: int, unit: str = "agent",
                 device: str | torch.device = "cpu", priority_alpha: float | None = None,
                 priority_beta: float = 0.4, extra: ExtraFields | None = None):
        if unit not in UNITS:
            raise ValueError(f"unit must be one of {UNITS}, got {unit!r}")
        dev = torch.device(device)
        self.capacity, self.n_agents, self.unit = capacity, n_agents, unit
        self.batch_size = batch_size
        self.slots = math.ceil(capacity / n_agents)  # S, env-step slots per member
        self.members = len(seeds)
        # [P, S, M, ...]: the agents of a step as the last lead dim
        self.data = storage((self.members, self.slots), n_agents, obs_dim, n_actions, dev,
                            extra)
        # what a sample indexes: per agent transition the same memory as [P, S·M, ...];
        # and member 0's alone (a single run's sample: one index_select per field)
        self.fields = (self.data if unit == "step" else
                       {k: v.flatten(1, 2) for k, v in self.data.items()})
        self.fields0 = {k: v[0] for k, v in self.fields.items()}
        # storage positions per member: what a sample indexes (S·M per agent, S per step)
        self.items = self.slots * (n_agents if unit == "agent" else 1)
        # every member's fields as one [P·items, ...] view (a population's sample: one
        # index_select per field at member p's offset, half the time of indexing [P, items]
        # with a row and a column index; the same copies)
        self.flat = {k: v.flatten(0, 1) for k, v in self.fields.items()}
        self.offsets = torch.arange(self.members, device=dev)[:, None] * self.items
        self.written = 0  # env steps written per member
        self.generators = [torch.Generator(device=dev).manual_seed(s) for s in seeds]
        self.samplers: list[Priorities] = []
        if priority_alpha is not None:  # one sampler per member, drawing from its generator
            self.samplers = [Priorities(self.items, priority_alpha, priority_beta, g)
                             for g in self.generators]

    # ------------------------------------------------------------------ sizes
    def __len__(self) -> int:
        """Per-agent transitions held by each member (at most ``capacity``)."""
        return min(self.written * self.n_agents, self.capacity)

    @property
    def steps_held(self) -> int:
        return min(self.written, self.slots)

    # ------------------------------------------------------------------ writing
    def extend(self, data: TensorDictBase | Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Append ``[P·n, M, ...]`` env-step transitions (member ``p``'s rows form block
        ``p``, as the population's env lays them out); returns the step slots written."""
        n = data["obs"].shape[0] // self.members
        if n > self.slots:
            raise ValueError(f"pushing {n} env steps into a buffer of {self.slots}")
        dev = self.data["obs"].device
        idx = (torch.arange(n, device=dev) + self.written) % self.slots
        for k, v in self.data.items():
            v.index_copy_(1, idx, data[k].reshape(self.members, n, *v.shape[2:]))
        self.written += n
        if self.samplers:  # the new transitions at the highest priority so far
            pos = idx if self.unit == "step" else (
                idx[:, None] * self.n_agents + torch.arange(self.n_agents, device=dev)).flatten()
            for sampler in self.samplers:
                sampler.mark_update(pos)
        return idx

    def held_items(self) -> int:
        """Storage positions holding a transition (what a prioritized draw ranges over)."""
        return self.steps_held * (self.n_agents if self.unit == "agent" else 1)

    # ------------------------------------------------------------------ sampling
    def draw(self, batch_size: int) -> torch.Tensor:
        """``[P, batch_size]`` indices, each member's from its own generator: per-agent
        positions ``step slot · M + agent`` (unit ``agent``) or step slots (``step``)."""
        dev = self.data["obs"].device
        if self.unit == "step":
            return torch.stack([torch.randint(0, self.steps_held, (batch_size,), generator=g,
                                              device=dev) for g in self.generators])
        size = len(self)
        slot = torch.stack([torch.randint(0, size, (batch_size,), generator=g, device=dev)
                            for g in self.generators])
        return flat_ring_position(slot, self.written * self.n_agents, self.capacity,
                                  self.slots * self.n_agents)

    def gather(self, index: torch.Tensor) -> dict[str, torch.Tensor]:
        """The transitions at ``index`` (``[P, B]``, as :meth:`draw` returns them):
        fields ``[P, B, ...]``, or ``[B, ...]`` for a single run."""
        if self.members == 1:
            out = {k: v.index_select(0, index[0]) for k, v in self.fields0.items()}
        else:
            flat = (index + self.offsets).flatten()
            out = {k: v.index_select(0, flat).view(*index.shape, *v.shape[1:])
                   for k, v in self.flat.items()}
        if self.unit == "step":  # with the team reward, the sum of the agents' rewards
            out["team_reward"] = out["reward"].sum(-1)
        return out

    def sample(self, batch_size: int | None = None, return_info: bool = False):
        """A batch of :data:`FIELDS` (``[B, ...]``, or ``[P, B, ...]`` for a population;
        ``unit`` step adds the agent dim), and with ``return_info`` ``{"index": ...}``.
        A prioritized sample also holds ``index`` and ``weight``."""
        n = batch_size or self.batch_size
        weight = None
        if self.samplers:
            index, weight = prioritized_draw(self.samplers, self.held_items(), n,
                                             self.data["obs"].device)
        else:
            index = self.draw(n)
        batch = self.gather(index)
        if self.members == 1:
            index, weight = index[0], None if weight is None else weight[0]
        if weight is not None:
            batch["index"], batch["weight"] = index, weight
        td = TensorDict(batch, batch_size=index.shape)
        return (td, {"index": index}) if return_info else td

    def update_priority(self, index: torch.Tensor, priority: torch.Tensor) -> None:
        """The priorities of the items at ``index`` (as :meth:`sample` gives it) set to
        ``priority``. Refused when sampling uniformly (TorchRL's uniform sampler ignores
        them silently; a learner that sets them expects them used)."""
        if not self.samplers:
            raise NotImplementedError("this replay samples uniformly; it keeps no priorities")
        index, priority = index.reshape(self.members, -1), priority.reshape(self.members, -1)
        for p, sampler in enumerate(self.samplers):
            sampler.update_priority(index[p], priority[p])

    # ------------------------------------------------------------------ state
    def member_state_dict(self, p: int) -> dict:
        """Member ``p``'s buffer (its held step slots, in slot order) and generator."""
        held = self.steps_held
        state = {"data": {k: v[p, :held].clone() for k, v in self.data.items()},
                 "written": self.written, "generator": self.generators[p].get_state()}
        if self.samplers:  # the stored (p + eps)^α and the highest priority
            state.update(self.samplers[p].state_dict(self.held_items()))
        return state

    def load_member(self, p: int, state: dict) -> None:
        """Member ``p`` from :meth:`member_state_dict`. Members are written in step, so
        every member's ``written`` must agree."""
        held = state["data"]["obs"].shape[0]
        if held > self.slots or state["data"]["obs"].shape[1] != self.n_agents:
            raise ValueError(f"the saved buffer holds {held} steps of "
                             f"{state['data']['obs'].shape[1]} agents, more than "
                             f"algo.buffer_size={self.capacity} or another fleet")
        missing = sorted(set(self.data) - set(state["data"]))
        if missing:
            raise ValueError(f"the saved buffer holds no {', '.join(missing)}: it was "
                             f"written by another learner, whose buffer this one cannot "
                             f"continue")
        for k in self.data:
            self.data[k][p, :held] = state["data"][k].to(self.data[k].device)
        self.written = int(state["written"])
        self.generators[p].set_state(state["generator"])
        if self.samplers:
            if "priority" not in state:
                raise ValueError("the saved buffer holds no priorities (it was sampled "
                                 "uniformly): resume it with algo.replay=uniform")
            self.samplers[p].load_state_dict(state)

    def state_dict(self) -> dict:
        """A single run's buffer (``P = 1``)."""
        return self.member_state_dict(0)

    def load_state_dict(self, state: dict) -> None:
        self.load_member(0, state)


def upgrade_flat_replay(old: dict, capacity: int, n_agents: int, total: int) -> dict:
    """A replay state of checkpoint format 1 (a flat ring of ``capacity`` per-agent
    transitions: ``data`` in slot order, ``cursor``, ``size``) in today's layout, given
    the ``total`` per-agent transitions the run had stored: the same held transitions,
    so a resumed run samples what it would have sampled."""
    slots = math.ceil(capacity / n_agents)
    written = total // n_agents
    held = min(written, slots)
    w = torch.arange(written - held, written)
    g = w[:, None] * n_agents + torch.arange(n_agents)  # global per-agent index [held, M]
    valid = g >= total - int(old["size"])
    src = (g % capacity).clamp(max=max(int(old["size"]) - 1, 0))
    order = torch.argsort(w % slots)  # step slots 0..held-1
    data = {}
    for k, v in old["data"].items():
        x = v[src]
        x[~valid] = 0
        data[k] = x[order]
    return {"data": data, "written": written, "generator": old["generator"]}
