"""Learners (algorithms) and their registry, keyed by ``algo.name``.

:mod:`uabs_rl.algorithms.base` defines the interface the trainer uses;
:mod:`uabs_rl.algorithms.replay` the replay every learner samples;
:mod:`uabs_rl.algorithms.dqn3` the paper's 3DQN (``algo=dqn3``, the default).
Importing this package registers every algorithm module listed below.
"""

from uabs_rl.algorithms import dqn3  # noqa: F401  (registers algo=dqn3)
from uabs_rl.algorithms.base import (
    ALGORITHMS,
    Algorithm,
    Dims,
    algorithm_class,
    make_algorithm,
    register,
)

__all__ = ["ALGORITHMS", "Algorithm", "Dims", "algorithm_class", "make_algorithm", "register"]
