"""Evaluation at the scale of a city: a learned policy on every test window of a large
scenario, timed and weighed as a user meets it, one `uabs-eval` process per (city, M).

    python benchmarks/eval_scale.py outputs/runs/<run>/seed=0 --at city:25 bologna:25 bologna:10

For each pair it runs ``uabs-eval RUN scenario=CITY scenario.n_uabs=M`` (the learned
policy, its best checkpoint, the test split), and prints the command's wall time (start
to exit: imports, traces, the network, the evaluation, the files it writes), the
evaluation's own time and the process's peak resident memory as ``uabs-eval`` reports
them, and whether they stay within the targets (``--max-s``, ``--max-mib``: 1 min and
2 GB by default). The run must have an observation whose size does not depend on M and
the area (``obs=egocentric``, for example ``experiment=generalist``). Exit status 1 when
a pair misses a target.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

LAST = re.compile(r"evaluated (\d+) polic(?:y|ies) in ([\d.]+) s, peak memory (\d+) MiB")
WINDOWS = re.compile(r", (\d+) windows of (\d+) steps")


def measure(run: Path, city: str, m: int, threads: int | None) -> dict:
    """One ``uabs-eval`` of the learned policy on CITY's test windows at M UABS."""
    with tempfile.TemporaryDirectory() as out:
        cmd = [sys.executable, "-m", "uabs_rl.cli.evaluate", str(run),
               *([] if city == "home" else [f"scenario={city}"]), f"scenario.n_uabs={m}",
               "--out", out]
        env = None if threads is None else {**os.environ, "OMP_NUM_THREADS": str(threads)}
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"uabs-eval failed on {city}:{m}:\n{proc.stderr.strip() or proc.stdout}")
    last, win = LAST.search(proc.stdout), WINDOWS.search(proc.stdout)
    if last is None or win is None:
        sys.exit(f"uabs-eval on {city}:{m} printed no time and memory line:\n{proc.stdout}")
    served = re.search(r"^\s*learned\s.*?([\d.]+) %", proc.stdout, re.M)
    return {"city": city, "m": m, "windows": int(win[1]), "steps": int(win[2]),
            "wall_s": wall, "eval_s": float(last[2]), "peak_mib": int(last[3]),
            "served": served[1] + " %" if served else "?"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a run folder (a member's, seed=N) or a .pt")
    ap.add_argument("--at", nargs="+", required=True, help="CITY:M pairs (home: the run's)")
    ap.add_argument("--max-s", type=float, default=60.0, help="target wall seconds")
    ap.add_argument("--max-mib", type=float, default=2048.0, help="target peak MiB")
    ap.add_argument("--threads", type=int, help="OMP_NUM_THREADS of each uabs-eval")
    args = ap.parse_args()
    rows = []
    for at in args.at:
        city, _, m = at.partition(":")
        if not m.isdigit():
            sys.exit(f"--at {at}: give CITY:M, for example bologna:25")
        rows.append(measure(args.run, city, int(m), args.threads))
        r = rows[-1]
        print(f"{r['city']}:{r['m']} done: {r['wall_s']:.1f} s", file=sys.stderr)
    print(f"| city | M | windows x steps | served | wall s (command) | eval s | peak MiB | "
          f"within {args.max_s:.0f} s and {args.max_mib:.0f} MiB |")
    print("|---|---|---|---|---|---|---|---|")
    ok = True
    for r in rows:
        fits = r["wall_s"] <= args.max_s and r["peak_mib"] <= args.max_mib
        ok &= fits
        print(f"| {r['city']} | {r['m']} | {r['windows']} x {r['steps']} | {r['served']} | "
              f"{r['wall_s']:.1f} | {r['eval_s']:.1f} | {r['peak_mib']} | "
              f"{'yes' if fits else 'NO'} |")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
