"""uabs-report on a tiny real sweep; uabs-eval on one of its runs."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from tests.test_train import records, smoke
from uabs_rl.cli.evaluate import main as eval_main
from uabs_rl.cli.report import main as report_main
from uabs_rl.report.build import build_report
from uabs_rl.runs.sweep import find_runs, group_runs
from uabs_rl.training.resume import run

QUIET = ("train.logger=none", "train.trajectory_images=false", "scenario.n_uabs=4")


@pytest.fixture(scope="module")
def sweep(trace_cache, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("multirun")
    for mode in ("penalty", "rank"):
        for seed in (0, 1):
            run(smoke(trace_cache, f"masking={mode}", f"seed={seed}", "train.logger=none",
                      "train.trajectory_images=false", "scenario.n_uabs=4"),
                root / f"masking={mode},seed={seed}")
    return root


@pytest.fixture(scope="module")
def report(sweep):
    out = sweep / "report"
    return out, build_report(sweep, out, with_baselines=True, command="uabs-report test",
                             export="marl-eval")


def test_table2_equals_the_runs_metrics(sweep, report):
    out, res = report
    rows = {r["mode"]: r for r in res["rows"]}
    for mode in ("penalty", "rank"):
        recs = [records(sweep / f"masking={mode},seed={s}") for s in (0, 1)]
        train = [[r for r in rr if r["kind"] == "train"] for rr in recs]
        evals = [[r for r in rr if r["kind"] == "eval"] for rr in recs]
        events = np.mean([sum(r["collisions"] for r in t) for t in train])
        with_coll = np.mean([sum(r["collisions"] > 0 for r in t) for t in train])
        eval_events = np.mean([sum(r["collisions"] for r in e) for e in evals])
        assert rows[mode]["train_collision_events"] == pytest.approx(events)
        assert rows[mode]["train_episodes_with_collision"] == pytest.approx(with_coll)
        assert rows[mode]["eval_collision_events"] == pytest.approx(eval_events)
        # the ± of Table 2: the sample standard deviation over the seeds (n − 1)
        per_seed = [sum(r["collisions"] for r in t) for t in train]
        assert rows[mode]["train_collision_events_std"] == pytest.approx(
            np.std(per_seed, ddof=1))
        assert rows[mode]["train_episodes"] == 6 and rows[mode]["eval_episodes"] == 4
    assert rows["rank"]["train_collision_events"] == 0
    with open(out / "table2.csv") as f:
        csv_rows = {r["mode"]: r for r in csv.DictReader(f)}
    assert float(csv_rows["penalty"]["train_collision_events"]) == pytest.approx(
        rows["penalty"]["train_collision_events"])
    md = (out / "table2.md").read_text()
    assert "Collisions in training" in md and "sample standard deviation" in md


def test_table2_of_one_seed_says_seed_and_its_sd_is_zero(sweep):
    from uabs_rl.report.tables import table2, table2_markdown

    rows = table2({"rank": find_runs(sweep / "masking=rank,seed=0")})
    assert rows[0]["seeds"] == 1 and rows[0]["train_collision_events_std"] == 0.0
    assert table2_markdown(rows).splitlines()[0] == "| | rank (1 seed) |"


def test_runs_of_two_scenarios_are_labelled_by_scenario_not_by_its_settings(trace_cache,
                                                                            tmp_path):
    """A report over runs of two scenarios names each group scenario=<name> and only the
    settings the group has otherwise (here the smoke preset's fleet, which grid6's own
    file overrides), not the score of settings the scenario's file sets (area, network,
    fleet); the summary's lines read the same."""
    quiet = ["train.trajectory_images=false", "train.logger=none"]
    run(smoke(trace_cache, *quiet), tmp_path / "runs" / "a")
    run(smoke(trace_cache, *quiet, "scenario=grid6"), tmp_path / "runs" / "b")
    labels = list(group_runs(find_runs(tmp_path / "runs")).groups)
    assert sorted(labels) == ["rank, scenario=grid6",
                              "rank, scenario=manhattan, scenario.sumo.fleet_size=20"]
    build_report(tmp_path / "runs", tmp_path / "report", with_baselines=False)
    summary = (tmp_path / "report" / "summary.md").read_text()
    [runs_line] = [ln for ln in summary.splitlines() if ln.startswith("Runs: ")]
    assert runs_line == ("Runs: rank, scenario=grid6: 1 seed; rank, scenario=manhattan, "
                         "scenario.sumo.fleet_size=20: 1 seed")
    assert ("; compared: scenario.name, scenario.sumo.fleet_size (and 3 settings each "
            "scenario's file sets).") in summary  # area width and height, network


def test_a_learners_own_default_is_left_out_of_a_scenario_label():
    """The scenario's defaults are composed with the group's learner: QMIX's own
    algo.mixing_embed_dim at its default is not named, another value of it is."""
    from uabs_rl.runs.sweep import _named, _scenario_defaults

    s = dict(_scenario_defaults("grid6", "qmix"))
    varied = ["scenario.name", "scenario.area.width", "algo.mixing_embed_dim"]
    assert _named(varied, s) == ["scenario=grid6"]
    assert _named(varied, s | {"algo.mixing_embed_dim": 8}) == [
        "scenario=grid6", "algo.mixing_embed_dim=8"]


def test_figures_exist_as_png_and_pdf(report):
    out, _ = report
    for name in ("fig3_eval_return", "fig4_pg"):
        data = (out / f"{name}.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n"
        assert 15_000 < len(data) < 2_000_000
        pdf = (out / f"{name}.pdf").read_bytes()
        assert pdf[:5] == b"%PDF-" and len(pdf) > 5_000


def keep_figures(monkeypatch) -> list:
    """The figures the report's functions draw, kept open (instead of closed) to look at."""
    import matplotlib.pyplot as plt  # imported here (a test run alone has not yet)

    figs: list = []
    monkeypatch.setattr(plt, "close", figs.append)
    return figs


def test_figures_have_panels_and_no_figure_numbers(sweep, report, tmp_path, monkeypatch):
    """Penalty gets its own panel in Fig. 3; Fig. 4 has a panel per mode, its baselines
    in greys and dashes; no title says 'Fig.'; the legend lies outside the axes; two
    evaluations are drawn with markers; the band of 2 seeds is called their range."""
    import matplotlib

    from uabs_rl.evaluation.plots import MODE_COLORS
    from uabs_rl.report.baselines import best_pg
    from uabs_rl.report.figures import fig3, fig4

    grouping = group_runs(find_runs(sweep))
    assert list(grouping.groups) == ["penalty", "rank"] and grouping.by_mode_only
    figs = keep_figures(monkeypatch)
    fig3(grouping, tmp_path / "f3")
    base = {"rank": {"greedy": {"pg_curve": list(best_pg(grouping.groups["rank"]).mean(0))}}}
    fig4(grouping, base, tmp_path / "f4")
    f3, f4 = figs
    assert [ax.get_title() for ax in f3.axes] == ["rank masking", "penalty (reward penalties)"]
    assert [ax.get_title() for ax in f4.axes] == ["penalty (2 seeds)", "rank masks (2 seeds)"]
    for fig in (f3, f4):
        assert not any("Fig" in ax.get_title() for ax in fig.axes)
        assert len(fig.legends) == 1 and all(ax.get_legend() is None for ax in fig.axes)
        legend_box = fig.legends[0].get_window_extent(fig.canvas.get_renderer())
        for ax in fig.axes:
            assert not legend_box.overlaps(ax.get_window_extent())
        texts = [t.get_text() for t in fig.legends[0].get_texts()]
        assert "shaded: min-max range of the 2 seeds" in texts
        assert not any("CI" in t for t in texts)
    (line,) = f3.axes[0].get_lines()
    assert len(line.get_xdata()) == 2 and line.get_marker() == "o"
    rank_ax = f4.axes[1]
    learned, greedy = rank_ax.get_lines()[:2]
    assert matplotlib.colors.same_color(learned.get_color(), MODE_COLORS["rank"])
    assert greedy.get_linestyle() == "--" and greedy.get_color() != learned.get_color()


def test_report_warns_on_short_runs(report, capsys):
    out, _ = report
    assert "WARNING: the shortest run trained 6 episodes" in (out / "summary.md").read_text()


def test_baselines_and_summary(report):
    out, res = report
    assert len(res["baselines"]) == 6  # 3 baselines x 2 masking modes
    with open(out / "baselines.csv") as f:
        assert len(list(csv.DictReader(f))) == 6
    text = (out / "summary.md").read_text()
    assert "Produced by: `uabs-report test`" in text
    assert "n/a (mode missing)" in text  # flat was not run: claims that need it say so
    assert "penalty: 2 seeds" in text


def test_uabs_eval_writes_json_and_pictures(sweep, capsys):
    run_dir = sweep / "masking=rank,seed=0"
    assert eval_main([str(run_dir), "--policy", "all", "--checkpoint", "last",
                      "--split", "eval"]) == 0
    out = json.loads((run_dir / "evaluation" / "eval.json").read_text())
    assert out["split"] == "eval"
    res = out["policies"]
    assert set(res) == {"learned", "random", "greedy", "oracle"}
    # paired differences: the mean of the per-window differences, inside its interval
    for name in ("random", "greedy", "oracle"):
        d = out["differences"][name]["return"]
        assert d["diff"] == pytest.approx(np.mean(np.subtract(res["learned"]["returns"],
                                                              res[name]["returns"])))
        assert d["ci_low"] <= d["diff"] <= d["ci_high"] and d["n"] == len(res[name]["returns"])
    last_eval = [r for r in records(run_dir) if r["kind"] == "eval"][-1]
    assert res["learned"]["return"] == pytest.approx(last_eval["return"])
    assert res["learned"]["pg_curve"] == pytest.approx(last_eval["pg_curve"])
    for name in res:
        assert (run_dir / "evaluation" / f"trajectories_{name}.png").stat().st_size > 10_000
    assert "learned" in capsys.readouterr().out
    assert eval_main([str(run_dir / "nowhere.pt")]) == 2


def test_uabs_eval_reports_on_test_traces_by_default(sweep, capsys):
    run_dir = next(sweep.glob("*rank*"))
    assert eval_main([str(run_dir), "--policy", "all", "--out", str(run_dir / "ev_test")]) == 0
    out = json.loads((run_dir / "ev_test" / "eval.json").read_text())
    assert out["split"] == "test" and out["windows"] == len(out["policies"]["learned"]["returns"])
    assert "split: test" in capsys.readouterr().out
    for metric in ("return", "served_fraction", "pg"):
        d = out["differences"]["greedy"][metric]
        assert d["ci_low"] <= d["diff"] <= d["ci_high"]


def test_learned_vs_baselines_on_test_traces(sweep, report):
    out, res = report
    with open(out / "learned_vs_baselines.csv") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["mode", "algo", "n_uabs", "config", "metric", "baseline", "learned",
                             "diff", "ci_low", "ci_high", "n_seeds", "method", "gap_share",
                             "gap_ci_low", "gap_ci_high"]
    assert {r["method"] for r in rows} == {"95 % CI, Student-t over 2 seeds"}
    assert {r["gap_share"] for r in rows} == {""}  # no planner asked for
    # 2 modes x 3 metrics x 3 baselines, 2 seeds each, smoke runs: recoverable, paper obs
    assert len(rows) == 18 and {r["n_seeds"] for r in rows} == {"2"}
    # every setting of the smoke preset that differs from the defaults is named, and the
    # run is not called "paper" (its scenario and traces are not the paper's)
    (config,) = {r["config"] for r in rows}
    assert "paper" not in config and "scenario.episode_steps=20" in config
    assert "algo.{hidden=[32, 32], batch_size=32," in config and "train.{episodes=6," in config
    md = (out / "learned_vs_baselines.md").read_text()
    assert md.count("algo.{hidden=[32, 32]") == 1  # named once (common settings), not per row
    assert "\n## penalty (M = 4, 2 seeds)\n" in md and "\n## rank (M = 4, 2 seeds)\n" in md
    assert "| served fraction | greedy |" in md and " pt [" in md
    assert "learned − baseline [95 % CI, Student-t over 2 seeds] |" in md
    for r, full in zip(rows, res["learned_vs_baselines"], strict=True):
        assert float(r["diff"]) == pytest.approx(full["learned"] - full["baseline_value"],
                                                 abs=1e-6)
        assert float(r["ci_low"]) <= float(r["diff"]) <= float(r["ci_high"])


def test_planner_places_each_group_on_the_greedy_to_planner_scale(sweep, tmp_path, capsys):
    """``uabs-report --planner H``: the planner runs once per panel, joins the baselines,
    and each group's greedy rows hold (learned − greedy) / (planner − greedy) with the
    interval of learned − greedy divided by the same gap; its value equals the planner
    of ``uabs-eval`` on the panel's run."""
    from uabs_rl.evaluation.load import evaluate_policies, load_evaluation

    out = tmp_path / "report"
    assert report_main([str(sweep), "--out", str(out), "--planner", "2"]) == 0
    with open(out / "baselines.csv") as f:
        planners = {r["policy"]: r for r in csv.DictReader(f) if r["policy"].startswith("planner")}
    assert set(planners) == {"planner (penalty masks)", "planner (rank masks)"}
    with open(out / "learned_vs_baselines.csv") as f:
        rows = list(csv.DictReader(f))
    shares = [r for r in rows if r["gap_share"]]
    assert {(r["mode"], r["metric"], r["baseline"]) for r in shares} == {
        (m, k, "greedy") for m in ("penalty", "rank") for k in ("served_fraction", "pg")}
    ev = load_evaluation(sweep / "masking=rank,seed=0", "best", split="test")
    planner = evaluate_policies(ev, ("planner",), horizon=2)["planner"][0]
    assert float(planners["planner (rank masks)"]["served_fraction"]) == pytest.approx(
        planner["served_fraction"])
    for r in (r for r in shares if r["mode"] == "rank" and r["metric"] == "served_fraction"):
        learned, diff = float(r["learned"]), float(r["diff"])
        gap = planner["served_fraction"] - (learned - diff)
        if gap > 0:
            assert float(r["gap_share"]) == pytest.approx(diff / gap, rel=1e-6)
            assert float(r["gap_ci_low"]) == pytest.approx(float(r["ci_low"]) / gap, rel=1e-6)
        else:
            assert r["gap_share"] == "nan"
    md = (out / "learned_vs_baselines.md").read_text()
    assert "learned share of the greedy-to-planner gap" in md
    assert "(learned − greedy's interval divided by the gap;" in md  # its method named
    # the summary prints each baseline's level as learned_vs_baselines.md does (the mean
    # of its per-window values: the record's float32 mean could round to another digit)
    summary = (out / "summary.md").read_text()
    for mode in ("penalty", "rank"):
        block = next(b for b in md.split("\n## ")[1:] if b.startswith(mode))
        level = next(ln for ln in block.splitlines()
                     if ln.startswith("| served fraction | greedy |")).split(" | ")[3]
        row = next(ln for ln in summary.splitlines() if ln.startswith(f"| greedy ({mode} masks)"))
        assert row.split(" | ")[5] == level, (row, level)
    assert "planner H=2 on" in capsys.readouterr().err  # its cost, per panel
    with pytest.raises(SystemExit) as refused:  # the planner needs the test evaluation
        report_main([str(sweep), "--no-baselines", "--planner", "2"])
    assert refused.value.code == 2


def test_runs_of_other_settings_are_grouped_not_refused(sweep, tmp_path):
    """Seeds of another scenario are not averaged with the sweep's: they form a group of
    their own, named by the setting that differs."""
    import shutil

    import torch

    root = tmp_path / "mixed"
    for name in ("masking=rank,seed=0", "masking=rank,seed=1"):
        shutil.copytree(sweep / name, root / name)
    ckpt = root / "masking=rank,seed=1" / "checkpoints" / "last.pt"
    state = torch.load(ckpt, weights_only=True)
    state["config"]["scenario"]["name"] = "elsewhere"
    state["config"]["device"] = "cuda"  # a setting that does not change results: ignored
    torch.save(state, ckpt)
    grouping = group_runs(find_runs(root))
    assert grouping.varied == ["scenario.name"]
    assert {k: [r.seed for r in v] for k, v in grouping.groups.items()} == {
        "rank, scenario=elsewhere": [1], "rank, scenario=manhattan": [0]}
    assert len(find_runs(sweep / "masking=rank,seed=0")) == 1  # a single run folder works


@pytest.mark.parametrize("scenario,algo,train,label", [
    ({}, {}, {}, "paper"),
    ({"lookahead_obs": True}, {"lr": 3e-4}, {}, "lookahead algo.lr=0.0003"),
    ({"lookahead_obs": True, "motion_obs": True}, {}, {"n_envs": 4},
     "lookahead+motion train.n_envs=4"),
    ({}, {"n_step": 3}, {"population": 5}, "paper algo.n_step=3"),  # population: neutral
    ({"episode_steps": 20}, {"loss": "torchrl"}, {"episodes": 6, "n_envs": 2},
     "scenario.episode_steps=20 train.n_envs=2 train.episodes=6"),  # not the paper's scenario
    ({"lookahead_obs": True}, {"hidden": [32, 32], "batch_size": 32, "target_update": 50},
     {}, "lookahead algo.{hidden=[32, 32], batch_size=32, target_update=50}"),
])
def test_run_labels_name_the_observation_and_learning_settings(scenario, algo, train, label):
    from uabs_rl.runs.sweep import Run

    cfg = {"scenario": scenario, "channel": {}, "masking": {"recoverable": True}, "algo": algo,
           "train": train, "traces": {}, "seed": 0}
    assert Run(Path("x"), "flat", 0, 1000, [], [], cfg).label == label


@pytest.mark.parametrize("obs,label", [
    ({"name": "lookahead", "lookahead": True}, "lookahead"),
    ({"name": "lookahead_motion", "lookahead": True, "motion": True}, "lookahead+motion"),
    ({"name": "egocentric", "frame": "egocentric", "motion": True}, "egocentric"),
    ({"frame": "egocentric", "map_radius": 3}, "egocentric-static obs.map_radius=3"),
])
def test_run_labels_name_the_obs_group(obs, label):
    """Runs written with the obs group; a run of the same observation written before
    it (scenario.lookahead_obs, above) gets the same label."""
    from uabs_rl.runs.sweep import Run

    cfg = {"scenario": {}, "obs": obs, "channel": {}, "masking": {"recoverable": True},
           "algo": {}, "train": {}, "traces": {}, "seed": 0}
    assert Run(Path("x"), "flat", 0, 1000, [], [], cfg).label == label


def test_run_labels_name_a_family_by_its_cities():
    from uabs_rl.runs.sweep import Run

    cfg = {"scenario": {}, "obs": {"frame": "egocentric", "motion": True}, "channel": {},
           "masking": {"recoverable": True}, "algo": {}, "train": {"n_envs": 4},
           "traces": {}, "seed": 0, "family": [{}, {"name": "blocks60"}, {"name": "b"}]}
    assert Run(Path("x"), "rank", 0, 1000, [], [], cfg).label == (
        "egocentric family=scenario+blocks60+b train.n_envs=4")


def test_runs_written_before_recoverable_masks_are_literal():
    from uabs_rl.runs.sweep import Run

    cfg = {"scenario": {}, "channel": {}, "masking": {"mode": "rank"}, "algo": {}, "train": {},
           "traces": {}, "seed": 0}
    old = Run(Path("x"), "rank", 0, 1000, [], [], cfg)
    assert old.label == "paper-literal" and old.settings["masking.recoverable"] is False


# ----------------------------------------------------------------------------- settings
@pytest.fixture(scope="module")
def lr_sweep(trace_cache, tmp_path_factory, sweep) -> Path:
    """``algo.lr=1e-4,1e-3 seed=0,1`` under rank masks: the sweep's rank runs (the
    default learning rate) beside two runs of a ten times larger one."""
    import shutil

    root = tmp_path_factory.mktemp("lr_sweep")
    for seed in (0, 1):
        shutil.copytree(sweep / f"masking=rank,seed={seed}", root / f"algo.lr=1e-4,seed={seed}")
        run(smoke(trace_cache, "algo.lr=1e-3", f"seed={seed}", *QUIET),
            root / f"algo.lr=1e-3,seed={seed}")
    return root


def test_a_sweep_of_a_learning_rate_is_compared_group_by_group(lr_sweep, tmp_path,
                                                               monkeypatch):
    """Two learning rates x 2 seeds: two groups named by the rate, one Table 2 column,
    one comparison row and one Fig. 3 line each, the rest of the settings said once."""
    out = tmp_path / "report"
    figs = keep_figures(monkeypatch)
    res = build_report(lr_sweep, out, with_baselines=False, command="uabs-report lr")
    labels = ["rank, algo.lr=0.0001", "rank, algo.lr=0.001"]
    assert list(res["grouping"].groups) == labels and res["grouping"].varied == ["algo.lr"]
    assert [[r.seed for r in g] for g in res["grouping"].groups.values()] == [[0, 1], [0, 1]]
    with open(out / "table2.csv") as f:
        rows = list(csv.DictReader(f))
    assert [(r["group"], r["mode"], r["seeds"]) for r in rows] == [
        (labels[0], "rank", "2"), (labels[1], "rank", "2")]
    assert "| | rank, algo.lr=0.0001 (2 seeds) | rank, algo.lr=0.001 (2 seeds) |" in (
        out / "table2.md").read_text()
    with open(out / "comparison.csv") as f:
        comp = list(csv.DictReader(f))
    assert [(r["group"], float(r["algo.lr"])) for r in comp] == [(labels[0], 1e-4),
                                                                (labels[1], 1e-3)]
    for r, lr in zip(comp, ("1e-4", "1e-3"), strict=True):  # the mean of the seeds' values
        best = [max(e["return"] for e in records(lr_sweep / f"algo.lr={lr},seed={s}")
                    if e["kind"] == "eval") for s in (0, 1)]
        assert float(r["return_best"]) == pytest.approx(np.mean(best))
        assert (float(r["return_best_low"]), float(r["return_best_high"])) == (min(best),
                                                                               max(best))
    text = (out / "summary.md").read_text()
    assert "Runs: rank, algo.lr=0.0001: 2 seeds; rank, algo.lr=0.001: 2 seeds" in text
    assert "compared: algo.lr." in text and text.count("scenario.episode_steps=20") == 1
    assert "## Settings compared" in text and f"| {labels[1]} | 2 | 6 |" in text
    assert "Not judged for algo.lr=0.0001 (rank only); algo.lr=0.001 (rank only)" in text
    assert (out / "fig3_eval_return.png").stat().st_size > 15_000
    f3 = figs[0]
    assert [line.get_label() for line in f3.axes[0].get_lines()] == [
        f"{lab} (2 seeds)" for lab in labels]
    assert len({line.get_color() for line in f3.axes[0].get_lines()}) == 2


def test_curves_of_runs_of_different_settings_overlay_in_one_figure(lr_sweep, tmp_path,
                                                                    monkeypatch, capsys):
    """uabs-report RUN RUN ... --curves: one figure, one line per run in each panel
    (training and validation return), named by group and seed."""
    figs = keep_figures(monkeypatch)
    runs = sorted(lr_sweep.iterdir())
    assert report_main([*map(str, runs), "--curves", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "curves.png").stat().st_size > 15_000 and (tmp_path / "curves.pdf").is_file()
    (fig,) = figs
    train_ax, eval_ax = fig.axes
    names = ["rank, algo.lr=0.0001, seed 0", "rank, algo.lr=0.0001, seed 1",
             "rank, algo.lr=0.001, seed 0", "rank, algo.lr=0.001, seed 1"]
    for ax in (train_ax, eval_ax):
        assert [line.get_label() for line in ax.get_lines()] == names
    first = records(lr_sweep / "algo.lr=1e-4,seed=0")
    assert list(eval_ax.get_lines()[0].get_ydata()) == [r["return"] for r in first
                                                        if r["kind"] == "eval"]
    assert eval_ax.get_lines()[0].get_marker() == "o"  # 2 points: each one marked
    assert "curves.png" in capsys.readouterr().out


def test_symlinked_run_folders_are_found_once(sweep, tmp_path):
    root = tmp_path / "links"
    root.mkdir()
    (root / "a").symlink_to(sweep / "masking=rank,seed=0", target_is_directory=True)
    (root / "b").symlink_to(sweep / "masking=penalty,seed=1", target_is_directory=True)
    (root / "again").symlink_to(sweep / "masking=rank,seed=0", target_is_directory=True)
    (root / "loop").symlink_to(root, target_is_directory=True)  # a cycle ends
    runs = find_runs(root)
    assert sorted((r.mode, r.seed) for r in runs) == [("penalty", 1), ("rank", 0)]
    assert len(find_runs(root, sweep / "masking=rank,seed=0")) == 2  # each run once


def test_a_run_with_no_evaluation_is_left_out_with_one_line(sweep, tmp_path, capsys):
    run_dir = tmp_path / "early"
    import shutil

    shutil.copytree(sweep / "masking=rank,seed=0", run_dir / "run")
    metrics = run_dir / "run" / "metrics.jsonl"
    metrics.write_text("".join(line + "\n" for line in metrics.read_text().splitlines()
                               if '"kind": "eval"' not in line))
    assert report_main([str(run_dir)]) == 2
    err = capsys.readouterr().err
    assert err.splitlines() == [
        f"error: nothing to report under {run_dir}: {run_dir / 'run'} has no evaluation yet "
        f"(one every train.eval_every = 3 episodes). Report once a run has evaluated, or "
        f"pass other folders."]
    # beside a run that has evaluated: a warning, and the report of the other
    assert report_main([str(run_dir), str(sweep / "masking=rank,seed=1"), "--curves",
                        "--out", str(tmp_path / "out")]) == 0
    assert capsys.readouterr().err.splitlines() == [
        f"warning: {run_dir / 'run'} has no evaluation yet (one every train.eval_every = 3 "
        f"episodes): left out"]


def test_report_errors_are_one_line_and_status_2(sweep, tmp_path, capsys):
    import shutil

    assert report_main([str(tmp_path / "nowhere")]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"error: {tmp_path / 'nowhere'} is not a folder: pass a run folder or a folder of "
        f"runs (such as outputs/multirun/<date_time>)."]
    # a setting typed as if uabs-report evaluated (it reports what was evaluated)
    assert report_main([str(sweep), "scenario=bologna"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        "error: scenario=bologna is not a folder: pass a run folder or a folder of runs (such "
        "as outputs/multirun/<date_time>). uabs-report takes no settings: to evaluate runs "
        "under scenario=bologna, use uabs-eval <run> scenario=bologna (one run) or python "
        "benchmarks/generalization.py <runs> --at <scenario>:<M> (several runs, cities and "
        "fleets)."]
    # a mistyped job folder of a sweep is a path, not a setting
    assert report_main([str(tmp_path / "masking=flat,seed=9")]) == 2
    assert "takes no settings" not in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert report_main([str(tmp_path / "empty")]) == 2
    assert capsys.readouterr().err.startswith(f"error: no run under {tmp_path / 'empty'}: ")
    shutil.copytree(sweep / "masking=rank,seed=0", tmp_path / "bad")
    with open(tmp_path / "bad" / "metrics.jsonl", "a") as f:
        f.write('{"kind": "tr\n')
    assert report_main([str(tmp_path / "bad"), "--curves"]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("error: ") and "metrics.jsonl, line " in line


# ----------------------------------------------------------------------------- figures
def test_bands_are_drawn_and_named_only_where_there_are_seeds():
    """1 seed: no band and no CI words; 2 seeds: the min-max range, said so; 3 or more:
    a Student-t 95 % CI."""
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    from uabs_rl.evaluation.plots import SeedCurve, band_label, return_curves_figure
    from uabs_rl.evaluation.stats import spread_over_seeds, t_interval

    vals = np.array([[1.0, 4.0], [3.0, 0.0], [2.0, 2.0]])
    m, lo, hi = spread_over_seeds(vals[:1])
    assert list(m) == list(lo) == list(hi) == [1.0, 4.0]
    m, lo, hi = spread_over_seeds(vals[:2])
    assert list(m) == [2.0, 2.0] and list(lo) == [1.0, 0.0] and list(hi) == [3.0, 4.0]
    m, lo, hi = spread_over_seeds(vals)
    assert (m[0], lo[0], hi[0]) == pytest.approx(t_interval(vals[:, 0]))

    def curve(seeds):
        return SeedCurve(f"rank ({seeds})", np.arange(30), np.zeros(30), -np.ones(30),
                         np.ones(30), seeds, "C0", "rank")

    assert band_label([curve(1)]) is None
    assert band_label([curve(2)]) == "shaded: min-max range of the 2 seeds"
    assert band_label([curve(5)]) == "shaded: 95 % CI, Student-t over seeds"
    assert band_label([curve(5), curve(2)]).endswith("(min-max range where 2 seeds)")
    fig = return_curves_figure([curve(1)])
    (ax,) = fig.axes
    assert not [c for c in ax.collections if isinstance(c, PolyCollection)]
    assert [t.get_text() for t in fig.legends[0].get_texts()] == ["rank (1)"]
    assert ax.get_lines()[0].get_marker() in (None, "None", "")  # 30 points: no markers
    plt.close(fig)


def test_live_evaluation_pictures_redraw_as_a_fresh_figure_draws():
    """A run keeps its evaluation pictures and redraws only their paths, curves and
    titles (LivePicture): after one episode's paths, the next episode's picture is the
    one a fresh figure of that episode draws, with no trace of the one before (the
    footprints now cross the axes' frame above it: a few pixels at its edge differ)."""
    import torch

    from uabs_rl.config import AreaConfig
    from uabs_rl.evaluation.plots import PgCurvePicture, TrajectoryPicture

    def fresh(pic):  # a full draw of a figure built for this episode only
        pic.fig.canvas.draw()
        return np.asarray(pic.fig.canvas.buffer_rgba()).copy()

    area = AreaConfig(width=350.0, height=170.0)
    gen = torch.Generator().manual_seed(0)
    steps, m, v = 21, 3, 12
    vehicles = torch.rand(steps, 2, v, generator=gen) * torch.tensor([[350.0], [170.0]])
    present = torch.rand(steps, v, generator=gen) > 0.3
    episodes = [torch.rand(steps, m, 2, generator=gen) * torch.tensor([350.0, 170.0])
                for _ in range(2)]
    live = TrajectoryPicture(area, vehicles, present, 11.6, 9, m, live=True)
    assert live.shows(vehicles, present) and not live.shows(vehicles + 1, present)
    drawn, want = [], []
    for i, uabs in enumerate(episodes):
        live.update(uabs, f"episode {i}")
        drawn.append(live.live.render().copy())
        pic = TrajectoryPicture(area, vehicles, present, 11.6, 9, m)
        pic.update(uabs, f"episode {i}")
        want.append(fresh(pic))
    differ = [[(drawn[i] != want[j]).any(-1).mean() for j in range(2)] for i in range(2)]
    assert differ[1][1] < 0.002 and differ[0][0] < 0.002  # the frame's few pixels
    assert differ[1][0] > 0.01  # the second picture is not the first one's

    curves = [np.linspace(0.9, 0.1, 10), np.linspace(0.5, 0.0, 10)]
    live = PgCurvePicture(["rank"], 10, live=True)
    for i, curve in enumerate(curves):
        live.update([curve], f"after {i} episodes")
        drawn = live.live.render().copy()
        pic = PgCurvePicture(["rank"], 10)
        pic.update([curve], f"after {i} episodes")
        assert np.array_equal(drawn, fresh(pic))


def test_trajectory_picture_is_cropped_to_the_area_and_tracks_are_not_lanes():
    """The axes fill the figure's height (no empty band above or below the map), at the
    area's aspect; vehicle positions are dots (one per present vehicle and step), the
    lanes the only lines."""
    import matplotlib.pyplot as plt
    import torch
    from matplotlib.collections import LineCollection, PathCollection

    from uabs_rl.config import AreaConfig
    from uabs_rl.evaluation.plots import trajectory_figure

    area = AreaConfig(width=350.0, height=170.0)
    gen = torch.Generator().manual_seed(0)
    steps, m, v = 21, 3, 12
    uabs = torch.rand(steps, m, 2, generator=gen) * torch.tensor([350.0, 170.0])
    vehicles = torch.rand(steps, 2, v, generator=gen) * torch.tensor([[350.0], [170.0]])
    present = torch.rand(steps, v, generator=gen) > 0.3
    lanes = np.array([[[0.0, 85.0], [350.0, 85.0]], [[175.0, 0.0], [175.0, 170.0]]])
    fig = trajectory_figure(area, uabs, vehicles, present, 11.6, 9, lanes)
    ax = fig.axes[0]
    fig.canvas.draw()
    box = ax.get_window_extent()
    assert box.height / fig.bbox.height > 0.75  # the map fills the height
    assert box.width / box.height == pytest.approx(350 / 170, rel=0.01)
    assert ax.get_xlim() == (0, 350) and ax.get_ylim() == (0, 170)
    (lane_lines,) = [c for c in ax.collections if isinstance(c, LineCollection)]
    assert len(lane_lines.get_segments()) == 2
    dots = [c for c in ax.collections if isinstance(c, PathCollection)]
    assert [len(c.get_offsets()) for c in dots] == [int(present.sum()), int(present[-1].sum())]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "vehicle positions, every step" in labels and "lanes" in labels
    plt.close(fig)


def test_several_folders_report_into_their_common_folder(tmp_path):
    from uabs_rl.report.build import default_out

    assert default_out([tmp_path / "a"]) == tmp_path / "a" / "report"
    assert default_out([tmp_path / "runs" / "a", tmp_path / "runs" / "b"]) == (
        tmp_path / "runs" / "report")


def test_copies_and_runs_without_a_checkpoint_are_left_out_with_a_warning(sweep, tmp_path,
                                                                          capsys):
    """A second run of the same settings and seed would count twice; a run stopped before
    its first checkpoint has no config to group it by: each is one warning line."""
    import shutil

    root = tmp_path / "runs"
    shutil.copytree(sweep / "masking=rank,seed=0", root / "a")
    shutil.copytree(sweep / "masking=rank,seed=0", root / "b")
    shutil.copytree(sweep / "masking=rank,seed=1", root / "c")
    shutil.rmtree(root / "c" / "checkpoints")
    grouping = group_runs(find_runs(root))
    assert [r.path.name for r in grouping.groups["rank"]] == ["a"]
    assert capsys.readouterr().err.splitlines() == [
        f"warning: {root / 'c'} has no checkpoints/last.pt yet (stopped before its first "
        f"checkpoint?): left out",
        f"warning: {root / 'b'} has the settings and seed of {root / 'a'}: left out (one run "
        f"per seed)"]


def test_a_damaged_checkpoint_is_one_line_naming_it(sweep, tmp_path, capsys):
    import shutil

    shutil.copytree(sweep / "masking=rank,seed=0", tmp_path / "run")
    ckpt = tmp_path / "run" / "checkpoints" / "last.pt"
    ckpt.write_bytes(ckpt.read_bytes()[:200])
    assert report_main([str(tmp_path / "run"), "--curves"]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("error: ") and str(ckpt) in line



def test_runs_of_two_learners_are_two_groups_with_their_algo_column(sweep, trace_cache,
                                                                     tmp_path):
    """uabs-report groups runs by learner as it groups by mode: the 3DQN's rank runs and
    QMIX's (the same seeds and settings otherwise) are two groups, each row named by its
    learner in ``algo``."""
    import shutil

    root = tmp_path / "two"
    for seed in (0, 1):
        shutil.copytree(sweep / f"masking=rank,seed={seed}", root / f"dqn3,seed={seed}")
        run(smoke(trace_cache, "masking=rank", f"seed={seed}", "algo=qmix", *QUIET),
            root / f"qmix,seed={seed}")
    out = tmp_path / "report"
    build_report(root, out, with_baselines=True, command="uabs-report test")
    with open(out / "learned_vs_baselines.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * 9 and {r["n_seeds"] for r in rows} == {"2"}
    assert sorted({r["algo"] for r in rows}) == ["dqn3", "qmix"]
    labels = {r["algo"]: r["config"] for r in rows}
    assert labels["dqn3"] != labels["qmix"] and "qmix" in labels["qmix"]


def test_a_learners_own_setting_labels_its_runs_only(sweep, trace_cache, tmp_path):
    """Runs of QMIX at two widths of its mixer beside 3DQN runs: the QMIX groups are named
    by algo.mixing_embed_dim, the 3DQN group is not (the setting is not the 3DQN's), and
    the settings common to every run do not hold it."""
    import shutil

    root = tmp_path / "mixed"
    shutil.copytree(sweep / "masking=rank,seed=0", root / "dqn3")
    for width in (8, 32):
        run(smoke(trace_cache, "masking=rank", "seed=0", "algo=qmix",
                  f"algo.mixing_embed_dim={width}", *QUIET, "train.episodes=3"),
            root / f"qmix{width}")
    grouping = group_runs(find_runs(root))
    assert sorted(grouping.groups) == [
        "rank, algo.name=dqn3, train.episodes=6",
        "rank, algo.name=qmix, algo.mixing_embed_dim=32, train.episodes=3",
        "rank, algo.name=qmix, algo.mixing_embed_dim=8, train.episodes=3"]
    assert "algo.mixing_embed_dim" not in grouping.common
    (dqn3,) = grouping.groups["rank, algo.name=dqn3, train.episodes=6"]
    assert "algo.mixing_embed_dim" not in dqn3.settings and "mixing" not in dqn3.label
    # the whole report of them: its claims per set of settings, its comparison table and
    # the marl-eval export name each group by its own settings
    out = tmp_path / "report"
    assert report_main([str(root), "--no-baselines", "--export", "marl-eval", "--out",
                        str(out)]) == 0
    with open(out / "comparison.csv") as f:
        cells = {r["group"]: r["algo.mixing_embed_dim"] for r in csv.DictReader(f)}
    assert cells == {"rank, algo.name=dqn3, train.episodes=6": "",
                     "rank, algo.name=qmix, algo.mixing_embed_dim=8, train.episodes=3": "8",
                     "rank, algo.name=qmix, algo.mixing_embed_dim=32, train.episodes=3": "32"}
    algos = json.loads((out / "marl_eval.json").read_text())["uabs_rl"]["rank"]
    assert sorted(algos) == ["dqn3, train.episodes=6",
                             "qmix, algo.mixing_embed_dim=32, train.episodes=3",
                             "qmix, algo.mixing_embed_dim=8, train.episodes=3"]


# ----------------------------------------------------------------------------- marl-eval
# marl-eval's README layout, written by hand: two runs of one algorithm on one task
MARL_EVAL_EXAMPLE = {"env": {"task": {"algo": {
    f"run_{k}": {"step_1": {"step_count": 100, "return": [1.0, 2.0], "win_rate": [0.5]},
                 "step_2": {"step_count": 200, "return": [3.0, 4.0], "win_rate": [0.7]},
                 "absolute_metrics": {"return": [3.5] * 20, "win_rate": [0.6]}}
    for k in (1, 2)}}}}


def test_marl_eval_export_matches_the_layout(sweep, report, tmp_path):
    """``--export marl-eval``: env / task (mode) / algorithm / run per seed / a step per
    validation evaluation of every run with its env steps and per-window metrics, and
    best.pt's test windows as absolute metrics; the checker takes the hand-written
    example of marl-eval's README and rejects what departs from it."""
    import copy

    from uabs_rl.evaluation.export import check_marl_eval

    check_marl_eval(MARL_EVAL_EXAMPLE)
    for breaking, match in (
            (lambda d: d["env"]["task"]["algo"]["run_1"].pop("absolute_metrics"), "last entry"),
            (lambda d: d["env"]["task"]["algo"]["run_1"]["step_1"].pop("step_count"),
             "step_count"),
            (lambda d: d["env"]["task"]["algo"]["run_1"]["step_2"].pop("win_rate"), "differ"),
            (lambda d: d["env"]["task"]["algo"]["run_2"].pop("step_2"), "numbers of steps"),
            (lambda d: d["env"]["task"]["algo"]["run_1"]["step_1"].update(
                {"return": "high"}), "list of numbers")):
        bad = copy.deepcopy(MARL_EVAL_EXAMPLE)
        breaking(bad)
        with pytest.raises(ValueError, match=match):
            check_marl_eval(bad)
    out, _ = report
    data = json.loads((out / "marl_eval.json").read_text())
    check_marl_eval(data)
    assert list(data) == ["uabs_rl"] and sorted(data["uabs_rl"]) == ["penalty", "rank"]
    with open(out / "learned_vs_baselines.csv") as f:
        learned = {r["mode"]: float(r["learned"]) for r in csv.DictReader(f)
                   if r["metric"] == "served_fraction"}
    for mode in ("penalty", "rank"):
        (algo,) = data["uabs_rl"][mode].values()
        assert sorted(algo) == ["run_0", "run_1"]
        evals = [r for r in records(sweep / f"masking={mode},seed=0") if r["kind"] == "eval"]
        run0 = algo["run_0"]
        assert len(run0) == len(evals) + 1 and list(run0)[-1] == "absolute_metrics"
        assert run0["step_1"]["return"] == pytest.approx(evals[0]["returns"])
        assert run0["step_2"]["step_count"] > run0["step_1"]["step_count"] > 0
        assert np.mean([np.mean(r["absolute_metrics"]["served_fraction"])
                        for r in algo.values()]) == pytest.approx(learned[mode])
    cli = tmp_path / "cli"
    assert report_main([str(sweep), "--out", str(cli), "--no-baselines",
                        "--export", "marl-eval"]) == 0
    check_marl_eval(json.loads((cli / "marl_eval.json").read_text()))


def test_runs_made_with_another_machines_trace_cache_are_reported_with_cache_dir(
        trace_cache, tmp_path, capsys):
    """A run trained with traces.cache_dir of a folder that this machine cannot use (a
    cluster's scratch; here a file now stands there): uabs-report says so in one line
    naming --cache-dir (it takes no settings), and with --cache-dir reads or builds the
    test traces there and reports; uabs-eval's traces.cache_dir=, which changes no
    result, names no evaluation folder."""
    import shutil

    cluster, laptop = tmp_path / "scratch", tmp_path / "laptop"
    shutil.copytree(trace_cache, cluster)  # the training traces, without SUMO again
    run_dir = tmp_path / "run"
    run(smoke(cluster, *QUIET, "train.episodes=3"), run_dir)
    capsys.readouterr()
    shutil.rmtree(cluster)
    cluster.write_text("")
    assert report_main([str(run_dir), "--out", str(tmp_path / "r1")]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"error: the trace cache {cluster} (run {run_dir}'s traces.cache_dir) cannot hold "
        f"the test traces here (a file, not a folder): give --cache-dir <a folder you can "
        f"write in>."]
    assert not (tmp_path / "r1").exists()
    assert report_main([str(run_dir), "--out", str(tmp_path / "r2"),
                        "--cache-dir", str(laptop)]) == 0
    assert (tmp_path / "r2" / "learned_vs_baselines.csv").exists()
    assert list(laptop.glob("*-test-*.pt"))  # the test traces, built there
    capsys.readouterr()
    with pytest.raises(SystemExit, match="2"):
        report_main([str(run_dir), "--cache-dir", str(cluster)])
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"error: --cache-dir {cluster} is a file: give a folder (it is made if missing) (see "
        f"uabs-report --help)")
    with pytest.raises(SystemExit, match="2"):  # before: OSError's traceback
        report_main([str(run_dir), "--cache-dir", str(tmp_path / ("a" * 300))])
    assert "--cache-dir" in capsys.readouterr().err.splitlines()[-1]
    assert eval_main([str(run_dir), f"traces.cache_dir={laptop}"]) == 0
    assert (run_dir / "evaluation" / "eval.json").exists()
    assert [p.name for p in (run_dir / "evaluation").iterdir() if p.is_dir()] == []
    # another device draws other random numbers: its evaluation keeps a folder of its own
    assert eval_main([str(run_dir), f"traces.cache_dir={laptop}", "device=cpu"]) == 0
    assert [p.name for p in (run_dir / "evaluation").iterdir() if p.is_dir()] == ["device=cpu"]
