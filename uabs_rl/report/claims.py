"""The report's summary: the paper's claims, each supported or not, for each set of
other settings run with several masking modes; the warning for runs too short or too
few for verdicts; the baselines section and the coverage bound."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uabs_rl.env.channel import beam_footprint_radius, coverage_bound
from uabs_rl.report.baselines import best_pg, learned_pg_on_test, learned_record, masks_text
from uabs_rl.report.tables import comparison, comparison_markdown, seeds_text, table2
from uabs_rl.runs.sweep import Grouping, Run, describe
from uabs_rl.safety import PAPER_ORDER, masks_collisions

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
             "Runs: " + sep.join(f"{m}: {seeds_text(v)}"
                                 + ("" if all(x.complete for x in v) else " (incomplete)")
                                 for m, v in groups.items()), ""]
    common = describe(grouping.common, skip=("masking.mode",), words=False) or "none"
    lines += [f"Settings common to all runs (where they differ from the defaults): {common}"
              + (f"; compared: {grouping.compared}" if len(groups) > 1 else "") + ".",
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


def _level(record: dict, key: str) -> float:
    """A record's served fraction or P_g as learned_vs_baselines.md computes it: the mean
    of its per-window values (the record's own float32 mean may round to the other side
    of a printed digit)."""
    per_window = record.get(f"{key}s")
    return float(np.nanmean(per_window)) if per_window else float(record[key])


def baselines_section(grouping: Grouping, baselines: dict[str, dict],
                      bounds: dict[str, float], nhat: int | None,
                      tests: dict[Path, dict] | None, where: str) -> list[str]:
    """The summary's baselines table and the learned policies' served fraction."""
    pg = f"P_g(N̂_s={nhat})" if nhat else "P_g(N̂_s)"
    lines = ["", "## Baselines (test traces, every window, the learned policies' masks)",
             "",
             f"| policy | R | collisions | proximity | fallbacks | served | {pg} |",
             "|---|---|---|---|---|---|---|"]
    level = {n: {k: _level(b, k) for k in ("served_fraction", "pg")}
             for n, b in baselines.items()}
    lines += [f"| {n} | {b['return']:.0f} | {b['collisions']:.0f} | {b['proximity']:.0f}"
              f" | {b['fallbacks']:.0f} | {100 * level[n]['served_fraction']:.1f} % | "
              f"{100 * level[n]['pg']:.1f} % |" for n, b in baselines.items()]
    sep = ", " if grouping.by_mode_only else "; "
    learned = {m: float(np.mean([_level(learned_record(run, tests), "served_fraction")
                                 for run in runs])) for m, runs in grouping.groups.items()}
    cover = {m: [learned_record(run, tests)["coverage"] for run in runs
                 if "coverage" in run.best_eval] for m, runs in grouping.groups.items()}
    bound = (f"{100 * next(iter(bounds.values())):.1f} %" if len(set(bounds.values())) == 1
             else ", ".join(f"{masks_text(k)} {100 * v:.1f} %" for k, v in bounds.items()))
    colon = "" if grouping.by_mode_only else ":"
    lines += ["", f"Learned policies' served fraction ({where}): "
              + sep.join(f"{m}{colon} {100 * v:.1f} %" for m, v in learned.items())
              + "".join(f"; {m}{colon} area coverage {100 * np.mean(c):.1f} %"
                        for m, c in cover.items() if c)
              + f". Coverage bound (share of the area under footprints, ideal beams, "
                f"no overlap): {bound}.", ""]
    return lines


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
