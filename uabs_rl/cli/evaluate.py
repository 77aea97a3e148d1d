"""``uabs-eval``: evaluate a trained run (and the baselines) on the held-out traces.

    uabs-eval outputs/runs/<run dir>                 # best checkpoint, test traces
    uabs-eval outputs/runs/<run dir> --policy all    # + random, greedy, oracle baselines
    uabs-eval outputs/runs/<run dir> --policy all --policy planner --horizon 10
    uabs-eval outputs/runs/<run dir> --policy all --policy mpc --mpc-horizon 5 --sees 150
    uabs-eval outputs/runs/<run dir> --policy mpc --policy hybrid --hybrid-weight 0.5
    uabs-eval path/to/last.pt --split eval --windows 20 --gif
    uabs-eval outputs/runs/<run dir> scenario.sumo.fleet_size=120 channel.los_mode=los
    uabs-eval outputs/runs/<run dir> --config-dir myconf scenario=mygrid   # another city

Evaluates on the test traces by default (``traces.test``: SUMO seeds that neither
training nor checkpoint selection ever read; every window of them), ``--split eval`` on
the validation traces that training evaluated on. Prints a table (returns as whole
numbers, fractions as percentages, their differences in percentage points) and writes
``eval.json`` (fractions as fractions): the split, per policy R, collisions, proximity
events, fallbacks, served fraction, P_g at N̂_s, the whole P_g(N̂_s) curve and the
per-window values, and with baselines the paired differences learned − baseline
(same windows, same masks) with Student-t 95 % CIs over the windows. ``--policy`` may
be given more than once; beyond ``all`` (learned, random, greedy, oracle) it takes the
``kmeans`` and ``junctions`` heuristics and ``planner``, a receding-horizon plan over
the vehicles' true future positions ``--horizon`` steps ahead (the clairvoyant ceiling),
and ``mpc``, the same planner ``--mpc-horizon`` steps ahead over the positions a
predictor gives (``--predictor cv``: constant velocity from the vehicles' current and
previous positions, the default; ``road``: along the SUMO network's lanes; ``learned``:
a small network fit on the scenario's training traces reads each vehicle's last moves,
:mod:`uabs_rl.evaluation.motion`) seeing every
vehicle or only those within ``--sees R`` metres of a UABS: a deployable policy;
``hybrid`` adds ``--hybrid-weight`` λ times the learned Q-values to the mpc's scores
(:mod:`uabs_rl.evaluation.hybrid`; choose λ on
``--split eval``), ``leaf`` adds λ times the learned value at the end of each of the
mpc's paths (:mod:`uabs_rl.evaluation.leaf`; a network of ``obs=egocentric``). Every
policy's compute per decision (ms per step for the whole fleet, amortised over the
windows run side by side) is printed. With learned, greedy and planner together it also
prints the learned policy's share of the greedy-to-planner gap. Also a
trajectory picture per policy and, with ``--gif``, an animation of one episode of the
learned policy, into ``<run dir>/evaluation/`` (or ``--out``, checked before anything
is evaluated).

Overrides after the path evaluate the checkpoint under other settings: the run's own
config with ``scenario``, ``channel``, ``masking`` and ``traces`` changed as on the
``uabs-train`` command line (``group=option`` takes a config file of that group, from
``conf/`` or a folder given with ``--config-dir``; ``group.key=value`` sets one value).
The observation (``obs``) belongs to the trained policy and stays as trained, whatever
the scenario; with the paper's observation its size fixes ``scenario.n_uabs`` and
``channel.n_beams`` too (a run trained with ``obs=egocentric`` evaluates at any
``scenario.n_uabs``, in any area); ``algo`` and ``train`` define the network and its
training and cannot change. Results then go to
``<run dir>/evaluation/<overrides>/`` (``traces.cache_dir`` and ``traces.workers``, which
change no result, name no folder).

Evaluation needs only the held-out env, the Q-network and the masking rule
(:mod:`uabs_rl.evaluation.evaluator`): no training traces, replay buffer or optimiser are built.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import torch

from uabs_rl.config import ConfigError
from uabs_rl.evaluation.baselines import HEURISTICS, MPC, PLANNER, passes_text
from uabs_rl.evaluation.hybrid import HYBRID
from uabs_rl.evaluation.leaf import LEAF
from uabs_rl.evaluation.load import (
    POLICIES,
    Evaluation,
    default_out_dir,
    differences,
    evaluate_policies,
    find_checkpoint,
    gap_shares,
    load_evaluation,
    peak_memory,
)
from uabs_rl.evaluation.planner import BEAM, ROUNDS
from uabs_rl.evaluation.predict import PREDICTORS, parse_sees
from uabs_rl.evaluation.stats import signed
from uabs_rl.paths import OutputFolder, OutputInterrupted, check_path
from uabs_rl.runs.checkpoint import CheckpointError
from uabs_rl.training.threads import ThreadGovernor

CHOICES = (*POLICIES, *HEURISTICS, PLANNER, MPC, HYBRID, LEAF)  # every --policy


def percent(x: float) -> str:
    """A fraction as a percentage, one decimal: ``12.3 %``."""
    return f"{round(100 * x, 1) + 0.0:.1f} %"  # + 0.0: never "-0.0"


def points(d: dict[str, float]) -> str:
    """A paired difference of fractions in percentage points with its CI:
    ``+1.2 pt [-0.3, +2.7]``."""
    lo, mid, hi = (signed(100 * d[k]) for k in ("ci_low", "diff", "ci_high"))
    return f"{mid} pt [{lo}, {hi}]"


def whole(x: float, sign: bool = False) -> str:
    """A return (or count) as an integer, ``+`` signed with ``sign``."""
    return f"{int(round(x)):{'+' if sign else ''}d}"


def return_difference(d: dict[str, float]) -> str:
    """A paired difference of returns with its CI, as integers: ``+46 [+7, +82]``."""
    return (f"{whole(d['diff'], True)} [{whole(d['ci_low'], True)}, "
            f"{whole(d['ci_high'], True)}]")


DIFF_FORMATS = {"return": ("R", return_difference), "served_fraction": ("served", points),
                "pg": ("P_g", points)}


def _print_differences(diffs: dict[str, dict[str, dict]]) -> None:
    if not diffs:
        return
    method = next(iter(next(iter(diffs.values())).values()))["method"]
    print(f"\nlearned − baseline, per window (mean [{method}, one run: the windows are "
          f"the unit, not seeds]; fractions in percentage points):")
    for name, per in diffs.items():
        print(f"{name:>8}  " + "   ".join(
            f"{DIFF_FORMATS[m][0]}: {DIFF_FORMATS[m][1](d):<24}" for m, d in per.items())
            .rstrip())


def _print_planner(results: dict[str, tuple[dict, Any]], shares: dict[str, dict]) -> None:
    if PLANNER not in results:
        return
    rec = results[PLANNER][0]
    print(f"\nplanner: horizon {rec['horizon']}, {rec['seconds'] / rec['windows']:.2f} s per "
          f"window ({rec['windows']} windows side by side, {rec['seconds']:.1f} s, "
          f"{torch.get_num_threads()} torch thread(s)); it knows the vehicles' future "
          f"positions: the clairvoyant ceiling, not a deployable policy")
    for m, d in shares.items():
        name = DIFF_FORMATS[m][0]
        print(f"learned share of the greedy-to-planner gap, {name}: "
              f"{signed(100 * d['share'], 0)} % [{signed(100 * d['ci_low'], 0)}, "
              f"{signed(100 * d['ci_high'], 0)}] (95 % CI, percentile bootstrap over the "
              f"{d['n']} windows)")


def _print_mpc(results: dict[str, tuple[dict, Any]]) -> None:
    for name in (MPC, HYBRID, LEAF):
        if name not in results:
            continue
        rec = results[name][0]
        sees = ("every vehicle" if rec["sees"] == "all"
                else f"the vehicles within {rec['sees']:g} m")
        weight = {HYBRID: f", weight {rec.get('weight', 0):g} of the learned Q-values",
                  LEAF: f", weight {rec.get('weight', 0):g} of the learned leaf values"
                  }.get(name, "")
        print(f"\n{name}: horizon {rec['horizon']}, beam {rec['beam']}, "
              f"{passes_text(rec['rounds'])}, predictor "
              f"{rec['predictor']}, sees {sees}{weight}; {rec['ms_per_decision']:.1f} ms per "
              f"decision ({rec['windows']} windows side by side, {rec['seconds']:.1f} s, "
              f"{torch.get_num_threads()} torch thread(s))")


def _print_table(results: dict[str, tuple[dict, Any]], nhat: int) -> None:
    heads = ("R", "R std", "collisions", "proximity", "fallbacks", "served",
             f"P_g(N̂s={nhat})")
    print(f"{'policy':>8} " + " ".join(f"{h:>12}" for h in heads))
    for name, (rec, _) in results.items():
        cells = (whole(rec["return"]), whole(rec["return_std"]), whole(rec["collisions"]),
                 whole(rec["proximity"]), whole(rec["fallbacks"]),
                 percent(rec["served_fraction"]), percent(rec["pg"]))
        print(f"{name:>8} " + " ".join(f"{c:>12}" for c in cells))
    print("compute per decision (the whole fleet, ms per step, amortised over the windows "
          "run side by side): " + ", ".join(f"{name} {rec['ms_per_decision']:.2f}"
                                            for name, (rec, _) in results.items()))


def parser() -> argparse.ArgumentParser:
    """``uabs-eval``'s command line."""
    from uabs_rl.cli.report import Parser

    ap = Parser(
        prog="uabs-eval",
        description="Evaluate a uabs-train run on held-out traces, under its own settings "
                    "or other scenario/channel/masking/traces values.")
    ap.add_argument("path", type=Path, help="a run directory or a checkpoint (.pt)")
    ap.add_argument("overrides", nargs="*", metavar="override",
                    help="group=option or key=value for scenario, channel, masking, traces "
                         "(and device), as on the uabs-train command line")
    ap.add_argument("--config-dir", type=Path, action="append", default=[],
                    help="a folder of your own configs (scenario/<name>.yaml, ...), beside "
                         "the package's conf/ (a file named as one of the package's is "
                         "refused); may be repeated")
    ap.add_argument("--checkpoint", choices=("best", "last"), default=None,
                    help="which checkpoint of a run directory (default: best); a .pt "
                         "PATH is the checkpoint itself")
    ap.add_argument("--policy", choices=(*CHOICES, "all"), action="append",
                    help="what to evaluate, may be repeated: learned (default), the "
                         "random, greedy and oracle baselines, all (these four), the "
                         "kmeans and junctions heuristics, planner (see --horizon), mpc "
                         "(see --mpc-horizon, --predictor, --sees), hybrid (the mpc's "
                         "scores plus the learned Q-values, see --hybrid-weight), leaf "
                         "(the mpc whose paths end in the learned values, an egocentric "
                         "network's; the same weight)")
    ap.add_argument("--horizon", type=int, default=None,
                    help="the planner's horizon in steps (default 10; 1 = the oracle)")
    ap.add_argument("--mpc-horizon", type=int, default=None,
                    help="the mpc's horizon in steps (default 5)")
    ap.add_argument("--mpc-beam", type=int, default=None, metavar="B",
                    help=f"the paths the mpc's (and the hybrids') beam search keeps per "
                         f"first move (default {BEAM}; 4 served as much on the project's "
                         f"grids for under half the compute: docs/evaluation.md)")
    ap.add_argument("--mpc-rounds", type=int, default=None, metavar="R",
                    help=f"the mpc's (and the hybrids') passes over the fleet per decision "
                         f"(default {ROUNDS}: a second pass replans each UABS given all the "
                         f"others' plans; docs/evaluation.md)")
    ap.add_argument("--predictor", choices=tuple(p for p in PREDICTORS), default=None,
                    help="what the mpc plans over: cv, the vehicles' current and previous "
                         "positions extrapolated at constant velocity (default); road, each "
                         "vehicle moved along its lane and the SUMO network's successors "
                         "(not its route); learned, as a network fit on the scenario's "
                         "training traces predicts from each vehicle's last moves (fit "
                         "once, cached beside the traces); or true, their true future "
                         "(then it is the clairvoyant planner)")
    ap.add_argument("--sees", default=None, metavar="all|R",
                    help="the vehicles the mpc sees: all (centralised, default) or those "
                         "within R metres of some UABS")
    ap.add_argument("--hybrid-weight", type=float, default=None, metavar="λ",
                    help="the hybrid's weight of the learned Q-values beside the mpc's "
                         "scores, and leaf's of the learned leaf values (default 1; 0 = "
                         "the mpc); choose it on --split eval")
    ap.add_argument("--split", choices=("test", "eval"), default="test",
                    help="test traces (default; never seen by training or selection) or "
                         "eval, the validation traces training evaluated on")
    ap.add_argument("--windows", type=int,
                    help="windows to evaluate (default: every test window, or the run's "
                         "train.eval_windows on eval)")
    ap.add_argument("--gif", action="store_true", help="also write an animation (learned)")
    ap.add_argument("--out", type=Path, help="output folder (default: <run>/evaluation)")
    return ap


# the options that set one kind of policy, their defaults, and the policies they set
# (given without one of them they would be ignored: refused instead, as uabs-report does)
POLICY_OPTIONS = {"horizon": (10, ("planner",)),
                  "mpc_horizon": (5, ("mpc", "hybrid", "leaf")),
                  "mpc_beam": (BEAM, ("mpc", "hybrid", "leaf")),
                  "mpc_rounds": (ROUNDS, ("mpc", "hybrid", "leaf")),
                  "predictor": ("cv", ("mpc", "hybrid", "leaf")),
                  "sees": ("all", ("mpc", "hybrid", "leaf")),
                  "hybrid_weight": (1.0, ("hybrid", "leaf"))}


def main(argv: list[str] | None = None) -> int:
    ap = parser()
    args = ap.parse_intermixed_args(argv)
    asked = set(args.policy or ["learned"])
    for key, (default, users) in POLICY_OPTIONS.items():
        if getattr(args, key) is None:
            setattr(args, key, default)
        elif not asked & set(users):
            flag = "--" + key.replace("_", "-")
            ap.error(f"{flag} sets the {' / '.join(users)} policy, which this command does "
                     f"not evaluate: add --policy {users[0]}, or leave {flag} out")
    if args.windows is not None and args.windows < 1:
        ap.error(f"--windows must be >= 1, got {args.windows}")
    if args.horizon < 1:
        ap.error(f"--horizon must be >= 1, got {args.horizon}")
    if args.mpc_horizon < 1:
        ap.error(f"--mpc-horizon must be >= 1, got {args.mpc_horizon}")
    if args.mpc_beam < 1:
        ap.error(f"--mpc-beam must be >= 1, got {args.mpc_beam}")
    if args.mpc_rounds < 1:
        ap.error(f"--mpc-rounds must be >= 1, got {args.mpc_rounds}")
    if not (math.isfinite(args.hybrid_weight) and args.hybrid_weight >= 0):
        ap.error(f"--hybrid-weight must be a number >= 0, got {args.hybrid_weight}")
    try:
        args.sees = parse_sees(args.sees)
    except ValueError as e:
        ap.error(str(e))
    try:  # a name too long to stat is refused below, by check_path
        a_file = args.path.is_file()
    except OSError:
        a_file = False
    if a_file and args.checkpoint is not None:
        ap.error(f"--checkpoint {args.checkpoint} chooses a run folder's checkpoint, and "
                 f"{args.path} is a checkpoint file itself: pass the run folder with "
                 f"--checkpoint, or the file alone")
    # what was evaluated, as printed and recorded: best or last of a run folder, or the file
    args.checkpoint = args.checkpoint or "best"
    checkpoint = str(args.path) if a_file else args.checkpoint
    try:  # the output folder is checked before anything is evaluated
        check_path(args.path, "PATH")
        for d in args.config_dir:
            check_path(d, "--config-dir")
        out = output_folder(args.out or default_out_dir(args.path, args.overrides),
                            args.out is not None)
        find_checkpoint(args.path, args.checkpoint)
        out.check()
        replaced = earlier_policies(out.path)
        ev = load_evaluation(args.path, args.checkpoint, args.windows, args.split,
                             args.overrides, args.config_dir, windows_name="--windows")
        # torch's default threads (or OMP_NUM_THREADS), fewer while other processes keep
        # the CPUs busy (more threads than free cores cost several times one), unless
        # OMP_NUM_THREADS fixes them
        governor = ThreadGovernor(torch.get_num_threads(), fixed="OMP_NUM_THREADS" in os.environ)
        ev.evaluator.on_step = governor.check if governor.active else None
        try:
            with out.writing() as folder:  # the previous evaluation stays whole until the end
                _evaluate_and_write(ev, args, folder, governor, checkpoint)
        finally:  # a caller of main() (a test, a script) keeps its own count
            torch.set_num_threads(governor.most)
    except (CheckpointError, ConfigError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OutputInterrupted as e:
        print(str(e), file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("interrupted: nothing was written", file=sys.stderr)
        return 130
    print(f"wrote {out.path / 'eval.json'} and pictures under {out.path}"
          + (f"; they replace the evaluation of {', '.join(replaced)} that was there "
             f"(--out DIR writes another folder)" if replaced else ""))
    return 0


def earlier_policies(out: Path) -> list[str]:
    """The policies of the evaluation already in ``out`` (which this one replaces), or
    none."""
    try:
        return list(json.loads((out / "eval.json").read_text())["policies"])
    except (OSError, ValueError, KeyError, TypeError):
        return []


# every file uabs-eval writes (an evaluation folder written before the marker file
# existed is recognised by these)
EVAL_FILES = ("eval.json", "trajectories_*.png", "trajectories_*.pdf", "episode_learned.gif")


def output_folder(out: Path, given: bool) -> OutputFolder:
    """The evaluation's output folder, written whole or not at all
    (:class:`uabs_rl.paths.OutputFolder`); the folders of evaluations under overrides
    inside it (``evaluation/<overrides>/``, :func:`~uabs_rl.evaluation.load.default_out_dir`)
    are kept."""
    return OutputFolder(out, "uabs-eval", EVAL_FILES,
                        "--out" if given else "the output folder", keep_dirs=True)


def _evaluate_and_write(ev: Evaluation, args: argparse.Namespace, out: Path,
                        governor: ThreadGovernor | None, checkpoint: str) -> None:
    """Evaluate the policies ``args`` asks for, print the tables, and write eval.json and
    the pictures into ``out``. ``checkpoint``: what was evaluated, "best" or "last" of a
    run folder or a checkpoint file's path."""
    policies = tuple(dict.fromkeys(
        q for p in args.policy or ["learned"] for q in (POLICIES if p == "all" else [p])))
    t0 = time.perf_counter()
    results = evaluate_policies(ev, policies, horizon=args.horizon,
                                mpc_horizon=args.mpc_horizon, predictor=args.predictor,
                                sees=args.sees, hybrid_weight=args.hybrid_weight,
                                beam=args.mpc_beam, rounds=args.mpc_rounds)
    n = ev.evaluator.env.base_env.n_envs
    tc = getattr(ev.cfg.traces, args.split)
    print(f"split: {args.split} (traces.{args.split}: SUMO seeds {tc.first_seed}.."
          f"{tc.first_seed + tc.n_sims - 1}), {n} windows of "
          f"{ev.cfg.scenario.episode_steps} steps, "
          + (f"checkpoint {checkpoint}" if checkpoint not in ("best", "last")
             else f"{checkpoint} checkpoint")
          + (f", scenario {ev.cfg.scenario.name}, overrides: {' '.join(args.overrides)}"
             if args.overrides else ""))
    _print_table(results, ev.evaluator.params.nhat_s)
    diffs = differences(results)
    _print_differences(diffs)
    shares = gap_shares(results)
    _print_planner(results, shares)
    _print_mpc(results)
    busy = (f"; torch threads: {governor.most}, fewer while other processes kept the CPUs "
            f"busy ({governor.changes} change(s))" if governor is not None and governor.changes
            else "")
    print(f"evaluated {len(results)} {'policy' if len(results) == 1 else 'policies'} in "
          f"{time.perf_counter() - t0:.1f} s{peak_memory()}{busy}")
    (out / "eval.json").write_text(json.dumps(
        {"split": args.split, "windows": n, "checkpoint": checkpoint,
         "overrides": args.overrides, "scenario": ev.cfg.scenario.name,
         "policies": {k: r for k, (r, _) in results.items()}, "differences": diffs,
         **({"gap_share": shares} if shares else {})},
        indent=1))
    _write_pictures(ev, results, out, args.gif, args.split)


def _write_pictures(ev: Evaluation, results: dict, out: Path, gif: bool, split: str) -> None:
    import matplotlib.pyplot as plt
    import torch.nn.functional as F

    from uabs_rl.env.uabs_env import DIAG
    from uabs_rl.evaluation.plots import (
        animate_episode,
        save_figure,
        scenario_lanes,
        trajectory_figure,
    )

    a, p = ev.cfg.scenario.area, ev.evaluator.params
    lanes = scenario_lanes(ev.cfg.scenario)
    for name, (rec, td) in results.items():
        fig = trajectory_figure(a, *ev.evaluator.trajectory_of(td), p.r_b, p.n_beams, lanes,
                                title=f"{name} ({ev.cfg.masking.mode} masking), {split} "
                                      f"window 0: R = {rec['returns'][0]:.0f}")
        save_figure(fig, out / f"trajectories_{name}.png")
        plt.close(fig)
    if gif and "learned" in results:
        td = results["learned"][1]
        after = td["next", DIAG, "ep_return"][0]  # the return after each step
        animate_episode(a, *ev.evaluator.trajectory_of(td), p.r_b, p.n_beams, lanes,
                        out / "episode_learned.gif", returns=F.pad(after, (1, 0)),  # R = 0 at t = 0
                        title=f"learned policy, {ev.cfg.masking.mode} masking, {split} "
                              f"window 0")


def run_main() -> None:
    sys.exit(main())


if __name__ == "__main__":
    run_main()
