"""Random draws for one run or for a population of runs batched in one env.

A solo run draws from one ``torch.Generator``. A population (``train.population``)
trains P seeds in one process, their episodes side by side in one env: env rows
``[p·n, (p+1)·n)`` belong to member ``p``. :class:`Generators` holds one generator per
member and draws each member's rows from that member's own generator, with the same
call and the same shape as the member's solo run makes, so every random decision of a
member (windows, start positions, LoS states, exploration) is the one its solo run
would make.

The draw helpers (:func:`rand`, :func:`randn`, :func:`randint`) take either kind.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import torch


class Generators:
    """P seeded generators; a draw of shape ``[P·n, ...]`` gives rows ``[p·n, (p+1)·n)``
    from generator ``p``."""

    def __init__(self, seeds: Sequence[int], device: str | torch.device = "cpu"):
        if not seeds:
            raise ValueError("Generators needs at least one seed")
        self.device = torch.device(device)
        self.gens = [torch.Generator(device=self.device) for _ in seeds]
        for g, s in zip(self.gens, seeds, strict=True):
            g.manual_seed(int(s))

    def __len__(self) -> int:
        return len(self.gens)

    def manual_seed(self, seed: int) -> Generators:
        """Every member's generator seeded with ``seed`` (evaluation: the same episodes
        for every member)."""
        for g in self.gens:
            g.manual_seed(int(seed))
        return self

    def get_state(self) -> list[torch.Tensor]:
        return [g.get_state() for g in self.gens]

    def set_state(self, states: Sequence[torch.Tensor]) -> None:
        for g, s in zip(self.gens, states, strict=True):
            g.set_state(s)

    def blocks(self, rows: int) -> Iterator[tuple[slice, torch.Generator]]:
        """(rows of member p, generator p) for a leading dimension of ``rows``."""
        p = len(self.gens)
        if rows % p:
            raise ValueError(f"{rows} env rows do not split into {p} population members")
        n = rows // p
        for i, g in enumerate(self.gens):
            yield slice(i * n, (i + 1) * n), g


AnyGen = torch.Generator | Generators


def _blockwise(draw, shape: Sequence[int], gen: AnyGen | None, device) -> torch.Tensor:
    shape = tuple(shape)
    if not isinstance(gen, Generators):
        return draw(shape, gen, device)
    return torch.cat([draw((sl.stop - sl.start, *shape[1:]), g, device)
                      for sl, g in gen.blocks(shape[0])])


def rand(shape: Sequence[int], gen: AnyGen | None, device: str | torch.device) -> torch.Tensor:
    """``torch.rand(shape)`` from ``gen`` (per member's rows for :class:`Generators`)."""
    return _blockwise(lambda s, g, d: torch.rand(s, generator=g, device=d), shape, gen, device)


def randn(shape: Sequence[int], gen: AnyGen | None, device: str | torch.device) -> torch.Tensor:
    """``torch.randn(shape)`` from ``gen`` (per member's rows for :class:`Generators`)."""
    return _blockwise(lambda s, g, d: torch.randn(s, generator=g, device=d), shape, gen, device)


def randint(low: int, high: int, shape: Sequence[int], gen: AnyGen | None,
            device: str | torch.device) -> torch.Tensor:
    """``torch.randint(low, high, shape)`` from ``gen`` (per member's rows)."""
    return _blockwise(lambda s, g, d: torch.randint(low, high, s, generator=g, device=d),
                      shape, gen, device)


def reseeded(gen: AnyGen, device: torch.device) -> AnyGen:
    """``gen`` moved to ``device``: new generators seeded from a draw of the old ones."""
    def one(g: torch.Generator) -> int:
        return int(torch.randint(0, 2**62, (1,), generator=g, device=g.device))

    if isinstance(gen, Generators):
        return Generators([one(g) for g in gen.gens], device)
    new = torch.Generator(device=device)
    new.manual_seed(one(gen))
    return new


def make_generator(seed: int | Sequence[int] | None, device: str | torch.device) -> AnyGen:
    """One generator for an int (or None: seed 0), :class:`Generators` for a list."""
    if isinstance(seed, Sequence):
        return Generators(seed, device)
    g = torch.Generator(device=device)
    g.manual_seed(0 if seed is None else int(seed))
    return g
