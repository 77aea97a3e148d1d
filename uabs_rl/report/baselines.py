"""The report's evaluations on the test traces: each run's ``best.pt`` beside the
baselines under the same masks, the runs each Fig. 4 panel's baselines come from, and
the records keyed for the tables and figures."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from uabs_rl.evaluation.baselines import BASELINES, MPC, PLANNER, policy_label
from uabs_rl.runs.sweep import Grouping, Run


def evaluate_on_test(runs: list[Run], planner_runs: frozenset[Path] = frozenset(),
                     horizon: int = 1, mpc: int | None = None,
                     mpc_runs: frozenset[Path] = frozenset(), mpc_beam: int | None = None,
                     mpc_rounds: int | None = None, cache_dir: Path | None = None
                     ) -> dict[Path, dict[str, dict]]:
    """Each run's ``best.pt`` (chosen on validation) and the random, greedy and oracle
    baselines with the run's masks, on every window of the test traces (read from, or
    built into, ``cache_dir`` where given, else each run's ``traces.cache_dir``); for the
    runs in ``planner_runs`` also the receding-horizon planner of ``horizon``, for those
    in ``mpc_runs`` the deployable mpc of horizon ``mpc`` (constant velocity; ``mpc_beam``
    paths per first move, ``mpc_rounds`` passes over the fleet, default planner's; their
    cost per decision said on stderr)."""
    from uabs_rl.evaluation.load import POLICIES, evaluate_policies, load_evaluation
    from uabs_rl.traces import CacheFolderError

    out = {}
    for run in runs:
        try:
            ev = load_evaluation(run.path, "best", split="test", cache_dir=cache_dir)
        except CacheFolderError as e:
            # the folder a run recorded may be another machine's (a cluster's scratch)
            given = (f"--cache-dir {cache_dir}" if cache_dir is not None else
                     f"the trace cache {e.folder} (run {run.path}'s traces.cache_dir)"
                     if (run.config.get("traces") or {}).get("cache_dir") else
                     f"the trace cache {e.folder} ($UABS_RL_CACHE/traces, or "
                     f"~/.cache/uabs_rl/traces when unset)")
            raise CacheFolderError(f"{given} cannot hold the test traces here ({e.reason}): "
                                   f"give --cache-dir <a folder you can write in>.",
                                   e.folder, e.reason) from None
        policies = ((*POLICIES, *([PLANNER] if run.path in planner_runs else []),
                     *([MPC] if mpc is not None and run.path in mpc_runs else [])))
        out[run.path] = {k: rec for k, (rec, _) in
                         evaluate_policies(ev, policies, horizon=horizon,
                                           mpc_horizon=mpc or 1, beam=mpc_beam,
                                           rounds=mpc_rounds).items()}
        if PLANNER in out[run.path]:
            rec = out[run.path][PLANNER]
            print(f"planner H={horizon} on {run.path}: {rec['seconds'] / rec['windows']:.2f} "
                  f"s per window ({rec['windows']} windows)", file=sys.stderr)
        if MPC in out[run.path]:
            rec = out[run.path][MPC]
            print(f"{policy_label(MPC, mpc, 'cv', beam=rec['beam'], rounds=rec['rounds'])} "
                  f"on {run.path}: "
                  f"{rec['ms_per_decision']:.1f} ms per decision ({rec['windows']} windows)",
                  file=sys.stderr)
    return out


def _panel_run(grouping: Grouping, labels: list[str]) -> Run:
    """The run a panel's baselines come from: the lowest seed of its first group (the
    baselines depend on the masks and the scenario, not on the learner)."""
    return min(grouping.groups[labels[0]], key=lambda r: r.seed)


def panel_runs(grouping: Grouping) -> frozenset[Path]:
    """The runs the baselines (and the planner, once per Fig. 4 panel: it is
    deterministic and independent of the learner) are taken from."""
    return frozenset(_panel_run(grouping, labels).path for labels in grouping.panels().values())


def baselines_by_panel(grouping: Grouping,
                       tests: dict[Path, dict]) -> dict[str, dict[str, dict]]:
    """``{panel: {baseline: test record}}`` (:meth:`Grouping.panels`), from
    :func:`_panel_run`; the planner too where it ran."""
    out = {}
    for key, labels in grouping.panels().items():
        rec = tests[_panel_run(grouping, labels).path]
        out[key] = {name: rec[name] for name in (*BASELINES, MPC, PLANNER) if name in rec}
    return out


def masks_text(panel: str) -> str:
    mode, _, rest = panel.partition(", ")
    return f"{mode} masks" + (f", {rest}" if rest else "")


def baselines_on_test(grouping: Grouping, tests: dict[Path, dict]) -> dict[str, dict]:
    """The same records keyed ``"<baseline> (<mode> masks[, settings])"``, for tables."""
    return {f"{name} ({masks_text(key)})": rec
            for key, per in baselines_by_panel(grouping, tests).items()
            for name, rec in per.items()}


def learned_pg_on_test(groups: dict[str, list[Run]],
                       tests: dict[Path, dict]) -> dict[str, np.ndarray]:
    """[seeds, N] learned P_g(N̂_s) curves on the test traces, per group."""
    return {label: np.array([tests[run.path]["learned"]["pg_curve"] for run in runs])
            for label, runs in groups.items()}


def best_pg(runs: list[Run]) -> np.ndarray:
    """[seeds, N] P_g curves of each run's best validation evaluation."""
    return np.array([run.best_eval["pg_curve"] for run in runs])


def learned_record(run: Run, tests: dict[Path, dict] | None) -> dict:
    """The record the summary's served fraction and P_g come from: best.pt on the test
    traces when evaluated there, else the best validation evaluation."""
    return tests[run.path]["learned"] if tests else run.best_eval
