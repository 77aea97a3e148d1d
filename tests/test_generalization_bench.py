"""benchmarks/generalization.py's table against the mpc: learned − mpc in the served
fraction and P_g per seed and window, each policy's ms per decision and the safety
counts summed over every rollout, checked on records of known values (no rollout)."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from tests.conftest import load_benchmark


def rec(served, pg, ms, collisions=0.0):
    return {"served": np.asarray(served), "pg": np.asarray(pg), "ms": ms,
            "collisions": collisions, "proximity": 0.0, "fallbacks": 0.0}


def test_the_table_holds_learned_minus_mpc_in_both_metrics_and_the_costs(
        monkeypatch, tmp_path, capsys):
    bench = load_benchmark("generalization")
    greedy = np.array([0.20, 0.30, 0.40, 0.50])
    seeds = [rec(greedy + 0.04, greedy + 0.10, 0.2), rec(greedy + 0.06, greedy + 0.12, 0.4)]
    base = {"greedy": rec(greedy, greedy + 0.05, 0.1),
            "oracle": rec(greedy + 0.02, greedy + 0.07, 0.1),
            "mpc": rec(greedy + 0.10, greedy + 0.20, 3.0, collisions=1.0)}

    asked = []

    def evaluate(runs, over, dirs, baselines=(), mpc_horizon=5, beam=None, rounds=None):
        assert over == ["scenario=grid6", "scenario.n_uabs=6"] and mpc_horizon == 5
        asked.append((beam, rounds))
        assert "mpc" in baselines
        return seeds, dict(base)

    class Runs:
        def __init__(self, path):
            pass

        def members(self):
            return ["seed=0", "seed=1"]

    monkeypatch.setattr(bench, "evaluate", evaluate)
    monkeypatch.setattr(bench, "RunFolder", Runs)
    out = tmp_path / "t.csv"
    bench.main(["runs", "--at", "grid6:6", "--mpc", "5", "--csv", str(out)])
    (row,) = csv.DictReader(out.open())
    # per seed the mean paired difference (−0.06, −0.04), then their mean over seeds
    assert float(row["learned_minus_mpc"]) == pytest.approx(-0.05)
    assert float(row["pg_learned_minus_mpc"]) == pytest.approx(-0.09)
    assert float(row["mpc_ci_low"]) < -0.05 < float(row["mpc_ci_high"])
    assert float(row["pg_mpc"]) == pytest.approx(0.55)
    assert float(row["ms_learned"]) == pytest.approx(0.3)
    assert float(row["ms_mpc"]) == pytest.approx(3.0)
    assert float(row["collisions"]) == 1.0 and float(row["fallbacks"]) == 0.0
    printed = capsys.readouterr()
    assert "P_g(5)" in printed.out and "-5.00 [" in printed.out and "-9.00 [" in printed.out
    assert "1 collisions" in printed.err

    from uabs_rl.evaluation.planner import BEAM, ROUNDS

    assert asked == [(BEAM, ROUNDS)] and (row["mpc_beam"], row["mpc_rounds"]) == (
        str(BEAM), str(ROUNDS))
    # the mpc's search as asked, in its columns
    bench.main(["runs", "--at", "grid6:6", "--mpc", "5", "--mpc-beam", "4", "--mpc-rounds",
                "1", "--csv", str(out)])
    (row,) = csv.DictReader(out.open())
    assert asked[-1] == (4, 1) and (row["mpc_beam"], row["mpc_rounds"]) == ("4", "1")


def test_a_recorded_mpc_of_another_search_is_refused_with_the_command(tmp_path):
    """``--mpc-from``: a uabs-eval record of the mpc at the default search is refused for
    ``--mpc-beam 4 --mpc-rounds 1`` (and taken for the default), naming the command."""
    import json

    bench = load_benchmark("generalization")
    path = tmp_path / "eval.json"
    path.write_text(json.dumps({"split": "test", "overrides": ["scenario=grid6",
                                                               "scenario.n_uabs=6"],
                                "policies": {"mpc": {
                                    "horizon": 5, "predictor": "cv", "sees": "all",
                                    "served_fractions": [0.3], "pgs": [0.4],
                                    "collisions": 0, "proximity": 0, "fallbacks": 0}}}))
    assert bench.mpc_from(path, "grid6:6", 5)["served"].tolist() == [0.3]
    with pytest.raises(SystemExit, match="set the search of --mpc H: give --mpc H too"):
        bench.main(["runs", "--at", "grid6:6", "--mpc-beam", "4"])
    with pytest.raises(SystemExit, match="beam 4, 1 round.*--mpc-horizon 5 --mpc-beam 4 "
                                         "--mpc-rounds 1$"):
        bench.mpc_from(path, "grid6:6", 5, beam=4, rounds=1)
