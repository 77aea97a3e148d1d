"""The study of ``uabs-train -m hydra/sweeper=optuna`` (docs/tuning.md): Optuna asks for
trials, each trial is one ``uabs-train`` job launched by Hydra's launcher (in this
process, or in parallel processes with ``hydra/launcher=local_parallel``, or on SLURM),
and the job's best validation return is told back.

The study lives in Optuna's RDB storage (``sqlite:///<sweep folder>/study.db`` unless
``hydra.sweeper.storage`` names another SQLAlchemy URL), which the jobs open too (they
report their periodic validation returns to the pruner). A study stopped in any way
continues when its command is re-typed with ``resume=<sweep folder>``: trials that
finished (complete, pruned or failed) are kept; a trial that was running when the study
stopped keeps its number and its values and its job continues its run folder from the
last checkpoint (the job's own ``resume``); only then are new trials asked for, up to
``n_trials`` in all. No trial is lost or run twice."""

from __future__ import annotations

import importlib.util
import logging
import math
import shutil
import sys
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from uabs_rl.config import ConfigError
from uabs_rl.runs.folder import RunLock
from uabs_rl.tuning.space import known_keys, search_space, trial_overrides
from uabs_rl.tuning.trial import TRIAL_ENV, TrialTask, make_pruner

log = logging.getLogger(__name__)

SAMPLERS = ("tpe", "random", "cmaes", "qmc")
# the settings of hydra.sweeper.sampler and .pruner that the study reads
SAMPLER_KEYS = ("name", "seed", "n_startup_trials")
PRUNER_KEYS = ("name", "n_startup_trials", "n_warmup_steps", "percentile", "lower", "upper")
STUDY_FILE = "study.yaml"  # in the sweep folder: where its study is (for uabs-report)


def make_sampler(spec: dict[str, Any], done: int):
    """The sampler ``hydra.sweeper.sampler`` names; its seed moves on by the trials the
    study already holds, so a resumed study draws new values, not the first session's."""
    import optuna

    name = str(spec.get("name", "tpe"))
    seed = spec.get("seed")
    seed = None if seed is None else int(seed) + done
    startup = int(spec.get("n_startup_trials", 10))
    if name == "tpe":
        return optuna.samplers.TPESampler(seed=seed, n_startup_trials=startup,
                                          constant_liar=True)
    if name == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    if name == "cmaes":
        return optuna.samplers.CmaEsSampler(seed=seed, n_startup_trials=startup)
    if name == "qmc":
        return optuna.samplers.QMCSampler(seed=seed)
    raise ConfigError(f"hydra.sweeper.sampler.name={name} is not a sampler: one of "
                      f"{', '.join(SAMPLERS)}.")


# the Python package of the default SQLAlchemy driver of each database
DRIVERS = {"postgresql": "psycopg2-binary", "mysql": "mysqlclient", "mariadb": "mysqlclient",
           "oracle": "oracledb", "mssql": "pyodbc"}


def open_storage(url: str):
    """Optuna's RDB storage at ``url``; a URL that names no database it can open is one
    line naming the setting."""
    import optuna

    try:
        return optuna.storages.RDBStorage(url)
    except ImportError:  # the database's driver: SQLAlchemy's dialect names it
        dialect = url.split(":", 1)[0]
        base, _, named = dialect.partition("+")  # mysql+pymysql://: the driver named
        driver = named or DRIVERS.get(base, "its SQLAlchemy driver")
        raise ConfigError(f"hydra.sweeper.storage={hidden(url)}: the {dialect} driver is not "
                          f"installed: pip install {driver}"
                          + ("" if named else f" (or name one in the URL: {base}+<driver>://)")
                          + ".") from None
    except Exception as e:  # sqlalchemy's and optuna's own errors, of many kinds
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise ConfigError(f"hydra.sweeper.storage={hidden(url)} cannot be opened ({first}): "
                          f"give a SQLAlchemy URL such as sqlite:////abs/path/study.db or "
                          f"postgresql://user@host/db, or leave it null (study.db in the "
                          f"sweep folder).") from None


def hidden(url: str) -> str:
    """``url`` with its password, if any, replaced by ``***``."""
    try:
        from sqlalchemy.engine import make_url

        return make_url(url).render_as_string(hide_password=True)
    except Exception:
        return url


def _flat(node: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(node, dict):
        out: dict[str, Any] = {}
        for k, v in node.items():
            out.update(_flat(v, f"{prefix}{k}."))
        return out or {prefix[:-1]: node}
    return {prefix[:-1]: node}


# a study stops when its first trials (this many, or more in a parallel batch) were all
# refused at start-up: a wrong fixed setting would refuse every one of its n_trials, and
# a search space that is wrong somewhere would let some of three random draws through
REFUSED_STOP = 3


def run_study(sweeper, arguments: list[str]) -> list[dict[str, Any]]:
    """Run (or continue) the study of a ``-m hydra/sweeper=optuna`` command line; a bad
    input is one line on stderr and exit status 2."""
    held: list[RunLock] = []  # the sweep folder's, for the study's life
    try:
        return _run_study(sweeper, arguments, held)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    finally:
        for lock in held:
            lock.release()


def _run_study(sweeper, arguments: list[str], held: list[RunLock]) -> list[dict[str, Any]]:
    import optuna
    from hydra.core.plugins import Plugins
    from optuna.trial import TrialState

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    s = OmegaConf.to_container(OmegaConf.create(sweeper.settings), resolve=True)
    config = sweeper.config
    task_cfg = OmegaConf.to_container(config, resolve=False)
    task_cfg.pop("hydra", None)
    space, fixed = search_space(s.get("params") or {}, arguments,
                                known_keys(_flat(task_cfg)))
    if not space:
        raise ConfigError("the search space is empty: give hydra.sweeper.params or a "
                          "sweep on the command line ('algo.lr=tag(log,interval(1e-5,1e-3))').")
    n_trials, n_jobs = int(s.get("n_trials", 30)), int(s.get("n_jobs", 1))
    if n_trials < 1 or n_jobs < 1:
        raise ConfigError(f"hydra.sweeper.n_trials={n_trials} and n_jobs={n_jobs} must be "
                          f"at least 1.")
    direction = str(s.get("direction", "maximize"))
    if direction not in ("maximize", "minimize"):
        raise ConfigError(f"hydra.sweeper.direction={direction}: maximize or minimize.")
    pruner, sampler = dict(s.get("pruner") or {}), dict(s.get("sampler") or {})
    for what, spec, known in (("sampler", sampler, SAMPLER_KEYS),
                              ("pruner", pruner, PRUNER_KEYS)):
        extra = sorted(set(spec) - set(known))
        if extra:  # added with +, which Hydra's own message suggests: else unread
            raise ConfigError(f"hydra.sweeper.{what}.{extra[0]} is not a setting of the "
                              f"{what}: its settings are {', '.join(known)} "
                              f"(docs/tuning.md).")
    make_pruner(pruner)  # a bad name, before anything is made
    make_sampler(sampler, 0)  # likewise
    sweep_dir = Path(str(config.hydra.sweep.dir)).absolute()
    resumed = any(w.split("=", 1)[0] == "resume" for w in fixed)
    # the highest folder of the sweep's path this command makes: removed with what it
    # holds if the study is refused before its trials, and only while this process holds
    # the lock (another that made it at the same moment, and won the lock, keeps it)
    made = next((p for p in (*reversed(sweep_dir.parents), sweep_dir) if not p.exists()),
                None)
    sweep_dir.mkdir(parents=True, exist_ok=True)
    try:
        # one process runs a study at a time: a second (its command re-typed with resume=
        # while it runs) would take its running trials for stopped ones and fail them
        lock = RunLock(sweep_dir)
        if not lock.acquire(record=False):  # its holder is named once the checks pass
            raise ConfigError(f"the study in {sweep_dir} is being run by another process "
                              f"({lock.holder()}): wait for it to end, or stop it (Ctrl-C there) "
                              f"and then resume it. Nothing was changed.")
        held.append(lock)
        if resumed:
            check_same_study(sweep_dir, space, fixed)
        db = sweep_dir / "study.db"  # the default storage
        url = s.get("storage") or f"sqlite:///{db}"
        # a resumed study is the one its folder records (a folder copied or moved keeps its
        # study's name, which the default, the folder's name, would not)
        recorded = kept = None  # the study's name and storage its study.yaml records
        if resumed and (sweep_dir / STUDY_FILE).is_file():
            try:
                record = OmegaConf.load(sweep_dir / STUDY_FILE)
                if isinstance(record, DictConfig):
                    if record.get("study_name") is not None and not s.get("study_name"):
                        recorded = str(record.study_name)
                    if record.get("storage") is not None:
                        kept = str(record.storage)
            except Exception:  # an unreadable record: the defaults
                recorded = kept = None
        # a study kept in another storage (a shared database), resumed without naming it,
        # or a folder whose default storage holds no study: refused before that storage is
        # opened (before: an empty study.db was made in the folder and the error said the
        # study was missing)
        bare = resumed and not s.get("storage")  # resumed without naming a storage
        elsewhere = bare and kept is not None and kept != hidden(url)
        retype = (f"re-type its command with hydra.sweeper.storage=<that URL"
                  f"{', its password in place of ***' if '***' in str(kept) else ''}> and "
                  f"resume= appended. Nothing was changed.")
        if bare and not db.exists():
            if elsewhere:
                raise ConfigError(f"resume={sweep_dir}: its study is kept in {kept} (its "
                                  f"{STUDY_FILE}), not in this folder: {retype}")
            what = "no study.db" if kept else f"neither study.db nor {STUDY_FILE}"
            raise ConfigError(f"resume={sweep_dir}: no study is kept there ({what}): pass the "
                              f"study's own sweep folder (for a study in another database, "
                              f"with its hydra.sweeper.storage=). Nothing was changed.")
        name = str(s.get("study_name") or recorded or sweep_dir.name)
        storage = open_storage(url)
        names = {st.study_name: st for st in optuna.get_all_study_summaries(storage)}
        if name in names and not resumed:
            raise ConfigError(f"a study named {name!r} is already in {hidden(url)}: continue "
                              f"it by re-typing its command with resume=<its sweep folder>, or "
                              f"name a new one with hydra.sweeper.study_name=<name>. Nothing "
                              f"was changed.")
        if resumed and name not in names:
            if elsewhere:  # a study.db the code before this check made there, empty
                raise ConfigError(f"resume={sweep_dir}: {hidden(url)} holds no study named "
                                  f"{name!r}, and its {STUDY_FILE} says it is kept in {kept}: "
                                  f"{retype}")
            raise ConfigError(f"resume={sweep_dir}: {hidden(url)} holds no study named {name!r} "
                              f"(it holds {', '.join(map(repr, names)) or 'none'}): pass the "
                              f"study's own folder, or name it with hydra.sweeper.study_name=.")
        if name in names and names[name].direction.name.lower() != direction:
            raise ConfigError(f"the study {name!r} in {hidden(url)} was made to "
                              f"{names[name].direction.name.lower()}, not {direction}: re-type "
                              f"its own command.")
        trials = (optuna.load_study(study_name=name, storage=storage).get_trials(deepcopy=False)
                  if name in names else [])
        if resumed:  # a study recorded before study.yaml kept its space: its trials'
            check_trial_space(sweep_dir, trials, space)
        finished = [t for t in trials if t.state.is_finished()]
        study = optuna.create_study(storage=storage, study_name=name, direction=direction,
                                    sampler=make_sampler(sampler, len(trials)),
                                    pruner=make_pruner(pruner), load_if_exists=True)
        OmegaConf.save(config, sweep_dir / "multirun.yaml")
        OmegaConf.save(OmegaConf.create({"storage": hidden(url), "study_name": name,
                                         "direction": direction, **study_record(space, fixed)}),
                       sweep_dir / STUDY_FILE)
        # trials that were running when the study stopped: same number, same values, and
        # their jobs continue their run folders (resume=)
        queue = [(t.number, t.params) for t in trials if t.state == TrialState.RUNNING]
        todo = n_trials - len(finished)
        log.info("study %s in %s: %d trials done, %d to continue, %d to run", name,
                 hidden(url), len(finished), len(queue), max(todo - len(queue), 0))
    except ConfigError:
        if made is not None and held:  # nothing of a study's: its storage refused it
            # the sweep folder (locked: this command's), then each parent it made while
            # empty (another process may have put a folder of its own beside it)
            shutil.rmtree(sweep_dir, ignore_errors=True)
            for parent in sweep_dir.parents:
                if parent == made.parent:
                    break
                try:
                    parent.rmdir()
                except OSError:  # not empty: no longer this command's alone
                    break
        raise
    lock.record()
    together = OmegaConf.select(config, "hydra.launcher.n_jobs")
    choices = OmegaConf.select(config, "hydra.runtime.choices") or {}
    if n_jobs > 1 and choices.get("hydra/launcher") == "basic":  # one job after another
        log.warning("hydra.sweeper.n_jobs=%d launches %d trials together, but Hydra's basic "
                    "launcher runs them one after another in this process: add "
                    "hydra/launcher=local_parallel hydra.launcher.n_jobs=%d to run them at "
                    "once", n_jobs, n_jobs, n_jobs)
    elif n_jobs == 1 and isinstance(together, int) and together != 1:
        log.warning("hydra.launcher.n_jobs=%s, but the study launches one trial at a time "
                    "(hydra.sweeper.n_jobs=1): set hydra.sweeper.n_jobs too to run trials "
                    "at once", together)
    launcher = Plugins.instance().instantiate_launcher(
        hydra_context=sweeper.hydra_context,
        task_function=TrialTask(sweeper.task_function, url, name, pruner), config=config)
    results: list[dict[str, Any]] = []
    job = 0
    while todo > 0:
        batch = []
        while len(batch) < min(n_jobs, todo):
            if queue:
                batch.append(queue.pop(0))
            else:
                trial = study.ask(space)
                batch.append((trial.number, trial.params))
        overrides = [[*fixed, *trial_overrides(params),
                      f"+hydra.job.env_set.{TRIAL_ENV}={number}",
                      f"hydra.sweep.subdir='trial={number}'"] for number, params in batch]
        numbers = [number for number, _ in batch]
        # Hydra labels the jobs #first, #first+1, ...: the trials' numbers where they
        # follow each other (after a resume they run on from the study's, not from 0)
        first = numbers[0] if numbers == list(range(numbers[0], numbers[0] + len(numbers))) \
            else job
        returns = launcher.launch(overrides, initial_job_idx=first)
        job += len(batch)
        todo -= len(batch)
        for (number, _), ret in zip(batch, returns, strict=True):
            results.append(_tell(study, number, ret))
        if todo > 0 and len(results) >= REFUSED_STOP and all(r.get("refused")
                                                               for r in results):
            raise ConfigError(
                f"the study stops: its first {len(results)} trials were refused before "
                f"their runs began (the error lines above), so a setting of the command "
                f"line, or a range of the search space, is wrong for the trials drawn; fix "
                f"it and start the study again in another sweep folder (these trials stay "
                f"in {hidden(url)} as failed, and count as done there).")
    _print_end(study, sweep_dir, url)
    trials = study.get_trials(deepcopy=False)
    if trials and all(t.state == TrialState.FAIL for t in trials):
        # nothing to report or go on from: a script that chains the study's report or a
        # re-training of its best settings must not carry on as after a success (a
        # study its pruner stopped everywhere ran as asked: its end says so, exit 0)
        print(f"error: every trial of the study failed ({len(trials)}; the 'trial N "
              f"failed' lines above say why): fix the settings and start the study again "
              f"in another sweep folder.", file=sys.stderr)
        sys.exit(1)
    return results


def study_record(space: dict[str, Any], fixed: list[str]) -> dict[str, Any]:
    """What a resumed study must share with its first session, as ``study.yaml`` keeps
    it: each setting of the search space with its distribution (Optuna's JSON), and the
    settings its trials share (the command line's others, less ``resume=``, Hydra's
    and those that cannot change results, as a plain sweep's resume compares them)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from optuna.distributions import distribution_to_json

    from uabs_rl.config import folder_name_excludes, override_key

    free = set(folder_name_excludes())
    words = [w for w in fixed if (key := override_key(w)) is not None
             and key != "resume" and key not in free and not key.startswith("hydra")]
    # as Hydra parses them: [32,32] and [32, 32] are one value
    shared = sorted(f"{o.get_key_element()}={o.get_value_element_as_str()}"
                    for o in OverridesParser.create().parse_overrides(overrides=words))
    return {"space": {k: distribution_to_json(d) for k, d in sorted(space.items())},
            "shared": shared}


def check_same_study(sweep_dir: Path, space: dict[str, Any], fixed: list[str]) -> None:
    """Refuse a resume whose search space or shared settings differ from those the study
    was started with (``study.yaml``; a study recorded before it kept them is not
    compared): Optuna fails on a changed choice after asking, leaving a trial half drawn,
    and other settings would mix two experiments in one study."""
    try:
        then = OmegaConf.to_container(OmegaConf.load(sweep_dir / STUDY_FILE))
    except Exception:  # no readable record: the storage's own checks decide
        return
    if not isinstance(then, dict) or "space" not in then or "shared" not in then:
        return
    now = study_record(space, fixed)
    said = []
    for key in sorted(set(then["space"]) | set(now["space"])):
        if then["space"].get(key) != now["space"].get(key):
            said.append(f"{key} ({_dist_text(then['space'].get(key))} then, "
                        f"{_dist_text(now['space'].get(key))} now)")
    gone = [w for w in then["shared"] if w not in now["shared"]]
    new = [w for w in now["shared"] if w not in then["shared"]]
    if gone or new:
        said.append("the settings the trials share (" + "; ".join(part for part in (
            f"then {' '.join(gone)}" if gone else "", f"now {' '.join(new)}" if new else "")
            if part) + ")")
    if said:
        raise other_study(sweep_dir, said)


def other_study(sweep_dir: Path, said: list[str]) -> ConfigError:
    """The refusal of a resume that differs from its study (``said``: what differs)."""
    return ConfigError(f"resume={sweep_dir} continues a study whose trials were drawn and "
                       f"run otherwise: {'; '.join(said)}. Re-type the study's own command "
                       f"with resume= appended (its search space and settings; n_trials, "
                       f"n_jobs and the launcher may change), or start the new one in "
                       f"another sweep folder. Nothing was changed.")


def check_trial_space(sweep_dir: Path, trials: list, space: dict[str, Any]) -> None:
    """Refuse a resume whose search space gives a setting another distribution than the
    study's trials were drawn from (Optuna keeps each trial's): what
    :func:`check_same_study` says of a study recorded before ``study.yaml`` kept it."""
    from optuna.distributions import distribution_to_json

    now = {k: distribution_to_json(d) for k, d in space.items()}
    for t in trials:
        for key, d in t.distributions.items():
            then = distribution_to_json(d)
            if key in now and now[key] != then:
                raise other_study(sweep_dir, [f"{key} ({_dist_text(then)} then, "
                                              f"{_dist_text(now[key])} now)"])


def _dist_text(text: str | None) -> str:
    """A distribution of ``study.yaml`` as a phrase: its kind and its values or range."""
    if text is None:
        return "not searched"
    from optuna.distributions import json_to_distribution

    d = json_to_distribution(text)
    if hasattr(d, "choices"):
        return f"choice({', '.join(map(str, d.choices))})"
    return f"{'log ' if getattr(d, 'log', False) else ''}interval({d.low:g}, {d.high:g})"


def _tell(study, number: int, ret) -> dict[str, Any]:
    """Tell the study how trial ``number``'s job ended."""
    from hydra.core.utils import JobStatus
    from optuna.trial import TrialState

    if ret.status != JobStatus.COMPLETED:  # an exception the job did not turn into a line
        err = ret._return_value
        print(f"trial {number} failed: {type(err).__name__}: {err}", file=sys.stderr)
        study.tell(number, state=TrialState.FAIL)
        return {"number": number, "value": None, "pruned_at": None, "failed": str(err)}
    res = ret.return_value
    if res["failed"]:
        print(f"trial {number} failed: {res['failed']}", file=sys.stderr)
        study.tell(number, state=TrialState.FAIL)
    elif res["pruned_at"] is not None:
        study.tell(number, state=TrialState.PRUNED)
    else:
        study.tell(number, res["value"])
    return res


def _print_end(study, sweep_dir: Path, url: str) -> None:
    import shlex

    from optuna.trial import TrialState

    done = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    counts = {s.name.lower(): len(study.get_trials(deepcopy=False, states=(s,)))
              for s in (TrialState.COMPLETE, TrialState.PRUNED, TrialState.FAIL)}
    lines = [f"\nstudy {study.study_name}: " + ", ".join(f"{n} {k}" for k, n in counts.items())]
    if done:
        best = study.best_trial
        value = f"{best.value:.1f}" if math.isfinite(best.value) else str(best.value)
        lines += [f"  best: trial {best.number}, validation return {value}",
                  "  " + " ".join(shlex.quote(o) for o in trial_overrides(best.params)),
                  f"  run folder: {sweep_dir / f'trial={best.number}'}"]
    else:
        lines.append("  no trial completed: the study has no best settings yet")
    q = shlex.quote(str(sweep_dir))
    # the tune extra installs the dashboard; the dev extra (optuna alone) does not
    install = ("" if importlib.util.find_spec("optuna_dashboard") is not None
               else " (pip install -e '.[tune]')")
    lines += ["next:",
              f"  uabs-report {q}   # best trials, parameter importances, history",
              f"  optuna-dashboard {shlex.quote(hidden(url))}   # the study in a browser"
              f"{install}"]
    print("\n".join(lines))
