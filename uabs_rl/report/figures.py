"""The report's figures: Fig. 3 (validation return against training episode), Fig. 4
(P_g against N̂_s beside the baselines) and every run's curves, coloured by group."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uabs_rl.evaluation.baselines import MPC
from uabs_rl.evaluation.stats import spread_over_seeds
from uabs_rl.report.baselines import best_pg
from uabs_rl.report.tables import seeds_text
from uabs_rl.runs.sweep import Grouping, Run
from uabs_rl.safety import mode_phrase


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


def eval_curves(runs: list[Run]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Episodes, mean and spread over seeds (:func:`uabs_rl.evaluation.stats.spread_over_seeds`) of
    the evaluation return, at the episodes every run evaluated."""
    common = sorted(set.intersection(*[{r["episode"] for r in run.evals} for run in runs]))
    vals = np.array([[next(r["return"] for r in run.evals if r["episode"] == e)
                      for e in common] for run in runs])
    return (np.array(common), *spread_over_seeds(vals.reshape(len(runs), len(common))))


def fig3(grouping: Grouping, path: Path) -> list[Path]:
    """Validation return against training episode, one line per group with its spread
    over seeds (:func:`uabs_rl.evaluation.plots.return_curves_figure`), as PNG and PDF."""
    from uabs_rl.evaluation.plots import SeedCurve, return_curves_figure, save_paper_figure

    colors = group_colors(grouping)
    curves = [SeedCurve(f"{label} ({seeds_text(runs)})", *eval_curves(runs), len(runs),
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
                    else f"learned, {label} ({seeds_text(runs)})")
            mean, lo, hi = spread_over_seeds(100 * (pg[label] if pg else best_pg(runs)))
            curves.append(SeedCurve(name, np.arange(1, len(mean) + 1), mean, lo, hi,
                                    len(runs), colors[label], mode))
        panels[key] = curves
        titles[key] = where + (f" ({seeds_text(grouping.groups[labels[0]])})"
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
