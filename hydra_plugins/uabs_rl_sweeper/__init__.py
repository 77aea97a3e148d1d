"""The Hydra door of uabs_rl's tuning sweeper (``uabs-train -m hydra/sweeper=optuna``).

Hydra instantiates sweepers only from the ``hydra_plugins`` package, and imports every
module under it whenever any Hydra app starts: this module stays light (no optuna, no
torch) and hands the study to :mod:`uabs_rl.tuning.sweeper`."""

from __future__ import annotations

from typing import Any

from hydra.plugins.sweeper import Sweeper


class OptunaSweeper(Sweeper):
    """Bayesian search over a run's settings with Optuna, one trial a ``uabs-train``
    job (conf/hydra/sweeper/optuna.yaml; docs/tuning.md)."""

    def __init__(self, **settings: Any) -> None:
        self.settings = settings  # the hydra.sweeper node, less _target_
        self.hydra_context = self.config = self.launcher = None
        self.task_function = None

    def setup(self, *, hydra_context, task_function, config) -> None:
        self.hydra_context, self.task_function, self.config = (hydra_context,
                                                               task_function, config)

    def sweep(self, arguments: list[str]) -> Any:
        from uabs_rl.tuning.sweeper import run_study

        return run_study(self, arguments)
