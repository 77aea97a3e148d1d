"""How often a learned policy moves as the one-step greedy baseline would.

    python benchmarks/greedy_agreement.py outputs/multirun/<sweep>/<run> [<run> ...]

For each run, its ``best.pt`` flies every test window (as ``uabs-eval``); at every step
and for every UABS the script checks whether the chosen move is one the greedy
baseline rates best among the legal moves (the priority its footprints would cover
after the move, at the vehicles' current positions; ties count as agreement) and
prints the share of agent-steps where it is. Legal moves are the mask the masking
rule writes into the step's TensorDict: exact for flat masks; for rank masks it is
the mask before the higher ranks' choices, so the share is approximate there.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from uabs_rl.cli import one_line_errors
from uabs_rl.env.service import move_scores
from uabs_rl.env.uabs_env import ACTION, POSITION
from uabs_rl.evaluation.load import load_evaluation


@torch.no_grad()
def agreement(run: Path) -> tuple[float, int]:
    ev = load_evaluation(run, "best", split="test")
    env, base = ev.evaluator.env, ev.evaluator.env.base_env
    p = base.params
    env.set_seed(ev.evaluator.seed)
    td = env.reset()
    agree = total = 0
    for _ in range(p.episode_steps):
        td = ev.greedy(td)
        veh, present = base.vehicles(0)
        cand = td.get(POSITION)[:, :, None, :] + base.math.moves
        score = move_scores(cand, veh, present, base.priority, p.r_b, p.n_beams)
        best = score.masked_fill(~td["agents", "action_mask"], -1e9).amax(-1)
        chosen = score.gather(-1, td[ACTION][..., None]).squeeze(-1)
        agree += int((chosen >= best - 1e-6).sum())
        total += chosen.numel()
        td = env.step(td)["next"]
    return agree / total, total


def main() -> None:
    if len(sys.argv) < 2:
        raise SystemExit(__doc__)
    for run in sys.argv[1:]:
        share, n = agreement(Path(run))
        print(f"{run}: {share:.3f} of {n} agent-steps move as one-step greedy would")


if __name__ == "__main__":
    one_line_errors(main)
