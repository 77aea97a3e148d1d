"""The four commands (``uabs-traces``, ``uabs-train``, ``uabs-eval``, ``uabs-report``),
their console entry points and the Hydra plumbing they share: the top of the package,
which nothing else in it imports (the benchmark scripts run under
:func:`one_line_errors`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any


def one_line_errors(main: Callable[[], Any]) -> None:
    """Run a script's ``main`` (``python benchmarks/<x>.py``) as the commands answer: a
    config or checkpoint error (a misspelt scenario, a population where one member is
    meant) is one line on stderr and exit status 2, not a traceback."""
    import sys

    from hydra.errors import HydraException

    from uabs_rl.config import ConfigError
    from uabs_rl.runs.checkpoint import CheckpointError

    try:
        main()
    except (ConfigError, CheckpointError) as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    except HydraException as e:  # a composition of a scenario or preset typed: its
        # message as uabs-train gives it (the options of a group, the closest keys)
        from uabs_rl.cli.hydra import composition_error

        cause = f"\n{e.__cause__}" if e.__cause__ is not None else ""
        print(f"error: {composition_error(f'{e}{cause}')}", file=sys.stderr)
        sys.exit(2)
