"""The report's tables: Table 2 (collisions), the comparison of the groups, the learned
policies against the baselines on the test traces, and their CSV files."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from uabs_rl.evaluation.baselines import MPC, PLANNER
from uabs_rl.evaluation.stats import (
    paired_over_seeds,
    signed,
    spread_name,
    spread_over_seeds,
)
from uabs_rl.report.baselines import baselines_by_panel, learned_record
from uabs_rl.runs.sweep import Grouping, Run


def seeds_text(runs: list[Run]) -> str:
    return f"{len(runs)} seed{'s' if len(runs) != 1 else ''}"


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
    """One row per group: the means over its seeds (and their sample standard deviations,
    n − 1 in the denominator; 0 for one seed) of :func:`collision_counts`. Rows are keyed
    ``mode`` when each group is a masking mode, else ``group`` (the label) and ``mode``."""
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
            row[key + "_std"] = vals.std(ddof=1) if vals.size > 1 else 0.0
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

    head = "| | " + " | ".join(
        f"{_name(r)} ({r['seeds']} seed{'s' if r['seeds'] != 1 else ''})" for r in rows) + " |"
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
    return "\n".join(lines) + (
        "\n\nMeans over seeds (± their sample standard deviation, n − 1 in the "
        "denominator); an evaluation episode is one validation window.\n")


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
                    "learned": float(np.mean([np.nanmean(r["learned"][k]) for r in per_seed])),
                    "diff": d["diff"], "ci_low": d["ci_low"], "ci_high": d["ci_high"],
                    "method": d["method"],
                    "baseline_value": float(np.mean([np.nanmean(r[base][k])
                                                     for r in per_seed])),
                    "n_seeds": len(per_seed), "group": group,
                    "nhat": int(runs[0].settings["scenario.nhat_s"])})
                if planner is not None and base == "greedy" and metric != "return":
                    rows[-1].update(_gap_share(rows[-1], float(np.nanmean(planner[k]))))
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
        return f"{signed(d, 0)} [{signed(lo, 0)}, {signed(hi, 0)}]"
    return f"{signed(100 * d)} pt [{signed(100 * lo)}, {signed(100 * hi)}]"


def learned_vs_baselines_markdown(rows: list[dict[str, Any]], common: str = "",
                                  mpc_label: str | None = None) -> str:
    """One block per group, headed by its label, seeds and M (named once, not per row);
    ``mpc_label``: the mpc's name with its search (``policy_label``), where it ran."""
    with_mpc = mpc_label is not None and any(r["baseline"] == MPC for r in rows)
    text = ("# Learned policies against the baselines on the test traces\n\n"
            "best.pt of every run (chosen on validation), evaluated with random, greedy "
            + (f"and oracle (and the deployable {mpc_label}, constant-velocity prediction) "
               if with_mpc else "and oracle ")
            + "on every test window with the same masks; differences are "
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
            f"{mpc_label if with_mpc and r['baseline'] == MPC else r['baseline']} | "
            f"{fmt_level(r['metric'], r['learned'])} | "
            f"{fmt_level(r['metric'], r['baseline_value'])} | "
            f"{fmt_diff(r['metric'], r['diff'], r['ci_low'], r['ci_high'])} |\n" for r in rs)
        text += "".join(
            f"\n{METRIC_NAMES[r['metric']].format(nhat=r['nhat'])}: planner "
            f"{fmt_level(r['metric'], r['planner_value'])}; learned share of the "
            f"greedy-to-planner gap {fmt_share(r)}"
            + ("" if np.isnan(r["gap_share"]) else
               " (learned − greedy's interval divided by the gap; uabs-eval's, over one "
               "run's windows, is a bootstrap)")
            + ".\n" for r in rs if "gap_share" in r)
    return text


def fmt_share(row: dict[str, Any]) -> str:
    """``+30 % [+26, +34]``, or why there is none."""
    if np.isnan(row["gap_share"]):
        return "none (the planner does not beat greedy here)"
    lo, mid, hi = (signed(100 * row[k], 0) for k in ("gap_ci_low", "gap_share", "gap_ci_high"))
    return f"{mid} % [{lo}, {hi}]"


def comparison(grouping: Grouping, tests: dict[Path, dict] | None) -> list[dict[str, Any]]:
    """One row per group: its varied settings, seeds, episodes trained, then mean and
    spread over seeds (``_low``/``_high``: :func:`uabs_rl.evaluation.stats.spread_over_seeds`) of
    the validation return (mean of the last 5 evaluations; best evaluation), the served
    fraction and P_g(N̂_s) (best.pt on the test traces, else the best validation
    evaluation) and the collision events in training."""
    rows = []
    for label, runs in grouping.groups.items():
        s = runs[0].settings
        # None (an empty cell) for another learner's own setting
        row: dict[str, Any] = {"group": label, "mode": runs[0].mode,
                               **{k: s.get(k) for k in grouping.others}, "seeds": len(runs),
                               "episodes": min(len(r.train) for r in runs),
                               "spread": spread_name(len(runs)) or "none (1 seed)",
                               "where": "test" if tests else "validation"}
        per_seed = {
            "return_last5": [np.mean([e["return"] for e in r.evals[-5:]]) for r in runs],
            "return_best": [r.best_eval["return"] for r in runs],
            "served_fraction": [learned_record(r, tests)["served_fraction"] for r in runs],
            "pg": [learned_record(r, tests)["pg"] for r in runs],
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


def write_csv(path: Path, rows: list[dict[str, Any]], columns: list[str] | None = None) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns or list(rows[0]), extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def write_baselines(path: Path, baselines: dict[str, dict]) -> None:
    with open(path, "w", newline="") as f:
        keys = ["policy", "return", "return_std", "collisions", "proximity", "fallbacks",
                "served_fraction", "pg"]
        search = ["horizon", "beam", "rounds", "predictor"]  # a planner's; blank elsewhere
        w = csv.writer(f)
        w.writerow(keys + search)
        for name, b in baselines.items():
            planned = name.split()[0] in (MPC, PLANNER)
            w.writerow([name] + [b[k] for k in keys[1:]]
                       + [b.get(k, "") if planned else "" for k in search])
