"""The Hydra plumbing shared by the ``uabs-train`` and ``uabs-traces`` entry points."""

from __future__ import annotations

import shutil
import sys
import time
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
from uabs_rl.training.runfolder import RunLock

_STARTED = time.time()


def _remove_if_empty(run_dir: Path) -> None:
    """Remove the folder Hydra made for a run that failed its start-up checks: only
    when it holds nothing but Hydra's config and log (never a run's results)."""
    hydra_dir = run_dir / ".hydra"
    if not hydra_dir.is_dir() or run_dir.resolve() == Path.cwd().resolve():
        return
    if hydra_dir.stat().st_mtime < _STARTED - 1.0:  # an earlier run's folder (a resume)
        return
    names = {p.name for p in run_dir.iterdir()}
    if not names <= {".hydra", ".lock"} | {p.name for p in run_dir.glob("*.log")}:
        return
    lock = RunLock(run_dir)
    if lock.acquire():  # never a folder another process is writing
        shutil.rmtree(run_dir, ignore_errors=True)
        lock.release()


def hydra_main(config_name: str, body: Callable[..., Any],
               pass_overrides: bool = False) -> None:
    """Run ``body(cfg, output_dir[, overrides])`` under ``@hydra.main`` with
    ``conf/<config_name>``: the config arrives as checked dataclasses; a config or
    checkpoint error is one line on stderr and exit status 2, Ctrl-C one line and
    status 130 (143 after SIGTERM), never a traceback."""
    interrupted = ("interrupted: the last checkpoint is kept" if pass_overrides
                   else "interrupted")
    import hydra
    from hydra.core.hydra_config import HydraConfig

    def app(dcfg) -> None:
        hc = HydraConfig.get()
        extra = (list(hc.overrides.task),) if pass_overrides else ()
        try:
            body(to_container(dcfg), Path(hc.runtime.output_dir), *extra)
        except (ConfigError, CheckpointError) as e:
            _remove_if_empty(Path(hc.runtime.output_dir))
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
    register_configs()
    # ${prefixed:_,<text>}: "_<text>", or nothing when <text> is empty (run folder names)
    OmegaConf.register_new_resolver("prefixed", lambda sep, text: f"{sep}{text}" if text
                                    else "", replace=True)
    hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=config_name)(app)()
