"""``uabs-eval``: evaluate a trained run (and the baselines) on the held-out traces.

    uabs-eval outputs/runs/<run dir>                 # best checkpoint, learned policy
    uabs-eval outputs/runs/<run dir> --policy all    # + random, greedy, oracle baselines
    uabs-eval path/to/last.pt --windows 20 --gif

Prints a table and writes ``eval.json`` (R, collisions, proximity events, fallbacks,
served fraction, P_g at N̂_s and the whole P_g(N̂_s) curve per policy), a trajectory
picture per policy and, with ``--gif``, an animation of one episode of the learned
policy, into ``<run dir>/evaluation/`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from uabs_rl.baselines import BASELINES, baseline_policy
from uabs_rl.config import ConfigError, RunConfig
from uabs_rl.make import make_selector
from uabs_rl.train import CheckpointError, Trainer, load_checkpoint

POLICIES = ("learned", *BASELINES)


def config_from_checkpoint(state: dict) -> Any:
    """The run's config (dataclasses) as stored in a checkpoint."""
    merged = OmegaConf.merge(OmegaConf.structured(RunConfig), state["config"])
    return OmegaConf.to_object(merged)


def checkpoint_path(path: Path, which: str = "best") -> Path:
    return path / "checkpoints" / f"{which}.pt" if path.is_dir() else path


def load_trainer(path: Path, which: str = "best", windows: int | None = None,
                 out_dir: Path | None = None) -> tuple[Trainer, Path]:
    """A Trainer restored from a run directory or checkpoint, ready to evaluate."""
    ckpt = checkpoint_path(path, which)
    state = load_checkpoint(ckpt)
    cfg = config_from_checkpoint(state)
    cfg.train.compile = False  # a few rollouts: compiling would cost more than it saves
    cfg.train.progress = False
    if windows is not None:
        cfg.train.eval_windows = windows
    out = out_dir or (path if path.is_dir() else path.parent.parent) / "evaluation"
    trainer = Trainer(cfg, out)
    trainer.load_state_dict(state, ckpt, resuming=False)
    return trainer, out


def evaluate_policies(trainer: Trainer, policies: tuple[str, ...],
                      seed: int = 0) -> dict[str, tuple[dict[str, Any], Any]]:
    """Records and rollouts of each policy on the same held-out windows and masks."""
    results = {}
    for name in policies:
        if name == "learned":
            results[name] = trainer.evaluate()
        else:
            sel = make_selector(trainer.eval_env, trainer.cfg.masking)
            results[name] = trainer.evaluate(baseline_policy(name, trainer.eval_env, sel, seed))
        results[name][0]["policy"] = name
    return results


def _print_table(results: dict[str, tuple[dict, Any]], nhat: int) -> None:
    cols = ("return", "return_std", "collisions", "proximity", "fallbacks",
            "served_fraction", "pg")
    pg_col = f"P_g(N̂s={nhat})"
    print(f"{'policy':>8} " + " ".join(f"{c:>15}" for c in cols[:-1]) + f" {pg_col:>15}")
    for name, (rec, _) in results.items():
        print(f"{name:>8} " + " ".join(f"{rec[c]:>15.3f}" for c in cols))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Evaluate a uabs-train run on held-out traces.")
    ap.add_argument("path", type=Path, help="a run directory or a checkpoint (.pt)")
    ap.add_argument("--checkpoint", choices=("best", "last"), default="best",
                    help="which checkpoint of a run directory (default: best)")
    ap.add_argument("--policy", choices=(*POLICIES, "all"), default="learned")
    ap.add_argument("--windows", type=int, help="held-out windows (default: the run's)")
    ap.add_argument("--gif", action="store_true", help="also write an animation (learned)")
    ap.add_argument("--out", type=Path, help="output folder (default: <run>/evaluation)")
    args = ap.parse_args(argv)
    try:
        trainer, out = load_trainer(args.path, args.checkpoint, args.windows, args.out)
    except (CheckpointError, ConfigError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    policies = POLICIES if args.policy == "all" else (args.policy,)
    results = evaluate_policies(trainer, policies)
    out.mkdir(parents=True, exist_ok=True)
    _print_table(results, trainer.params.nhat_s)
    (out / "eval.json").write_text(json.dumps({k: r for k, (r, _) in results.items()},
                                              indent=1))
    _write_pictures(trainer, results, out, args.gif)
    print(f"wrote {out / 'eval.json'} and pictures under {out}")
    return 0


def _write_pictures(trainer: Trainer, results: dict, out: Path, gif: bool) -> None:
    import matplotlib.pyplot as plt

    from uabs_rl.plots import animate_episode, scenario_lanes, trajectory_figure

    a, p = trainer.cfg.scenario.area, trainer.params
    lanes = scenario_lanes(trainer.cfg.scenario)
    for name, (rec, td) in results.items():
        fig = trajectory_figure(a, *trainer.trajectory_of(td), p.r_b, p.n_beams, lanes,
                                title=f"{name} ({trainer.cfg.masking.mode} masking), held-out "
                                      f"window 0: R = {rec['returns'][0]:.0f}")
        fig.savefig(out / f"trajectories_{name}.png")
        plt.close(fig)
    if gif and "learned" in results:
        animate_episode(a, *trainer.trajectory_of(results["learned"][1]), p.r_b, p.n_beams,
                        lanes, out / "episode_learned.gif")


def run_main() -> None:
    sys.exit(main())


if __name__ == "__main__":
    run_main()
