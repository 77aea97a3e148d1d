"""Doors to other frameworks. :mod:`uabs_rl.interop.pettingzoo`: the env as a PettingZoo
``ParallelEnv`` (needs the ``interop`` extra: ``pip install -e ".[interop]"``)."""
