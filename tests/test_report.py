"""uabs-report on a tiny real sweep; uabs-eval on one of its runs."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from tests.test_train import records, smoke
from uabs_rl.evaluate import main as eval_main
from uabs_rl.report import build_report
from uabs_rl.train import run


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
    return out, build_report(sweep, out, with_baselines=True, command="uabs-report test")


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
        assert rows[mode]["train_episodes"] == 6 and rows[mode]["eval_episodes"] == 4
    assert rows["rank"]["train_collision_events"] == 0
    with open(out / "table2.csv") as f:
        csv_rows = {r["mode"]: r for r in csv.DictReader(f)}
    assert float(csv_rows["penalty"]["train_collision_events"]) == pytest.approx(
        rows["penalty"]["train_collision_events"])
    assert "Collisions in training" in (out / "table2.md").read_text()


def test_figures_exist_as_png_and_pdf(report):
    out, _ = report
    for name in ("fig3_eval_return", "fig4_pg"):
        data = (out / f"{name}.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n"
        assert 15_000 < len(data) < 2_000_000
        pdf = (out / f"{name}.pdf").read_bytes()
        assert pdf[:5] == b"%PDF-" and len(pdf) > 5_000


def test_figures_have_panels_and_no_figure_numbers(sweep, report, tmp_path):
    """Penalty gets its own panel in Fig. 3; Fig. 4 has a panel per mode, its baselines
    in greys and dashes; no title says 'Fig.'; the legend lies outside the axes."""
    import matplotlib

    from uabs_rl.plots import MODE_COLORS
    from uabs_rl.report import best_pg, fig3, fig4, find_runs

    runs = find_runs(sweep)
    by_mode = {m: [r for r in runs if r.mode == m] for m in ("penalty", "rank")}
    figs = []
    real_close = matplotlib.pyplot.close
    matplotlib.pyplot.close = figs.append  # keep the figures to look at them
    try:
        fig3(by_mode, tmp_path / "f3")
        base = {"rank": {"greedy": {"pg_curve": list(best_pg(by_mode["rank"]).mean(0))}}}
        fig4(by_mode, base, tmp_path / "f4")
    finally:
        matplotlib.pyplot.close = real_close
    f3, f4 = figs
    assert [ax.get_title() for ax in f3.axes] == ["rank masking", "penalty (reward penalties)"]
    assert len(f4.axes) == 2
    for fig in (f3, f4):
        assert not any("Fig" in ax.get_title() for ax in fig.axes)
        assert len(fig.legends) == 1 and all(ax.get_legend() is None for ax in fig.axes)
        legend_box = fig.legends[0].get_window_extent(fig.canvas.get_renderer())
        for ax in fig.axes:
            assert not legend_box.overlaps(ax.get_window_extent())
    rank_ax = f4.axes[1]
    learned, greedy = rank_ax.get_lines()[:2]
    assert matplotlib.colors.same_color(learned.get_color(), MODE_COLORS["rank"])
    assert greedy.get_linestyle() == "--" and greedy.get_color() != learned.get_color()
    for fig in figs:
        real_close(fig)


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
    assert list(rows[0]) == ["mode", "n_uabs", "config", "metric", "baseline", "learned",
                             "diff", "ci_low", "ci_high", "n_seeds"]
    # 2 modes x 3 metrics x 3 baselines, 2 seeds each, smoke runs: recoverable, paper obs
    assert len(rows) == 18 and {r["n_seeds"] for r in rows} == {"2"}
    # the smoke preset's network and learning settings differ from the defaults: named
    (config,) = {r["config"] for r in rows}
    assert config.startswith("paper ") and "algo.hidden=[32, 32]" in config
    for r, full in zip(rows, res["learned_vs_baselines"], strict=True):
        assert float(r["diff"]) == pytest.approx(full["learned"] - full["baseline_value"],
                                                 abs=1e-6)
        assert float(r["ci_low"]) <= float(r["diff"]) <= float(r["ci_high"])


def test_report_refuses_runs_of_different_experiments(sweep, tmp_path):
    """Seeds of another scenario or preset must not be averaged with the sweep's."""
    import shutil

    import torch

    from uabs_rl.report import find_runs

    root = tmp_path / "mixed"
    for name in ("masking=rank,seed=0", "masking=rank,seed=1"):
        shutil.copytree(sweep / name, root / name)
    ckpt = root / "masking=rank,seed=1" / "checkpoints" / "last.pt"
    state = torch.load(ckpt, weights_only=True)
    state["config"]["scenario"]["name"] = "elsewhere"
    torch.save(state, ckpt)
    with pytest.raises(SystemExit, match=r"not one experiment.*scenario\.name"):
        find_runs(root)
    assert len(find_runs(sweep / "masking=rank,seed=0")) == 1  # a single run folder works


@pytest.mark.parametrize("scenario,algo,train,label", [
    ({}, {}, {}, "paper"),
    ({"lookahead_obs": True}, {"lr": 3e-4}, {}, "lookahead algo.lr=0.0003"),
    ({"lookahead_obs": True, "motion_obs": True}, {}, {"n_envs": 4},
     "lookahead+motion train.n_envs=4"),
    ({}, {"n_step": 3}, {"population": 5}, "paper algo.n_step=3"),  # population: neutral
])
def test_run_labels_name_the_observation_and_learning_settings(scenario, algo, train, label):
    from uabs_rl.report import Run

    cfg = {"scenario": scenario, "masking": {"recoverable": True}, "algo": algo,
           "train": train}
    assert Run(Path("x"), "flat", 0, 1000, [], [], cfg).label == label
