"""benchmarks/planning_vs_learning.py flying its policies (``evaluate``) on the smoke
case's test traces: every mpc of ``--beams`` × ``--rounds`` flown with the search its row
names, every guarantee kept, and the rows written with their settings."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

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


@pytest.mark.parametrize("script,args,said", [
    ("decision_cost", ["RUN", "--policies", "mcp"], "'mcp' is not a policy: one of learned"),
    ("decision_cost", ["RUN", "--policies", "greedy:5"],
     "greedy searches nothing, so takes no horizon, beam or rounds"),
    ("decision_cost", ["NOWHERE", "--policies", "greedy"], "error: no checkpoint at NOWHERE"),
    ("hybrid", ["RUN", "--out", "OUT", "--predictor", "rod"], "invalid choice: 'rod'"),
    ("hybrid", ["RUN", "--out", "OUT", "--mpc-horizon", "0"], "--mpc-horizon must be >= 1"),
    ("hybrid", ["RUN", "--out", "OUT", "--eval-windows", "0"], "--eval-windows must be >= 1"),
    ("hybrid", ["NOWHERE", "--out", "OUT"], "error: no checkpoint at NOWHERE"),
    ("planning_vs_learning", ["--horizons", "0"], "--horizons must be >= 1, got 0"),
    ("planning_vs_learning", ["--paired", "RUN"], "RUN holds no per_window.json"),
    ("planning_vs_learning", ["--paired", "OLD", "--chosen-on", "OLD"],
     "OLD was not written by --split eval of this version of the script"),
    ("planning_vs_learning", ["--paired", "OLD", "--chosen-on", "OLD", "--learned", "RUN"],
     "--chosen-on and --learned are two readings of --paired: one at a time"),
    ("generalization", ["RUN", "--mpc", "0", "--at", "grid6:3"], "--mpc H must be >= 1"),
    ("cities_table", ["NOWHERE"], "NOWHERE holds no cities/ folder"),
])
def test_the_benchmarks_answer_bad_inputs_in_one_line(tmp_path, script, args, said):
    """What a user mistypes in the comparison scripts (before: tracebacks, a wrong flag
    named, a table silently without its mpc, an empty table with status 0, a log left in
    --out): one line, status 2, nothing written."""
    run, old = tmp_path / "run", tmp_path / "old"
    run.mkdir()
    old.mkdir()  # a folder of before --split: rows without their split and ms
    (old / "per_window.json").write_text(json.dumps(
        [{"scenario": "grid6", "mode": "rank", "n_uabs": 3, "policy": "mpc H=5 (cv)",
          "served_fractions": [0.3], "pgs": [0.3]}]))
    words = [str(run) if a == "RUN" else str(tmp_path / "out") if a == "OUT" else
             str(tmp_path / "nowhere") if a == "NOWHERE" else str(old) if a == "OLD" else a
             for a in args]
    said = said.replace("NOWHERE", str(tmp_path / "nowhere")).replace(
        "RUN", str(run)).replace("OLD", str(old))
    p = subprocess.run([sys.executable, f"benchmarks/{script}.py", *words],
                       capture_output=True, text=True, timeout=120,
                       cwd=Path(__file__).resolve().parents[1])
    assert p.returncode == 2 and said in p.stderr, p.stderr[-2000:]
    assert "Traceback" not in p.stderr and said in p.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "out").exists()


def test_a_learned_predictors_mpc_is_paired_with_cv_at_every_horizon():
    """``--paired``: the mpc over the learned predictor against constant velocity at its
    own horizon and at each other (is a longer search over it better than the default
    mpc?); the road predictor's against cv at its own only."""
    bench = load_benchmark("planning_vs_learning")
    w = [0.30, 0.32, 0.34, 0.31]
    rows = [{"mode": "rank", "n_uabs": 3, "policy": label,
             "served_fractions": [x + shift for x in w], "pgs": [x + shift for x in w]}
            for label, shift in (("mpc H=5 (cv)", 0.0), ("mpc H=10 (cv)", 0.001),
                                 ("mpc H=10 (learned)", 0.01), ("mpc H=10 (road)", 0.002))]
    lines = []
    bench.paired(rows, lines.append)
    learned = [ln for ln in lines if ln.startswith("rank M=3 mpc H=10 (learned) - ")]
    assert sorted(ln.split(" - ")[1].split(":")[0] for ln in learned) == [
        "mpc H=10 (cv)", "mpc H=5 (cv)"]
    line = next(ln for ln in learned if " - mpc H=5 (cv):" in ln)
    assert "served +1.00 [+1.00, +1.00]" in line  # 0.01 above on every window
    road = [ln for ln in lines if ln.startswith("rank M=3 mpc H=10 (road) - ")]
    assert [ln.split(" - ")[1].split(":")[0] for ln in road] == ["mpc H=10 (cv)"]


def test_the_validation_split_flies_every_one_of_its_windows(trace_cache, monkeypatch):
    """``--split eval``: the validation traces, every window of them (not the
    ``train.eval_windows`` that training evaluates on), each row saying its split."""
    bench = load_benchmark("planning_vs_learning")
    compose = bench.compose
    monkeypatch.setattr(bench, "compose", lambda name, over: compose(
        name, ["experiment=smoke", f"traces.cache_dir={trace_cache}", *over]))
    said = []
    rows, _ = bench.evaluate("rank", 3, [1], [], ["all"], said.append, split="eval")
    # the smoke case's validation traces: 90 s recorded after a 10 s warm-up, 20-step
    # episodes; train.eval_windows=2
    assert [r["windows"] for r in rows] == [4, 4, 4]
    assert {r["split"] for r in rows} == {"eval"}
    assert said[0] == "scenario=manhattan, rank masks, M=3: its validation traces"


def test_a_setting_is_chosen_on_validation_within_the_mpcs_cost_and_reported_on_test():
    """``--paired TEST --chosen-on VAL``: per predictor, the setting that served most on
    validation among those no costlier than the default mpc there (a costlier one that
    served more is passed over), then paired with the default mpc on test."""
    bench = load_benchmark("planning_vs_learning")
    w = [0.30, 0.32, 0.34, 0.31]

    def rows(split, shifts):
        return [{"scenario": "grid6", "split": split, "mode": "rank", "n_uabs": 6,
                 "policy": label, "sees": "all", "predictor": pred, "ms_per_decision": ms,
                 "served_fractions": [x + shifts[label] for x in w],
                 "pgs": [x + shifts[label] for x in w]}
                for label, pred, ms in (("mpc H=5 (cv)", "cv", 2.0),
                                        ("mpc H=5 (cv, beam 4)", "cv", 0.9),
                                        ("mpc H=5 (learned, beam 4)", "learned", 1.0),
                                        ("mpc H=5 (learned)", "learned", 2.1),
                                        ("mpc H=5 (learned, uncoordinated)", "learned",
                                         0.5),
                                        ("mpc H=5 (road)", "road", 2.2))]
    val = rows("eval", {"mpc H=5 (cv)": 0.0, "mpc H=5 (cv, beam 4)": -0.001,
                        "mpc H=5 (learned, beam 4)": 0.004, "mpc H=5 (learned)": 0.02,
                        "mpc H=5 (learned, uncoordinated)": 0.05, "mpc H=5 (road)": 0.1})
    test = rows("test", {"mpc H=5 (cv)": 0.0, "mpc H=5 (cv, beam 4)": 0.03,
                         "mpc H=5 (learned, beam 4)": 0.003, "mpc H=5 (learned)": -0.01,
                         "mpc H=5 (learned, uncoordinated)": 0.05, "mpc H=5 (road)": 0.1})
    lines = []
    bench.chosen(val, test, lines.append)
    learned = next(ln for ln in lines if ln.startswith("grid6 rank M=6 learned: chosen"))
    assert "chosen mpc H=5 (learned, beam 4) (validation 32.15 % against 31.75 %, 0.50x" in learned
    assert "test − mpc H=5 (cv): served +0.30 [+0.30, +0.30]" in learned
    cv = next(ln for ln in lines if ln.startswith("grid6 rank M=6 cv: chosen"))
    assert "chosen mpc H=5 (cv) (validation 31.75 % against 31.75 %, 1.00x" in cv
    assert ("grid6 rank M=6 learned's choice − cv's choice on test: served +0.30 "
            "[+0.30, +0.30] points") in lines
    # for scale, the choice made on the test windows: cv's differs from validation's
    assert any(ln.startswith("grid6 rank M=6 cv: best on test mpc H=5 (cv, beam 4): − mpc "
                             "H=5 (cv): served +3.00 [+3.00, +3.00]") for ln in lines)
    # a predictor whose every setting costs more than the mpc is said, not skipped
    assert ("grid6 rank M=6 road: no setting costs at most the mpc's 2.00 ms per decision "
            "on validation") in lines
    assert not any("road: chosen" in ln for ln in lines)
