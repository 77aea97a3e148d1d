"""``uabs-eval``: evaluate a trained run (and the baselines) on the held-out traces.

    uabs-eval outputs/runs/<run dir>                 # best checkpoint, test traces
    uabs-eval outputs/runs/<run dir> --policy all    # + random, greedy, oracle baselines
    uabs-eval path/to/last.pt --split eval --windows 20 --gif

Evaluates on the test traces by default (``traces.test``: SUMO seeds that neither
training nor checkpoint selection ever read; every window of them), ``--split eval`` on
the validation traces that training evaluated on. Prints a table and writes
``eval.json``: the split, per policy R, collisions, proximity events, fallbacks, served
fraction, P_g at N̂_s, the whole P_g(N̂_s) curve and the per-window values, and with
baselines the paired differences learned − baseline (same windows, same masks) with
bootstrap 95 % confidence intervals. Also a trajectory picture per policy and, with
``--gif``, an animation of one episode of the learned policy, into
``<run dir>/evaluation/`` (or ``--out``).

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
from uabs_rl.stats import paired_difference

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


def load_evaluation(path: Path, which: str = "best", windows: int | None = None,
                    split: str = "test") -> Evaluation:
    """The learned policy of a run directory or checkpoint on the fixed windows of
    ``split`` ("test" or "eval", the validation traces)."""
    state = load_checkpoint(checkpoint_path(path, which))
    cfg = config_from_checkpoint(state)
    # a few rollouts: compiling would cost more than it saves
    env = make_eval_env(cfg, windows=windows, compile=False, split=split)
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


METRICS = {"return": "returns", "served_fraction": "served_fractions", "pg": "pgs"}


def differences(results: dict[str, tuple[dict, Any]]) -> dict[str, dict[str, dict]]:
    """Paired differences learned − baseline per window, with bootstrap 95 % CIs, for
    R, the served fraction and P_g at N̂_s: ``{baseline: {metric: {diff, ci_low,
    ci_high, n}}}``."""
    if "learned" not in results:
        return {}
    learned = results["learned"][0]
    return {name: {m: paired_difference(learned[k], rec[k]) for m, k in METRICS.items()}
            for name, (rec, _) in results.items() if name != "learned"}


def _print_differences(diffs: dict[str, dict[str, dict]]) -> None:
    if not diffs:
        return
    print("\nlearned − baseline, per window (mean [95 % bootstrap CI]):")
    for name, per in diffs.items():
        print(f"{name:>8} " + "   ".join(
            f"{m}: {d['diff']:+.4g} [{d['ci_low']:+.4g}, {d['ci_high']:+.4g}]"
            for m, d in per.items()))


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
    ap.add_argument("--split", choices=("test", "eval"), default="test",
                    help="test traces (default; never seen by training or selection) or "
                         "eval, the validation traces training evaluated on")
    ap.add_argument("--windows", type=int,
                    help="windows to evaluate (default: every test window, or the run's "
                         "train.eval_windows on eval)")
    ap.add_argument("--gif", action="store_true", help="also write an animation (learned)")
    ap.add_argument("--out", type=Path, help="output folder (default: <run>/evaluation)")
    args = ap.parse_args(argv)
    if args.windows is not None and args.windows < 1:
        ap.error(f"--windows must be >= 1, got {args.windows}")
    try:
        ev = load_evaluation(args.path, args.checkpoint, args.windows, args.split)
    except (CheckpointError, ConfigError) as e:
        msg = str(e)
        if args.windows is not None:  # the env names its own argument: name the flag
            msg = msg.replace(f"n_eval_windows={args.windows}", f"--windows {args.windows}")
        print(f"error: {msg}", file=sys.stderr)
        return 2
    out = args.out or default_out_dir(args.path)
    policies = POLICIES if args.policy == "all" else (args.policy,)
    results = evaluate_policies(ev, policies)
    out.mkdir(parents=True, exist_ok=True)
    n = ev.evaluator.env.base_env.n_envs
    tc = getattr(ev.cfg.traces, args.split)
    print(f"split: {args.split} (traces.{args.split}: SUMO seeds {tc.first_seed}.."
          f"{tc.first_seed + tc.n_sims - 1}), {n} windows of "
          f"{ev.cfg.scenario.episode_steps} steps, {args.checkpoint} checkpoint")
    _print_table(results, ev.evaluator.params.nhat_s)
    diffs = differences(results)
    _print_differences(diffs)
    (out / "eval.json").write_text(json.dumps(
        {"split": args.split, "windows": n, "checkpoint": args.checkpoint,
         "policies": {k: r for k, (r, _) in results.items()}, "differences": diffs},
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
