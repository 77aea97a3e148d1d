"""A run folder has one writer and one identity.

- :class:`RunLock`: an advisory lock (``flock``) on ``<run>/.lock``, held by the process
  that writes the run for as long as it runs. A second writer is refused with one line
  naming the PID that holds it; the kernel drops the lock when its holder dies (kill -9
  included), so a stale lock is taken over without anyone removing a file.
- :func:`claim`: a new run takes its folder, or, when another process took the same
  automatically named folder first (two identical commands started in the same second),
  a fresh sibling ``<name>-2``, ``-3``, ...; a folder the user named is never swapped.
- ``<run>/run.json``: the run's identity (a random id, when and how it started), written
  once when the run starts. Every checkpoint carries the id (``state["run"]``), and a
  checkpoint of another run is refused where it does not belong
  (:func:`check_identity`).
"""

from __future__ import annotations

import errno
import fcntl
import json
import logging
import os
import shutil
import socket
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

from uabs_rl.config import ConfigError

LOCK_NAME = ".lock"
IDENTITY_NAME = "run.json"


class RunFolderError(ConfigError):
    """A run folder is held by another process, unwritable, or holds another run."""


class RunLock:
    """``flock`` on ``<run_dir>/.lock``; :meth:`acquire` returns False while another
    process holds it (:meth:`holder` says which)."""

    def __init__(self, run_dir: Path):
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK_NAME
        self._file = None

    def acquire(self) -> bool:
        f = open(self.path, "a+")  # held open for the lifetime of the run
        try:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.close()
            return False
        f.seek(0)
        f.truncate()
        f.write(json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                            "since": time.strftime("%Y-%m-%d %H:%M:%S")}) + "\n")
        f.flush()
        self._file = f
        return True

    def holder(self) -> str:
        """Who holds the lock, as a phrase: "pid 123 on host since ..."."""
        try:
            info = json.loads(self.path.read_text() or "{}")
        except (OSError, json.JSONDecodeError):
            info = {}
        if not info.get("pid"):
            return "another process"
        return f"pid {info['pid']} on {info.get('host', '?')} since {info.get('since', '?')}"

    def release(self) -> None:
        if self._file is not None:
            self._file.close()  # closing drops the flock
            self._file = None


def _check_writable(run_dir: Path) -> None:
    """The folder exists (or can be made) and takes a file, else one line saying why."""
    if run_dir.exists() and not run_dir.is_dir():
        raise RunFolderError(f"the run folder {run_dir} is a file: set hydra.run.dir (or "
                             f"resume=) to a folder.")
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        probe = run_dir / f".probe{os.getpid()}"
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise RunFolderError(f"cannot write into the run folder {run_dir} ({e.strerror}): "
                             f"choose a writable place with hydra.run.dir=... (or fix the "
                             f"folder's permissions).") from None


def lock(run_dir: Path) -> RunLock:
    """Hold ``run_dir``'s lock, or refuse naming the process that holds it."""
    _check_writable(run_dir)
    lk = RunLock(run_dir)
    if not lk.acquire():
        raise RunFolderError(f"{run_dir} is being written by another uabs-train process "
                             f"({lk.holder()}): wait for it to end, or stop it and then "
                             f"resume={run_dir}.")
    return lk


def holds_run(run_dir: Path) -> bool:
    """True when ``run_dir`` holds a run's records (it has started training)."""
    return (run_dir / "metrics.jsonl").exists() or (run_dir / IDENTITY_NAME).exists()


def claim(run_dir: Path, auto_named: bool, sweep_dir: Path | None = None,
          on_move: Callable[[Path], None] | None = None) -> tuple[Path, RunLock]:
    """The folder a new run writes into, locked. ``run_dir`` when it is free. When
    another process holds or already filled it and its name was chosen automatically
    (two identical commands started in the same second), the first free sibling
    ``<run_dir>-k`` (k = 2, 3, ...), or for a sweep's job ``<sweep_dir>-k/<job folder>``,
    made with an exclusive mkdir so two processes never pick the same one;
    ``on_move(folder)`` then writes the run's own Hydra files there. A folder the user
    named is never swapped: a second writer is refused."""
    _check_writable(run_dir)
    lk = RunLock(run_dir)
    if lk.acquire():
        if not (auto_named and holds_run(run_dir)):
            return run_dir, lk
        lk.release()
    elif not auto_named:
        raise RunFolderError(f"{run_dir} is being written by another uabs-train process "
                             f"({lk.holder()}): choose another hydra.run.dir, or wait for "
                             f"it to end.")
    for k in range(2, 1000):
        if sweep_dir is None:
            other = run_dir.with_name(f"{run_dir.name}-{k}")
        else:
            other = sweep_dir.with_name(f"{sweep_dir.name}-{k}") / run_dir.relative_to(
                sweep_dir)
            other.parent.mkdir(parents=True, exist_ok=True)
        try:
            other.mkdir()
        except FileExistsError:
            continue
        if on_move is not None:
            on_move(other)
        _move_log_handlers(run_dir, other)
        logging.getLogger(__name__).warning(
            "%s was taken by another run started at the same time: this run writes into %s",
            run_dir, other)
        return other, lock(other)
    raise RunFolderError(f"no free folder beside {run_dir}: choose hydra.run.dir=...")


def _move_log_handlers(old: Path, new: Path) -> None:
    """Point the log files Hydra opened in ``old`` at the same names in ``new``."""
    for h in logging.getLogger().handlers:
        path = Path(getattr(h, "baseFilename", "") or ".")
        if isinstance(h, logging.FileHandler) and path.parent == old.resolve():
            h.acquire()
            try:
                h.close()
                h.baseFilename = str(new.resolve() / path.name)
                h.stream = h._open()
            finally:
                h.release()


# ----------------------------------------------------------------------------- identity
def identity(run_dir: Path) -> dict[str, Any]:
    """The run's identity from ``run.json``, written now if the folder has none yet
    (a new run, or a run started before identities existed)."""
    path = Path(run_dir) / IDENTITY_NAME
    if path.is_file():
        try:
            ident = json.loads(path.read_text())
            if isinstance(ident, dict) and isinstance(ident.get("id"), str):
                return ident
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            pass
        raise RunFolderError(f"{path} is damaged (not the run's identity record): restore "
                             f"it, or remove it to adopt the run's checkpoints as they are.")
    ident = {"id": uuid.uuid4().hex, "started": time.strftime("%Y-%m-%d %H:%M:%S"),
             "host": socket.gethostname(), "command": " ".join(sys.argv)}
    tmp = path.with_name(f".{IDENTITY_NAME}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(ident, indent=1) + "\n")
    os.replace(tmp, path)
    return ident


def check_identity(state: dict, run_dir: Path, source: Path) -> None:
    """Refuse a checkpoint that another run wrote (copied into this folder): its run id
    must be this folder's. Checkpoints written before identities existed carry none and
    pass (their settings are still checked against the run's own)."""
    theirs = (state.get("run") or {}).get("id") if isinstance(state.get("run"), dict) else None
    path = Path(run_dir) / IDENTITY_NAME
    if theirs is None or not path.is_file():
        return
    ours = identity(run_dir)["id"]
    if theirs != ours:
        raise RunFolderError(
            f"{source} belongs to another run (run id {theirs[:8]}, written in a folder "
            f"named {state['run'].get('folder', '?')!r}), not to {run_dir} (run id "
            f"{ours[:8]}): it was copied here. Put this run's own checkpoint back, or "
            f"resume the run it belongs to.")


def write_error(e: OSError | RuntimeError, run_dir: Path) -> Exception:
    """A failed write of a run's files as one line saying why and what to do; ``e``
    itself when it is not about the run folder."""
    if not run_dir.is_dir():
        return RunFolderError(f"the run folder {run_dir} was removed or moved while the "
                              f"run was writing it: the run stopped; nothing more was "
                              f"written.")
    where = getattr(e, "filename", None) or run_dir
    if getattr(e, "errno", None) == errno.ENOSPC or "unexpected pos" in str(e):
        free = shutil.disk_usage(run_dir).free / 2**20
        return RunFolderError(f"no space left on the device while writing {where} "
                              f"({free:.0f} MiB free): free some space, then continue with "
                              f"resume={run_dir} (the last complete checkpoint is kept).")
    if getattr(e, "errno", None) in (errno.EACCES, errno.EROFS, errno.EPERM):
        return RunFolderError(f"cannot write {where} ({e.strerror}): make the run folder "
                              f"writable, then continue with resume={run_dir}.")
    return e
