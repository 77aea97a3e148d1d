"""benchmarks/cities_table.py: the one table of every (city, M) from the folders the
other benchmarks wrote, checked on folders of known values (nothing flown)."""

from __future__ import annotations

import csv
import json
import sys

import pytest

from tests.conftest import load_benchmark

GREEDY = [0.20, 0.30, 0.40, 0.50]


def planners(folder, m, served, scenario="grid6"):
    """A planning_vs_learning.py folder: ``served`` maps a policy to its per-window
    values."""
    folder.mkdir(parents=True)
    (folder / "log.txt").write_text(f"scenario={scenario}, rank masks, M={m}: its test traces\n")
    rows = [{"mode": "rank", "n_uabs": m, "policy": p, "served": sum(v) / len(v),
             "pg": sum(v) / len(v) + 0.01} for p, v in served.items()]
    with open(folder / "table.csv", "w", newline="") as f:
        w = csv.DictWriter(f, list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (folder / "per_window.json").write_text(json.dumps(
        [{"mode": "rank", "n_uabs": m, "policy": p, "served_fractions": v,
          "pgs": [x + 0.01 for x in v]} for p, v in served.items()]))


def hybrid(folder, mpc, learned, flown, weight, kind=None):
    folder.mkdir(parents=True)
    kind = kind or ("leaf" if folder.name.startswith("leaf_") else "hybrid")
    (folder / "hybrid.json").write_text(json.dumps({
        "hybrid": kind,
        "best_weight": weight, "mpc_horizon": 5, "predictor": "cv", "sees": "all",
        "members": ["outputs/runs/generalist_rank5/seed=0"], "policies": {
            "mpc": {"served": mpc, "pg": [x + 0.01 for x in mpc]},
            "learned": {"served": learned}, "hybrid": {"served": flown, "pg": flown}}}))


def test_the_table_pairs_learned_and_hybrid_with_the_mpc_and_the_best_mpc(
        tmp_path, monkeypatch, capsys):
    bench = load_benchmark("cities_table")
    mpc5 = [x + 0.10 for x in GREEDY]
    mpc10 = [x + 0.12 for x in GREEDY]  # the best mpc: 2 points above H = 5
    planners(tmp_path / "cities/planners_grid6", 3,
             {"greedy": GREEDY, "mpc H=5 (cv)": mpc5, "mpc H=10 (road)": mpc10})
    (tmp_path / "cities").mkdir(exist_ok=True)
    with open(tmp_path / "cities/table.csv", "w", newline="") as f:
        w = csv.DictWriter(f, ["city", "M", "learned", "pg_learned", "other"])
        w.writeheader()
        w.writerow({"city": "grid6", "M": 3, "learned": 0.37, "pg_learned": 0.38, "other": ""})
    learned = [[x + 0.05 for x in GREEDY], [x + 0.07 for x in GREEDY]]
    hybrid(tmp_path / "cities/hybrid_grid6", mpc5, learned, [mpc5, [x + 0.01 for x in mpc5]],
           0.5)
    # the leaf values: the mpc + 3 and + 4 points: +3.5 against H = 5, +1.5 against the best
    hybrid(tmp_path / "cities/leaf_grid6_3", mpc5, learned,
           [[x + 0.03 for x in mpc5], [x + 0.04 for x in mpc5]], 1.0)
    monkeypatch.setattr(sys, "argv", ["cities_table.py", str(tmp_path)])
    bench.main()
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| grid6 | 3 | mpc"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2:4] == ["mpc H=10 road", "47.00"]
    # learned − mpc H=5: per member −5 and −3 points, mean −4; − best mpc: −6
    assert cells[4].startswith("-4.00 [") and cells[5].startswith("-6.00 [")
    # hybrid: the mpc, and the mpc + 1 point: +0.5 against H = 5, −1.5 against the best
    assert cells[6].startswith("+0.50 [") and cells[7].startswith("-1.50 [")
    assert cells[8].startswith("+3.50 [") and cells[9].startswith("+1.50 [")
    assert "45.50 (λ* = 0.5)" in out  # the hybrid's mean over members and windows
    assert "48.50 (λ* = 1)" in out  # the leaf's
    assert cells[10:] == ["generalist_rank5", "generalist_rank5"]
    for line in out.splitlines():  # every row as wide as its table's header
        if line.startswith("| city"):
            width = line.count("|")
        elif line.startswith("|"):
            assert line.count("|") == width, line


def test_a_planners_folder_of_another_scenario_is_refused(tmp_path, monkeypatch):
    bench = load_benchmark("cities_table")
    planners(tmp_path / "cities/planners_grid6", 3, {"mpc H=5 (cv)": GREEDY}, "lanes75")
    monkeypatch.setattr(sys, "argv", ["cities_table.py", str(tmp_path)])
    with pytest.raises(SystemExit, match="scenario=lanes75"):
        bench.main()


def test_a_hybrid_or_leaf_flown_beside_another_mpc_is_refused(tmp_path, monkeypatch):
    bench = load_benchmark("cities_table")
    mpc5 = [x + 0.10 for x in GREEDY]
    planners(tmp_path / "cities/planners_grid6", 3, {"greedy": GREEDY, "mpc H=5 (cv)": mpc5})
    (tmp_path / "cities").mkdir(exist_ok=True)
    (tmp_path / "cities/table.csv").write_text("city,M,learned,pg_learned,other\n")
    hybrid(tmp_path / "cities/hybrid_grid6", GREEDY, [GREEDY], [GREEDY], 0.0)
    monkeypatch.setattr(sys, "argv", ["cities_table.py", str(tmp_path)])
    with pytest.raises(SystemExit, match="hybrid_grid6's mpc .* other settings, windows"):
        bench.main()
    (tmp_path / "cities/hybrid_grid6/hybrid.json").unlink()  # the leaf's is checked alike
    hybrid(tmp_path / "cities/leaf_grid6_3", GREEDY, [GREEDY], [GREEDY], 0.0)
    with pytest.raises(SystemExit, match="leaf_grid6_3's mpc .* other settings, windows"):
        bench.main()


def test_a_folder_holding_the_other_kind_of_hybrid_is_refused(tmp_path, monkeypatch):
    bench = load_benchmark("cities_table")
    mpc5 = [x + 0.10 for x in GREEDY]
    planners(tmp_path / "cities/planners_grid6", 3, {"greedy": GREEDY, "mpc H=5 (cv)": mpc5})
    (tmp_path / "cities/table.csv").write_text("city,M,learned,pg_learned,other\n")
    hybrid(tmp_path / "cities/hybrid_grid6", mpc5, [GREEDY], [mpc5], 1.0, kind="leaf")
    monkeypatch.setattr(sys, "argv", ["cities_table.py", str(tmp_path)])
    with pytest.raises(SystemExit, match="holds the 'leaf' hybrid, not 'hybrid'"):
        bench.main()


def test_the_windows_table_pairs_the_members_mean_per_window_with_the_mpc(
        tmp_path, monkeypatch, capsys):
    bench = load_benchmark("cities_table")
    mpc5 = [x + 0.10 for x in GREEDY]
    planners(tmp_path / "cities/planners_grid6", 3, {"greedy": GREEDY, "mpc H=5 (cv)": mpc5})
    (tmp_path / "cities").mkdir(exist_ok=True)
    (tmp_path / "cities/table.csv").write_text("city,M,learned,pg_learned,other\n")
    # the members' mean per window: the mpc + 2, −1, 3, 4 points (mean +2; over the 4
    # windows sd √(14/3), half-width t(0.975, 3) · sd / 2 = 3.437: [−1.44, +5.44]); better
    # in 3 of the 4 windows. Over the 2 members (+1.75 and +2.25) it reads [−1.18, +5.18].
    leaf = [[m + d for m, d in zip(mpc5, (0.01, -0.02, 0.02, 0.06), strict=True)],
            [m + d for m, d in zip(mpc5, (0.03, 0.00, 0.04, 0.02), strict=True)]]
    hybrid(tmp_path / "cities/leaf_grid6_3", mpc5, [GREEDY, GREEDY], leaf, 1.0)
    monkeypatch.setattr(sys, "argv", ["cities_table.py", str(tmp_path)])
    bench.main()
    out = capsys.readouterr().out
    table = out[out.index("over the windows: the members' mean"):]
    row = next(line for line in table.splitlines() if line.startswith("| grid6 | 3 |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells == ["grid6", "3", "4", "", "", "+2.00 [-1.44, +5.44], 3 of 4"]
    assert "| +2.00 [-1.18, +5.18] |" in out  # the same over the members


def test_a_leaf_variant_gets_its_row_against_the_mpc_it_was_flown_beside(
        tmp_path, monkeypatch, capsys):
    bench = load_benchmark("cities_table")
    mpc5 = [x + 0.10 for x in GREEDY]
    planners(tmp_path / "cities/planners_grid6", 3, {"greedy": GREEDY, "mpc H=5 (cv)": mpc5})
    (tmp_path / "cities/table.csv").write_text("city,M,learned,pg_learned,other\n")
    hybrid(tmp_path / "cities/leaf_h3_grid6_3", mpc5, [GREEDY],
           [[x + 0.02 for x in mpc5], [x + 0.04 for x in mpc5]], 1.0)
    spec = json.loads((tmp_path / "cities/leaf_h3_grid6_3/hybrid.json").read_text())
    spec["hybrid_horizon"] = 3
    (tmp_path / "cities/leaf_h3_grid6_3/hybrid.json").write_text(json.dumps(spec))
    monkeypatch.setattr(sys, "argv", ["cities_table.py", str(tmp_path)])
    bench.main()
    row = next(line for line in capsys.readouterr().out.splitlines()
               if "leaf_h3_grid6_3" in line)
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[:7] == ["grid6", "3", "leaf_h3_grid6_3", "generalist_rank5", "3", "1", "48.00"]
    assert cells[7].startswith("+3.00 [") and cells[8] == "+3.00 [+3.00, +3.00], 4 of 4"
    assert cells[9].startswith("+3.00 [") and cells[9].endswith("(mpc H=5 cv)")
    # flown beside an mpc the planners' folder does not hold: refused
    hybrid(tmp_path / "cities/leaf_h2_grid6_3", GREEDY, [GREEDY], [GREEDY], 0.0)
    with pytest.raises(SystemExit,
                       match=r"leaf_h2_grid6_3's mpc is not the planners' mpc H=5 \(cv\)"):
        bench.main()


def test_an_mpc_flown_by_uabs_eval_joins_the_planners_of_its_city(tmp_path, monkeypatch,
                                                                   capsys):
    bench = load_benchmark("cities_table")
    mpc5 = [x + 0.10 for x in GREEDY]
    planners(tmp_path / "cities/planners_grid6", 3, {"greedy": GREEDY, "mpc H=5 (cv)": mpc5})
    (tmp_path / "cities/table.csv").write_text("city,M,learned,pg_learned,other\n")
    mpc10 = [x + 0.13 for x in GREEDY]  # 3 points above H = 5: the best mpc
    folder = tmp_path / "cities/mpc_h10_grid6_3"
    folder.mkdir()
    spec = {"split": "test", "scenario": "grid6", "overrides": ["scenario=grid6",
                                                                "scenario.n_uabs=3"],
            "policies": {"mpc": {"horizon": 10, "predictor": "cv", "sees": "all",
                                 "served_fraction": sum(mpc10) / 4, "pg": 0.5,
                                 "served_fractions": mpc10, "pgs": mpc10}}}
    (folder / "eval.json").write_text(json.dumps(spec))
    hybrid(tmp_path / "cities/leaf_grid6_3", mpc5, [GREEDY], [[x + 0.04 for x in mpc5]], 1.0)
    monkeypatch.setattr(sys, "argv", ["cities_table.py", str(tmp_path)])
    bench.main()
    out = capsys.readouterr().out
    assert "| grid6 | 3 | 35.00 |" in out  # greedy, then ... the mpc at H = 10's column
    assert "| 48.00 |" in out.splitlines()[4]
    row = next(line for line in out.splitlines() if line.startswith("| grid6 | 3 | mpc"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2:4] == ["mpc H=10 cv", "48.00"]
    assert cells[8].startswith("+4.00 [") and cells[9].startswith("+1.00 [")
    for other in ({"overrides": ["scenario=grid6", "scenario.n_uabs=6"]},  # another fleet
                  {"policies": {"mpc": spec["policies"]["mpc"] | {"rounds": 1}}},  # one pass
                  {"policies": {"mpc": spec["policies"]["mpc"] | {"beam": 4}}}):  # 4 paths
        (folder / "eval.json").write_text(json.dumps(spec | other))
        with pytest.raises(SystemExit, match="mpc_h10_grid6_3 is not an mpc on grid6's test"):
            bench.main()
    assert bench.own_mpc({"mpc_horizon": 5, "predictor": "cv", "mpc_beam": 4,
                          "mpc_rounds": 1}) == "mpc H=5 (cv, beam 4, 1 round)"
    assert bench.own_mpc({"mpc_horizon": 5, "predictor": "cv"}) == "mpc H=5 (cv)"


def test_the_paired_script_pairs_the_learned_policy_and_the_leaf_with_each_planner(
        tmp_path):
    """``planning_vs_learning.py --paired DIR --learned HYBRID_DIR``: learned − each
    policy of DIR and the hybrid (here a 2-step leaf at λ* = 1) − each, the members'
    mean paired differences over the windows; a folder whose mpc is another refused."""
    bench = load_benchmark("planning_vs_learning")
    mpc, narrow = [0.30, 0.40], [0.20, 0.40]
    rows = [{"mode": "rank", "n_uabs": 3, "policy": "mpc H=5 (cv)",
             "served_fractions": mpc, "pgs": mpc},
            {"mode": "rank", "n_uabs": 3, "policy": "mpc H=5 (cv, beam 4)",
             "served_fractions": narrow, "pgs": narrow}]
    folder = tmp_path / "leaf_h2"
    folder.mkdir()
    flown = [[0.35, 0.45], [0.36, 0.46]]
    (folder / "hybrid.json").write_text(json.dumps({
        "hybrid": "leaf", "hybrid_horizon": 2, "best_weight": 1.0, "mpc_horizon": 5,
        "predictor": "cv", "sees": "all", "policies": {
            "mpc": {"served": mpc, "pg": mpc},
            "learned": {"served": [mpc, mpc], "pg": [mpc, mpc]},
            "hybrid": {"served": flown, "pg": flown}}}))
    lines = []
    bench.paired_learned(rows, folder, lines.append)
    assert len(lines) == 4
    assert lines[0].startswith("rank M=3 learned (2 members) - mpc H=5 (cv): served +0.00")
    # (0.15 + 0.05) / 2 and (0.16 + 0.06) / 2 above the narrower mpc: 10.5 points
    assert lines[3].startswith("rank M=3 leaf H=2 λ=1 (2 members) - mpc H=5 (cv, beam 4): "
                               "served +10.50 [")
    # and the members' mean per window paired over the windows: (0.355 - 0.20, 0.455 - 0.40)
    assert lines[3].endswith("; over the windows: served +10.50 [-53.03, +74.03], above it "
                             "in 2 of 2")
    # a folder written before --leaf (no "hybrid" key): its hybrid named so
    record = json.loads((folder / "hybrid.json").read_text())
    del record["hybrid"], record["hybrid_horizon"]
    (folder / "hybrid.json").write_text(json.dumps(record))
    lines = []
    bench.paired_learned(rows, folder, lines.append)
    assert lines[2].startswith("rank M=3 hybrid H=5 λ=1 (2 members) - mpc H=5 (cv): ")
    # flown beside the mpc at 4 paths (hybrid.py --mpc-beam 4), its own search at 8
    record |= {"mpc_beam": 4, "hybrid_beam": 8}
    record["policies"]["mpc"] = {"served": narrow, "pg": narrow}
    (folder / "hybrid.json").write_text(json.dumps(record))
    lines = []
    bench.paired_learned(rows, folder, lines.append)
    assert lines[2].startswith("rank M=3 hybrid H=5 λ=1 beam 8 (2 members) - mpc H=5 (cv): ")
    # beside the mpc at 4 paths in one pass (--mpc-rounds 1), itself in one pass too
    rows.append({"mode": "rank", "n_uabs": 3, "policy": "mpc H=5 (cv, beam 4, 1 round)",
                 "served_fractions": mpc, "pgs": mpc})
    record |= {"mpc_rounds": 1, "hybrid_rounds": 1}
    record["policies"]["mpc"] = {"served": mpc, "pg": mpc}
    (folder / "hybrid.json").write_text(json.dumps(record))
    lines = []
    bench.paired_learned(rows, folder, lines.append)
    assert lines[-1].startswith("rank M=3 hybrid H=5 λ=1 beam 8 1 round (2 members) - "
                                "mpc H=5 (cv, beam 4, 1 round): served +5.50 [")
    rows.pop()
    record |= {"mpc_rounds": 2, "hybrid_rounds": 2}
    record["policies"]["mpc"] = {"served": narrow, "pg": narrow}
    (folder / "hybrid.json").write_text(json.dumps(record))
    rows[1]["served_fractions"] = mpc
    with pytest.raises(SystemExit, match=r"mpc is none of this folder's mpc H=5 \(cv, beam 4\)"):
        bench.paired_learned(rows, folder, lines.append)
    rows[0]["served_fractions"] = narrow
    record["policies"]["mpc"], record["mpc_beam"] = {"served": mpc, "pg": mpc}, 16
    (folder / "hybrid.json").write_text(json.dumps(record))
    with pytest.raises(SystemExit, match="mpc is none of this folder's"):
        bench.paired_learned(rows, folder, lines.append)


def test_the_paired_script_pairs_each_narrower_or_single_pass_mpc_with_its_default(
        tmp_path):
    """``planning_vs_learning.py --beams 16 4 --rounds 2 1`` writes the four mpcs; the
    paired differences put each beside the same mpc at the default beam, at the default
    passes, and one off both defaults beside the default mpc too (per-window values
    chosen so that every difference is known)."""
    bench = load_benchmark("planning_vs_learning")
    served = {"mpc H=5 (cv)": [0.30, 0.40], "mpc H=5 (cv, beam 4)": [0.29, 0.39],
              "mpc H=5 (cv, 1 round)": [0.28, 0.38],
              "mpc H=5 (cv, beam 4, 1 round)": [0.26, 0.36]}
    rows = [{"mode": "rank", "n_uabs": 3, "policy": k, "served_fractions": v, "pgs": v}
            for k, v in served.items()]
    lines = []
    bench.paired(rows, lines.append)
    said = {line.split(": served")[0]: line.split("served ")[1].split(" [")[0]
            for line in lines}
    assert said == {
        "rank M=3 mpc H=5 (cv, beam 4) - mpc H=5 (cv)": "-1.00",
        "rank M=3 mpc H=5 (cv, 1 round) - mpc H=5 (cv)": "-2.00",
        "rank M=3 mpc H=5 (cv, beam 4, 1 round) - mpc H=5 (cv, 1 round)": "-2.00",
        "rank M=3 mpc H=5 (cv, beam 4, 1 round) - mpc H=5 (cv, beam 4)": "-3.00",
        "rank M=3 mpc H=5 (cv, beam 4, 1 round) - mpc H=5 (cv)": "-4.00"}, lines


def test_two_hybrid_folders_are_compared_only_beside_the_same_mpc(tmp_path, capsys):
    """``hybrid.py --compare A B``: learned(A) − learned(B) with Welch's interval when both
    were flown beside the same mpc (a record without the beam or passes counts as the
    defaults); refused when the mpc's search differs."""
    bench = load_benchmark("hybrid")
    mpc = [0.30, 0.40]

    def folder(name, learned, **extra):
        path = tmp_path / name
        path.mkdir()
        (path / "hybrid.json").write_text(json.dumps({
            "mpc_horizon": 5, "predictor": "cv", "sees": "all", "overrides": [], **extra,
            "policies": {"mpc": {"served": mpc, "pg": mpc},
                         "learned": {"served": learned, "pg": learned}}}))
        return path

    a = folder("a", [[0.32, 0.42], [0.34, 0.44]])  # before the keys: the defaults
    b = folder("b", [[0.30, 0.40], [0.31, 0.41]], mpc_beam=16, mpc_rounds=2)
    bench.compare(a, b)
    assert "served: +2.50 [" in capsys.readouterr().out  # 0.38 − 0.355
    c = folder("c", [[0.30, 0.40], [0.31, 0.41]], mpc_beam=16, mpc_rounds=1)
    with pytest.raises(SystemExit, match="not comparable"):
        bench.compare(a, c)
