"""A shared replay buffer of per-agent transitions, as preallocated device tensors.

Every agent's step is one transition (o, a, r, o', mask', terminated'), where mask' is
the mask the double-DQN target maximises over at o'. A ring buffer of plain tensors:
pushes are slice copies, samples are one ``index_select`` per field.

Why not TorchRL's ``ReplayBuffer(LazyTensorStorage)``: measured on the 2-core
development CPU, one push of a step's transitions plus one sample of 128 takes 130 µs
here against 622 µs there (TensorDict construction and indexing per call), and a
training step does both once per env step.
"""

from __future__ import annotations

import torch

FIELDS = ("obs", "action", "mask", "reward", "next_obs", "next_mask", "terminated")


def storage(lead: tuple[int, ...], capacity: int, obs_dim: int, n_actions: int,
            device: torch.device) -> dict[str, torch.Tensor]:
    """Zeroed tensors for every field of :data:`FIELDS`, shaped ``[*lead, capacity, ...]``."""
    shapes = {"obs": ((obs_dim,), torch.float32), "action": ((), torch.long),
              "mask": ((n_actions,), torch.bool), "reward": ((), torch.float32),
              "next_obs": ((obs_dim,), torch.float32),
              "next_mask": ((n_actions,), torch.bool), "terminated": ((), torch.bool)}
    return {k: torch.zeros(*lead, capacity, *shapes[k][0], dtype=shapes[k][1], device=device)
            for k in FIELDS}


class ReplayBuffer:
    """A fixed-capacity ring of per-agent transitions (fields :data:`FIELDS`) with
    uniform sampling from its own seeded generator; :meth:`state_dict` makes it part of
    a checkpoint."""

    def __init__(self, capacity: int, obs_dim: int, n_actions: int,
                 device: str | torch.device = "cpu", seed: int = 0,
                 data: dict[str, torch.Tensor] | None = None):
        """``data``: storage to use instead of new tensors (a population's buffers are
        slices of one stacked storage, see :class:`PopulationReplay`)."""
        dev = torch.device(device)
        self.capacity = capacity
        self.data = data if data is not None else storage((), capacity, obs_dim,
                                                          n_actions, dev)
        self.cursor = 0  # next slot to write
        self.size = 0
        self.generator = torch.Generator(device=dev)
        self.generator.manual_seed(seed)

    def __len__(self) -> int:
        return self.size

    def push(self, **batch: torch.Tensor) -> None:
        """Append ``n`` transitions (every field with leading dim ``n``)."""
        n = batch["obs"].shape[0]
        idx = self.slots(n)
        for k in FIELDS:
            self.data[k].index_copy_(0, idx, batch[k].reshape(n, *self.data[k].shape[1:]))
        self.advance(n)

    def slots(self, n: int) -> torch.Tensor:
        """The ring slots the next ``n`` transitions go to."""
        if n > self.capacity:
            raise ValueError(f"pushing {n} transitions into a buffer of {self.capacity}")
        return (torch.arange(n, device=self.data["obs"].device) + self.cursor) % self.capacity

    def advance(self, n: int) -> None:
        """Count ``n`` transitions written at :meth:`slots` ``(n)``."""
        self.cursor = (self.cursor + n) % self.capacity
        self.size = min(self.size + n, self.capacity)

    def draw(self, batch_size: int) -> torch.Tensor:
        """``batch_size`` uniform slot indices from this buffer's generator."""
        return torch.randint(0, self.size, (batch_size,), generator=self.generator,
                             device=self.data["obs"].device)

    def sample(self, batch_size: int) -> dict[str, torch.Tensor]:
        idx = self.draw(batch_size)
        return {k: v.index_select(0, idx) for k, v in self.data.items()}

    def state_dict(self) -> dict:
        return {"data": {k: v[: self.size].clone() for k, v in self.data.items()},
                "cursor": self.cursor, "size": self.size,
                "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict) -> None:
        size = int(state["size"])
        if size > self.capacity:
            raise ValueError(f"the saved buffer holds {size} transitions, more than "
                             f"algo.buffer_size={self.capacity}")
        for k in FIELDS:
            self.data[k][:size] = state["data"][k].to(self.data[k].device)
        self.cursor, self.size = int(state["cursor"]), size
        self.generator.set_state(state["generator"])


class PopulationReplay:
    """One :class:`ReplayBuffer` per population member, each seeded as that member's
    solo run seeds its own, their storage slices ``[p]`` of one stacked storage
    ``[P, capacity, ...]``. :meth:`push` takes the transitions of the population's env
    (member ``p``'s rows form block ``p``) and writes every member's at once;
    :meth:`sample` draws each member's indices from its own generator, as its solo run
    does, and gathers ``[P, B, ...]`` for :class:`~uabs_rl.learner.PopulationLearner`
    in one indexing per field (the same transitions as member-by-member sampling)."""

    def __init__(self, capacity: int, obs_dim: int, n_actions: int,
                 device: str | torch.device, seeds: list[int]):
        dev = torch.device(device)
        self.data = storage((len(seeds),), capacity, obs_dim, n_actions, dev)
        self.buffers = [ReplayBuffer(capacity, obs_dim, n_actions, dev, seed=s,
                                     data={k: v[p] for k, v in self.data.items()})
                        for p, s in enumerate(seeds)]
        self.rows = torch.arange(len(seeds), device=dev)[:, None]

    def __len__(self) -> int:
        return min(len(b) for b in self.buffers)

    def push(self, **batch: torch.Tensor) -> None:
        P, first = len(self.buffers), self.buffers[0]
        n = batch["obs"].shape[0] // P
        # members push alike, so their cursors agree (a resumed population restores them
        # from its members' checkpoints, written at the same step)
        if any(b.cursor != first.cursor or b.size != first.size for b in self.buffers):
            raise RuntimeError("population replay buffers out of step: cursors "
                               f"{[b.cursor for b in self.buffers]}, sizes "
                               f"{[b.size for b in self.buffers]}")
        idx = first.slots(n)
        for k, v in self.data.items():
            v.index_copy_(1, idx, batch[k].reshape(P, n, *v.shape[2:]))
        for b in self.buffers:
            b.advance(n)

    def sample(self, batch_size: int) -> dict[str, torch.Tensor]:
        idx = torch.stack([b.draw(batch_size) for b in self.buffers])
        return {k: v[self.rows, idx] for k, v in self.data.items()}
