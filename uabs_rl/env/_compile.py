"""``torch.compile`` with a safety net: eager if compilation fails on this machine."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Hashable, Iterator

import torch

log = logging.getLogger(__name__)


def compiled_or_eager(fn: Callable, name: str,
                      device: torch.device | str = "cpu", ahead: bool = False) -> Callable:
    """``torch.compile(fn)`` that falls back to ``fn`` (with a warning) if compiling
    fails at the first call, e.g. on a machine without a C++ compiler.

    On CPU the compiled code is called through Inductor's C++ wrapper
    (``cpp_wrapper``) instead of its Python one: the same kernels, so the same results,
    with less overhead per call. The env step at ``n_envs = 1`` is a graph of about 120
    small ops whose kernels take a few microseconds; the Python wrapper around them
    (allocating outputs, launching kernels) took about 80 us a step against 58 us with
    the C++ one (``benchmarks/numpy_reference.py`` prints both).

    ``ahead``: compiled once per call :func:`signature` and called without Dynamo's
    per-call work (:class:`AheadOfTime`). Only for a ``fn`` whose result depends on
    nothing but its arguments and state fixed when it is built (the modules it reads
    updated in place)."""
    return CompiledOrEager(fn, name, device, ahead)


class CompiledOrEager:
    """What :func:`compiled_or_eager` returns: calls ``fn`` (the compiled program, or
    the eager function once compiling it failed)."""

    def __init__(self, fn: Callable, name: str, device: torch.device | str, ahead: bool):
        self.eager, self.name = fn, name
        options = compile_options(device)
        compiled = torch.compile(fn, dynamic=False, options=options)
        self.fn = compiled if not ahead else AheadOfTime(
            torch.compile(fn, fullgraph=True, dynamic=False, options=options), compiled, name)

    def __call__(self, *args, **kwargs):
        try:
            return self.fn(*args, **kwargs)
        except Exception as e:  # compilation errors surface at the first calls
            if self.fn is self.eager:
                raise
            log.warning("torch.compile failed for %s (%s: %s); running it eagerly. Set "
                        "train.compile=false to skip compilation.", self.name,
                        type(e).__name__, str(e).splitlines()[0][:200])
            self.fn = self.eager
            return self.eager(*args, **kwargs)


def compile_options(device: torch.device | str) -> dict | None:
    """Inductor's options for a program on ``device`` (the C++ wrapper on CPU)."""
    return {"cpp_wrapper": True} if torch.device(device).type == "cpu" else None


def signature(x) -> Hashable:
    """What compiled code specialises on in a call's arguments: each tensor's shape,
    strides, dtype, device and whether it requires grad, the structure of lists, tuples
    and dicts (their keys), and every other value itself (None, numbers, strings; an
    unhashable object by its identity)."""
    if isinstance(x, torch.Tensor):
        return x.shape, x.stride(), x.dtype, x.device, x.requires_grad
    if isinstance(x, (list, tuple)):
        return type(x), tuple(map(signature, x))
    if isinstance(x, dict):
        return tuple((k, signature(v)) for k, v in x.items())
    try:
        hash(x)
    except TypeError:  # an object the code reads by identity
        return type(x), id(x)
    return x


class AheadOfTime:
    """A ``torch.compile(fn, fullgraph=True)`` program compiled ahead of its calls, once
    per key (``key(args)``; by default the thread count and the arguments'
    :func:`signature`), and then called directly.

    A ``torch.compile`` function enters Dynamo at every call: it looks the frame up in
    its cache and evaluates the guards of the compiled code (every tensor input's
    metadata, every module and attribute the code read), 0.1-0.3 ms a call on the
    development CPU, the order of the small programs' own run time. Here the program is
    compiled with ``aot_compile`` (the same trace, the same Inductor code) and called
    with its guards off: what they would check is the key, computed by the caller, and
    state that the caller guarantees fixed (the functions this class serves read no
    Python state that changes after they are built; the modules they read are updated
    in place). Each new key compiles once (Inductor's caches apply).

    Where ahead-of-time compilation fails (a torch without it, a graph break), the
    calls for that key go through ``fallback``, the plain ``torch.compile`` function,
    as before; a compile error there reaches the caller as before."""

    def __init__(self, compiled: Callable, fallback: Callable, name: str,
                 key: Callable[[tuple], Hashable] | None = None):
        self.compiled, self.fallback, self.name = compiled, fallback, name
        self.key = key or (lambda args: (torch.get_num_threads(), signature(args)))
        self.programs: dict[Hashable, Callable] = {}

    def __getstate__(self) -> dict:
        """Pickled without its programs. Compiling ahead of time, Dynamo pickles the
        state its guards read (``aot_compile``'s guards state), which for a function
        that reads its owner (the env wrapper's decision and step, the learner's update)
        reaches this object; the programs already compiled hold Dynamo's C++ guard
        managers, which do not pickle, and every key after the first (another thread
        count on a busy machine) failed to compile ahead."""
        return {**self.__dict__, "programs": {}}

    def __call__(self, *args):
        key = self.key(args)
        program = self.programs.get(key)
        if program is None:
            program = self.programs[key] = self.build(args)
        return program(*args)

    def build(self, args: tuple) -> Callable:
        """The program for ``args``' key: ahead-of-time compiled, or ``fallback``."""
        from torch._dynamo.exc import RestartAnalysis
        try:
            for _ in range(4):  # Dynamo's own compile loop restarts a trace this way
                try:
                    with stable_program_names(), linear_indices_kept():
                        program = self.compiled.aot_compile((args, {}))
                    break
                except RestartAnalysis:
                    continue
            else:
                raise RuntimeError("the trace restarted 4 times")
            if not program.guard_check(*args):
                raise RuntimeError("its guards fail on the arguments it was traced with")
            program.disable_guard_check()
            return program
        except Exception as e:  # noqa: BLE001 (any failure: the plain torch.compile path)
            log.info("%s: compiled without ahead-of-time compilation (%s: %s)", self.name,
                     type(e).__name__, str(e).splitlines()[0][:200] if str(e) else "")
            return self.fallback


@contextlib.contextmanager
def stable_program_names() -> Iterator[None]:
    """Dynamo names each compiled graph ``__compiled_fn_<n>_<uuid4>``, and under
    ``aot_compile`` that name is part of AOTAutograd's cache key, so no program compiled
    ahead of time was ever found in Inductor's on-disk caches: every run compiled from
    scratch (the main job's two programs ~40 s, the generalist's ~65 s on the
    development CPU), where the plain ``torch.compile`` path finds them from the second
    run on. Within this context the name is ``__compiled_fn_<n>`` (the counter still
    makes it unique in the process; the same command compiles its programs in the same
    order, so their keys repeat from run to run; a process that compiled other graphs
    before, as a sweep's later jobs in one process, names them otherwise and compiles
    them once more). The key still holds the whole graph, the inputs' layout and the
    compiler's configuration, so a hit is the same program. A torch without this
    function is left as it is."""
    from torch._dynamo import output_graph
    named = getattr(output_graph, "unique_id", None)
    with _replaced(output_graph, "unique_id", named and (
            lambda name, with_uuid=False: named(name))):
        yield


@contextlib.contextmanager
def linear_indices_kept() -> Iterator[None]:
    """Inductor's C++ code generation asks, for every load and store of every kernel,
    how its index moves along the vectorised loop variable
    (``torch._inductor.sizevars.stride_at_vec_range``): it passes the index (unless it
    holds a relation) and then the index's difference between ``x + 1`` and ``x`` to
    ``sympy.simplify``, about 6 ms a call. Almost every index of this project's programs
    is linear with integer coefficients (``24*d0 + 6*d1 + 2*d2 + d3``; its difference is
    an integer), which ``simplify`` returns unchanged: in the generalist's compile on an
    empty cache, 1557 of 1600 calls and 8.9 s at one thread (3079 of 3156 calls, 16 s,
    on a busy machine where the thread count changed and each program compiled twice);
    none of them returned another expression. Within this context those calls return such an
    expression as it is without calling ``simplify``; every other expression goes to
    ``simplify`` as before. What Inductor derives from a linear index, its stride, is
    the integer sympy reduces the difference to as it builds it, whatever the index's
    form, so the generated code is the same (``tests/test_ahead_of_time.py``). The swap
    is of a module attribute, for the process: compiling from two threads at once
    could leave it in place, which would change no result. A torch whose ``sizevars``
    reads ``sympy`` otherwise is left as it is."""
    from torch._inductor import sizevars
    real = getattr(sizevars, "sympy", None)
    with _replaced(sizevars, "sympy", getattr(real, "simplify", None) and _LinearKept(real)):
        yield


@contextlib.contextmanager
def _replaced(owner, name: str, value) -> Iterator[None]:
    """``owner.name`` is ``value`` within the block and what it was after it, also on
    errors; a ``value`` of None (what the caller needed is absent) changes nothing."""
    if value is None:
        yield
        return
    before = getattr(owner, name)
    setattr(owner, name, value)
    try:
        yield
    finally:
        setattr(owner, name, before)


class _LinearKept:
    """The ``sympy`` module with a ``simplify`` that returns a linear expression with
    integer coefficients as it is (:func:`linear_indices_kept`)."""

    def __init__(self, sympy):
        self._sympy = sympy

    def __getattr__(self, name: str):
        return getattr(self._sympy, name)

    def simplify(self, expr, *args, **kwargs):
        if not args and not kwargs and _linear(expr):
            return expr
        return self._sympy.simplify(expr, *args, **kwargs)


def _linear(expr) -> bool:
    """Whether ``expr`` is an integer, a symbol or a sum of them and of integer multiples
    of symbols."""
    for term in (expr.args if getattr(expr, "is_Add", False) else (expr,)):
        if getattr(term, "is_Integer", False) or getattr(term, "is_Symbol", False):
            continue
        if (getattr(term, "is_Mul", False) and len(term.args) == 2
                and term.args[0].is_Integer and term.args[1].is_Symbol):
            continue
        return False
    return True
