"""What a training run writes besides checkpoints: ``metrics.jsonl``
(:mod:`uabs_rl.runs.metrics`: one JSON line per training episode and per evaluation, the
record every figure is computed from), the same numbers through a TorchRL logger
(``train.logger``: TensorBoard by default, CSV, wandb or MLflow; env steps on the x-axis,
hyper-parameters, env steps per second), and the evaluation pictures under ``eval/``.

A resumed run continues its logs as an uninterrupted one would have written them: what
was logged after the checkpoint is dropped from ``metrics.jsonl``, from TensorBoard's
event files (rewritten into one, each scalar once per env step, equal to
``metrics.jsonl``) and from the CSV logger's files."""

from __future__ import annotations

import importlib.util
import shutil
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

from tensordict import TensorDictBase

from uabs_rl.config import ConfigError, LoggerKind, RunConfig
from uabs_rl.evaluation.evaluator import Evaluator
from uabs_rl.paths import atomic_write
from uabs_rl.runs.layout import TB, RunFolder
from uabs_rl.runs.metrics import MetricsFile, check_history

# record fields that count or index rather than measure: kept in metrics.jsonl, never
# plotted as curves
COUNTERS = frozenset({"kind", "episode", "env_steps", "updates", "windows"})
# the package each optional logger needs
LOGGER_PACKAGES = {LoggerKind.wandb: "wandb", LoggerKind.mlflow: "mlflow"}
# the figures TensorBoard's HPARAMS tab shows beside each run's hyper-parameters (their
# last value in the run's own curves)
HPARAM_METRICS = ("eval/return", "eval/served_fraction", "eval/pg", "eval/collisions")


def check_logger(kind: LoggerKind) -> None:
    """Refuse, at start-up, an optional logger whose package is not installed."""
    pkg = LOGGER_PACKAGES.get(LoggerKind(kind))
    if pkg and importlib.util.find_spec(pkg) is None:
        raise ConfigError(f"train.logger={kind} needs the {pkg} package, which is not "
                          f"installed: pip install {pkg}, or use train.logger=tensorboard, "
                          f"csv or none.")


def flat_hparams(d: dict, prefix: str = "") -> dict[str, Any]:
    """A nested config as ``{"algo.lr": 1e-4, ...}`` with lists as strings and nulls as
    "null": the flat scalars every logger's ``log_hparams`` accepts."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(flat_hparams(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = ("null" if v is None else str(v) if isinstance(v, list | tuple)
                                   else v)
    return out


def _quiet_writer_thread(args) -> None:
    """``threading.excepthook`` that leaves a file error of TensorBoard's writer thread
    to the run: the writer raises it again in the run's thread, which stops with one
    line (:func:`uabs_rl.runs.folder.write_error`); anything else as before."""
    if isinstance(args.exc_value, OSError) and type(args.thread).__name__ == "_AsyncWriterThread":
        return
    _THREAD_HOOK(args)


_THREAD_HOOK = threading.excepthook


def make_logger(kind: LoggerKind, run_dir: Path):
    """TorchRL's logger of ``kind`` writing under ``run_dir`` (``tb/``, ``csv/``,
    ``mlruns/``; wandb under its own project ``uabs_rl``), or None for ``none``."""
    from torchrl.record.loggers import get_logger

    kind = LoggerKind(kind)
    if kind is LoggerKind.none:
        return None
    check_logger(kind)
    run_dir = Path(run_dir)
    if kind is LoggerKind.tensorboard:
        threading.excepthook = _quiet_writer_thread
        return get_logger("tensorboard", str(run_dir), TB)
    if kind is LoggerKind.csv:
        return get_logger("csv", str(run_dir), "csv")
    if kind is LoggerKind.mlflow:
        return get_logger("mlflow", str(run_dir / "mlruns"), run_dir.name)
    return get_logger("wandb", str(run_dir), run_dir.name,
                      wandb_kwargs={"project": "uabs_rl", "dir": str(run_dir)})


def curves(record: dict[str, Any]) -> list[tuple[str, float]]:
    """``(tag, value)`` of each measured number of a record (``train/return``, ...): its
    counters and non-numbers are not curves."""
    return [(f"{record['kind']}/{k}", v) for k, v in record.items()
            if isinstance(v, int | float) and not isinstance(v, bool) and k not in COUNTERS]


def write_hparams(writer, hparams: dict[str, Any]) -> None:
    """The hyper-parameters into ``writer``'s own event file (SummaryWriter.add_hparams
    would write them to a timestamped sub-run, which TensorBoard lists as a second run)."""
    from torch.utils.tensorboard.summary import hparams as hparams_summaries

    for summary in hparams_summaries(hparams, dict.fromkeys(HPARAM_METRICS, 0.0)):
        writer.file_writer.add_summary(summary)


def read_events(files: list[Path]) -> list:
    """The events of TensorBoard event files, in order, without their file-version
    headers, each once (a rewrite killed before it removed the old files leaves copies);
    a record cut by a kill ends its file."""
    from tensorboard.backend.event_processing.event_file_loader import LegacyEventFileLoader

    seen, events = set(), []
    for f in files:
        for ev in LegacyEventFileLoader(str(f)).Load():
            key = ev.SerializeToString()
            if not ev.HasField("file_version") and key not in seen:
                seen.add(key)
                events.append(ev)
    return events


def events_up_to(events: list, cutoff: int, records: list[dict[str, Any]]) -> list:
    """``events`` up to env step ``cutoff``, in step order, with the curves of
    ``metrics.jsonl`` (``records``) exactly: a curve's values at a step are kept when
    the events hold as many as the records, else rebuilt from the records (events never
    flushed before a kill; two copies of a step after a resume without this rewrite)."""
    from tensorboard.compat.proto.event_pb2 import Event
    from tensorboard.compat.proto.summary_pb2 import Summary

    want: dict[tuple[str, int], list[float]] = defaultdict(list)
    for r in records:
        for tag, v in curves(r):
            want[tag, r["env_steps"]].append(v)
    have: dict[tuple[str, int], list[int]] = defaultdict(list)
    kept = sorted((ev for ev in events if ev.step <= cutoff), key=lambda ev: ev.step)
    for i, ev in enumerate(kept):
        vals = ev.summary.value if ev.HasField("summary") else []
        if len(vals) == 1 and vals[0].HasField("simple_value") and \
                vals[0].tag.startswith(("train/", "eval/")):
            have[vals[0].tag, ev.step].append(i)
    drop = {i for key, idx in have.items() if len(idx) != len(want.get(key, ())) for i in idx}
    out = [ev for i, ev in enumerate(kept) if i not in drop]
    missing = [(step, tag, v) for (tag, step), vals in want.items()
               if len(have.get((tag, step), ())) != len(vals) for v in vals]
    for step, tag, v in missing:
        out.append(Event(step=step, summary=Summary(value=[Summary.Value(tag=tag,
                                                                         simple_value=v)])))
    out.sort(key=lambda ev: ev.step)
    last = time.time()
    for ev in reversed(out):  # the rebuilt ones take the time of the event after them
        if ev.wall_time:
            last = ev.wall_time
        else:
            ev.wall_time = last
    return out


class RunLog:
    """Writes a run's records and figures under ``run_dir``."""

    def __init__(self, cfg: RunConfig, run_dir: Path):
        self.cfg, self.run_dir = cfg, Path(run_dir)
        self.folder = RunFolder(self.run_dir)
        self.metrics = MetricsFile(self.folder.metrics)
        # the evaluation pictures, made at their first draw (eval_figures) and kept
        self.pictures: dict[str, Any] = {}
        self.logger = None
        self._rate: tuple[float, int] | None = None  # (time, env steps) of the last record

    def open(self, resume_episode: int | None = None) -> None:
        """Create the run folder; on resume, drop what was logged after the checkpoint
        (episode ``resume_episode``) so every episode and evaluation appears once."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        for tmp in self.folder.checkpoints.glob(".*.tmp"):  # a write killed midway
            tmp.unlink()
        kind = LoggerKind(self.cfg.train.logger)
        tb = self.folder.tb
        old = sorted(tb.glob("events.out.tfevents.*")) if kind is LoggerKind.tensorboard else []
        records = self.truncate(resume_episode) if resume_episode is not None else []
        self.metrics.open()
        # env steps of the checkpoint: those of the last record kept (records are written
        # before the checkpoint that follows them); a fresh start keeps no old event
        cutoff = max((r["env_steps"] for r in records), default=-1)
        self.logger = make_logger(kind, self.run_dir)
        if self.logger is None:
            return
        from uabs_rl.runs.checkpoint import config_dict

        hparams = flat_hparams(config_dict(self.cfg))
        if kind is LoggerKind.tensorboard:
            self._continue_tensorboard(tb, old, cutoff, records, hparams)
            return
        if kind is LoggerKind.csv:
            truncate_csv(self.run_dir / "csv" / "scalars", cutoff)
        if resume_episode is None:
            self.logger.log_hparams(hparams)

    def _continue_tensorboard(self, tb: Path, old: list[Path], cutoff: int,
                              records: list[dict[str, Any]], hparams: dict[str, Any]) -> None:
        """Rewrite the events of the ``old`` event files up to env step ``cutoff`` into
        the new writer's file (so each step appears once), then remove them; write the
        hyper-parameters unless kept, taking in those of a timestamped sub-run."""
        writer = self.logger.experiment
        subruns = [d for d in tb.iterdir() if d.is_dir() and _is_timestamp(d.name)]
        events = events_up_to(read_events(old), cutoff, records)
        if cutoff >= 0:
            events += [ev for ev in read_events(
                [f for d in subruns for f in sorted(d.glob("events.out.tfevents.*"))])
                if _tag(ev).startswith("_hparams_/")]
        for ev in events:
            writer.file_writer.add_event(ev, walltime=ev.wall_time)
        if not any(_tag(ev) == "_hparams_/experiment" for ev in events):
            write_hparams(writer, hparams)
        writer.flush()
        for f in old:
            f.unlink()
        for d in subruns:
            shutil.rmtree(d)

    def close(self) -> None:
        self.pictures.clear()
        if self.logger is not None:
            exp = getattr(self.logger, "experiment", None)
            for name in ("close", "finish", "end_run"):  # SummaryWriter, wandb, ...
                if callable(getattr(exp, name, None)):
                    getattr(exp, name)()
                    break
            self.logger = None

    def check_history(self, episode: int) -> None:
        """See :func:`uabs_rl.runs.metrics.check_history` (this run's metrics.jsonl)."""
        check_history(self.metrics.path, episode)

    def truncate(self, episode: int) -> list[dict[str, Any]]:
        """See :meth:`uabs_rl.runs.metrics.MetricsFile.truncate`."""
        return self.metrics.truncate(episode)

    def record(self, record: dict[str, Any]) -> None:
        """One line of ``metrics.jsonl``; its measured numbers also go to the logger,
        against env steps (the counters do not; training records add the env steps per
        second since the previous one, a figure of the machine kept out of the file)."""
        self.metrics.append(record)
        if self.logger is None:
            return
        step = record["env_steps"]
        for tag, v in curves(record):
            self.logger.log_scalar(tag, v, step=step)
        if record["kind"] == "train":
            now = time.perf_counter()
            if self._rate is not None and step > self._rate[1]:
                self.logger.log_scalar("speed/env_steps_per_s",
                                       (step - self._rate[1]) / (now - self._rate[0]), step=step)
            self._rate = (now, step)

    def _figure_writer(self):
        """The TensorBoard writer behind the logger (figures go there), else None."""
        exp = getattr(self.logger, "experiment", None)
        return exp if callable(getattr(exp, "add_figure", None)) else None

    def eval_figures(self, record: dict[str, Any], td: TensorDictBase, evaluator: Evaluator,
                     is_best: bool) -> None:
        """P_g curve and trajectory picture of an evaluation: ``eval/last_*.png``, also
        ``eval/best_*.png`` when ``is_best``, and TensorBoard."""
        writer = self._figure_writer()
        if writer is None and not self.cfg.train.trajectory_images:
            return
        import matplotlib.pyplot as plt

        from uabs_rl.evaluation.plots import PgCurvePicture, TrajectoryPicture, scenario_lanes

        # the pictures live as long as the run: each evaluation places its curve and
        # paths on them and redraws those only (LivePicture)
        cfg, p, pics = self.cfg, evaluator.params, self.pictures
        if "pg_curve" not in pics:
            pics["pg_curve"] = PgCurvePicture([cfg.masking.mode], len(record["pg_curve"]),
                                              live=True)
        pics["pg_curve"].update([record["pg_curve"]],
                                title=f"P_g after {record['episode']} episodes")
        if cfg.train.trajectory_images:
            uabs, vehicles, present = evaluator.trajectory_of(td)
            pic = pics.get("trajectories")
            if pic is None or not pic.shows(vehicles, present):
                pic = pics["trajectories"] = TrajectoryPicture(
                    cfg.scenario.area, vehicles, present, p.r_b, p.n_beams, uabs.shape[1],
                    scenario_lanes(cfg.scenario), live=True)
            pic.update(uabs, title=f"{cfg.masking.mode}, episode {record['episode']}, "
                                   f"held-out window 0: R = {record['returns'][0]:.0f}")
        out = self.folder.eval
        out.mkdir(exist_ok=True)
        for name, pic in pics.items():
            # rendered once, for the PNG and TensorBoard alike
            rgba = pic.live.render()
            plt.imsave(out / f"last_{name}.png", rgba)
            if is_best:  # the same picture: copied, not drawn again
                shutil.copyfile(out / f"last_{name}.png", out / f"best_{name}.png")
            if writer is not None:
                writer.add_image(f"eval/{name}", rgba[..., :3], record["env_steps"],
                                 dataformats="HWC")
        if writer is not None:
            # on disk before the checkpoint that follows an evaluation, so a resume after
            # a kill finds every event up to its checkpoint
            writer.flush()


def _tag(event) -> str:
    """The tag of an event's first summary value ("" if it has none)."""
    vals = event.summary.value if event.HasField("summary") else []
    return vals[0].tag if vals else ""


def _is_timestamp(name: str) -> bool:
    """A sub-run folder of SummaryWriter.add_hparams (named ``str(time.time())``)."""
    try:
        float(name)
    except ValueError:
        return False
    return True


def truncate_csv(scalars: Path, cutoff: int) -> None:
    """Keep the rows of the CSV logger's ``step,value`` files up to env step ``cutoff``
    (a fresh start, ``cutoff`` -1, keeps none), and no half-written row."""
    for f in scalars.rglob("*.csv"):
        keep = []
        for line in f.read_text().splitlines():
            step, _, value = line.partition(",")
            try:
                float(value)
                if int(step) <= cutoff:
                    keep.append(line + "\n")
            except ValueError:
                continue
        atomic_write(f, "".join(keep))
