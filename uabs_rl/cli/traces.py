"""``uabs-traces``: build (or load from the cache) the vehicle traces of a scenario's
splits and say which, one line each."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from uabs_rl.cli.hydra import hydra_main
from uabs_rl.config import TracesAppConfig, family_scenarios
from uabs_rl.traces.store import SPLITS, TracesInterrupted, cache_path, get_traces


def build(cfg: TracesAppConfig, _output_dir: Path | None = None) -> None:
    """Body of ``uabs-traces``: build or load the requested splits and say which (with
    a ``family``, the training traces of each of its cities too). An interrupted build
    is one line on stderr and exit status 130 (143 after SIGTERM)."""
    splits = SPLITS if cfg.split == "all" else (cfg.split,)
    jobs = [(cfg.scenario, split) for split in splits]
    if "train" in splits:
        jobs += [(city, "train") for city in family_scenarios(cfg)
                 if city != cfg.scenario]
    for scenario, split in jobs:
        t0 = time.perf_counter()
        try:
            ts = get_traces(scenario, cfg.traces, split, verbose=False)
        except TracesInterrupted as e:
            print(str(e), file=sys.stderr)
            sys.exit(e.exit_code)
        how = "built with SUMO" if ts.source == "built" else "loaded from cache"
        print(f"{scenario.name} {how} in {time.perf_counter() - t0:.2f} s: {ts.summary()}\n"
              f"  {cache_path(scenario, cfg.traces, split)}")


def main() -> None:
    """Entry point of ``uabs-traces``."""
    hydra_main("build_traces", build)


if __name__ == "__main__":
    main()
