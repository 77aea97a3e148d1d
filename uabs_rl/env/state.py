"""The episode state of a batch of envs (``UABSEnv.state``: a dict of tensors that
``env.to(device)`` moves with the traces), and the memory it takes."""

from __future__ import annotations

import torch

from uabs_rl.env.links import link_bytes
from uabs_rl.env.params import EnvParams


def empty_state(p: EnvParams, e: int, v: int, dev: torch.device,
                family: bool = False) -> dict[str, torch.Tensor]:
    """The episode state of ``e`` envs over ``v`` vehicle slots, all zeros (with
    ``family``, each env's area ``bounds [E, 2]`` too)."""
    m, n = p.n_uabs, p.window_steps
    z = lambda *s, dt=torch.float32: torch.zeros(*s, dtype=dt, device=dev)  # noqa: E731
    return {
        **({"bounds": z(e, 2)} if family else {}),
        "pos": z(e, m, 2), "backup": z(e, m, dt=torch.long), "t": z(e, dt=torch.long),
        "sim": z(e, dt=torch.long),
        "start": z(e, dt=torch.long), "cursor": torch.arange(e, device=dev),
        "priority": z(e, v), "served_count": z(e, v, dt=torch.long),
        "window_full": z(e, v, dt=torch.bool), "prev_present": z(e, v, dt=torch.bool),
        "n_windows": z(e, v), "ns_hist": z(e, v, n + 1), "b": z(e, m, p.n_beams),
        "look": z(e, m, p.n_lookahead),
        **{f"ep_{k}": z(e) for k in ("return", "collisions", "proximity", "fallbacks")},
    }


def state_bytes(p: EnvParams, v: int) -> int:
    """A lower bound on one env's memory over ``v`` vehicle slots: its episode state
    (:func:`empty_state`, sized on the meta device) and one step's link coordinates
    (:func:`uabs_rl.env.links.link_bytes`)."""
    state = empty_state(p, 1, v, torch.device("meta"))
    return sum(t.numel() * t.element_size() for t in state.values()) + link_bytes(p.n_uabs, v)
