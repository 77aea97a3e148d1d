"""Programs compiled ahead of their calls (uabs_rl.env._compile.AheadOfTime): called
without Dynamo's per-call guards, they must still never run code compiled for other
arguments. What the guards would have caught, the key catches: a new shape, new strides
(the same shape, transposed), another dtype, another thread count, an argument that is
None where it was a tensor, each compile a program of their own, and every call returns
what the function computes eagerly (to float rounding)."""

from __future__ import annotations

import contextlib
import logging

import pytest
import torch

from tests.conftest import another_thread_count
from uabs_rl.env._compile import AheadOfTime, compiled_or_eager, signature


def affine(x: torch.Tensor, w: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    y = x @ w
    return torch.relu(y if bias is None else y + bias).sum(-1)


def test_a_program_compiled_ahead_recompiles_for_what_its_guards_would_check():
    call = compiled_or_eager(affine, "a test program", ahead=True)
    ahead = call.fn
    assert isinstance(ahead, AheadOfTime)
    g = torch.Generator().manual_seed(0)
    x, w, b = (torch.randn(6, 5, generator=g), torch.randn(5, 4, generator=g),
               torch.randn(4, generator=g))
    cases = [
        (x, w, b), (x + 1, w, b), (x, w, b),  # the same key: one program
        (x.t().contiguous().t(), w, b),  # the same shape, other strides
        (torch.randn(3, 5, generator=g), w, b),  # another shape
        (x.double(), w.double(), b.double()),  # another dtype
        (x, w, None),  # None where a tensor was
    ]
    # to float rounding: where the compiled code folds the bias into the product (as on
    # some CPUs it does) the last bit can differ; a program run on arguments it was not
    # compiled for (another shape, layout or dtype) is wrong by far more, or fails
    for args in cases:
        torch.testing.assert_close(call(*args), affine(*args))
    assert len(ahead.programs) == 5
    assert all(p is not ahead.fallback for p in ahead.programs.values())  # all ahead
    with another_thread_count():
        torch.testing.assert_close(call(x, w, b), affine(x, w, b))
    assert len(ahead.programs) == 6


def test_the_key_holds_what_compiled_code_specialises_on():
    x = torch.zeros(2, 3)
    assert signature((x, None, 2.0)) == signature((torch.ones(2, 3), None, 2.0))
    for other in ((x.t().contiguous().t(), None, 2.0), (x.double(), None, 2.0),
                  (x, x, 2.0), (x, None, 3.0), [x, None, 2.0], (x[:1], None, 2.0)):
        assert signature(other) != signature((x, None, 2.0))
    assert signature({"a": x}) != signature({"b": x})


def graph_break(x: torch.Tensor) -> torch.Tensor:
    if x.sum().item() > 0:  # data-dependent Python control flow: no single graph
        return x * 2
    return x - 1


def test_a_function_that_cannot_be_compiled_ahead_runs_through_torch_compile(caplog):
    call = compiled_or_eager(graph_break, "a program with a graph break", ahead=True)
    with caplog.at_level(logging.INFO, logger="uabs_rl.env._compile"):
        for x in (torch.ones(3), -torch.ones(3), torch.ones(3)):
            assert torch.equal(call(x), graph_break(x))
    ahead = call.fn
    assert list(ahead.programs.values()) == [ahead.fallback]
    assert any("without ahead-of-time compilation" in r.message for r in caplog.records)


class Owner:
    """Holds a program whose function reads the owner (as the env wrapper's decision
    and step and the learner's update do): Dynamo's ahead-of-time compilation pickles
    what the traced function reaches, here the program with its compiled code."""

    def __init__(self):
        self.w = torch.randn(5, 4, generator=torch.Generator().manual_seed(1))
        self.call = compiled_or_eager(self.program(), "an owned program", ahead=True)

    def program(self):
        def run(x: torch.Tensor) -> torch.Tensor:
            return torch.relu(x @ self.w).sum(-1)
        return run


def test_a_program_reaching_itself_compiles_ahead_for_each_thread_count(caplog):
    """The training loop's programs reach their own AheadOfTime: each new key (another
    thread count, as the thread governor sets on a busy machine) still compiles ahead
    of time, not through the fallback (the programs compiled before do not pickle)."""
    owner = Owner()
    x = torch.randn(6, 5, generator=torch.Generator().manual_seed(2))
    def check():
        assert torch.equal(owner.call(x), torch.relu(x @ owner.w).sum(-1))

    with caplog.at_level(logging.INFO, logger="uabs_rl.env._compile"):
        check()
        with another_thread_count():
            check()
        check()
    ahead = owner.call.fn
    assert len(ahead.programs) == 2
    assert all(p is not ahead.fallback for p in ahead.programs.values()), caplog.text


CACHED_RUN = """
import torch
from torch._dynamo.utils import counters
from uabs_rl.env._compile import compiled_or_eager

def affine(x, w):
    return torch.relu(x @ w * SCALE).sum(-1)

call = compiled_or_eager(affine, "a cached program", ahead=True)
x, w = torch.ones(6, 5), torch.ones(5, 4)
assert torch.equal(call(x, w), affine(x, w))
(program,) = call.fn.programs.values()
assert program is not call.fn.fallback
cache = counters["aot_autograd"]
print(cache["autograd_cache_hit"], cache["autograd_cache_miss"])
"""


def test_a_program_compiled_ahead_is_found_in_inductors_cache_by_the_next_process():
    """The second process that compiles the same program ahead of time loads it from
    Inductor's on-disk cache (AOTAutograd's: a hit, no miss) instead of compiling it
    again, as the plain torch.compile path does; the first compiles it (a miss). The
    program is new to the cache (a constant of this test run in its graph); the cache
    is the machine's, whose compiler checks are already there."""
    import random
    import subprocess
    import sys
    code = f"SCALE = {1 + random.random()!r}\n" + CACHED_RUN
    runs = [subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                           text=True).stdout.split() for _ in range(2)]
    assert runs == [["0", "1"], ["1", "0"]]


def gathered(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """A small program of the env's kinds of indexing: a permuted 4-d view, a gather,
    a flatten of a strided slice."""
    y = x.permute(0, 2, 1, 3).reshape(x.shape[0], -1)
    g = torch.gather(y, 1, idx)
    return g.cumsum(-1) + x[:, ::2, 1:, :].flatten(1)[:, : g.shape[1]]


def test_linear_indices_kept_generates_the_same_code_without_simplifying_them(monkeypatch):
    """Within linear_indices_kept, Inductor's stride analysis no longer sends linear
    indices to sympy.simplify (fewer calls) and the generated C++ is the same, character
    for character, as without it (each compiled from scratch: no cache)."""
    import sympy
    from torch._inductor import config
    from torch._inductor.utils import run_and_get_code

    from uabs_rl.env._compile import _linear, linear_indices_kept

    calls = []
    real = sympy.simplify
    monkeypatch.setattr(sympy, "simplify", lambda e, *a, **k: calls.append(e) or real(e, *a, **k))
    x = torch.randn(4, 6, 5, 8)
    idx = torch.randint(0, 240, (4, 37))
    codes = []
    for kept in (False, True):
        torch._dynamo.reset()
        from torch._inductor import sizevars  # its analyses are cached per expression
        sizevars.stride_at_vec_range.cache_clear()
        sizevars.simplify_index_in_vec_range.cache_clear()
        sizevars.stride_at.cache_clear()
        calls.clear()
        program = torch.compile(gathered, dynamic=False, options={"cpp_wrapper": True})
        # torch's own patch: monkeypatch would delete the setting when it undoes itself
        with config.patch(fx_graph_cache=False), \
                linear_indices_kept() if kept else contextlib.nullcontext():
            out, code = run_and_get_code(program, x, idx)
        torch.testing.assert_close(out, gathered(x, idx), rtol=0, atol=1e-5)
        codes.append((code, len(calls), sum(map(_linear, calls))))
    (plain, n_plain, linear_plain), (kept, n_kept, linear_kept) = codes
    if not linear_plain:
        pytest.skip("Inductor analysed no linear index here (no vectorised C++ loops)")
    assert kept == plain
    assert n_kept < n_plain and linear_kept == 0, (n_kept, n_plain, linear_kept)


def test_programs_compiled_ahead_are_compiled_within_linear_indices_kept(monkeypatch):
    """AheadOfTime.build compiles inside the context, and Inductor's sympy is its own
    again afterwards."""
    from torch._inductor import sizevars

    import uabs_rl.env._compile as compile_module
    seen = []
    real = compile_module.linear_indices_kept

    @contextlib.contextmanager
    def spy():
        with real():
            seen.append(type(sizevars.sympy).__name__)
            yield

    monkeypatch.setattr(compile_module, "linear_indices_kept", spy)
    program = compiled_or_eager(affine, "affine", ahead=True)
    x, w = torch.randn(3, 4), torch.randn(4, 2)
    torch.testing.assert_close(program(x, w, None), affine(x, w, None))
    assert seen == ["_LinearKept"] and sizevars.sympy.__name__ == "sympy"


def test_linear_means_integer_multiples_of_symbols():
    import sympy
    from torch.utils._sympy.functions import FloorDiv

    from uabs_rl.env._compile import _linear
    d0, d1, x = sympy.symbols("d0 d1 x", integer=True)
    for e in (24 * d0 + 6 * d1 + 2, d0, sympy.Integer(3), -d1 + 4, 4 * x - 2 * d0):
        assert _linear(e) and sympy.simplify(e) == e
    for e in (FloorDiv(x, 4) + d0, d0 * d1, d0 / 2, 2 ** d0, sympy.Rational(1, 2) * d0):
        assert not _linear(e)
