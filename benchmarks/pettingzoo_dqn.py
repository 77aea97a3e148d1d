"""A learner of another framework through the PettingZoo door: TorchRL's own
``PettingZooWrapper`` over :class:`uabs_rl.interop.pettingzoo.UABSParallelEnv`, a
``Collector`` and TorchRL's ``DQNLoss`` (one Q-network shared by the agents, masked
ε-greedy on the ``action_mask`` the door gives). Prints the frames, updates, the mean
loss and the closest any two UABS came against d_th (docs/interop.md).
``--mask-sizes`` prints instead, under uniformly random legal actions, each agent's mean
number of legal moves under the boundary, recoverable flat, parallel rank and
sequential rank masks (the last given the same higher-ranked choices).

    pip install -e ".[interop]"
    python benchmarks/pettingzoo_dqn.py --masking rank --frames 400 experiment=smoke
    python benchmarks/pettingzoo_dqn.py --mask-sizes scenario.n_uabs=6 experiment=smoke
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import PettingZooWrapper
from torchrl.modules import MLP, EGreedyModule, QValueModule
from torchrl.objectives import DQNLoss, SoftUpdate

from uabs_rl.config import compose
from uabs_rl.env.uabs_env import BACKUP, MASK, POSITION
from uabs_rl.interop.pettingzoo import UABSParallelEnv, make_parallel_env
from uabs_rl.safety.rules import flat_recoverable_mask
from uabs_rl.traces.build import get_traces

GROUP = "uabs"  # PettingZooWrapper groups the agents uabs_0 ... uabs_{M-1} as "uabs"


def train(penv: UABSParallelEnv, frames: int = 400, frames_per_batch: int = 20,
          seed: int = 0, threads: int = 1) -> dict[str, float]:
    """Train a parameter-shared DQN on ``penv`` for ``frames`` env steps; returns the
    updates made, the mean loss, how far the parameters moved, the closest approach of
    two UABS over the run (m) and the actions the door had to repair. ``threads``: torch
    threads meanwhile (a network this small runs fastest on one: ten times slower on two
    cores that other processes keep busy)."""
    before_threads = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        return _train(penv, frames, frames_per_batch, seed)
    finally:
        torch.set_num_threads(before_threads)


def _train(penv: UABSParallelEnv, frames: int, frames_per_batch: int,
           seed: int) -> dict[str, float]:
    torch.manual_seed(seed)
    env = PettingZooWrapper(penv, categorical_actions=True, seed=seed)
    action_spec = env.full_action_spec[GROUP, "action"]
    obs_dim = env.observation_spec[GROUP, "observation", "observation"].shape[-1]
    keys = dict(obs=(GROUP, "observation", "observation"), mask=(GROUP, "action_mask"),
                action=(GROUP, "action"), value=(GROUP, "action_value"))
    net = TensorDictModule(MLP(in_features=obs_dim, out_features=action_spec.space.n,
                               num_cells=[64, 64]), in_keys=[keys["obs"]],
                           out_keys=[keys["value"]])
    qvalue = QValueModule(action_value_key=keys["value"], action_mask_key=keys["mask"],
                          out_keys=[keys["action"], keys["value"],
                                    (GROUP, "chosen_action_value")], spec=action_spec,
                          strict_shape=False)
    policy = TensorDictSequential(net, qvalue)
    explore = TensorDictSequential(policy, EGreedyModule(
        action_spec, eps_init=1.0, eps_end=0.05, annealing_num_steps=frames // 2,
        action_key=keys["action"], action_mask_key=keys["mask"]))
    loss = DQNLoss(policy, action_space=action_spec, delay_value=True, double_dqn=True)
    loss.set_keys(action_value=keys["value"], action=keys["action"],
                  value=(GROUP, "chosen_action_value"), reward=(GROUP, "reward"),
                  done=(GROUP, "done"), terminated=(GROUP, "terminated"))
    loss.make_value_estimator(gamma=0.9)
    target = SoftUpdate(loss, eps=0.95)
    optim = torch.optim.Adam(loss.parameters(), lr=1e-3)
    buffer = ReplayBuffer(storage=LazyTensorStorage(10_000), batch_size=32)
    collector = Collector(env, explore, frames_per_batch=frames_per_batch,
                          total_frames=frames, auto_register_policy_transforms=False)
    before = [p.detach().clone() for p in net.parameters()]
    losses = []
    for batch in collector:
        buffer.extend(batch.reshape(-1))
        explore[-1].step(batch.numel())
        if len(buffer) < 64:
            continue
        for _ in range(frames_per_batch // 2):
            out = loss(buffer.sample())
            optim.zero_grad()
            out["loss"].backward()
            optim.step()
            target.step()
            losses.append(float(out["loss"].detach()))
    collector.shutdown()
    moved = sum(float((p.detach() - b).abs().sum()) for p, b in zip(net.parameters(), before,
                                                                 strict=True))
    return {"frames": float(frames), "updates": float(len(losses)),
            "mean_loss": sum(losses) / max(len(losses), 1), "parameter_change": moved,
            "closest_approach": penv.totals["closest_approach"], "d_th": penv.params.d_th,
            "repaired": penv.totals["repaired"], "collisions": penv.totals["collisions"]}


def mask_sizes(penv: UABSParallelEnv, episodes: int = 10,
               seed: int = 0) -> dict[str, float]:
    """Mean legal moves per agent and step (of 4) under random legal actions from the
    parallel rank masks ``penv`` gives (masking=rank, recoverable)."""
    if not penv.parallel_rank:
        raise SystemExit("--mask-sizes needs masking=rank with masking.recoverable=true")
    rng = np.random.default_rng(seed)
    sums = dict.fromkeys(("boundary", "flat", "parallel rank", "sequential rank"), 0.0)
    count = 0
    for episode in range(episodes):
        obs, _ = penv.reset(seed=seed + episode)
        while penv.agents:
            out, rule = penv._out, penv.rule
            acts = {a: int(rng.choice(np.flatnonzero(obs[a]["action_mask"])))
                    for a in penv.agents}
            want = torch.tensor([[acts[a] for a in penv.possible_agents]])
            _, seq, _ = rule.choose(torch.nn.functional.one_hot(want, 4).float(),
                                    out.get(MASK), *(out.get(k) for k in rule.choice_keys))
            flat = flat_recoverable_mask(out.get(POSITION), out.get(MASK), out.get(BACKUP),
                                         rule.moves, rule.d_th)
            for k, mask in zip(sums, (out.get(MASK), flat, penv._mask, seq), strict=True):
                sums[k] += float(mask.sum())
            count += len(acts)
            obs, *_ = penv.step(acts)
    return {k: v / count for k, v in sums.items()}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--masking", default="rank", choices=["penalty", "flat", "rank"])
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--mask-sizes", action="store_true",
                    help="print the mean legal moves per mask instead of training")
    ap.add_argument("overrides", nargs="*", help="config overrides (uabs-train's)")
    args = ap.parse_args(argv)
    cfg = compose("config", [f"masking={args.masking}", *args.overrides])
    traces = get_traces(cfg.scenario, cfg.traces, "train")
    penv = make_parallel_env(cfg.scenario, cfg.channel, cfg.masking, traces,
                             seed=args.seed, obs=cfg.obs)
    result = (mask_sizes(penv, seed=args.seed) if args.mask_sizes
              else train(penv, args.frames, seed=args.seed))
    for k, v in result.items():
        print(f"{k}: {v:.4g}")


if __name__ == "__main__":
    main()
