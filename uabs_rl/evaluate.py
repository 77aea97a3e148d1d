"""``uabs-eval``: evaluate a trained run (and the baselines) on the held-out traces.

    uabs-eval outputs/runs/<run dir>                 # best checkpoint, test traces
    uabs-eval outputs/runs/<run dir> --policy all    # + random, greedy, oracle baselines
    uabs-eval path/to/last.pt --split eval --windows 20 --gif
    uabs-eval outputs/runs/<run dir> scenario.sumo.fleet_size=120 channel.los_mode=los
    uabs-eval outputs/runs/<run dir> --config-dir myconf scenario=grid6   # another city

Evaluates on the test traces by default (``traces.test``: SUMO seeds that neither
training nor checkpoint selection ever read; every window of them), ``--split eval`` on
the validation traces that training evaluated on. Prints a table and writes
``eval.json``: the split, per policy R, collisions, proximity events, fallbacks, served
fraction, P_g at N̂_s, the whole P_g(N̂_s) curve and the per-window values, and with
baselines the paired differences learned − baseline (same windows, same masks) with
bootstrap 95 % confidence intervals. Also a trajectory picture per policy and, with
``--gif``, an animation of one episode of the learned policy, into
``<run dir>/evaluation/`` (or ``--out``).

Overrides after the path evaluate the checkpoint under other settings: the run's own
config with ``scenario``, ``channel``, ``masking`` and ``traces`` changed as on the
``uabs-train`` command line (``group=option`` takes a config file of that group, from
``conf/`` or a folder given with ``--config-dir``; ``group.key=value`` sets one value).
The network fixes the observation size, so ``scenario.n_uabs``, ``channel.n_beams``
and ``scenario.lookahead_obs`` must stay as trained; ``algo`` and ``train`` define the
network and its training and cannot change. Results then go to
``<run dir>/evaluation/<overrides>/``.

Evaluation needs only the held-out env, the Q-network and the masking rule
(:mod:`uabs_rl.evaluation`): no training traces, replay buffer or optimiser are built.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException
from tensordict.nn import TensorDictModuleBase

from uabs_rl.baselines import BASELINES, baseline_policy
from uabs_rl.checkpoint import (
    CheckpointError,
    checkpoint_path,
    config_from_checkpoint,
    load_checkpoint,
)
from uabs_rl.config import (
    CONF_DIR,
    ConfigError,
    RunConfig,
    to_container,
    validate_masking,
    validate_scenario_traces,
)
from uabs_rl.env import N_ACTIONS
from uabs_rl.evaluation import Evaluator, greedy_policy, make_eval_env
from uabs_rl.make import make_selector, resolve_device
from uabs_rl.model import DuelingQNet
from uabs_rl.params import EnvParams
from uabs_rl.stats import paired_difference

POLICIES = ("learned", *BASELINES)


@dataclass
class Evaluation:
    """What evaluating a checkpoint needs: its config, the held-out env's evaluator, the
    greedy learned policy and the counters the checkpoint was written at."""

    cfg: RunConfig
    evaluator: Evaluator
    greedy: TensorDictModuleBase
    episode: int
    env_steps: int


# what uabs-eval may change: the world the policy is put in, not the policy
EVAL_GROUPS = ("scenario", "channel", "masking", "traces")
# the settings that fix the network's input size (EnvParams.obs_dim)
OBS_KEYS = ("scenario.n_uabs", "channel.n_beams", "scenario.lookahead_obs",
            "scenario.motion_obs")


def _group_file(group: str, option: str, config_dirs: list[Path]) -> Path:
    for d in (*config_dirs, CONF_DIR):
        f = Path(d) / group / f"{option}.yaml"
        if f.is_file():
            return f
    looked = ", ".join(str(Path(d) / group) for d in (*config_dirs, CONF_DIR))
    raise ConfigError(f"{group}={option}: no {option}.yaml in {looked}. Give the folder "
                      f"that holds {group}/{option}.yaml with --config-dir.")


def with_overrides(cfg: RunConfig, overrides: list[str],
                   config_dirs: list[Path] | None = None) -> RunConfig:
    """``cfg`` (a run's own config) with command-line style ``overrides`` of the
    ``EVAL_GROUPS`` sections: ``group=option`` replaces the section by that config file
    (the schema's defaults plus the file, as ``uabs-train`` composes it), ``key=value``
    sets one value. Anything else is refused, naming the key."""
    conf = OmegaConf.structured(cfg)
    section_types = {f.name: type(getattr(cfg, f.name)) for f in fields(cfg)}
    dotted = []
    for o in overrides:
        key, sep, value = o.partition("=")
        key = key.lstrip("+")
        top = key.split(".", 1)[0]
        if not sep or not value and "." not in key:
            raise ConfigError(f"override {o!r}: expected group=option or key=value.")
        if top == "experiment":
            raise ConfigError(f"override {o!r}: presets change how a policy is trained; "
                              f"set the scenario, channel, masking or traces values "
                              f"instead.")
        if top not in EVAL_GROUPS and key != "device":
            raise ConfigError(
                f"override {o!r}: uabs-eval changes only {', '.join(EVAL_GROUPS)} (and "
                f"device); {top} belongs to the trained policy. Train a new run to change it.")
        if "." in key or key == "device":
            dotted.append(f"{key}={value}")
            continue
        body = OmegaConf.load(_group_file(key, value, list(config_dirs or [])))
        if "defaults" in body:  # a schema reference: the section starts from it anyway
            body.pop("defaults")
        try:
            conf[key] = OmegaConf.merge(OmegaConf.structured(section_types[key]), body)
        except OmegaConfBaseException as e:
            raise ConfigError(f"{key}={value}: {str(e).splitlines()[0]}") from None
    try:
        conf = OmegaConf.merge(conf, OmegaConf.from_dotlist(dotted))
    except OmegaConfBaseException as e:
        raise ConfigError(f"override: {str(e).splitlines()[0]} (check the key's spelling "
                          f"and type in uabs_rl/config.py)") from None
    new = to_container(conf)
    validate_scenario_traces(new.scenario, new.traces)
    validate_masking(new.masking)
    return new


def _obs_values(cfg: RunConfig) -> dict[str, Any]:
    return {k: OmegaConf.select(OmegaConf.structured(cfg), k) for k in OBS_KEYS}


def check_network_fits(trained: RunConfig, cfg: RunConfig) -> None:
    """Refuse settings under which the trained network's input size would change."""
    a = EnvParams.from_config(trained.scenario, trained.channel).obs_dim
    b = EnvParams.from_config(cfg.scenario, cfg.channel).obs_dim
    if a != b:
        before, now = _obs_values(trained), _obs_values(cfg)
        changed = ", ".join(f"{k}={now[k]}" for k in OBS_KEYS if before[k] != now[k])
        trained_as = ", ".join(f"{k}={before[k]}" for k in OBS_KEYS)
        raise ConfigError(
            f"the network was trained on observations of size {a} ({trained_as}); with "
            f"{changed} they would have size {b}. These settings cannot change at "
            f"evaluation: keep them as trained (or train a run with them).")


def load_evaluation(path: Path, which: str = "best", windows: int | None = None,
                    split: str = "test", overrides: list[str] | None = None,
                    config_dirs: list[Path] | None = None) -> Evaluation:
    """The learned policy of a run directory or checkpoint on the fixed windows of
    ``split`` ("test" or "eval", the validation traces), under the run's own config
    or that config with ``overrides`` (:func:`with_overrides`)."""
    state = load_checkpoint(checkpoint_path(path, which))
    cfg = config_from_checkpoint(state)
    device = "cpu"  # where the run trained does not matter here, unless device= is given
    if overrides:
        trained, cfg = cfg, with_overrides(cfg, overrides, config_dirs)
        check_network_fits(trained, cfg)
        if trained.device != cfg.device:
            device = resolve_device(cfg.device)
    # a few rollouts: compiling would cost more than it saves
    env = make_eval_env(cfg, windows=windows, compile=False, split=split, device=device)
    p = env.base_env.params
    qnet = DuelingQNet(p.obs_dim, N_ACTIONS, list(cfg.algo.hidden))
    qnet.load_state_dict(state["learner"]["qnet"])
    qnet.to(env.base_env.device)
    c = state["counters"]
    return Evaluation(cfg, Evaluator(env, cfg.train.eval_seed), greedy_policy(qnet, env, cfg),
                      int(c["episode"]), int(c["env_steps"]))


def default_out_dir(path: Path, overrides: list[str] | None = None) -> Path:
    """``<run>/evaluation``, or ``<run>/evaluation/<overrides>`` under overrides."""
    out = (path if path.is_dir() else path.parent.parent) / "evaluation"
    return out / ",".join(o.replace("/", "_") for o in overrides) if overrides else out


def evaluate_policies(ev: Evaluation, policies: tuple[str, ...],
                      seed: int = 0) -> dict[str, tuple[dict[str, Any], Any]]:
    """Records and rollouts of each policy on the same held-out windows and masks."""
    results = {}
    env = ev.evaluator.env
    for name in policies:
        if name == "learned":
            policy = ev.greedy
        else:
            policy = baseline_policy(name, env, make_selector(env, ev.cfg.masking), seed)
        results[name] = ev.evaluator.evaluate(policy, ev.episode, ev.env_steps)
        results[name][0]["policy"] = name
    return results


METRICS = {"return": "returns", "served_fraction": "served_fractions", "pg": "pgs"}


def differences(results: dict[str, tuple[dict, Any]]) -> dict[str, dict[str, dict]]:
    """Paired differences learned − baseline per window, with bootstrap 95 % CIs, for
    R, the served fraction and P_g at N̂_s: ``{baseline: {metric: {diff, ci_low,
    ci_high, n}}}``."""
    if "learned" not in results:
        return {}
    learned = results["learned"][0]
    return {name: {m: paired_difference(learned[k], rec[k]) for m, k in METRICS.items()}
            for name, (rec, _) in results.items() if name != "learned"}


def _print_differences(diffs: dict[str, dict[str, dict]]) -> None:
    if not diffs:
        return
    print("\nlearned − baseline, per window (mean [95 % bootstrap CI]):")
    for name, per in diffs.items():
        print(f"{name:>8} " + "   ".join(
            f"{m}: {d['diff']:+.4g} [{d['ci_low']:+.4g}, {d['ci_high']:+.4g}]"
            for m, d in per.items()))


def _print_table(results: dict[str, tuple[dict, Any]], nhat: int) -> None:
    cols = ("return", "return_std", "collisions", "proximity", "fallbacks",
            "served_fraction", "pg")
    pg_col = f"P_g(N̂s={nhat})"
    print(f"{'policy':>8} " + " ".join(f"{c:>15}" for c in cols[:-1]) + f" {pg_col:>15}")
    for name, (rec, _) in results.items():
        print(f"{name:>8} " + " ".join(f"{rec[c]:>15.3f}" for c in cols))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description="Evaluate a uabs-train run on held-out traces, under its own settings "
                    "or other scenario/channel/masking/traces values.")
    ap.add_argument("path", type=Path, help="a run directory or a checkpoint (.pt)")
    ap.add_argument("overrides", nargs="*", metavar="override",
                    help="group=option or key=value for scenario, channel, masking, traces "
                         "(and device), as on the uabs-train command line")
    ap.add_argument("--config-dir", type=Path, action="append", default=[],
                    help="a folder of your own configs (scenario/<name>.yaml, ...), searched "
                         "before the package's conf/; may be repeated")
    ap.add_argument("--checkpoint", choices=("best", "last"), default="best",
                    help="which checkpoint of a run directory (default: best)")
    ap.add_argument("--policy", choices=(*POLICIES, "all"), default="learned")
    ap.add_argument("--split", choices=("test", "eval"), default="test",
                    help="test traces (default; never seen by training or selection) or "
                         "eval, the validation traces training evaluated on")
    ap.add_argument("--windows", type=int,
                    help="windows to evaluate (default: every test window, or the run's "
                         "train.eval_windows on eval)")
    ap.add_argument("--gif", action="store_true", help="also write an animation (learned)")
    ap.add_argument("--out", type=Path, help="output folder (default: <run>/evaluation)")
    args = ap.parse_intermixed_args(argv)
    if args.windows is not None and args.windows < 1:
        ap.error(f"--windows must be >= 1, got {args.windows}")
    try:
        ev = load_evaluation(args.path, args.checkpoint, args.windows, args.split,
                             args.overrides, args.config_dir)
    except (CheckpointError, ConfigError) as e:
        msg = str(e)
        if args.windows is not None:  # the env names its own argument: name the flag
            msg = msg.replace(f"n_eval_windows={args.windows}", f"--windows {args.windows}")
        print(f"error: {msg}", file=sys.stderr)
        return 2
    out = args.out or default_out_dir(args.path, args.overrides)
    policies = POLICIES if args.policy == "all" else (args.policy,)
    results = evaluate_policies(ev, policies)
    out.mkdir(parents=True, exist_ok=True)
    n = ev.evaluator.env.base_env.n_envs
    tc = getattr(ev.cfg.traces, args.split)
    print(f"split: {args.split} (traces.{args.split}: SUMO seeds {tc.first_seed}.."
          f"{tc.first_seed + tc.n_sims - 1}), {n} windows of "
          f"{ev.cfg.scenario.episode_steps} steps, {args.checkpoint} checkpoint"
          + (f", scenario {ev.cfg.scenario.name}, overrides: {' '.join(args.overrides)}"
             if args.overrides else ""))
    _print_table(results, ev.evaluator.params.nhat_s)
    diffs = differences(results)
    _print_differences(diffs)
    (out / "eval.json").write_text(json.dumps(
        {"split": args.split, "windows": n, "checkpoint": args.checkpoint,
         "overrides": args.overrides, "scenario": ev.cfg.scenario.name,
         "policies": {k: r for k, (r, _) in results.items()}, "differences": diffs},
        indent=1))
    _write_pictures(ev, results, out, args.gif, args.split)
    print(f"wrote {out / 'eval.json'} and pictures under {out}")
    return 0


def _write_pictures(ev: Evaluation, results: dict, out: Path, gif: bool, split: str) -> None:
    import matplotlib.pyplot as plt
    import torch.nn.functional as F

    from uabs_rl.env import DIAG
    from uabs_rl.plots import animate_episode, save_figure, scenario_lanes, trajectory_figure

    a, p = ev.cfg.scenario.area, ev.evaluator.params
    lanes = scenario_lanes(ev.cfg.scenario)
    for name, (rec, td) in results.items():
        fig = trajectory_figure(a, *ev.evaluator.trajectory_of(td), p.r_b, p.n_beams, lanes,
                                title=f"{name} ({ev.cfg.masking.mode} masking), {split} "
                                      f"window 0: R = {rec['returns'][0]:.0f}")
        save_figure(fig, out / f"trajectories_{name}.png")
        plt.close(fig)
    if gif and "learned" in results:
        td = results["learned"][1]
        after = td["next", DIAG, "ep_return"][0]  # the return after each step
        animate_episode(a, *ev.evaluator.trajectory_of(td), p.r_b, p.n_beams, lanes,
                        out / "episode_learned.gif", returns=F.pad(after, (1, 0)),  # R = 0 at t = 0
                        title=f"learned policy, {ev.cfg.masking.mode} masking, {split} "
                              f"window 0")


def run_main() -> None:
    sys.exit(main())


if __name__ == "__main__":
    run_main()
