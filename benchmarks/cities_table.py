"""Planning against learning on every (city, M): one table from the folders the other
benchmarks wrote, nothing flown.

    python benchmarks/cities_table.py docs/results/planning_vs_learning \
        > docs/results/planning_vs_learning/cities/summary.md

Reads, under the folder given (``docs/results/planning_vs_learning``):

* the planners, flown by ``benchmarks/planning_vs_learning.py`` (greedy, the oracle, the
  mpc at H = 1, 5, 10 with both predictors, the clairvoyant planner at H = 5 and 10): the
  default grid's in ``road/``, each other city's in ``cities/planners_<city>/``; an mpc
  that folder lacks, from ``uabs-eval --policy mpc ... --out cities/mpc_<variant>_<city>_<M>``
  (its ``eval.json``: the test split of that city at that M);
* the learned policies, ``cities/table.csv`` of ``benchmarks/generalization.py`` (the
  generalist and the 3DQN trained on the default grid at M = 3, flown on each grid at
  M = 3, 5 seeds each);
* the hybrids, each a folder of ``benchmarks/hybrid.py``: ``hybrid/`` (the default grid at
  M = 3, with the 3DQN's Q-values), ``cities/hybrid_<city>/`` (M = 3) and
  ``cities/hybrid_<city>_<M>/`` (other fleets; the city's ``cities/hybrid_city/``), with
  the generalist's; the mpc with the generalist's leaf values (``--leaf``),
  ``cities/leaf_<city>_<M>/`` (the default grid: ``leaf_home_<M>``), and its variants,
  ``cities/leaf_<variant>_<city>_<M>/`` (another horizon, another population's values:
  each flown beside an mpc of the planners' folder, which it must match).

Prints four markdown tables: the served fraction of every policy, its P_g(5), the
paired differences of the learned policy and of each hybrid against the mpc (H = 5,
constant velocity: the one both were flown beside) and against the best deployable
planner of the row (the mpc variant that served most on these test windows: chosen on
the test windows, which favours the planner), each member's mean paired difference over
the windows, Student-t 95 % CI over the 5 members; and the same differences against the
mpc (H = 5) over the windows: the members' mean per window paired with the mpc's,
Student-t over the windows (which also counts the windows' sampling), with the number of
windows where it serves more; then one row per leaf variant, against the same mpc and the
best mpc. A (city, M) without its planners'
folder is left out (said on stderr); one without a learned row or a hybrid has blank
cells there. A planners' folder flown on another scenario (its ``log.txt``) or a hybrid
flown beside another mpc (its settings, its per-window values) is refused.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from uabs_rl.cli import one_line_errors
from uabs_rl.evaluation.baselines import MPC as MPC_NAME
from uabs_rl.evaluation.baselines import PLANNER, policy_label
from uabs_rl.evaluation.stats import paired_difference, paired_over_seeds

PAIRS = [("home", 3), ("home", 6), ("grid6", 3), ("grid6", 6), ("lights60", 3),
         ("lights60", 6), ("lanes75", 3), ("lanes75", 6), ("city", 25)]
PLANNERS = ["greedy", "oracle",
            *(policy_label(MPC_NAME, h, p) for p in ("cv", "road") for h in (1, 5, 10)),
            policy_label(PLANNER, 5), policy_label(PLANNER, 10)]
MPC = policy_label(MPC_NAME, 5, "cv")


def short(policy: str) -> str:
    """``mpc H=5 (cv)`` -> ``mpc H=5 cv``; ``planner H=5 (clairvoyant)`` ->
    ``clairvoyant H=5``."""
    name, _, rest = policy.partition(" (")
    if name.startswith(PLANNER + " ") and rest == "clairvoyant)":
        return "clairvoyant" + name[len(PLANNER):]
    return policy.replace(" (", " ").rstrip(")")


def planners(root: Path, city: str, m: int) -> dict[str, dict]:
    """Each planner's per-window values and its row of ``table.csv``, by policy."""
    folder = root / ("road" if city == "home" else f"cities/planners_{city}")
    if not all((folder / f).exists() for f in ("per_window.json", "table.csv", "log.txt")):
        return {}
    flown = (folder / "log.txt").read_text().split(",")[0]  # "scenario=<name>" unless home
    if (flown if flown.startswith("scenario=") else None) != (
            None if city == "home" else f"scenario={city}"):
        sys.exit(f"{folder} was flown on {flown.split()[0]!r}, not scenario={city}")
    rows = {r["policy"]: r for r in csv.DictReader(open(folder / "table.csv"))
            if r["mode"] == "rank" and int(r["n_uabs"]) == m}
    plan = {r["policy"]: {**rows[r["policy"]], "per_window": r}
            for r in json.loads((folder / "per_window.json").read_text())
            if r["mode"] == "rank" and r["n_uabs"] == m and r["policy"] in rows}
    for extra in sorted((root / "cities").glob(f"mpc_*_{city}_{m}/eval.json")):
        j = json.loads(extra.read_text())
        rec = j["policies"].get("mpc", {})
        name = policy_label(MPC_NAME, rec.get("horizon"), rec.get("predictor"),
                            beam=rec.get("beam"),  # another width or passes: not a planner row
                            rounds=rec.get("rounds"))
        if (j["split"] != "test" or j["scenario"] != city or rec.get("sees") != "all"
                or f"scenario.n_uabs={m}" not in j["overrides"] or name not in PLANNERS
                or plan and len(rec["served_fractions"]) != len(
                    next(iter(plan.values()))["per_window"]["served_fractions"])):
            sys.exit(f"{extra.parent} is not an mpc on {city}'s test windows at M = {m}")
        plan.setdefault(name, {"served": rec["served_fraction"], "pg": rec["pg"],
                               "per_window": {"served_fractions": rec["served_fractions"],
                                              "pgs": rec["pgs"]}})
    return plan


def hybrid(root: Path, city: str, m: int, kind: str = "hybrid") -> dict | None:
    """The hybrid (``kind`` "hybrid": Q at the first move) or the mpc with learned leaf
    values ("leaf") of (city, M), as ``benchmarks/hybrid.py`` wrote it; None if absent."""
    if kind == "leaf":
        name = f"cities/leaf_{city}_{m}"
    elif (city, m) == ("home", 3):
        name = "hybrid"
    else:
        name = f"cities/hybrid_{city}" + ("" if m == 3 or city == "city" else f"_{m}")
    return load(root, name, kind)


def load(root: Path, name: str, kind: str) -> dict | None:
    """The ``hybrid.json`` of folder ``name`` (under ``root``), checked to hold ``kind``;
    None if absent."""
    path = root / name / "hybrid.json"
    if not path.exists():
        return None
    j = json.loads(path.read_text())
    if j.get("hybrid", "hybrid") != kind:  # files before --leaf have no such key
        sys.exit(f"{path} holds the {j['hybrid']!r} hybrid, not {kind!r}: "
                 f"another folder's results")
    return j | {"folder": name}


def own_mpc(hyb: dict) -> str:
    """The planners' name of the mpc ``hyb`` was flown beside (``mpc H=5 (cv)``)."""
    return policy_label(MPC_NAME, hyb.get("mpc_horizon"), hyb.get("predictor"),
                        beam=hyb.get("mpc_beam"), rounds=hyb.get("mpc_rounds"))


def check_mpc(hyb: dict | None, plan: dict, city: str, m: int, name: str = MPC) -> None:
    """Exit unless ``hyb`` (if any) was flown beside the planners' mpc ``name`` itself
    (its settings, its per-window values)."""
    if hyb is not None and (
            (own_mpc(hyb), hyb.get("sees")) != (name, "all") or name not in plan
            or hyb["policies"]["mpc"]["served"] != plan[name]["per_window"]["served_fractions"]
            or hyb["policies"]["mpc"]["pg"] != plan[name]["per_window"]["pgs"]):
        sys.exit(f"{hyb['folder']}'s mpc is not the planners' {name} of {city}:{m}: "
                 f"other settings, windows or masks")


def variants(root: Path, city: str, m: int, plan: dict) -> list[dict]:
    """The leaf variants of (city, M), ``cities/leaf_<variant>_<city>_<M>/``, each checked
    flown beside the planners' mpc of its own settings."""
    out = []
    for folder in sorted((root / "cities").glob(f"leaf_*_{city}_{m}")):
        j = load(root, f"cities/{folder.name}", "leaf")
        if j is not None:
            check_mpc(j, plan, city, m, own_mpc(j))
            out.append(j)
    return out


def mean_cell(hyb: dict | None, key: str) -> str:
    """A hybrid's mean over members and windows, with its λ*; blank if absent."""
    if hyb is None:
        return ""
    h = hyb["policies"]["hybrid"][key]
    return f"{pct(sum(sum(w) / len(w) for w in h) / len(h))} (λ* = {hyb['best_weight']:g})"


def pct(x) -> str:
    return "" if x is None else f"{100 * float(x):.2f}"


def ci(d: dict | None) -> str:
    if d is None:
        return ""
    return f"{100 * d['diff']:+.2f} [{100 * d['ci_low']:+.2f}, {100 * d['ci_high']:+.2f}]"


def over_windows(values: list[list[float]] | None, mpc: list[float]) -> str:
    """The members' mean per window (``values[member][window]``) paired with ``mpc``'s:
    its interval over the windows and the windows where it serves more; blank if none."""
    if not values:
        return ""
    mean = np.nanmean(np.asarray(values, dtype=float), axis=0)
    better = int(np.sum(mean > np.asarray(mpc, dtype=float)))
    return f"{ci(paired_difference(mean, mpc))}, {better} of {len(mpc)}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("root", type=Path, help="docs/results/planning_vs_learning")
    args = ap.parse_args()
    if not (args.root / "cities").is_dir():
        ap.error(f"{args.root} holds no cities/ folder: give the folder of "
                 f"docs/results/planning_vs_learning's layout (cities/, rounds/)")
    learned_csv = args.root / "cities/table.csv"
    learned = ({(r["city"], int(r["M"])): r for r in csv.DictReader(open(learned_csv))}
               if learned_csv.exists() else {})
    served, pg, diffs, windows, extra = [], [], [], [], []
    for city, m in PAIRS:
        plan, lrn = planners(args.root, city, m), learned.get((city, m))
        hyb, leaf = hybrid(args.root, city, m), hybrid(args.root, city, m, "leaf")
        if not plan:
            print(f"{city}:{m}: no planners' folder, left out", file=sys.stderr)
            continue
        check_mpc(hyb, plan, city, m)
        check_mpc(leaf, plan, city, m)
        head = [city, str(m)]
        for table, key, lkey, hkey in ((served, "served", "learned", "served"),
                                       (pg, "pg", "pg_learned", "pg")):
            cells = [pct(plan[p][key]) if p in plan else "" for p in PLANNERS]
            cells.append(pct(lrn[lkey]) if lrn else "")
            if key == "served":  # the default grid's 3DQN (M = 3 only): its served fraction
                cells.append(pct(lrn["other"]) if lrn and lrn.get("other") else "")
            cells += [mean_cell(hyb, hkey), mean_cell(leaf, hkey)]
            table.append(head + cells)
        mpcs = [p for p in PLANNERS if p.startswith("mpc") and p in plan]
        if not mpcs:
            sys.exit(f"{city}:{m}: the planners' folder holds no mpc")
        best = max(mpcs, key=lambda p: float(plan[p]["served"]))
        row = head + [short(best), pct(plan[best]["served"])]
        values = [hyb["policies"]["learned"]["served"] if hyb else None,
                  hyb["policies"]["hybrid"]["served"] if hyb else None,
                  leaf["policies"]["hybrid"]["served"] if leaf else None]
        for v in values:
            for base in (MPC, best):
                b = plan[base]["per_window"]["served_fractions"]
                row.append(ci(paired_over_seeds(v, [b] * len(v))) if v else "")
        row += [Path(h["members"][0]).parent.name if h else ""  # the population's folder
                for h in (hyb, leaf)]
        diffs.append(row)
        if MPC in plan:
            mpc5 = plan[MPC]["per_window"]["served_fractions"]
            windows.append(head + [str(len(mpc5))] + [over_windows(v, mpc5) for v in values])
            for j in variants(args.root, city, m, plan):
                v = j["policies"]["hybrid"]["served"]
                b = plan[best]["per_window"]["served_fractions"]
                extra.append(head + [
                    Path(j["folder"]).name, Path(j["members"][0]).parent.name,
                    str(j.get("hybrid_horizon", j["mpc_horizon"])), f"{j['best_weight']:g}",
                    mean_cell(j, "served").split(" (")[0],
                    ci(paired_over_seeds(v, [mpc5] * len(v))), over_windows(v, mpc5),
                    ci(paired_over_seeds(v, [b] * len(v))) + f" ({short(best)})"])

    cols = [short(p) for p in PLANNERS]
    for title, table, learners in (
            ("Served fraction, %", served,
             ["generalist", "3DQN (default grid's)", "hybrid", "leaf"]),
            ("P_g(5), %", pg, ["generalist", "hybrid", "leaf"])):
        markdown(f"{title} (test windows; learned, hybrid and leaf: the mean over 5 seeds)",
                 ["city", "M", *cols, *learners], table, first=table is served)
    markdown("Paired differences on the test windows, served fraction, points [95 % CI, "
             "Student-t over the 5 members]",
             ["city", "M", "best mpc (on test)", "served %", "learned − mpc H=5 cv",
              "learned − best mpc", "hybrid − mpc H=5 cv", "hybrid − best mpc",
              "leaf − mpc H=5 cv", "leaf − best mpc",
              "learned (the hybrid's Q-values: its run folder)",
              "the leaf values' run folder"], diffs)
    markdown("The same against the mpc H=5 cv over the windows: the members' mean per "
             "window paired with the mpc's, points [95 % CI, Student-t over the windows], "
             "and the windows where it serves more",
             ["city", "M", "windows", "learned − mpc H=5 cv", "hybrid − mpc H=5 cv",
              "leaf − mpc H=5 cv"], windows)
    if extra:
        markdown("Leaf variants (`cities/leaf_<variant>_<city>_<M>/`): served fraction, "
                 "points [95 % CI]; − mpc H=5 cv over seeds and over the windows, as above",
                 ["city", "M", "folder", "values' run folder", "leaf H", "λ*", "served %",
                  "leaf − mpc H=5 cv", "over the windows", "leaf − best mpc"], extra)


def markdown(title: str, header: list[str], rows: list[list[str]],
             first: bool = False) -> None:
    """A titled markdown table, a blank line before it unless it is the ``first``."""
    print(("" if first else "\n") + f"{title}\n")
    print("| " + " | ".join(header) + " |")
    print("|---" * len(header) + "|")
    for r in rows:
        print("| " + " | ".join(r) + " |")


if __name__ == "__main__":
    one_line_errors(main)
