"""The committed results of docs/results/ with the intervals of
``uabs_rl/evaluation/stats.py``, from what the csv files hold (the run folders are not in
the repository, so nothing is evaluated again).

Until issue #38 every interval over seeds was a percentile bootstrap of the seed means
(10 000 resamples). What can be recovered from it:

- 3 seeds (and 2): the bootstrap's 2.5 % and 97.5 % quantiles are the smallest and the
  largest seed value (each resample of three equal values has probability 1/27 > 2.5 %),
  so with the mean the three seed values are known exactly, and the Student-t interval
  is computed exactly (``exact``);
- 5 seeds: the five values are not recoverable. The Student-t interval is estimated by
  widening each side of the bootstrap's by the ratio (t side) / (bootstrap side),
  whose median over simulated seeds is printed (``estimated``); a verdict against zero
  counts as settled only where it holds over the ratio's 1 to 99 % range (normal and
  log-normal σ = 0.25 seeds), else it is ``undetermined`` until the per-seed values
  are read from the run folders (``uabs-report`` on them recomputes everything).

    python benchmarks/reinterval.py            # rewrites the csv and learned_vs_baselines.md files

``--sample-sd``: Table 2's "±" was the standard deviation over seeds with n in the
denominator until ``uabs_rl/report/tables.py`` took n − 1 (the sample standard deviation:
with 3 seeds the old figure was 0.82 of it). The means are unchanged and each old figure
times sqrt(n / (n − 1)) is the new one, so every committed table2.csv is rewritten from
its own columns and its table2.md's "±" figures and closing line from that (a file whose
closing line already says "sample" is left as it is).

    python benchmarks/reinterval.py --sample-sd   # rewrites every table2.csv and table2.md
"""

from __future__ import annotations

import argparse
import csv
import math
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from uabs_rl.evaluation.stats import t_interval, welch_difference  # noqa: E402

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"
LVB = ("diff", "ci_low", "ci_high", "n_seeds")
GAP = ("gap_share", "gap_ci_low", "gap_ci_high", "n_seeds")  # the same interval / the gap
# file (relative to docs/results) -> its intervals: (value, low, high, seeds column)
FILES: dict[str, list[tuple[str, str, str, str]]] = {
    **{str(p.relative_to(RESULTS)): [LVB, GAP]
       for p in sorted(RESULTS.rglob("learned_vs_baselines.csv"))},
    "headroom/learned_gap.csv": [("share", "ci_low", "ci_high", "n_seeds")],
    **{f"generalization/{n}.csv": [
        ("learned_minus_greedy", "ci_low", "ci_high", "seeds"),
        ("learned_minus_oracle", "oracle_ci_low", "oracle_ci_high", "seeds"),
        ("other_minus_greedy", "other_ci_low", "other_ci_high", "seeds")]
       for n in ("zero_shot", "single_city")},
    **{f"{d}/comparison.csv": [(k, f"{k}_low", f"{k}_high", "seeds") for k in (
        "return_last5", "return_best", "served_fraction", "pg", "train_collision_events")]
       for d in ("algorithms", "algorithms/lookahead_motion", "generalization/training")},
}


def ratios(two_groups: bool = False, trials: int = 4000) -> np.ndarray:
    """(Student-t or Welch side) / (percentile bootstrap side) over simulated 5-seed
    experiments, both sides, normal and log-normal σ = 0.25 seeds (seeded)."""
    rng = np.random.default_rng(38)
    out = []
    for i in range(trials):
        draw = (lambda s: rng.normal(0, 1, s)) if i % 2 else (lambda s: rng.lognormal(0, .25, s))
        a, b = draw(5), draw(5)
        idx = rng.integers(0, 5, (4000, 5))
        if two_groups:
            boot = a[idx].mean(1) - b[rng.integers(0, 5, (4000, 5))].mean(1)
            d = welch_difference(a, b)
            m, lo, hi = d["diff"], d["ci_low"], d["ci_high"]
        else:
            boot = a[idx].mean(1)
            m, lo, hi = t_interval(a)
        q_lo, q_hi = np.quantile(boot, [0.025, 0.975])
        out += [(m - lo) / (m - q_lo), (hi - m) / (q_hi - m)]
    return np.asarray(out)


def exact_from_three(mean: float, lo: float, hi: float, n: int) -> tuple[float, float]:
    """The Student-t interval of 2 or 3 seeds whose bootstrap interval was [lo, hi]
    (their smallest and largest values) and whose mean is ``mean``."""
    values = [lo, hi] if n == 2 else [lo, n * mean - lo - hi, hi]
    return t_interval(values)[1:]


def against_zero(lo: float, hi: float) -> str:
    return "above zero" if lo > 0 else "below zero" if hi < 0 else "includes zero"


def reinterval(mean: float, lo: float, hi: float, n: int, ratio: np.ndarray
               ) -> dict[str, str | float]:
    """The new interval (exact or estimated), its method and its verdict against zero."""
    if n <= 3:
        t_lo, t_hi = exact_from_three(mean, lo, hi, n)
        return {"low": t_lo, "high": t_hi, "how": "exact",
                "vs_zero": against_zero(t_lo, t_hi),
                "method": f"95 % CI, Student-t over {n} seeds"}
    med, r_min, r_max = np.quantile(ratio, [0.5, 0.01, 0.99])
    t_lo, t_hi = mean - med * (mean - lo), mean + med * (hi - mean)
    wide = against_zero(mean - r_max * (mean - lo), mean + r_max * (hi - mean))
    narrow = against_zero(mean - r_min * (mean - lo), mean + r_min * (hi - mean))
    return {"low": t_lo, "high": t_hi, "how": "estimated",
            "vs_zero": wide if wide == narrow else "undetermined",
            "method": f"95 % CI, Student-t over {n} seeds, estimated from the percentile "
                      f"bootstrap's (x {med:.2f} per side)"}


def rewrite(path: Path, triples: list[tuple[str, str, str, str]], ratio: np.ndarray,
            changes: list[str]) -> list[dict[str, str]]:
    """Rewrites ``path``: each interval replaced by the new one, with ``<value>_method``
    and ``<value>_vs_zero`` columns; the old bootstrap kept as ``<low>_bootstrap``."""
    with path.open() as f:
        rows = list(csv.DictReader(f))
    columns = list(rows[0])
    for value, low, high, seeds in triples:
        if value not in columns:
            continue
        for extra in (f"{low}_bootstrap", f"{high}_bootstrap", f"{value}_method",
                      f"{value}_vs_zero"):
            if extra not in columns:
                columns.append(extra)
        for r in rows:
            if r.get(value, "") in ("", "nan") or r.get(low, "") in ("", "nan"):
                continue
            old = [float(r.get(f"{low}_bootstrap") or r[low]),
                   float(r.get(f"{high}_bootstrap") or r[high])]
            new = reinterval(float(r[value]), *old, int(r[seeds]), ratio)
            r[f"{low}_bootstrap"], r[f"{high}_bootstrap"] = old
            r[low], r[high] = new["low"], new["high"]
            r[f"{value}_method"], r[f"{value}_vs_zero"] = new["method"], new["vs_zero"]
            if against_zero(*old) != new["vs_zero"]:
                changes.append(f"{path.relative_to(RESULTS)}: {_row_name(r)} {value} "
                               f"{float(r[value]):+.4g}: bootstrap [{old[0]:+.4g}, "
                               f"{old[1]:+.4g}] {against_zero(*old)} -> {new['how']} "
                               f"[{new['low']:+.4g}, {new['high']:+.4g}] {new['vs_zero']}")
    if "spread" in columns:  # comparison.csv: the words of its intervals
        for r in rows:
            r["spread"] = r[f"{triples[0][0]}_method"]
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    return rows


def _row_name(r: dict[str, str]) -> str:
    keys = ("group", "mode", "n_uabs", "config", "city", "M", "metric", "baseline")
    return " ".join(f"{r[k]}" for k in keys if r.get(k) not in (None, ""))


def fmt(metric: str, v: float) -> str:
    return f"{v:+.0f}" if metric == "return" else f"{100 * v:+.1f}"


def level(metric: str, v: float) -> str:
    return f"{v:.0f}" if metric == "return" else f"{100 * v:.1f} %"


def lvb_markdown(rows: list[dict[str, str]]) -> str:
    """A learned_vs_baselines.md from its rewritten csv (one table, every row)."""
    head = ("# Learned policies against the baselines on the test traces\n\n"
            "best.pt of every run (chosen on validation), evaluated with random, greedy and "
            "oracle on every test window with the same masks; differences are learned − "
            "baseline per window, averaged per seed, with a Student-t 95 % CI over seeds "
            "(`docs/evaluation.md`): exact where the run had 3 seeds, estimated from the "
            "committed percentile bootstrap where it had 5 (the per-seed values are in the "
            "run folders only; `benchmarks/reinterval.py`). The bootstrap interval, the "
            "method and the verdict against zero are in the csv. Served fraction and "
            "P_g(N̂_s) in %, differences in percentage points.\n\n"
            "| mode | M | config | learner | metric | baseline | learned | baseline value | "
            "learned − baseline [95 % CI, Student-t] | seeds | against zero |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        m = r["metric"]
        d, lo, hi = (float(r[k]) for k in ("diff", "ci_low", "ci_high"))
        learned = float(r["learned"])
        est = "" if int(r["n_seeds"]) <= 3 else " (est.)"
        lines.append(f"| {r['mode']} | {r['n_uabs']} | {r['config']} | {r.get('algo', 'dqn3')} "
                     f"| {m} | {r['baseline']} | "
                     f"{level(m, learned)} | {level(m, learned - d)} | {fmt(m, d)} [{fmt(m, lo)}, "
                     f"{fmt(m, hi)}]{est} | {r['n_seeds']} | {r['diff_vs_zero']} |")
    return head + "\n".join(lines) + "\n"


CELL = re.compile(r"([+-]\d+\.\d+)( pt)? \[([+-]\d+\.\d+), ([+-]\d+\.\d+)\]")


def settle(d: float, lo: float, hi: float, ratio: np.ndarray) -> tuple[float, float, str]:
    """An estimated interval from a percentile bootstrap one (``ratio``'s median per
    side) and its verdict against zero over ``ratio``'s 1 to 99 % range."""
    med, r_min, r_max = np.quantile(ratio, [0.5, 0.01, 0.99])
    wide = against_zero(d - r_max * (d - lo), d + r_max * (hi - d))
    narrow = against_zero(d - r_min * (d - lo), d + r_min * (hi - d))
    return d - med * (d - lo), d + med * (hi - d), wide if wide == narrow else "undetermined"


def relearners(path: Path, ratio: np.ndarray, changes: list[str]) -> None:
    """learners.md: each two-group percentile bootstrap interval (5 and 5 seeds) replaced
    by the estimated Welch interval and its verdict against zero."""
    text = path.read_text()
    if "Welch" in text:
        return

    def sub(m: re.Match) -> str:
        d, lo, hi = (float(m.group(k)) for k in (1, 3, 4))
        new_lo, new_hi, verdict = settle(d, lo, hi, ratio)
        if verdict != against_zero(lo, hi):
            changes.append(f"{path.relative_to(RESULTS)}: {m.group(0)} {against_zero(lo, hi)}"
                           f" -> Welch est. [{new_lo:+.2f}, {new_hi:+.2f}] {verdict}")
        return f"{d:+.2f}{m.group(2) or ''} [{new_lo:+.2f}, {new_hi:+.2f}] ({verdict})"

    text = CELL.sub(sub, text).replace("[95 % CI]", "[95 % CI, Welch, estimated]")
    path.write_text(text + WELCH_NOTE)


WELCH_NOTE = ("\nDifferences: Welch's 95 % CI over the two groups of 5 seeds, estimated from "
              "the percentile bootstrap that `benchmarks/learners.py` printed before issue #38 "
              "(each side widened by the median ratio of simulated 5-and-5-seed experiments; "
              "`benchmarks/reinterval.py`); against zero: settled only where it holds over "
              "the ratio's 1 to 99 % range. `python benchmarks/learners.py` on the run "
              "folders computes the exact Welch intervals.\n")


def generalist_against_single_city(changes: list[str], ratio: np.ndarray) -> None:
    """generalization/two_groups.csv: generalist − single-city policy (two independent
    populations of 5 seeds, the same greedy baseline and windows) per (city, M), Welch's
    interval estimated from each population's own interval: standard errors from the
    bootstrap half-widths (x sqrt(n / (n − 1)), the plug-in's bias), Welch–Satterthwaite
    degrees of freedom. Against zero: settled only where it holds with the half-width
    scaled over the one-group ratio's 1 to 99 % range (relative to its median)."""
    from uabs_rl.evaluation.stats import t_quantile

    rows = {}
    for name in ("zero_shot", "single_city"):
        with (RESULTS / "generalization" / f"{name}.csv").open() as f:
            for r in csv.DictReader(f):
                rows.setdefault((r["city"], r["M"]), {})[name] = r
    out = []
    for (city, m), pair in rows.items():
        a, b = pair["zero_shot"], pair["single_city"]
        n_a, n_b = int(a["seeds"]), int(b["seeds"])
        se = [(float(r["ci_high_bootstrap"]) - float(r["ci_low_bootstrap"])) / (2 * 1.96)
              * math.sqrt(n / (n - 1)) for r, n in ((a, n_a), (b, n_b))]
        va, vb = se[0] ** 2, se[1] ** 2
        df = (va + vb) ** 2 / (va ** 2 / (n_a - 1) + vb ** 2 / (n_b - 1))
        d = float(a["learned_minus_greedy"]) - float(b["learned_minus_greedy"])
        half = t_quantile(0.975, df) * math.sqrt(va + vb)
        out.append({"city": city, "M": m, "generalist_minus_greedy": a["learned_minus_greedy"],
                    "single_city_minus_greedy": b["learned_minus_greedy"],
                    "generalist_minus_single_city": d, "ci_low": d - half, "ci_high": d + half,
                    "df": df, "vs_zero": settle(d, d - half, d + half, ratio / np.median(ratio))[2],
                    "method": f"95 % CI, Welch over {n_a} and {n_b} seeds, estimated from "
                              f"each population's bootstrap interval"})
    with (RESULTS / "generalization" / "two_groups.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(out[0]))
        w.writeheader()
        w.writerows(out)
    for r in out:
        changes.append(f"generalization/two_groups.csv (new): {r['city']} M={r['M']} "
                       f"generalist − single-city {100 * r['generalist_minus_single_city']:+.2f}"
                       f" pt [{100 * r['ci_low']:+.2f}, {100 * r['ci_high']:+.2f}] "
                       f"{r['vs_zero']}")


def generalization_tables() -> None:
    """zero_shot.md and single_city.md from their rewritten csv files, each interval
    marked with its verdict against zero."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from generalization import table

    for name, other in (("zero_shot", True), ("single_city", False)):
        with (RESULTS / "generalization" / f"{name}.csv").open() as f:
            rows = [{k: _number(v) for k, v in r.items()} for r in csv.DictReader(f)]
        marks = {v: f"{v}_vs_zero" for v in ("learned_minus_greedy", "learned_minus_oracle",
                                             "other_minus_greedy")}
        (RESULTS / "generalization" / f"{name}.md").write_text(
            table(rows, other, marks) + "\n" + GENERALIZATION_NOTE)


GENERALIZATION_NOTE = (
    "Intervals: Student-t 95 % CI over the 5 seeds, estimated from the percentile "
    "bootstrap this table had before issue #38 (`benchmarks/reinterval.py`; the "
    "bootstrap values are in the csv); against zero: settled only where it holds over "
    "the ratio's 1 to 99 % range, else undetermined. `python benchmarks/generalization.py` "
    "on the run folders computes the exact intervals.\n")


def _number(v: str) -> str | float | int:
    try:
        return int(v)
    except ValueError:
        try:
            return float(v)
        except ValueError:
            return v


def summary_tables() -> None:
    """The "Settings compared" table of each summary.md beside a comparison.csv, from the
    rewritten csv (the report's own table function)."""
    from uabs_rl.report.tables import comparison_markdown

    for path in sorted(RESULTS.rglob("comparison.csv")):
        summary = path.with_name("summary.md")
        with path.open() as f:
            rows = [{k: _number(v) for k, v in r.items()} for r in csv.DictReader(f)]
        text = summary.read_text()
        start = text.index("## Settings compared")
        end = text.index("\n## ", start + 1) + 1
        nhat = re.search(r"P_g\(N̂_s=(\d+)\)", text[start:end])
        table = comparison_markdown(rows, int(nhat.group(1)) if nhat else None)
        table[-2] = (table[-2].rstrip(".") + ", estimated from the percentile bootstrap first "
                     "committed (`benchmarks/reinterval.py`; exact in a new `uabs-report`).")
        summary.write_text(text[:start] + "\n".join(table) + "\n" + text[end:])


OLD_TABLE2_NOTE = "Means over seeds (± standard deviation)"
NEW_TABLE2_NOTE = ("Means over seeds (± their sample standard deviation, n − 1 in the "
                   "denominator)")


def table2_sample_sd() -> None:
    """Every committed table2.csv / table2.md with the sample standard deviation."""
    for md in sorted(RESULTS.rglob("table2.md")):
        text, path = md.read_text(), md.with_suffix(".csv")
        if OLD_TABLE2_NOTE not in text:
            print(f"{md.relative_to(RESULTS)}: already the sample standard deviation")
            continue
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            fields, rows = reader.fieldnames, list(reader)
        for r in rows:
            n = int(r["seeds"])
            scale = math.sqrt(n / (n - 1)) if n > 1 else 0.0
            for k in fields:
                if k.endswith("_std"):
                    r[k] = repr(float(r[k]) * scale)
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=fields)
            w.writeheader()
            w.writerows(rows)
        lines = text.split("\n")
        for i, line in enumerate(lines):  # one cell per row of the csv, in its order
            for label, key in (("| Collisions in training |", "train_collision_events"),
                               ("| Collisions in evaluation |", "eval_collision_events")):
                if line.startswith(label):
                    cells = iter(f"± {float(r[key + '_std']):.1f} events" for r in rows)
                    lines[i] = re.sub(r"± [0-9.]+ events", lambda _, c=cells: next(c), line)
        md.write_text("\n".join(lines).replace(OLD_TABLE2_NOTE, NEW_TABLE2_NOTE))
        print(f"{md.relative_to(RESULTS)}: {len(rows)} rows, seeds "
              f"{sorted({int(r['seeds']) for r in rows})}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sample-sd", action="store_true",
                    help="only Table 2's standard deviations: n -> n - 1 (table2.csv, .md)")
    if ap.parse_args().sample_sd:
        table2_sample_sd()
        return
    one, two = ratios(), ratios(two_groups=True, trials=1000)
    for name, r in (("Student-t / bootstrap, 5 seeds", one),
                    ("Welch / two-group bootstrap, 5 and 5 seeds", two)):
        print(f"{name}: median {np.median(r):.2f}, 1-99 % {np.quantile(r, 0.01):.2f} to "
              f"{np.quantile(r, 0.99):.2f}")
    changes: list[str] = []
    for rel, triples in FILES.items():
        path = RESULTS / rel
        if not path.exists():
            continue
        rows = rewrite(path, triples, one, changes)
        md = path.with_suffix(".md")
        if path.name == "learned_vs_baselines.csv" and md.exists():
            md.write_text(lvb_markdown(rows))
    for path in sorted(RESULTS.rglob("learners.md")):
        relearners(path, two, changes)
    generalist_against_single_city(changes, one)
    generalization_tables()
    summary_tables()
    print(f"\n{len(changes)} intervals whose verdict against zero changed (and the new "
          f"two-group ones):")
    print("\n".join(changes))
    print(f"\nthe two-group ratio, for learners.md and the generalization's comparisons: "
          f"x {np.median(two):.2f} (1-99 %: {np.quantile(two, 0.01):.2f} to "
          f"{np.quantile(two, 0.99):.2f}); sqrt(2) = {math.sqrt(2):.2f}")


if __name__ == "__main__":
    main()
