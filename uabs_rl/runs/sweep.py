"""The runs of a sweep (or of any folders) as ``uabs-report`` sees them: found on disk
(following symbolic links), read (metrics and the config stored in ``last.pt``), and
grouped by every setting that changes results, so that each group holds the seeds of
one experiment and is named by what sets it apart from the others."""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from functools import cache, cached_property
from pathlib import Path
from typing import Any

from uabs_rl.config import MaskingMode, default_settings, keys_with_role
from uabs_rl.config.roles import BASELINE_ROLES, NEUTRAL_ROLES
from uabs_rl.runs.layout import METRICS, RunFolder
from uabs_rl.runs.metrics import read_metrics

MODES = tuple(m.value for m in MaskingMode)

# settings that do not change results: never a reason to tell runs apart (the seed is
# what a group's runs differ in; their roles: uabs_rl.config.roles)
NEUTRAL = keys_with_role(*NEUTRAL_ROLES)
# settings the baselines depend on (what uabs-eval may change, and the start positions
# of evaluations): groups that differ in one of them get their own Fig. 4 panel
ENV_SETTINGS = keys_with_role(*BASELINE_ROLES)


class ReportError(ValueError):
    """An input ``uabs-report`` cannot use: one line on stderr, exit status 2."""


def fmt_value(v: Any) -> str:
    """A setting's value as typed on the command line (``true``, ``null``, ``0.001``);
    a family of cities by their names (``scenario+blocks60+...``, ``none`` when empty:
    ``{}`` is the run's scenario)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, list) and all(isinstance(c, dict) for c in v):
        return "+".join(str(c.get("name", "scenario")) for c in v) or "none"
    return "null" if v is None else str(v)


def _is(key: str, prefixes: tuple[str, ...]) -> bool:
    return any(key == p or key.startswith(p if p.endswith(".") else p + ".")
               for p in prefixes)


@dataclass
class Run:
    path: Path
    mode: str
    seed: int
    episodes_planned: int
    train: list[dict]
    evals: list[dict]
    config: dict

    @cached_property
    def settings(self) -> dict[str, Any]:
        """Every setting that changes results, flat (``{"algo.lr": 1e-4, ...}``), in
        today's keys: settings added since the run was written get their defaults,
        except ``masking.recoverable``, absent from runs written when the paper's
        literal masks were the only ones (so false)."""
        from uabs_rl.runs.checkpoint import (
            CheckpointError,
            config_dict,
            config_from_checkpoint,
            flatten,
        )

        stored = dict(self.config)
        if isinstance(stored.get("masking"), dict) and "recoverable" not in stored["masking"]:
            stored["masking"] = {**stored["masking"], "recoverable": False}
        try:
            full = flatten(config_dict(config_from_checkpoint({"config": stored})))
        except CheckpointError as e:
            ckpt = RunFolder(self.path).last
            raise CheckpointError(e if str(ckpt) in str(e) else f"{ckpt}: {e}") from None
        # in the schemas' order; config_from_checkpoint gives the run its learner's schema
        # (its own settings, algo.mixing_embed_dim of qmix, with their defaults where the
        # run was written before they existed; another learner's are not the run's)
        return {k: full[k] for k in default_settings() if k in full and not _is(k, NEUTRAL)}

    @property
    def label(self) -> str:
        """The run's settings named against the defaults (the ``config`` column of
        ``learned_vs_baselines.csv``, comparable across reports; the masking mode and
        M have their own columns): see :func:`describe`."""
        return describe(self.settings, skip=("masking.mode", "scenario.n_uabs"))

    @property
    def complete(self) -> bool:
        return bool(self.train) and self.train[-1]["episode"] >= self.episodes_planned

    @property
    def best_eval(self) -> dict:
        return max(self.evals, key=lambda r: r["return"])


def describe(settings: dict[str, Any], skip: tuple[str, ...] = (), words: bool = True) -> str:
    """Settings against the defaults: the observation (``paper``, ``lookahead``,
    ``lookahead+motion``, ``egocentric`` or ``egocentric-static`` (without the motion
    map); ``paper`` is left out when the scenario, channel or traces differ from the
    paper's too), ``-literal`` for the paper's literal masks, then every other setting
    that differs from its default (``lookahead algo.lr=0.0003``), three or more of one
    section as ``algo.{hidden=[32, 32], batch_size=32, ...}``. With ``words=False``,
    settings only (``obs.lookahead=true``), "" for none."""
    defaults = default_settings()
    obs = ("obs.frame", "obs.lookahead", "obs.motion", "masking.recoverable")
    keys = [k for k, v in settings.items()
            if k not in skip and (k not in obs or not words) and v != defaults.get(k)]
    train_first = ("train.n_envs", "train.episodes")  # as reports have named them
    keys.sort(key=lambda k: (k.startswith("train."), k not in train_first,
                             train_first.index(k) if k in train_first else 0))
    ego = settings.get("obs.frame") == "egocentric"
    word = ("egocentric" + ("" if settings.get("obs.motion") else "-static") if ego else
            "lookahead+motion" if settings.get("obs.motion") else
            "lookahead" if settings.get("obs.lookahead") else
            "" if any(_is(k, ("scenario", "channel", "traces")) for k in keys) else "paper")
    if settings.get("masking.recoverable") is False:
        word = (word or "paper") + "-literal"
    parents: dict[str, list[str]] = {}
    for k in keys:
        parents.setdefault(k.rsplit(".", 1)[0] if "." in k else "", []).append(k)
    parts = [word] if word and words else []
    for parent, ks in parents.items():
        if len(ks) >= 3 and parent:
            inner = ", ".join(f"{k[len(parent) + 1:]}={fmt_value(settings[k])}" for k in ks)
            parts.append(f"{parent}.{{{inner}}}")
        else:
            parts += [f"{k}={fmt_value(settings[k])}" for k in ks]
    return " ".join(parts) or ("paper" if words else "")


def _metrics_files(root: Path) -> list[Path]:
    """Every metrics.jsonl under ``root``, following symbolic links to folders (each real
    folder visited once, so a link cycle ends)."""
    found, seen = [], set()
    for here, dirs, files in os.walk(root, followlinks=True):
        real = os.path.realpath(here)
        if real in seen:
            dirs[:] = []
            continue
        seen.add(real)
        dirs.sort()
        if METRICS in files:
            found.append(RunFolder(here).metrics)
    return sorted(found)


def _load_run(metrics: Path) -> Run | str:
    """The run of a metrics.jsonl, or why it cannot be reported (no checkpoint yet, no
    evaluation yet)."""
    from uabs_rl.runs.checkpoint import check_own, load_checkpoint

    run_dir = metrics.parent
    ckpt = RunFolder(run_dir).last
    if not ckpt.is_file():
        return f"{run_dir} has no checkpoints/last.pt yet (stopped before its first checkpoint?)"
    state = load_checkpoint(ckpt)
    check_own(state, run_dir, ckpt)  # a last.pt copied in from another run is refused
    cfg = state["config"]
    recs = read_metrics(metrics)
    evals = [r for r in recs if r["kind"] == "eval"]
    if not evals:
        return (f"{run_dir} has no evaluation yet (one every train.eval_every = "
                f"{cfg['train']['eval_every']} episodes)")
    return Run(run_dir, cfg["masking"]["mode"], int(cfg["seed"]), int(cfg["train"]["episodes"]),
               [r for r in recs if r["kind"] == "train"], evals, cfg)


def find_runs(*roots: Path) -> list[Run]:
    """Every run under the folders ``roots`` (a folder with metrics.jsonl and
    checkpoints/last.pt), each once however it is reached; runs with no evaluation yet
    are left out with a warning line each, and refused (one line) when none is left."""
    runs, skipped, seen = [], [], set()
    for root in map(Path, roots):
        if not root.is_dir():
            key = str(root).split("=", 1)[0] if "=" in str(root) else ""
            setting = bool(key) and "/" not in key and key.replace(".", "").isidentifier()
            advice = (" (give the trace cache with --cache-dir)" if key == "traces.cache_dir"
                      else f": to evaluate runs under {root}, use uabs-eval <run> {root} (one "
                           f"run) or python benchmarks/generalization.py <runs> --at "
                           f"<scenario>:<M> (several runs, cities and fleets)")
            raise ReportError(
                f"{root} is not a folder: pass a run folder or a folder of runs (such as "
                f"outputs/multirun/<date_time>)"
                + (f". uabs-report takes no settings{advice}" if setting else "") + ".")
        for metrics in _metrics_files(root):
            real = os.path.realpath(metrics.parent)
            if real not in seen:
                seen.add(real)
                run = _load_run(metrics)
                (runs if isinstance(run, Run) else skipped).append(run)
    where = " or ".join(map(str, roots))
    if not runs and skipped:
        more = f" (and {len(skipped) - 1} more like it)" if len(skipped) > 1 else ""
        raise ReportError(f"nothing to report under {where}: {skipped[0]}{more}. Report "
                          f"once a run has evaluated, or pass other folders.")
    if not runs:
        raise ReportError(f"no run under {where}: a run folder holds metrics.jsonl and "
                          f"checkpoints/last.pt. Pass the folder uabs-train printed, or a "
                          f"folder above several runs.")
    for why in skipped:
        print(f"warning: {why}: left out", file=sys.stderr)
    return runs


# ----------------------------------------------------------------------------- groups
@dataclass
class Grouping:
    """Runs grouped by their settings: ``groups[label]`` the runs of one set of settings
    (sorted by seed), ``varied`` the settings that differ between groups, ``common`` the
    settings every run shares."""

    groups: dict[str, list[Run]]
    varied: list[str]
    common: dict[str, Any]

    @property
    def by_mode_only(self) -> bool:
        """True when the groups differ in the masking mode alone (or there is one)."""
        return set(self.varied) <= {"masking.mode"}

    def mode(self, label: str) -> str:
        return self.groups[label][0].mode

    @property
    def compared(self) -> str:
        """The varied settings in words: each by its key, except those a scenario's own
        file sets wherever they vary with the scenario (:func:`_label_keys` leaves them
        out of every label), said once as "what each scenario sets"."""
        named = {k for runs in self.groups.values()
                 for k in _label_keys(self.varied, runs[0].settings)}
        shown = [k for k in self.varied if k in named]
        left = len(self.varied) - len(shown)
        return ", ".join(shown) + (f" (and {left} settings each scenario's file sets)"
                                   if left else "")

    def values(self, label: str, keys: list[str]) -> str:
        """``k=v, ...`` of ``keys`` in the group ``label`` (those its runs have: another
        learner's own settings are not theirs)."""
        return ", ".join(_named(keys, self.groups[label][0].settings))

    @property
    def others(self) -> list[str]:
        """The varied settings other than the masking mode."""
        return [k for k in self.varied if k != "masking.mode"]

    def contexts(self) -> dict[str, dict[str, list[Run]]]:
        """``{other settings: {mode: runs}}``: the groups that differ only in the mode,
        together (one context, named "", when nothing else differs)."""
        out: dict[str, dict[str, list[Run]]] = {}
        for label, runs in self.groups.items():
            out.setdefault(self.values(label, self.others), {})[runs[0].mode] = runs
        return out

    def panels(self) -> dict[str, list[str]]:
        """``{panel: group labels}``: the groups whose baselines are the same (same masks,
        scenario, channel, traces), named by the mode and those settings (Fig. 4)."""
        env = [k for k in self.others if _is(k, ENV_SETTINGS)]
        out: dict[str, list[str]] = {}
        for label, runs in self.groups.items():
            key = ", ".join([runs[0].mode] + ([self.values(label, env)] if env else []))
            out.setdefault(key, []).append(label)
        return out


def _sort_key(v: Any) -> tuple:
    if isinstance(v, int | float) and not isinstance(v, bool):
        return (0, float(v), "")
    return (1, 0.0, fmt_value(v))


def group_runs(runs: list[Run]) -> Grouping:
    """Runs with equal settings together, groups ordered by masking mode, then by the
    values of the other settings that differ; labels name the mode, then those settings
    (``rank, algo.lr=0.001``): the mode alone for a sweep over modes."""
    keyed: dict[str, list[Run]] = {}
    for run in runs:
        keyed.setdefault(repr(sorted(run.settings.items())), []).append(run)
    members = list(keyed.values())
    first = members[0][0].settings
    order = {k: i for i, k in enumerate(default_settings())}  # the schemas' order
    keys = sorted({k for m in members for k in m[0].settings}, key=order.__getitem__)
    # a learner's own setting varies where the runs of that learner differ in it (the
    # others have none: algo.name tells them apart)
    varied = [k for k in keys if len({repr(m[0].settings[k]) for m in members
                                      if k in m[0].settings}) > 1]
    varied.sort(key=lambda k: k != "masking.mode")
    others = [k for k in varied if k != "masking.mode"]
    members.sort(key=lambda m: (MODES.index(m[0].mode),
                                [_sort_key(m[0].settings.get(k)) for k in others]))
    groups = {}
    for m in members:
        s = m[0].settings
        label = ", ".join([m[0].mode, *_named(others, s)])
        groups[label] = _one_per_seed(sorted(m, key=lambda r: r.seed))
    common = {k: v for k, v in first.items()
              if k not in varied and all(k in m[0].settings for m in members)}
    return Grouping(groups, varied, common)


def _label_keys(varied: list[str], settings: dict[str, Any]) -> list[str]:
    """The varied settings a group's label names (those its runs have). Where runs of
    several scenarios are grouped, the label leaves out the settings the group has as
    ``uabs-train scenario=<name>`` alone sets them (the scenario file's area, SUMO
    inputs, fleet, traces: a score of settings otherwise; a default the group kept,
    too); a setting the group has otherwise stays named."""
    keys = [k for k in varied if k in settings]
    if "scenario.name" in keys:
        own = _scenario_defaults(settings["scenario.name"], settings.get("algo.name", "dqn3"))
        if own is not None:
            keys = [k for k in keys if k == "scenario.name" or k not in own
                    or repr(own[k]) != repr(settings[k])]
    return keys


def _named(varied: list[str], settings: dict[str, Any]) -> list[str]:
    """``k=v`` of :func:`_label_keys`, the scenario as ``scenario=<name>``."""
    return [f"scenario={settings[k]}" if k == "scenario.name" else f"{k}={fmt_value(settings[k])}"
            for k in _label_keys(varied, settings)]


@cache
def _scenario_defaults(name: str, algo: str) -> dict[str, Any] | None:
    """Every setting, flat, as ``uabs-train scenario=<name> algo=<algo>`` alone gives it
    (the learner's own settings among them); None for a scenario or learner the
    package's conf/ does not hold (one of a --config-dir) or where a config cannot be
    composed here (a Hydra app already running)."""
    from uabs_rl.config import compose
    from uabs_rl.runs.checkpoint import config_dict, flatten

    try:
        return flatten(config_dict(compose("config", [f"scenario={name}", f"algo={algo}"])))
    except Exception:  # noqa: BLE001 - labels then name every setting, as before
        return None


def _one_per_seed(runs: list[Run]) -> list[Run]:
    """The runs of one group, one per seed: a second run of the same settings and seed
    (a copy, or the same run trained again) is left out with a warning, so that it does
    not count twice."""
    kept: dict[int, Run] = {}
    for run in runs:
        if run.seed in kept:
            print(f"warning: {run.path} has the settings and seed of {kept[run.seed].path}: "
                  f"left out (one run per seed)", file=sys.stderr)
        else:
            kept[run.seed] = run
    return list(kept.values())
