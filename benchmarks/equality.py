"""The equality set: ten short trainings whose ``metrics.jsonl`` files a change that
claims to keep behaviour must leave byte for byte as they were.

    python benchmarks/equality.py --check benchmarks/equality_record.json  # the committed record
    python benchmarks/equality.py --record /tmp/eq_before.json   # before the change
    python benchmarks/equality.py --check /tmp/eq_before.json    # after: exit 1 if any differs
    python benchmarks/equality.py --check /tmp/eq_before.json --set train.compile_update=false

The set covers the three masking modes (``experiment=smoke``), a population of two
(``train.population=2``: one file per member), the four channel variants and 40 episodes
of the paper's defaults (``train.episodes=40``: the main job's network, compiled env step
and update). Each run is ``uabs-train`` in its own process with ``train.threads=1`` (the
thread count enters float rounding, and on a busy machine the governor would change it
mid-run), into a fresh folder under ``--out`` (a temporary one by default). The record is
the md5 of every metrics file, with the CPU and the torch version it was recorded on
(float rounding depends on both: compare records from the same kind of machine);
``--check`` prints each run as ``same`` or ``DIFFERS``. ``benchmarks/equality_record.json``
is the record of the compiled default (recorded twice, identical), on the machine it
names; recorded again (twice, identical) when a population's value and advantage heads
changed to a faster product that rounds otherwise (``StackedQNet``): the two population
files changed, the other eight stayed as they were (its machine line moved from AVX2 to
AVX512, torch's capability where it was recorded again; the code before the change gives
the old population files there too).
``--set`` appends overrides to every run (a path kept beside a new default: the eager
update after ``train.compile_update`` became the default).
About 3 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SMOKE = ["experiment=smoke"]
RUNS: dict[str, list[str]] = {
    "smoke_penalty": [*SMOKE, "masking=penalty"],
    "smoke_flat": [*SMOKE, "masking=flat"],
    "smoke_rank": [*SMOKE, "masking=rank"],
    "smoke_population": [*SMOKE, "masking=rank", "train.population=2"],
    "channel_los_expected": [*SMOKE, "channel.los_mode=expected"],
    "channel_los": [*SMOKE, "channel.los_mode=los"],
    "channel_shadowing": [*SMOKE, "channel.shadow_fading=true"],
    "channel_outside_beam_0db": [*SMOKE, "channel.outside_beam_gain_db=0"],
    "paper_40_episodes": ["train.episodes=40"],
}


def train(name: str, overrides: list[str], out: Path, extra: list[str]) -> dict[str, str]:
    """Train one run of the set; the md5 of each of its metrics files, keyed
    ``name`` (a population's ``name/seed=<s>``)."""
    folder = out / name
    cmd = [sys.executable, "-m", "uabs_rl.cli.train", *overrides, *extra, "train.threads=1",
           "train.progress=false", "train.logger=none", f"hydra.run.dir={folder}"]
    ran = subprocess.run(cmd, capture_output=True, text=True)
    if ran.returncode != 0:
        sys.exit(f"{name}: uabs-train failed (exit {ran.returncode}):\n{ran.stderr[-2000:]}")
    files = sorted(folder.rglob("metrics.jsonl"))
    if not files:
        sys.exit(f"{name}: no metrics.jsonl under {folder}")
    return {str(f.parent.relative_to(out)): hashlib.md5(f.read_bytes()).hexdigest()
            for f in files}


def machine() -> dict[str, str]:
    """What the metrics' float rounding depends on, stored beside the md5s."""
    import platform

    import torch

    cpu = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        names = [ln.split(":", 1)[1].strip() for ln in cpuinfo.read_text().splitlines()
                 if ln.startswith("model name")]
        cpu = names[0] if names else cpu
    return {"_cpu": cpu, "_torch": torch.__version__,
            "_capability": torch.backends.cpu.get_cpu_capability()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    what = ap.add_mutually_exclusive_group(required=True)
    what.add_argument("--record", type=Path, help="write the md5 record here")
    what.add_argument("--check", type=Path, help="compare with this record")
    ap.add_argument("--out", type=Path, help="the runs' parent folder (default: a temporary one)")
    ap.add_argument("--only", nargs="+", choices=sorted(RUNS), help="train these runs only")
    ap.add_argument("--set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="overrides appended to every run")
    args = ap.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="uabs_equality_"))
    expected = json.loads(args.check.read_text()) if args.check else None
    here = machine()
    if expected is not None:
        other = {k: (expected[k], v) for k, v in here.items() if k in expected and expected[k] != v}
        if other:
            print(f"warning: recorded on another machine or torch ({other}): "
                  "float rounding may differ without any change of behaviour")
    md5: dict[str, str] = {}
    t0 = time.perf_counter()
    for name in args.only or RUNS:
        got = train(name, RUNS[name], out, args.set)
        md5.update(got)
        for key, h in got.items():
            verdict = "" if expected is None else (
                "  same" if expected.get(key) == h else "  DIFFERS")
            print(f"{key:<32} {h}{verdict}", flush=True)
    print(f"{len(md5)} metrics files in {time.perf_counter() - t0:.0f} s, under {out}")
    if args.record:
        args.record.write_text(json.dumps({**here, **md5}, indent=1, sort_keys=True) + "\n")
        return 0
    differ = [k for k, h in md5.items() if expected.get(k) != h]
    print("identical" if not differ else f"{len(differ)} of {len(md5)} differ: {differ}")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
