"""How much of the clairvoyant planner an observation can express: a network of the
run's own size fit to the planner's moves by supervised learning alone, and its
agreement with the planner on held-out traces.

    python benchmarks/imitation_ceiling.py outputs/runs/lookahead_motion5/seed=0

1. States: the run's own greedy policy (``best.pt``) flies ``--windows`` random
   windows of the training traces (``traces.train``) side by side for one episode, and
   every window of the validation traces (``traces.eval``, held out: other SUMO seeds);
   at every step the teacher of ``algo=dqfd`` (:class:`uabs_rl.training.teacher.Teacher`,
   horizon ``--horizon``) scores each UABS's moves, and the moves of best score among
   those the mask that applied allows are that decision's *best set* (ties kept).
2. On the training windows a network of the run's architecture is fit by
   cross-entropy towards the best set (Adam, batches of 256 decisions), once from
   scratch and once from the run's own weights; agreement is printed after each count
   of ``--steps``.
3. Agreement: the share of decisions with a choice (two legal moves or more; a forced
   move always agrees) whose greedy legal move lies in the best set, on the fitting
   windows and on the validation ones, for the run itself and for each fit.

A fit that ends level with the run on the held-out traces says that the planner's other
moves were not learnt from this observation by reinforcement or by imitation, within
the fit's budget (a lower bound on what imitation can reach, not a proof that nothing
can). One process, 2 torch threads.
"""

from __future__ import annotations

import argparse
import copy
import time
from pathlib import Path

import torch

from uabs_rl.algorithms import Dims, algorithm_class
from uabs_rl.cli import one_line_errors
from uabs_rl.env.uabs_env import MASK, OBS, window_count
from uabs_rl.evaluation.evaluator import make_eval_env
from uabs_rl.evaluation.load import load_evaluation
from uabs_rl.runs.checkpoint import load_checkpoint
from uabs_rl.safety.make import make_env, make_selector
from uabs_rl.safety.rules import ACTION_VALUE
from uabs_rl.traces.build import get_traces
from uabs_rl.training.teacher import Teacher


def network(run: Path):
    """The run's config, its env parameters and its network (``best.pt``)."""
    ev = load_evaluation(run, "best", split="eval")
    cfg, p = ev.cfg, ev.evaluator.env.base_env.params
    algorithm = algorithm_class(cfg.algo.name)
    net = algorithm.acting_network(cfg.algo, Dims(p.obs_dim, 4, p.n_uabs))
    net.load_state_dict(load_checkpoint(run / "checkpoints" / "best.pt")["learner"]
                        [algorithm.acting_key])
    return ev, net


@torch.no_grad()
def collect(env, net: torch.nn.Module, horizon: int):
    """Over one episode of ``env``'s windows flown by ``net``: observations
    ``[W, T, M, D]``, applied masks and best sets ``[W, T, M, 4]``."""
    selector, teacher = make_selector(env), Teacher(env.base_env, horizon)
    td = env.reset()
    obs, masks, best = [], [], []
    for _ in range(env.base_env.params.episode_steps):
        scores = teacher.scores(td)
        td.set(ACTION_VALUE, net(td.get(OBS)))
        selector(td)
        mask = td.get(MASK)
        obs.append(td.get(OBS))
        masks.append(mask)
        best.append(Teacher.best_moves(scores, mask))
        td = env.step(td)["next"]
    return tuple(torch.stack(x, 1) for x in (obs, masks, best))


@torch.no_grad()
def agreement(net: torch.nn.Module, obs, mask, best) -> float:
    """Share of decisions with a choice (two legal moves or more) whose greedy legal move
    is in the best set."""
    move = net(obs).masked_fill(~mask, -torch.inf).argmax(-1, keepdim=True)
    choice = mask.sum(-1) > 1
    return float((best.gather(-1, move).squeeze(-1) & choice).sum() / choice.sum())


def fit(net: torch.nn.Module, obs, mask, best, steps: list[int], seed: int, report) -> None:
    """``net`` fit by cross-entropy of its legal values (as logits) towards the best set;
    ``report(net, n)`` after each count ``n`` of ``steps``."""
    torch.manual_seed(seed)
    keep = mask.any(-1)
    x, m, b = obs[keep], mask[keep], best[keep]
    opt = torch.optim.Adam(net.parameters(), lr=3e-4)
    for n in range(1, max(steps) + 1):
        i = torch.randint(0, x.shape[0], (256,))
        logits = net(x[i]).masked_fill(~m[i], -1e9)
        loss = (torch.logsumexp(logits, -1)
                - torch.logsumexp(logits.masked_fill(~b[i], -1e9), -1)).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if n in steps:
            report(net, n)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a run folder (a population's member)")
    ap.add_argument("--horizon", type=int, default=5, help="the teacher planner's H")
    ap.add_argument("--windows", type=int, default=96, help="training windows flown")
    ap.add_argument("--steps", type=int, nargs="+", default=[1000, 3000, 10000],
                    help="Adam steps after which each fit is reported")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(2)
    t0 = time.perf_counter()
    ev, net = network(args.run)
    cfg = ev.cfg
    traces = get_traces(cfg.scenario, cfg.traces, "train", verbose=False)
    train_env = make_env(cfg.scenario, cfg.channel, cfg.masking, traces, "train",
                         n_envs=args.windows, seed=args.seed, obs=cfg.obs)
    held = get_traces(cfg.scenario, cfg.traces, "eval", verbose=False)
    held_env = make_eval_env(cfg, held, split="eval", windows=window_count(
        held.n_sims, held.steps, cfg.scenario.episode_steps))  # every validation window
    held_env.set_seed(ev.evaluator.seed)
    data = {"fitting": collect(train_env, net, args.horizon),
            "validation": collect(held_env, net, args.horizon)}
    counts = {k: int((d[1].sum(-1) > 1).sum()) for k, d in data.items()}
    ties = float(torch.cat([(d[2].sum(-1) > 1)[d[1].sum(-1) > 1] for d in data.values()])
                 .float().mean())
    print(f"{args.run}: teacher H = {args.horizon}; decisions with a choice: "
          f"{counts['fitting']} to fit ({args.windows} training windows), "
          f"{counts['validation']} held out ({data['validation'][0].shape[0]} validation "
          f"windows); {100 * ties:.1f} % of them tie between moves; collected in "
          f"{time.perf_counter() - t0:.0f} s", flush=True)

    def line(name: str, model: torch.nn.Module) -> None:
        a = {k: 100 * agreement(model, *d) for k, d in data.items()}
        print(f"  {name:<36} agreement: fitting {a['fitting']:.1f} %, validation "
              f"{a['validation']:.1f} %", flush=True)

    line("the run (its RL training)", net)
    fresh = copy.deepcopy(net)
    torch.manual_seed(args.seed)
    for layer in fresh.modules():
        if hasattr(layer, "reset_parameters"):
            layer.reset_parameters()
    for name, model in (("from scratch", fresh), ("from the run", copy.deepcopy(net))):
        fit(model, *data["fitting"], args.steps, args.seed,
            lambda m, n, name=name: line(f"fit {name}, {n} steps", m))


if __name__ == "__main__":
    one_line_errors(main)
