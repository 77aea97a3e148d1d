"""``uabs-train``: 3DQN training with periodic held-out evaluation (SPEC §7, §8).

    uabs-train                                    # paper protocol, masking=rank
    uabs-train masking=flat seed=3
    uabs-train -m masking=penalty,flat,rank seed=0,1,2
    uabs-train experiment=smoke                   # the whole pipeline in seconds
    uabs-train resume=outputs/runs/<run dir>      # continue a stopped run

Every run writes under its Hydra output directory: ``metrics.jsonl`` (one line per
training episode and per evaluation), ``tb/`` (TensorBoard), ``checkpoints/last.pt``
and ``checkpoints/best.pt`` (by evaluation return), ``eval/*.png``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from tqdm.auto import tqdm

from uabs_rl.channel import coverage_fraction
from uabs_rl.config import ConfigError, to_container, validate_run
from uabs_rl.env import ACTION, DIAG, MASK, N_ACTIONS, OBS, POSITION, REWARD
from uabs_rl.learner import DQNLearner
from uabs_rl.make import make_env, make_selector
from uabs_rl.masking import ACTION_VALUE, COLLIDERS, RANK_ORDER
from uabs_rl.model import DuelingQNet
from uabs_rl.replay import ReplayBuffer

log = logging.getLogger(__name__)

CKPT_FORMAT = 1
# config sections a checkpoint must agree with to be resumed or evaluated
COMPAT_KEYS = ("scenario", "channel", "masking", "algo", "traces", "seed", "train.n_envs")


# ----------------------------------------------------------------------------- checkpoints
class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable or from an incompatible config."""


def save_checkpoint(state: dict, path: Path) -> None:
    """Atomic write: a crash or Ctrl-C mid-write never damages the previous file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)


def load_checkpoint(path: Path) -> dict:
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}: pass a run directory that holds "
                              f"checkpoints/last.pt, or a .pt file written by uabs-train.")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise CheckpointError(f"cannot read checkpoint {path} ({type(e).__name__}: {e}); "
                              f"the file is damaged or not a uabs-train checkpoint.") from e
    if not isinstance(state, dict) or state.get("format") != CKPT_FORMAT:
        raise CheckpointError(f"{path} is not a uabs-train checkpoint of format {CKPT_FORMAT}.")
    return state


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: d}


def config_differences(saved: dict, current: dict) -> list[str]:
    """Settings of ``COMPAT_KEYS`` that differ between a checkpoint and a config."""
    a, b = _flatten(saved), _flatten(current)
    keys = sorted(k for k in set(a) | set(b) if any(
        k == c or k.startswith(c + ".") for c in COMPAT_KEYS) and not k.endswith("cache_dir"))
    return [f"{k}: {a.get(k, '<absent>')!r} in the checkpoint, {b.get(k, '<absent>')!r} now"
            for k in keys if a.get(k) != b.get(k)]


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device={name} but CUDA is not available here: use device=cpu "
                          f"or device=auto.")
    return torch.device(name)


# ----------------------------------------------------------------------------- trainer
class Trainer:
    """Collect / optimise / evaluate / checkpoint, one method each."""

    def __init__(self, cfg: Any, run_dir: Path, traces: dict[str, Any] | None = None):
        """``traces`` may hold ready TraceSets per split ("train", "eval"); by default
        they come from the trace cache (built with SUMO if missing)."""
        validate_run(cfg)
        self.cfg, self.run_dir = cfg, Path(run_dir)
        self.device = resolve_device(cfg.device)
        tr = cfg.train
        if tr.threads is not None:
            torch.set_num_threads(tr.threads)
        torch.manual_seed(cfg.seed)
        traces = traces or {}
        self.env = make_env(cfg.scenario, cfg.channel, cfg.masking,
                            traces.get("train", cfg.traces), "train",
                            n_envs=tr.n_envs, device=self.device, seed=cfg.seed,
                            compile=tr.compile, spec_mask=False)
        self.eval_env = make_env(cfg.scenario, cfg.channel, cfg.masking,
                                 traces.get("eval", cfg.traces), "eval",
                                 n_envs=tr.eval_windows, device=self.device,
                                 n_eval_windows=tr.eval_windows, seed=tr.eval_seed,
                                 compile=tr.compile, spec_mask=False)
        self.params = p = self.env.base_env.params
        self.qnet = DuelingQNet(p.obs_dim, N_ACTIONS, list(cfg.algo.hidden)).to(self.device)
        self.learner = DQNLearner(self.qnet, cfg.algo, N_ACTIONS)
        self.buffer = ReplayBuffer(cfg.algo.buffer_size, p.obs_dim, N_ACTIONS, self.device,
                                   seed=cfg.seed)
        self.gen = torch.Generator(device=self.device)
        self.gen.manual_seed(cfg.seed)
        self.selector = make_selector(self.env, cfg.masking, cfg.algo.eps_start, self.gen,
                                      compile=tr.compile)
        qmod = TensorDictModule(self.qnet, in_keys=[OBS], out_keys=[ACTION_VALUE])
        self.policy = TensorDictSequential(qmod, self.selector)
        eval_gen = torch.Generator(device=self.device)
        eval_gen.manual_seed(tr.eval_seed)  # greedy: no draw decides anything, but keep
        self.greedy_policy = TensorDictSequential(  # evaluation off the global RNG
            qmod, make_selector(self.eval_env, cfg.masking, 0.0, eval_gen, compile=tr.compile))
        self.greedy_next = cfg.masking.mode == "rank" and cfg.masking.rank_next_mask == "greedy"
        self.total_steps = tr.episodes * p.episode_steps  # per-env steps of the protocol
        self.episode, self.env_steps, self.update_credit = 0, 0, 0.0
        self.best_eval = -math.inf
        self.writer = None
        self.metrics_path = self.run_dir / "metrics.jsonl"

    # ------------------------------------------------------------------ schedule
    def epsilon(self) -> float:
        a = self.cfg.algo
        frac = min(1.0, self.env_steps / max(1.0, a.eps_fraction * self.total_steps))
        return a.eps_start + frac * (a.eps_end - a.eps_start)

    # ------------------------------------------------------------------ collect
    def _next_mask(self, td) -> torch.Tensor:
        """Masks of the double-DQN target at this state (see masking.next_state_mask);
        called before the selector overwrites the mask with the applied one."""
        if not self.greedy_next:
            return td.get(MASK)
        _, applied, _ = self.selector._select(  # the selector's (compiled) core, greedy
            "rank", td.get(ACTION_VALUE), td.get(MASK), td.get(POSITION), td.get(RANK_ORDER),
            td.get(COLLIDERS), self.selector.moves, self.params.d_th, 0.0, None)
        return applied

    def _push(self, tr: dict[str, torch.Tensor], next_mask: torch.Tensor) -> None:
        n = tr["obs"].shape[0] * tr["obs"].shape[1]
        self.buffer.push(**{k: v.reshape(n, *v.shape[2:]) for k, v in tr.items()},
                         next_mask=next_mask.reshape(n, N_ACTIONS))

    def collect_round(self) -> list[dict[str, float]]:
        """Run ``n_envs`` training episodes to the end, storing every agent's transitions
        and updating the network as the schedule says. Returns one record per episode."""
        p, e = self.params, self.cfg.train.n_envs
        td = self.env.reset()
        served = torch.zeros(e, device=self.device)
        loss_sum = torch.zeros((), device=self.device)
        q_sum = torch.zeros((), device=self.device)
        n_updates, pending = 0, None
        for t in range(p.episode_steps):
            eps = self.epsilon()
            self.selector.eps.fill_(eps)
            with torch.no_grad():
                td.set(ACTION_VALUE, self.qnet(td.get(OBS)))
            if pending is not None:
                self._push(pending, self._next_mask(td))
            self.selector(td)
            nxt = self.env.step(td)["next"]
            pending = {"obs": td.get(OBS), "action": td.get(ACTION), "mask": td.get(MASK),
                       "reward": nxt.get(REWARD).squeeze(-1), "next_obs": nxt.get(OBS),
                       "terminated": nxt.get(("agents", "terminated")).squeeze(-1)}
            if not self.greedy_next or t == p.episode_steps - 1:
                self._push(pending, nxt.get(MASK))  # terminal: the mask is not used
                pending = None
            served += nxt.get((DIAG, "served_fraction"))
            self.env_steps += 1
            for loss, q in self.optimise(e):
                loss_sum += loss
                q_sum += q
                n_updates += 1
            td = nxt.exclude(REWARD)
        last = nxt.get(DIAG)
        loss = (loss_sum / n_updates).item() if n_updates else float("nan")
        q_mean = (q_sum / n_updates).item() if n_updates else float("nan")
        records = []
        for i in range(e):
            self.episode += 1
            records.append({
                "kind": "train", "episode": self.episode, "env_steps": self.env_steps,
                "return": last["ep_return"][i].item(),
                "collisions": last["ep_collisions"][i].item(),
                "proximity": last["ep_proximity"][i].item(),
                "fallbacks": last["ep_fallbacks"][i].item(),
                "served_fraction": (served[i] / p.episode_steps).item(),
                "pg": last["pg"][i].item(), "epsilon": eps, "loss": loss, "q_chosen": q_mean,
                "updates": self.learner.updates})
        return records

    # ------------------------------------------------------------------ optimise
    def optimise(self, new_env_steps: int):
        """T_u = ``algo.update_every``: one update per T_u env steps of each env, so the
        paper's one update per step with n_envs = 1, and n_envs updates per collector
        step otherwise. Yields (loss, mean chosen Q) per update."""
        self.update_credit += new_env_steps / self.cfg.algo.update_every
        while self.update_credit >= 1.0:
            self.update_credit -= 1.0
            if len(self.buffer) >= self.cfg.algo.learning_starts:
                yield self.learner.update(self.buffer.sample(self.cfg.algo.batch_size))

    # ------------------------------------------------------------------ evaluate
    @torch.no_grad()
    def evaluate(self, policy=None) -> tuple[dict[str, Any], Any]:
        """The greedy learned policy (or ``policy``) on the fixed held-out windows,
        seeded: comparable across calls. Returns the record and the rollout."""
        env, steps = self.eval_env, self.params.episode_steps
        env.set_seed(self.cfg.train.eval_seed)
        td = env.rollout(steps, policy or self.greedy_policy, break_when_any_done=False)
        last = td["next", DIAG][:, -1]
        ret = last["ep_return"]
        record = {
            "kind": "eval", "episode": self.episode, "env_steps": self.env_steps,
            "return": ret.mean().item(),
            "return_std": ret.std().item() if ret.numel() > 1 else 0.0,
            "returns": ret.tolist(),
            "collisions": last["ep_collisions"].sum().item(),
            "episodes_with_collision": int((last["ep_collisions"] > 0).sum().item()),
            "proximity": last["ep_proximity"].sum().item(),
            "fallbacks": last["ep_fallbacks"].sum().item(),
            "served_fraction": td["next", DIAG, "served_fraction"].mean().item(),
            "pg": last["pg"].mean().item(),
            "pg_curve": last["pg_curve"].mean(0).tolist(),
            "closest_approach": td["next", DIAG, "closest_approach"].min().item(),
            "coverage": self._coverage(td["next", POSITION]),
            "windows": int(ret.numel())}
        return record, td

    def _coverage(self, pos: torch.Tensor) -> float:
        """Mean share of the area under footprints over the evaluated steps (10 m grid)."""
        p = self.params
        return coverage_fraction(pos, p.r_b, p.n_beams, p.width, p.height, 10.0).mean().item()

    def trajectory_of(self, td, window: int = 0):
        """UABS path [T+1, M, 2], vehicles [T+1, 2, V] and presence of one eval window."""
        base = self.eval_env.base_env
        path = torch.cat([td[POSITION][window, :1], td["next", POSITION][window]])
        sim, start = base._windows[window].tolist()
        sl = slice(start, start + self.params.episode_steps + 1)
        return path, base.veh_pos[sim, sl], base.veh_present[sim, sl]

    # ------------------------------------------------------------------ checkpoint
    def state_dict(self) -> dict:
        return {
            "format": CKPT_FORMAT, "config": _config_dict(self.cfg),
            "learner": self.learner.state_dict(),
            "counters": {"episode": self.episode, "env_steps": self.env_steps,
                         "update_credit": self.update_credit, "best_eval": self.best_eval},
            "rng": {"torch": torch.get_rng_state(), "selector": self.gen.get_state(),
                    "env": self.env.base_env.rng.get_state()},
            "replay": self.buffer.state_dict() if self.cfg.train.checkpoint_buffer else None,
        }

    def load_state_dict(self, state: dict, source: Path, resuming: bool = True) -> None:
        diffs = config_differences(state["config"], _config_dict(self.cfg))
        if diffs:
            raise CheckpointError(f"{source} was written with other settings:\n  "
                                  + "\n  ".join(diffs)
                                  + "\nRun with the checkpoint's settings to continue it.")
        self.learner.load_state_dict(state["learner"])
        c = state["counters"]
        self.episode, self.env_steps = int(c["episode"]), int(c["env_steps"])
        self.update_credit, self.best_eval = float(c["update_credit"]), float(c["best_eval"])
        torch.set_rng_state(state["rng"]["torch"])
        self.gen.set_state(state["rng"]["selector"])
        self.env.base_env.rng.set_state(state["rng"]["env"])
        if state.get("replay") is not None:
            self.buffer.load_state_dict(state["replay"])
        elif resuming:
            log.warning("the checkpoint holds no replay buffer (train.checkpoint_buffer="
                        "false): learning restarts after algo.learning_starts transitions")

    def save(self, name: str) -> Path:
        path = self.run_dir / "checkpoints" / f"{name}.pt"
        save_checkpoint(self.state_dict(), path)
        return path

    # ------------------------------------------------------------------ loop
    def _log(self, record: dict[str, Any]) -> None:
        with open(self.metrics_path, "a") as f:
            f.write(json.dumps(record) + "\n")
        if self.writer is None:
            return
        prefix = record["kind"]
        for k, v in record.items():
            if isinstance(v, int | float) and k not in ("episode", "kind"):
                self.writer.add_scalar(f"{prefix}/{k}", v, record["episode"])

    def _log_eval_figures(self, record: dict[str, Any], td) -> None:
        import matplotlib.pyplot as plt

        from uabs_rl.plots import pg_curve_figure, scenario_lanes, trajectory_figure

        figs = {"pg_curve": pg_curve_figure(
            {self.cfg.masking.mode: record["pg_curve"]},
            title=f"P_g after {record['episode']} episodes")}
        if self.cfg.train.trajectory_images:
            figs["trajectories"] = trajectory_figure(
                self.cfg.scenario.area, *self.trajectory_of(td), self.params.r_b,
                self.params.n_beams, scenario_lanes(self.cfg.scenario),
                title=f"{self.cfg.masking.mode}, episode {record['episode']}, held-out window "
                      f"0: R = {record['returns'][0]:.0f}")
        out = self.run_dir / "eval"
        out.mkdir(exist_ok=True)
        for name, fig in figs.items():
            fig.savefig(out / f"last_{name}.png")
            if record["return"] >= self.best_eval:
                fig.savefig(out / f"best_{name}.png")
            if self.writer is not None:
                self.writer.add_figure(f"eval/{name}", fig, record["episode"])
            plt.close(fig)

    def fit(self) -> dict[str, Any]:
        """Train to ``train.episodes``, evaluating every ``train.eval_every`` episodes.
        Ctrl-C saves ``last`` before exiting."""
        tr = self.cfg.train
        self.run_dir.mkdir(parents=True, exist_ok=True)
        if tr.tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(str(self.run_dir / "tb"))
        bar = tqdm(total=tr.episodes, initial=self.episode, unit="ep", disable=not tr.progress,
                   dynamic_ncols=True)
        collisions, last_eval, t0 = 0.0, float("nan"), time.perf_counter()
        try:
            while self.episode < tr.episodes:
                for rec in self.collect_round():
                    self._log(rec)
                    collisions += rec["collisions"]
                    bar.update()
                    bar.set_postfix(R=f"{rec['return']:.0f}", eps=f"{rec['epsilon']:.2f}",
                                    coll=int(collisions), eval_R=f"{last_eval:.0f}")
                if self.episode % tr.eval_every == 0 or self.episode >= tr.episodes:
                    last_eval = self._evaluate_and_checkpoint()
        except KeyboardInterrupt:
            path = self.save("last")
            bar.close()
            print(f"\ninterrupted at episode {self.episode}: saved {path}; continue with "
                  f"resume={self.run_dir}", file=sys.stderr)
            raise
        finally:
            bar.close()
            if self.writer is not None:
                self.writer.close()
        self.save("last")
        summary = {"episodes": self.episode, "updates": self.learner.updates,
                   "best_eval_return": self.best_eval, "last_eval_return": last_eval,
                   "minutes": (time.perf_counter() - t0) / 60}
        log.info("done: %s", summary)
        return summary

    def _evaluate_and_checkpoint(self) -> float:
        record, td = self.evaluate()
        self._log(record)
        if self.writer is not None or self.cfg.train.trajectory_images:
            self._log_eval_figures(record, td)
        if record["return"] >= self.best_eval:
            self.best_eval = record["return"]
            self.save("best")
        self.save("last")
        return record["return"]


def _config_dict(cfg: Any) -> dict:
    d = asdict(cfg)
    d.pop("resume", None)
    return d


# ----------------------------------------------------------------------------- entry point
def run(cfg: Any, run_dir: Path) -> dict[str, Any]:
    """Train (or resume) one run; the Hydra entry point's body."""
    if cfg.resume:
        run_dir = Path(cfg.resume)
        trainer = Trainer(cfg, run_dir)
        source = run_dir / "checkpoints" / "last.pt"
        trainer.load_state_dict(load_checkpoint(source), source)
        log.info("resuming %s at episode %d", run_dir, trainer.episode)
    else:
        if (Path(run_dir) / "metrics.jsonl").exists():
            raise ConfigError(f"{run_dir} already holds a run (metrics.jsonl): continue it "
                              f"with resume={run_dir}, or choose another hydra.run.dir.")
        trainer = Trainer(cfg, run_dir)
    return trainer.fit()


def _app(dcfg) -> None:
    from hydra.core.hydra_config import HydraConfig

    try:
        cfg = to_container(dcfg)
        run(cfg, Path(HydraConfig.get().runtime.output_dir))
    except (ConfigError, CheckpointError) as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)


def main() -> None:
    """Entry point of ``uabs-train``."""
    import hydra

    from uabs_rl.config import register_configs

    register_configs()
    hydra.main(version_base="1.3", config_path=str(Path(__file__).parents[1] / "conf"),
               config_name="config")(_app)()


if __name__ == "__main__":
    main()
