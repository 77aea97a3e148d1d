"""``uabs-report <study folder>``: a tuning study's best trials (a table), the parameter
importances and the optimisation history (figures), from its storage (the folder's
``study.yaml`` says where; ``study.db`` in the folder by default). Figures are drawn
with matplotlib (no plotly)."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

from uabs_rl.runs.sweep import ReportError
from uabs_rl.tuning.space import override_text
from uabs_rl.tuning.sweeper import STUDY_FILE

FILES = ("study.md", "trials.csv", "importances.png", "importances.pdf", "history.png",
         "history.pdf")


def is_study(folder: Path) -> bool:
    """True for the sweep folder of a tuning study; False for a path that cannot be a
    folder (too long a name, ...): the report's own checks then say why in one line."""
    try:
        return (Path(folder) / STUDY_FILE).is_file()
    except OSError:
        return False


def load_study(folder: Path, storage: str | None = None):
    """The study of a sweep folder (``storage`` in place of the one it names, e.g. for a
    database URL whose password ``study.yaml`` does not keep)."""
    import optuna
    from omegaconf import OmegaConf

    from uabs_rl.tuning.sweeper import open_storage

    rec = OmegaConf.load(Path(folder) / STUDY_FILE)
    url = storage or str(rec.storage)
    if "***" in url:
        raise ReportError(f"{folder}/{STUDY_FILE} names its storage without its password "
                          f"({url}): give the full URL with --storage.")
    try:
        return optuna.load_study(study_name=str(rec.study_name), storage=open_storage(url))
    except KeyError:
        raise ReportError(f"no study named {rec.study_name!r} in {url}: pass the sweep "
                          f"folder the study wrote, or its storage with --storage.") from None


def _value(v: Any) -> Any:
    """A trial's value of a setting as ``trials.csv`` keeps it: a number exactly (the
    tuned value, to paste), anything else as an override writes it."""
    return v if isinstance(v, (str, int, float)) else override_text(v)


def _shown(v: Any) -> str:
    """The same in ``study.md``'s table: 3 significant digits."""
    return f"{v:.3g}" if isinstance(v, float) else str(v)


def trial_rows(study) -> list[dict[str, Any]]:
    """Every finished trial, best first (complete trials by value, then pruned, then
    failed)."""
    from optuna.trial import TrialState

    sign = -1 if study.direction.name == "MAXIMIZE" else 1
    order = {TrialState.COMPLETE: 0, TrialState.PRUNED: 1, TrialState.FAIL: 2,
             TrialState.RUNNING: 3, TrialState.WAITING: 4}
    trials = sorted(study.get_trials(deepcopy=False),
                    key=lambda t: (order[t.state], sign * (t.value if t.value is not None
                                                           else math.inf), t.number))
    rows = []
    for t in trials:
        last = max(t.intermediate_values) if t.intermediate_values else None
        rows.append({"trial": t.number, "state": t.state.name.lower(),
                     "value": t.value, "episodes": last,
                     **{k: _value(v) for k, v in sorted(t.params.items())}})
    return rows


def markdown(study, rows: list[dict[str, Any]], top: int, importances: dict[str, float]
             ) -> str:
    params = sorted({k for r in rows for k in r} - {"trial", "state", "value", "episodes"})
    counts: dict[str, int] = {}
    for r in rows:
        counts[r["state"]] = counts.get(r["state"], 0) + 1
    complete = counts.get("complete", 0)
    shown = min(top, len(rows))
    lines = [f"# study {study.study_name}",
             "",
             f"{len(rows)} trials (" + ", ".join(f"{n} {s}" for s, n in counts.items())
             + "); objective: the best validation return of each trial's run (a "
               "population's mean over its members), to "
             + study.direction.name.lower(),
             "",
             # each value is one run's, and the best of many runs is the luckiest too
             ("The best trial's value is the best of "
              + (f"{complete} single runs" if complete != 1 else "one single run")
              + ": selection makes it high. Before relying on its settings, train "
                "them with several seeds (`uabs-train -m <its settings> "
                "seed=0,1,2,3,4`) and compare with `uabs-report`." if complete else
              "No trial completed: the study has no best settings.")
             + (f" Only {complete} trial{'s' * (complete != 1)} completed: too few to "
                "say which settings matter." if 0 < complete < 10 else ""),
             "",
             (f"## best {shown} trials" if shown <= complete else
              f"## {shown} trials: the {complete} complete ones, best first, then "
              f"the pruned and failed"),
             "",
             "| trial | state | validation R | last eval ep | " + " | ".join(params) + " |",
             "|---:|---|---:|---:|" + "---|" * len(params)]
    for r in rows[:top]:
        value = "" if r["value"] is None else f"{r['value']:.1f}"
        ep = "" if r["episodes"] is None else str(r["episodes"])
        lines.append(f"| {r['trial']} | {r['state']} | {value} | {ep} | "
                     + " | ".join(_shown(r.get(p, "")) for p in params) + " |")
    if importances:
        lines += ["", "## parameter importances (PED-ANOVA)", ""]
        lines += [f"- {k}: {v:.2f}" for k, v in importances.items()]
    return "\n".join(lines) + "\n"


def importance(study) -> dict[str, float]:
    """PED-ANOVA importances of the parameters (Optuna's default evaluator); empty with
    fewer than two complete trials (or no variation to explain)."""
    import optuna
    from optuna.trial import TrialState

    if len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))) < 2:
        return {}
    try:
        # PED-ANOVA, Optuna's default (fANOVA would need scikit-learn)
        return optuna.importance.get_param_importances(study)
    except (RuntimeError, ValueError):
        return {}


def figures(study, importances: dict[str, float], out: Path) -> list[Path]:
    """The optimisation history (each trial's value and the best so far) and the
    parameter importances, as PNG and PDF."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from optuna.trial import TrialState

    written = []
    done = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    pruned = study.get_trials(deepcopy=False, states=(TrialState.PRUNED,))
    fig, ax = plt.subplots(figsize=(6, 3.5))
    maximize = study.direction.name == "MAXIMIZE"
    if done:
        xs, ys = [t.number for t in done], [t.value for t in done]
        ax.plot(xs, ys, "o", color="C0", label="complete")
        best, run = [], None
        for y in ys:
            run = y if run is None else (max(run, y) if maximize else min(run, y))
            best.append(run)
        ax.step(xs, best, where="post", color="C1", label="best so far")
    if pruned:
        ax.plot([t.number for t in pruned], [t.value for t in pruned], "x", color="0.5",
                label="pruned (last report)")
    ax.set_xlabel("trial")
    ax.set_ylabel("validation return")
    ax.set_title("optimisation history")
    if done or pruned:
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no complete or pruned trial", ha="center", va="center",
                transform=ax.transAxes)
    fig.tight_layout()
    for ext in ("png", "pdf"):
        fig.savefig(out / f"history.{ext}")
        written.append(out / f"history.{ext}")
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 0.4 * max(len(importances), 2) + 1))
    if importances:
        names = list(importances)[::-1]
        ax.barh(names, [importances[n] for n in names], color="C0")
        ax.set_xlabel("importance (PED-ANOVA, normalised to sum 1)")
    else:
        ax.text(0.5, 0.5, "fewer than two complete trials", ha="center", va="center")
        ax.set_axis_off()
    ax.set_title("parameter importances")
    fig.tight_layout()
    for ext in ("png", "pdf"):
        fig.savefig(out / f"importances.{ext}")
        written.append(out / f"importances.{ext}")
    plt.close(fig)
    return written


def study_report(folder: Path, out: Path, storage: str | None = None, top: int = 10) -> str:
    """Write the study report into ``out``; return its Markdown text."""
    study = load_study(folder, storage)
    rows = trial_rows(study)
    if not rows:
        raise ReportError(f"the study in {folder} has no trial yet: report once one has "
                          f"run.")
    imp = importance(study)
    text = markdown(study, rows, top, imp)
    (out / "study.md").write_text(text)
    columns = list(dict.fromkeys(k for r in rows for k in r))
    with open(out / "trials.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns)
        w.writeheader()
        w.writerows(rows)
    figures(study, imp, out)
    return text
