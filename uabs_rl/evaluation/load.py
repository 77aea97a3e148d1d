"""Loading a trained run for evaluation: its checkpoint (a run folder's ``best.pt`` or
``last.pt``, or a file), checked to be the run's own and finite, under the run's own
config or that config with the world changed (``scenario``, ``channel``, ``masking``,
``traces``: :func:`with_overrides`); the held-out env's evaluator and the greedy learned
policy; every policy's records on the same windows, and the paired differences and the
share of the greedy-to-planner gap that ``uabs-eval`` prints.

Evaluation needs only the held-out env, the Q-network and the masking rule
(:mod:`uabs_rl.evaluation.evaluator`): no training traces, replay buffer or optimiser are
built."""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException
from tensordict.nn import TensorDictModuleBase, TensorDictSequential

from uabs_rl.algorithms import Dims, algorithm_class
from uabs_rl.config import (
    CONF_DIR,
    ConfigError,
    MaskingMode,
    Role,
    RunConfig,
    check_config_dirs,
    check_group_choices,
    check_moved_overrides,
    global_package,
    keys_with_role,
    option_bases,
    option_file,
    override_key,
    sections_with_role,
    to_container,
)
from uabs_rl.env.channel import CHANNELS
from uabs_rl.env.params import EnvParams, validate_world
from uabs_rl.env.uabs_env import N_ACTIONS
from uabs_rl.evaluation.baselines import BASELINES, MPC, PLANNER, baseline_policy
from uabs_rl.evaluation.evaluator import Evaluator, greedy_policy, make_eval_env
from uabs_rl.evaluation.hybrid import HYBRID, HybridScore
from uabs_rl.evaluation.leaf import LEAF, LeafValue
from uabs_rl.evaluation.planner import gap_share, junction_sites
from uabs_rl.evaluation.predict import make_predictor
from uabs_rl.evaluation.stats import paired_difference
from uabs_rl.paths import safe_component
from uabs_rl.runs.checkpoint import (
    CheckpointError,
    check_finite,
    check_own,
    config_from_checkpoint,
    load_checkpoint,
    load_into,
)
from uabs_rl.runs.layout import CHECKPOINTS, RunFolder, run_of_checkpoint
from uabs_rl.safety.make import make_selector, resolve_device

POLICIES = ("learned", *BASELINES)  # --policy all


@dataclass
class Evaluation:
    """What evaluating a checkpoint needs: its config, the held-out env's evaluator, the
    greedy learned policy and the counters the checkpoint was written at."""

    cfg: RunConfig
    evaluator: Evaluator
    greedy: TensorDictModuleBase
    episode: int
    env_steps: int


# what uabs-eval may change: the world the policy is put in, not the policy (the
# sections that hold its settings, uabs_rl.config.roles)
EVAL_GROUPS = sections_with_role(Role.world)
# the settings uabs-eval may change that can change the network's input size
# (EnvParams.obs_dim; the obs group itself belongs to the trained policy)
OBS_KEYS = ("scenario.n_uabs", "channel.n_beams")


def _group_file(group: str, option: str, config_dirs: list[Path]) -> Path:
    check_config_dirs([Path(d) for d in config_dirs], [(group, option)])
    found = option_file([*config_dirs, CONF_DIR], group, option)
    if found is not None:
        return found
    looked = ", ".join(str(Path(d) / group) for d in (*config_dirs, CONF_DIR))
    options = sorted({f.stem for d in (*config_dirs, CONF_DIR)
                      for f in (Path(d) / group).glob("*.yaml")})
    raise ConfigError(f"{group}={option}: no {option}.yaml in {looked}. Choose from "
                      f"{', '.join(options)}, or give the folder that holds "
                      f"{group}/{option}.yaml with --config-dir.")


def _load_yaml(path: Path, override: str) -> Any:
    """A config file as OmegaConf reads it (YAML tags such as ``!!python/object`` are
    refused, never run); unreadable or not YAML is a :class:`ConfigError` naming it."""
    try:
        return OmegaConf.load(path)
    except Exception as e:  # yaml's scanner, parser and constructor errors, OSError
        first = (str(e).strip().splitlines() or [type(e).__name__])[0][:160]
        raise ConfigError(f"{override}: {path} is not a readable config file ({first}). "
                          f"Fix the file or choose another.") from None


def with_overrides(cfg: RunConfig, overrides: list[str],
                   config_dirs: list[Path] | None = None) -> RunConfig:
    """``cfg`` (a run's own config) with command-line style ``overrides`` of the
    ``EVAL_GROUPS`` sections: ``group=option`` replaces the section by that config file
    (the schema's defaults plus the file, as ``uabs-train`` composes it), ``key=value``
    sets one value. Anything else is refused, naming the key."""
    check_moved_overrides(overrides)
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
        safe_component(value, key)  # a config file's name in the group's folder
        body, others = _option_sections(key, value, list(config_dirs or []), o)
        try:
            conf[key] = OmegaConf.merge(OmegaConf.structured(section_types[key]), *body)
            for k, v in others:
                conf[k] = OmegaConf.merge(conf[k], v)
        except OmegaConfBaseException as e:
            raise ConfigError(f"{key}={value}: {str(e).splitlines()[0]}") from None
    try:
        conf = OmegaConf.merge(conf, OmegaConf.from_dotlist(dotted))
    except OmegaConfBaseException as e:
        raise ConfigError(f"override: {str(e).splitlines()[0]} (check the key's spelling "
                          f"and type in uabs_rl/config/schema.py)") from None
    # an option file that does not name itself would evaluate under another's name
    check_group_choices({o.partition("=")[0].lstrip("+"): o.partition("=")[2]
                         for o in overrides if "." not in o.partition("=")[0]
                         and o.partition("=")[0].lstrip("+") in EVAL_GROUPS},
                        conf, [*(config_dirs or []), CONF_DIR], overrides,
                        {"channel": set(CHANNELS), "masking": {m.value for m in MaskingMode}})
    new = to_container(conf)
    validate_world(new)
    return new


def _option_sections(group: str, option: str, config_dirs: list[Path], override: str,
                     seen: frozenset = frozenset()) -> tuple[list[Any], list[tuple[str, Any]]]:
    """What the file of ``group=option`` sets, as ``uabs-train`` composes it: the
    group's section (after those of the options of its group it builds on, its
    ``defaults``; a schema there is where the section starts anyway) and, for a file of
    ``# @package _global_`` (``scenario=city`` sizes the traces too), the other sections
    of ``EVAL_GROUPS`` it sets, in merge order (its train settings belong to the trained
    policy)."""
    path = _group_file(group, option, config_dirs)
    body = _load_yaml(path, override)
    if option in seen:
        raise ConfigError(f"{override}: {path} builds on itself through its defaults: "
                          f"fix the file.")
    sections: list[Any] = []
    others: list[tuple[str, Any]] = []
    for base in option_bases(OmegaConf.to_container(body), group):
        more, also = _option_sections(group, base, config_dirs, override, seen | {option})
        sections += more
        others += also
    if "defaults" in body:
        body.pop("defaults")
    if global_package(path.read_text()):
        others += [(k, v) for k, v in body.items() if k in EVAL_GROUPS and k != group]
        body = body.get(group, {})
    return sections + [body], others


def _obs_values(cfg: RunConfig) -> dict[str, Any]:
    return {k: OmegaConf.select(OmegaConf.structured(cfg), k) for k in OBS_KEYS}


def check_network_fits(trained: RunConfig, cfg: RunConfig) -> None:
    """Refuse settings under which the trained network's input size would change."""
    a = EnvParams.from_config(trained.scenario, trained.channel, trained.obs).obs_dim
    b = EnvParams.from_config(cfg.scenario, cfg.channel, cfg.obs).obs_dim
    if a != b:
        before, now = _obs_values(trained), _obs_values(cfg)
        changed = ", ".join(f"{k}={now[k]}" for k in OBS_KEYS if before[k] != now[k])
        trained_as = ", ".join(f"{k}={before[k]}" for k in OBS_KEYS)
        fleet = ("" if trained.obs.frame == "egocentric" else
                 " A policy trained with obs=egocentric (whose size depends on neither "
                 "the fleet size nor the area) flies any scenario.n_uabs.")
        raise ConfigError(
            f"the network was trained on observations of size {a} ({trained_as}, "
            f"obs={trained.obs.name}); with {changed} they would have size {b}. These "
            f"settings cannot change at evaluation: keep them as trained (or train a run "
            f"with them).{fleet}")


def find_checkpoint(path: Path, which: str = "best") -> Path:
    """The checkpoint ``uabs-eval PATH --checkpoint which`` means: ``path`` itself, or
    ``<run>/checkpoints/<which>.pt`` of a run folder. A folder that holds none says
    what was looked for, and what to pass instead."""
    if path.is_file():
        return path
    if not path.exists():
        raise CheckpointError(f"no checkpoint at {path}: no such file or folder. Pass a run "
                              f"folder (it holds checkpoints/best.pt and last.pt) or a .pt "
                              f"file written by uabs-train.")
    folder = RunFolder(path)
    ckpt = folder.checkpoint(which)
    if ckpt.is_file():
        return ckpt
    held = sorted(p.name for p in folder.checkpoints.glob("*.pt"))
    members = sorted({p.parent.parent.name for p in folder.member_checkpoints("*")},
                     key=lambda name: (len(name), name))
    if not held and members:
        raise CheckpointError(f"{path} is a population: evaluate one member, e.g. uabs-eval "
                              f"{path / members[0]}, or report all with uabs-report {path}.")
    if held:
        other = "last" if which == "best" else "best"
        hint = (f"evaluate it with --checkpoint {other}" if f"{other}.pt" in held else
                f"pass one of them as the path, e.g. uabs-eval {folder.checkpoints / held[0]}")
        raise CheckpointError(f"no checkpoint at {ckpt}: {folder.checkpoints} holds only "
                              f"{', '.join(held)}; {hint}.")
    if path.name == CHECKPOINTS and (path / f"{which}.pt").is_file():
        raise CheckpointError(f"{path} is a run's checkpoints folder: pass the run folder, "
                              f"uabs-eval {path.parent}, or the file {path / f'{which}.pt'}.")
    if folder.checkpoints.is_dir() or folder.metrics.is_file():
        raise CheckpointError(f"no checkpoint at {ckpt}: the run in {path} stopped before its "
                              f"first evaluation (train.eval_every) wrote one; continue it "
                              f"with uabs-train resume={path}.")
    raise CheckpointError(f"no checkpoint at {ckpt}: {path} is not a uabs-train run folder "
                          f"(it has no checkpoints/); pass a run folder or a .pt file written "
                          f"by uabs-train.")


def check_belongs(state: dict, ckpt: Path) -> None:
    """A checkpoint in a run's ``checkpoints/`` must be that run's own: its run id that
    of the folder's ``run.json``, its result-changing settings those of the folder's
    ``.hydra/config.yaml`` (as ``resume`` checks); one copied in from another run is
    refused, naming the file and the fix, instead of being evaluated as this run's."""
    run = run_of_checkpoint(ckpt)
    if run is not None:
        check_own(state, run, ckpt)


def load_evaluation(path: Path, which: str = "best", windows: int | None = None,
                    split: str = "test", overrides: list[str] | None = None,
                    config_dirs: list[Path] | None = None,
                    windows_name: str = "windows", cache_dir: Path | None = None
                    ) -> Evaluation:
    """The learned policy of a run directory or checkpoint on the fixed windows of
    ``split`` ("test" or "eval", the validation traces), under the run's own config
    or that config with ``overrides`` (:func:`with_overrides`); the traces read from
    (or built into) ``cache_dir`` where given, else the run's ``traces.cache_dir``. A
    network with NaN or infinite weights is refused."""
    ckpt = find_checkpoint(path, which)
    state = load_checkpoint(ckpt)
    check_belongs(state, ckpt)
    check_finite(state["learner"]["qnet"], ckpt, "learner.qnet")
    cfg = config_from_checkpoint(state, ckpt)
    device = "cpu"  # where the run trained does not matter here, unless device= is given
    if overrides:
        trained, cfg = cfg, with_overrides(cfg, overrides, config_dirs)
        check_network_fits(trained, cfg)
        if trained.device != cfg.device:
            device = resolve_device(cfg.device)
    else:
        validate_world(cfg)
    if cache_dir is not None:  # where the traces are kept changes no result
        cfg = replace(cfg, traces=replace(cfg.traces, cache_dir=str(cache_dir)))
    env = make_eval_env(cfg, windows=windows, split=split, device=device,
                        windows_name=windows_name)
    p = env.base_env.params
    algorithm = algorithm_class(cfg.algo.name)
    qnet = algorithm.acting_network(cfg.algo, Dims(p.obs_dim, N_ACTIONS, p.n_uabs))
    key = algorithm.acting_key
    load_into(qnet, state["learner"][key], ckpt, f"learner.{key}")
    qnet.to(env.base_env.device)
    c = state["counters"]
    return Evaluation(cfg, Evaluator(env, cfg.train.eval_seed), greedy_policy(qnet, env, cfg),
                      int(c["episode"]), int(c["env_steps"]))


def default_out_dir(path: Path, overrides: list[str] | None = None) -> Path:
    """``<run>/evaluation``, or ``<run>/evaluation/<overrides>`` under overrides that
    may change results (``traces.cache_dir`` and ``traces.workers`` name no folder, as in
    a run folder's name; ``device`` does: another device's random generator draws other
    start positions and LoS states); beside a checkpoint file that is not in a run's
    ``checkpoints/``."""
    if path.is_dir():
        run = path
    else:
        run = run_of_checkpoint(path) or path.parent
    out = RunFolder(run).evaluation
    runtime = set(keys_with_role(Role.runtime)) - {"device"}
    named = [o for o in overrides or () if override_key(o) not in runtime]
    return out / ",".join(o.replace("/", "_") for o in named) if named else out


def evaluate_policies(ev: Evaluation, policies: tuple[str, ...], seed: int = 0,
                      horizon: int = 1, mpc_horizon: int = 5, predictor: str = "cv",
                      sees: str | float = "all", hybrid_weight: float = 1.0,
                      cut: bool = True, beam: int | None = None, rounds: int | None = None
                      ) -> dict[str, tuple[dict[str, Any], Any]]:
    """Records and rollouts of each policy on the same held-out windows and masks
    (``horizon``: the planner's; ``mpc_horizon``, ``predictor`` and ``sees``: the mpc's
    and the hybrids'; ``hybrid_weight``: the hybrids' λ, :mod:`uabs_rl.evaluation.hybrid`
    and :mod:`uabs_rl.evaluation.leaf`); ``cut=False``: the mpc's and the hybrids' searches
    over every vehicle instead of those each UABS can reach (``PlannerScore.cut``: the
    same moves at a higher cost; the planner's own search always cuts); ``beam``: the
    paths the mpc's and the hybrids' beam search keeps per first move (default
    ``planner.BEAM``); ``rounds``: their passes over the fleet (default
    ``planner.ROUNDS``: a second pass replans each UABS given every other's plan).
    The planner's, the mpc's and the hybrids' records hold their ``horizon`` and
    ``seconds``, the wall time of the rollout of all the windows side by side (the mpc's
    and the hybrids' also their ``predictor`` and ``sees``, the hybrids' their ``weight``);
    every record holds ``ms_per_decision``, that time per step of one window (the whole
    fleet's decision, amortised over the windows)."""
    results = {}
    env = ev.evaluator.env
    made = {}  # the mpc's and the hybrid's predictor, made once (road reads the network)

    def mpc_policy() -> TensorDictSequential:
        if not made:
            made["predictor"] = make_predictor(predictor, sees, ev.cfg.scenario,
                                               env.base_env.device, ev.cfg.traces)
        policy = baseline_policy(MPC, env, make_selector(env), seed, horizon=mpc_horizon,
                                 predictor=made["predictor"], beam=beam, rounds=rounds)
        policy[0].cut = cut
        return policy

    for name in policies:
        if name == "learned":
            policy = ev.greedy
        elif name == MPC:
            policy = mpc_policy()
        elif name == HYBRID:  # the mpc's scores (same seeded tie-break) + λ Q, its selector
            score, selector = mpc_policy()
            policy = TensorDictSequential(
                HybridScore(score, ev.greedy[0].module, hybrid_weight), selector)
        elif name == LEAF:  # the mpc whose paths end in λ V (uabs_rl.evaluation.leaf)
            policy = mpc_policy()
            leaf = LeafValue(env.base_env, ev.greedy[0].module, hybrid_weight)  # checked
            if hybrid_weight:  # λ = 0: the mpc itself
                policy[0].leaf = leaf
        else:
            sites = junction_sites(ev.cfg, env.base_env) if name == "junctions" else None
            policy = baseline_policy(name, env, make_selector(env), seed, horizon=horizon,
                                     sites=sites)
        t0 = time.perf_counter()
        results[name] = ev.evaluator.evaluate(policy, ev.episode, ev.env_steps)
        sec = time.perf_counter() - t0
        rec = results[name][0]
        rec["policy"] = name
        rec["ms_per_decision"] = 1000 * sec / (rec["windows"] * ev.evaluator.params.episode_steps)
        if name == PLANNER:
            rec.update(horizon=horizon, seconds=sec)
        elif name in (MPC, HYBRID, LEAF):
            search = getattr(policy[0], "planner", policy[0])  # the hybrid's, or itself
            rec.update(horizon=mpc_horizon, seconds=sec, predictor=predictor, sees=sees,
                       beam=search.beam, rounds=search.rounds)
            if name in (HYBRID, LEAF):
                rec["weight"] = hybrid_weight
    return results


def gap_shares(results: dict[str, tuple[dict, Any]]) -> dict[str, dict]:
    """The learned policy's share of the greedy-to-planner gap per metric (served
    fraction, P_g), per window paired, with percentile bootstrap CIs over the windows
    (a ratio; :func:`uabs_rl.evaluation.planner.gap_share`); {} unless all three ran."""
    if not {"learned", "greedy", PLANNER} <= set(results):
        return {}
    recs = {k: results[k][0] for k in ("learned", "greedy", PLANNER)}
    return {m: gap_share(*(r[METRICS[m]] for r in recs.values()))
            for m in ("served_fraction", "pg")}


METRICS = {"return": "returns", "served_fraction": "served_fractions", "pg": "pgs"}


def differences(results: dict[str, tuple[dict, Any]]) -> dict[str, dict[str, dict]]:
    """Paired differences learned − baseline per window, with Student-t 95 % CIs over
    the windows of this one run (the windows are the unit: one seed), for R, the served
    fraction and P_g at N̂_s: ``{baseline: {metric: {diff, ci_low, ci_high, n,
    method}}}``."""
    if "learned" not in results:
        return {}
    learned = results["learned"][0]
    return {name: {m: paired_difference(learned[k], rec[k]) for m, k in METRICS.items()}
            for name, (rec, _) in results.items() if name != "learned"}


def peak_memory() -> str:
    """", peak memory N MiB" (this process's largest resident set so far), or "" where
    the platform does not say (no ``resource`` module: Windows)."""
    try:
        import resource
    except ImportError:
        return ""
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
    mib = kib / 1024 / (1024 if sys.platform == "darwin" else 1)
    return f", peak memory {mib:.0f} MiB"
