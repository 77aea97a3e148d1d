"""The hybrid policy (mpc scores + λ · learned Q-values, ``uabs-eval --policy hybrid``)
against the deployable planner (mpc) and the learned policy, with λ chosen on
validation traces and every reported figure on test traces.

    python benchmarks/hybrid.py outputs/runs/<population> --weights 0 0.25 0.5 1 2 \
        --out docs/results/planning_vs_learning/hybrid
    python benchmarks/hybrid.py outputs/runs/<egocentric population> --leaf --weights 0 0.5 1 \
        --out docs/results/planning_vs_learning/leaf

``--leaf``: the learned values at the ends of the mpc's paths (``--policy leaf``,
:mod:`uabs_rl.evaluation.leaf`) in place of Q added at the first move.

1. Validation: each member's ``best.pt`` flies the hybrid at every λ of ``--weights`` on
   the validation split (``--split eval``: the traces training selected its checkpoint
   on; ``--eval-windows`` windows, default every one); λ = 0, the mpc, which no member's
   network enters, once; λ* maximises the served fraction's mean over members and
   windows.
2. Test: on every test window, each member's learned policy and hybrid at λ*, beside
   greedy and the mpc under the same masks (greedy and the mpc are deterministic on these
   windows: flown once). Per member, the mean over windows of the paired differences
   hybrid − mpc and learned − mpc; their mean over members with a Student-t 95 % CI over
   members (:func:`uabs_rl.evaluation.stats.paired_over_seeds`).

``--compare A B`` reads two such folders (two populations flown by it) and prints
learned(A) − learned(B) with Welch's interval over their members' means.

Prints a markdown table and writes ``hybrid.json`` (every per-window value, the
validation sweep, λ*) and ``log.txt`` (what it printed) into ``--out``. ``--mpc-horizon``,
``--predictor`` and ``--sees`` set the planner of both the mpc and the hybrid
(``uabs-eval``'s options); ``--hybrid-horizon H`` lets the hybrid search H steps while
the mpc beside it keeps ``--mpc-horizon`` (a shorter search with learned values against
the mpc: its λ = 0 on validation is the mpc at H); ``--mpc-beam B`` sets the paths both
searches keep per first move (``uabs-eval --mpc-beam``, default planner.BEAM) and
``--hybrid-beam B`` the hybrid's alone (a narrower mpc beside the default hybrid, say),
``--mpc-rounds R`` and ``--hybrid-rounds R`` their passes over the fleet likewise
(``uabs-eval --mpc-rounds``, default planner.ROUNDS);
extra ``key=value`` overrides evaluate under other world settings, as ``uabs-eval`` takes
them.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from uabs_rl.cli import one_line_errors
from uabs_rl.config import ConfigError
from uabs_rl.evaluation.baselines import passes_text
from uabs_rl.evaluation.hybrid import HYBRID
from uabs_rl.evaluation.leaf import LEAF
from uabs_rl.evaluation.load import Evaluation, evaluate_policies, load_evaluation
from uabs_rl.evaluation.planner import BEAM, ROUNDS
from uabs_rl.evaluation.predict import PREDICTORS, parse_sees
from uabs_rl.evaluation.stats import paired_over_seeds, t_interval, welch_difference
from uabs_rl.runs.layout import RunFolder

METRICS = {"served": "served_fractions", "pg": "pgs"}


LOADED: dict[tuple, Evaluation] = {}  # each member's best.pt, env and traces, per split


def flown(run: Path, policies: tuple[str, ...], split: str, windows: int | None,
          args: argparse.Namespace, weight: float = 0.0,
          horizon: int | None = None, beam: int | None = None,
          rounds: int | None = None) -> dict[str, dict]:
    """Each policy's record on ``split`` (every window, or ``windows``), the planners'
    search ``horizon`` steps long keeping ``beam`` paths per first move, in ``rounds``
    passes (defaults ``--mpc-horizon``, ``--mpc-beam``, ``--mpc-rounds``); a member and
    split are loaded once, for every λ."""
    ev = loaded(run, split, windows, args.overrides)
    try:
        out = evaluate_policies(ev, policies,
                                mpc_horizon=horizon or args.mpc_horizon,
                                predictor=args.predictor, sees=args.sees, hybrid_weight=weight,
                                beam=beam or args.mpc_beam, rounds=rounds or args.mpc_rounds)
    except ConfigError as e:  # a setting the run cannot take: one line, status 2
        raise ConfigError(f"{run}: {e}") from None
    recs = {name: rec for name, (rec, _) in out.items()}
    for name, rec in recs.items():  # the masks' guarantees, checked for every rollout
        unsafe = rec["collisions"] + rec["proximity"] + rec["fallbacks"]
        if unsafe:
            sys.exit(f"{run} {name} on {split}: {rec['collisions']} collisions, "
                     f"{rec['proximity']} proximity events, {rec['fallbacks']} fallbacks")
    return recs


def loaded(run: Path, split: str, windows: int | None, overrides: list[str]) -> Evaluation:
    """A member on a split, loaded once (every λ flies it); a setting the run cannot take
    is a ConfigError naming the run (one line, status 2)."""
    key = (run, split, windows)
    if key not in LOADED:
        try:
            LOADED[key] = load_evaluation(run, "best", windows, split, overrides)
        except ConfigError as e:
            raise ConfigError(f"{run}: {e}") from None
    return LOADED[key]


def finite(values: list[float]) -> list[float]:
    """The windows that hold a vehicle (the others are NaN): an interval over windows."""
    return [x for x in values if not np.isnan(x)]


def pct(x: float) -> str:
    return f"{100 * x:.2f}"


def ci(d: dict) -> str:
    return f"{100 * d['diff']:+.2f} [{100 * d['ci_low']:+.2f}, {100 * d['ci_high']:+.2f}]"


def compare(a: Path, b: Path) -> None:
    """Two learned policies (two populations, each flown by this benchmark into ``a`` and
    ``b``) on the same test windows: the difference of their means over members with
    Welch's 95 % interval (independent groups of seeds), served fraction and P_g."""
    ja, jb = (json.loads((d / "hybrid.json").read_text()) for d in (a, b))
    same = {"mpc_horizon": None, "predictor": None, "sees": None, "overrides": None,
            "mpc_beam": BEAM, "mpc_rounds": ROUNDS}  # each with its value where unrecorded
    if any(ja.get(k, d) != jb.get(k, d) for k, d in same.items()) or (
            ja["policies"]["mpc"]["served"] != jb["policies"]["mpc"]["served"]):
        sys.exit(f"{a} and {b} were flown under other settings or windows "
                 f"({', '.join(same)}, the test windows): not comparable")
    ra, rb = ja["policies"]["learned"], jb["policies"]["learned"]
    print(f"learned({a}) − learned({b}), test windows, Welch over the members' means:")
    for k in METRICS:
        ma, mb = ([float(np.nanmean(w)) for w in r[k]] for r in (ra, rb))
        d = welch_difference(ma, mb)
        print(f"  {k}: {100 * d['diff']:+.2f} [{100 * d['ci_low']:+.2f}, "
              f"{100 * d['ci_high']:+.2f}] pt ({d['n_a']} and {d['n_b']} members)")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, nargs="?", help="a run folder or a population's folder")
    ap.add_argument("overrides", nargs="*", help="world overrides, as uabs-eval takes them")
    ap.add_argument("--weights", type=float, nargs="+", default=[0.0, 0.25, 0.5, 1.0, 2.0])
    ap.add_argument("--mpc-horizon", type=int, default=5)
    ap.add_argument("--hybrid-horizon", type=int,
                    help="the hybrid's own search horizon (default: --mpc-horizon); the mpc "
                         "beside it keeps --mpc-horizon")
    ap.add_argument("--mpc-beam", type=int, default=BEAM,
                    help=f"paths kept per first move by the mpc's and the hybrid's search "
                         f"(default {BEAM})")
    ap.add_argument("--hybrid-beam", type=int,
                    help="the hybrid's own (default: --mpc-beam)")
    ap.add_argument("--mpc-rounds", type=int, default=ROUNDS,
                    help=f"passes over the fleet of the mpc's and the hybrid's search "
                         f"(default {ROUNDS})")
    ap.add_argument("--hybrid-rounds", type=int,
                    help="the hybrid's own (default: --mpc-rounds)")
    ap.add_argument("--predictor", default="cv", choices=PREDICTORS)
    ap.add_argument("--sees", default="all")
    ap.add_argument("--eval-windows", type=int, help="validation windows (default: all)")
    ap.add_argument("--leaf", action="store_true",
                    help="the learned values at the ends of the mpc's paths (--policy leaf, "
                         "an egocentric network's) instead of Q added at the first move")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--compare", type=Path, nargs=2, metavar=("A", "B"),
                    help="print learned(A) − learned(B) from two --out folders, nothing flown")
    args = ap.parse_args(argv)
    if args.compare:
        return compare(*args.compare)
    if args.run is None or args.out is None:
        ap.error("give a run folder and --out (or --compare A B)")
    args.sees = parse_sees(args.sees)
    if any(not w >= 0 for w in args.weights):
        ap.error("--weights must be >= 0")
    if args.mpc_horizon < 1:
        ap.error("--mpc-horizon must be >= 1")
    if args.hybrid_horizon is None:
        args.hybrid_horizon = args.mpc_horizon
    if args.hybrid_horizon < 1:
        ap.error("--hybrid-horizon must be >= 1")
    if args.eval_windows is not None and args.eval_windows < 1:
        ap.error("--eval-windows must be >= 1 (or left out: every validation window)")
    if args.hybrid_beam is None:
        args.hybrid_beam = args.mpc_beam
    if min(args.mpc_beam, args.hybrid_beam) < 1:
        ap.error("--mpc-beam and --hybrid-beam must be >= 1")
    if args.hybrid_rounds is None:
        args.hybrid_rounds = args.mpc_rounds
    if min(args.mpc_rounds, args.hybrid_rounds) < 1:
        ap.error("--mpc-rounds and --hybrid-rounds must be >= 1")
    runs = RunFolder(args.run).members()
    for run in runs:  # each member loaded (its overrides applied) before --out is made
        loaded(run, "eval", args.eval_windows, args.overrides)
    args.out.mkdir(parents=True, exist_ok=True)
    log = open(args.out / "log.txt", "w")

    def say(line: str = "") -> None:
        print(line, flush=True)
        log.write(line + "\n")

    say(f"$ python benchmarks/hybrid.py {' '.join(sys.argv[1:] if argv is None else argv)}")
    t0 = time.perf_counter()
    # 1. validation: lambda* over the members' mean served fraction
    hybrid = LEAF if args.leaf else HYBRID
    sweep = {}
    for w in args.weights:
        # λ = 0 is the mpc, which no member's network enters: flown once, as on test
        members = runs[:1] if w == 0 else runs
        per = [float(np.nanmean(flown(r, (hybrid,), "eval", args.eval_windows, args, w,
                                      args.hybrid_horizon, args.hybrid_beam,
                                      args.hybrid_rounds)[hybrid]["served_fractions"]))
               for r in members]
        per = per * len(runs) if w == 0 else per
        sweep[w] = per
        say(f"validation  λ = {w:g}: served {pct(float(np.mean(per)))} % (members: "
            f"{', '.join(pct(x) for x in per)})")
    best = max(args.weights, key=lambda w: np.mean(sweep[w]))
    say(f"λ* = {best:g} (chosen on validation)")
    # 2. test
    fixed = flown(runs[0], ("greedy", "mpc"), "test", None, args)
    per_member = [flown(r, ("learned", hybrid), "test", None, args, best, args.hybrid_horizon,
                        args.hybrid_beam, args.hybrid_rounds) for r in runs]
    for m in per_member:  # the table and hybrid.json name either hybrid "hybrid"
        m["hybrid"] = m.pop(hybrid)
    rows, out = [], {"weights": sweep, "best_weight": best, "members": [str(r) for r in runs],
                     "hybrid": hybrid,
                     "mpc_horizon": args.mpc_horizon, "hybrid_horizon": args.hybrid_horizon,
                     "mpc_beam": args.mpc_beam, "hybrid_beam": args.hybrid_beam,
                     "mpc_rounds": args.mpc_rounds, "hybrid_rounds": args.hybrid_rounds,
                     "predictor": args.predictor,
                     "sees": args.sees, "overrides": args.overrides, "policies": {}}
    for name in ("greedy", "mpc"):
        rec = fixed[name]
        out["policies"][name] = {k: rec[v] for k, v in METRICS.items()} | {
            "ms_per_decision": rec["ms_per_decision"]}
        rows.append((name, *(t_interval(finite(rec[v])) for v in METRICS.values()),
                     None, None, rec["ms_per_decision"]))
    for name in ("learned", "hybrid"):
        recs = [m[name] for m in per_member]
        out["policies"][name] = {k: [r[v] for r in recs] for k, v in METRICS.items()} | {
            "ms_per_decision": [r["ms_per_decision"] for r in recs]}
        seed_means = {k: [float(np.nanmean(r[v])) for r in recs] for k, v in METRICS.items()}
        diffs = {k: paired_over_seeds([r[v] for r in recs], [fixed["mpc"][v]] * len(recs))
                 for k, v in METRICS.items()}
        out["policies"][name]["minus_mpc"] = diffs
        # over the members' means; one member's over its windows (not a zero width)
        spread = {k: seed_means[k] if len(recs) > 1 else finite(recs[0][v])
                  for k, v in METRICS.items()}
        rows.append((hybrid if name == "hybrid" else name, t_interval(spread["served"]),
                     t_interval(spread["pg"]), diffs["served"], diffs["pg"],
                     float(np.mean([r["ms_per_decision"] for r in recs]))))
    n = len(runs)
    say("")
    kind = "the learned values at the paths' ends" if args.leaf else "Q at the first move"
    say(f"test split, every window; {n} member(s); mpc H = {args.mpc_horizon} "
        f"({args.predictor}, sees {args.sees}"
        + (f", beam {args.mpc_beam}" if args.mpc_beam != BEAM else "")
        + (f", {passes_text(args.mpc_rounds)}" if args.mpc_rounds != ROUNDS else "")
        + f"); hybrid ({kind}) λ* = {best:g}"
        + (f", H = {args.hybrid_horizon}" if args.hybrid_horizon != args.mpc_horizon else "")
        + (f", beam {args.hybrid_beam}" if args.hybrid_beam != args.mpc_beam else "")
        + (f", {passes_text(args.hybrid_rounds)}" if args.hybrid_rounds != args.mpc_rounds
           else ""))
    say("| policy | served % [95 % CI] | P_g % [95 % CI] | − mpc, served pt | − mpc, P_g pt "
        "| ms per decision |")
    say("|---|---|---|---|---|---|")
    for name, served, pg, ds, dp, ms in rows:
        cell = lambda t: f"{pct(t[0])} [{pct(t[1])}, {pct(t[2])}]"  # noqa: E731
        say(f"| {name} | {cell(served)} | {cell(pg)} | {ci(ds) if ds else '—'} | "
            f"{ci(dp) if dp else '—'} | {ms:.2f} |")
    say("")
    say(f"greedy and mpc: CI over the windows; learned and {hybrid}: over the members' "
        "means; − mpc: each member's mean paired difference over the windows, Student-t "
        f"over {n} members" if n > 1 else f"CIs over the windows (one member: learned and "
        f"{hybrid} too, and − mpc paired over the windows)")
    say(f"{time.perf_counter() - t0:.0f} s")
    (args.out / "hybrid.json").write_text(json.dumps(out, indent=1))
    log.close()


if __name__ == "__main__":
    one_line_errors(main)
