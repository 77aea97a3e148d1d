"""How much room is left above the baselines: the receding-horizon planner (it knows the
vehicles' future positions), the k-means and junction heuristics, greedy and the oracle
on every window of the test traces of the default grid, per masking mode and fleet size,
and the learned runs of docs/results/ placed on that scale.

    python benchmarks/headroom.py --out docs/results/headroom            # the whole table
    python benchmarks/headroom.py --modes flat --fleets 3 --horizons 10 --beam 32 --rounds 3

Writes ``headroom.csv`` (one row per policy and setting: served fraction, P_g(N̂_s),
return, seconds per window), ``per_window.json`` (each policy's per-window values) and
``learned_gap.csv`` (each learned configuration of ``docs/results/learned_vs_baselines.csv``:
its share of the greedy-to-planner gap, (learned − greedy) / (planner − greedy), with the
CI of learned − greedy over seeds divided by the planner's gap on the same windows).
Before that it checks that greedy and the oracle here equal those the learned runs were
compared with (``docs/results/*/baselines.csv``). One process, one torch thread.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import torch
from tensordict.nn import TensorDictSequential

from uabs_rl.cli import one_line_errors
from uabs_rl.config import compose
from uabs_rl.evaluation.baselines import baseline_policy
from uabs_rl.evaluation.evaluator import Evaluator, make_eval_env
from uabs_rl.evaluation.planner import PlannerScore, junction_sites, scale_to_gap
from uabs_rl.safety.make import make_selector

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"
# where the learned runs' baselines of each fleet size were written
BASELINE_FILES = {3: RESULTS / "paper" / "baselines.csv",
                  6: RESULTS / "lookahead_m6" / "baselines.csv"}
METRICS = (("served_fraction", "served_fractions"), ("pg", "pgs"))


def evaluate(mode: str, m: int, horizons: list[int], beam: int, rounds: int,
             log) -> list[dict]:
    """Every policy's record on the test windows of (mode, M)."""
    cfg = compose("config", [f"masking={mode}", f"scenario.n_uabs={m}"])
    env = make_eval_env(cfg, split="test")
    ev = Evaluator(env, cfg.train.eval_seed)
    sites = junction_sites(cfg, env.base_env)
    runs = [("greedy", 1), ("oracle", 1), ("kmeans", 1), ("junctions", 1)]
    runs += [("planner", h) for h in horizons]
    rows = []
    for name, h in runs:
        selector = make_selector(env)
        if name == "planner":  # as baseline_policy builds it, with this beam and rounds
            gen = torch.Generator().manual_seed(0)
            policy = TensorDictSequential(PlannerScore(env.base_env, h, gen, beam, rounds),
                                          selector)
        else:
            policy = baseline_policy(name, env, selector, 0, sites=sites)
        t0 = time.perf_counter()
        rec, _ = ev.evaluate(policy)
        sec = time.perf_counter() - t0
        label = f"planner H={h}" if name == "planner" else name
        row = {"mode": mode, "n_uabs": m, "policy": label, "horizon": h if name == "planner"
               else "", "served_fraction": rec["served_fraction"], "pg": rec["pg"],
               "return": rec["return"], "collisions": rec["collisions"],
               "proximity": rec["proximity"], "fallbacks": rec["fallbacks"],
               "seconds_per_window": sec / rec["windows"], "windows": rec["windows"],
               "served_fractions": rec["served_fractions"], "pgs": rec["pgs"]}
        rows.append(row)
        log(f"{mode} M={m} {label:>12}: served {100 * row['served_fraction']:.2f} %, "
            f"P_g {100 * row['pg']:.2f} %, R {row['return']:.0f}, "
            f"{row['seconds_per_window']:.3f} s/window")
    return rows


def check_baselines(rows: list[dict], log) -> list[str]:
    """Greedy and the oracle here against the baselines.csv the learned runs were compared
    with: a line per pair, "equal" or what differs."""
    out = []
    for r in rows:
        if r["policy"] not in ("greedy", "oracle") or r["n_uabs"] not in BASELINE_FILES:
            continue
        with open(BASELINE_FILES[r["n_uabs"]]) as f:
            ref = {b["policy"]: b for b in csv.DictReader(f)}
        b = ref.get(f"{r['policy']} ({r['mode']} masks)")
        if b is None:
            continue
        same = all(abs(float(b[k]) - r[k]) < 1e-6 for k in ("served_fraction", "pg"))
        line = (f"{r['policy']} {r['mode']} M={r['n_uabs']} vs "
                f"{BASELINE_FILES[r['n_uabs']].relative_to(RESULTS.parent.parent)}: "
                + ("equal" if same else f"DIFFERENT ({b['served_fraction']}, {b['pg']})"))
        out.append(line)
        log(line)
    return out


def learned_gap(rows: list[dict]) -> list[dict]:
    """Each learned configuration's share of the greedy-to-planner gap per metric, with the
    planner at its best horizon for that (mode, M)."""
    by = {(r["mode"], r["n_uabs"], r["policy"]): r for r in rows}
    out = []
    with open(RESULTS / "learned_vs_baselines.csv") as f:
        lvb = [r for r in csv.DictReader(f) if r["baseline"] == "greedy"]
    for r in lvb:
        mode, m, metric = r["mode"], int(r["n_uabs"]), r["metric"]
        greedy = by.get((mode, m, "greedy"))
        plans = [x for x in rows if x["mode"] == mode and x["n_uabs"] == m
                 and x["horizon"] != ""]
        if metric not in ("served_fraction", "pg") or greedy is None or not plans:
            continue
        best = max(plans, key=lambda x: x[metric])
        gap = best[metric] - greedy[metric]
        learned = float(r["learned"])
        csv_greedy = learned - float(r["diff"])
        out.append({"mode": mode, "n_uabs": m, "config": r["config"], "metric": metric,
                    "n_seeds": r["n_seeds"], "learned": learned, "greedy": greedy[metric],
                    "greedy_in_csv_matches": abs(csv_greedy - greedy[metric]) < 1e-6,
                    "planner": best[metric], "planner_horizon": best["horizon"],
                    **scale_to_gap(float(r["diff"]), float(r["ci_low"]), float(r["ci_high"]),
                                   gap)})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--modes", nargs="+", default=["flat", "rank"])
    ap.add_argument("--fleets", type=int, nargs="+", default=[3, 6])
    ap.add_argument("--horizons", type=int, nargs="+", default=[5, 10, 20])
    ap.add_argument("--beam", type=int, default=16, help="paths kept per first move")
    ap.add_argument("--rounds", type=int, default=2, help="planning passes over the fleet")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(1)
    lines: list[str] = []

    def log(line: str) -> None:
        print(line, flush=True)
        lines.append(line)

    log(f"beam {args.beam}, rounds {args.rounds}, 1 torch thread, test traces")
    t0 = time.perf_counter()
    rows = [r for mode in args.modes for m in args.fleets
            for r in evaluate(mode, m, args.horizons, args.beam, args.rounds, log)]
    check_baselines(rows, log)
    log(f"total {time.perf_counter() - t0:.0f} s")
    if args.out is None:
        return
    args.out.mkdir(parents=True, exist_ok=True)
    scalar = [k for k in rows[0] if k not in ("served_fractions", "pgs")]
    with open(args.out / "headroom.csv", "w", newline="") as f:
        w = csv.DictWriter(f, scalar, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    (args.out / "per_window.json").write_text(json.dumps(
        [{k: r[k] for k in ("mode", "n_uabs", "policy", "served_fractions", "pgs")}
         for r in rows]))
    gap = learned_gap(rows)
    if gap:
        with open(args.out / "learned_gap.csv", "w", newline="") as f:
            w = csv.DictWriter(f, list(gap[0]))
            w.writeheader()
            w.writerows(gap)
    (args.out / "log.txt").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    one_line_errors(main)
