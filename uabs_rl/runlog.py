"""What a training run writes besides checkpoints: ``metrics.jsonl`` (one JSON line per
training episode and per evaluation), TensorBoard scalars and figures, and the
evaluation pictures under ``eval/``."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from tensordict import TensorDictBase

from uabs_rl.config import RunConfig
from uabs_rl.evaluation import Evaluator


class RunLog:
    """Writes a run's records and figures under ``run_dir``."""

    def __init__(self, cfg: RunConfig, run_dir: Path):
        self.cfg, self.run_dir = cfg, Path(run_dir)
        self.metrics_path = self.run_dir / "metrics.jsonl"
        self.writer = None

    def open(self, resume_episode: int | None = None) -> None:
        """Create the run folder; on resume, drop what was logged after the checkpoint
        (episode ``resume_episode``) so every episode and evaluation appears once."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        for tmp in (self.run_dir / "checkpoints").glob(".*.tmp"):  # a write killed midway
            tmp.unlink()
        if resume_episode is not None:
            self.truncate(resume_episode)
        if self.cfg.train.tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(str(self.run_dir / "tb"))

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()

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
        """One line of ``metrics.jsonl``; its numbers also go to TensorBoard."""
        with open(self.metrics_path, "a") as f:
            f.write(json.dumps(record) + "\n")
        if self.writer is None:
            return
        prefix = record["kind"]
        for k, v in record.items():
            if isinstance(v, int | float) and k not in ("episode", "kind"):
                self.writer.add_scalar(f"{prefix}/{k}", v, record["episode"])

    def eval_figures(self, record: dict[str, Any], td: TensorDictBase, evaluator: Evaluator,
                     is_best: bool) -> None:
        """P_g curve and trajectory picture of an evaluation: ``eval/last_*.png``, also
        ``eval/best_*.png`` when ``is_best``, and TensorBoard."""
        if self.writer is None and not self.cfg.train.trajectory_images:
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
            fig.savefig(out / f"last_{name}.png")
            if is_best:
                fig.savefig(out / f"best_{name}.png")
            if self.writer is not None:
                self.writer.add_figure(f"eval/{name}", fig, record["episode"])
            plt.close(fig)
