from __future__ import annotations

import contextlib
import importlib
import importlib.util
import io
import logging
import os
import signal
import sys
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path

import pytest

from uabs_rl.config import compose
from uabs_rl.traces.build import get_traces

# A small but real SUMO case: 20 vehicles, 60 s recorded after 10 s of warm-up.
SMALL_TRACES = [
    "scenario.sumo.fleet_size=20",
    "traces.train.n_sims=2",
    "traces.train.duration_s=60",
    "traces.train.warmup_s=10",
    "traces.eval.n_sims=1",
    "traces.eval.duration_s=60",
    "traces.eval.warmup_s=10",
]


def load_benchmark(name: str):
    """The script benchmarks/<name>.py as a module (its functions, without running it)."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"benchmark_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def thread_count(n: int):
    """torch's thread count set to ``n`` for the block; restored after."""
    import torch
    threads = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def another_thread_count():
    """torch's thread count changed for the block (1, or 2 where it is 1), as the thread
    governor changes it on a busy machine; restored after."""
    import torch
    return thread_count(1 if torch.get_num_threads() > 1 else 2)


def compose_cfg(config_name: str, overrides: list[str]):
    """Compose a config exactly as the CLI would, and return it as dataclasses."""
    return compose(config_name, overrides)


@pytest.fixture(scope="session")
def trace_cache(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("trace_cache")


@pytest.fixture(scope="session")
def small_traces_cfg(trace_cache):
    return compose_cfg("build_traces", SMALL_TRACES + [f"traces.cache_dir={trace_cache}"])


@pytest.fixture(scope="session")
def train(small_traces_cfg):
    """The small case's training traces (2 sims x 60 s, 20 vehicles)."""
    return get_traces(small_traces_cfg.scenario, small_traces_cfg.traces, "train")


@pytest.fixture(scope="session")
def held_out(small_traces_cfg):
    """The small case's held-out traces (1 sim x 60 s)."""
    return get_traces(small_traces_cfg.scenario, small_traces_cfg.traces, "eval")


def _ignore_hang_up(signum, frame) -> None:
    """This test process survives a hang-up as under nohup (a Python handler, unlike
    SIG_IGN, is not inherited by the commands the tests start)."""


def pytest_configure(config) -> None:
    """Started under nohup or as a background job (``cmd &``), this process ignores SIGHUP
    or SIGINT, and every command a test starts would inherit that (an ignored signal
    stays ignored across exec): the tests that stop a run or a trace build with a
    signal would fail. Python handlers in their place (a hang-up still ignored here,
    Ctrl-C a KeyboardInterrupt as pytest expects) let the commands start with the
    default dispositions, as from a terminal."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if hasattr(signal, "SIGHUP") and signal.getsignal(signal.SIGHUP) is signal.SIG_IGN:
        signal.signal(signal.SIGHUP, _ignore_hang_up)


@dataclass
class Ran:
    """What a command run by :func:`run_command` left: its exit status and output, as
    ``subprocess.run(..., capture_output=True, text=True)`` reports them."""

    args: list[str]
    returncode: int
    stdout: str
    stderr: str


def _print_warning(message, category, filename, lineno, file=None, line=None) -> None:
    sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


ENTRY = {"train": "main", "traces": "main", "evaluate": "run_main", "report": "run_main"}


def run_command(module: str, *args: str, cwd: Path | None = None,
                env: dict[str, str] | None = None) -> Ran:
    """``python -m uabs_rl.cli.<module> args`` run in this process: the module's entry
    point with ``sys.argv`` set, in ``cwd``, with ``env`` added to the environment, its
    standard output and error captured and
    its exit status taken from ``SystemExit`` (an exception it lets out is a traceback on
    stderr and status 1, as Python reports it). For the refusals, which end before any
    work; a few tests run the real commands as subprocesses (test_train's
    test_cli_entry_point, test_faults, test_bologna's walkthrough, the kills and signals).
    Logging and warnings are as a fresh interpreter has them (what it would print on
    stderr is in ``stderr``); what the command sets for its own process (sys.argv, the
    working folder, environment variables, logging, signal handlers, torch's threads) is
    put back afterwards."""
    import torch

    entry = getattr(importlib.import_module(f"uabs_rl.cli.{module}"), ENTRY[module])
    loggers = [logging.getLogger(), *(lg for lg in logging.Logger.manager.loggerDict.values()
                                      if isinstance(lg, logging.Logger))]
    saved_loggers = [(lg, lg.level, lg.disabled, lg.propagate, lg.handlers[:])
                     for lg in loggers]
    saved = (sys.argv[:], os.getcwd(), dict(os.environ), logging.raiseExceptions,
             {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)},
             torch.get_num_threads())
    out, err = io.StringIO(), io.StringIO()
    code: int | str | None = 0
    try:
        sys.argv = [f"uabs_rl/cli/{module}.py", *args]
        if cwd is not None:
            os.chdir(cwd)
        os.environ.update(env or {})
        # logging and warnings as a fresh interpreter has them (pytest captures both):
        # the root logger without handlers at WARNING, Python's default warning filters,
        # a warning printed on stderr
        logging.root.handlers[:] = []
        logging.root.setLevel(logging.WARNING)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
                warnings.catch_warnings():
            warnings.resetwarnings()
            for category in (DeprecationWarning, PendingDeprecationWarning, ImportWarning,
                             ResourceWarning):
                warnings.filterwarnings("ignore", category=category)
            warnings.filterwarnings("default", category=DeprecationWarning, module="__main__")
            warnings.showwarning = _print_warning
            try:
                entry()
            except SystemExit as e:
                code = e.code
                if isinstance(code, str):  # sys.exit("message"): the message, status 1
                    print(code, file=sys.stderr)
                    code = 1
            except Exception:
                traceback.print_exc()
                code = 1
    finally:
        argv, where, env, raise_exceptions, handlers, threads = saved
        sys.argv = argv
        os.chdir(where)
        os.environ.clear()
        os.environ.update(env)
        logging.raiseExceptions = raise_exceptions
        for s, h in handlers.items():
            signal.signal(s, h)
        torch.set_num_threads(threads)
        for lg, level, disabled, propagate, kept in saved_loggers:
            for h in lg.handlers:
                if h not in kept:
                    h.close()  # the command's log file, or a stream it captured
            lg.handlers[:] = kept
            lg.setLevel(level)
            lg.disabled, lg.propagate = disabled, propagate
    return Ran([module, *args], 0 if code is None else int(code), out.getvalue(),
               err.getvalue())
