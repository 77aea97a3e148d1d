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
    out = None
    if sys.stdout is not None:  # None: started with standard output closed (>&-)
        out = sys.stdout = ReaderLeft(sys.stdout)
    try:
        command()
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
    except BrokenPipeError:  # a write around the wrapper (to the descriptor itself)
        if out is not None:
            out.discard()
    except SystemExit as e:  # a command that ends with sys.exit(main())
        if out is not None and out.left and not e.code:
            sys.exit(128 + 13)
        raise
    if out is not None and out.left:  # as a shell reports a process ended by SIGPIPE;
        sys.exit(128 + 13)  # its files are whole


class ReaderLeft:
    """Standard output that outlives its reader: once a write finds the pipe closed
    (``uabs-eval ... | head``), the rest of the output goes nowhere and the command
    carries on, so the files it writes after its tables (eval.json, the pictures, a
    report) are written whole; before, the broken pipe ended it with nothing written.
    Everything else is the wrapped stream's."""

    def __init__(self, stream):
        self._stream, self.left = stream, False

    def write(self, text: str) -> int:
        if not self.left:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self.discard()
        return len(text)

    def flush(self) -> None:
        if not self.left:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self.discard()

    def discard(self) -> None:
        """From now on the output goes to the null device (the interpreter's last flush
        of what is buffered too)."""
        self.left = True
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, self._stream.fileno())

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def train() -> None:
    _run("uabs_rl.cli.train", "main")


def traces() -> None:
    _run("uabs_rl.cli.traces", "main")


def evaluate() -> None:
    _run("uabs_rl.cli.evaluate", "run_main")


def report() -> None:
    _run("uabs_rl.cli.report", "run_main")
