"""``uabs-train``: 3DQN training with periodic held-out evaluation (docs/model.md §7, §8).

    uabs-train                                    # paper protocol, masking=rank
    uabs-train masking=flat seed=3
    uabs-train -m masking=penalty,flat,rank seed=0,1,2
    uabs-train experiment=smoke                   # the whole pipeline in seconds
    uabs-train resume=outputs/runs/<run dir>      # continue a stopped run

Every run writes under its Hydra output directory: ``metrics.jsonl`` (one line per
training episode and per evaluation), ``tb/`` (TensorBoard; ``train.logger`` picks
another TorchRL logger), ``checkpoints/last.pt``
and ``checkpoints/best.pt`` (by evaluation return), ``eval/*.png``. The run itself is
:class:`uabs_rl.training.experiment.Experiment`.

``resume=<run dir>`` takes the run's own configuration (from its last checkpoint, or
from its ``.hydra/config.yaml`` if it stopped before one) and writes into that folder;
overrides typed beside it may change only what does not change results
(``train.episodes``, ``device``, ``train.progress``, ...).
"""

from __future__ import annotations

import os
import shlex
import shutil
import sys
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from uabs_rl.cli.hydra import hydra_main, path_safe
from uabs_rl.config import ConfigError, LoggerKind, RunConfig
from uabs_rl.paths import check_path, name_max
from uabs_rl.runs import folder as runfolder
from uabs_rl.runs.layout import RunFolder
from uabs_rl.runs.metrics import MetricsError, read_metrics
from uabs_rl.training.resume import prepare
from uabs_rl.tuning.sweeper import STUDY_FILE
from uabs_rl.tuning.trial import evaluation_hook


def command(name: str) -> str:
    """How to call one of this installation's commands from the shell it was started
    in: the bare name when that is what the PATH finds, else its full path (a virtual
    environment that was not activated)."""
    here = Path(sys.executable).parent / name
    found = shutil.which(name)
    if here.is_file() and (found is None or Path(found).resolve() != here.resolve()):
        return shlex.quote(str(here))
    return name


def summary_text(cfg: RunConfig, summary: dict[str, Any], run_dir: Path) -> str:
    """The end of a run: where it is, a table of its headline figures (from its whole
    ``metrics.jsonl``, so a resumed run counts every episode), and the next commands,
    ready to copy."""
    metrics = RunFolder(run_dir).metrics
    recs = read_metrics(metrics) if metrics.is_file() else []
    train = [r for r in recs if r["kind"] == "train"]
    evals = [r for r in recs if r["kind"] == "eval"]
    steps = train[-1]["env_steps"] if train else 0
    lines = [f"\nrun folder: {run_dir}",
             f"  {summary['episodes']} episodes, {steps} env steps, {summary['updates']} "
             f"updates; this session {summary['minutes']:.1f} min"]
    if evals:
        best = max(evals, key=lambda r: r["return"])  # the checkpoint best.pt holds
        last = evals[-1]
        nhat = cfg.scenario.nhat_s
        rows = [("return R", "{:.0f}", "return"),
                ("served fraction", "{:.1%}", "served_fraction"),
                (f"P_g(N̂s={nhat})", "{:.1%}", "pg"),
                ("collisions", "{:.0f}", "collisions"),
                ("proximity events", "{:.0f}", "proximity"),
                ("mask fallbacks", "{:.0f}", "fallbacks")]
        head_b, head_l = f"best (ep {best['episode']})", f"last (ep {last['episode']})"
        title = f"validation ({best['windows']} windows)"
        lines.append(f"  {title:<24} {head_b:>16} {head_l:>16}")
        for name, fmt, key in rows:
            lines.append(f"  {name:<24} {fmt.format(best[key]):>16} {fmt.format(last[key]):>16}")
    if train:
        lines.append("  training: " + ", ".join(
            f"{sum(r[k] for r in train):.0f} {name}" for k, name in (
                ("collisions", "collisions"), ("proximity", "proximity events"),
                ("fallbacks", "mask fallbacks"))) + f" in {len(train)} episodes")
    q = shlex.quote(str(run_dir))
    # a sweep's job: the report over the whole sweep (it groups the sweep's settings)
    sweep = run_dir.parent if RunFolder(run_dir.parent).sweep_record.is_file() else run_dir
    report_dir = shlex.quote(str(sweep))
    study = (sweep / STUDY_FILE).is_file()  # a tuning study's trial: its report is the study's
    lines += ["next:",
              f"  {command('uabs-eval')} {q} --policy all   # test traces, beside the "
              f"baselines, with CIs",
              f"  {command('uabs-report')} {report_dir}   # "
              + ("the study: its best trials, importances, history" if study else
                 "tables and figures of the runs in that folder")]
    logger = LoggerKind(cfg.train.logger)
    if logger is LoggerKind.tensorboard:
        tb = shlex.quote(str(RunFolder(run_dir).tb))
        lines.append(f"  {command('tensorboard')} --logdir {tb}")
    elif logger is LoggerKind.csv:
        lines.append(f"  ls {shlex.quote(str(run_dir / 'csv' / 'scalars'))}   # one CSV per "
                     f"curve")
    return "\n".join(lines)


def population_summary_text(cfg: RunConfig, summary: dict[str, Any], run_dir: Path) -> str:
    """The end of a population: one row per member (validation R at its best and last
    evaluation, served fraction and P_g at its best, training collisions), then the
    next commands."""
    nhat = cfg.scenario.nhat_s
    lines = [f"\npopulation folder: {run_dir}",
             f"  {len(summary['members'])} members x {summary['episodes']} episodes, "
             f"{summary['updates']} batched updates; this session {summary['minutes']:.1f} min",
             f"  {'member':<22} {'best R (ep)':>14} {'last R':>8} {'served':>8} "
             f"{f'P_g({nhat})':>8} {'train coll.':>11}"]
    for m in summary["members"]:
        path = RunFolder(m["run_dir"]).metrics
        recs = read_metrics(path) if path.is_file() else []
        evals = [r for r in recs if r["kind"] == "eval"]
        coll = sum(r["collisions"] for r in recs if r["kind"] == "train")
        if evals:
            best = max(evals, key=lambda r: r["return"])
            lines.append(f"  {Path(m['run_dir']).name:<22} "
                         f"{best['return']:>8.0f} ({best['episode']:>3}) "
                         f"{evals[-1]['return']:>8.0f} {best['served_fraction']:>8.1%} "
                         f"{best['pg']:>8.1%} {coll:>11.0f}")
    q = shlex.quote(str(run_dir))
    first = shlex.quote(str(summary["members"][0]["run_dir"]))
    lines += ["next:",
              f"  {command('uabs-eval')} {first} --policy all   # a member on the test "
              f"traces, beside the baselines",
              f"  {command('uabs-report')} {q}   # tables and figures over the members"]
    if LoggerKind(cfg.train.logger) is LoggerKind.tensorboard:
        lines.append(f"  {command('tensorboard')} --logdir {q}")
    return "\n".join(lines)


def _quote_resume(argv: list[str]) -> list[str]:
    """``resume=<dir>`` as Hydra would not parse it: a run folder named after overrides
    holds '=' and ','. Quote it, and make the resumed job log into that folder (Hydra
    writes no .hydra/ there: conf/config.yaml's ``hydra.output_subdir`` is null). With
    ``-m`` (a sweep re-typed with ``resume=<sweep folder>`` appended), every job
    continues its own folder under that sweep."""
    multirun = any(a in ("-m", "--multirun") for a in argv)
    out = []
    for a in argv:
        if a.startswith("resume=") and a[7:] and a[7] not in "'\"":
            path = a[7:].replace("\\", "\\\\").replace("'", "\\'")
            where = "hydra.sweep.dir" if multirun else "hydra.run.dir"
            out += [f"resume='{path}'", f"{where}='{path}'"]
        else:
            out.append(a)
    return out


def _check_paths(argv: list[str]) -> None:
    """Refuse, before Hydra makes any folder, a ``resume=`` that names no run and a run
    folder (``hydra.run.dir`` / ``hydra.sweep.dir``) that cannot be one."""
    multirun = any(a in ("-m", "--multirun") for a in argv)
    for a in argv:
        key, _, value = a.partition("=")
        path = Path(value.strip("'\""))
        if key in ("resume", "hydra.run.dir", "hydra.sweep.dir") and value:
            check_path(path, key)  # before a stat that would fail on it
        if key == "resume" and not value.strip("'\""):  # an empty shell variable
            raise ConfigError("resume= names no folder: pass the folder of a uabs-train "
                              "run (resume=outputs/runs/<run dir>), or drop resume= to "
                              "start a new run.")
        if key == "resume" and value:
            if not path.exists():
                raise ConfigError(f"resume={path}: no such folder. Pass the folder of a "
                                  f"uabs-train run (the one printed when it started).")
            if not path.is_dir():
                parent = path.parent.parent if path.suffix == ".pt" else path.parent
                raise ConfigError(f"resume={path} is a file: pass the run folder that "
                                  f"holds checkpoints/last.pt, e.g. resume={parent}.")
            if multirun and not RunFolder(path).sweep_record.is_file():
                raise ConfigError(f"resume={path} with -m: pass the sweep's folder (the "
                                  f"one holding multirun.yaml) with the sweep's own "
                                  f"command, or drop -m to resume this one run.")
            if multirun:
                _check_sweep_command(path, argv)
            elif RunFolder(path).sweep_record.is_file() and not runfolder.holds_run(path):
                raise ConfigError(f"resume={path} is a sweep's folder (multirun.yaml): "
                                  f"re-type the sweep's own command, with -m, and "
                                  f"resume={path} appended; or pass one of its jobs' "
                                  f"folders to resume that run alone.")
        elif key in ("hydra.run.dir", "hydra.sweep.dir", "hydra.sweep.subdir") and not \
                value.strip("'\""):  # an empty shell variable: the current folder
            raise ConfigError(f"{key}= names no folder (the run would write into the "
                              f"current folder): name one, or leave {key} out.")
        elif key in ("hydra.run.dir", "hydra.sweep.dir") and value:
            blocking = next((p for p in (path, *path.parents) if p.exists()), None)
            if blocking is not None and not blocking.is_dir():
                raise ConfigError(f"{key}={value}: {blocking} is a file, not a folder: "
                                  f"name a folder for the run.")
            _check_not_inside_a_run(key, path)
            resumed = [b[7:].strip("'\"") for b in argv if b.startswith("resume=") and b[7:]]
            if resumed and key == "hydra.run.dir" and not multirun and \
                    Path(resumed[0]).resolve() != path.resolve():
                raise ConfigError(f"resume={resumed[0]} writes into the run's own folder, "
                                  f"not {key}={value}: drop {key}.")
            if (key == "hydra.sweep.dir" and multirun and not resumed
                    and RunFolder(path).sweep_record.exists() and _holds_jobs(path)):
                raise ConfigError(f"hydra.sweep.dir={value} holds another sweep "
                                  f"(multirun.yaml): continue it by re-typing its command "
                                  f"with resume={value} appended, or choose another "
                                  f"hydra.sweep.dir. Nothing was changed.")
    if not any(a.split("=", 1)[0] == "resume" for a in argv):
        typed = [Path(a.partition("=")[2].strip("'\"")) for a in argv if a.split("=", 1)[0]
                 in (("hydra.sweep.dir",) if multirun else ("hydra.run.dir",))]
        _check_writable_place(typed[0] if typed else Path("outputs"))
    _check_auto_name(argv, multirun)


def _sweep_settings(words: list[str]) -> dict[str, frozenset[str]]:
    """A sweep's command-line overrides as ``key -> the values it takes`` (a sweep's in
    any order, ``range(0,3)`` as 0, 1, 2), less what may change when it is re-typed with
    ``resume=``: Hydra's settings and those that cannot change results (left out of the
    jobs' folder names; every other setting names the folders, so a sweep re-typed with
    another ``train.episodes`` would start new runs beside its own, not extend them)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from uabs_rl.config import folder_name_excludes

    free = set(folder_name_excludes())
    words = [w for w in words if w.split("=", 1)[0].lstrip("+~") not in free
             and not w.lstrip("+~").startswith("hydra")]  # resume= may hold , and =
    out = {}
    for o in OverridesParser.create().parse_overrides(overrides=words):
        key = o.get_key_element()
        values = (list(o.sweep_string_iterator()) if o.is_sweep_override()
                  and not o.is_interval_sweep() else [o.get_value_element_as_str()])
        out[key] = frozenset(values)
    return out


def _check_sweep_command(sweep: Path, argv: list[str]) -> None:
    """``-m ... resume=<sweep folder>`` continues the sweep its ``multirun.yaml`` records
    only when the command is that sweep's (up to what may change on resume): another
    command would start other jobs in the folder (with no sweep at all, one run in the
    sweep folder itself) and Hydra would overwrite the record. A study (the Optuna
    sweeper) checks its own resume."""
    from hydra.errors import HydraException

    from uabs_rl.config import chooses_study, command_line_overrides

    words = command_line_overrides(argv)
    if (sweep / STUDY_FILE).is_file() and _sweeper(argv, words) == "basic":
        # Hydra's own sweeper would run a grid of the search space's values there
        raise ConfigError(f"resume={sweep} holds a tuning study (its {STUDY_FILE}): re-type "
                          f"the study's own command, hydra/sweeper included, with "
                          f"resume={sweep} appended. Nothing was changed.")
    try:
        record = OmegaConf.load(RunFolder(sweep).sweep_record)
        typed = [str(w) for w in record.hydra.overrides.task]
    except Exception:  # no readable record of the command: the jobs' own checks decide
        return
    if chooses_study([*typed, *words]):
        return
    try:
        then, now = _sweep_settings(typed), _sweep_settings(words)
    except HydraException:
        return
    if then == now:
        return
    lacks = [k for k in then if k not in now]
    adds = [k for k in now if k not in then]
    changes = [k for k in then if k in now and then[k] != now[k]]
    said = "; ".join(part for part in (
        f"lacks {', '.join(lacks)}" if lacks else "",
        f"adds {', '.join(adds)}" if adds else "",
        f"changes {', '.join(changes)}" if changes else "") if part)
    command = " ".join(shlex.quote(w) for w in typed if not w.startswith(("resume=", "hydra.")))
    raise ConfigError(f"resume={sweep} continues the sweep typed as `uabs-train -m "
                      f"{command}`; this command {said}: re-type that one with "
                      f"resume={sweep} appended (another sweep goes into another "
                      f"folder). Nothing was changed.")


def _sweeper(argv: list[str], words: list[str]) -> str | None:
    """The sweeper a command line chooses (``hydra/sweeper=optuna`` typed, or chosen by
    a preset), composed as Hydra will; None where it does not compose here."""
    from hydra import compose, initialize_config_dir

    from uabs_rl.cli.hydra import config_dirs, search_overrides
    from uabs_rl.config import CONF_DIR, register_configs

    search = search_overrides(config_dirs(argv))
    # the groups and presets chosen (one value each): the sweeper is among them
    chosen = [w for w in words if "." not in w.split("=", 1)[0]
              and not any(c in w.split("=", 1)[-1] for c in ",()")]
    register_configs()
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            c = compose(config_name="config", return_hydra_config=True,
                        overrides=[*search, *chosen])
        return str(c.hydra.runtime.choices.get("hydra/sweeper"))
    except Exception:  # another search path, a value Hydra refuses: its own answer
        return None


def _holds_jobs(sweep: Path) -> bool:
    """True when a sweep folder holds a job that started (a refused sweep leaves only
    its multirun.yaml: a corrected command may take the folder)."""
    return any(runfolder.holds_run(d) or RunFolder(d).hydra.is_dir()
               for d in sweep.iterdir() if d.is_dir())


def _check_not_inside_a_run(key: str, path: Path) -> None:
    """A run folder inside another run's (``hydra.run.dir=<run>/eval``) would mix the
    two: its records would be reported as a seed of the outer run."""
    for parent in path.absolute().parents:
        if parent.is_dir() and runfolder.holds_run(parent):
            raise ConfigError(f"{key}={path}: {parent} holds a run, so a run inside it "
                              f"would be mixed with it: choose a folder outside it.")


def _check_writable_place(path: Path) -> None:
    """The nearest folder that exists at or above ``path`` takes new files (not a
    read-only file system), else one line before Hydra's own mkdir fails."""
    here = next((p for p in (path.absolute(), *path.absolute().parents) if p.exists()),
                Path("/"))
    if here.is_dir() and not os.access(here, os.W_OK | os.X_OK):
        raise ConfigError(f"cannot write the run folder under {here} (read-only or not "
                          f"yours): choose a writable place with hydra.run.dir=... .")


def _check_auto_name(argv: list[str], multirun: bool) -> None:
    """A run folder named after its overrides (the default) whose name the file system
    cannot hold: refused before Hydra makes it, saying how to name the folder."""
    typed = "hydra.sweep.subdir" if multirun else "hydra.run.dir"
    if any(a.split("=", 1)[0] == typed for a in argv):
        return
    from uabs_rl.config import CONF_DIR

    exclude = set(OmegaConf.load(CONF_DIR / "config.yaml").hydra.job.config
                  .override_dirname.exclude_keys)
    parts = []
    for a in argv:
        key, eq, value = a.partition("=")
        if not eq or key.startswith(("hydra.", "-")) or key.lstrip("+~") in exclude:
            continue
        # a sweep's job is named after one value of each list
        value = max(value.split(","), key=len) if multirun else value
        parts.append(path_safe(f"{key}={value}"))
    name = "2000-01-01_00-00-00_" + ",".join(sorted(parts))
    limit = name_max(Path("outputs"))
    if len(os.fsencode(name)) > limit:
        raise ConfigError(f"the run folder would be named after the overrides, "
                          f"{len(os.fsencode(name))} bytes, more than the {limit} the file "
                          f"system takes: name it with {typed}=<folder>.")


def _run_and_report(cfg: RunConfig, run_dir: Path, overrides: list[str]) -> dict[str, Any]:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    hc = HydraConfig.get()
    multirun = hc.mode == RunMode.MULTIRUN
    sweep_dir = Path(hc.sweep.dir) if multirun else None
    if cfg.resume and multirun:  # a re-typed sweep: this job's own folder under it
        if runfolder.holds_run(run_dir) or RunFolder(run_dir).hydra_config.is_file():
            cfg.resume = str(run_dir)
        else:  # a job the stopped sweep never reached: it starts now, in its folder
            cfg.resume = None
    exp = prepare(cfg, run_dir, overrides, auto_named=not os.environ.get(_TYPED_DIR),
                  sweep_dir=sweep_dir,
                  on_move=(lambda folder: runfolder.copy_sweep_record(sweep_dir, folder))
                  if multirun else None,
                  record=lambda folder: runfolder.write_hydra_record(cfg, folder))
    print(f"{'resuming' if cfg.resume else 'run folder:'} {exp.run_dir}", file=sys.stderr)
    if multirun:  # a job continues with its sweep (or study), re-typed
        exp.continue_hint = (f"continue the whole {'study' if _in_study() else 'sweep'} by "
                             f"re-typing its command (with -m) and resume={sweep_dir} "
                             f"appended")
    exp.on_eval = evaluation_hook()  # a tuning study's trial reports to its pruner
    text = summary_text if exp.solo else population_summary_text
    summary = exp.fit()
    try:
        print(text(exp.cfg, summary, exp.run_dir))
    except MetricsError as e:  # a metrics.jsonl damaged by another process meanwhile
        sys.exit(f"error: {e}")
    return summary  # a study's trial is scored on it (uabs_rl.tuning.trial.score)


# set (for the jobs of a sweep too) when the command line names the run folder: a name
# the user typed is theirs, one made from the clock (the default, ${now:...}) is not
_TYPED_DIR = "UABS_RL_TYPED_RUN_DIR"


def main() -> None:
    """Entry point of ``uabs-train``."""
    try:
        _check_paths(sys.argv[1:])
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    if any(a.split("=", 1)[0] in ("hydra.run.dir", "hydra.sweep.dir", "hydra.sweep.subdir")
           and "${now:" not in a for a in sys.argv[1:]):
        os.environ[_TYPED_DIR] = "1"
    sys.argv = [sys.argv[0], *_quote_resume(sys.argv[1:])]
    hydra_main("config", _run_and_report, pass_overrides=True, check=_check_job)


def _in_study() -> bool:
    """True in a job of a tuning study (the sweeper sets its trial number)."""
    from uabs_rl.tuning.trial import TRIAL_ENV

    return TRIAL_ENV in os.environ


def _check_job(composed) -> None:
    """A sweep's job's start-up checks, before any job of the sweep runs (a resumed
    job's settings are its run's, checked when it continues): those of its settings
    alone, not of the machine (its device and memory are the machine's the job runs
    on, a SLURM node's perhaps: checked there, as it starts)."""
    from uabs_rl.config import to_container
    from uabs_rl.training.startup import validate_settings

    cfg = to_container(composed)
    if not cfg.resume:
        validate_settings(cfg)


if __name__ == "__main__":
    main()
