"""``uabs-eval``: evaluate a trained run (and the baselines) on the held-out traces.

    uabs-eval outputs/runs/<run dir>                 # best checkpoint, learned policy
    uabs-eval outputs/runs/<run dir> --policy all    # + random, greedy, oracle baselines
    uabs-eval path/to/last.pt --windows 20 --gif

Prints a table and writes ``eval.json`` (R, collisions, proximity events, fallbacks,
served fraction, P_g at N̂_s and the whole P_g(N̂_s) curve per policy), a trajectory
picture per policy and, with ``--gif``, an animation of one episode of the learned
policy, into ``<run dir>/evaluation/`` (or ``--out``).

Evaluation needs only the held-out env, the Q-network and the masking rule
(:mod:`uabs_rl.evaluation`): no training traces, replay buffer or optimiser are built.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tensordict.nn import TensorDictModuleBase

from uabs_rl.baselines import BASELINES, baseline_policy
from uabs_rl.checkpoint import (
    CheckpointError,
    checkpoint_path,
    config_from_checkpoint,
    load_checkpoint,
)
from uabs_rl.config import ConfigError, RunConfig
from uabs_rl.env import N_ACTIONS
from uabs_rl.evaluation import Evaluator, greedy_policy, make_eval_env
from uabs_rl.make import make_selector
from uabs_rl.model import DuelingQNet

POLICIES = ("learned", *BASELINES)


@dataclass
class Evaluation:
    """What evaluating a checkpoint needs: its config, the held-out env's evaluator, the
    greedy learned policy and the counters the checkpoint was written at."""

    cfg: RunConfig
    evaluator: Evaluator
    greedy: TensorDictModuleBase
    episode: int
    env_steps: int


def load_evaluation(path: Path, which: str = "best", windows: int | None = None) -> Evaluation:
    """The learned policy of a run directory or checkpoint on its held-out windows."""
    state = load_checkpoint(checkpoint_path(path, which))
    cfg = config_from_checkpoint(state)
    # a few rollouts: compiling would cost more than it saves
    env = make_eval_env(cfg, windows=windows, compile=False)
    p = env.base_env.params
    qnet = DuelingQNet(p.obs_dim, N_ACTIONS, list(cfg.algo.hidden))
    qnet.load_state_dict(state["learner"]["qnet"])
    c = state["counters"]
    return Evaluation(cfg, Evaluator(env, cfg.train.eval_seed), greedy_policy(qnet, env, cfg),
                      int(c["episode"]), int(c["env_steps"]))


def default_out_dir(path: Path) -> Path:
    return (path if path.is_dir() else path.parent.parent) / "evaluation"


def evaluate_policies(ev: Evaluation, policies: tuple[str, ...],
                      seed: int = 0) -> dict[str, tuple[dict[str, Any], Any]]:
    """Records and rollouts of each policy on the same held-out windows and masks."""
    results = {}
    env = ev.evaluator.env
    for name in policies:
        if name == "learned":
            policy = ev.greedy
        else:
            policy = baseline_policy(name, env, make_selector(env, ev.cfg.masking), seed)
        results[name] = ev.evaluator.evaluate(policy, ev.episode, ev.env_steps)
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
        ev = load_evaluation(args.path, args.checkpoint, args.windows)
    except (CheckpointError, ConfigError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    out = args.out or default_out_dir(args.path)
    policies = POLICIES if args.policy == "all" else (args.policy,)
    results = evaluate_policies(ev, policies)
    out.mkdir(parents=True, exist_ok=True)
    _print_table(results, ev.evaluator.params.nhat_s)
    (out / "eval.json").write_text(json.dumps({k: r for k, (r, _) in results.items()},
                                              indent=1))
    _write_pictures(ev, results, out, args.gif)
    print(f"wrote {out / 'eval.json'} and pictures under {out}")
    return 0


def _write_pictures(ev: Evaluation, results: dict, out: Path, gif: bool) -> None:
    import matplotlib.pyplot as plt

    from uabs_rl.plots import animate_episode, scenario_lanes, trajectory_figure

    a, p = ev.cfg.scenario.area, ev.evaluator.params
    lanes = scenario_lanes(ev.cfg.scenario)
    for name, (rec, td) in results.items():
        fig = trajectory_figure(a, *ev.evaluator.trajectory_of(td), p.r_b, p.n_beams, lanes,
                                title=f"{name} ({ev.cfg.masking.mode} masking), held-out "
                                      f"window 0: R = {rec['returns'][0]:.0f}")
        fig.savefig(out / f"trajectories_{name}.png")
        plt.close(fig)
    if gif and "learned" in results:
        animate_episode(a, *ev.evaluator.trajectory_of(results["learned"][1]), p.r_b,
                        p.n_beams, lanes, out / "episode_learned.gif")


def run_main() -> None:
    sys.exit(main())


if __name__ == "__main__":
    run_main()
