"""How much of the clairvoyant planner an observation can express: a network of the
run's own size fit to the planner's moves by supervised learning alone, on states of
the training traces, and its agreement with the planner on held-out windows.

    python benchmarks/imitation_ceiling.py outputs/runs/lookahead_motion5/seed=0

1. States: the run's own greedy policy (``best.pt``) flies ``--windows`` random
   windows of the training traces (``traces.train``) side by side for one episode; at
   every step the teacher of ``algo=dqfd`` (:class:`uabs_rl.training.teacher.Teacher`,
   horizon ``--horizon``) scores each UABS's moves, and the moves of best score among
   those the mask that applied allows are that decision's *best set* (ties kept).
2. The last ``--held-out`` windows are kept aside; on the others a network of the
   run's architecture is fit by cross-entropy towards the best set (``--steps`` Adam
   steps of 256 decisions), once from scratch and once from the run's own weights.
3. Agreement: the share of decisions whose greedy legal move lies in the best set, on
   the fitting windows and on the held-out ones, for the run itself and for each fit.

If the fit from scratch does not get above the run on held-out windows, the teacher's
other moves depend on what the observation does not hold, and no amount of imitation
(``algo=dqfd``'s margin term included) can teach them. One process, 2 torch threads.
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import torch

from uabs_rl.algorithms import Dims, algorithm_class
from uabs_rl.env.uabs_env import MASK, OBS
from uabs_rl.evaluation.load import load_evaluation
from uabs_rl.runs.checkpoint import load_checkpoint
from uabs_rl.safety.make import make_env, make_selector
from uabs_rl.safety.rules import ACTION_VALUE
from uabs_rl.traces.build import get_traces
from uabs_rl.training.teacher import Teacher


@torch.no_grad()
def collect(run: Path, windows: int, horizon: int, seed: int):
    """The run's network and, over one episode of ``windows`` training windows flown by
    it: observations ``[W, T, M, D]``, applied masks and best sets ``[W, T, M, 4]``."""
    ev = load_evaluation(run, "best", split="eval", windows=1)
    cfg, p = ev.cfg, ev.evaluator.env.base_env.params
    algorithm = algorithm_class(cfg.algo.name)
    net = algorithm.acting_network(cfg.algo, Dims(p.obs_dim, 4, p.n_uabs))
    net.load_state_dict(load_checkpoint(run / "checkpoints" / "best.pt")["learner"]
                        [algorithm.acting_key])
    traces = get_traces(cfg.scenario, cfg.traces, "train", verbose=False)
    env = make_env(cfg.scenario, cfg.channel, cfg.masking, traces, "train",
                   n_envs=windows, seed=seed, obs=cfg.obs)
    selector, teacher = make_selector(env), Teacher(env.base_env, horizon)
    td = env.reset()
    obs, masks, best = [], [], []
    for _ in range(p.episode_steps):
        scores = teacher.scores(td)
        td.set(ACTION_VALUE, net(td.get(OBS)))
        selector(td)
        mask = td.get(MASK)
        legal = scores.masked_fill(~mask, -torch.inf)
        obs.append(td.get(OBS))
        masks.append(mask)
        best.append((legal == legal.amax(-1, keepdim=True)) & mask)
        td = env.step(td)["next"]
    return net, *(torch.stack(x, 1) for x in (obs, masks, best))


@torch.no_grad()
def agreement(net: torch.nn.Module, obs, mask, best) -> float:
    """Share of decisions (with a legal move) whose greedy legal move is in the best set."""
    move = net(obs).masked_fill(~mask, -torch.inf).argmax(-1, keepdim=True)
    ok = mask.any(-1)
    return float((best.gather(-1, move).squeeze(-1) & ok).sum() / ok.sum())


def fit(net: torch.nn.Module, obs, mask, best, steps: int, seed: int) -> torch.nn.Module:
    """``net`` fit by cross-entropy of its legal values (as logits) towards the best set."""
    torch.manual_seed(seed)
    keep = mask.any(-1)
    x, m, b = obs[keep], mask[keep], best[keep]
    opt = torch.optim.Adam(net.parameters(), lr=3e-4)
    for _ in range(steps):
        i = torch.randint(0, x.shape[0], (256,))
        logits = net(x[i]).masked_fill(~m[i], -1e9)
        loss = (torch.logsumexp(logits, -1)
                - torch.logsumexp(logits.masked_fill(~b[i], -1e9), -1)).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return net


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a run folder (a population's member)")
    ap.add_argument("--horizon", type=int, default=5, help="the teacher planner's H")
    ap.add_argument("--windows", type=int, default=96, help="training windows flown")
    ap.add_argument("--held-out", type=int, default=24, help="of them, kept aside")
    ap.add_argument("--steps", type=int, default=3000, help="Adam steps of each fit")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    if not 0 < args.held_out < args.windows:
        ap.error("--held-out must be between 0 and --windows")
    torch.set_num_threads(2)
    t0 = time.perf_counter()
    net, obs, mask, best = collect(args.run, args.windows, args.horizon, args.seed)
    n = args.windows - args.held_out
    fitting, held = (slice(0, n), slice(n, None))
    parts = {"fitting": fitting, "held-out": held}
    decisions = {k: int(mask[s].any(-1).sum()) for k, s in parts.items()}
    ties = float((best.sum(-1) > 1)[mask.any(-1)].float().mean())
    print(f"{args.run}: {args.windows} training windows ({decisions['fitting']} decisions to "
          f"fit, {decisions['held-out']} held out), teacher H = {args.horizon}; "
          f"{100 * ties:.1f} % of decisions have tied best moves; "
          f"collected in {time.perf_counter() - t0:.0f} s", flush=True)

    def line(name: str, model: torch.nn.Module) -> None:
        a = {k: 100 * agreement(model, obs[s], mask[s], best[s]) for k, s in parts.items()}
        print(f"  {name:<34} agreement: fitting {a['fitting']:.1f} %, held-out "
              f"{a['held-out']:.1f} %", flush=True)

    line("the run (its RL training)", net)
    fresh = copy.deepcopy(net)
    torch.manual_seed(args.seed)
    for layer in fresh.modules():
        if hasattr(layer, "reset_parameters"):
            layer.reset_parameters()
    args_fit = (obs[fitting], mask[fitting], best[fitting], args.steps, args.seed)
    line(f"fit from scratch ({args.steps} steps)", fit(fresh, *args_fit))
    line(f"the run, then fit ({args.steps} steps)", fit(copy.deepcopy(net), *args_fit))


if __name__ == "__main__":
    main()
