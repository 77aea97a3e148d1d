"""Every file of a report of runs, written into one folder (``uabs-report``)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from uabs_rl.evaluation.baselines import MPC, policy_label
from uabs_rl.report.baselines import (
    baselines_by_panel,
    baselines_on_test,
    evaluate_on_test,
    learned_pg_on_test,
    panel_runs,
)
from uabs_rl.report.claims import coverage_bounds, summary
from uabs_rl.report.figures import curves_figure, fig3, fig4
from uabs_rl.report.tables import (
    LVB_COLUMNS,
    comparison,
    learned_vs_baselines,
    learned_vs_baselines_markdown,
    table2,
    table2_markdown,
    write_baselines,
    write_csv,
)
from uabs_rl.runs.sweep import Run, describe, find_runs, group_runs


def build_report(roots: Path | list[Path], out: Path, with_baselines: bool = True,
                 command: str = "", planner: int | None = None,
                 runs: list[Run] | None = None, export: str | None = None,
                 mpc: int | None = None, mpc_beam: int | None = None,
                 mpc_rounds: int | None = None, cache_dir: Path | None = None
                 ) -> dict[str, Any]:
    """Every file of the report of the runs under ``roots`` (``runs``: those already
    found there), written to ``out`` (``planner``: the planner's horizon, to place the
    learned runs between greedy and it; ``mpc``: the deployable mpc's horizon, beside
    greedy and the oracle, ``mpc_beam`` and ``mpc_rounds`` its search's paths per first
    move and passes over the fleet (default planner.BEAM and planner.ROUNDS);
    ``export="marl-eval"``: also ``marl_eval.json``; ``cache_dir``: the trace cache of
    the test traces, in place of each run's ``traces.cache_dir``)."""
    roots = [roots] if isinstance(roots, str | Path) else list(roots)
    grouping = group_runs(find_runs(*roots) if runs is None else runs)
    groups = grouping.groups
    out.mkdir(parents=True, exist_ok=True)
    rows = table2(groups)
    (out / "table2.md").write_text(table2_markdown(rows))
    write_csv(out / "table2.csv", rows)
    fig3(grouping, out / "fig3_eval_return")
    curves_figure(grouping, out / "curves")
    tests = evaluate_on_test([r for runs in groups.values() for r in runs],
                             panel_runs(grouping) if planner is not None else frozenset(),
                             planner or 1, mpc, panel_runs(grouping) if mpc is not None
                             else frozenset(), mpc_beam, mpc_rounds, cache_dir
                             ) if with_baselines else {}
    baselines = baselines_on_test(grouping, tests) if tests else {}
    if baselines:
        write_baselines(out / "baselines.csv", baselines)
    fig4(grouping, baselines_by_panel(grouping, tests) if tests else {}, out / "fig4_pg",
         learned_pg_on_test(groups, tests) if tests else None)
    write_csv(out / "comparison.csv", comparison(grouping, tests or None))
    common = describe(grouping.common, skip=("masking.mode",), words=False) or "none"
    lvb = learned_vs_baselines(grouping, tests) if tests else []
    if lvb:
        write_csv(out / "learned_vs_baselines.csv", lvb, LVB_COLUMNS)
        label = (policy_label(MPC, mpc, "cv", beam=mpc_beam, rounds=mpc_rounds)
                 if mpc is not None else None)
        (out / "learned_vs_baselines.md").write_text(
            learned_vs_baselines_markdown(lvb, common, label))
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
