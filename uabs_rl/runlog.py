"""What a training run writes besides checkpoints: ``metrics.jsonl`` (one JSON line per
training episode and per evaluation: the record every figure is computed from), the
same numbers through a TorchRL logger (``train.logger``: TensorBoard by default, CSV,
wandb or MLflow; env steps on the x-axis, hyper-parameters, env steps per second), and
the evaluation pictures under ``eval/``."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
from tensordict import TensorDictBase

from uabs_rl.config import ConfigError, LoggerKind, RunConfig
from uabs_rl.evaluation import Evaluator

# record fields that count or index rather than measure: kept in metrics.jsonl, never
# plotted as curves
COUNTERS = frozenset({"kind", "episode", "env_steps", "updates", "windows"})
# the package each optional logger needs
LOGGER_PACKAGES = {LoggerKind.wandb: "wandb", LoggerKind.mlflow: "mlflow"}


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
        return get_logger("tensorboard", str(run_dir), "tb")
    if kind is LoggerKind.csv:
        return get_logger("csv", str(run_dir), "csv")
    if kind is LoggerKind.mlflow:
        return get_logger("mlflow", str(run_dir / "mlruns"), run_dir.name)
    return get_logger("wandb", str(run_dir), run_dir.name,
                      wandb_kwargs={"project": "uabs_rl", "dir": str(run_dir)})


def read_metrics(path: Path) -> list[dict]:
    """The records of a metrics.jsonl; a damaged line is an error naming file and line
    (a run killed mid-write is repaired by resuming it)."""
    recs = []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            recs.append(json.loads(line))
        except json.JSONDecodeError as e:
            raise SystemExit(f"error: {path}, line {i}, is not a JSON record ({e.msg}): "
                             f"resume that run (uabs-train resume={path.parent}) to repair "
                             f"its metrics, or move the folder out of the sweep.") from None
    return recs


class RunLog:
    """Writes a run's records and figures under ``run_dir``."""

    def __init__(self, cfg: RunConfig, run_dir: Path):
        self.cfg, self.run_dir = cfg, Path(run_dir)
        self.metrics_path = self.run_dir / "metrics.jsonl"
        self.logger = None
        self._rate: tuple[float, int] | None = None  # (time, env steps) of the last record

    def open(self, resume_episode: int | None = None) -> None:
        """Create the run folder; on resume, drop what was logged after the checkpoint
        (episode ``resume_episode``) so every episode and evaluation appears once."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        for tmp in (self.run_dir / "checkpoints").glob(".*.tmp"):  # a write killed midway
            tmp.unlink()
        if resume_episode is not None:
            self.truncate(resume_episode)
        self.logger = make_logger(self.cfg.train.logger, self.run_dir)
        if self.logger is not None and resume_episode is None:
            from uabs_rl.checkpoint import config_dict

            self.logger.log_hparams(flat_hparams(config_dict(self.cfg)))

    def close(self) -> None:
        if self.logger is not None:
            exp = getattr(self.logger, "experiment", None)
            for name in ("close", "finish", "end_run"):  # SummaryWriter, wandb, ...
                if callable(getattr(exp, name, None)):
                    getattr(exp, name)()
                    break
            self.logger = None

    def truncate(self, episode: int) -> None:
        """Keep the records of episodes up to ``episode`` (and no half-written line)."""
        if not self.metrics_path.exists():
            return
        keep = []
        for line in self.metrics_path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue  # a line cut by a crash
            if rec.get("episode", 0) <= episode:
                keep.append(line + "\n")
        tmp = self.metrics_path.with_suffix(".jsonl.tmp")
        tmp.write_text("".join(keep))
        os.replace(tmp, self.metrics_path)

    def record(self, record: dict[str, Any]) -> None:
        """One line of ``metrics.jsonl``; its measured numbers also go to the logger,
        against env steps (the counters do not; training records add the env steps per
        second since the previous one, a figure of the machine kept out of the file)."""
        with open(self.metrics_path, "a") as f:
            f.write(json.dumps(record) + "\n")
        if self.logger is None:
            return
        step, kind = record["env_steps"], record["kind"]
        for k, v in record.items():
            if isinstance(v, int | float) and not isinstance(v, bool) and k not in COUNTERS:
                self.logger.log_scalar(f"{kind}/{k}", v, step=step)
        if kind == "train":
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

        from uabs_rl.plots import pg_curve_figure, scenario_lanes, trajectory_figure

        cfg, p = self.cfg, evaluator.params
        figs = {"pg_curve": pg_curve_figure(
            {cfg.masking.mode: record["pg_curve"]},
            title=f"P_g after {record['episode']} episodes")}
        if cfg.train.trajectory_images:
            figs["trajectories"] = trajectory_figure(
                cfg.scenario.area, *evaluator.trajectory_of(td), p.r_b, p.n_beams,
                scenario_lanes(cfg.scenario),
                title=f"{cfg.masking.mode}, episode {record['episode']}, held-out window "
                      f"0: R = {record['returns'][0]:.0f}")
        out = self.run_dir / "eval"
        out.mkdir(exist_ok=True)
        for name, fig in figs.items():
            # rendered once, for the PNG and TensorBoard alike (savefig and add_figure
            # would each render it: the pictures were a tenth of the main job's time)
            fig.canvas.draw()
            rgba = np.asarray(fig.canvas.buffer_rgba())
            plt.imsave(out / f"last_{name}.png", rgba)
            if is_best:  # the same picture: copied, not drawn again
                shutil.copyfile(out / f"last_{name}.png", out / f"best_{name}.png")
            if writer is not None:
                writer.add_image(f"eval/{name}", rgba[..., :3], record["env_steps"],
                                 dataformats="HWC")
            plt.close(fig)
