"""The env step at ``n_envs = 1`` against a plain NumPy implementation of the same step.

    python benchmarks/numpy_reference.py                 # verify, then time
    python benchmarks/numpy_reference.py --no-compile    # only the eager variants

:class:`NumpyStep` is the step of the default configuration (ideal beams, no shadow
fading, where every link inside a footprint reaches SNR_th, so no random draw decides
service) for one env, written as directly as NumPy allows: move, vehicles of the step,
beam cells, priorities and service windows, beam sums, rewards, observation, P_g.
It is first checked against ``UABSEnv`` over whole episodes (same start state, same
random legal actions), through ``env.step`` and through ``env.step_direct``:
observations, rewards, served fractions and P_g curves must agree to float32 rounding,
or the script stops. Then all are timed side by side, interleaved, in one process:
NumPy; the env's step math on raw tensors; ``env.step_direct``, the step the training
loop takes (the step math, its outputs keyed as the env's TensorDict, no TensorDict);
and ``env.step`` (TorchRL: TensorDicts, shape and done checks). Each eager and
compiled as training compiles it (``train.compile=true``: Inductor with its C++
wrapper), plus the step math compiled with Inductor's default Python wrapper. Ratios
are NumPy time / other time: at least 1 means at least as fast as NumPy.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from uabs_rl.config import ChannelConfig, ScenarioConfig, TracesConfig
from uabs_rl.env.links import LinkModel
from uabs_rl.env.params import EnvParams
from uabs_rl.env.uabs_env import ACTION, DIAG, OBS, UABSEnv
from uabs_rl.traces.build import get_traces

MOVES = np.array([[0.0, 1.0], [1.0, 0.0], [0.0, -1.0], [-1.0, 0.0]], dtype=np.float32)


class NumpyStep:
    """One env's step in NumPy (the default configuration; see the module docstring)."""

    def __init__(self, p: EnvParams, veh_pos: np.ndarray, veh_present: np.ndarray):
        self.p = p
        self.veh_pos, self.veh_present = veh_pos, veh_present  # [S, steps, 2, V], [S, steps, V]
        self.k = int(round(p.n_beams ** 0.5))
        self.inv = 1.0 / (2.0 * p.r_b)
        self.moves = MOVES * p.step_m
        self.area = np.array([p.width, p.height], dtype=np.float32)

    def load(self, st: dict[str, torch.Tensor]) -> None:
        """Take env 0 of the torch env's state."""
        self.s = {k: v[0].cpu().numpy().copy() for k, v in st.items()}

    def step(self, action: np.ndarray) -> dict[str, np.ndarray]:
        p, s, k = self.p, self.s, self.k
        old = s["pos"]
        x, y = old[:, 0], old[:, 1]
        legal = np.stack([y + p.step_m <= p.height, x + p.step_m <= p.width,
                          y - p.step_m >= 0.0, x - p.step_m >= 0.0], -1)[np.arange(len(action)),
                                                                           action]
        pos = np.where(legal[:, None], old + self.moves[action], old).astype(np.float32)
        s["pos"] = pos
        t = int(s["t"]) + 1
        s["t"] = t
        # the vehicles of this step
        steps = self.veh_pos.shape[1]
        row = int(s["start"]) + min(t, steps - 1 - int(s["start"]))
        veh = self.veh_pos[int(s["sim"]), row]  # [2, V]
        present = self.veh_present[int(s["sim"]), row]  # [V]
        # beam cells: nearest beam centre per axis, inside if within r_b of it
        half = (k - 1) / 2.0
        gx = veh[0][None, :] * self.inv - (pos[:, 0:1] * self.inv - half)
        gy = (pos[:, 1:2] * self.inv + half) - veh[1][None, :] * self.inv
        col = np.clip(np.round(gx), 0, k - 1)
        rowb = np.clip(np.round(gy), 0, k - 1)
        fx, fy = gx - col, gy - rowb
        inside = (fx * fx + fy * fy <= 0.25) & present[None, :]  # [M, V]
        beam = (col + rowb * k).astype(np.int64)
        served = inside.any(0)
        # priorities and service windows
        n = p.window_steps
        start = t % n == 0
        arrived = present & ~s["prev_present"]
        prio = s["priority"] + served
        prio[start | arrived] = 1.0
        prio[~present] = 0.0
        s["priority"] = prio.astype(np.float32)
        s["served_count"] = served.astype(np.int64) if start else s["served_count"] + served
        s["window_full"] = present.copy() if start else s["window_full"] & present
        s["prev_present"] = present
        if t % n == n - 1:
            ended = s["window_full"]
            s["n_windows"][ended] += 1.0
            s["ns_hist"][np.nonzero(ended)[0], s["served_count"][ended]] += 1.0
        # beam sums and rewards
        b = np.zeros((p.n_uabs, p.n_beams), dtype=np.float32)
        for u in range(p.n_uabs):
            b[u] = np.bincount(beam[u][inside[u]], weights=s["priority"][inside[u]],
                               minlength=p.n_beams)
        d = np.sqrt(((pos[:, None, :] - pos[None, :, :]) ** 2).sum(-1))
        np.fill_diagonal(d, np.inf)
        r = b.sum(-1)
        r[(d < p.d_th).any(-1)] = -p.lambda_s
        r[(d < p.collision_distance).any(-1)] = -p.lambda_c
        s["ep_return"] = s["ep_return"] + r.sum()
        # observation and P_g
        m = p.n_uabs
        norm = pos / self.area
        obs = np.concatenate([norm, np.full((m, 1), t / p.episode_steps, np.float32),
                              np.broadcast_to(norm.reshape(1, 2 * m), (m, 2 * m)),
                              b / p.obs_scale], -1)
        counted = s["n_windows"] > 0
        inv = np.where(counted, 1.0 / np.maximum(s["n_windows"], 1.0), 0.0)
        per_ns = inv @ s["ns_hist"]
        pg = np.cumsum(per_ns[::-1])[::-1][1:] / max(int(counted.sum()), 1)
        return {"observation": obs, "reward": r,
                "served_fraction": served.sum() / max(present.sum(), 1), "pg_curve": pg}


def check_equal(env: UABSEnv, twin: UABSEnv, ref: NumpyStep, episodes: int,
                gen: torch.Generator) -> int:
    """Step ``env`` (``env.step``), ``twin`` (``step_direct``) and ``ref`` through
    ``episodes`` episodes of random legal actions; stop on the first mismatch. Returns
    the steps compared."""
    compared = 0
    for _ in range(episodes):
        td = env.reset()
        twin.reset_direct()
        ref.load(env.state)
        for _ in range(env.params.episode_steps):
            mask = td["agents", "action_mask"][0]
            action = torch.multinomial(mask.float(), 1, generator=gen).squeeze(-1)
            out = ref.step(action.numpy())
            td = env.step(td.set(ACTION, action[None]))["next"]
            direct = twin.step_direct(action[None])
            for name, got in (("env.step", td), ("env.step_direct", direct)):
                for key, value in {"observation": got[OBS][0],
                                   "reward": got["agents", "reward"][0, :, 0],
                                   "served_fraction": got[DIAG, "served_fraction"][0],
                                   "pg_curve": got[DIAG, "pg_curve"][0]}.items():
                    if not np.allclose(value.numpy(), out[key], rtol=1e-5, atol=1e-6):
                        raise SystemExit(f"mismatch in {key} at step {compared}: {name} "
                                         f"{value.numpy()} numpy {out[key]}")
            compared += 1
    return compared


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=3, help="episodes compared for equality")
    ap.add_argument("--repeats", type=int, default=7, help="timed episodes per variant")
    ap.add_argument("--no-compile", dest="compile", action="store_false",
                    help="skip the compiled variants (about 30 s of compilation)")
    args = ap.parse_args()
    scenario, channel = ScenarioConfig(), ChannelConfig()
    traces = get_traces(scenario, TracesConfig(), "train", verbose=False)
    env = UABSEnv(scenario, channel, traces, n_envs=1, seed=0)
    p = env.params
    if not LinkModel(p, env.device).always_served:
        raise SystemExit("the reference covers the default channel (every link inside a "
                         "footprint served); run it without channel overrides")
    ref = NumpyStep(p, env.veh_pos.numpy(), env.veh_present.numpy())
    gen = torch.Generator().manual_seed(0)
    twin = UABSEnv(scenario, channel, traces, n_envs=1, seed=0)
    n = check_equal(env, twin, ref, args.episodes, gen)
    print(f"equal: {n} steps ({args.episodes} episodes of random legal actions): "
          f"observation, reward, served fraction and P_g curve of env.step and "
          f"env.step_direct agree with numpy (rtol 1e-5)")

    steps, m = p.episode_steps, p.n_uabs
    actions = torch.randint(0, 4, (steps, 1, m), generator=gen)
    np_actions = actions[:, 0].numpy()

    def numpy_episode():
        env.reset()
        ref.load(env.state)
        t0 = time.perf_counter()
        for a in np_actions:
            ref.step(a)
        return time.perf_counter() - t0

    def raw_episode(fn):
        def run():
            env.reset()
            st = env.state
            t0 = time.perf_counter()
            for a in actions:
                fn(st, a, env.veh_pos, env.veh_present, env.rng)
            return time.perf_counter() - t0
        return run

    def env_episode(e: UABSEnv):
        def run():
            td = e.reset()
            t0 = time.perf_counter()
            for a in actions:
                td = e.step(td.set(ACTION, a))["next"]
            return time.perf_counter() - t0
        return run

    def direct_episode(e: UABSEnv):
        def run():
            e.reset_direct()
            t0 = time.perf_counter()
            for a in actions:
                e.step_direct(a)
            return time.perf_counter() - t0
        return run

    variants = {"numpy": numpy_episode, "step math, eager": raw_episode(env.math.step),
                "env.step_direct, eager": direct_episode(env),
                "env.step, eager": env_episode(env)}
    if args.compile:  # what training runs (train.compile=true)
        cenv = UABSEnv(scenario, channel, traces, n_envs=1, seed=0, compile_step=True)
        variants.update({
            "step math, compiled (Python wrapper)": raw_episode(
                torch.compile(env.math.step, dynamic=False)),
            "step math, compiled": raw_episode(cenv._step_math),
            "env.step_direct, compiled": direct_episode(cenv),
            "env.step, compiled": env_episode(cenv)})
    best = dict.fromkeys(variants, float("inf"))
    for fn in variants.values():  # warm-up (and compilation)
        fn()
    for _ in range(args.repeats):  # interleaved, so load on the machine hits all alike
        for name, fn in variants.items():
            best[name] = min(best[name], fn())
    print(f"n_envs=1, M={m}, vehicles={traces.max_vehicles}, threads={torch.get_num_threads()}; "
          f"fastest of {args.repeats} episodes of {steps} steps, interleaved")
    print(f"{'variant':>38} {'agent-steps/s':>14} {'us per step':>12} "
          f"{'numpy time / this':>18}")
    for name, t in best.items():
        print(f"{name:>38} {steps * m / t:>14.0f} {1e6 * t / steps:>12.1f} "
              f"{best['numpy'] / t:>18.2f}")


if __name__ == "__main__":
    main()
