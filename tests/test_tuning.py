"""The tuning sweeper (uabs-train -m hydra/sweeper=optuna, uabs_rl/tuning): studies of
experiment=smoke in a subprocess, with every open of a trace file recorded by an audit
hook, so that a study that read a test trace fails."""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

optuna = pytest.importorskip("optuna")

from tests.test_faults import QUIET, uabs_train, uabs_train_here  # noqa: E402
from uabs_rl.runs.checkpoint import load_checkpoint  # noqa: E402

# every file a process opens whose name is a cached trace set (<scenario>-<split>-<hash>.pt)
AUDIT = '''import os, sys
_log = os.environ["UABS_RL_TEST_OPENS"]
def _hook(event, args):
    if event == "open" and args and isinstance(args[0], (str, bytes, os.PathLike)):
        name = os.path.basename(os.fsdecode(args[0]))
        if name.endswith(".pt") and any(f"-{s}-" in name for s in ("train", "eval", "test")):
            with open(_log, "a") as f:
                f.write(name + "\\n")
sys.addaudithook(_hook)
'''


@pytest.fixture
def audited(tmp_path) -> dict[str, str]:
    """The environment of a subprocess whose trace-file opens go to tmp_path/opens.txt."""
    hook = tmp_path / "audit"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(AUDIT)
    path = os.pathsep.join([str(hook), os.environ.get("PYTHONPATH", ""), os.getcwd()])
    return {"PYTHONPATH": path, "UABS_RL_TEST_OPENS": str(tmp_path / "opens.txt")}


def opened(tmp_path: Path) -> list[str]:
    log = tmp_path / "opens.txt"
    return log.read_text().split() if log.is_file() else []


def study_args(trace_cache: Path, n: int, *extra: str) -> list[str]:
    # batch sizes within experiment=smoke's learning_starts (64)
    return ["-m", "hydra/sweeper=optuna", "experiment=smoke", f"traces.cache_dir={trace_cache}",
            *QUIET, f"hydra.sweeper.n_trials={n}", "algo.batch_size=choice(16,32)",
            "hydra.sweep.dir=study", *extra]


def load(tmp_path: Path, name: str = "study"):
    db = tmp_path / "study" / "study.db"
    return optuna.load_study(study_name=name, storage=f"sqlite:///{db}")


def eval_returns(run_dir: Path) -> list[float]:
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return [r["return"] for r in map(json.loads, lines) if r["kind"] == "eval"]


def episodes(run_dir: Path) -> list[int]:
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return [r["episode"] for r in map(json.loads, lines) if r["kind"] == "train"]


def finish(p: subprocess.Popen, timeout: float = 600) -> str:
    """The standard error and output of a study that succeeded."""
    out, err = p.communicate(timeout=timeout)
    assert p.returncode == 0, err[-3000:]
    return err + out


def test_a_killed_study_continues_with_resume_and_never_reads_a_test_trace(
        trace_cache, tmp_path, audited):
    args = study_args(trace_cache, 4)
    p = uabs_train(tmp_path, *args, env=audited)
    deadline = time.monotonic() + 600
    made = tmp_path / "study" / "study.yaml"
    while True:  # kill -9 once trial 2 is done
        assert p.poll() is None, p.communicate()[1][-3000:]
        assert time.monotonic() < deadline, "the study never finished 2 trials"
        # study.yaml: written once the study is in the database
        done = [t for t in load(tmp_path).get_trials(deepcopy=False)
                if t.state.is_finished()] if made.is_file() else []
        if len(done) >= 2:
            break
        time.sleep(0.2)
    p.send_signal(signal.SIGKILL)
    p.communicate()
    before = {t.number: t for t in load(tmp_path).get_trials()}
    first_ids = {n: load_checkpoint(tmp_path / "study" / f"trial={n}" / "checkpoints" /
                                    "last.pt")["run"]["id"]
                 for n, t in before.items() if t.state.is_finished()}
    assert len(first_ids) == 2
    err = finish(uabs_train(tmp_path, *args, f"resume={tmp_path / 'study'}", env=audited))
    trials = load(tmp_path).get_trials()
    assert [t.number for t in trials] == [0, 1, 2, 3]
    assert all(t.state == optuna.trial.TrialState.COMPLETE for t in trials), trials
    for n, t in before.items():  # finished trials kept; a running one kept its values
        assert trials[n].params == t.params
    for n, run_id in first_ids.items():  # never run again
        ckpt = load_checkpoint(tmp_path / "study" / f"trial={n}" / "checkpoints" / "last.pt")
        assert ckpt["run"]["id"] == run_id
        assert f"/trial={n}" not in err  # not launched again
    for t in trials:  # each ran its 6 episodes once; the objective is the best validation R
        run_dir = tmp_path / "study" / f"trial={t.number}"
        assert episodes(run_dir) == [1, 2, 3, 4, 5, 6]
        assert t.value == max(eval_returns(run_dir))
        assert t.value == load_checkpoint(run_dir / "checkpoints" / "best.pt")[
            "counters"]["best_eval"]
    names = opened(tmp_path)
    assert any("-eval-" in n for n in names)  # the hook saw the validation traces ...
    assert not [n for n in names if "-test-" in n]  # ... and never a test trace
    # the study's report: the best trials, the importances, the history
    from uabs_rl.cli.report import main as report

    assert report([str(tmp_path / "study")]) == 0
    text = (tmp_path / "study" / "report" / "study.md").read_text()
    assert "4 trials (4 complete)" in text and "parameter importances" in text
    best = max(trials, key=lambda t: t.value)
    lines = text.splitlines()
    first = lines[next(i for i, ln in enumerate(lines) if ln.startswith("|---")) + 1]
    assert first.startswith(f"| {best.number} | complete | {best.value:.1f} |")
    # a copy of the folder continues its own study (named after the first folder: it
    # once made a second, empty study named after the copy and ran its trials again)
    shutil.copytree(tmp_path / "study", tmp_path / "copy")
    again = [a for a in args if not a.startswith(("hydra.sweep.dir=", "hydra.sweeper.n_trials="))]
    err = finish(uabs_train(tmp_path, *again, "hydra.sweeper.n_trials=5",
                            f"resume={tmp_path / 'copy'}"))
    assert "4 trials done, 0 to continue, 1 to run" in err
    copied = optuna.load_study(study_name="study",
                               storage=f"sqlite:///{tmp_path / 'copy' / 'study.db'}")
    assert [t.number for t in copied.get_trials()] == [0, 1, 2, 3, 4]
    assert len(load(tmp_path).get_trials()) == 4  # the first folder's study untouched
    for name in ("history.png", "importances.png", "trials.csv"):
        assert (tmp_path / "study" / "report" / name).is_file()


def test_a_pruned_trial_stops_saving_its_checkpoint_and_a_population_scores_its_mean(
        trace_cache, tmp_path, audited):
    # a threshold no return reaches: each trial stops at its first evaluation (episode 3)
    args = study_args(trace_cache, 1, "hydra.sweeper.pruner.name=threshold",
                      "hydra.sweeper.pruner.lower=1e9", "train.population=2")
    out = finish(uabs_train(tmp_path, *args, env=audited))
    assert "trial 0 pruned at episode 3" in out and "0 complete, 1 pruned" in out
    (trial,) = load(tmp_path).get_trials()
    assert trial.state == optuna.trial.TrialState.PRUNED
    folder = tmp_path / "study" / "trial=0"
    bests = []
    for seed in (0, 1):
        member = folder / f"seed={seed}"
        assert episodes(member) == [1, 2, 3]
        assert load_checkpoint(member / "checkpoints" / "last.pt")["counters"]["episode"] == 3
        bests.append(max(eval_returns(member)))
    # the value of a pruned trial is its last report: the members' mean at episode 3
    assert trial.intermediate_values == {3: sum(bests) / 2}
    assert not [n for n in opened(tmp_path) if "-test-" in n]


def run_refused(tmp_path: Path, *args: str) -> str:
    p = uabs_train_here(tmp_path, *args)
    err = p.stderr
    assert p.returncode == 2, err[-3000:]
    lines = [ln for ln in err.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, err[-3000:]
    return lines[0]


def test_bad_study_inputs_are_one_line_naming_the_fix(trace_cache, tmp_path):
    line = run_refused(tmp_path, *study_args(trace_cache, 1, "algo.lrate=interval(0.1,1)"))
    assert "algo.lrate is not a setting" in line and "did you mean algo.lr" in line
    line = run_refused(tmp_path, *study_args(trace_cache, 1, "hydra.sweeper.storage=nosuch://x"))
    assert "hydra.sweeper.storage=nosuch://x cannot be opened" in line
    from uabs_rl.config import ConfigError
    from uabs_rl.tuning.sweeper import open_storage

    if importlib.util.find_spec("psycopg2") is None:  # the database's driver, named
        with pytest.raises(ConfigError, match=r"^hydra.sweeper.storage=postgresql://u:\*\*\*@"
                                              r"h/db: the postgresql driver is not installed: "
                                              r"pip install psycopg2-binary \(or name one"):
            open_storage("postgresql://u:pw@h/db")
    shared = f"sqlite:///{tmp_path / 'shared.db'}"
    optuna.create_study(study_name="mine", storage=shared)
    line = run_refused(tmp_path, *study_args(trace_cache, 1, f"hydra.sweeper.storage={shared}",
                                             "hydra.sweeper.study_name=mine"))
    assert "a study named 'mine' is already in" in line and "resume=" in line
    # a refused start leaves no folder it made (its parents included), and a folder that
    # was there as it was
    (tmp_path / "had").mkdir()
    (tmp_path / "had" / "notes.txt").write_text("mine\n")
    for where in ("new/a/b", "had"):
        line = run_refused(tmp_path, *(a.replace("=study", f"={where}") for a in study_args(
            trace_cache, 1, f"hydra.sweeper.storage={shared}", "hydra.sweeper.study_name=mine")))
        assert "a study named 'mine' is already in" in line
    assert not (tmp_path / "new").exists()
    assert sorted(p.name for p in (tmp_path / "had").iterdir()) == ["notes.txt"]
    # a folder another process put beside the sweep's meanwhile stays (before: the
    # highest folder this command made was removed, with what others had put in it)
    from uabs_rl.tuning import sweeper

    def beside_then_refuse(url):
        (tmp_path / "new2" / "a" / "theirs").mkdir(parents=True)
        raise ConfigError("refused")

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sweeper, "open_storage", beside_then_refuse)
        line = run_refused(tmp_path, *(a.replace("=study", "=new2/a/b") for a in study_args(
            trace_cache, 1)))
    assert line == "error: refused"
    assert (tmp_path / "new2" / "a" / "theirs").is_dir()
    assert not (tmp_path / "new2" / "a" / "b").exists()
    # a sampler setting added with + (as Hydra's own message suggests) was never read
    line = run_refused(tmp_path, *study_args(trace_cache, 1,
                                             "+hydra.sweeper.sampler.n_startup=3"))
    assert line == ("error: hydra.sweeper.sampler.n_startup is not a setting of the "
                    "sampler: its settings are name, seed, n_startup_trials "
                    "(docs/tuning.md).")
    # an unknown sampler is refused before its sweep folder is made
    line = run_refused(tmp_path, *(a.replace("=study", "=fresh") for a in study_args(
        trace_cache, 1, "hydra.sweeper.sampler.name=x")))
    assert "hydra.sweeper.sampler.name=x is not a sampler" in line
    assert not (tmp_path / "fresh").exists()
    assert not (tmp_path / "study" / "trial=0").exists()


def test_a_study_whose_trials_are_all_refused_at_start_up_stops_after_three(trace_cache,
                                                                           tmp_path):
    """A fixed setting every trial is refused for (``algo.gamma=2``): before, the study ran
    all its n_trials jobs, each refused, and a resume= after the fix had none left to run;
    now it stops after the first three with one error line naming the fix, exit 2."""
    p = uabs_train_here(tmp_path, *study_args(trace_cache, 10, "algo.gamma=2"))
    assert p.returncode == 2, p.stderr[-3000:]
    assert p.stderr.count("error: algo.gamma must be in [0, 1], got 2.0.") == 3
    last = [ln for ln in p.stderr.splitlines() if ln.startswith("error:")][-1]
    assert last.startswith("error: the study stops: its first 3 trials were refused before "
                           "their runs began")
    assert len(load(tmp_path).trials) == 3


def test_a_study_whose_trials_all_fail_ends_with_an_error_and_its_report_says_so(
        trace_cache, tmp_path, monkeypatch):
    """Every trial's run diverges after it started (not refused: the study goes on): the
    study ended with exit status 0 and "next: uabs-report", as if it had a best trial;
    now status 1 and one error line. Its report does not head failed trials "best", and
    draws its history without matplotlib's warning of a legend with nothing in it."""
    from tests.conftest import run_command
    from tests.test_value_faults import diverge_after

    diverge_after(monkeypatch, 20)
    p = uabs_train_here(tmp_path, *study_args(trace_cache, 2))
    assert p.returncode == 1, p.stderr[-3000:]
    assert "trial 0 failed" in p.stderr and "trial 1 failed" in p.stderr
    last = [ln for ln in p.stderr.splitlines() if ln.startswith("error:")][-1]
    assert last.startswith("error: every trial of the study failed (2;")
    assert [t.state for t in load(tmp_path).trials] == [optuna.trial.TrialState.FAIL] * 2
    r = run_command("report", "study", cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    text = (tmp_path / "study" / "report" / "study.md").read_text()
    assert "## best" not in text
    assert "## 2 trials: the 0 complete ones, best first, then the pruned and failed" in text
    assert "No trial completed: the study has no best settings." in text
    assert "best of 0" not in text and "Only 0 trials" not in text
    assert "No artists with labels" not in r.stderr + r.stdout


def test_a_resumed_study_is_its_own_command_and_one_process_runs_it(trace_cache, tmp_path):
    """A resume= that would mix two studies in one is refused before anything changes
    (before: a changed choice() left a half-drawn trial and a traceback; another fixed
    setting ran new trials of another experiment and overwrote multirun.yaml; without
    the sweeper Hydra ran a grid in the study's folder; a second process beside a
    running study failed its running trial and crashed the first). n_trials may grow.
    A trial whose last evaluation the pruner would stop completes (its budget is spent);
    trials.csv keeps the tuned values exactly."""
    from uabs_rl.runs.folder import RunLock

    args = study_args(trace_cache, 1, "train.episodes=3", "algo.lr=interval(1e-4,1e-3)",
                      "hydra.sweeper.pruner.name=threshold", "algo.hidden=[32,32]",
                      "hydra.sweeper.pruner.lower=1e9")
    p = uabs_train_here(tmp_path, *args)
    assert p.returncode == 0, p.stderr[-3000:]
    # the threshold stops every trial at its first evaluation, but that is its last
    assert "1 complete, 0 pruned" in p.stdout + p.stderr
    study = tmp_path / "study"
    record = {f: (study / f).read_bytes() for f in ("multirun.yaml", "study.yaml")}
    resume = f"resume={study}"

    def refused(*argv: str) -> str:
        return run_refused(tmp_path, *argv)

    line = refused(*[a.replace("choice(16,32)", "choice(16,24)") for a in args], resume)
    assert line.startswith(f"error: resume={study} continues a study whose trials were "
                           f"drawn and run otherwise: algo.batch_size (choice(16, 32) then, "
                           f"choice(16, 24) now)"), line
    # a study recorded before study.yaml kept its space: the trials' own distributions
    old = study / "study.yaml"
    kept = old.read_text()
    old.write_text("".join(ln for ln in kept.splitlines(keepends=True)
                           if ln.startswith(("storage:", "study_name:", "direction:"))))
    line = refused(*[a.replace("choice(16,32)", "choice(16,24)") for a in args], resume)
    assert "algo.batch_size (choice(16, 32) then, choice(16, 24) now)" in line, line
    old.write_text(kept)
    line = refused(*[a.replace("train.episodes=3", "train.episodes=9") for a in args], resume)
    assert "the settings the trials share (then train.episodes=3; now train.episodes=9)" in line
    line = refused(*[a for a in args if not a.startswith("hydra/sweeper=optuna")
                     and not a.startswith("hydra.sweeper.")], resume)
    assert line == (f"error: resume={study} holds a tuning study (its study.yaml): re-type "
                    f"the study's own command, hydra/sweeper included, with {resume} "
                    f"appended. Nothing was changed.")
    lock = RunLock(study)  # the study's own process, still running
    assert lock.acquire()
    try:
        line = refused(*args, resume)
    finally:
        lock.release()
    assert line.startswith(f"error: the study in {study} is being run by another process "
                           f"(pid {os.getpid()} on ")
    assert len(load(tmp_path).trials) == 1 and not (study / "trial=1").exists()
    # a process that made the folder at the same moment as the study's own, and lost its
    # lock, leaves the folder to it (before: it removed the folder, study and all)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(RunLock, "acquire", lambda self, record=True: False)
        line = refused(*(a.replace("=study", "=race") for a in args))
    assert "is being run by another process" in line and (tmp_path / "race").is_dir()
    assert record == {f: (study / f).read_bytes() for f in record}  # nothing changed
    # the study's command, with more trials launched two at a time; a setting typed
    # with other spaces is the same setting
    more = [a.replace("n_trials=1", "n_trials=2").replace("[32,32]", "[32, 32]")
            for a in args]
    p = uabs_train_here(tmp_path, *more, "hydra.sweeper.n_jobs=2", resume)
    assert p.returncode == 0, p.stderr[-3000:]
    assert ("hydra.sweeper.n_jobs=2 launches 2 trials together, but Hydra's basic launcher "
            "runs them one after another") in p.stderr + p.stdout
    trials = load(tmp_path).trials
    assert [t.state for t in trials] == [optuna.trial.TrialState.COMPLETE] * 2
    from uabs_rl.cli.report import main as report

    assert report([str(study)]) == 0
    with open(study / "report" / "trials.csv") as f:
        rows = {int(r["trial"]): float(r["algo.lr"]) for r in csv.DictReader(f)}
    assert rows == {t.number: t.params["algo.lr"] for t in trials}


def test_search_space_overrides_as_distributions():
    from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution

    from uabs_rl.config import ConfigError
    from uabs_rl.tuning.space import search_space, trial_overrides

    known = {"algo.lr", "algo.hidden", "algo.n_step", "algo.batch_size", "masking", "seed"}
    space, fixed = search_space(
        {"algo.lr": "tag(log, interval(1e-5, 1e-2))", "algo.hidden": "choice([64, 64], [128])",
         "algo.n_step": "range(1, 6, 2)"},
        ["masking=flat,rank", "seed=3", "algo.n_step=1"], known)
    assert space == {"algo.lr": FloatDistribution(1e-5, 1e-2, log=True),
                     "algo.hidden": CategoricalDistribution(["[64, 64]", "[128]"]),
                     "masking": CategoricalDistribution(["flat", "rank"])}
    assert fixed == ["seed=3", "algo.n_step=1"]  # a value typed pins the setting
    space, _ = search_space({"algo.n_step": "range(1, 6, 2)"}, [], known)
    assert space["algo.n_step"] == IntDistribution(1, 5, step=2)
    assert trial_overrides({"algo.lr": 1e-4, "algo.hidden": "[64, 64]"}) == [
        "algo.hidden=[64, 64]", "algo.lr=0.0001"]
    with pytest.raises(ConfigError, match="needs low < high and low > 0"):
        search_space({"algo.lr": "tag(log, interval(0, 1))"}, [], known)


@pytest.mark.slow
def test_parallel_trials_share_the_storage(trace_cache, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    finish(uabs_train(tmp_path, *study_args(trace_cache, 2, "hydra.sweeper.n_jobs=2",
                                            "hydra/launcher=local_parallel",
                                            "hydra.launcher.n_jobs=2")))
    trials = load(tmp_path).get_trials()
    assert [t.state for t in trials] == [optuna.trial.TrialState.COMPLETE] * 2
    for t in trials:
        assert t.value == max(eval_returns(tmp_path / "study" / f"trial={t.number}"))
        assert t.intermediate_values  # reported from the worker processes


def test_a_study_in_a_shared_storage_resumed_without_it_is_refused_naming_it(
        trace_cache, tmp_path):
    """A study kept in a database of its own (hydra.sweeper.storage=) and resumed without
    it is refused, naming the storage its study.yaml records, and nothing is made (before:
    an empty study.db appeared in the folder and the error said the study was missing);
    with the storage re-typed it continues."""
    shared = f"sqlite:///{tmp_path / 'shared.db'}"
    args = study_args(trace_cache, 1, "train.episodes=3", "algo.hidden=[32,32]",
                      f"hydra.sweeper.storage={shared}")
    finish(uabs_train(tmp_path, *args))
    study = tmp_path / "study"
    before = {p.name: p.read_bytes() for p in study.iterdir() if p.is_file()}
    without = [a for a in args if not a.startswith("hydra.sweeper.storage")]
    line = run_refused(tmp_path, *without, f"resume={study}")
    retype = ("re-type its command with hydra.sweeper.storage=<that URL> and resume= "
              "appended. Nothing was changed.")
    assert line == (f"error: resume={study}: its study is kept in {shared} (its study.yaml), "
                    f"not in this folder: {retype}"), line
    assert {p.name: p.read_bytes() for p in study.iterdir() if p.is_file()} == before
    assert "study.db" not in before and "multirun.yaml" in before
    # a folder where the code before this check had left an empty study.db
    optuna.storages.RDBStorage(f"sqlite:///{study / 'study.db'}")
    line = run_refused(tmp_path, *without, f"resume={study}")
    assert line == (f"error: resume={study}: sqlite:///{study / 'study.db'} holds no study "
                    f"named 'study', and its study.yaml says it is kept in {shared}: "
                    f"{retype}"), line
    err = finish(uabs_train(tmp_path, *args, f"resume={study}"))
    assert "1 trials done, 0 to continue, 0 to run" in err
    # a sweep's folder that holds no study (a grid's): refused, nothing made in it
    grid = tmp_path / "grid"
    grid.mkdir()
    shutil.copy(study / "multirun.yaml", grid)
    line = run_refused(tmp_path, *without, f"resume={grid}")
    assert line == (f"error: resume={grid}: no study is kept there (neither study.db nor "
                    f"study.yaml): pass the study's own sweep folder (for a study in another "
                    f"database, with its hydra.sweeper.storage=). Nothing was changed."), line
    assert [p.name for p in grid.iterdir()] == ["multirun.yaml"]
    # a study in the folder's own study.db, that file gone: refused the same way
    (grid / "study.yaml").write_text(f"storage: sqlite:///{grid / 'study.db'}\n"
                                     f"study_name: grid\ndirection: maximize\n")
    line = run_refused(tmp_path, *without, f"resume={grid}")
    assert line.startswith(f"error: resume={grid}: no study is kept there (no study.db): "), line
    assert sorted(p.name for p in grid.iterdir()) == ["multirun.yaml", "study.yaml"]
