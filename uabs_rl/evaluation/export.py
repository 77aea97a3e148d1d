"""Runs in marl-eval's JSON layout (instadeepai/marl-eval, the data format of its
README), so that this project's runs can be aggregated and plotted beside BenchMARL's and
Mava's with their tools (``uabs-report --export marl-eval``)::

    {env_name: {task_name: {algo_name: {"run_<seed>": {
        "step_<j>": {"step_count": int, metric: [one value per evaluation window]},
        ...,
        "absolute_metrics": {metric: [one value per window]}}}}}}

Here the environment is ``uabs_rl``; a task is a masking mode with the settings its
baselines depend on (scenario, channel, traces: a Fig. 4 panel, ``rank`` or ``rank,
scenario.n_uabs=6``); an algorithm is the learner with any other setting that sets its
group apart (``dqn3``, ``dqn3, algo.lr=0.001``); a run is a seed. The steps are the
periodic evaluations on the validation traces that every run of the group made,
``step_count`` the environment steps taken by then (per env times ``train.n_envs``); the
metrics are the return, served fraction and P_g(N̂_s) per evaluation window; the absolute
metrics are those of ``best.pt`` on every test window (or of the best validation
evaluation with ``--no-baselines``). The layout is written directly: the ``id-marl-eval``
package pins an old numpy.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from uabs_rl.runs.sweep import ENV_SETTINGS, Grouping, Run, _is

ENV_NAME = "uabs_rl"
# metric name in the export: (per-window key of an evaluation record, its mean's key)
METRICS = {"return": ("returns", "return"), "served_fraction": ("served_fractions",
                                                                 "served_fraction"),
           "pg": ("pgs", "pg")}
ABSOLUTE = "absolute_metrics"


def _per_window(record: dict) -> dict[str, list[float]]:
    """A record's metrics per window (a record older than per-window values: its mean)."""
    return {m: [float(v) for v in record.get(k, [record[mean]])]
            for m, (k, mean) in METRICS.items()}


def _algo_name(grouping: Grouping, label: str) -> str:
    s = grouping.groups[label][0].settings
    rest = [k for k in grouping.others if not _is(k, ENV_SETTINGS) and k != "algo.name"]
    return ", ".join(filter(None, [str(s["algo.name"]), grouping.values(label, rest)]))


def _run_entry(run: Run, episodes: list[int], absolute: dict) -> dict[str, Any]:
    n_envs = int(run.settings.get("train.n_envs", 1))
    by_episode = {r["episode"]: r for r in run.evals}
    out: dict[str, Any] = {}
    for j, episode in enumerate(episodes, start=1):
        rec = by_episode[episode]
        out[f"step_{j}"] = {"step_count": int(rec.get("env_steps", 0)) * n_envs,
                            **_per_window(rec)}
    out[ABSOLUTE] = _per_window(absolute)
    return out


def marl_eval(grouping: Grouping, tests: dict[Path, dict] | None = None) -> dict[str, Any]:
    """The runs of ``grouping`` in marl-eval's layout; the absolute metrics from
    ``tests[run.path]["learned"]`` (best.pt on the test traces) where given, else from
    each run's best validation evaluation."""
    tasks: dict[str, dict[str, Any]] = {}
    for task, labels in grouping.panels().items():
        for label in labels:
            runs = grouping.groups[label]
            episodes = sorted(set.intersection(*[{r["episode"] for r in run.evals}
                                                 for run in runs]))
            algo = tasks.setdefault(task, {}).setdefault(_algo_name(grouping, label), {})
            for run in runs:
                best = tests[run.path]["learned"] if tests else run.best_eval
                algo[f"run_{run.seed}"] = _run_entry(run, episodes, best)
    return {ENV_NAME: tasks}


def check_marl_eval(data: Any) -> None:
    """Raises ValueError naming the first place where ``data`` departs from marl-eval's
    layout: four levels of names, then steps (``step_count`` and lists of numbers) and
    ``absolute_metrics`` last, the same metrics in every step and the absolute metrics,
    and as many steps in every run of an algorithm."""
    def fail(where: str, what: str) -> None:
        raise ValueError(f"marl-eval layout, {where}: {what}")

    def numbers(where: str, values: Any) -> None:
        if not isinstance(values, list) or not values or not all(
                isinstance(v, int | float) and not isinstance(v, bool) for v in values):
            fail(where, "a metric must be a non-empty list of numbers")

    if not isinstance(data, dict) or not data:
        fail("top", "a non-empty object of environments")
    for env, tasks in data.items():
        for task, algos in _objects(env, tasks, fail):
            for algo, runs in _objects(f"{env}/{task}", algos, fail):
                lengths = set()
                for run, steps in _objects(f"{env}/{task}/{algo}", runs, fail):
                    where = f"{env}/{task}/{algo}/{run}"
                    if not isinstance(steps, dict) or list(steps)[-1:] != [ABSOLUTE]:
                        fail(where, f"the last entry must be {ABSOLUTE!r}")
                    metrics = set(steps[ABSOLUTE])
                    for step, values in steps.items():
                        if step == ABSOLUTE:
                            continue
                        if not isinstance(values, dict) or not isinstance(
                                values.get("step_count"), int):
                            fail(f"{where}/{step}", "a step needs an integer 'step_count'")
                        if set(values) - {"step_count"} != metrics:
                            fail(f"{where}/{step}", "its metrics differ from the absolute "
                                 "metrics'")
                    for step, values in steps.items():
                        for m, v in values.items():
                            if m != "step_count":
                                numbers(f"{where}/{step}/{m}", v)
                    lengths.add(len(steps))
                if len(lengths) > 1:
                    fail(f"{env}/{task}/{algo}", "its runs have different numbers of steps")


def _objects(where: str, value: Any, fail) -> list[tuple[str, Any]]:
    if not isinstance(value, dict) or not value:
        fail(where, "a non-empty object")
    return list(value.items())
