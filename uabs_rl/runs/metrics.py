"""A run's ``metrics.jsonl``: one JSON line per training episode and per evaluation, the
record every figure is computed from. Read whole (:func:`read_metrics`), checked before
a resume (:func:`check_history`), and written by one run (:class:`MetricsFile`: appended
line by line, cut back to a checkpoint's episode on resume)."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path
from typing import Any

from uabs_rl.paths import atomic_write
from uabs_rl.runs.folder import RunFolderError, write_error


class MetricsError(RuntimeError):
    """A metrics.jsonl that is not a run's whole history: a damaged line, or training
    episodes that do not run 1, 2, ...; the text names the file and the fix."""


def parse_record(raw: bytes) -> dict[str, Any] | str:
    """A metrics.jsonl line as its record, or why it is not one."""
    try:
        rec = json.loads(raw.decode())
    except UnicodeDecodeError:
        return "not UTF-8 text"
    except json.JSONDecodeError as e:
        return f"not JSON: {e.msg}"
    if not isinstance(rec, dict) or rec.get("kind") not in ("train", "eval"):
        return "not a train or eval record"
    if not isinstance(rec.get("episode"), int) or not isinstance(rec.get("env_steps"), int):
        return "its episode or env_steps is not a whole number"
    return rec


def read_metrics(path: Path) -> list[dict]:
    """The records of a metrics.jsonl; a damaged line is a :class:`MetricsError` naming
    file and line (a run killed mid-write is repaired by resuming it)."""
    recs = []
    for i, line in enumerate(path.read_bytes().splitlines(), 1):
        if not line.strip():
            continue
        rec = parse_record(line)
        if isinstance(rec, str):
            raise MetricsError(f"{path}, line {i}, is {rec}: resume that run "
                               f"(uabs-train resume={path.parent}) to repair its metrics, or "
                               f"move the folder out of the sweep.")
        recs.append(rec)
    gap = history_gap([r["episode"] for r in recs if r["kind"] == "train"])
    if gap:
        raise MetricsError(f"{path} {gap}: the file was removed, cut or mixed while "
                           f"its run wrote it. Restore it from a copy, or move the folder "
                           f"out of the sweep.")
    return recs


def history_gap(episodes: list[int], upto: int | None = None) -> str | None:
    """Why the training episodes of a metrics.jsonl are not 1, 2, ... (``upto``: and
    up to that episode), as a phrase; None when they are."""
    want = list(range(1, (len(episodes) if upto is None else upto) + 1))
    if episodes == want:
        return None
    if not episodes:
        return f"holds no training episode, where its checkpoint is at episode {upto}"
    if episodes[0] != 1:
        return f"starts at episode {episodes[0]} (episodes 1 to {episodes[0] - 1} are missing)"
    for i, (a, b) in enumerate(zip(episodes, episodes[1:], strict=False)):
        if b != a + 1:
            return f"jumps from episode {a} to {b} (line {i + 2} of its training records)"
    return (f"ends at episode {episodes[-1]}, where its checkpoint is at episode {upto}"
            if upto is not None else None)


def check_history(metrics: Path, episode: int) -> None:
    """Before a resume from a checkpoint at ``episode`` changes anything: ``metrics``
    holds each training episode 1 .. ``episode`` (a file removed or cut would continue
    as a history with a hole), else refused naming the gap. A damaged line is left for
    :meth:`MetricsFile.truncate` to judge (it repairs a last line cut by a crash)."""
    if not metrics.exists():
        raise RunFolderError(f"{metrics} is missing, where the run's checkpoint is at "
                             f"episode {episode}: restore it from a copy to continue "
                             f"(nothing was changed).")
    lines = [raw for raw in metrics.read_bytes().splitlines() if raw.strip()]
    episodes = []
    for i, raw in enumerate(lines, 1):
        rec = parse_record(raw)
        if isinstance(rec, str):
            if i < len(lines):
                return  # not cut by a crash: truncate refuses it, naming the line
            continue
        if rec["kind"] == "train" and rec["episode"] <= episode:
            episodes.append(rec["episode"])
    gap = history_gap(episodes, episode)
    if gap:
        raise RunFolderError(f"{metrics} {gap}: its history was cut or mixed. Restore it "
                             f"from a copy to continue (nothing was changed), or start a "
                             f"new run.")


def count_evaluations(metrics: Path) -> int:
    """The evaluation records of ``metrics`` (0 when it is absent); damaged lines are
    not evaluations."""
    evals = 0
    if metrics.is_file():
        for line in metrics.read_bytes().splitlines():
            try:
                evals += json.loads(line).get("kind") == "eval"
            except (ValueError, AttributeError):  # a damaged line: not an evaluation
                continue
    return evals


class MetricsFile:
    """The metrics.jsonl one run writes: appended a line per record, and refused
    (:class:`~uabs_rl.runs.folder.RunFolderError`) when another process removed,
    replaced or changed it since."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.run_dir = self.path.parent
        self._file: tuple[int, int, int] | None = None  # the file as last written

    def _identity(self) -> tuple[int, int, int] | None:
        """The file's device, inode and size (None when absent)."""
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return None
        return st.st_dev, st.st_ino, st.st_size

    def open(self) -> None:
        """From now on, the file as it is is this run's."""
        self._file = self._identity()

    def truncate(self, episode: int) -> list[dict[str, Any]]:
        """Keep the records of episodes up to ``episode`` and drop a last line cut by a
        crash; returns the records kept. A damaged line before the last one was not cut
        by a crash (the file was edited or mixed): refused, naming it, nothing changed."""
        if not self.path.exists():
            return []
        keep, recs = [], []
        lines = self.path.read_bytes().splitlines()
        while lines and not lines[-1].strip():
            lines.pop()
        for i, raw in enumerate(lines, 1):
            rec = parse_record(raw)
            if isinstance(rec, str):
                if i == len(lines):
                    break  # a line cut by a crash
                raise RunFolderError(
                    f"{self.path}, line {i} of {len(lines)}, is damaged ({rec}): "
                    f"only a last line cut by a crash is repaired on resume. Restore the "
                    f"file, or remove that line, and resume again.")
            if rec["episode"] <= episode:
                keep.append(raw.decode() + "\n")
                recs.append(rec)
        atomic_write(self.path, "".join(keep))
        return recs

    def append(self, record: dict[str, Any]) -> None:
        """One line, after checking that the file is still the one this run wrote."""
        if self._identity() != self._file:
            if not self.run_dir.is_dir():  # the whole folder: write_error says so
                raise write_error(FileNotFoundError(errno.ENOENT, "removed",
                                                    str(self.path)), self.run_dir)
            raise RunFolderError(
                f"{self.path} was removed, replaced or changed by another process "
                f"while this run wrote it: the run stopped so that its history is not "
                f"mixed. Restore the file, then continue with resume={self.run_dir} (its "
                f"last checkpoint is kept).")
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")
            f.flush()
            st = os.fstat(f.fileno())
        self._file = st.st_dev, st.st_ino, st.st_size
