"""``torch.compile`` with a safety net: eager if compilation fails on this machine."""

from __future__ import annotations

import logging
from collections.abc import Callable

import torch

log = logging.getLogger(__name__)


def compiled_or_eager(fn: Callable, name: str) -> Callable:
    """``torch.compile(fn)`` that falls back to ``fn`` (with a warning) if compiling
    fails at the first call, e.g. on a machine without a C++ compiler."""
    compiled = torch.compile(fn, dynamic=False)
    state = {"fn": compiled}

    def call(*args, **kwargs):
        try:
            return state["fn"](*args, **kwargs)
        except Exception as e:  # compilation errors surface at the first calls
            if state["fn"] is fn:
                raise
            log.warning("torch.compile failed for %s (%s: %s); running it eagerly. Set "
                        "train.compile=false to skip compilation.", name, type(e).__name__,
                        str(e).splitlines()[0][:200])
            state["fn"] = fn
            return fn(*args, **kwargs)

    return call
