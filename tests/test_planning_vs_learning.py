"""benchmarks/planning_vs_learning.py flying its policies (``evaluate``) on the smoke
case's test traces: every mpc of ``--beams`` × ``--rounds`` flown with the search its row
names, every guarantee kept, and the rows written with their settings."""

from __future__ import annotations

import json
import sys

from tests.conftest import load_benchmark


def test_each_mpc_is_flown_with_the_beam_and_passes_its_row_names(trace_cache, monkeypatch,
                                                                   tmp_path):
    bench = load_benchmark("planning_vs_learning")
    compose = bench.compose
    monkeypatch.setattr(bench, "compose", lambda name, over: compose(
        name, ["experiment=smoke", f"traces.cache_dir={trace_cache}", *over]))
    flown, policy = {}, bench.baseline_policy

    def spy(name, env, selector, seed, **kw):  # what each policy was built with
        made = policy(name, env, selector, seed, **kw)
        flown[len(flown)] = (name, kw.get("horizon"), kw.get("beam"), kw.get("rounds"))
        return made

    monkeypatch.setattr(bench, "baseline_policy", spy)
    rows, errs = bench.evaluate("rank", 3, [3], [], ["all"], lambda line: None,
                                beams=(16, 4), rounds=(2, 1))
    said = [(r["policy"], r["horizon"], r["beam"], r["rounds"]) for r in rows]
    assert said == [("greedy", 1, None, None), ("oracle", 1, None, None),
                    ("mpc H=3 (cv)", 3, 16, 2), ("mpc H=3 (cv, 1 round)", 3, 16, 1),
                    ("mpc H=3 (cv, beam 4)", 3, 4, 2),
                    ("mpc H=3 (cv, beam 4, 1 round)", 3, 4, 1)]
    # an untimed greedy rollout first (its one-off costs kept out of the first row's ms)
    assert [flown[i][0] for i in range(3)] == ["greedy", "greedy", "oracle"]
    assert [flown[i][2:] for i in range(3, 7)] == [(16, 2), (16, 1), (4, 2), (4, 1)]
    for r in rows:
        assert r["collisions"] == r["proximity"] == r["fallbacks"] == 0, r["policy"]
        assert r["windows"] == len(r["served_fractions"]) > 1
    assert {e["predictor"] for e in errs} == {"cv"}

    # the files: per_window.json names each row's search, not only its label
    monkeypatch.setattr(bench, "evaluate", lambda *a, **k: (rows, errs))
    monkeypatch.setattr(sys, "argv", ["planning_vs_learning.py", "--horizons", "3",
                                      "--out", str(tmp_path)])
    bench.main()
    written = json.loads((tmp_path / "per_window.json").read_text())
    assert [(w["policy"], w["horizon"], w["beam"], w["rounds"]) for w in written] == said
    assert {(w["scenario"], w["mode"], w["n_uabs"]) for w in written} == {("manhattan", "rank", 3)}
    table = (tmp_path / "table.csv").read_text().splitlines()
    assert table[0].startswith("scenario,mode,n_uabs,policy,horizon,beam,rounds,")
    assert table[1].startswith("manhattan,rank,3,greedy,1,,,")
