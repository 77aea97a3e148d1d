"""Zero-shot evaluation over cities and fleet sizes: each run's best.pt (chosen on its
own validation traces) on the test traces of every (city, M) given, beside the greedy
and oracle baselines under the same masks and windows. Prints a markdown table (rows:
city x M; learned, greedy and oracle served fraction, learned − greedy with a
Student-t 95 % CI over seeds: each seed's mean over windows of the paired differences)
and writes every number to a csv (with each pair's collisions, proximity events and mask
fallbacks summed over every rollout flown, also printed per pair). Over the held-out
pairs it adds rliable's aggregates of the greedy-to-oracle normalised score, (learned −
greedy) / (oracle − greedy) per seed and pair: its IQM with a stratified bootstrap CI.

    python benchmarks/generalization.py outputs/runs/<generalist population> \
        --at grid6:3 grid6:6 lights60:3 city:25 --csv docs/results/generalization/table.csv

``--at CITY:M`` names a scenario option (conf/scenario or --config-dir) and a fleet
size; ``home:M`` is the run's own scenario. ``--beside RUNS`` evaluates a second
population (for example a single-city policy of the paper's observation size) on the
pairs where its network fits, in the columns ``other − greedy``, and the two-group
difference learned − other with Welch's 95 % CI (``learned_minus_other``). ``--mpc H``
adds the deployable receding-horizon planner of horizon H (constant-velocity prediction,
``uabs-eval --policy mpc``) beside greedy and the oracle: its served fraction and
learned − mpc (columns ``mpc``, ``learned_minus_mpc``; with ``--beside``, also
``other_minus_mpc``), and for every policy P_g at N̂_s = 5 (``pg_*``, learned − mpc in
``pg_learned_minus_mpc``) and the ms per fleet decision of its rollout (``ms_*``: all the
windows flown side by side, the time per step of one window; the learned policy's the
mean over its seeds). The mpc costs far more than the learned policies (about a second
per fleet decision at M = 25 over a district): ``--mpc-from CITY:M=EVAL_JSON`` takes a
pair's mpc from a ``uabs-eval RUN <the pair's overrides> --policy mpc --mpc-horizon H``
of a run with the same masking and channel (its ``eval.json``: per window, the same
windows) instead of flying it again. ``--mpc-beam B`` and ``--mpc-rounds R`` set its
search as ``uabs-eval``'s do (paths per first move, passes over the fleet; columns
``mpc_beam``, ``mpc_rounds``); a record of ``--mpc-from`` must have the same.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np

from uabs_rl.cli import one_line_errors
from uabs_rl.config import ConfigError
from uabs_rl.evaluation.baselines import passes_text
from uabs_rl.evaluation.load import evaluate_policies, load_evaluation
from uabs_rl.evaluation.planner import BEAM, ROUNDS
from uabs_rl.evaluation.stats import (
    AGGREGATE_METHOD,
    iqm_runs,
    paired_over_seeds,
    stratified_bootstrap,
    welch_difference,
)
from uabs_rl.runs.layout import RunFolder

METRIC = "served_fractions"  # per window
# the table's two metrics, per window: the served fraction and P_g at N̂_s = 5
METRICS = {"served": METRIC, "pg": "pgs"}


def overrides(at: str) -> list[str]:
    city, m = at.split(":")
    return ([] if city == "home" else [f"scenario={city}"]) + [f"scenario.n_uabs={m}"]


def mpc_from(path: Path, at: str, horizon: int, beam: int = BEAM,
             rounds: int = ROUNDS) -> dict:
    """The mpc's record (:func:`record`) from a ``uabs-eval --policy mpc`` record
    (``eval.json``) of the pair ``at``: the test split, the pair's overrides, horizon H,
    the constant-velocity predictor, every vehicle seen, ``beam`` paths per first move
    and ``rounds`` passes (the defaults where a record predates them); refused
    otherwise."""
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise SystemExit(f"--mpc-from {at}={path}: cannot read it ({e})") from None
    d = d if isinstance(d, dict) else {}
    rec = (d.get("policies") or {}).get("mpc") or {}
    if ((d.get("split"), sorted(d.get("overrides") or [])) != ("test", sorted(overrides(at)))
            or (rec.get("horizon"), rec.get("predictor"), rec.get("sees")) != (horizon, "cv", "all")
            or (rec.get("beam", BEAM), rec.get("rounds", ROUNDS)) != (beam, rounds)
            or any(key not in rec for key in METRICS.values())):
        search = "".join(f" --mpc-{k} {v}" for k, v, default in (("beam", beam, BEAM),
                                                                  ("rounds", rounds, ROUNDS))
                         if v != default)
        raise SystemExit(
            f"--mpc-from {at}={path}: not the mpc of {at} on the test split at horizon "
            f"{horizon} (constant velocity, every vehicle seen, beam {beam}, "
            f"{passes_text(rounds)}); write it with uabs-eval RUN "
            f"{' '.join(overrides(at))} --policy mpc --mpc-horizon {horizon}{search}")
    return record({"ms_per_decision": float("nan"), **rec})


def evaluate(runs: list[Path], over: list[str], dirs: list[Path],
             baselines: tuple[str, ...] = (), mpc_horizon: int = 5,
             beam: int = BEAM, rounds: int = ROUNDS
             ) -> tuple[list[dict], dict[str, dict]] | None:
    """Per seed, the learned policy's record (its served fraction and P_g per window,
    :data:`METRICS`, and its ms per decision), and the records of the ``baselines`` (on
    the first seed's env: they do not depend on the run's seed; the mpc's search
    ``mpc_horizon`` steps, ``beam`` paths, ``rounds`` passes); None where the network
    does not fit (the paper's observation at another M)."""
    out, base = [], {}
    for i, run in enumerate(runs):
        try:
            ev = load_evaluation(run, "best", split="test", overrides=over, config_dirs=dirs)
        except ConfigError as e:  # check_network_fits' refusal; any other error stands
            if "observations of size" in str(e):
                return None
            raise
        res = evaluate_policies(ev, ("learned", *(baselines if i == 0 else ())),
                                mpc_horizon=mpc_horizon, beam=beam, rounds=rounds)
        values = {k: record(rec) for k, (rec, _) in res.items()}
        out.append(values.pop("learned"))
        base = base or values
    return out, base


SAFETY = ("collisions", "proximity", "fallbacks")  # each rollout's counts, summed


def record(rec: dict) -> dict:
    """A policy's per-window metrics (:data:`METRICS`), its ms per decision and its
    :data:`SAFETY` counts."""
    return {**{m: np.asarray(rec[key], dtype=float) for m, key in METRICS.items()},
            "ms": float(rec["ms_per_decision"]),
            **{k: float(rec.get(k, float("nan"))) for k in SAFETY}}


def versus(per_seed: list[dict], base: dict, metric: str = "served"
           ) -> tuple[float, float, float]:
    """learned − baseline in ``metric``: per seed the mean over windows of the paired
    differences, then their mean over seeds and its Student-t 95 % CI (over the windows
    for one seed)."""
    d = paired_over_seeds([s[metric] for s in per_seed], [base[metric]] * len(per_seed))
    return d["diff"], d["ci_low"], d["ci_high"]


def interval_words(rows: list[dict]) -> str:
    """Which interval the table's differences carry."""
    seeds = rows[0]["seeds"]
    words = (f"95 % CI, Student-t over {seeds} seeds" if seeds > 1 else
             f"95 % CI, Student-t over the {rows[0]['windows']} windows of the one seed")
    return words + ("; learned − other: 95 % CI, Welch over the two populations' seeds"
                    if any("learned_minus_other" in r for r in rows) else "")


def aggregate(rows: list[dict]) -> None:
    """rliable's IQM over the held-out pairs (every pair but ``home``) of the normalised
    score (learned − greedy) / (oracle − greedy), each seed one run, with its stratified
    bootstrap CI (runs resampled within each pair)."""
    held = [r for r in rows if r["city"] != "home" and r["oracle"] > r["greedy"]]
    if not held or len({len(r["scores"]) for r in held}) != 1:
        return
    scores = np.array([r["scores"] for r in held]).T  # [seeds, pairs]
    v, lo, hi = stratified_bootstrap([scores], iqm_runs)
    print(f"\nIQM over the {len(held)} held-out pairs of (learned − greedy) / (oracle − "
          f"greedy): {v:+.2f} [{lo:+.2f}, {hi:+.2f}] ({AGGREGATE_METHOD}; it covers 88 % "
          f"at 3 seeds, 91 % at 5, 93 % at 10: docs/evaluation.md)")


def mean_of(per_seed: list[dict], metric: str = "served") -> float:
    """The mean over seeds of each seed's mean over windows."""
    return float(np.mean([s[metric].mean() for s in per_seed]))


def pt(x: float) -> str:
    return f"{100 * x:+.2f}"


def table(rows: list[dict], other: bool, marks: dict[str, str] | None = None) -> str:
    """The markdown table of the rows (``other``: with the beside population's column;
    ``marks``: a word after each interval, by its value column)."""
    marks = marks or {}
    mpc = any("mpc" in r for r in rows)
    head = ("| city | M | windows | learned | greedy | oracle |" + (" mpc |" if mpc else "")
            + " learned − greedy [95 % CI] | learned − oracle [95 % CI] |"
            + (" learned − mpc [95 % CI] | P_g(5): learned | greedy | mpc | learned − mpc"
               " [95 % CI] | ms per decision: learned | mpc |" if mpc else "")
            + (" beside − greedy [95 % CI] |" if other else "")
            + (" beside − mpc [95 % CI] |" if other and mpc else ""))
    lines = [head, "|" + "---|" * (head.count("|") - 1)]

    def cell(r: dict, value: str, lo: str, hi: str) -> str:
        mark = f" ({r[marks[value]]})" if value in marks and r.get(marks[value]) else ""
        return f"{pt(r[value])} [{pt(r[lo])}, {pt(r[hi])}]{mark}"

    for r in rows:
        cells = [r["city"], str(r["M"]), str(r["windows"]), f"{100 * r['learned']:.2f} %",
                 f"{100 * r['greedy']:.2f} %", f"{100 * r['oracle']:.2f} %",
                 *([f"{100 * r['mpc']:.2f} %"] if mpc else []),
                 cell(r, "learned_minus_greedy", "ci_low", "ci_high"),
                 cell(r, "learned_minus_oracle", "oracle_ci_low", "oracle_ci_high"),
                 *([cell(r, "learned_minus_mpc", "mpc_ci_low", "mpc_ci_high"),
                    *(f"{100 * r[k]:.2f} %" for k in ("pg_learned", "pg_greedy", "pg_mpc")),
                    cell(r, "pg_learned_minus_mpc", "pg_mpc_ci_low", "pg_mpc_ci_high"),
                    *(f"{r[k]:.3g}" for k in ("ms_learned", "ms_mpc"))] if mpc else [])]
        if other:
            fits = r.get("other") not in (None, "")
            cells.append(cell(r, "other_minus_greedy", "other_ci_low", "other_ci_high")
                         if fits else "does not fit")
            if mpc:
                cells.append(cell(r, "other_minus_mpc", "other_mpc_ci_low",
                                  "other_mpc_ci_high") if fits else "does not fit")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", type=Path)
    ap.add_argument("--at", nargs="+", required=True, help="CITY:M pairs")
    ap.add_argument("--beside", type=Path, help="a second population, on the pairs it fits")
    ap.add_argument("--config-dir", type=Path, action="append", default=[])
    ap.add_argument("--csv", type=Path)
    ap.add_argument("--mpc", type=int, metavar="H",
                    help="also the deployable mpc of horizon H (constant velocity)")
    ap.add_argument("--mpc-from", nargs="+", default=[], metavar="CITY:M=EVAL_JSON",
                    help="a pair's mpc from a uabs-eval --policy mpc record (with --mpc)")
    ap.add_argument("--mpc-beam", type=int, metavar="B",
                    help=f"with --mpc: its paths per first move (default {BEAM})")
    ap.add_argument("--mpc-rounds", type=int, metavar="R",
                    help=f"with --mpc: its passes over the fleet (default {ROUNDS})")
    args = ap.parse_args(argv)
    if args.mpc is not None and args.mpc < 1:  # not a table without its mpc, silently
        ap.error(f"--mpc H must be >= 1, got {args.mpc}")
    if (args.mpc_beam, args.mpc_rounds) != (None, None) and not args.mpc:
        raise SystemExit("--mpc-beam and --mpc-rounds set the search of --mpc H: give "
                         "--mpc H too")
    args.mpc_beam = BEAM if args.mpc_beam is None else args.mpc_beam
    args.mpc_rounds = ROUNDS if args.mpc_rounds is None else args.mpc_rounds
    if min(args.mpc_beam, args.mpc_rounds) < 1:
        ap.error(f"--mpc-beam and --mpc-rounds must be >= 1, got {args.mpc_beam} and "
                 f"{args.mpc_rounds}")
    if any("=" not in item for item in args.mpc_from):
        raise SystemExit("--mpc-from takes CITY:M=EVAL_JSON items")
    given = dict(item.split("=", 1) for item in args.mpc_from)
    if given and not args.mpc:
        raise SystemExit("--mpc-from needs --mpc H (the horizon the records must have)")
    if set(given) - set(args.at):
        raise SystemExit(f"--mpc-from names pairs not in --at: {sorted(set(given) - set(args.at))}")
    recorded = {at: mpc_from(Path(path), at, args.mpc, args.mpc_beam, args.mpc_rounds)
                for at, path in given.items()}
    runs = RunFolder(args.runs).members()
    other = RunFolder(args.beside).members() if args.beside else []
    rows = []
    print(f"{len(runs)} seeds of {args.runs}" + (f"; beside: {len(other)} seeds of "
                                                 f"{args.beside}" if other else ""),
          file=sys.stderr)
    for at in args.at:
        t0 = time.perf_counter()
        over = overrides(at)
        fly_mpc = args.mpc and at not in given
        found = evaluate(runs, over, args.config_dir,
                         ("greedy", "oracle", *(["mpc"] if fly_mpc else [])), args.mpc or 5,
                         args.mpc_beam, args.mpc_rounds)
        if found is None:
            raise SystemExit(f"{args.runs}: its network does not fit {at}")
        mine, base = found
        if args.mpc and not fly_mpc:
            base["mpc"] = recorded[at]
            if base["mpc"]["served"].shape != base["greedy"]["served"].shape:
                raise SystemExit(f"--mpc-from {at}: {base['mpc']['served'].size} windows, "
                                 f"the test split has {base['greedy']['served'].size} here")
        theirs = evaluate(other, over, args.config_dir) if other else None
        theirs = theirs and theirs[0]
        d, lo, hi = versus(mine, base["greedy"])
        do, lo_o, hi_o = versus(mine, base["oracle"])
        row = {"city": at.split(":")[0], "M": int(at.split(":")[1]),
               "windows": int(base["greedy"]["served"].size), "seeds": len(mine),
               "learned": mean_of(mine), "greedy": float(base["greedy"]["served"].mean()),
               "oracle": float(base["oracle"]["served"].mean()),
               "learned_minus_greedy": d, "ci_low": lo, "ci_high": hi,
               "learned_minus_oracle": do, "oracle_ci_low": lo_o, "oracle_ci_high": hi_o}
        if args.mpc:  # the planning-against-learning columns: P_g and the cost too
            dm, lo_m, hi_m = versus(mine, base["mpc"])
            dp, lo_p, hi_p = versus(mine, base["mpc"], "pg")
            row.update(mpc=float(base["mpc"]["served"].mean()), mpc_horizon=args.mpc,
                       mpc_beam=args.mpc_beam, mpc_rounds=args.mpc_rounds,
                       learned_minus_mpc=dm, mpc_ci_low=lo_m, mpc_ci_high=hi_m,
                       pg_learned=mean_of(mine, "pg"),
                       **{f"pg_{k}": float(base[k]["pg"].mean()) for k in base},
                       pg_learned_minus_mpc=dp, pg_mpc_ci_low=lo_p, pg_mpc_ci_high=hi_p,
                       ms_learned=float(np.mean([s["ms"] for s in mine])),
                       **{f"ms_{k}": base[k]["ms"] for k in base})
        if theirs is not None:
            d2, lo2, hi2 = versus(theirs, base["greedy"])
            row.update(other=mean_of(theirs),
                       other_minus_greedy=d2, other_ci_low=lo2, other_ci_high=hi2)
            if args.mpc:
                d3, lo3, hi3 = versus(theirs, base["mpc"])
                row.update(other_minus_mpc=d3, other_mpc_ci_low=lo3, other_mpc_ci_high=hi3)
            if len(mine) > 1 and len(theirs) > 1:
                w = welch_difference([s["served"].mean() for s in mine],
                                     [s["served"].mean() for s in theirs])
                row.update(learned_minus_other=w["diff"], welch_ci_low=w["ci_low"],
                           welch_ci_high=w["ci_high"])
        row["scores"] = [float((s["served"].mean() - row["greedy"])
                               / (row["oracle"] - row["greedy"])) for s in mine]
        flown = [*mine, *(theirs or []), *base.values()]
        row.update({k: sum(r[k] for r in flown) for k in SAFETY})
        rows.append(row)
        print(f"{at}: {time.perf_counter() - t0:.0f} s; every rollout ({len(flown)}): "
              + ", ".join(f"{row[k]:.0f} {k}" for k in SAFETY), file=sys.stderr)
    print(table(rows, bool(other)), end="")
    print(f"\nDifferences: {interval_words(rows)}.")
    aggregate(rows)
    if args.csv:
        args.csv.parent.mkdir(parents=True, exist_ok=True)
        keys = sorted({k for r in rows for k in r} - {"scores"},
                      key=lambda k: list(rows[0]).index(k) if k in rows[0] else 99)
        with args.csv.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)


if __name__ == "__main__":
    one_line_errors(main)
