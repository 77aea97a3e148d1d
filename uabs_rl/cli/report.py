"""``uabs-report``: the paper's Table 2, Fig. 3 and Fig. 4 from a sweep, with baselines,
for runs of any settings side by side.

    uabs-train -m masking=penalty,flat,rank seed=0,1,2
    uabs-report outputs/multirun/<date_time>            # writes <dir>/report/
    uabs-report outputs/multirun/<date_time> --no-baselines --out docs/results
    uabs-report RUN_A RUN_B --curves                    # training curves overlaid, only

Finds every run under the folders given (following symbolic links), and groups them by
every setting that changes results (what ``uabs-train`` was told: masking mode,
learning settings, scenario, observation, ...; seeds, device, threads, loggers, cache
folders and the like are left out): each group is one line in the figures and one row
(or block) in the tables, with its spread over the group's seeds (a Student-t 95 % CI
with 3 seeds or more, the min-max range with 2, none with 1; each table names its
method, :mod:`uabs_rl.evaluation.stats`). Groups are named by the
settings that differ between them only (``rank, algo.lr=0.001``; the masking mode alone
for a sweep over modes); the settings common to all runs are named once, in the
summary. A run with no evaluation yet is left out with a warning.

Writes: ``table2.md``/``table2.csv`` (collisions in training and evaluation, as events
and as the share of episodes with at least one), ``fig3_eval_return.png``/``.pdf``
(validation return against training episode; penalty in a panel of its own),
``fig4_pg.png``/``.pdf`` (P_g against N̂_s, one panel per masking mode, and per scenario
where groups differ in one, the learned policies beside the baselines under the same
masks), ``curves.png``/``.pdf`` (training and validation return of every run, one line
per run), ``comparison.csv`` (one row per group), ``baselines.csv``, ``summary.md``
(each claim of the paper, supported or not, with the numbers, for each set of other
settings that was run with several masking modes; a table of the groups when they
differ in more than the mode) and ``learned_vs_baselines.csv``/``.md``. Table 2 and
Fig. 3 come from the runs' ``metrics.jsonl`` (training episodes and the periodic
evaluations on the validation traces); Fig. 4, the baselines and the learned-vs-baselines
differences come from each run's ``best.pt`` (chosen on validation) evaluated on the test
traces beside the random, greedy and oracle baselines with the same masks
(``--no-baselines``: Fig. 4 from the best validation evaluations instead).
``--export marl-eval`` also writes ``marl_eval.json``, the runs in marl-eval's layout
(:mod:`uabs_rl.evaluation.export`), for BenchMARL's and Mava's plotting tools.

Numbers in the Markdown files: fractions as ``12.3 %``, their differences in percentage
points as ``+1.2 pt [-0.3, +2.7]``, returns as integers.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from uabs_rl.config import ConfigError
from uabs_rl.env.channel import beam_footprint_radius, coverage_bound
from uabs_rl.evaluation.baselines import BASELINES, MPC, PLANNER
from uabs_rl.evaluation.stats import paired_over_seeds, spread_name, spread_over_seeds
from uabs_rl.paths import OutputFolder, OutputInterrupted, check_path
from uabs_rl.runs.checkpoint import CheckpointError
from uabs_rl.runs.sweep import (  # noqa: F401  (find_runs, Run: the runs, for callers)
    Grouping,
    ReportError,
    Run,
    describe,
    find_runs,
    group_runs,
)
from uabs_rl.safety.masking import PAPER_ORDER, masks_collisions, mode_phrase
from uabs_rl.training.runlog import read_metrics  # noqa: F401  (the metrics reader, for callers)


def group_colors(grouping: Grouping) -> dict[str, str]:
    """A colour per group: the masking mode's where each mode is one group; shades of
    it (darker to lighter) where a mode has several; the usual colour cycle where all
    groups share one mode."""
    from matplotlib.colors import to_hex, to_rgb

    from uabs_rl.evaluation.plots import COLORS, MODE_COLORS

    labels = list(grouping.groups)
    modes = [grouping.mode(lab) for lab in labels]
    if len(set(modes)) == 1 and len(labels) > 1:
        return {lab: COLORS[i % len(COLORS)] for i, lab in enumerate(labels)}
    out = {}
    for mode in dict.fromkeys(modes):
        mine = [lab for lab, m in zip(labels, modes, strict=True) if m == mode]
        base = np.array(to_rgb(MODE_COLORS.get(mode, "0.3")))
        for lab, t in zip(mine, np.linspace(-0.4, 0.4, len(mine)) if len(mine) > 1 else [0.0],
                          strict=True):
            out[lab] = to_hex(base * (1 + t) if t < 0 else base + (1 - base) * t)
    return out


def _seeds(runs: list[Run]) -> str:
    return f"{len(runs)} seed{'s' if len(runs) != 1 else ''}"


# ----------------------------------------------------------------------------- table 2
def collision_counts(run: Run) -> dict[str, float]:
    """Table 2 figures of one run, straight from its metrics."""
    ev = run.evals
    return {
        "train_episodes": len(run.train),
        "train_collision_events": sum(r["collisions"] for r in run.train),
        "train_episodes_with_collision": sum(r["collisions"] > 0 for r in run.train),
        "evaluations": len(ev),
        "eval_episodes": sum(r["windows"] for r in ev),
        "eval_collision_events": sum(r["collisions"] for r in ev),
        "eval_episodes_with_collision": sum(r["episodes_with_collision"] for r in ev),
        "evaluations_with_collision": sum(r["episodes_with_collision"] > 0 for r in ev),
        "train_proximity_events": sum(r["proximity"] for r in run.train),
        "train_fallbacks": sum(r["fallbacks"] for r in run.train),
        "eval_proximity_events": sum(r["proximity"] for r in ev),
        "eval_fallbacks": sum(r["fallbacks"] for r in ev),
    }


def table2(groups: dict[str, list[Run]]) -> list[dict[str, Any]]:
    """One row per group: the means over its seeds (and standard deviations) of
    :func:`collision_counts`. Rows are keyed ``mode`` when each group is a masking mode,
    else ``group`` (the label) and ``mode``."""
    by_mode = all(label == runs[0].mode for label, runs in groups.items())
    rows = []
    for label, runs in groups.items():
        counts = [collision_counts(r) for r in runs]
        row: dict[str, Any] = ({"mode": label} if by_mode else
                               {"group": label, "mode": runs[0].mode})
        row["seeds"] = len(runs)
        for key in counts[0]:
            vals = np.array([c[key] for c in counts], dtype=float)
            row[key] = vals.mean()
            row[key + "_std"] = vals.std()
        row["train_share"] = row["train_episodes_with_collision"] / max(row["train_episodes"], 1)
        row["eval_share"] = (row["eval_episodes_with_collision"]
                             / max(row["eval_episodes"], 1))
        rows.append(row)
    return rows


def _name(row: dict[str, Any]) -> str:
    return row.get("group", row["mode"])


def table2_markdown(rows: list[dict[str, Any]]) -> str:
    def cell(r, events, share_num, share_den):
        return (f"{r[events]:.1f} ± {r[events + '_std']:.1f} events; "
                f"{r[share_num]:.1f} of {r[share_den]:.0f} episodes "
                f"({100 * r[share_num] / max(r[share_den], 1):.1f} %)")

    head = "| | " + " | ".join(f"{_name(r)} ({r['seeds']} seeds)" for r in rows) + " |"
    lines = [head, "|---" * (len(rows) + 1) + "|"]
    lines.append("| Collisions in training | " + " | ".join(
        cell(r, "train_collision_events", "train_episodes_with_collision", "train_episodes")
        for r in rows) + " |")
    lines.append("| Collisions in evaluation | " + " | ".join(
        cell(r, "eval_collision_events", "eval_episodes_with_collision", "eval_episodes")
        for r in rows) + " |")
    lines.append("| Evaluations with a collision | " + " | ".join(
        f"{r['evaluations_with_collision']:.1f} of {r['evaluations']:.0f}" for r in rows) + " |")
    lines.append("| Proximity events (train / eval) | " + " | ".join(
        f"{r['train_proximity_events']:.0f} / {r['eval_proximity_events']:.0f}"
        for r in rows) + " |")
    lines.append("| Mask fallbacks (train / eval) | " + " | ".join(
        f"{r['train_fallbacks']:.0f} / {r['eval_fallbacks']:.0f}" for r in rows) + " |")
    return "\n".join(lines) + "\n\nMeans over seeds (± standard deviation); an evaluation " \
        "episode is one validation window.\n"


# ----------------------------------------------------------------------------- figures
def eval_curves(runs: list[Run]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Episodes, mean and spread over seeds (:func:`uabs_rl.evaluation.stats.spread_over_seeds`) of
    the evaluation return, at the episodes every run evaluated."""
    common = sorted(set.intersection(*[{r["episode"] for r in run.evals} for run in runs]))
    vals = np.array([[next(r["return"] for r in run.evals if r["episode"] == e)
                      for e in common] for run in runs])
    return (np.array(common), *spread_over_seeds(vals.reshape(len(runs), len(common))))


def best_pg(runs: list[Run]) -> np.ndarray:
    """[seeds, N] P_g curves of each run's best validation evaluation."""
    return np.array([run.best_eval["pg_curve"] for run in runs])


def fig3(grouping: Grouping, path: Path) -> list[Path]:
    """Validation return against training episode, one line per group with its spread
    over seeds (:func:`uabs_rl.evaluation.plots.return_curves_figure`), as PNG and PDF."""
    from uabs_rl.evaluation.plots import SeedCurve, return_curves_figure, save_paper_figure

    colors = group_colors(grouping)
    curves = [SeedCurve(f"{label} ({_seeds(runs)})", *eval_curves(runs), len(runs),
                        colors[label], runs[0].mode)
              for label, runs in grouping.groups.items()]
    return save_paper_figure(lambda: return_curves_figure(curves), path)


def fig4(grouping: Grouping, baselines: dict[str, dict[str, dict]], path: Path,
         pg: dict[str, np.ndarray] | None = None) -> list[Path]:
    """P_g(N̂_s), one panel per masking mode (and per scenario where groups differ in
    one: :meth:`Grouping.panels`): the learned policies (mean and spread over seeds; on
    the test traces when ``pg[group]`` holds those curves, else each run's best
    validation evaluation) beside the baselines under the same masks
    (``baselines[panel][name]``; :func:`uabs_rl.evaluation.plots.pg_panels_figure`), as PNG
    and PDF."""
    from uabs_rl.evaluation.plots import (
        BASELINE_STYLES,
        SeedCurve,
        pg_panels_figure,
        save_paper_figure,
    )

    # uabs-report --mpc: the deployable planner, a grey solid line with its own marker
    BASELINE_STYLES.setdefault(MPC, {"color": "0.35", "ls": "-", "marker": "D"})
    colors = group_colors(grouping)
    panels, titles = {}, {}
    for key, labels in grouping.panels().items():
        mode, _, rest = key.partition(", ")
        where = mode_phrase(mode) + (f", {rest}" if rest else "")
        curves = []
        for label in labels:
            runs = grouping.groups[label]
            name = (f"learned, {where}" if grouping.by_mode_only
                    else f"learned, {label} ({_seeds(runs)})")
            mean, lo, hi = spread_over_seeds(100 * (pg[label] if pg else best_pg(runs)))
            curves.append(SeedCurve(name, np.arange(1, len(mean) + 1), mean, lo, hi,
                                    len(runs), colors[label], mode))
        panels[key] = curves
        titles[key] = where + (f" ({_seeds(grouping.groups[labels[0]])})"
                               if grouping.by_mode_only else "")
    curves = {k: {name: 100 * np.asarray(rec["pg_curve"]) for name, rec in b.items()}
              for k, b in baselines.items()}
    return save_paper_figure(lambda: pg_panels_figure(panels, curves, titles), path)


def curves_figure(grouping: Grouping, path: Path) -> list[Path]:
    """Training and validation return of every run, one line per run, coloured by group
    (:func:`uabs_rl.evaluation.plots.run_curves_figure`), as PNG and PDF."""
    from uabs_rl.evaluation.plots import run_curves_figure, save_paper_figure

    colors = group_colors(grouping)
    lines = [(f"{label}, seed {run.seed}", colors[label],
              [r["episode"] for r in run.train], [r["return"] for r in run.train],
              [r["episode"] for r in run.evals], [r["return"] for r in run.evals])
             for label, runs in grouping.groups.items() for run in runs]
    return save_paper_figure(lambda: run_curves_figure(lines), path)


# ----------------------------------------------------------------------------- baselines
def evaluate_on_test(runs: list[Run], planner_runs: frozenset[Path] = frozenset(),
                     horizon: int = 1, mpc: int | None = None,
                     mpc_runs: frozenset[Path] = frozenset()) -> dict[Path, dict[str, dict]]:
    """Each run's ``best.pt`` (chosen on validation) and the random, greedy and oracle
    baselines with the run's masks, on every window of the test traces; for the runs in
    ``planner_runs`` also the receding-horizon planner of ``horizon``, for those in
    ``mpc_runs`` the deployable mpc of horizon ``mpc`` (constant velocity; their cost
    per decision said on stderr)."""
    from uabs_rl.evaluation.load import POLICIES, evaluate_policies, load_evaluation

    out = {}
    for run in runs:
        ev = load_evaluation(run.path, "best", split="test")
        policies = ((*POLICIES, *([PLANNER] if run.path in planner_runs else []),
                     *([MPC] if mpc is not None and run.path in mpc_runs else [])))
        out[run.path] = {k: rec for k, (rec, _) in
                         evaluate_policies(ev, policies, horizon=horizon,
                                           mpc_horizon=mpc or 1).items()}
        if PLANNER in out[run.path]:
            rec = out[run.path][PLANNER]
            print(f"planner H={horizon} on {run.path}: {rec['seconds'] / rec['windows']:.2f} "
                  f"s per window ({rec['windows']} windows)", file=sys.stderr)
        if MPC in out[run.path]:
            rec = out[run.path][MPC]
            print(f"mpc H={mpc} (constant velocity) on {run.path}: "
                  f"{rec['ms_per_decision']:.1f} ms per decision ({rec['windows']} windows)",
                  file=sys.stderr)
    return out


def _panel_run(grouping: Grouping, labels: list[str]) -> Run:
    """The run a panel's baselines come from: the lowest seed of its first group (the
    baselines depend on the masks and the scenario, not on the learner)."""
    return min(grouping.groups[labels[0]], key=lambda r: r.seed)


def panel_runs(grouping: Grouping) -> frozenset[Path]:
    """The runs the baselines (and the planner, once per Fig. 4 panel: it is
    deterministic and independent of the learner) are taken from."""
    return frozenset(_panel_run(grouping, labels).path for labels in grouping.panels().values())


def baselines_by_panel(grouping: Grouping,
                       tests: dict[Path, dict]) -> dict[str, dict[str, dict]]:
    """``{panel: {baseline: test record}}`` (:meth:`Grouping.panels`), from
    :func:`_panel_run`; the planner too where it ran."""
    out = {}
    for key, labels in grouping.panels().items():
        rec = tests[_panel_run(grouping, labels).path]
        out[key] = {name: rec[name] for name in (*BASELINES, MPC, PLANNER) if name in rec}
    return out


def _masks(panel: str) -> str:
    mode, _, rest = panel.partition(", ")
    return f"{mode} masks" + (f", {rest}" if rest else "")


def baselines_on_test(grouping: Grouping, tests: dict[Path, dict]) -> dict[str, dict]:
    """The same records keyed ``"<baseline> (<mode> masks[, settings])"``, for tables."""
    return {f"{name} ({_masks(key)})": rec
            for key, per in baselines_by_panel(grouping, tests).items()
            for name, rec in per.items()}


def learned_pg_on_test(groups: dict[str, list[Run]],
                       tests: dict[Path, dict]) -> dict[str, np.ndarray]:
    """[seeds, N] learned P_g(N̂_s) curves on the test traces, per group."""
    return {label: np.array([tests[run.path]["learned"]["pg_curve"] for run in runs])
            for label, runs in groups.items()}


# ----------------------------------------------------------------------------- test set
LVB_COLUMNS = ["mode", "algo", "n_uabs", "config", "metric", "baseline", "learned", "diff",
               "ci_low", "ci_high", "n_seeds", "method", "gap_share", "gap_ci_low",
               "gap_ci_high"]


def learned_vs_baselines(grouping: Grouping, tests: dict[Path, dict]) -> list[dict[str, Any]]:
    """Every run's ``best.pt`` (chosen on validation) and the baselines on the test
    traces, same windows and masks. Per group: the learned and baseline values (mean
    over seeds), the mean over seeds of each seed's per-window paired difference, and
    its Student-t 95 % CI over seeds (over the windows for one seed; ``method`` says
    which: :func:`uabs_rl.evaluation.stats.paired_over_seeds`). ``config`` names the
    group's settings against the defaults (:attr:`Run.label`), so rows of several reports
    can be put in one table.

    Where the planner ran (``uabs-report --planner H``), the greedy rows of the served
    fraction and P_g also hold the learned share of the greedy-to-planner gap,
    (learned − greedy) / (planner − greedy), its interval that of learned − greedy
    divided by the gap (the planner and greedy are deterministic on these windows)."""
    from uabs_rl.evaluation.load import METRICS, POLICIES

    order = sorted(grouping.groups.items(), key=lambda g: (
        g[1][0].mode, int(g[1][0].settings["scenario.n_uabs"]), g[1][0].label, g[0]))
    panel_of = {label: key for key, labels in grouping.panels().items() for label in labels}
    planners = baselines_by_panel(grouping, tests)
    rows = []
    for group, runs in order:
        per_seed = [tests[run.path] for run in runs]
        planner = planners[panel_of[group]].get(PLANNER)
        mpc = planners[panel_of[group]].get(MPC)  # deterministic: the same for every seed
        bases = (*POLICIES[1:], *([MPC] if mpc is not None else []))
        per_seed = [{**r, MPC: mpc} for r in per_seed] if mpc is not None else per_seed
        for metric, k in METRICS.items():
            for base in bases:
                d = paired_over_seeds([r["learned"][k] for r in per_seed],
                                      [r[base][k] for r in per_seed])
                rows.append({
                    "mode": runs[0].mode, "algo": runs[0].settings["algo.name"],
                    "n_uabs": int(runs[0].settings["scenario.n_uabs"]),
                    "config": runs[0].label, "metric": metric, "baseline": base,
                    "learned": float(np.mean([np.mean(r["learned"][k]) for r in per_seed])),
                    "diff": d["diff"], "ci_low": d["ci_low"], "ci_high": d["ci_high"],
                    "method": d["method"],
                    "baseline_value": float(np.mean([np.mean(r[base][k]) for r in per_seed])),
                    "n_seeds": len(per_seed), "group": group,
                    "nhat": int(runs[0].settings["scenario.nhat_s"])})
                if planner is not None and base == "greedy" and metric != "return":
                    rows[-1].update(_gap_share(rows[-1], float(np.mean(planner[k]))))
    return rows


def _gap_share(row: dict[str, Any], planner: float) -> dict[str, float]:
    """The learned share of the greedy-to-planner gap of a greedy row, with its interval
    (NaN where the planner does not beat greedy: no gap to share)."""
    from uabs_rl.evaluation.planner import scale_to_gap

    s = scale_to_gap(row["diff"], row["ci_low"], row["ci_high"], planner - row["baseline_value"])
    return {"planner_value": planner, "gap_share": s["share"], "gap_ci_low": s["ci_low"],
            "gap_ci_high": s["ci_high"]}


METRIC_NAMES = {"return": "return R", "served_fraction": "served fraction",
                "pg": "P_g(N̂_s={nhat})"}


def fmt_level(metric: str, v: float) -> str:
    """A fraction as ``12.3 %``, a return as ``8272``."""
    return f"{v:.0f}" if metric == "return" else f"{100 * v:.1f} %"


def fmt_diff(metric: str, d: float, lo: float, hi: float) -> str:
    """A difference with its interval: ``+1.2 pt [-0.3, +2.7]`` (percentage points) for a
    fraction, ``+123 [-45, +290]`` for a return."""
    if metric == "return":
        return f"{d:+.0f} [{lo:+.0f}, {hi:+.0f}]"
    return f"{100 * d:+.1f} pt [{100 * lo:+.1f}, {100 * hi:+.1f}]"


def learned_vs_baselines_markdown(rows: list[dict[str, Any]], common: str = "") -> str:
    """One block per group, headed by its label, seeds and M (named once, not per row)."""
    text = ("# Learned policies against the baselines on the test traces\n\n"
            "best.pt of every run (chosen on validation), evaluated with random, greedy "
            "and oracle on every test window with the same masks; differences are "
            "learned − baseline per window, averaged per seed. Served fraction and "
            "P_g(N̂_s) in %, their differences in percentage points (pt).\n")
    if common:
        text += f"\nSettings common to all runs (where they differ from the defaults): {common}.\n"
    groups: dict[str, list[dict]] = {}
    for r in rows:
        groups.setdefault(r["group"], []).append(r)
    for group, rs in groups.items():
        n, interval = rs[0]["n_seeds"], rs[0]["method"]
        text += (f"\n## {group} (M = {rs[0]['n_uabs']}, {n} seed{'s' if n != 1 else ''})\n\n"
                 f"| metric | baseline | learned | baseline value | learned − baseline "
                 f"[{interval}] |\n|---|---|---|---|---|\n")
        text += "".join(
            f"| {METRIC_NAMES.get(r['metric'], r['metric']).format(nhat=r['nhat'])} | "
            f"{r['baseline']} | "
            f"{fmt_level(r['metric'], r['learned'])} | "
            f"{fmt_level(r['metric'], r['baseline_value'])} | "
            f"{fmt_diff(r['metric'], r['diff'], r['ci_low'], r['ci_high'])} |\n" for r in rs)
        text += "".join(
            f"\n{METRIC_NAMES[r['metric']].format(nhat=r['nhat'])}: planner "
            f"{fmt_level(r['metric'], r['planner_value'])}; learned share of the "
            f"greedy-to-planner gap {fmt_share(r)}.\n" for r in rs if "gap_share" in r)
    return text


def fmt_share(row: dict[str, Any]) -> str:
    """``+30 % [+26, +34]``, or why there is none."""
    if np.isnan(row["gap_share"]):
        return "none (the planner does not beat greedy here)"
    lo, mid, hi = (round(100 * row[k]) + 0 for k in ("gap_ci_low", "gap_share", "gap_ci_high"))
    return f"{mid:+d} % [{lo:+d}, {hi:+d}]"


# ----------------------------------------------------------------------------- comparison
def _learned(run: Run, tests: dict[Path, dict] | None) -> dict:
    """The record the summary's served fraction and P_g come from: best.pt on the test
    traces when evaluated there, else the best validation evaluation."""
    return tests[run.path]["learned"] if tests else run.best_eval


def comparison(grouping: Grouping, tests: dict[Path, dict] | None) -> list[dict[str, Any]]:
    """One row per group: its varied settings, seeds, episodes trained, then mean and
    spread over seeds (``_low``/``_high``: :func:`uabs_rl.evaluation.stats.spread_over_seeds`) of
    the validation return (mean of the last 5 evaluations; best evaluation), the served
    fraction and P_g(N̂_s) (best.pt on the test traces, else the best validation
    evaluation) and the collision events in training."""
    rows = []
    for label, runs in grouping.groups.items():
        s = runs[0].settings
        row: dict[str, Any] = {"group": label, "mode": runs[0].mode,
                               **{k: s[k] for k in grouping.others}, "seeds": len(runs),
                               "episodes": min(len(r.train) for r in runs),
                               "spread": spread_name(len(runs)) or "none (1 seed)",
                               "where": "test" if tests else "validation"}
        per_seed = {
            "return_last5": [np.mean([e["return"] for e in r.evals[-5:]]) for r in runs],
            "return_best": [r.best_eval["return"] for r in runs],
            "served_fraction": [_learned(r, tests)["served_fraction"] for r in runs],
            "pg": [_learned(r, tests)["pg"] for r in runs],
            "train_collision_events": [sum(t["collisions"] for t in r.train) for r in runs]}
        for key, vals in per_seed.items():
            mean, lo, hi = spread_over_seeds(np.array(vals, dtype=float)[:, None])
            row[key], row[key + "_low"], row[key + "_high"] = (float(mean[0]), float(lo[0]),
                                                               float(hi[0]))
        rows.append(row)
    return rows


def comparison_markdown(rows: list[dict[str, Any]], nhat: int | None) -> list[str]:
    """The summary's table of the groups: means over seeds with their spread."""
    def cell(r, key, pct=False):
        f = (lambda v: f"{100 * v:.1f}") if pct else (lambda v: f"{v:.0f}")
        unit = " %" if pct else ""
        if r["seeds"] == 1:
            return f"{f(r[key])}{unit}"
        return f"{f(r[key])}{unit} [{f(r[key + '_low'])}, {f(r[key + '_high'])}]"

    where = "best.pt on the test traces" if rows[0]["where"] == "test" else \
        "best validation evaluation"
    pg = f"P_g(N̂_s={nhat})" if nhat else "P_g(N̂_s)"
    lines = ["## Settings compared", "",
             f"Means over seeds [spread]; served fraction and {pg}: {where}.", "",
             f"| group | seeds | episodes | validation R, last 5 evaluations | best "
             f"validation R | served fraction | {pg} | collisions in training |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['group']} | {r['seeds']} | {r['episodes']} | "
              f"{cell(r, 'return_last5')} | {cell(r, 'return_best')} | "
              f"{cell(r, 'served_fraction', True)} | {cell(r, 'pg', True)} | "
              f"{cell(r, 'train_collision_events')} |" for r in rows]
    seeds = sorted({r["seeds"] for r in rows}, reverse=True)
    spreads = [spread_name(n) for n in seeds if n > 1] + (
        ["none with 1 seed"] if 1 in seeds else [])
    if spreads != ["none with 1 seed"]:
        lines += ["", "Spread: " + "; ".join(spreads) + "."]
    return lines + [""]


# ----------------------------------------------------------------------------- summary
# below these the verdicts are not worth much: validation curves of the paper's protocol
# level off after about 100 episodes (docs/results/learning.md), and a CI over fewer
# than 3 seeds says little
MIN_EPISODES, MIN_SEEDS = 200, 3


def short_run_warning(groups: dict[str, list[Run]]) -> str | None:
    """A warning when the runs are too short or too few for verdicts, else None."""
    episodes = min(run.train[-1]["episode"] if run.train else 0
                   for runs in groups.values() for run in runs)
    seeds = min(len(runs) for runs in groups.values())
    what = "mode" if all(label == runs[0].mode for label, runs in groups.items()) else "group"
    problems = []
    if episodes < MIN_EPISODES:
        problems.append(f"the shortest run trained {episodes} episodes (< {MIN_EPISODES}; "
                        f"the paper's protocol trains 1000)")
    if seeds < MIN_SEEDS:
        problems.append(f"a {what} has {seeds} seed{'s' if seeds != 1 else ''} (< {MIN_SEEDS})")
    if not problems:
        return None
    return ("WARNING: " + "; ".join(problems) + ". This report's verdicts are not evidence "
            "for or against the paper's claims; run the full protocol for that.")


def claims(by_mode: dict[str, list[Run]], tests: dict[Path, dict] | None,
           level: str = "##") -> list[str]:
    """The paper's three claims (Table 2, Fig. 3, Fig. 4), each supported or not, for
    runs that differ in the masking mode only."""
    r = {row["mode"]: row for row in table2(by_mode)}
    final = {m: float(np.mean([np.mean([e["return"] for e in run.evals[-5:]]) for run in runs]))
             for m, runs in by_mode.items()}
    best = {m: float(np.mean([run.best_eval["return"] for run in runs]))
            for m, runs in by_mode.items()}
    pg = ({m: v.mean(0) for m, v in learned_pg_on_test(by_mode, tests).items()} if tests
          else {m: best_pg(runs).mean(0) for m, runs in by_mode.items()})
    where = ("best.pt on the test traces" if tests else "best validation evaluation")

    def verdict(ok: bool | None) -> str:
        return "n/a (mode missing)" if ok is None else ("supported" if ok else "NOT supported")

    all3 = set(PAPER_ORDER) <= set(by_mode)
    worst, middle, top = PAPER_ORDER
    c1 = None if not all3 else (
        all(r[m]["train_collision_events"] > 0 for m in PAPER_ORDER
            if not masks_collisions(m))
        and all(r[m]["train_collision_events"] == 0 and r[m]["eval_collision_events"] == 0
                for m in PAPER_ORDER if masks_collisions(m)))
    lines = [f"{level} Table 2: masking avoids collisions, penalties do not",
             f"**{verdict(c1)}**. "
             + "; ".join(f"{m}: {r[m]['train_collision_events']:.1f} collision events in "
                         f"training ({100 * r[m]['train_share']:.1f} % of episodes), "
                         f"{r[m]['eval_collision_events']:.1f} in evaluation "
                         f"({100 * r[m]['eval_share']:.1f} % of episodes)" for m in r)
             + ". The paper: penalty 170 (17 %) and 14 (28 %); flat and rank 0.", ""]
    c2 = None if not all3 else final[top] > final[middle] > final[worst]
    lines += [f"{level} Fig. 3: evaluation reward rank > flat > penalty", f"**{verdict(c2)}** "
              "(mean over seeds of the last 5 evaluations): "
              + ", ".join(f"{m} {final[m]:.0f}" for m in final) + "; best evaluation: "
              + ", ".join(f"{m} {best[m]:.0f}" for m in best) + ".", ""]
    c3 = None if not all3 else bool(
        (pg[top] >= pg[middle] - 1e-9).all() and (pg[middle] > pg[worst]).all())
    lines += [f"{level} Fig. 4: P_g rank ≥ flat, both above penalty", f"**{verdict(c3)}** "
              f"(P_g in % for N̂_s = 1..N, {where}, mean over seeds):", ""]
    return lines + [f"- {m}: " + ", ".join(f"{100 * v:.1f}" for v in pg[m]) for m in pg]


def claims_per_context(grouping: Grouping, tests: dict[Path, dict] | None) -> list[str]:
    """The claims for each set of other settings run with several masking modes; a
    line saying why where none was."""
    contexts = grouping.contexts()
    if len(contexts) == 1 and len(grouping.groups) == 1:
        return ["## The paper's claims", f"Not judged: they compare masking modes, and "
                f"these runs have one ({grouping.mode(next(iter(grouping.groups)))})."]
    if len(contexts) == 1:
        return claims(next(iter(contexts.values())), tests)
    several = {ctx: by_mode for ctx, by_mode in contexts.items() if len(by_mode) > 1}
    lines = []
    for ctx, by_mode in several.items():
        lines += [f"## The paper's claims, {ctx}", "", *claims(by_mode, tests, "###"), ""]
    alone = [f"{ctx} ({', '.join(by_mode)} only)" for ctx, by_mode in contexts.items()
             if len(by_mode) == 1]
    if alone:
        lines += ["## The paper's claims" + (", other settings" if several else ""),
                  "Not judged for " + "; ".join(alone) + ": they compare masking modes run "
                  "under the same other settings, and these were run with one mode.", ""]
    return lines[:-1] if lines and lines[-1] == "" else lines


def summary(grouping: Grouping, baselines: dict[str, dict], command: str,
            bounds: dict[str, float], nhat: int | None,
            tests: dict[Path, dict] | None = None) -> str:
    groups = grouping.groups
    sep = ", " if grouping.by_mode_only else "; "
    lines = ["# Sweep summary", "", f"Produced by: `{command}`", "",
             "Runs: " + sep.join(f"{m}: {_seeds(v)}"
                                 + ("" if all(x.complete for x in v) else " (incomplete)")
                                 for m, v in groups.items()), ""]
    common = describe(grouping.common, skip=("masking.mode",), words=False) or "none"
    lines += [f"Settings common to all runs (where they differ from the defaults): {common}"
              + (f"; compared: {', '.join(grouping.varied)}" if len(groups) > 1 else "") + ".",
              ""]
    warning = short_run_warning(groups)
    if warning:
        lines += [f"**{warning}**", ""]
    if not grouping.by_mode_only:
        lines += comparison_markdown(comparison(grouping, tests), nhat)
    lines += claims_per_context(grouping, tests)
    if baselines:
        where = "best.pt on the test traces" if tests else "best validation evaluation"
        lines += baselines_section(grouping, baselines, bounds, nhat, tests, where)
    return "\n".join(lines) + "\n"


def baselines_section(grouping: Grouping, baselines: dict[str, dict],
                      bounds: dict[str, float], nhat: int | None,
                      tests: dict[Path, dict] | None, where: str) -> list[str]:
    """The summary's baselines table and the learned policies' served fraction."""
    pg = f"P_g(N̂_s={nhat})" if nhat else "P_g(N̂_s)"
    lines = ["", "## Baselines (test traces, every window, the learned policies' masks)",
             "",
             f"| policy | R | collisions | proximity | fallbacks | served | {pg} |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {n} | {b['return']:.0f} | {b['collisions']:.0f} | {b['proximity']:.0f}"
              f" | {b['fallbacks']:.0f} | {100 * b['served_fraction']:.1f} % | "
              f"{100 * b['pg']:.1f} % |" for n, b in baselines.items()]
    sep = ", " if grouping.by_mode_only else "; "
    learned = {m: float(np.mean([_learned(run, tests)["served_fraction"] for run in runs]))
               for m, runs in grouping.groups.items()}
    cover = {m: [_learned(run, tests)["coverage"] for run in runs if "coverage" in run.best_eval]
             for m, runs in grouping.groups.items()}
    bound = (f"{100 * next(iter(bounds.values())):.1f} %" if len(set(bounds.values())) == 1
             else ", ".join(f"{_masks(k)} {100 * v:.1f} %" for k, v in bounds.items()))
    colon = "" if grouping.by_mode_only else ":"
    lines += ["", f"Learned policies' served fraction ({where}): "
              + sep.join(f"{m}{colon} {100 * v:.1f} %" for m, v in learned.items())
              + "".join(f"; {m}{colon} area coverage {100 * np.mean(c):.1f} %"
                        for m, c in cover.items() if c)
              + f". Coverage bound (share of the area under footprints, ideal beams, "
                f"no overlap): {bound}.", ""]
    return lines


# ----------------------------------------------------------------------------- main
def coverage_bounds(grouping: Grouping) -> dict[str, float]:
    """The coverage bound of each Fig. 4 panel's scenario (share of the area under
    footprints, ideal beams, no overlap)."""
    out = {}
    for key, labels in grouping.panels().items():
        s = grouping.groups[labels[0]][0].settings
        r_b = beam_footprint_radius(s["scenario.altitude"], s["channel.fov_deg"],
                                    s["channel.n_beams"])
        out[key] = coverage_bound(s["scenario.n_uabs"], s["channel.n_beams"], r_b,
                                  s["scenario.area.width"] * s["scenario.area.height"])
    return out


def _write_csv(path: Path, rows: list[dict[str, Any]], columns: list[str] | None = None) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns or list(rows[0]), extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def _write_baselines(path: Path, baselines: dict[str, dict]) -> None:
    with open(path, "w", newline="") as f:
        keys = ["policy", "return", "return_std", "collisions", "proximity", "fallbacks",
                "served_fraction", "pg"]
        w = csv.writer(f)
        w.writerow(keys)
        for name, b in baselines.items():
            w.writerow([name] + [b[k] for k in keys[1:]])


def build_report(roots: Path | list[Path], out: Path, with_baselines: bool = True,
                 command: str = "", planner: int | None = None,
                 runs: list[Run] | None = None, export: str | None = None,
                 mpc: int | None = None) -> dict[str, Any]:
    """Every file of the report of the runs under ``roots`` (``runs``: those already
    found there), written to ``out`` (``planner``: the planner's horizon, to place the
    learned runs between greedy and it; ``mpc``: the deployable mpc's horizon, beside
    greedy and the oracle; ``export="marl-eval"``: also ``marl_eval.json``)."""
    roots = [roots] if isinstance(roots, str | Path) else list(roots)
    grouping = group_runs(find_runs(*roots) if runs is None else runs)
    groups = grouping.groups
    out.mkdir(parents=True, exist_ok=True)
    rows = table2(groups)
    (out / "table2.md").write_text(table2_markdown(rows))
    _write_csv(out / "table2.csv", rows)
    fig3(grouping, out / "fig3_eval_return")
    curves_figure(grouping, out / "curves")
    tests = evaluate_on_test([r for runs in groups.values() for r in runs],
                             panel_runs(grouping) if planner is not None else frozenset(),
                             planner or 1, mpc, panel_runs(grouping) if mpc is not None
                             else frozenset()) if with_baselines else {}
    baselines = baselines_on_test(grouping, tests) if tests else {}
    if baselines:
        _write_baselines(out / "baselines.csv", baselines)
    fig4(grouping, baselines_by_panel(grouping, tests) if tests else {}, out / "fig4_pg",
         learned_pg_on_test(groups, tests) if tests else None)
    _write_csv(out / "comparison.csv", comparison(grouping, tests or None))
    common = describe(grouping.common, skip=("masking.mode",), words=False) or "none"
    lvb = learned_vs_baselines(grouping, tests) if tests else []
    if lvb:
        _write_csv(out / "learned_vs_baselines.csv", lvb, LVB_COLUMNS)
        (out / "learned_vs_baselines.md").write_text(learned_vs_baselines_markdown(lvb, common))
    if export == "marl-eval":
        from uabs_rl.evaluation.export import marl_eval

        (out / "marl_eval.json").write_text(json.dumps(marl_eval(grouping, tests or None)))
    nhats = {run.settings["scenario.nhat_s"] for runs in groups.values() for run in runs}
    (out / "summary.md").write_text(summary(
        grouping, baselines, command or "uabs-report " + " ".join(map(str, roots)),
        coverage_bounds(grouping), nhats.pop() if len(nhats) == 1 else None, tests or None))
    return {"rows": rows, "baselines": baselines, "grouping": grouping,
            "by_mode": groups, "learned_vs_baselines": lvb}


def default_out(roots: list[Path]) -> Path:
    """``<folder>/report`` for one folder; for several, ``report`` in their deepest
    common folder."""
    if len(roots) == 1:
        return roots[0] / "report"
    return Path(os.path.commonpath([os.path.abspath(r) for r in roots])) / "report"


# every file uabs-report writes (a report folder written before the marker file
# existed is recognised by these)
REPORT_FILES = ("table2.md", "table2.csv", "fig3_eval_return.png", "fig3_eval_return.pdf",
                "fig4_pg.png", "fig4_pg.pdf", "curves.png", "curves.pdf", "comparison.csv",
                "baselines.csv", "summary.md", "learned_vs_baselines.csv",
                "learned_vs_baselines.md", "marl_eval.json")


class Parser(argparse.ArgumentParser):
    """An argument parser whose refusal is one line on stderr (and exit status 2), not
    the usage text followed by the error."""

    def error(self, message: str):
        self.exit(2, f"error: {message} (see {self.prog} --help)\n")


def output_folder(out: Path, given: bool) -> OutputFolder:
    """The report's output folder: written whole or not at all
    (:class:`uabs_rl.paths.OutputFolder`), never one holding files of others."""
    return OutputFolder(out, "uabs-report", REPORT_FILES,
                        "--out" if given else "the report folder")


def main(argv: list[str] | None = None) -> int:
    ap = Parser(
        prog="uabs-report",
        description="Table 2, Fig. 3 and Fig. 4 of uabs-train runs, grouped by the settings "
                    "that differ between them, with the baselines on the test traces.")
    ap.add_argument("roots", type=Path, nargs="+", metavar="FOLDER",
                    help="run folders or folders of runs (a multirun folder); several "
                         "are reported together")
    ap.add_argument("--out", type=Path,
                    help="output folder (default: FOLDER/report; with several folders, "
                         "report/ in the folder that holds them all)")
    ap.add_argument("--no-baselines", dest="baselines", action="store_false",
                    help="skip the test-trace evaluation: Fig. 4 from each run's best "
                         "validation evaluation, no baselines")
    ap.add_argument("--planner", type=int, metavar="H",
                    help="also run the receding-horizon planner of horizon H (it knows the "
                         "vehicles' future positions: an upper reference) and give each "
                         "group's share of the greedy-to-planner gap; about 1 s per test "
                         "window and masking mode at H = 10")
    ap.add_argument("--mpc", type=int, metavar="H",
                    help="also run the deployable receding-horizon planner of horizon H "
                         "(mpc: the vehicles' current and previous positions extrapolated "
                         "at constant velocity) beside greedy and the oracle, in the "
                         "baseline tables and Fig. 4")
    ap.add_argument("--export", choices=("marl-eval",),
                    help="also write the runs in marl-eval's JSON layout (marl_eval.json: "
                         "per run, per evaluation, per metric; best.pt's test windows as "
                         "absolute metrics), for BenchMARL's and Mava's plotting tools")
    ap.add_argument("--curves", action="store_true",
                    help="only overlay the runs' training and validation curves "
                         "(curves.png/.pdf), in seconds")
    args = ap.parse_args(argv)
    if args.planner is not None and (args.planner < 1 or not args.baselines):
        ap.error("--planner H needs H >= 1 and the test-trace evaluation (no --no-baselines)")
    if args.mpc is not None and (args.mpc < 1 or not args.baselines):
        ap.error("--mpc H needs H >= 1 and the test-trace evaluation (no --no-baselines)")
    cmd = "uabs-report " + " ".join(sys.argv[1:] if argv is None else argv)
    try:
        for root in args.roots:
            check_path(root, "FOLDER")
        out = output_folder(args.out or default_out(args.roots), args.out is not None)
        out.check()
        runs = find_runs(*args.roots)  # the inputs are refused before any folder is made
        with out.writing() as folder:  # the previous report stays whole until the end
            if args.curves:
                curves_figure(group_runs(runs), folder / "curves")
            else:
                res = build_report(args.roots, folder, args.baselines, cmd, args.planner,
                                   runs=runs, export=args.export, mpc=args.mpc)
                text = (folder / "summary.md").read_text()
    except (ReportError, ConfigError, CheckpointError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OutputInterrupted as e:
        print(str(e), file=sys.stderr)
        return e.exit_code
    except SystemExit as e:  # read_metrics: a damaged metrics line, one line already
        if isinstance(e.code, str):
            print(e.code, file=sys.stderr)
            return 2
        raise
    except OSError as e:  # an input that cannot be read (permissions, a name too long)
        print(f"error: cannot read {e.filename or 'an input'} ({e.strerror or e}): check "
              f"the FOLDER arguments.", file=sys.stderr)
        return 2
    if args.curves:
        print(f"wrote {out.path / 'curves.png'} (and .pdf)")
        return 0
    out = out.path
    print(text)
    warning = short_run_warning(res["grouping"].groups)
    if warning:
        print(warning, file=sys.stderr)
    print(f"wrote {out} (figures as PNG and PDF)")
    return 0


def run_main() -> None:
    sys.exit(main())


if __name__ == "__main__":
    run_main()
