"""Population training (train.population): members equal their solo runs where the
docs say they do, write solo run folders that uabs-eval, uabs-report and resume read,
and one batched update is every member's solo update."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from tests.test_algorithms import batch, dqn3
from tests.test_train import records, smoke
from uabs_rl.algorithms.model import DuelingQNet
from uabs_rl.config import AlgoConfig, ConfigError
from uabs_rl.evaluation.load import load_evaluation
from uabs_rl.rng import Generators, rand, randint
from uabs_rl.runs.checkpoint import CheckpointError, Interrupted, load_checkpoint
from uabs_rl.runs.sweep import find_runs
from uabs_rl.training.experiment import Experiment
from uabs_rl.training.resume import prepare, run
from uabs_rl.training.startup import validate_run

QUIET = ["train.trajectory_images=false", "train.logger=none"]


def same(a: list[dict], b: list[dict]) -> bool:
    """Records equal value for value (NaN equal to NaN: a round without updates)."""
    def norm(r):
        return {k: ("nan" if isinstance(v, float) and math.isnan(v) else v)
                for k, v in r.items()}
    return [norm(r) for r in a] == [norm(r) for r in b]


def test_generators_draw_each_members_rows_as_its_solo_run(trace_cache):
    gens = Generators([3, 4])
    pop = rand((4, 5), gens, "cpu")
    ints = randint(0, 9, (2, 3), gens, "cpu")
    for i, s in enumerate([3, 4]):
        g = torch.Generator().manual_seed(s)
        assert torch.equal(pop[2 * i:2 * i + 2], torch.rand(2, 5, generator=g))
        assert torch.equal(ints[i:i + 1], torch.randint(0, 9, (1, 3), generator=g))
    with pytest.raises(ValueError, match="do not split"):
        rand((3, 5), gens, "cpu")


def test_members_without_updates_equal_their_solo_runs(trace_cache, tmp_path):
    """No update (learning never starts): every record of every member, training and
    evaluation, equals its solo run's: the env, exploration and evaluation draws are
    the solo run's, seed for seed."""
    args = ["algo.learning_starts=100000", "algo.buffer_size=100000", *QUIET]
    run(smoke(trace_cache, "seed=3", "train.population=2", *args), tmp_path / "pop")
    for s in (3, 4):
        run(smoke(trace_cache, f"seed={s}", *args), tmp_path / f"solo{s}")
        solo, member = records(tmp_path / f"solo{s}"), records(tmp_path / "pop" / f"seed={s}")
        assert len(member) == 8 and same(member, solo)
    # members differ from each other (their own seeds)
    assert records(tmp_path / "pop" / "seed=3") != records(tmp_path / "pop" / "seed=4")


def test_members_with_updates_track_their_solo_runs(trace_cache, tmp_path):
    """With updates the batched products round differently from the solo ones: the
    first round's losses agree to float precision."""
    run(smoke(trace_cache, "train.population=2", *QUIET), tmp_path / "pop")
    run(smoke(trace_cache, "seed=1", *QUIET), tmp_path / "solo1")
    solo = [r for r in records(tmp_path / "solo1") if r["kind"] == "train"]
    member = [r for r in records(tmp_path / "pop" / "seed=1") if r["kind"] == "train"]
    first = next(i for i, r in enumerate(solo) if not math.isnan(r["loss"]))
    assert member[first]["updates"] == solo[first]["updates"] > 0
    assert member[first]["loss"] == pytest.approx(solo[first]["loss"], rel=1e-4)
    assert same(member[:first + 1], solo[:first + 1]) or \
        member[first]["return"] == solo[first]["return"]


def test_one_population_update_is_each_members_solo_update():
    algo = AlgoConfig(hidden=[64, 64], lr=1e-3, target_update=1, grad_clip=0.5)
    pop = dqn3(algo, seeds=(0, 1, 2))
    solos = [dqn3(algo, seeds=(s,)) for s in (0, 1, 2)]
    for step in range(3):
        bs = [batch(seed=10 * step + i) for i in range(3)]
        stacked = {k: torch.stack([b[k] for b in bs]) for k in bs[0]}
        losses, _ = pop.update(stacked)
        for i, (learner, b) in enumerate(zip(solos, bs, strict=True)):
            loss, _ = learner.update(b)
            assert losses[i].item() == pytest.approx(loss.item(), rel=1e-5)
    for i, learner in enumerate(solos):
        member = pop.member_state_dict(i)
        for part in ("qnet", "target"):
            for k, v in learner.state_dict()[part].items():
                torch.testing.assert_close(member[part][k], v, rtol=1e-5, atol=1e-6)
        mine = learner.optim.state_dict()["state"]
        for j, st in member["optim"]["state"].items():
            torch.testing.assert_close(st["exp_avg"], mine[j]["exp_avg"], rtol=1e-4, atol=1e-7)
            assert st["step"].item() == mine[j]["step"].item() == 3
        # the member's state loads into a solo learner and back unchanged
        solo = dqn3(algo, seeds=(9,))
        solo.load_state_dict(member)
        pop.load_member(i, solo.state_dict())
        assert all(torch.equal(a, b) for a, b in zip(
            pop.member_state_dict(i)["qnet"].values(), member["qnet"].values(), strict=True))


def test_members_write_solo_run_folders_read_by_eval_and_report(trace_cache, tmp_path):
    run(smoke(trace_cache, "train.population=2", "train.logger=none"), tmp_path)
    runs = find_runs(tmp_path)
    assert sorted(r.path.name for r in runs) == ["seed=0", "seed=1"]
    for s in (0, 1):
        d = tmp_path / f"seed={s}"
        assert (d / "eval" / "best_trajectories.png").is_file()
        state = load_checkpoint(d / "checkpoints" / "best.pt")
        assert state["config"]["seed"] == s and state["population"]["seeds"] == [0, 1]
        net = DuelingQNet(state["learner"]["qnet"]["trunk.0.weight"].shape[1], 4, [32, 32])
        net.load_state_dict(state["learner"]["qnet"])  # a solo network's state
        # uabs-eval's evaluation of the member's best.pt is the member's best record
        best = [r for r in records(d) if r["kind"] == "eval"
                and r["episode"] == state["counters"]["episode"]][0]
        again, _ = load_evaluation(d, "best", split="eval").evaluator.evaluate(
            load_evaluation(d, "best", split="eval").greedy)
        for key in ("return", "returns", "collisions", "pg_curve", "served_fraction"):
            assert again[key] == pytest.approx(best[key]), key


def test_a_population_resumes_as_one_and_refuses_a_member_alone(trace_cache, tmp_path):
    args = ["train.population=2", "train.checkpoint_buffer=true", *QUIET]
    run(smoke(trace_cache, *args), tmp_path / "ref")
    pop = prepare(smoke(trace_cache, *args), tmp_path / "pop")
    collect = pop.collect

    def stop_after_3():  # as Ctrl-C would: the round ends, last.pt is saved
        out = collect()
        pop.interrupt.requested = pop.episode == 3
        return out
    pop.collect = stop_after_3
    with pytest.raises(Interrupted):
        pop.fit()
    run(smoke(trace_cache, *args, f"resume={tmp_path / 'pop'}"), Path("unused"))
    for s in (0, 1):
        assert same(records(tmp_path / "pop" / f"seed={s}"),
                    records(tmp_path / "ref" / f"seed={s}"))
    alone = smoke(trace_cache)
    alone.resume = str(tmp_path / "pop" / "seed=0")
    with pytest.raises(CheckpointError, match=r"member of a population.*resume=.*pop\."):
        prepare(alone, Path("unused"))
    with pytest.raises(ConfigError, match="already holds a run"):
        prepare(smoke(trace_cache, *args), tmp_path / "pop")


@pytest.mark.parametrize("override,key", [("train.population=0", "train.population"),
                                          ("algo.loss=torchrl", "algo.loss")])
def test_bad_population_settings_name_the_key(trace_cache, override, key):
    cfg = smoke(trace_cache, "train.population=2", override)
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        validate_run(cfg)
    with pytest.raises(ConfigError):
        Experiment(cfg, Path("unused"))


def test_run_folder_members_by_seed_or_the_run_alone(tmp_path):
    """The runs a benchmark flies: a population's members in seed order (10 after 2),
    a single run as itself."""
    from uabs_rl.runs.layout import RunFolder

    for s in (10, 2, 0):
        (tmp_path / "pop" / f"seed={s}").mkdir(parents=True)
    assert RunFolder(tmp_path / "pop").members() == [
        tmp_path / "pop" / f"seed={s}" for s in (0, 2, 10)]
    assert RunFolder(tmp_path / "pop" / "seed=2").members() == [tmp_path / "pop" / "seed=2"]
