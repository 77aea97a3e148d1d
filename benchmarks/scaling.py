"""Scaling study: environment and training throughput against n_envs, and environment
cost against fleet size M and vehicle count |G|.

    python benchmarks/scaling.py                  # prints three tables, saves scaling.png
    python benchmarks/scaling.py --device cuda --out scaling_cuda.png
    python benchmarks/scaling.py --law-only --out docs/cost_law.png   # table 3 only,
                                                   # plotted against M·|G|

Vehicle counts beyond the cached SUMO traces use synthetic traces (vehicles on a random
walk over the area): the env's cost depends on how many there are, not on where.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))
from env_bench import bench  # noqa: E402

from uabs_rl.config import ChannelConfig, ScenarioConfig, TracesConfig, compose  # noqa: E402
from uabs_rl.env.uabs_env import UABSEnv  # noqa: E402
from uabs_rl.traces.build import get_traces  # noqa: E402
from uabs_rl.traces.cache import TraceSet  # noqa: E402


def synthetic_traces(n_vehicles: int, steps: int, width: float, height: float) -> TraceSet:
    g = torch.Generator().manual_seed(0)
    start = torch.rand(n_vehicles, 2, generator=g) * torch.tensor([width, height])
    walk = torch.randn(steps, n_vehicles, 2, generator=g).cumsum(0) * 5.0
    pos = (start + walk).abs()
    pos[..., 0] = width - (width - pos[..., 0] % (2 * width)).abs()  # reflect into the area
    pos[..., 1] = height - (height - pos[..., 1] % (2 * height)).abs()
    return TraceSet(pos[None].float(), torch.ones(1, steps, n_vehicles, dtype=torch.bool),
                    {"split": "synthetic", "dt": 1.0})


def step_cost(m: int, n_vehicles: int, n_envs: int, device: str, reps: int = 3) -> float:
    """Milliseconds per batched step of the raw step math."""
    sc = ScenarioConfig(n_uabs=m)
    env = UABSEnv(sc, ChannelConfig(), synthetic_traces(n_vehicles, 200, 350.0, 170.0),
                  n_envs=n_envs, device=device)
    a = torch.randint(0, 4, (n_envs, m), device=device)
    best = float("inf")
    for _ in range(reps):
        env.reset()
        st = env.state
        t0 = time.perf_counter()
        for _ in range(20):
            env.math.step(st, a, env.veh_pos, env.veh_present, env.rng)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        best = min(best, (time.perf_counter() - t0) / 20)
    return 1000 * best


def training_rate(n_envs: int, device: str, rounds: int) -> tuple[float, float]:
    """(env steps/s, updates/s) of the trainer with n_envs parallel episodes."""
    from uabs_rl.training.experiment import Experiment

    cfg = compose("config", [f"train.n_envs={n_envs}", f"train.episodes={n_envs * 100}",
                             "train.progress=false", "train.logger=none",
                             f"device={device}", "train.compile=false"])
    tr = Experiment(cfg, tempfile.mkdtemp(prefix="uabs_scaling_"))
    while len(tr.buffer) < cfg.algo.learning_starts:
        tr.collect()
    steps0, upd0, t0 = tr.collector.env_steps, tr.learner.updates, time.perf_counter()
    for _ in range(rounds):
        tr.collect()
    dt = time.perf_counter() - t0
    return (tr.collector.env_steps - steps0) * n_envs / dt, (tr.learner.updates - upd0) / dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path, default=Path("scaling.png"))
    ap.add_argument("--n-envs", type=int, nargs="+", default=[1, 16, 64, 256, 1024])
    ap.add_argument("--train-n-envs", type=int, nargs="+", default=[1, 4, 16])
    ap.add_argument("--fleets", type=int, nargs="+", default=[3, 10, 30])
    ap.add_argument("--vehicles", type=int, nargs="+", default=[80, 800, 8000])
    ap.add_argument("--law-only", action="store_true",
                    help="only table 3, plotted as cost per step against M·|G|")
    args = ap.parse_args()
    if args.law_only:
        grid = _cost_table(args)
        _plot_law(grid, args.vehicles, args.out)
        print(f"\nsaved {args.out}")
        return
    scenario, channel = ScenarioConfig(), ChannelConfig()
    traces = get_traces(scenario, TracesConfig(), "train", verbose=False)

    print(f"device={args.device} threads={torch.get_num_threads()}\n")
    print("1. environment throughput (M=3, |G|=80, SUMO traces)")
    print(f"{'n_envs':>7} {'env steps/s':>12} {'agent-steps/s':>14}")
    env_rows = []
    for n in args.n_envs:
        r = bench(n, args.device, 3, scenario, channel, traces)
        env_rows.append((n, r["env_asps"]))
        print(f"{n:>7} {r['env_sps']:>12.0f} {r['env_asps']:>14,.0f}")

    print("\n2. training throughput (paper network; updates per collector step = n_envs)")
    print(f"{'n_envs':>7} {'env steps/s':>12} {'updates/s':>10}")
    for n in args.train_n_envs:
        sps, ups = training_rate(n, args.device, max(1, 8 // n))
        print(f"{n:>7} {sps:>12.0f} {ups:>10.0f}")

    grid = _cost_table(args)
    _plot(env_rows, grid, args.vehicles, args.out)
    print(f"\nsaved {args.out}")


def _cost_table(args) -> dict[int, list[float]]:
    print("\n3. environment cost (ms per batched step, n_envs=64) against M and |G|")
    print(f"{'M, |G|=':>8} " + " ".join(f"{v:>9}" for v in args.vehicles))
    grid = {}
    for m in args.fleets:
        row = [step_cost(m, v, 64, args.device) for v in args.vehicles]
        grid[m] = row
        print(f"{m:>8} " + " ".join(f"{c:>9.2f}" for c in row))
    return grid


def _plot_law(grid: dict[int, list[float]], vehicles: list[int], path: Path) -> None:
    """Cost per env step against the links per env M·|G|, with the proportional line
    through the largest point (the law the cost tends to)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from uabs_rl.evaluation.plots import COLUMN_IN, PAPER_RC, save_figure

    with plt.rc_context(PAPER_RC):
        fig, ax = plt.subplots(figsize=(COLUMN_IN, 2.6))
        pts = []
        for m, row in grid.items():
            x = [m * v for v in vehicles]
            y = [1000 * c / 64 for c in row]  # µs per env step
            pts += list(zip(x, y, strict=True))
            ax.loglog(x, y, marker="o", ls="", label=f"M = {m}")
        x_max, y_max = max(pts)
        xs = np.array([min(x for x, _ in pts), x_max])
        ax.loglog(xs, y_max * xs / x_max, color="0.4", ls="--", lw=1,
                  label="proportional to M·|G|")
        ax.set_xlabel("links per env step, M·|G|")
        ax.set_ylabel("µs per env step")
        ax.grid(alpha=0.3, which="both")
        ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False)
        fig.tight_layout()
        save_figure(fig, path)
        plt.close(fig)


def _plot(env_rows, grid, vehicles, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4), dpi=110)
    a1.loglog([n for n, _ in env_rows], [r for _, r in env_rows], marker="o")
    a1.set_xlabel("n_envs")
    a1.set_ylabel("agent-steps / s")
    a1.set_title("environment throughput (M=3, |G|=80)")
    a1.grid(alpha=0.3, which="both")
    for m, row in grid.items():
        a2.loglog(vehicles, row, marker="o", label=f"M = {m}")
    a2.set_xlabel("|G| (vehicles)")
    a2.set_ylabel("ms per step (64 envs)")
    a2.set_title("environment cost")
    a2.grid(alpha=0.3, which="both")
    a2.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__":
    main()
