"""Planning against learning: greedy, the oracle, the deployable receding-horizon planner
(``mpc``: the planner fed by a predictor, constant velocity by default) and the
clairvoyant planner (the ceiling) on every window of the default grid's test traces,
with Student-t 95 % CIs over the windows and the compute per decision.

    python benchmarks/planning_vs_learning.py --out docs/results/planning_vs_learning
    python benchmarks/planning_vs_learning.py --modes rank --fleets 3 6 --sees all 100
    python benchmarks/planning_vs_learning.py --predictors cv road --horizons 1 5 10
    python benchmarks/planning_vs_learning.py --paired docs/results/planning_vs_learning/road
    python benchmarks/planning_vs_learning.py --horizons 5 --uncoordinated
    python benchmarks/planning_vs_learning.py --paired DIR --learned HYBRID_DIR
    python benchmarks/planning_vs_learning.py --scenario grid6 --fleets 3 6 --out DIR
    python benchmarks/planning_vs_learning.py --scenario city --fleets 25 --horizons 1 5
    python benchmarks/planning_vs_learning.py --horizons 5 --beams 16 8 4 --ceiling 5
    python benchmarks/planning_vs_learning.py --horizons 5 --beams 16 4 --rounds 2 1
    python benchmarks/planning_vs_learning.py --split eval --horizons 5 10 --beams 16 4 \
        --rounds 2 1 3 --predictors cv learned --out VAL_DIR     # and --split test: TEST_DIR
    python benchmarks/planning_vs_learning.py --paired TEST_DIR --chosen-on VAL_DIR
    python benchmarks/planning_vs_learning.py traces.eval.n_sims=8 --split eval ...  # 56 windows

``--scenario NAME`` flies a preset of ``conf/scenario`` (a held-out grid, the city)
instead of the default grid: its test traces, its network for ``--predictors road``.

Writes ``table.csv`` (per policy and setting: served fraction and P_g(N̂_s) with their
intervals over windows, paired differences against greedy, ms per decision for the
whole fleet, amortised over the windows run side by side; a search's beam and passes,
blank for greedy and the oracle), ``per_window.json`` (each policy's per-window values
with its scenario, masks, fleet, label, horizon, beam, passes, predictor and
visibility) and
``prediction_error.csv`` (each predictor's error k steps ahead on the same windows;
``--predictors``: constant velocity, ``road`` along the SUMO network's lanes, ``learned``
a network fit on the scenario's training traces, :mod:`uabs_rl.evaluation.motion`). One
process, one torch thread. No trained checkpoint is read.

At the end (or alone, ``--paired DIR`` on a folder it wrote) it prints the paired
differences over the same windows that say what prediction costs and what the road
network adds: each mpc against the clairvoyant planner at the same horizon, the road
and learned predictors against constant velocity at the same horizon, beam, passes and
visibility, the learned predictor's also against the plain constant-velocity mpc (every
vehicle seen, default beam and passes) at every other horizon, and each horizon against
the shorter ones (above 1) of the same policy.

``--uncoordinated`` adds each mpc (constant velocity, seeing every vehicle) and each
clairvoyant planner of horizon above 1 with its UABS planning alone
(``PlannerScore(coordinated=False)``: no other plan takes vehicles out of a path's
gains), paired with the coordinated one (run too if ``--predictors`` or ``--sees`` left
it out): what coordinating the fleet's plans is worth.

``--beams 16 8 4`` flies each mpc with each beam width (the paths its search keeps per
first move; ``PlannerScore.beam``, ``uabs-eval --mpc-beam``), each narrower one paired
with the same mpc at the default width (16, flown too if not asked for). ``--rounds 2 1``
likewise flies each with each number of passes over the fleet (``PlannerScore.rounds``,
``uabs-eval --mpc-rounds``), each other one paired with the same mpc at the default 2,
and an mpc off the default in both with the default mpc too.

``--split eval`` flies every window of the validation traces instead of the test
traces (14 on a grid), so that a setting can be chosen where no reported figure comes
from. ``--paired TEST_DIR --chosen-on VAL_DIR`` then chooses, per (city, masks, M) and
predictor, the mpc setting that served most on validation among those seeing every
vehicle, planning the fleet together and costing no more ms per decision than the
default mpc (H = 5, cv, default beam and passes) in the validation run, and pairs that
setting with the default mpc on the test windows (and each predictor's choice with
constant velocity's). ``KEY=VALUE`` overrides (before the options) change the world
flown, e.g. ``traces.eval.n_sims=8``: 56 validation windows instead of 14.

``--paired DIR --learned HYBRID_DIR`` pairs a population's learned policy, and the
hybrid or leaf at its λ*, as ``benchmarks/hybrid.py`` flew them on the test windows into
``HYBRID_DIR``, with every policy of ``DIR`` flown on the same windows under the same
masks and fleet (found by the mpc's per-window values, which must be equal in both):
learned − policy and hybrid − policy, each member's mean paired difference over the
windows, Student-t over the members; then the members' mean per window paired with the
policy's, Student-t over the windows (which also counts the windows' sampling), and in
how many windows it served more.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import sys
import time
from pathlib import Path

import torch

from uabs_rl.cli import one_line_errors
from uabs_rl.config import compose
from uabs_rl.env.uabs_env import window_count
from uabs_rl.evaluation.baselines import (
    MPC,
    PLANNER,
    baseline_policy,
    passes_text,
    policy_label,
)
from uabs_rl.evaluation.evaluator import Evaluator, make_eval_env
from uabs_rl.evaluation.planner import BEAM, ROUNDS
from uabs_rl.evaluation.predict import Within, make_predictor, prediction_error
from uabs_rl.evaluation.stats import paired_difference, paired_over_seeds, t_interval
from uabs_rl.safety.make import make_selector
from uabs_rl.traces import get_traces


def evaluate(mode: str, m: int, horizons: list[int], ceiling: list[int], sees: list[str],
             log, predictors: tuple[str, ...] = ("cv",), uncoordinated: bool = False,
             scenario: str | None = None,
             beams: tuple[int, ...] = (BEAM,),
             rounds: tuple[int, ...] = (ROUNDS,),
             split: str = "test",
             overrides: tuple[str, ...] = ()) -> tuple[list[dict], list[dict]]:
    over = [] if scenario is None else [f"scenario={scenario}"]
    cfg = compose("config", over + [f"masking={mode}", f"scenario.n_uabs={m}", *overrides])
    # every window of the split: on "eval" too (not train.eval_windows)
    traces = get_traces(cfg.scenario, cfg.traces, split)
    env = make_eval_env(cfg, traces, split=split, windows=window_count(
        traces.n_sims, traces.steps, cfg.scenario.episode_steps))
    ev = Evaluator(env, cfg.train.eval_seed)
    if scenario is not None or split != "test" or overrides:
        log(f"scenario={cfg.scenario.name}, {mode} masks, M={m}: its "
            f"{'test' if split == 'test' else 'validation'} traces"
            + (f" ({' '.join(overrides)})" if overrides else ""))
    made = {pred: make_predictor(pred, "all", cfg.scenario, traces=cfg.traces)
            for pred in predictors}
    default = (BEAM, ROUNDS)
    runs = [("greedy", 1, None, "all", True, *default),
            ("oracle", 1, None, "all", True, *default)]
    runs += [("mpc", h, pred, s, True, b, r) for pred in predictors for s in sees
             for h in horizons for b in beams for r in rounds]
    runs += [("planner", h, "true", "all", True, *default) for h in ceiling]
    if uncoordinated:  # each beside its coordinated self (added if not asked for)
        for name, pred, hs in (("mpc", "cv", horizons), ("planner", "true", ceiling)):
            together = [(name, h, pred, "all", True, *default) for h in hs if h > 1]
            runs += [r for r in together if r not in runs]
            runs += [(name, h, pred, "all", False, *default) for h in hs if h > 1]
    # one untimed rollout first: the first one of a process pays its one-off costs
    # (allocations, lazy imports), which would have gone into the first row's ms
    ev.evaluate(baseline_policy("greedy", env, make_selector(env), 0))
    rows, greedy = [], None
    for name, h, pred, s, coordinated, beam, passes in runs:
        predictor = ((made.get(pred) or make_predictor(pred, "all", cfg.scenario,
                                                       traces=cfg.traces)
                      if s == "all" else Within(made[pred], float(s)))
                     if name == "mpc" else None)
        policy = baseline_policy(name, env, make_selector(env), 0, horizon=h,
                                 predictor=predictor, coordinated=coordinated, beam=beam,
                                 rounds=passes)
        t0 = time.perf_counter()
        rec, _ = ev.evaluate(policy)
        sec = time.perf_counter() - t0
        label = policy_label(name, h, pred, s, coordinated, beam, passes)
        search = name in (MPC, PLANNER)  # the beam and passes of a search; none else
        row = {"scenario": cfg.scenario.name, "mode": mode, "n_uabs": m, "policy": label,
               "horizon": h,
               "beam": beam if search else None,
               "rounds": (passes if coordinated else 1) if search else None,
               "predictor": pred or "", "sees": s, "split": split, "windows": rec["windows"],
               "ms_per_decision": 1000 * sec / (rec["windows"] * cfg.scenario.episode_steps),
               "collisions": rec["collisions"], "proximity": rec["proximity"],
               "fallbacks": rec["fallbacks"],
               "served_fractions": rec["served_fractions"], "pgs": rec["pgs"]}
        for metric, key in (("served", "served_fractions"), ("pg", "pgs")):
            mean, lo, hi = t_interval([x for x in rec[key] if x == x])
            row.update({metric: mean, f"{metric}_ci_low": lo, f"{metric}_ci_high": hi})
            if greedy is not None:
                d = paired_difference(rec[key], greedy[key])
                row.update({f"{metric}_minus_greedy": d["diff"],
                            f"{metric}_minus_greedy_ci_low": d["ci_low"],
                            f"{metric}_minus_greedy_ci_high": d["ci_high"]})
        if name == "greedy":
            greedy = row
        rows.append(row)
        log(f"{mode} M={m} {label:>28}: served {100 * row['served']:.2f} % "
            f"[{100 * row['served_ci_low']:.2f}, {100 * row['served_ci_high']:.2f}], "
            f"P_g {100 * row['pg']:.2f} % [{100 * row['pg_ci_low']:.2f}, "
            f"{100 * row['pg_ci_high']:.2f}], collisions {row['collisions']:.0f}, "
            f"proximity {row['proximity']:.0f}, {row['ms_per_decision']:.2f} ms/decision")
    env.set_seed(cfg.train.eval_seed)
    env.reset()
    errs = [{"mode": mode, "n_uabs": m, "predictor": pred, "k": k, **e}
            for pred, predictor in made.items()
            for k, e in prediction_error(env.base_env, predictor, (1, 2, 5, 10)).items()]
    for e in errs:
        log(f"{mode} M={m} predictor {e['predictor']}, {e['k']} steps ahead: mean error "
            f"{e['mean_m']:.2f} m, rmse {e['rmse_m']:.2f} m over {e['n']} vehicle-steps")
    return rows, errs


METRICS = (("served", "served_fractions"), ("P_g", "pgs"))  # name, per-window key


def differences(a: dict, b: dict, metrics=METRICS) -> str:
    """Row ``a`` − row ``b``, paired over their windows, in points with the Student-t
    95 % CI: ``served +0.43 [+0.03, +0.84], P_g ... points``."""
    parts = []
    for metric, key in metrics:
        d = paired_difference(a[key], b[key])
        parts.append(f"{metric} {100 * d['diff']:+.2f} [{100 * d['ci_low']:+.2f}, "
                     f"{100 * d['ci_high']:+.2f}]")
    return f"{', '.join(parts)} points"


def paired(rows: list[dict], log) -> None:
    """mpc − planner and mpc (road or learned) − mpc (cv), paired over windows (module
    docstring)."""
    by = {(r["mode"], r["n_uabs"], r["policy"]): r for r in rows}

    def line(a: dict, b: dict, what: str) -> None:
        log(f"{a['mode']} M={a['n_uabs']} {what}: {differences(a, b)}")

    for (mode, m, label), r in by.items():
        name, h = (label.split()[0], label.split()[1][2:]) if " H=" in label else (label, "")
        if name in ("mpc", "planner"):  # a longer horizon against each shorter one > 1
            for (mode2, m2, label2), shorter in by.items():
                h2 = label2.split()[1][2:] if label2.startswith(name + " H=") else ""
                if ((mode2, m2) == (mode, m) and h2 and 1 < int(h2) < int(h)
                        and label2 == label.replace(f"H={h} ", f"H={h2} ")):
                    line(r, shorter, f"{label} - {label2}")
        if ", uncoordinated)" in label:
            together = by.get((mode, m, label.replace(", uncoordinated)", ")")))
            if together is not None:
                line(r, together, f"{label} - {together['policy']}")
            continue
        if name != "mpc":
            continue
        ceiling = by.get((mode, m, policy_label(PLANNER, h)))
        if ceiling is not None:
            line(r, ceiling, f"{label} - planner H={h}")
        for other in ("(road", "(learned"):  # another predictor against cv
            if other not in label:
                continue
            cv = by.get((mode, m, label.replace(other, "(cv")))
            if cv is not None:
                line(r, cv, f"{label} - {cv['policy']}")
        if "(learned" in label:  # and against the plain cv mpc at every other horizon
            same_h = label.replace("(learned", "(cv")
            for (mode2, m2, label2), cv in by.items():
                if ((mode2, m2) == (mode, m) and label2.startswith("mpc H=")
                        and label2.endswith(" (cv)") and label2 != same_h):
                    line(r, cv, f"{label} - {label2}")
        if ", beam " in label:  # against the same mpc at the default beam
            wide = by.get((mode, m, re.sub(r", beam \d+", "", label)))
            if wide is not None:
                line(r, wide, f"{label} - {wide['policy']}")
        if " round" in label:  # against the same mpc in the default passes
            twice = by.get((mode, m, re.sub(r", \d+ rounds?", "", label)))
            if twice is not None:
                line(r, twice, f"{label} - {twice['policy']}")
            if ", beam " in label:  # and the default mpc
                plain = by.get((mode, m, re.sub(r", beam \d+|, \d+ rounds?", "", label)))
                if plain is not None:
                    line(r, plain, f"{label} - {plain['policy']}")


def chosen(val_rows: list[dict], test_rows: list[dict], log) -> None:
    """Per (scenario, masks, M) and predictor: among the mpc settings of ``val_rows`` (a
    ``--split eval`` folder) that see every vehicle, plan the fleet together and cost
    no more ms per decision than the default mpc (H = 5, cv, default beam and passes)
    in the same run, the one that served most on validation (the cheaper of equals);
    then that setting on the test windows of ``test_rows``, paired with the default mpc
    there, and each predictor's choice paired with constant velocity's. A choice made on
    validation, reported on test. For scale, the same choice made on the test windows
    themselves is printed after it ("best on test"): a choice on the data it is then
    reported on, which favours the settings it picks.
    The ms are each run's own, one figure per setting: a setting near the mpc's cost
    may fall either side of it in another run (the test run's ratio is printed too)."""
    ref = policy_label(MPC, 5, "cv")

    def mean(r: dict) -> float:  # windows without a vehicle have no served fraction
        return t_interval([x for x in r["served_fractions"] if x == x])[0]

    def rows_of(rows):
        out = {}
        for r in rows:
            key = (r["scenario"], r["mode"], r["n_uabs"])
            out.setdefault(key, {})[r["policy"]] = r
        return out

    def searches(by: dict) -> list[dict]:  # the mpc settings that can be chosen
        return [r for r in by.values() if r["policy"].startswith("mpc H=")
                and r["sees"] == "all" and "uncoordinated" not in r["policy"]]

    def pick(by: dict, pred: str) -> dict | None:
        cap = by[ref]["ms_per_decision"]
        ok = [r for r in searches(by) if r["predictor"] == pred and r["ms_per_decision"] <= cap]
        return max(ok, key=lambda r: (mean(r), -r["ms_per_decision"]), default=None)

    val, test = rows_of(val_rows), rows_of(test_rows)
    for key, by in val.items():
        scen, mode, m = key
        where = f"{scen} {mode} M={m}"
        if ref not in by or key not in test or ref not in test[key]:
            log(f"{where}: no default mpc ({ref}) on both splits; nothing chosen")
            continue
        base, tbase = by[ref], test[key][ref]
        picks = {}
        for pred in dict.fromkeys(r["predictor"] for r in searches(by)):
            r = pick(by, pred)
            if r is None:
                log(f"{where} {pred}: no setting costs at most the mpc's "
                    f"{base['ms_per_decision']:.2f} ms per decision on validation")
                continue
            picks[pred] = r
            t = test[key].get(r["policy"])
            if t is None:
                log(f"{where} {pred}: {r['policy']} not flown on test")
                continue
            log(f"{where} {pred}: chosen {r['policy']} (validation {100 * mean(r):.2f} % "
                f"against {100 * mean(base):.2f} %, "
                f"{r['ms_per_decision'] / base['ms_per_decision']:.2f}x its ms); test − {ref}: "
                f"{differences(t, tbase)} "
                f"({t['ms_per_decision'] / tbase['ms_per_decision']:.2f}x its ms)")
            own = pick(test[key], pred)
            if own is not None:
                log(f"{where} {pred}: best on test {own['policy']}: − {ref}: "
                    f"{differences(own, tbase)} "
                    f"({own['ms_per_decision'] / tbase['ms_per_decision']:.2f}x its ms)")
        if "cv" not in picks:
            continue
        for pred, r in picks.items():
            a, b = test[key].get(r["policy"]), test[key].get(picks["cv"]["policy"])
            if pred == "cv" or a is None or b is None:
                continue
            log(f"{where} {pred}'s choice − cv's choice on test: "
                f"{differences(a, b, METRICS[:1])}")


def paired_learned(rows: list[dict], hybrid_dir: Path, log) -> None:
    """learned − every policy of ``rows`` on the same windows (module docstring)."""
    record = json.loads((hybrid_dir / "hybrid.json").read_text())
    flown = record["policies"]
    label = policy_label(MPC, record["mpc_horizon"], record["predictor"], record["sees"],
                         beam=record.get("mpc_beam"), rounds=record.get("mpc_rounds"))
    mpc = [r for r in rows if r["policy"] == label
           and r["served_fractions"] == flown["mpc"]["served"]
           and r["pgs"] == flown["mpc"]["pg"]]
    if not mpc:
        sys.exit(f"{hybrid_dir}'s mpc is none of this folder's {label} rows: other "
                 f"windows, masks or fleet; nothing to pair")
    mode, m = mpc[0]["mode"], mpc[0]["n_uabs"]
    # the learned policy, then the hybrid (Q at the first move) or leaf it flew at λ*
    width, passes = record.get("hybrid_beam", BEAM), record.get("hybrid_rounds", ROUNDS)
    hyb = (f"{record.get('hybrid', 'hybrid')} "  # files before --leaf have no such key
           f"H={record.get('hybrid_horizon', record['mpc_horizon'])} "
           f"λ={record['best_weight']:g}" + (f" beam {width}" if width != BEAM else "")
           + (f" {passes_text(passes)}" if passes != ROUNDS else ""))
    for what, mine in (("learned", flown["learned"]), (hyb, flown.get("hybrid"))):
        if mine is None:
            continue
        for r in rows:
            if (r["mode"], r["n_uabs"]) != (mode, m):
                continue
            parts = []
            for metric, key, col in (("served", "served_fractions", "served"),
                                     ("P_g", "pgs", "pg")):
                d = paired_over_seeds(mine[col], [r[key]] * len(mine[col]))
                parts.append(f"{metric} {100 * d['diff']:+.2f} [{100 * d['ci_low']:+.2f}, "
                             f"{100 * d['ci_high']:+.2f}]")
            # the members' mean per window against the policy's, over the windows: the
            # interval that also counts the windows' sampling
            per_window = [sum(w) / len(w) for w in zip(*mine["served"], strict=True)]
            d = paired_difference(per_window, r["served_fractions"])
            above = sum(a > b for a, b in zip(per_window, r["served_fractions"], strict=True))
            log(f"{mode} M={m} {what} ({len(mine['served'])} members) - {r['policy']}: "
                f"{', '.join(parts)} points; over the windows: served "
                f"{100 * d['diff']:+.2f} [{100 * d['ci_low']:+.2f}, {100 * d['ci_high']:+.2f}],"
                f" above it in {above} of {len(per_window)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                    help="config overrides of the world flown (traces.eval.n_sims=8: more "
                         "validation traces)")
    ap.add_argument("--modes", nargs="+", default=["rank"])
    ap.add_argument("--fleets", type=int, nargs="+", default=[3])
    ap.add_argument("--horizons", type=int, nargs="+", default=[1, 5], help="the mpc's")
    ap.add_argument("--ceiling", type=int, nargs="+", default=[5],
                    help="the clairvoyant planner's horizons")
    ap.add_argument("--sees", nargs="+", default=["all"], help="all or radii in metres")
    ap.add_argument("--predictors", nargs="+", default=["cv"], choices=("cv", "road", "learned"),
                    help="the mpc's predictors (default cv)")
    ap.add_argument("--beams", type=int, nargs="+", default=[BEAM],
                    help=f"the mpc's beam widths, paths kept per first move (default {BEAM})")
    ap.add_argument("--rounds", type=int, nargs="+", default=[ROUNDS],
                    help=f"the mpc's passes over the fleet (default {ROUNDS})")
    ap.add_argument("--uncoordinated", action="store_true",
                    help="also each mpc (cv) and planner with its UABS planning alone")
    ap.add_argument("--scenario", metavar="NAME",
                    help="a preset of conf/scenario instead of the default grid")
    ap.add_argument("--split", choices=("test", "eval"), default="test",
                    help="the traces flown: test (default) or eval, the validation traces "
                         "(every window of either)")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--paired", type=Path, metavar="DIR",
                    help="only print the paired differences of a folder this script wrote")
    ap.add_argument("--learned", type=Path, metavar="HYBRID_DIR",
                    help="with --paired: also learned − each policy, from a folder "
                         "benchmarks/hybrid.py wrote")
    ap.add_argument("--chosen-on", type=Path, metavar="VAL_DIR",
                    help="with --paired TEST_DIR: per predictor, the mpc setting chosen on "
                         "the validation folder VAL_DIR (--split eval) among those no "
                         "costlier than the default mpc, paired with it on TEST_DIR")
    args = ap.parse_args()
    if args.learned is not None and args.paired is None:
        ap.error("--learned goes with --paired DIR")
    if args.chosen_on is not None and args.paired is None:
        ap.error("--chosen-on goes with --paired TEST_DIR")
    if args.chosen_on is not None and args.learned is not None:
        ap.error("--chosen-on and --learned are two readings of --paired: one at a time")
    # each width and number of passes once, the default among them: the others are
    # paired with it
    for flag in ("horizons", "ceiling"):
        if min(getattr(args, flag)) < 1:
            ap.error(f"--{flag} must be >= 1, got {min(getattr(args, flag))}")
    for flag, default in (("beams", BEAM), ("rounds", ROUNDS)):
        values = getattr(args, flag)
        if min(values) < 1:
            ap.error(f"--{flag} must be >= 1, got {min(values)}")
        setattr(args, flag, list(dict.fromkeys(values if default in values
                                               else [default, *values])))
    if args.paired is not None:
        for d in (args.paired, args.chosen_on):
            if d is not None and not (d / "per_window.json").is_file():
                ap.error(f"{d} holds no per_window.json: give a folder this script wrote "
                         f"(--out)")
        rows = json.loads((args.paired / "per_window.json").read_text())
        if args.chosen_on is not None:
            val = json.loads((args.chosen_on / "per_window.json").read_text())
            for d, split, rs in ((args.chosen_on, "eval", val), (args.paired, "test", rows)):
                if not rs or any(r.get("split") != split or "ms_per_decision" not in r
                                 for r in rs):
                    ap.error(f"{d} was not written by --split {split} of this version of "
                             f"the script (each row's split and ms per decision); run it "
                             f"again with --split {split}")
            chosen(val, rows, print)
            return
        paired(rows, print)
        if args.learned is not None:
            paired_learned(rows, args.learned, print)
        return
    torch.set_num_threads(1)
    lines: list[str] = []

    def log(line: str) -> None:
        print(line, flush=True)
        lines.append(line)

    t0 = time.perf_counter()
    rows, errs = [], []
    for mode in args.modes:
        for m in args.fleets:
            r, e = evaluate(mode, m, args.horizons, args.ceiling, args.sees, log,
                            tuple(args.predictors), args.uncoordinated, args.scenario,
                            tuple(args.beams), tuple(args.rounds), args.split,
                            tuple(args.overrides))
            rows += r
            errs += e
    paired(rows, log)
    log(f"total {time.perf_counter() - t0:.0f} s (1 torch thread)")
    if args.out is None:
        return
    args.out.mkdir(parents=True, exist_ok=True)
    scalar = [k for k in rows[-1] if k not in ("served_fractions", "pgs")]
    with open(args.out / "table.csv", "w", newline="") as f:
        w = csv.DictWriter(f, scalar, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    with open(args.out / "prediction_error.csv", "w", newline="") as f:
        w = csv.DictWriter(f, list(errs[0]))
        w.writeheader()
        w.writerows(errs)
    (args.out / "per_window.json").write_text(json.dumps(
        [{k: r[k] for k in ("scenario", "split", "mode", "n_uabs", "policy", "horizon", "beam",
                            "rounds", "predictor", "sees", "ms_per_decision",
                            "served_fractions", "pgs")}
         for r in rows]))
    (args.out / "log.txt").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    one_line_errors(main)
