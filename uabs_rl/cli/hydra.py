"""The Hydra plumbing shared by the ``uabs-train`` and ``uabs-traces`` entry points."""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from uabs_rl.config import (
    CONF_DIR,
    ConfigError,
    check_duplicate_overrides,
    check_moved_overrides,
    register_configs,
    to_container,
)
from uabs_rl.training.checkpoint import CheckpointError, Interrupted
from uabs_rl.training.runfolder import Before


def start_folders(argv: list[str]) -> list[Path]:
    """The folders a command line may write a run in or under: those it names
    (``hydra.run.dir``, ``hydra.sweep.dir``, ``resume``) and the default run and sweep
    folders (``outputs/runs``, ``outputs/multirun``)."""
    out = [Path("outputs/runs"), Path("outputs/multirun")]
    for a in argv:
        key, _, value = a.partition("=")
        if key in ("hydra.run.dir", "hydra.sweep.dir", "resume") and value.strip("'\""):
            out.append(Path(value.strip("'\"").replace("\\'", "'")))
    return out


def path_safe(text: str) -> str:
    """``text`` (a run's overrides) as one folder name: a ``/`` in a value (a file path,
    ``..``) would nest the run folder or lead it out of ``outputs/``; it reads ``%2F``."""
    return str(text).replace("/", "%2F")


def hydra_main(config_name: str, body: Callable[..., Any],
               pass_overrides: bool = False) -> None:
    """Run ``body(cfg, output_dir[, overrides])`` under ``@hydra.main`` with
    ``conf/<config_name>``: the config arrives as checked dataclasses; a config or
    checkpoint error is one line on stderr and exit status 2, Ctrl-C one line and
    status 130 (143 after SIGTERM), never a traceback."""
    interrupted = ("interrupted: the last checkpoint, if the run had one, is kept"
                   if pass_overrides else "interrupted")
    import hydra
    from hydra.core.hydra_config import HydraConfig

    def app(dcfg) -> None:
        hc = HydraConfig.get()
        # a log file that cannot be written (a full disk) loses lines, not the run
        # (the run says what failed, in one line); no "--- Logging error ---" traces
        logging.raiseExceptions = False
        extra = (list(hc.overrides.task),) if pass_overrides else ()
        try:
            body(to_container(dcfg), Path(hc.runtime.output_dir), *extra)
        except (ConfigError, CheckpointError) as e:
            # only what this invocation made: never a folder or file that was there
            before.undo_start(Path(hc.runtime.output_dir),
                              {".hydra", ".lock", "run.json", f"{hc.job.name}.log"})
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
        except Interrupted as e:
            print(str(e), file=sys.stderr)
            sys.exit(getattr(e, "exit_code", 130))
        except KeyboardInterrupt as e:  # a second Ctrl-C, or one outside training
            print(str(e) or interrupted, file=sys.stderr)
            sys.exit(getattr(e, "exit_code", 130))

    try:  # before Hydra, whose own message would not say what to type instead
        check_moved_overrides(sys.argv[1:])
        check_duplicate_overrides(sys.argv[1:])
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    before = Before(start_folders(sys.argv[1:]))  # what exists before Hydra makes folders
    register_configs()
    # ${prefixed:_,<text>}: "_<text>", or nothing when <text> is empty (run folder names)
    OmegaConf.register_new_resolver("prefixed", lambda sep, text: f"{sep}{text}" if text
                                    else "", replace=True)
    # ${path_safe:<text>}: <text> as one folder name (run and sweep job folder names)
    OmegaConf.register_new_resolver("path_safe", path_safe, replace=True)
    hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=config_name)(app)()
