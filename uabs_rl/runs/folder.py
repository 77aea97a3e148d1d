"""A run folder has one writer and one identity.

- :class:`RunLock`: an advisory lock (``flock``) on the run folder itself, held by the
  process that writes the run for as long as it runs; ``<run>/.lock`` only names the
  holder. A second writer is refused with one line naming the PID that holds it; the
  kernel drops the lock when its holder dies (kill -9 included), so a stale lock is
  taken over without anyone removing a file, and removing ``.lock`` under a live holder
  does not free the folder (the lock is on the folder, which stays while it is written).
- :func:`claim`: a new run takes its folder, or, when another process took the same
  automatically named folder first (two identical commands started in the same second),
  a fresh sibling ``<name>-2``, ``-3``, ...; a folder the user named is never swapped.
- ``<run>/run.json``: the run's identity (a random id, when and how it started), written
  once when the run starts. Every checkpoint carries the id (``state["run"]``), and a
  checkpoint of another run is refused where it does not belong
  (:func:`check_identity`).
"""

from __future__ import annotations

import enum
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
from uabs_rl.paths import atomic_file, atomic_write
from uabs_rl.runs.layout import RunFolder


class RunFolderError(ConfigError):
    """A run folder is held by another process, unwritable, or holds another run."""


class RunLock:
    """``flock`` on the folder ``run_dir`` (on ``<run_dir>/.lock`` where the file system
    cannot lock a folder); :meth:`acquire` returns False while another process holds it
    (:meth:`holder` says which, from ``.lock``)."""

    def __init__(self, run_dir: Path):
        self.run_dir = Path(run_dir)
        self.path = RunFolder(self.run_dir).lock
        self._fd: int | None = None

    def _locked_fd(self) -> int | None:
        """A descriptor of the folder (or, where folders cannot be locked, of ``.lock``)
        holding the exclusive lock, or None while another process holds it."""
        for path, flags in ((self.run_dir, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0)),
                            (self.path, os.O_RDWR | os.O_CREAT)):
            fd = os.open(path, flags, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return fd
            except BlockingIOError:
                os.close(fd)
                return None
            except OSError:  # a file system that locks files only (NFS without flock)
                os.close(fd)
                if path == self.path:
                    raise
        return None

    def acquire(self, record: bool = True) -> bool:
        """Take the lock; with ``record``, write who holds it into ``.lock`` (else
        :meth:`record` does, once the holder's start-up checks have passed: a refused
        command leaves ``.lock`` as it was)."""
        fd = self._locked_fd()
        if fd is None:
            return False
        self._fd = fd  # held open for the lifetime of the run
        if record:
            self.record()
        return True

    def record(self) -> None:
        """Write who holds the lock into ``.lock``, for a second writer's refusal."""
        info = json.dumps({"pid": os.getpid(), "host": socket.gethostname(),
                           "since": time.strftime("%Y-%m-%d %H:%M:%S")}) + "\n"
        try:  # who holds it, for the refusal's message; the lock does not depend on it
            atomic_write(self.path, info)
        except OSError:
            pass

    def holder(self) -> str:
        """Who holds the lock, as a phrase: "pid 123 on host since ..."."""
        try:
            info = json.loads(self.path.read_text() or "{}")
        except (OSError, json.JSONDecodeError):
            info = {}
        if not isinstance(info, dict) or not info.get("pid"):
            return "another process"
        return f"pid {info['pid']} on {info.get('host', '?')} since {info.get('since', '?')}"

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock
            self._fd = None


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
    """Hold ``run_dir``'s lock (:meth:`RunLock.record` names the holder once the
    start-up checks pass), or refuse naming the process that holds it."""
    _check_writable(run_dir)
    lk = RunLock(run_dir)
    if not lk.acquire(record=False):
        raise RunFolderError(f"{run_dir} is being written by another uabs-train process "
                             f"({lk.holder()}): wait for it to end, or stop it and then "
                             f"resume={run_dir}.")
    return lk


def holds_run(run_dir: Path) -> bool:
    """True when ``run_dir`` holds a run's records (it has started training)."""
    folder = RunFolder(run_dir)
    return folder.metrics.exists() or folder.identity.exists()


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
    if lk.acquire(record=False):
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
    path = RunFolder(run_dir).identity
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
    atomic_write(path, json.dumps(ident, indent=1) + "\n")
    return ident


def check_identity(state: dict, run_dir: Path, source: Path) -> None:
    """Refuse a checkpoint that another run wrote (copied into this folder): its run id
    must be this folder's. Checkpoints written before identities existed carry none and
    pass (their settings are still checked against the run's own)."""
    theirs = (state.get("run") or {}).get("id") if isinstance(state.get("run"), dict) else None
    path = RunFolder(run_dir).identity
    if theirs is None or not path.is_file():
        return
    ours = identity(run_dir)["id"]
    if theirs != ours:
        raise RunFolderError(
            f"{source} belongs to another run (run id {theirs[:8]}, written in a folder "
            f"named {state['run'].get('folder', '?')!r}), not to {run_dir} (run id "
            f"{ours[:8]}): it was copied here. Put this run's own checkpoint back, or "
            f"resume the run it belongs to.")


def _then(run_dir: Path) -> str:
    """What the user does once the cause is fixed: resume from the last checkpoint, or,
    where the run stopped before its first one, start it again."""
    folder = RunFolder(run_dir)
    if folder.last.is_file() or folder.member_checkpoints():
        return f"continue with resume={run_dir} (its last complete checkpoint is kept)"
    return (f"start the run again (it stopped before its first checkpoint; remove "
            f"{run_dir} or choose another hydra.run.dir)")


def write_error(e: OSError | RuntimeError, run_dir: Path) -> Exception:
    """A failed write of a run's files as one line saying why and what to do; ``e``
    itself when it is not about the run folder."""
    if not run_dir.is_dir():
        return RunFolderError(f"the run folder {run_dir} was removed or moved while the "
                              f"run was writing it: the run stopped; nothing more was "
                              f"written.")
    where = getattr(e, "filename", None) or run_dir
    if isinstance(where, bytes):
        where = os.fsdecode(where)
    if getattr(e, "errno", None) == errno.ENOENT:
        return RunFolderError(f"{where} (or its folder) was removed while the run wrote "
                              f"it: the run stopped. Then {_then(run_dir)}; TensorBoard's "
                              f"curves are rebuilt from metrics.jsonl.")
    if getattr(e, "errno", None) in (errno.ENOSPC, errno.EDQUOT) or "unexpected pos" in str(e):
        free = shutil.disk_usage(run_dir).free / 2**20
        return RunFolderError(f"no space left on the device while writing {where} "
                              f"({free:.0f} MiB free): free some space, then "
                              f"{_then(run_dir)}.")
    if getattr(e, "errno", None) in (errno.EACCES, errno.EROFS, errno.EPERM):
        return RunFolderError(f"cannot write {where} ({e.strerror}): make the run folder "
                              f"writable, then {_then(run_dir)}.")
    return e


# ------------------------------------------------------------------- a refused start
class _Absent(enum.Enum):
    """A folder that did not exist: an enum member, so it is still itself after the
    pickling that takes a :class:`Before` to a parallel launcher's worker process (an
    ``object()`` sentinel was not: its copy read as a folder's names, and a refused
    job of a local_parallel sweep ended in a TypeError traceback)."""

    ABSENT = 0


_ABSENT = _Absent.ABSENT


def write_hydra_record(cfg: Any, folder: Path) -> None:
    """The Hydra record of this job (config, overrides, Hydra's config) in
    ``folder/.hydra``, each file written whole or not at all. Hydra itself writes none
    (``hydra.output_subdir`` is null): the run writes its record once its start-up
    checks have passed, so a refused command never changes a run's record."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    hc = HydraConfig.get()
    out = RunFolder(folder).hydra
    out.mkdir(parents=True, exist_ok=True)
    for name, node in (("config.yaml", OmegaConf.structured(cfg)),
                       ("overrides.yaml", OmegaConf.create(list(hc.overrides.task))),
                       ("hydra.yaml", OmegaConf.create({"hydra": hc}))):
        with atomic_file(out / name, "w") as f:
            OmegaConf.save(node, f)


def copy_sweep_record(sweep_dir: Path, folder: Path) -> None:
    """A sweep's job that moved to ``<sweep>-k/<job>``: that sweep folder gets the
    sweep's ``multirun.yaml`` too (re-typing the sweep with resume= needs it)."""
    src, dst = RunFolder(sweep_dir).sweep_record, RunFolder(folder.parent).sweep_record
    if src.is_file() and not dst.exists():
        atomic_write(dst, src.read_bytes())


class Before:
    """What existed before a command made anything: for each folder a run may be
    written in or under, and each of their parents, the names it held (or that it was
    absent). A start refused after Hydra made the run folder is undone with it
    (:meth:`undo_start`): only what this invocation made goes, never a folder or file
    that was there before."""

    def __init__(self, folders: list[Path]):
        self.names: dict[str, Any] = {}
        for folder in folders:
            path = Path(os.path.abspath(folder))
            for p in (path, *path.parents):
                key = str(p)
                if key in self.names:
                    continue
                try:
                    self.names[key] = frozenset(os.listdir(p)) if p.is_dir() else (
                        _ABSENT if not p.exists() else frozenset())
                except OSError:  # unreadable: known to exist, contents unknown
                    self.names[key] = None

    def created(self, path: Path) -> bool:
        """True when ``path`` did not exist before (known from the nearest recorded
        folder at or above it); False when it did, or when that cannot be told."""
        path = Path(os.path.abspath(path))
        child = None  # the name, under the nearest recorded folder, on the way to path
        for p in (path, *path.parents):
            if str(p) not in self.names:
                child = p.name
                continue
            held = self.names[str(p)]
            if held is _ABSENT:
                return True
            if p == path or held is None:
                return False
            return child not in held
        return False

    def held(self, path: Path) -> frozenset[str] | None:
        """The names ``path`` held before, when it was recorded and existed."""
        held = self.names.get(str(Path(os.path.abspath(path))))
        return held if isinstance(held, frozenset) else None

    def undo_start(self, run_dir: Path, ours: set[str]) -> None:
        """Remove what a refused start made in ``run_dir``: the folder itself (and the
        empty parents made with it) when it is new and holds only ``ours`` (Hydra's log,
        the lock's record, the run's .hydra record); in a folder that was there before,
        those of ``ours`` it did not hold. A folder another process writes is left."""
        run_dir = Path(run_dir)
        if not run_dir.is_dir() or run_dir.resolve() == Path.cwd().resolve():
            return
        lk = RunLock(run_dir)
        if not lk.acquire(record=False):  # another process writes it
            return
        try:
            if self.created(run_dir):
                if {p.name for p in run_dir.iterdir()} <= ours:
                    shutil.rmtree(run_dir, ignore_errors=True)
                    for parent in run_dir.parents:
                        if not self.created(parent):
                            break
                        try:
                            parent.rmdir()  # only an empty folder: nothing of anyone's
                        except OSError:
                            break
                return
            before = self.held(run_dir)
            if before is None:
                return
            for p in run_dir.iterdir():
                if p.name in ours and p.name not in before:
                    if p.is_dir() and not p.is_symlink():
                        shutil.rmtree(p, ignore_errors=True)
                    else:
                        p.unlink(missing_ok=True)
        finally:
            lk.release()
