"""The mpc's own value as the leaf values of ``--policy leaf``: fitted to the mpc's returns.

The leaf hybrid (:mod:`uabs_rl.evaluation.leaf`) scores each path of the mpc's search by
what it covers over H steps plus λ V(o_{t+H}), V = max_a Q of a learned network. With
the generalist's network, V is the value of the *learned* policy from o_{t+H}, a weaker
policy than the mpc that continues after the horizon. This benchmark fits V to the
*mpc's* discounted return instead (policy evaluation of the mpc, by Monte Carlo): the
mpc flown on the training traces of the generalist's cities (its family, at the fleet
sizes of ``--fleets``), each UABS's return G_t = Σ_k γ^k r_{t+k} (its own covered
priority, γ = ``--gamma``, 0 past the episode's end) regressed on its egocentric
observation o_t by a network of the template run's architecture, all its outputs to G
(so max_a Q = V). The search with these values is one step of policy improvement over
the mpc: it plans H steps, then assumes the mpc continues.

    python benchmarks/mpc_value.py outputs/runs/<egocentric run> --out outputs/runs/mpc_value5 \
        --members 5 --fleets 3 6 --windows 96
    python benchmarks/hybrid.py outputs/runs/mpc_value5 scenario=lights60 --leaf \
        --weights 0 0.5 1 2 --out docs/results/planning_vs_learning/mpc_value/lights60_3

``--out`` is a population folder (``seed=<s>/``), each member a copy of the template
run's folder whose ``best.pt`` holds the fitted network in place of the run's
(``learner.qnet``): ``uabs-eval`` and ``hybrid.py`` fly it as any run. Members differ
in the fit's seed (initialisation, batches and a bootstrap draw of the training
windows). Nothing of the template's own is changed. Prints the data's size, each
member's held-out R² and the wall time; writes ``fit.json`` into ``--out``. An ``--out``
that holds files without a ``fit.json`` (not written by this script) is refused, since
its ``seed=<s>`` folders would be replaced.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

from uabs_rl.cli import one_line_errors
from uabs_rl.config import ConfigError, family_scenarios
from uabs_rl.env.uabs_env import N_ACTIONS, OBS, REWARD
from uabs_rl.evaluation.baselines import MPC, baseline_policy
from uabs_rl.evaluation.evaluator import Evaluator, make_eval_env
from uabs_rl.evaluation.predict import make_predictor
from uabs_rl.runs.checkpoint import config_from_checkpoint, load_checkpoint, save_checkpoint
from uabs_rl.runs.layout import RunFolder
from uabs_rl.safety.make import make_selector


def returns(reward: torch.Tensor, gamma: float) -> torch.Tensor:
    """``[E, T, M]`` discounted returns of the rewards ``[E, T, M]`` of whole episodes:
    G_t = r_t + γ G_{t+1}, G_T = 0."""
    out = torch.zeros_like(reward)
    acc = torch.zeros_like(reward[:, 0])
    for t in range(reward.shape[1] - 1, -1, -1):
        acc = reward[:, t] + gamma * acc
        out[:, t] = acc
    return out


def mpc_samples(cfg, city, fleet: int, windows: int, horizon: int, gamma: float,
                explore: float = 0.0
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, float]:
    """(observations [N, D], returns [N], window index [N], served fraction) of the
    mpc flown on ``windows`` training windows of ``city`` with ``fleet`` UABS, each move
    replaced with probability ``explore`` by a legal one drawn at random (the masks'
    ε-greedy choice)."""
    c = replace(cfg, scenario=replace(city, n_uabs=fleet))
    env = make_eval_env(c, windows=windows, split="train")
    gen = torch.Generator().manual_seed(0)
    policy = baseline_policy(MPC, env, make_selector(env, explore, gen), 0, horizon=horizon,
                             predictor=make_predictor("cv", "all", c.scenario))
    ev = Evaluator(env, c.train.eval_seed)
    td = ev.rollout(policy)
    rec = ev.record(td)
    unsafe = rec["collisions"] + rec["proximity"] + rec["fallbacks"]
    if unsafe:
        sys.exit(f"{city.name} M={fleet}: the mpc was unsafe ({unsafe} events)")
    obs = td[OBS]  # [E, T, M, D]
    reward = td["next", REWARD].squeeze(-1)  # [E, T, M]
    g = returns(reward, gamma)
    e, t, m = g.shape
    win = torch.arange(e)[:, None, None].expand(e, t, m)
    return (obs.reshape(e * t * m, -1), g.reshape(-1), win.reshape(-1),
            rec["served_fraction"])


def fit(net: torch.nn.Module, x: torch.Tensor, y: torch.Tensor, seed: int, steps: int,
        lr: float, batch: int) -> tuple[torch.nn.Module, float]:
    """Every output of ``net`` regressed on ``y`` (scaled to unit spread, the heads
    scaled back after); returns the net and its R² on a held-out tenth of the rows
    (rows of the same windows, and copies of a row a bootstrap drew twice, lie on both
    sides: optimistic; :func:`r2_on` over whole windows left out is the honest one)."""
    gen = torch.Generator().manual_seed(seed)
    perm = torch.randperm(len(y), generator=gen)
    cut = len(y) // 10
    test, train = perm[:cut], perm[cut:]
    scale = float(y[train].std()) or 1.0
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    for _ in range(steps):
        idx = train[torch.randint(len(train), (batch,), generator=gen)]
        q = net(x[idx])
        loss = ((q - (y[idx] / scale)[:, None]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        for head in (net.value, net.advantage):
            head.weight.mul_(scale)
            head.bias.mul_(scale)
    return net, r2_on(net, x[test], y[test])


@torch.no_grad()
def r2_on(net: torch.nn.Module, x: torch.Tensor, y: torch.Tensor) -> float:
    """R² of ``net``'s mean output as a prediction of ``y``."""
    pred = net(x).mean(-1)
    return 1 - float(((pred - y) ** 2).mean() / y.var())


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("template", type=Path, help="an egocentric run folder (its config, "
                    "network shape and folder are copied)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--members", type=int, default=5)
    ap.add_argument("--fleets", type=int, nargs="+", default=[3, 6])
    ap.add_argument("--windows", type=int, default=96, help="training windows per city")
    ap.add_argument("--horizon", type=int, default=5, help="the mpc's")
    ap.add_argument("--gamma", type=float, default=0.8)
    ap.add_argument("--explore", type=float, default=0.0,
                    help="probability of a random legal move in place of the mpc's (the "
                         "data then holds states beside the mpc's own; the returns are "
                         "those of that perturbed mpc)")
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--batch", type=int, default=512)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    template = RunFolder(args.template).members()[0]
    if Path(args.out).resolve().is_relative_to(Path(template).resolve()):
        ap.error(f"--out {args.out} lies inside the template run {template}: the members "
                 f"are copies of it")
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not (out / "fit.json").is_file():
        # its members' folders are replaced: only a folder this script wrote before
        ap.error(f"--out {out} holds files this script did not write (no fit.json): its "
                 f"seed=<s> folders would be replaced; give a new or empty folder")
    ckpt = RunFolder(template).checkpoint("best")
    state = load_checkpoint(ckpt)
    cfg = config_from_checkpoint(state, ckpt)
    if not cfg.obs.name.startswith("egocentric"):
        raise ConfigError(f"{template}: obs={cfg.obs.name}; the leaf values need an "
                          f"egocentric run (experiment=generalist)")
    cities = family_scenarios(cfg) or [cfg.scenario]
    xs, ys, groups = [], [], []
    for city in cities:
        for m in args.fleets:
            try:
                x, y, w, served = mpc_samples(cfg, city, m, args.windows, args.horizon,
                                              args.gamma, args.explore)
            except ConfigError as e:
                print(f"{city.name} M={m}: skipped ({str(e).splitlines()[0][:120]})")
                continue
            groups.append(len(groups) * args.windows + w)  # a window of one (city, M)
            xs.append(x)
            ys.append(y)
            print(f"{city.name} M={m}: {len(y)} samples, mpc served {100 * served:.2f} %, "
                  f"mean return {float(y.mean()):.1f} ({time.perf_counter() - t0:.0f} s)",
                  flush=True)
    x, y, group = torch.cat(xs), torch.cat(ys), torch.cat(groups)
    from uabs_rl.algorithms.dqn3 import DuelingQNet

    fits = []
    for s in range(args.members):
        torch.manual_seed(s)
        gen = torch.Generator().manual_seed(1000 + s)
        ids = group.unique()
        drawn = ids[torch.randint(len(ids), (len(ids),), generator=gen)]  # a bootstrap
        counts = torch.bincount(torch.searchsorted(ids, drawn), minlength=len(ids))
        rows = counts[torch.searchsorted(ids, group)]
        sel = torch.repeat_interleave(torch.arange(len(y)), rows)
        net = DuelingQNet(x.shape[1], N_ACTIONS, list(cfg.algo.hidden))
        net, r2 = fit(net, x[sel], y[sel], s, args.steps, args.lr, args.batch)
        dest = RunFolder(args.out).member(s).path
        if dest.exists():
            shutil.rmtree(dest)
        shutil.copytree(template, dest, ignore=shutil.ignore_patterns("tb", "evaluation"))
        new = load_checkpoint(RunFolder(dest).checkpoint("best"))
        new["learner"]["qnet"] = net.state_dict()
        save_checkpoint(new, RunFolder(dest).checkpoint("best"))
        left = ~torch.isin(group, drawn)  # the windows this member's bootstrap left out
        oob = r2_on(net, x[left], y[left]) if bool(left.any()) else float("nan")
        n_left = int((~torch.isin(ids, drawn)).sum())
        fits.append({"seed": s, "r2_held_out": r2, "r2_windows_left_out": oob,
                     "windows_left_out": n_left, "rows": int(len(sel))})
        print(f"member {s}: R² {r2:.3f} on a held-out tenth of its rows (optimistic), "
              f"{oob:.3f} on the {n_left} windows its bootstrap left out "
              f"({time.perf_counter() - t0:.0f} s)",
              flush=True)
    (Path(args.out) / "fit.json").write_text(json.dumps(
        {"template": str(template), "gamma": args.gamma, "horizon": args.horizon,
         "explore": args.explore,
         "fleets": args.fleets, "windows": args.windows, "steps": args.steps,
         "samples": int(len(y)), "members": fits}, indent=1))
    print(f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    one_line_errors(main)
