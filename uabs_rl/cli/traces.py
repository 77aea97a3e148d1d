"""``uabs-traces``: build (or load from the cache) the vehicle traces of a scenario's
splits and say which, one line each."""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

from uabs_rl.cli.hydra import hydra_main
from uabs_rl.config import ConfigError, TracesAppConfig, family_scenarios
from uabs_rl.traces.build import SPLITS, TracesInterrupted, check_names, get_traces
from uabs_rl.traces.cache import cache_path


class Said(logging.Formatter):
    """This command's log lines (conf/hydra/job_logging/uabs_traces.yaml): the bare
    message, ``warning: `` before a warning's."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        return f"warning: {text}" if record.levelno >= logging.WARNING else text


def build(cfg: TracesAppConfig, _output_dir: Path | None = None) -> None:
    """Body of ``uabs-traces``: build or load the requested splits and say which (with
    a ``family``, the training traces of each of its cities too). An interrupted build
    is one line on stderr and exit status 130 (143 after SIGTERM)."""
    if cfg.split not in (*SPLITS, "all"):
        raise ConfigError(f"split must be one of {', '.join(SPLITS)} or all, got "
                          f"{cfg.split!r}.")
    splits = SPLITS if cfg.split == "all" else (cfg.split,)
    check_names(cfg)  # before any SUMO run: every name becomes a cache file's
    jobs = [(cfg.scenario, split, "scenario.name") for split in splits]
    if "train" in splits:
        jobs += [(city, "train", f"family[{i}].name")
                 for i, city in enumerate(family_scenarios(cfg)) if city != cfg.scenario]
    for scenario, split, setting in jobs:
        t0 = time.perf_counter()
        try:
            ts = get_traces(scenario, cfg.traces, split, verbose=False, name_setting=setting)
        except TracesInterrupted as e:
            print(str(e), file=sys.stderr)
            sys.exit(e.exit_code)
        how = "built with SUMO" if ts.source == "built" else "loaded from cache"
        print(f"{scenario.name} {how} in {time.perf_counter() - t0:.2f} s: {ts.summary()}\n"
              f"  {cache_path(scenario, cfg.traces, split, setting)}")
        if ts.steps < scenario.episode_steps + 1:  # as the env refuses them
            print(f"  warning: these {split} traces hold {ts.steps} steps, fewer than an "
                  f"episode's scenario.episode_steps + 1 = {scenario.episode_steps + 1}: "
                  f"uabs-train and uabs-eval refuse them (raise traces.{split}.duration_s, "
                  f"or lower scenario.episode_steps)")


def main() -> None:
    """Entry point of ``uabs-traces``."""
    hydra_main("build_traces", build)


if __name__ == "__main__":
    main()
