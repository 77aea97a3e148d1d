"""The hybrid policy (``uabs-eval --policy hybrid``): the mpc's scores plus λ times the
learned Q-values, through the masks. With λ = 0 it is the mpc action for action; with a
λ that dwarfs the planner's scores it flies the learned policy's moves; it reports its
settings and refuses a bad weight in one line."""

from __future__ import annotations

import json

import pytest
import torch

from tests.test_train import smoke
from uabs_rl.cli.evaluate import main as eval_main
from uabs_rl.env.uabs_env import ACTION
from uabs_rl.evaluation.hybrid import HybridScore
from uabs_rl.evaluation.load import evaluate_policies, load_evaluation
from uabs_rl.training.resume import run


@pytest.fixture(scope="module")
def rank_run(trace_cache, tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("hybrid") / "run"
    run(smoke(trace_cache, "train.episodes=6", "train.trajectory_images=false"), run_dir)
    return run_dir


def actions(rank_run, *policies: str, weight: float) -> dict[str, torch.Tensor]:
    ev = load_evaluation(rank_run, "last", 3, "test")
    out = evaluate_policies(ev, policies, mpc_horizon=3, hybrid_weight=weight)
    for rec, _ in out.values():  # every guarantee kept
        assert rec["collisions"] == rec["proximity"] == rec["fallbacks"] == 0
    return {name: td.get(ACTION) for name, (_, td) in out.items()}


def test_hybrid_with_weight_0_is_the_mpc_action_for_action(rank_run):
    a = actions(rank_run, "mpc", "hybrid", weight=0.0)
    assert torch.equal(a["hybrid"], a["mpc"])


def test_hybrid_with_an_overwhelming_weight_flies_the_learned_moves(rank_run):
    """The planner's scores are sums of priorities over 3 steps (hundreds at most) plus a
    jitter below 1e-3; at λ = 1e7 they only break exact ties of λ·Q, which floats of a
    trained network do not make: the learned policy's moves, step for step."""
    a = actions(rank_run, "learned", "hybrid", weight=1e7)
    assert torch.equal(a["hybrid"], a["learned"])
    # and the two terms differ here: the mpc does not fly the learned moves
    assert not torch.equal(actions(rank_run, "mpc", weight=0.0)["mpc"], a["learned"])


def test_uabs_eval_hybrid_reports_its_settings(rank_run, tmp_path, capsys):
    out = tmp_path / "ev"
    assert eval_main([str(rank_run), "--checkpoint", "last", "--policy", "hybrid",
                      "--hybrid-weight", "0.5", "--mpc-horizon", "2", "--windows", "2",
                      "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rec = json.loads((out / "eval.json").read_text())["policies"]["hybrid"]
    assert (rec["horizon"], rec["predictor"], rec["sees"], rec["weight"]) == (2, "cv", "all", 0.5)
    assert "hybrid: horizon 2, beam 16, 2 rounds, predictor cv, sees every vehicle, weight 0.5 " \
           "of the learned Q-values; " in text
    assert rec["ms_per_decision"] > 0


@pytest.mark.parametrize("weight", ["-1", "nan", "inf"])
def test_a_bad_hybrid_weight_is_one_line(weight, capsys):
    with pytest.raises(SystemExit) as e:
        eval_main(["RUN", "--policy", "hybrid", "--hybrid-weight", weight])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--hybrid-weight must be a number >= 0" in err[0]


def test_hybrid_score_refuses_a_negative_weight():
    with pytest.raises(ValueError, match="weight must be >= 0"):
        HybridScore(None, None, -0.5)
