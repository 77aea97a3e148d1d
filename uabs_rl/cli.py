"""The Hydra plumbing shared by the ``uabs-train`` and ``uabs-traces`` entry points."""

from __future__ import annotations

import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from uabs_rl.checkpoint import CheckpointError, Interrupted
from uabs_rl.config import CONF_DIR, ConfigError, register_configs, to_container

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
    if names <= {".hydra"} | {p.name for p in run_dir.glob("*.log")}:
        shutil.rmtree(run_dir, ignore_errors=True)


def hydra_main(config_name: str, body: Callable[..., Any],
               pass_overrides: bool = False) -> None:
    """Run ``body(cfg, output_dir[, overrides])`` under ``@hydra.main`` with
    ``conf/<config_name>``: the config arrives as checked dataclasses; a config or
    checkpoint error is one line on stderr and exit status 2, Ctrl-C one line and
    status 130, never a traceback."""
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
            sys.exit(130)
        except KeyboardInterrupt:
            print("interrupted: the last checkpoint is kept", file=sys.stderr)
            sys.exit(130)

    register_configs()
    hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=config_name)(app)()
