"""Console entry points (``uabs-train``, ``uabs-traces``, ``uabs-eval``,
``uabs-report``). Each imports its command inside a guard, so Ctrl-C while torch and
Hydra load (a few seconds) is one line and exit status 130, not a traceback."""

from __future__ import annotations

import importlib
import os
import signal
import sys


def _run(module: str, func: str) -> None:
    # Ctrl-C while torch, numpy and Hydra load is held until they have loaded (a
    # KeyboardInterrupt inside a library's import can leave it half made, and some
    # import paths catch it), then ends the command with one line and status 130
    held: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: held.append(signum))
    try:
        command = getattr(importlib.import_module(module), func)
    finally:
        signal.signal(signal.SIGINT, previous)
    if held:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
    try:
        command()
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
    except BrokenPipeError:  # `uabs-report ... | head`: the reader left; what was
        # written to files is complete, and the rest of standard output goes nowhere
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        sys.exit(128 + 13)  # as a shell reports a process ended by SIGPIPE


def train() -> None:
    _run("uabs_rl.cli.train", "main")


def traces() -> None:
    _run("uabs_rl.cli.traces", "main")


def evaluate() -> None:
    _run("uabs_rl.cli.evaluate", "run_main")


def report() -> None:
    _run("uabs_rl.cli.report", "run_main")
