"""Learners (algorithms) and their registry, keyed by ``algo.name``.

:mod:`uabs_rl.algorithms.base` defines the interface the trainer uses;
:mod:`uabs_rl.algorithms.replay` the replay every learner samples;
:mod:`uabs_rl.algorithms.dqn3` the paper's 3DQN (``algo=dqn3``, the default). Every other
module of this package is an algorithm too, imported (and so registered) here: a new
learner is one module in this folder and one ``conf/algo/<name>.yaml``.
"""

import importlib
import pkgutil

from uabs_rl.algorithms.base import (
    ALGORITHMS,
    Algorithm,
    Dims,
    algorithm_class,
    make_algorithm,
    register,
)

for _module in pkgutil.iter_modules(__path__):
    if _module.name not in ("base", "replay"):
        importlib.import_module(f"{__name__}.{_module.name}")

__all__ = ["ALGORITHMS", "Algorithm", "Dims", "algorithm_class", "make_algorithm", "register"]
