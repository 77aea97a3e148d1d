"""The job side of a study: one trial is one ``uabs-train`` job. :class:`TrialTask`
wraps the Hydra task so that the job reports its periodic validation returns to the
trial (:func:`evaluation_hook`, the training loop's per-evaluation callback), stops when
the pruner says so, and hands the sweeper its objective (:func:`score`).

Imported by every ``uabs-train`` run: light (Optuna is imported by a trial only)."""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from uabs_rl.config import ConfigError

log = logging.getLogger(__name__)

# the trial a job runs (set per job by the sweeper through hydra.job.env_set)
TRIAL_ENV = "UABS_RL_TRIAL"
# exit statuses of a job that was stopped by the user, not by its settings: they stop
# the study (Ctrl-C, SIGTERM, SIGHUP) and the trial is continued on resume=
STOPPED = (129, 130, 143)


def score(summary: dict[str, Any]) -> float:
    """A run's objective: its best validation return (the evaluation ``best.pt`` was
    saved at); a population's mean over its members. Never a test figure."""
    values = [float(m["best_eval_return"]) for m in summary["members"]]
    return sum(values) / len(values)


@dataclass
class Reporter:
    """Reports a job's validation returns to its trial; says when to stop (pruned)."""

    storage: str
    study_name: str
    number: int
    pruner: dict[str, Any]
    pruned_at: int | None = None
    _trial: Any = field(default=None, repr=False)

    def trial(self):
        if self._trial is None:
            import optuna

            study = optuna.load_study(study_name=self.study_name, storage=self.storage,
                                      pruner=make_pruner(self.pruner))
            trial_id = study._storage.get_trial_id_from_study_id_trial_number(
                study._study_id, self.number)
            self._trial = optuna.trial.Trial(study, trial_id)
        return self._trial

    def __call__(self, episode: int, returns: list[float], last: bool = False) -> bool:
        """After an evaluation at ``episode``: report the members' mean validation
        return; True (stop training, the checkpoint is saved) when the pruner stops the
        trial. At the run's ``last`` evaluation its budget is spent: nothing is saved
        by stopping it, and it completes (a pruned trial would leave the best trials
        and the importances)."""
        import warnings

        trial = self.trial()
        with warnings.catch_warnings():  # a resumed trial reports its last step again
            warnings.simplefilter("ignore")
            trial.report(sum(returns) / len(returns), episode)
        if not last and trial.should_prune():
            self.pruned_at = episode
            log.info("trial %d pruned at episode %d: its validation return is below the "
                     "other trials' at this point; its checkpoint is saved", self.number,
                     episode)
            return True
        return False


_current: Reporter | None = None


def evaluation_hook() -> Callable[[int, list[float], bool], bool] | None:
    """The per-evaluation callback of this job's trial, or None outside a study."""
    return _current


def refused_at_start() -> bool:
    """True when this job ended before its run began: its folder holds no
    ``metrics.jsonl`` (the start-up checks pass before anything is written), so its
    settings, not its training, failed."""
    from hydra.core.hydra_config import HydraConfig

    from uabs_rl.runs.layout import RunFolder

    try:
        out = HydraConfig.get().runtime.output_dir
    except ValueError:  # outside a Hydra job
        return False
    return not RunFolder(out).metrics.exists()


@dataclass
class TrialTask:
    """The Hydra task of a study's jobs: runs ``task`` (``uabs-train``'s) as trial
    ``$UABS_RL_TRIAL`` and returns ``{"number", "value", "pruned_at", "failed"}`` (and
    ``"refused"`` for a failed one: refused before its run began). A job that fails on
    its settings (a diverging run, exit status 2) is a failed trial and the study goes
    on; one stopped by the user stops the study."""

    task: Callable[[Any], Any]
    storage: str
    study_name: str
    pruner: dict[str, Any]

    def __call__(self, cfg) -> dict[str, Any]:
        global _current
        number = int(os.environ[TRIAL_ENV])
        _current = reporter = Reporter(self.storage, self.study_name, number, self.pruner)
        try:
            summary = self.task(cfg)
        except SystemExit as e:
            if e.code in STOPPED:
                raise
            return {"number": number, "value": None, "pruned_at": None,
                    "failed": f"the job stopped with status {e.code} (its error line "
                              f"above)", "refused": refused_at_start()}
        finally:
            _current = None
        if summary is None:  # a parallel study's job stopped by a signal: its launcher
            return {"number": number, "value": None, "pruned_at": None,  # stops the study
                    "failed": "stopped"}
        value = score(summary)
        return {"number": number, "value": value if math.isfinite(value) else None,
                "pruned_at": reporter.pruned_at,
                "failed": None if math.isfinite(value) else "no validation return"}


PRUNERS = ("median", "percentile", "hyperband", "threshold", "none")


def make_pruner(spec: dict[str, Any]):
    """The pruner ``hydra.sweeper.pruner`` names (``name`` and its settings)."""
    import optuna

    name = str(spec.get("name", "median"))
    startup, warmup = int(spec.get("n_startup_trials", 5)), int(spec.get("n_warmup_steps", 0))
    if name == "median":
        return optuna.pruners.MedianPruner(n_startup_trials=startup, n_warmup_steps=warmup)
    if name == "percentile":
        return optuna.pruners.PercentilePruner(float(spec.get("percentile", 25.0)),
                                               n_startup_trials=startup,
                                               n_warmup_steps=warmup)
    if name == "threshold":
        lower, upper = spec.get("lower"), spec.get("upper")
        if lower is None and upper is None:
            raise ConfigError("hydra.sweeper.pruner.name=threshold needs pruner.lower or "
                              "pruner.upper: the validation return below (above) which a "
                              "trial stops.")
        return optuna.pruners.ThresholdPruner(
            lower=None if lower is None else float(lower),
            upper=None if upper is None else float(upper), n_warmup_steps=warmup)
    if name == "hyperband":
        return optuna.pruners.HyperbandPruner()
    if name == "none":
        return optuna.pruners.NopPruner()
    raise ConfigError(f"hydra.sweeper.pruner.name={name} is not a pruner: one of "
                      f"{', '.join(PRUNERS)}.")
