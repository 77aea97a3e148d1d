"""Names that become paths, and output folders that hold one invocation's files.

- :func:`safe_component`: the one rule for a setting whose value becomes part of a file
  or folder name (``scenario.name``, ``family[i].name``, ...): a plain file-name
  component, refused otherwise with one line naming the setting.
- :func:`inside`: a derived path must stay inside the folder it was derived from.
- :func:`atomic_file`, :func:`atomic_write`: a file written whole or not at all (a
  temporary sibling, flushed to disk, renamed over the file).
- :class:`OutputFolder`: a command's output folder is written as a fresh sibling
  ``.<name>.tmp-<pid>`` and swapped in at the end with renames (old ->
  ``.<name>.old-<pid>``, new -> name, then the old one removed), so a kill at any
  point leaves either the previous complete folder or the new complete one; the next
  start finishes or cleans up a swap a killed process left. Only a folder the command
  itself wrote (its marker file lists what it wrote) is ever replaced: one holding
  anything else is refused.
"""

from __future__ import annotations

import errno
import fnmatch
import json
import os
import re
import shutil
import signal
import stat
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

from uabs_rl.config import ConfigError

MAX_COMPONENT = 100  # characters; file systems allow 255 bytes, and names get suffixes
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


@contextmanager
def atomic_file(path: Path, mode: str = "wb") -> Iterator[IO]:
    """A file to write ``path`` through, whole or not at all: the temporary sibling
    ``.<name>.<pid>.tmp``, flushed to disk and renamed over ``path`` when the block ends;
    a failure or a kill midway (Ctrl-C, a full disk) leaves the previous file as it was
    and removes the temporary one. Through a Python file, a full disk is ``OSError``
    (ENOSPC)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, mode) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write(path: Path, data: str | bytes) -> None:
    """``data`` (text or bytes) as the whole of ``path``, whole or not at all
    (:func:`atomic_file`)."""
    with atomic_file(path, "wb" if isinstance(data, bytes) else "w") as f:
        f.write(data)


def safe_component(value: object, setting: str) -> str:
    """``value`` when it is a plain file-name component: non-empty, no ``/`` or ``\\``,
    not ``.`` or ``..``, no NUL or control characters, at most ``MAX_COMPONENT``
    characters. Otherwise a :class:`ConfigError` naming ``setting``."""
    text = str(value)
    why = None
    if not text.strip():
        why = "it is empty"
    elif "/" in text or "\\" in text:
        why = "it holds a / or \\ (it names a file, not a folder path)"
    elif text in (".", ".."):
        why = f"it is {text!r}, a folder"
    elif _CONTROL.search(text):
        why = "it holds a control character"
    elif len(text) > MAX_COMPONENT:
        why = f"it is {len(text)} characters long (at most {MAX_COMPONENT})"
    elif len(text.encode()) > 2 * MAX_COMPONENT:  # letters of several bytes each
        why = (f"it is {len(text.encode())} bytes long (at most {2 * MAX_COMPONENT} "
               f"bytes)")
    if why is None:
        return text
    shown = text if len(text) <= 60 else text[:57] + "..."
    raise ConfigError(f"{setting}={shown!r} cannot name a file: {why}. Set {setting} to a "
                      f"plain name such as 'mycity' (letters, digits, - _ .).")


def name_max(path: Path) -> int:
    """The longest file name, in bytes, that the file system of ``path`` (its nearest
    existing folder) takes; 255 where it cannot be asked."""
    try:
        here = next((p for p in Path(path).absolute().parents if p.is_dir()), Path("/"))
        return os.pathconf(here, "PC_NAME_MAX")
    except (OSError, ValueError):
        return 255


def check_path(path: Path, setting: str) -> Path:
    """``path`` (a folder or file the user named) when the file system can take it: no
    component longer than its file system takes (:func:`name_max`), no NUL; a
    :class:`ConfigError` naming ``setting`` otherwise."""
    text = str(path)
    if "\x00" in text:
        raise ConfigError(f"{setting}: the path holds a NUL character. Set {setting} to "
                          f"a path without one.")
    limit = name_max(Path(text))
    long = next((c for c in Path(text).parts if len(os.fsencode(c)) > limit), None)
    if long is not None:
        raise ConfigError(f"{setting}: the path {text[:60]}... has a component "
                          f"{len(os.fsencode(long))} bytes long (at most {limit}). Set "
                          f"{setting} to a shorter path.")
    return path


def inside(path: Path, root: Path, setting: str) -> Path:
    """``path`` when it resolves inside ``root``; a :class:`ConfigError` naming
    ``setting`` otherwise."""
    p, r = Path(path).resolve(), Path(root).resolve()
    if p == r or not p.is_relative_to(r):
        raise ConfigError(f"{setting}: the file it names, {path}, would lie outside "
                          f"{root}. Set {setting} to a plain name.")
    return path


# ----------------------------------------------------------------------------- output folders
def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` is running (another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        try:
            path.unlink()
        except FileNotFoundError:
            pass


def _os_words(e: OSError) -> str:
    if e.errno == errno.ENOSPC:
        return "no space left on the device"
    if e.errno == errno.EROFS:
        return "read-only file system"
    if e.errno in (errno.EACCES, errno.EPERM):
        return "permission denied"
    if e.errno == errno.ENAMETOOLONG:
        return "a file name is too long"
    return e.strerror or type(e).__name__


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread so that the output is cleaned up as on Ctrl-C."""


class OutputInterrupted(KeyboardInterrupt):
    """A command stopped on Ctrl-C or SIGTERM while writing its output folder; nothing
    of it was kept. ``str()`` is the line for the user, ``exit_code`` 130 or 143."""

    def __init__(self, message: str, exit_code: int):
        super().__init__(message)
        self.exit_code = exit_code


class OutputFolder:
    """The output folder ``path`` of one command (``marker`` names the command, e.g.
    ``uabs-report``; its marker file ``.<marker>`` lists the files it wrote).

    ``patterns``: names the command writes (fnmatch), so a folder it wrote before
    markers existed is recognised as its own; ``keep_dirs``: sub-folders that are the
    same command's outputs (``uabs-eval``'s per-override folders) are carried into the
    new folder instead of being removed. ``setting`` names the folder in messages
    (``--out``, or words such as "the output folder" for a default one), ``flag`` the
    option that chooses another."""

    def __init__(self, path: Path, marker: str, patterns: tuple[str, ...],
                 setting: str, keep_dirs: bool = False, flag: str = "--out"):
        self.given = Path(path)
        self.path = Path(os.path.abspath(Path(path).expanduser()))
        self.marker, self.patterns, self.keep_dirs = marker, patterns, keep_dirs
        self.setting, self.fix = setting, f"pass a folder you can write with {flag}"
        self.marker_name = f".{marker}"
        self._siblings()

    def _siblings(self) -> None:
        name = self.path.name
        self.tmp = self.path.with_name(f".{name}.tmp-{os.getpid()}")
        self.old = self.path.with_name(f".{name}.old-{os.getpid()}")

    # -- checks
    def _what(self) -> str:
        given = str(self.given)
        return f"{self.setting} {given if len(given) <= 120 else given[:117] + '...'}"

    def check(self) -> None:
        """Refuse, before anything is computed, an output folder this command cannot
        write or must not replace: a file, a path through a file, a name too long, a
        folder holding files the command did not write."""
        name = self.path.name
        if not name or self.path == self.path.parent:
            raise ConfigError(f"{self._what()} is the root folder: {self.fix}.")
        if len(name.encode()) > 200:
            raise ConfigError(f"{self._what()}: the folder name is {len(name.encode())} "
                              f"bytes long (at most 200 here): {self.fix}.")
        try:
            if self.path.is_symlink():  # write where it points: the link keeps working
                self.path = self.path.resolve()
                self._siblings()
            self.recover()
            p = self.path
            while not p.exists() and p != p.parent:
                p = p.parent
            if p.exists() and not p.is_dir():
                what = "is a file" if p == self.path else f"cannot be made: {p} is a file"
                raise ConfigError(f"{self._what()} {what}, not a folder: {self.fix}.")
            if self.path.is_dir() and os.path.ismount(self.path):
                raise ConfigError(f"{self._what()} is a mount point, which cannot be "
                                  f"replaced whole: {self.fix} (a folder inside it).")
            if self.path.is_dir():
                foreign = self.foreign(self.path)
                if foreign:
                    raise ConfigError(
                        f"{self._what()} holds files {self.marker} did not write "
                        f"({', '.join(foreign[:3])}{' ...' if len(foreign) > 3 else ''}): "
                        f"writing there would replace them; {self.fix} (a new or empty "
                        f"one), or move those files away.")
            where = p if p != self.path else self.path.parent  # where the new one is made
            probe = where / f".{name}.probe-{os.getpid()}"
            try:  # a real write: root, ACLs and read-only mounts all answer truly
                probe.mkdir()
                probe.rmdir()
            except OSError as e:
                raise ConfigError(f"{self._what()} cannot be written: {where} is not "
                                  f"writable here ({_os_words(e)}); {self.fix}.") from None
        except OSError as e:
            raise ConfigError(f"{self._what()} cannot be used ({_os_words(e)}): "
                              f"{self.fix}.") from None

    def _listed(self, folder: Path) -> set[str] | None:
        try:
            record = json.loads((folder / self.marker_name).read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            return None
        files = record.get("files") if isinstance(record, dict) else None
        return set(files) if isinstance(files, list) else None

    def _ours(self, entry: Path, listed: set[str] | None) -> bool:
        name = entry.name
        if name == self.marker_name or re.fullmatch(r"\..+\.(tmp|old|probe)-\d+", name):
            return True  # the marker, and another swap's leftovers (cleaned on their start)
        if entry.is_dir() and not entry.is_symlink():
            return self.keep_dirs and not self.foreign(entry)
        if listed is not None and name in listed:
            return True
        return any(fnmatch.fnmatchcase(name, pat) for pat in self.patterns)

    def foreign(self, folder: Path) -> list[str]:
        """The entries of ``folder`` this command did not write (sorted names)."""
        listed = self._listed(folder)
        return sorted(e.name for e in folder.iterdir() if not self._ours(e, listed))

    # -- the swap
    def recover(self) -> None:
        """Finish, or undo, the swap of a process that was killed: a complete new folder
        (``.tmp``) whose old one was already moved away is put in place; a new folder
        never swapped in is removed; a moved-away old one is removed once the new one
        is in place (its kept sub-folders carried over first)."""
        parent = self.path.parent
        if not parent.is_dir():
            return
        name = self.path.name
        for kind in ("old", "tmp"):
            for left in parent.glob(f".{glob_escape(name)}.{kind}-*"):
                pid = left.name.rsplit("-", 1)[1]
                if not pid.isdigit() or int(pid) == os.getpid() or pid_alive(int(pid)):
                    continue
                tmp = self.path.with_name(f".{name}.tmp-{pid}")
                if kind == "old":
                    if not self.path.exists():
                        os.replace(tmp if tmp.is_dir() else left, self.path)
                    if left.exists():
                        self._carry(left, self.path)
                        _remove(left)
                    _remove(tmp)
                elif left.exists():  # a new folder never swapped in: incomplete
                    _remove(left)

    def _carry(self, old: Path, new: Path) -> None:
        if not self.keep_dirs or not old.is_dir():
            return
        for entry in old.iterdir():
            if entry.is_dir() and not entry.is_symlink() and not (new / entry.name).exists():
                os.replace(entry, new / entry.name)

    @contextmanager
    def writing(self) -> Iterator[Path]:
        """The fresh folder to write into; swapped in when the block ends normally,
        removed on any failure (a full disk or a write refused is one
        :class:`ConfigError`, Ctrl-C or SIGTERM an :class:`OutputInterrupted`)."""
        self.check()
        main = threading.current_thread() is threading.main_thread()

        def terminate(signum, frame) -> None:
            stop = _Terminated()
            stop.exit_code = 128 + signum  # 143 after SIGTERM, 129 after SIGHUP
            raise stop

        previous = signal.signal(signal.SIGTERM, terminate) if main else None
        hangup = signal.getsignal(signal.SIGHUP) if main else None
        if main and hangup is not signal.SIG_IGN:  # under nohup a hang-up stops nothing
            signal.signal(signal.SIGHUP, terminate)
        made = [d for d in self.path.parents if not d.exists()]  # removed again on failure
        try:
            try:
                self.tmp.mkdir(parents=True)
                yield self.tmp
                written = sorted(p.name for p in self.tmp.iterdir())
                (self.tmp / self.marker_name).write_text(json.dumps(
                    {"command": self.marker, "files": written}, indent=1) + "\n")
                self._swap()
            except OSError as e:
                where = getattr(e, "filename", None)
                ours = where is not None and str(where).startswith(str(self.tmp))
                if not ours and e.errno not in (errno.ENOSPC, errno.EROFS, errno.EDQUOT):
                    raise
                raise ConfigError(
                    f"{self._what()}: writing the output failed ({_os_words(e)}"
                    f"{f': {e.filename}' if getattr(e, 'filename', None) else ''}); "
                    f"nothing was changed there. Free space, or {self.fix}.") from None
        except KeyboardInterrupt as e:
            self._undo(made)
            if isinstance(e, OutputInterrupted):
                raise
            code = getattr(e, "exit_code", 143) if isinstance(e, _Terminated) else 130
            raise OutputInterrupted(f"interrupted: nothing was written to {self.path} (its "
                                    f"previous contents are kept)", code) from None
        except BaseException:
            self._undo(made)
            raise
        finally:
            if main:
                signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None
                              else previous)
                signal.signal(signal.SIGHUP, signal.SIG_DFL if hangup is None else hangup)

    def _undo(self, made: list[Path]) -> None:
        """Remove the unfinished new folder, and the parents made for it (when empty)."""
        _remove(self.tmp)
        for d in made:  # innermost first
            try:
                d.rmdir()
            except OSError:
                break

    def _swap(self) -> None:
        """old -> ``.old``, new -> name, old removed. Ctrl-C and SIGTERM wait until the
        renames are done (the command has finished by then); a failed second rename
        puts the old folder back."""
        main = threading.current_thread() is threading.main_thread()
        held = {s: signal.signal(s, lambda *_: None) for s in (
            signal.SIGINT, signal.SIGTERM, signal.SIGHUP)} if main else {}
        try:
            had_old = self.path.exists()
            if had_old:
                os.replace(self.path, self.old)
            try:
                os.replace(self.tmp, self.path)
            except OSError:
                if had_old:
                    os.replace(self.old, self.path)
                raise
            if had_old:
                self._carry(self.old, self.path)
        finally:
            for sig, handler in held.items():
                signal.signal(sig, handler)
        if had_old:
            _remove(self.old)


def glob_escape(name: str) -> str:
    """``name`` with glob's special characters taken literally."""
    return re.sub(r"([*?\[])", r"[\1]", name)


def detach_terminal() -> None:
    """Point standard output and error that write to a terminal at /dev/null (after
    SIGHUP the terminal is gone: writing to it would fail); files and pipes stay as they
    are. A terminal that has hung up is no longer a tty to ``isatty``: any character
    device is taken for one (/dev/null again is harmless)."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in (1, 2):
            try:
                if stat.S_ISCHR(os.fstat(fd).st_mode):
                    os.dup2(devnull, fd)
            except OSError:  # closed
                pass
    finally:
        os.close(devnull)
