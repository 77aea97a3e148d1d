"""``torch.compile`` with a safety net: eager if compilation fails on this machine."""

from __future__ import annotations

import logging
from collections.abc import Callable

import torch

log = logging.getLogger(__name__)


def compiled_or_eager(fn: Callable, name: str,
                      device: torch.device | str = "cpu") -> Callable:
    """``torch.compile(fn)`` that falls back to ``fn`` (with a warning) if compiling
    fails at the first call, e.g. on a machine without a C++ compiler.

    On CPU the compiled code is called through Inductor's C++ wrapper
    (``cpp_wrapper``) instead of its Python one: the same kernels, so the same results,
    with less overhead per call. The env step at ``n_envs = 1`` is a graph of about 120
    small ops whose kernels take a few microseconds; the Python wrapper around them
    (allocating outputs, launching kernels) took about 80 us a step against 58 us with
    the C++ one (``benchmarks/numpy_reference.py`` prints both)."""
    options = {"cpp_wrapper": True} if torch.device(device).type == "cpu" else None
    compiled = torch.compile(fn, dynamic=False, options=options)
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
