"""``uabs-report``: the paper's Table 2, Fig. 3 and Fig. 4 from a sweep, with baselines.

    uabs-train -m masking=penalty,flat,rank seed=0,1,2
    uabs-report outputs/multirun/<date_time>            # writes <dir>/report/
    uabs-report outputs/multirun/<date_time> --no-baselines --out docs/results

Groups the sweep's runs by masking mode (across seeds) and writes:
``table2.md``/``table2.csv`` (collisions in training and evaluation, as events and as
the share of episodes with at least one), ``fig3_eval_return.png``/``.pdf`` (validation
return against training episode, mean and 95 % bootstrap CI over seeds; penalty in a
panel of its own), ``fig4_pg.png``/``.pdf`` (P_g against N̂_s, one panel per masking
mode, the learned policy beside the baselines under the same masks), ``baselines.csv`` and
``summary.md`` (each claim of the paper, supported or not, with the numbers) and
``learned_vs_baselines.csv``/``.md``. Table 2 and Fig. 3 come from the runs'
``metrics.jsonl`` (training episodes and the periodic evaluations on the validation
traces); Fig. 4, the baselines and the learned-vs-baselines differences come from each
run's ``best.pt`` (chosen on validation) evaluated on the test traces beside the
random, greedy and oracle baselines with the same masks (``--no-baselines``: Fig. 4
from the best validation evaluations instead).
"""

from __future__ import annotations

import argparse
import csv
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from uabs_rl.baselines import BASELINES
from uabs_rl.channel import coverage_bound
from uabs_rl.config import AlgoConfig, MaskingMode, TrainConfig
from uabs_rl.runlog import read_metrics
from uabs_rl.stats import bootstrap_ci

MODES = tuple(m.value for m in MaskingMode)


@dataclass
class Run:
    path: Path
    mode: str
    seed: int
    episodes_planned: int
    train: list[dict]
    evals: list[dict]
    config: dict

    @property
    def label(self) -> str:
        """``paper``, ``lookahead`` or ``lookahead+motion`` (the observation),
        ``-literal`` for the paper's
        literal masks (runs written before masks became recoverable are literal), then
        any learning setting (``algo``, ``train.n_envs``, ``train.episodes``) that
        differs from the defaults (``lookahead algo.lr=0.0003``)."""
        sc = self.config["scenario"]
        label = ("paper" if not sc.get("lookahead_obs") else
                 "lookahead+motion" if sc.get("motion_obs") else "lookahead")
        literal = not self.config["masking"].get("recoverable")  # absent: written before
        defaults = asdict(AlgoConfig())
        tuned = [f"algo.{k}={v}" for k, v in self.config.get("algo", {}).items()
                 if k in defaults and k != "loss" and v != defaults[k]]
        train, train_defaults = self.config.get("train", {}), asdict(TrainConfig())
        tuned += [f"train.{k}={train[k]}" for k in ("n_envs", "episodes")
                  if k in train and train[k] != train_defaults[k]]
        return " ".join([label + ("-literal" if literal else ""), *tuned])

    @property
    def complete(self) -> bool:
        return bool(self.train) and self.train[-1]["episode"] >= self.episodes_planned

    @property
    def best_eval(self) -> dict:
        return max(self.evals, key=lambda r: r["return"])


def find_runs(root: Path) -> list[Run]:
    """Every run under ``root`` (a folder with metrics.jsonl and checkpoints/last.pt)."""
    runs = []
    for metrics in sorted(root.rglob("metrics.jsonl")):
        ckpt = metrics.parent / "checkpoints" / "last.pt"
        if not ckpt.is_file():
            continue
        cfg = torch.load(ckpt, map_location="cpu", weights_only=True)["config"]
        recs = read_metrics(metrics)
        runs.append(Run(metrics.parent, cfg["masking"]["mode"], int(cfg["seed"]),
                        int(cfg["train"]["episodes"]),
                        [r for r in recs if r["kind"] == "train"],
                        [r for r in recs if r["kind"] == "eval"], cfg))
    if not runs:
        raise SystemExit(f"error: no run (metrics.jsonl + checkpoints/last.pt) under {root}")
    check_one_experiment(runs, root)
    return runs


# settings that may differ between the runs of one report: what a sweep varies (seed,
# masking mode) and what does not change results
SWEPT_OR_NEUTRAL = ("seed", "masking.mode", "resume", "device", "train.progress",
                    "train.population",
                    "train.logger", "train.threads", "train.compile",
                    "train.trajectory_images", "train.checkpoint_buffer", "traces.cache_dir",
                    "traces.workers")


def check_one_experiment(runs: list[Run], root: Path) -> None:
    """Refuse a folder whose runs differ in other settings (another scenario, preset or
    length): their seeds would be averaged as if they were one experiment."""
    from uabs_rl.checkpoint import config_dict, config_from_checkpoint, flatten

    def key(run: Run) -> dict[str, Any]:
        # today's keys, with the defaults of settings added since the run was written
        full = config_dict(config_from_checkpoint({"config": run.config}))
        return {k: v for k, v in flatten(full).items()
                if not any(k == s or k.startswith(s + ".") for s in SWEPT_OR_NEUTRAL)}

    ref = key(runs[0])
    for run in runs[1:]:
        other = key(run)
        diff = sorted(k for k in set(ref) | set(other) if ref.get(k) != other.get(k))
        if diff:
            shown = ", ".join(f"{k} ({ref.get(k)!r} vs {other.get(k)!r})" for k in diff[:4])
            raise SystemExit(
                f"error: the runs under {root} are not one experiment: {runs[0].path} and "
                f"{run.path} differ in {shown}"
                f"{f' and {len(diff) - 4} more' if len(diff) > 4 else ''}. Report "
                f"one sweep (or run folder) at a time: pass its folder, or move the other "
                f"runs out.")


# ----------------------------------------------------------------------------- table 2
def collision_counts(run: Run) -> dict[str, float]:
    """Table 2 figures of one run, straight from its metrics."""
    ev = run.evals
    return {
        "train_episodes": len(run.train),
        "train_collision_events": sum(r["collisions"] for r in run.train),
        "train_episodes_with_collision": sum(r["collisions"] > 0 for r in run.train),
        "evaluations": len(ev),
        "eval_episodes": sum(r["windows"] for r in ev),
        "eval_collision_events": sum(r["collisions"] for r in ev),
        "eval_episodes_with_collision": sum(r["episodes_with_collision"] for r in ev),
        "evaluations_with_collision": sum(r["episodes_with_collision"] > 0 for r in ev),
        "train_proximity_events": sum(r["proximity"] for r in run.train),
        "train_fallbacks": sum(r["fallbacks"] for r in run.train),
        "eval_proximity_events": sum(r["proximity"] for r in ev),
        "eval_fallbacks": sum(r["fallbacks"] for r in ev),
    }


def table2(by_mode: dict[str, list[Run]]) -> list[dict[str, Any]]:
    rows = []
    for mode, runs in by_mode.items():
        counts = [collision_counts(r) for r in runs]
        row: dict[str, Any] = {"mode": mode, "seeds": len(runs)}
        for key in counts[0]:
            vals = np.array([c[key] for c in counts], dtype=float)
            row[key] = vals.mean()
            row[key + "_std"] = vals.std()
        row["train_share"] = row["train_episodes_with_collision"] / max(row["train_episodes"], 1)
        row["eval_share"] = (row["eval_episodes_with_collision"]
                             / max(row["eval_episodes"], 1))
        rows.append(row)
    return rows


def table2_markdown(rows: list[dict[str, Any]]) -> str:
    def cell(r, events, share_num, share_den):
        return (f"{r[events]:.1f} ± {r[events + '_std']:.1f} events; "
                f"{r[share_num]:.1f} of {r[share_den]:.0f} episodes "
                f"({100 * r[share_num] / max(r[share_den], 1):.1f} %)")

    head = "| | " + " | ".join(f"{r['mode']} ({r['seeds']} seeds)" for r in rows) + " |"
    lines = [head, "|---" * (len(rows) + 1) + "|"]
    lines.append("| Collisions in training | " + " | ".join(
        cell(r, "train_collision_events", "train_episodes_with_collision", "train_episodes")
        for r in rows) + " |")
    lines.append("| Collisions in evaluation | " + " | ".join(
        cell(r, "eval_collision_events", "eval_episodes_with_collision", "eval_episodes")
        for r in rows) + " |")
    lines.append("| Evaluations with a collision | " + " | ".join(
        f"{r['evaluations_with_collision']:.1f} of {r['evaluations']:.0f}" for r in rows) + " |")
    lines.append("| Proximity events (train / eval) | " + " | ".join(
        f"{r['train_proximity_events']:.0f} / {r['eval_proximity_events']:.0f}"
        for r in rows) + " |")
    lines.append("| Mask fallbacks (train / eval) | " + " | ".join(
        f"{r['train_fallbacks']:.0f} / {r['eval_fallbacks']:.0f}" for r in rows) + " |")
    return "\n".join(lines) + "\n\nMeans over seeds (± standard deviation); an evaluation " \
        "episode is one validation window.\n"


# ----------------------------------------------------------------------------- figures
def ci_over_seeds(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean over seeds (axis 0) and its 95 % bootstrap interval, per column."""
    cols = [bootstrap_ci(values[:, j], n_boot=2000) for j in range(values.shape[1])]
    if not cols:  # no common column (a run that has not evaluated yet)
        return np.zeros(0), np.zeros(0), np.zeros(0)
    return tuple(np.array(c) for c in zip(*cols, strict=True))


def eval_curves(runs: list[Run]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Episodes, mean and 95 % bootstrap CI over seeds of the evaluation return, at the
    episodes every run evaluated."""
    common = sorted(set.intersection(*[{r["episode"] for r in run.evals} for run in runs]))
    vals = np.array([[next(r["return"] for r in run.evals if r["episode"] == e)
                      for e in common] for run in runs])
    return (np.array(common), *ci_over_seeds(vals))


def best_pg(runs: list[Run]) -> np.ndarray:
    """[seeds, N] P_g curves of each run's best validation evaluation."""
    return np.array([run.best_eval["pg_curve"] for run in runs])


def _seeds(runs: list[Run]) -> str:
    return f"{len(runs)} seed{'s' if len(runs) != 1 else ''}"


def fig3(by_mode: dict[str, list[Run]], path: Path) -> list[Path]:
    """Validation return against training episode, mean and 95 % CI over seeds
    (:func:`uabs_rl.plots.return_curves_figure`), as PNG and PDF."""
    from uabs_rl.plots import return_curves_figure, save_paper_figure

    curves = {f"{mode} ({_seeds(runs)})": (mode, *eval_curves(runs))
              for mode, runs in by_mode.items()}
    return save_paper_figure(lambda: return_curves_figure(curves), path)


def fig4(by_mode: dict[str, list[Run]], baselines: dict[str, dict[str, dict]], path: Path,
         pg: dict[str, np.ndarray] | None = None) -> list[Path]:
    """P_g(N̂_s), one panel per masking mode: the learned policy (mean and 95 % CI over
    seeds; on the test traces when ``pg`` holds those curves, else each run's best
    validation evaluation) beside the baselines under the same masks
    (``baselines[mode][name]``; :func:`uabs_rl.plots.pg_panels_figure`), as PNG and PDF."""
    from uabs_rl.plots import pg_panels_figure, save_paper_figure

    panels = {mode: (_seeds(runs), *ci_over_seeds(100 * (pg[mode] if pg else best_pg(runs))))
              for mode, runs in by_mode.items()}
    curves = {m: {name: 100 * np.asarray(rec["pg_curve"]) for name, rec in b.items()}
              for m, b in baselines.items()}
    return save_paper_figure(lambda: pg_panels_figure(panels, curves), path)


# ----------------------------------------------------------------------------- baselines
def evaluate_on_test(runs: list[Run]) -> dict[Path, dict[str, dict]]:
    """Each run's ``best.pt`` (chosen on validation) and the random, greedy and oracle
    baselines with the run's masks, on every window of the test traces."""
    from uabs_rl.evaluate import POLICIES, evaluate_policies, load_evaluation

    out = {}
    for run in runs:
        ev = load_evaluation(run.path, "best", split="test")
        out[run.path] = {k: rec for k, (rec, _) in evaluate_policies(ev, POLICIES).items()}
    return out


def baselines_by_mode(by_mode: dict[str, list[Run]],
                      tests: dict[Path, dict]) -> dict[str, dict[str, dict]]:
    """``{mode: {baseline: test record}}``, from the lowest seed's run of each mode (the
    baselines depend on the masks, not on the learner)."""
    return {mode: {name: tests[min(runs, key=lambda r: r.seed).path][name]
                   for name in BASELINES}
            for mode, runs in by_mode.items()}


def baselines_on_test(by_mode: dict[str, list[Run]], tests: dict[Path, dict]) -> dict[str, dict]:
    """The same records keyed ``"<baseline> (<mode> masks)"``, for tables."""
    return {f"{name} ({mode} masks)": rec
            for mode, per in baselines_by_mode(by_mode, tests).items()
            for name, rec in per.items()}


def learned_pg_on_test(by_mode: dict[str, list[Run]],
                       tests: dict[Path, dict]) -> dict[str, np.ndarray]:
    """[seeds, N] learned P_g(N̂_s) curves on the test traces, per mode."""
    return {mode: np.array([tests[run.path]["learned"]["pg_curve"] for run in runs])
            for mode, runs in by_mode.items()}


# ----------------------------------------------------------------------------- test set
LVB_COLUMNS = ["mode", "n_uabs", "config", "metric", "baseline", "learned", "diff", "ci_low",
               "ci_high", "n_seeds"]


def learned_vs_baselines(runs: list[Run], tests: dict[Path, dict]) -> list[dict[str, Any]]:
    """Every run's ``best.pt`` (chosen on validation) and the baselines on the test
    traces, same windows and masks. Per group (mode, fleet size, config): the learned
    and baseline values (mean over seeds), the mean over seeds of each seed's per-window
    paired difference, and its bootstrap 95 % CI over seeds (over windows for one seed)."""
    from uabs_rl.evaluate import METRICS, POLICIES
    from uabs_rl.stats import bootstrap_ci

    groups: dict[tuple, list[dict]] = {}
    for run in runs:
        res = tests[run.path]
        key = (run.mode, int(run.config["scenario"]["n_uabs"]), run.label)
        groups.setdefault(key, []).append(res)
    rows = []
    for (mode, m, label), per_seed in sorted(groups.items()):
        for metric, k in METRICS.items():
            for base in POLICIES[1:]:
                diffs = [np.subtract(r["learned"][k], r[base][k]) for r in per_seed]
                seed_means = [float(d.mean()) for d in diffs]
                _, lo, hi = bootstrap_ci(seed_means if len(per_seed) > 1 else diffs[0])
                rows.append({
                    "mode": mode, "n_uabs": m, "config": label, "metric": metric,
                    "baseline": base,
                    "learned": float(np.mean([np.mean(r["learned"][k]) for r in per_seed])),
                    "diff": float(np.mean(seed_means)), "ci_low": lo, "ci_high": hi,
                    "baseline_value": float(np.mean([np.mean(r[base][k]) for r in per_seed])),
                    "n_seeds": len(per_seed)})
    return rows


def learned_vs_baselines_markdown(rows: list[dict[str, Any]]) -> str:
    head = ("| mode | M | config | metric | baseline | learned | baseline value | "
            "learned − baseline [95 % CI] | seeds |\n|---|---|---|---|---|---|---|---|---|\n")
    fmt = lambda r, v: f"{100 * v:.1f} %" if r["metric"] != "return" else f"{v:.0f}"  # noqa: E731
    dfmt = lambda r, v: f"{100 * v:+.1f}" if r["metric"] != "return" else f"{v:+.0f}"  # noqa: E731
    return head + "".join(
        f"| {r['mode']} | {r['n_uabs']} | {r['config']} | {r['metric']} | {r['baseline']} | "
        f"{fmt(r, r['learned'])} | {fmt(r, r['baseline_value'])} | {dfmt(r, r['diff'])} "
        f"[{dfmt(r, r['ci_low'])}, {dfmt(r, r['ci_high'])}] | {r['n_seeds']} |\n"
        for r in rows)


# ----------------------------------------------------------------------------- summary
# below these the verdicts are not worth much: validation curves of the paper's protocol
# level off after about 100 episodes (docs/results/learning.md), and a CI over fewer
# than 3 seeds says little
MIN_EPISODES, MIN_SEEDS = 200, 3


def short_run_warning(by_mode: dict[str, list[Run]]) -> str | None:
    """A warning when the sweep is too short or too small for its verdicts, else None."""
    episodes = min(run.train[-1]["episode"] if run.train else 0
                   for runs in by_mode.values() for run in runs)
    seeds = min(len(runs) for runs in by_mode.values())
    problems = []
    if episodes < MIN_EPISODES:
        problems.append(f"the shortest run trained {episodes} episodes (< {MIN_EPISODES}; "
                        f"the paper's protocol trains 1000)")
    if seeds < MIN_SEEDS:
        problems.append(f"a mode has {seeds} seed{'s' if seeds != 1 else ''} (< {MIN_SEEDS})")
    if not problems:
        return None
    return ("WARNING: " + "; ".join(problems) + ". This report's verdicts are not evidence "
            "for or against the paper's claims; run the full protocol for that.")


def summary(by_mode: dict[str, list[Run]], rows: list[dict], baselines: dict[str, dict],
            command: str, bound: float, nhat: int,
            tests: dict[Path, dict] | None = None) -> str:
    r = {row["mode"]: row for row in rows}
    final = {m: float(np.mean([np.mean([e["return"] for e in run.evals[-5:]]) for run in runs]))
             for m, runs in by_mode.items()}
    best = {m: float(np.mean([run.best_eval["return"] for run in runs]))
            for m, runs in by_mode.items()}
    pg = ({m: v.mean(0) for m, v in learned_pg_on_test(by_mode, tests).items()} if tests
          else {m: best_pg(runs).mean(0) for m, runs in by_mode.items()})
    where = ("best.pt on the test traces" if tests else "best validation evaluation")
    lines = ["# Sweep summary", "", f"Produced by: `{command}`", "",
             "Runs: " + ", ".join(f"{m}: {len(v)} seeds"
                                  + ("" if all(x.complete for x in v) else " (incomplete)")
                                  for m, v in by_mode.items()), ""]
    warning = short_run_warning(by_mode)
    if warning:
        lines += [f"**{warning}**", ""]

    def verdict(ok: bool | None) -> str:
        return "n/a (mode missing)" if ok is None else ("supported" if ok else "NOT supported")

    have = set(by_mode)
    c1 = None if not {"penalty", "flat", "rank"} <= have else (
        r["penalty"]["train_collision_events"] > 0
        and all(r[m]["train_collision_events"] == 0 and r[m]["eval_collision_events"] == 0
                for m in ("flat", "rank")))
    lines += ["## Table 2: masking avoids collisions, penalties do not", f"**{verdict(c1)}**. "
              + "; ".join(f"{m}: {r[m]['train_collision_events']:.1f} collision events in "
                          f"training ({100 * r[m]['train_share']:.1f} % of episodes), "
                          f"{r[m]['eval_collision_events']:.1f} in evaluation "
                          f"({100 * r[m]['eval_share']:.1f} % of episodes)" for m in r)
              + ". The paper: penalty 170 (17 %) and 14 (28 %); flat and rank 0.", ""]
    c2 = None if not {"penalty", "flat", "rank"} <= have else (
        final["rank"] > final["flat"] > final["penalty"])
    lines += ["## Fig. 3: evaluation reward rank > flat > penalty", f"**{verdict(c2)}** "
              "(mean over seeds of the last 5 evaluations): "
              + ", ".join(f"{m} {final[m]:.0f}" for m in final) + "; best evaluation: "
              + ", ".join(f"{m} {best[m]:.0f}" for m in best) + ".", ""]
    c3 = None if not {"penalty", "flat", "rank"} <= have else bool(
        (pg["rank"] >= pg["flat"] - 1e-9).all() and (pg["flat"] > pg["penalty"]).all())
    lines += ["## Fig. 4: P_g rank ≥ flat, both above penalty", f"**{verdict(c3)}** "
              f"(P_g in % for N̂_s = 1..N, {where}, mean over seeds):", ""]
    lines += [f"- {m}: " + ", ".join(f"{100 * v:.1f}" for v in pg[m]) for m in pg]
    if baselines:
        lines += baselines_section(by_mode, baselines, bound, nhat, tests, where)
    return "\n".join(lines) + "\n"


def baselines_section(by_mode: dict[str, list[Run]], baselines: dict[str, dict], bound: float,
                      nhat: int, tests: dict[Path, dict] | None, where: str) -> list[str]:
    """The summary's baselines table and the learned policies' served fraction."""
    lines = ["", "## Baselines (test traces, every window, the learned policies' masks)",
              "",
              f"| policy | R | collisions | proximity | fallbacks | served | P_g(N̂_s={nhat}) |",
              "|---|---|---|---|---|---|---|"]
    lines += [f"| {n} | {b['return']:.0f} | {b['collisions']:.0f} | {b['proximity']:.0f}"
              f" | {b['fallbacks']:.0f} | {100 * b['served_fraction']:.1f} % | "
              f"{100 * b['pg']:.1f} % |" for n, b in baselines.items()]
    learned = {m: float(np.mean([tests[run.path]["learned"]["served_fraction"]
                                 if tests else run.best_eval["served_fraction"]
                                 for run in runs])) for m, runs in by_mode.items()}
    cover = {m: [(tests[run.path]["learned"] if tests else run.best_eval)["coverage"]
                 for run in runs if "coverage" in run.best_eval]
             for m, runs in by_mode.items()}
    lines += ["", f"Learned policies' served fraction ({where}): "
              + ", ".join(f"{m} {100 * v:.1f} %" for m, v in learned.items())
              + "".join(f"; {m} area coverage {100 * np.mean(c):.1f} %"
                        for m, c in cover.items() if c)
              + f". Coverage bound (share of the area under footprints, ideal beams, "
                f"no overlap): {100 * bound:.1f} %.", ""]
    return lines


# ----------------------------------------------------------------------------- main
def build_report(root: Path, out: Path, with_baselines: bool = True,
                 command: str = "") -> dict[str, Any]:
    runs = find_runs(root)
    by_mode = {m: [r for r in runs if r.mode == m] for m in MODES}
    by_mode = {m: sorted(v, key=lambda r: r.seed) for m, v in by_mode.items() if v}
    out.mkdir(parents=True, exist_ok=True)
    rows = table2(by_mode)
    (out / "table2.md").write_text(table2_markdown(rows))
    with open(out / "table2.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    fig3(by_mode, out / "fig3_eval_return")
    tests = evaluate_on_test(runs) if with_baselines else {}
    baselines = baselines_on_test(by_mode, tests) if tests else {}
    if baselines:
        with open(out / "baselines.csv", "w", newline="") as f:
            keys = ["policy", "return", "return_std", "collisions", "proximity", "fallbacks",
                    "served_fraction", "pg"]
            w = csv.writer(f)
            w.writerow(keys)
            for name, b in baselines.items():
                w.writerow([name] + [b[k] for k in keys[1:]])
    fig4(by_mode, baselines_by_mode(by_mode, tests) if tests else {}, out / "fig4_pg",
         learned_pg_on_test(by_mode, tests) if tests else None)
    lvb = learned_vs_baselines(runs, tests) if tests else []
    if lvb:
        with open(out / "learned_vs_baselines.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=LVB_COLUMNS, extrasaction="ignore")
            w.writeheader()
            w.writerows(lvb)
        (out / "learned_vs_baselines.md").write_text(
            "# Learned policies against the baselines on the test traces\n\n"
            "best.pt of every run (chosen on validation), evaluated with random, greedy "
            "and oracle on every test window with the same masks; differences are "
            "learned − baseline per window, averaged per seed; CI: bootstrap over seeds. "
            "Served fraction and P_g(N̂_s) in percentage points.\n\n"
            + learned_vs_baselines_markdown(lvb))
    first = next(iter(by_mode.values()))[0]
    cfg = torch.load(first.path / "checkpoints" / "last.pt", weights_only=True)["config"]
    sc = cfg["scenario"]
    from uabs_rl.channel import beam_footprint_radius

    r_b = beam_footprint_radius(sc["altitude"], cfg["channel"]["fov_deg"],
                                cfg["channel"]["n_beams"])
    bound = coverage_bound(sc["n_uabs"], cfg["channel"]["n_beams"], r_b,
                           sc["area"]["width"] * sc["area"]["height"])
    (out / "summary.md").write_text(summary(by_mode, rows, baselines,
                                            command or f"uabs-report {root}", bound,
                                            int(sc["nhat_s"]), tests or None))
    return {"rows": rows, "baselines": baselines, "by_mode": by_mode,
            "learned_vs_baselines": lvb}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Table 2, Fig. 3 and Fig. 4 of a uabs-train sweep.")
    ap.add_argument("root", type=Path, help="a multirun folder (or any folder of runs)")
    ap.add_argument("--out", type=Path, help="output folder (default: <root>/report)")
    ap.add_argument("--no-baselines", dest="baselines", action="store_false")
    args = ap.parse_args(argv)
    out = args.out or args.root / "report"
    cmd = "uabs-report " + " ".join(sys.argv[1:] if argv is None else argv)
    res = build_report(args.root, out, args.baselines, cmd)
    print((out / "summary.md").read_text())
    warning = short_run_warning(res["by_mode"])
    if warning:
        print(warning, file=sys.stderr)
    print(f"wrote {out} (figures as PNG and PDF)")
    return 0


def run_main() -> None:
    sys.exit(main())


if __name__ == "__main__":
    run_main()
