"""How often a learned policy flies the clairvoyant planner's move, on the states it
reaches itself: the share of agent decisions where the greedy learned move equals the
label ``algo=dqfd``'s teacher would give there (:class:`uabs_rl.training.teacher.Teacher`:
the planner's best move among those the mask that applied allows; under rank masks,
given the moves the higher-ranked UABS took).

    python benchmarks/teacher_agreement.py outputs/runs/lookahead_motion5 \
        outputs/runs/dqfd_motion5 --horizon 5

Each run folder (a population's members, ``seed=*``, or a single run) is flown from its
``best.pt`` on every window of ``--split`` (default ``eval``, the validation traces);
prints each member's agreement and the mean over members. One torch thread.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from uabs_rl.env.uabs_env import ACTION, MASK
from uabs_rl.evaluation.load import load_evaluation
from uabs_rl.training.teacher import NO_LABEL, Teacher


def members(root: Path) -> list[Path]:
    found = sorted(root.glob("seed=*"), key=lambda p: int(p.name.split("=")[1]))
    return found or [root]


@torch.no_grad()
def agreement(run: Path, horizon: int, split: str) -> tuple[float, int]:
    """(share of labelled agent decisions where the greedy move is the teacher's, their
    number) over one episode of every window of ``split``."""
    ev = load_evaluation(run, "best", split=split)
    env = ev.evaluator.env
    teacher = Teacher(env.base_env, horizon)
    env.set_seed(ev.evaluator.seed)  # the windows and starts of every evaluation
    td = env.reset()
    same = labelled = 0
    for _ in range(env.base_env.params.episode_steps):
        scores = teacher.scores(td)
        ev.greedy(td)  # the network's values, then the masked selector
        label = Teacher.label(scores, td.get(MASK))
        ok = label != NO_LABEL
        same += int(((label == td.get(ACTION)) & ok).sum())
        labelled += int(ok.sum())
        td = env.step(td)["next"]
    return same / max(labelled, 1), labelled


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--horizon", type=int, default=5, help="the teacher planner's H")
    ap.add_argument("--split", default="eval", choices=("eval", "test"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    for root in args.runs:
        shares = []
        for run in members(root):
            share, n = agreement(run, args.horizon, args.split)
            shares.append(share)
            print(f"{run}: {100 * share:.1f} % of {n} decisions", flush=True)
        print(f"{root}: mean {100 * sum(shares) / len(shares):.1f} % over "
              f"{len(shares)} member(s) (teacher H = {args.horizon}, {args.split} split)\n",
              flush=True)


if __name__ == "__main__":
    main()
