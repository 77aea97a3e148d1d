"""The compiled update (uabs_rl.algorithms.compiled_update): the same learning as the
eager update up to float32 rounding, for every learner, without recompiling.

Compiled and eager updates are not bit-identical (Inductor's fused loops add in another
order than the eager kernels), so these tests bound the difference instead:

* the loss of every update, from the same state on the same batch, agrees to
  ``LOSS_RTOL`` = 1e-5 relative. The loss is a mean of Huber terms over a batch of a
  few hundred rows, each from products of length <= 256 in three layers; adding n
  float32 terms in another order moves a sum by about sqrt(n) ulps (eps = 6e-8, so
  about 1e-6 here; measured up to 5.5e-7 over 200 updates), while any real difference
  (a mask, a target, a missed term) moves it by at least one row's share, 1/384 ~ 3e-3;
* the parameters after ``UPDATES`` updates differ by at most ``PARAM_ATOL`` = 1e-6: one
  hundredth of one Adam step (lr = 1e-4). Adam normalises its steps, so a gradient that
  differs by rounding moves a weight by a few ulps (measured <= 3e-8 after 200
  updates, one or two ulps of the largest weights), while a wrong gradient moves it by
  whole steps within the first updates.
"""

from __future__ import annotations

import math

import pytest
import torch

from tests.conftest import another_thread_count, thread_count
from uabs_rl.algorithms import Dims, make_algorithm
from uabs_rl.algorithms.base import Algorithm
from uabs_rl.algorithms.compiled_update import LossProgram
from uabs_rl.config import algo_schema

LOSS_RTOL = 1e-5
PARAM_ATOL = 1e-6
UPDATES = 100


def learner(name: str, members: int, replay: str = "uniform", grad_clip: float | None = None,
            hidden: tuple[int, ...] = (32, 32)):
    """A small learner (3 agents) whose replay holds 400 random env steps per member
    (``dqfd``: with random teacher labels, some missing)."""
    algo = algo_schema(name)(name=name, replay=replay, hidden=list(hidden), target_update=20,
                             grad_clip=grad_clip)
    m = make_algorithm(algo, Dims(18, 4, 3), list(range(members)), torch.device("cpu"))
    g = torch.Generator().manual_seed(1)
    n = 400 * members
    labels = {"teacher": torch.randint(-1, 4, (n, 3), generator=g)} if name == "dqfd" else {}
    m.buffer.extend({**labels,
        "obs": torch.randn(n, 3, 18, generator=g),
        "action": torch.randint(0, 4, (n, 3), generator=g),
        "mask": torch.ones(n, 3, 4, dtype=torch.bool), "reward": torch.randn(n, 3, generator=g),
        "next_obs": torch.randn(n, 3, 18, generator=g),
        "next_mask": torch.rand(n, 3, 4, generator=g) < 0.7,
        "terminated": torch.rand(n, 3, generator=g) < 0.1})
    return m


def parameters(m) -> list[torch.Tensor]:
    extras = [q for e in m.extras if e is not None for q in e.parameters()]
    return [*m.policy.parameters(), *extras, *m.loss_module.target_network.parameters()]


def check_tracks_eager(name: str, members: int, replay: str = "uniform",
                       grad_clip: float | None = None) -> Algorithm:
    eager = learner(name, members, replay, grad_clip)
    compiled = learner(name, members, replay, grad_clip)
    compiled.compile_update()
    for _ in range(UPDATES):
        b = eager.buffer.sample()
        compiled.buffer.sample()  # the same draws from its own generator
        le, qe = eager.update(b)
        lc, qc = compiled.update(b)
        torch.testing.assert_close(lc, le, rtol=LOSS_RTOL, atol=0)
        torch.testing.assert_close(qc, qe, rtol=LOSS_RTOL, atol=1e-6)
    assert compiled.compiled  # it ran compiled, not the eager fallback
    # one program, compiled once, ahead of time: no recompile over the updates (static
    # shapes, the target's copies in place)
    programs = compiled.whole.compiled.programs
    assert len(programs) == 1
    assert all(p is not compiled.whole.compiled.fallback for p in programs.values())
    for pe, pc in zip(parameters(eager), parameters(compiled), strict=True):
        torch.testing.assert_close(pc, pe, rtol=0, atol=PARAM_ATOL)
    if replay == "prioritized":  # the TD errors set the same priorities
        held = eager.buffer.held_items()
        for se, sc in zip(eager.buffer.samplers, compiled.buffer.samplers, strict=True):
            torch.testing.assert_close(sc.state_dict(held)["priority"],
                                       se.state_dict(held)["priority"], rtol=1e-4, atol=0)
    return compiled


def test_compiled_3dqn_update_tracks_the_eager_one():
    compiled = check_tracks_eager("dqn3", 1)
    # another thread count (the thread governor's, on a busy machine) compiles a second
    # program, ahead of time too
    with another_thread_count():
        compiled.update(compiled.buffer.sample())
    programs = compiled.whole.compiled.programs
    assert len(programs) == 2
    assert all(p is not compiled.whole.compiled.fallback for p in programs.values())


@pytest.mark.slow
@pytest.mark.parametrize("name, members, replay, grad_clip", [
    ("dqn3", 3, "uniform", None), ("dqn3", 1, "prioritized", None), ("vdn", 2, "uniform", None),
    ("qmix", 1, "uniform", None), ("qmix", 2, "uniform", None), ("dqfd", 2, "uniform", None),
    # a bound the random batches' gradients exceed, so every update is clipped
    ("dqn3", 1, "uniform", 0.05), ("qmix", 2, "uniform", 0.05)])
def test_compiled_update_tracks_the_eager_one(name, members, replay, grad_clip):
    check_tracks_eager(name, members, replay, grad_clip)


def test_a_failing_compile_falls_back_to_the_eager_update(monkeypatch, caplog):
    """The first call's compilation error (here: no working C++ compiler) is one warning,
    then the same update eagerly: bit-identical to an eager learner's."""
    eager, fallback = learner("dqn3", 1), learner("dqn3", 1)

    def broken(*args, **kwargs):
        def fail(*a, **k):
            raise RuntimeError("no C++ compiler")
        return fail

    monkeypatch.setattr(torch, "compile", broken)
    fallback.compile_update()
    for _ in range(3):
        b = eager.buffer.sample()
        fallback.buffer.sample()
        assert torch.equal(fallback.update(b)[0], eager.update(b)[0])
    assert not fallback.compiled
    assert [r.message for r in caplog.records if "torch.compile failed" in r.message] and \
        len([r for r in caplog.records if "torch.compile failed" in r.message]) == 1
    for pe, pf in zip(parameters(eager), parameters(fallback), strict=True):
        assert torch.equal(pe, pf)


def test_without_ahead_of_time_compilation_the_update_is_the_same():
    """Where a program cannot be compiled ahead (AheadOfTime's fallback: the plain
    torch.compile function, its guards checked once per key), updates are those of the
    ahead-of-time program bit for bit."""
    ahead, plain = learner("dqn3", 1), learner("dqn3", 1)
    ahead.compile_update()
    plain.compile_update()
    program = plain.whole.compiled
    program.build = lambda args: program.fallback  # as when aot_compile fails
    for _ in range(5):
        b = ahead.buffer.sample()
        plain.buffer.sample()
        assert torch.equal(plain.update(b)[0], ahead.update(b)[0])
    assert list(program.programs.values()) == [program.fallback]
    assert all(p is not ahead.whole.compiled.fallback
               for p in ahead.whole.compiled.programs.values())
    for pa, pp in zip(parameters(ahead), parameters(plain), strict=True):
        assert torch.equal(pa, pp)


def test_an_eager_program_raises_its_errors():
    program = LossProgram(lambda b: (_ for _ in ()).throw(ValueError("bad batch")))
    with pytest.raises(ValueError, match="bad batch"):
        program(None, lambda: None)


@pytest.mark.slow
def test_a_compiled_run_learns_within_the_eager_seed_spread(trace_cache, tmp_path):
    """A short training run (3 seeds in a population) with ``train.compile_update=true``:
    at every evaluation the compiled members' mean return lies within the eager
    members' range of returns, widened by that range (rounding differences change
    ε-greedy choices on near ties, so the runs part like different seeds do, not more)."""
    from tests.test_train import records, smoke
    from uabs_rl.training.resume import run

    args = ["train.population=3", "train.episodes=30", "train.eval_every=5",
            "train.trajectory_images=false", "train.logger=none"]
    run(smoke(trace_cache, *args), tmp_path / "eager")
    run(smoke(trace_cache, *args, "train.compile_update=true"), tmp_path / "compiled")

    def curves(run_dir):
        return [[r["return"] for r in records(run_dir / f"seed={s}") if r["kind"] == "eval"]
                for s in range(3)]

    eager, compiled = curves(tmp_path / "eager"), curves(tmp_path / "compiled")
    assert len(eager[0]) == len(compiled[0]) == 6
    for i in range(6):
        at = [c[i] for c in eager]
        spread = max(at) - min(at)
        mean = sum(c[i] for c in compiled) / 3
        assert min(at) - spread <= mean <= max(at) + spread, (i, at, mean)
        assert not any(math.isnan(c[i]) for c in compiled)


def test_the_programs_adam_step_is_torchs_fused_adam():
    """:func:`adam_` (with :meth:`UpdateProgram.corrections`' step sizes) against
    ``torch.optim.Adam(fused=True)`` over 200 steps of the same gradients: the parameters
    agree to float32 rounding (the same formula; Inductor may fuse it otherwise), and the
    moments and the step count are Adam's own state."""
    from uabs_rl.algorithms.compiled_update import adam_

    g = torch.Generator().manual_seed(0)
    ref = torch.nn.Parameter(torch.randn(64, 32, generator=g))
    mine = ref.detach().clone()
    opt = torch.optim.Adam([ref], lr=1e-3, fused=True)
    m, v, step = torch.zeros_like(mine), torch.zeros_like(mine), torch.zeros(())
    beta1, beta2 = opt.param_groups[0]["betas"]
    for _ in range(200):
        grad = torch.randn(64, 32, generator=g) * torch.rand((), generator=g)
        ref.grad = grad.clone()
        opt.step()
        t = float(step) + 1
        adam_(mine, grad, m, v, step, beta1, beta2, 1e-8,
              torch.tensor(1e-3 / (1 - beta1 ** t), dtype=torch.float64),
              torch.tensor(math.sqrt(1 - beta2 ** t), dtype=torch.float64))
    st = opt.state[ref]
    assert float(step) == float(st["step"]) == 200
    torch.testing.assert_close(m, st["exp_avg"], rtol=1e-5, atol=1e-8)
    torch.testing.assert_close(v, st["exp_avg_sq"], rtol=1e-5, atol=1e-10)
    torch.testing.assert_close(mine, ref.detach(), rtol=0, atol=1e-6)


@pytest.mark.parametrize("compile, every_layer", [(False, False), (True, False), (True, True)])
def test_grouped_member_products_keep_the_population_update_bit_for_bit(monkeypatch, compile,
                                                                         every_layer):
    """Three members on two threads: the paper network's 256 x 256 layer runs two members
    batched and the third on its own (``member_products``; with ``every_layer``, every
    layer, heads and the 18-wide first layer included, shapes it leaves batched). The
    population's updates, eager and compiled, leave every parameter as the single
    batched product does, bit for bit: the grouping changes which threads compute a
    member, not what they add in which order (measured on this machine's MKL, not
    promised by it: a CPU where it fails fails here). Left to autograd, the grouped
    products' backward compiled to a wrong weight gradient: the compiled case without
    ``every_layer`` fails on it."""
    from uabs_rl.algorithms import model
    with thread_count(2):
        # the replay batch's 128 rows through the 256 x 256 layer: two batched, one alone
        assert model.batched_members(3, 128, 256, 256) == 2
        runs = []
        for grouped in (True, False):
            if every_layer and grouped:
                for limit in ("MACS", "ROWS", "INPUTS"):
                    monkeypatch.setattr(model, f"OWN_PRODUCT_{limit}", 0)
                assert model.batched_members(3, 128, 18, 256) == 2
            if not grouped:
                monkeypatch.setattr(model, "OWN_PRODUCT_MACS", math.inf)
                assert model.batched_members(3, 128, 256, 256) == 3
            m = learner("dqn3", 3, hidden=(256, 256))
            m.compile_update(compile)
            for _ in range(10):
                m.update(m.buffer.sample())
            assert m.compiled == compile
            runs.append(parameters(m))
    for grouped, batched in zip(*runs, strict=True):
        assert torch.equal(grouped, batched)
