"""``uabs-report``: the paper's Table 2, Fig. 3 and Fig. 4 from a sweep, with baselines,
for runs of any settings side by side.

    uabs-train -m masking=penalty,flat,rank seed=0,1,2
    uabs-report outputs/multirun/<date_time>            # writes <dir>/report/
    uabs-report outputs/multirun/<date_time> --no-baselines --out docs/results
    uabs-report RUN_A RUN_B --curves                    # training curves overlaid, only
    uabs-report outputs/multirun/<study>                # a tuning study (docs/tuning.md)

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
import sys
from pathlib import Path

from uabs_rl.config import ConfigError
from uabs_rl.paths import OutputFolder, OutputInterrupted, check_path
from uabs_rl.report.build import REPORT_FILES, build_report, default_out
from uabs_rl.report.claims import short_run_warning
from uabs_rl.report.figures import curves_figure
from uabs_rl.runs.checkpoint import CheckpointError
from uabs_rl.runs.metrics import MetricsError
from uabs_rl.runs.sweep import ReportError, find_runs, group_runs


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
    ap.add_argument("--mpc-beam", type=int, metavar="B",
                    help="with --mpc: the paths its beam search keeps per first move "
                         "(default 16, as uabs-eval --mpc-beam)")
    ap.add_argument("--mpc-rounds", type=int, metavar="R",
                    help="with --mpc: its passes over the fleet (default 2, as uabs-eval "
                         "--mpc-rounds)")
    ap.add_argument("--cache-dir", type=Path, metavar="DIR",
                    help="the trace cache to read (or build) the test traces in, in place "
                         "of the runs' traces.cache_dir (runs made on another machine)")
    ap.add_argument("--export", choices=("marl-eval",),
                    help="also write the runs in marl-eval's JSON layout (marl_eval.json: "
                         "per run, per evaluation, per metric; best.pt's test windows as "
                         "absolute metrics), for BenchMARL's and Mava's plotting tools")
    ap.add_argument("--curves", action="store_true",
                    help="only overlay the runs' training and validation curves "
                         "(curves.png/.pdf), in seconds")
    ap.add_argument("--storage", metavar="URL",
                    help="a tuning study's storage, in place of the one its folder's "
                         "study.yaml names (which keeps no password)")
    args = ap.parse_args(argv)
    from uabs_rl.tuning.report import is_study

    if len(args.roots) == 1 and is_study(args.roots[0]) and not args.curves:
        return study_main(args.roots[0], args.out, args.storage)
    if args.planner is not None and (args.planner < 1 or not args.baselines):
        ap.error("--planner H needs H >= 1 and the test-trace evaluation (no --no-baselines)")
    if args.mpc is not None and (args.mpc < 1 or not args.baselines):
        ap.error("--mpc H needs H >= 1 and the test-trace evaluation (no --no-baselines)")
    for flag, value in (("--mpc-beam", args.mpc_beam), ("--mpc-rounds", args.mpc_rounds)):
        if value is not None and args.mpc is None:
            ap.error(f"{flag} sets the search of --mpc H: give --mpc H too")
        if value is not None and value < 1:
            ap.error(f"{flag} must be >= 1, got {value}")
    if args.cache_dir is not None:
        if not args.baselines or args.curves:
            ap.error("--cache-dir holds the test traces: --no-baselines and --curves "
                     "read none")
        try:
            check_path(args.cache_dir, "--cache-dir")  # a name too long, before a stat
        except ConfigError as e:
            ap.error(str(e))
        if args.cache_dir.exists() and not args.cache_dir.is_dir():
            ap.error(f"--cache-dir {args.cache_dir} is a file: give a folder (it is made "
                     f"if missing)")
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
                                   runs=runs, export=args.export, mpc=args.mpc,
                                   mpc_beam=args.mpc_beam, mpc_rounds=args.mpc_rounds,
                                   cache_dir=args.cache_dir)
                text = (folder / "summary.md").read_text()
    except (ReportError, ConfigError, CheckpointError, MetricsError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OutputInterrupted as e:
        print(str(e), file=sys.stderr)
        return e.exit_code
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


def study_main(root: Path, given: Path | None, storage: str | None) -> int:
    """``uabs-report <study folder>`` (uabs-train -m hydra/sweeper=optuna): the best
    trials, the parameter importances and the optimisation history (docs/tuning.md)."""
    from uabs_rl.tuning.report import FILES, study_report

    out = OutputFolder(given or root / "report", "uabs-report", FILES,
                       "--out" if given else "the report folder")
    try:
        check_path(root, "FOLDER")
        out.check()
        with out.writing() as folder:
            text = study_report(root, folder, storage)
    except ImportError as e:
        print(f"error: the study report needs optuna ({e}): pip install -e \".[tune]\"",
              file=sys.stderr)
        return 2
    except (ReportError, ConfigError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OutputInterrupted as e:
        print(str(e), file=sys.stderr)
        return e.exit_code
    print(text)
    print(f"wrote {out.path} (study.md, trials.csv, history and importances as PNG and "
          f"PDF); each trial's run folder is a run for uabs-report and uabs-eval")
    return 0


def run_main() -> None:
    sys.exit(main())


if __name__ == "__main__":
    run_main()


if __name__ == "__main__":
    run_main()
