"""How often a learned policy flies the clairvoyant planner's move, on the states it
reaches itself: the share of agent decisions with a choice (two legal moves or more; a
forced move always agrees) where the greedy learned move is one the teacher of
``algo=dqfd`` rates best there (:class:`uabs_rl.training.teacher.Teacher`: the planner's
best moves among those the mask that applied allows, ties kept, as
``benchmarks/imitation_ceiling.py`` counts them; under rank masks, given the moves the
higher-ranked UABS took).

    python benchmarks/teacher_agreement.py outputs/runs/lookahead_motion5 \
        outputs/runs/dqfd_motion5 --horizon 5

Each run folder (a population's members, ``seed=*``, or a single run) is flown from its
``best.pt`` for one episode on every window of ``--split`` (default ``eval``, the
validation traces); prints each member's agreement and the mean over members. One torch
thread.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from uabs_rl.cli import one_line_errors
from uabs_rl.env.uabs_env import ACTION, MASK, window_count
from uabs_rl.evaluation.load import find_checkpoint, load_evaluation
from uabs_rl.runs.checkpoint import config_from_checkpoint, load_checkpoint
from uabs_rl.runs.layout import RunFolder
from uabs_rl.traces.build import get_traces
from uabs_rl.training.teacher import Teacher


def every_window(run: Path, split: str) -> int:
    """How many non-overlapping windows ``split``'s traces hold for ``run``'s episodes."""
    ckpt = find_checkpoint(run)
    cfg = config_from_checkpoint(load_checkpoint(ckpt), ckpt)
    traces = get_traces(cfg.scenario, cfg.traces, split, verbose=False)
    return window_count(traces.n_sims, traces.steps, cfg.scenario.episode_steps)


@torch.no_grad()
def agreement(run: Path, horizon: int, split: str) -> tuple[float, int]:
    """(share of agent decisions with a choice where the greedy move is one the teacher
    rates best, their number) over one episode of every window of ``split``."""
    ev = load_evaluation(run, "best", split=split, windows=every_window(run, split))
    env = ev.evaluator.env
    teacher = Teacher(env.base_env, horizon)
    env.set_seed(ev.evaluator.seed)  # the windows and starts of every evaluation
    td = env.reset()
    same = chosen = 0
    for _ in range(env.base_env.params.episode_steps):
        scores = teacher.scores(td)
        ev.greedy(td)  # the network's values, then the masked selector
        mask = td.get(MASK)
        best = Teacher.best_moves(scores, mask)
        ok = mask.sum(-1) > 1
        same += int((best.gather(-1, td.get(ACTION)[..., None]).squeeze(-1) & ok).sum())
        chosen += int(ok.sum())
        td = env.step(td)["next"]
    return same / max(chosen, 1), chosen


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--horizon", type=int, default=5, help="the teacher planner's H")
    ap.add_argument("--split", default="eval", choices=("eval", "test"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    for root in args.runs:
        shares = []
        for run in RunFolder(root).members():
            share, n = agreement(run, args.horizon, args.split)
            shares.append(share)
            print(f"{run}: {100 * share:.1f} % of {n} decisions", flush=True)
        print(f"{root}: mean {100 * sum(shares) / len(shares):.1f} % over "
              f"{len(shares)} member(s) (teacher H = {args.horizon}, {args.split} split)\n",
              flush=True)


if __name__ == "__main__":
    one_line_errors(main)
