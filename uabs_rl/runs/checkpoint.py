"""Checkpoints: atomic save, safe load (``weights_only``), the config they were written
with, and the checks that a loaded checkpoint is whole (:func:`validate_state`) and fits
the config it is resumed or evaluated under.

A checkpoint is one dict: ``format``, ``config`` (plain types: enums as strings),
``learner`` (networks, target, optimiser, update count), ``counters``, ``rng`` and
optionally ``replay`` (``train.checkpoint_buffer``) and ``population`` (a member of
one). Every way a file can fail to be one ends in a :class:`CheckpointError` naming the
file, never in torch's advice to load it unsafely.
"""

from __future__ import annotations

import pickle
import re
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from uabs_rl.config import (
    MOVED,
    ConfigError,
    RunConfig,
    default_settings,
    flatten,
    keys_with_role,
    own_learner_settings,
    structured_run,
    to_container,
)
from uabs_rl.config.roles import RESUME_ROLES
from uabs_rl.env.params import EnvParams
from uabs_rl.paths import atomic_file
from uabs_rl.runs.folder import check_identity
from uabs_rl.runs.layout import RunFolder

# 2: the replay keeps the agent dimension (step slots of M agents); format 1's flat
# ring of per-agent transitions is converted on load (upgrade_state)
CKPT_FORMAT = 2
# the settings a checkpoint must agree with to be resumed or evaluated: those a resumed
# run keeps (their roles: uabs_rl.config.roles), not names (obs.name), runtime settings
# (traces.workers, traces.cache_dir), the test traces or the training protocol
COMPAT_KEYS = frozenset(keys_with_role(*RESUME_ROLES))
# what a checkpoint holds (Experiment.member_state, and its format), entry by entry: a
# nested layout, or the kind of value
TENSORS, BYTES, NUMBER, INT, DICT = ("a dict of tensors", "a uint8 tensor (an RNG state)",
                                     "a number", "an integer", "a dict")
LAYOUT: dict[str, Any] = {
    "config": DICT,
    "learner": {"qnet": TENSORS, "target": TENSORS,
                "optim": {"state": DICT, "param_groups": "a list"}, "updates": INT},
    "counters": {"episode": INT, "env_steps": INT, "update_credit": NUMBER,
                 "best_eval": NUMBER},
    "rng": {"torch": BYTES, "selector": BYTES, "env": BYTES},
}
# the config's sections (each a dict of settings)
CONFIG_SECTIONS = ("scenario", "channel", "masking", "algo", "train", "traces")
ANOTHER = "use another checkpoint of the run (best.pt or last.pt) or one written by uabs-train"


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable or from an incompatible config."""


class Interrupted(Exception):
    """Training stopped on Ctrl-C after saving a consistent ``last`` checkpoint."""


class UnreadableFile(Exception):
    """``torch.load`` refused a file; the text says why in a few words (never torch's
    advice to retry with ``weights_only=False``). ``objects`` names the Python object a
    pickle would have built, when that is why."""

    def __init__(self, reason: str, objects: str | None = None):
        super().__init__(reason)
        self.objects = objects


def save_checkpoint(state: dict, path: Path) -> None:
    """Atomic write: a crash or Ctrl-C mid-write never damages the previous file, and a
    failed write (a full disk) leaves no temporary file. Only ``checkpoints/`` itself is
    made: a run folder removed while the run writes it is not made again."""
    path.parent.mkdir(exist_ok=True)
    with atomic_file(path) as f:
        torch.save(state, f)


def read_weights(path: Path) -> Any:
    """``torch.load(path, weights_only=True)`` on the CPU, torch's warnings silenced;
    any failure is an :class:`UnreadableFile` whose text is safe to show (also for
    the trace cache)."""
    try:
        with warnings.catch_warnings():  # e.g. "Detected pickle protocol 4": noise here
            warnings.simplefilter("ignore")
            return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise _unreadable(e, path) from None


def _unreadable(e: Exception, path: Path) -> UnreadableFile:
    text = str(e)
    if isinstance(e, IsADirectoryError):
        return UnreadableFile("it is a folder")
    if path.is_file() and path.stat().st_size == 0:
        return UnreadableFile("the file is empty")
    if isinstance(e, PermissionError):
        return UnreadableFile("permission denied: it cannot be read here")
    if not _torch_save_start(path) or "Invalid magic number" in text:
        return UnreadableFile("not a file written by torch.save")
    if isinstance(e, pickle.UnpicklingError):
        found = re.search(r"Unsupported global: GLOBAL (\S+)", text)
        if found:
            return UnreadableFile("it holds Python objects", objects=found.group(1))
        return UnreadableFile("its pickled data is not readable")
    if isinstance(e, EOFError):
        return UnreadableFile("the file ends early")
    if isinstance(e, OSError):  # a truncated zip archive, read past its end
        return UnreadableFile(f"a truncated or damaged file: {e.strerror or type(e).__name__}")
    if "central directory" in text:
        return UnreadableFile("a truncated or damaged zip archive")
    if "not in a subdirectory" in text:
        return UnreadableFile("a zip archive that torch.save did not write")
    first = next((line.strip() for line in text.splitlines() if line.strip()), "")
    if not first or "weights_only" in text:
        return UnreadableFile(type(e).__name__)
    return UnreadableFile(f"{type(e).__name__}: {first[:160]}")


def _torch_save_start(path: Path) -> bool:
    """Whether ``path`` starts as torch.save's files do: a zip archive, or (before torch
    1.6) a pickle."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError:
        return True  # unreadable: the error says why
    return head in (b"PK\x03\x04", b"PK\x05\x06") or head[:1] == b"\x80"


def load_checkpoint(path: Path) -> dict:
    """The checkpoint at ``path``, checked whole by :func:`validate_state`."""
    if not path.is_file():
        raise CheckpointError(
            f"no checkpoint at {path}: " + ("it is a folder; " if path.is_dir() else "")
            + "pass a run directory that holds checkpoints/last.pt, or a .pt file written "
              "by uabs-train.")
    try:
        state = read_weights(path)
    except UnreadableFile as e:
        if e.objects:
            raise CheckpointError(
                f"{path} holds Python objects beyond tensors and plain values ({e.objects}), "
                f"so it is not a uabs-train checkpoint; it was refused because loading it "
                f"could run code. Use a checkpoint written by uabs-train.") from None
        raise CheckpointError(f"cannot read checkpoint {path} ({e}); the file is damaged or "
                              f"not a uabs-train checkpoint: {ANOTHER}.") from None
    state = upgrade_state(state)
    validate_state(state, path)
    return state


def upgrade_state(state: Any) -> Any:
    """A checkpoint of format 1 in format 2: its replay buffer, a flat ring of per-agent
    transitions, laid out in step slots (the same transitions, so a resumed run samples
    what it would have). Anything else is returned as it is, for :func:`validate_state`."""
    from uabs_rl.algorithms.replay import upgrade_flat_replay

    if not (isinstance(state, dict) and state.get("format") == 1):
        return state
    replay = state.get("replay")
    if replay is not None:
        try:
            cfg = state["config"]
            m = int(cfg["scenario"]["n_uabs"])
            total = int(state["counters"]["env_steps"]) * int(cfg["train"]["n_envs"]) * m
            replay = upgrade_flat_replay(replay, int(cfg["algo"]["buffer_size"]), m, total)
        except (KeyError, TypeError, ValueError, IndexError, RuntimeError):
            return state  # not whole: validate_state names what is wrong
    return {**state, "format": CKPT_FORMAT, "replay": replay}


def validate_state(state: Any, path: Path) -> None:
    """Refuse a loaded checkpoint that lacks what
    :meth:`uabs_rl.training.experiment.Experiment.member_state` writes, holds a config
    uabs_rl's settings cannot take, or holds networks whose shapes do not fit that
    config; each message names the entry and the file."""
    if not isinstance(state, dict):
        raise CheckpointError(f"{path} holds {_kind(state)}, not a uabs-train checkpoint (a "
                              f"dict of format, config, learner, counters, rng): {ANOTHER}.")
    if state.get("format") != CKPT_FORMAT:
        found = f"format {state['format']!r}" if "format" in state else "no format entry"
        raise CheckpointError(f"{path} is not a uabs-train checkpoint of format {CKPT_FORMAT} "
                              f"(it has {found}): {ANOTHER}.")
    _check_layout(state, LAYOUT, "", path)
    if state.get("replay") is not None:
        _check_layout(state, {"replay": {"data": TENSORS, "written": INT,
                                         "generator": BYTES}}, "", path)
    cfg = config_from_checkpoint(state, path)
    _check_network(state["learner"], cfg, path)


def _kind(v: Any) -> str:
    return "None" if v is None else f"a {type(v).__name__}"


def _is(v: Any, kind: str) -> bool:
    if kind == TENSORS:
        return isinstance(v, dict) and all(isinstance(t, torch.Tensor) for t in v.values())
    if kind == BYTES:
        return isinstance(v, torch.Tensor) and v.dtype == torch.uint8
    if kind == NUMBER:
        return isinstance(v, (int, float)) and not isinstance(v, bool)
    if kind == INT:
        return isinstance(v, int) and not isinstance(v, bool)
    return isinstance(v, list if kind == "a list" else dict)


def _check_layout(d: dict, layout: dict[str, Any], prefix: str, path: Path) -> None:
    for key, kind in layout.items():
        name = prefix + key
        if key not in d:
            raise CheckpointError(f"{path} is not a complete uabs-train checkpoint: it lacks "
                                  f"{name}. The file was edited or not written by "
                                  f"uabs-train: {ANOTHER}.")
        v = d[key]
        if isinstance(kind, dict):
            if not isinstance(v, dict):
                raise CheckpointError(f"{path}: {name} is {_kind(v)}, expected a dict; the "
                                      f"file is damaged or not a uabs-train checkpoint: "
                                      f"{ANOTHER}.")
            _check_layout(v, kind, name + ".", path)
        elif not _is(v, kind):
            raise CheckpointError(f"{path}: {name} is {_kind(v)}, expected {kind}; the file is "
                                  f"damaged or not a uabs-train checkpoint: {ANOTHER}.")


def checkpoint_config(state: Mapping, path: Path | None = None) -> dict:
    """The stored config of ``state`` in today's keys, its sections checked to be
    dicts (OmegaConf's merge would name neither the section nor the file)."""
    d = state.get("config")
    where = f"{path}: " if path else ""
    if not isinstance(d, dict) or not d:
        raise CheckpointError(f"{where}its config is {'empty' if d == {} else _kind(d)}, not "
                              f"the run's settings: {ANOTHER}.")
    for key in (*CONFIG_SECTIONS, "seed"):
        if key not in d:
            raise CheckpointError(f"{where}its config lacks config.{key}: {ANOTHER}.")
        if key != "seed" and not isinstance(d[key], dict):
            raise CheckpointError(f"{where}config.{key} is {_kind(d[key])} ({d[key]!r:.40}), "
                                  f"expected the {key} settings (a dict): {ANOTHER}.")
    return upgrade_config(d)


def config_dict(cfg: RunConfig) -> dict:
    """The run config as plain types (enums as strings), without ``resume``: what a
    checkpoint stores and what compatibility is checked on."""
    d = OmegaConf.to_container(OmegaConf.structured(cfg), enum_to_str=True)
    d.pop("resume", None)
    return d


def upgrade_config(d: Any) -> Any:
    """A stored run config (checkpoint or ``.hydra/config.yaml``) in today's keys:
    ``train.tensorboard: true|false`` became ``train.logger: tensorboard|none``; the
    observation settings moved from ``scenario`` to the ``obs`` group (``MOVED``; a run
    written before has the paper's observation frame, and ``obs.name`` says which of
    ``conf/obs`` it matches); a learner's own settings (``mixing_embed_dim``, once in
    every run's ``algo``) stay only in the runs of that learner."""
    if not hasattr(d, "get"):
        return d
    train = d.get("train")
    if train is not None and "tensorboard" in train:
        train = dict(train)
        train["logger"] = "tensorboard" if train.pop("tensorboard") else "none"
        d = {**d, "train": train}
    scenario = d.get("scenario")
    if hasattr(scenario, "get") and any(old in scenario for _, old in MOVED):
        scenario, obs = dict(scenario), dict(d.get("obs") or {})
        for (_, old), (_, new) in MOVED.items():
            if old in scenario:
                obs[new] = scenario.pop(old)
        obs.setdefault("name", "lookahead_motion" if obs.get("motion") else
                       "lookahead" if obs.get("lookahead") else "paper")
        d = {**d, "scenario": scenario, "obs": obs}
    algo = own_learner_settings(d.get("algo"))  # algo.mixing_embed_dim: QMIX's alone
    return d if algo is d.get("algo") else {**d, "algo": algo}


def config_from_checkpoint(state: Mapping, path: Path | None = None) -> RunConfig:
    """The run's config (dataclasses) as stored in a checkpoint (read from ``path``):
    a config uabs_rl's settings cannot take is a :class:`CheckpointError` naming the
    key."""
    d = checkpoint_config(state, path)
    try:
        merged = OmegaConf.merge(structured_run(d), d)
        return OmegaConf.to_object(merged)
    except (OmegaConfBaseException, ValueError, TypeError, KeyError) as e:
        key = getattr(e, "full_key", None)
        first = next((ln for ln in str(e).splitlines() if ln.strip()), type(e).__name__)
        raise CheckpointError(
            f"{f'{path}: ' if path else ''}its stored config does not fit uabs_rl's "
            f"settings ({f'config.{key}: ' if key else ''}{first}); it was edited or written "
            f"by another version of uabs_rl: {ANOTHER}.") from None


def network_shapes(cfg: RunConfig) -> dict[str, torch.Size]:
    """The parameter shapes of the acting network ``cfg``'s algorithm builds, keyed as
    its state dict."""
    # here: the env's and the algorithms' imports are heavy for uabs-traces
    from uabs_rl.algorithms import Dims, algorithm_class
    from uabs_rl.env.uabs_env import N_ACTIONS

    p = EnvParams.from_config(cfg.scenario, cfg.channel, cfg.obs)
    with torch.device("meta"):  # shapes only: no memory, no initialisation
        net = algorithm_class(cfg.algo.name).acting_network(
            cfg.algo, Dims(p.obs_dim, N_ACTIONS, p.n_uabs))
    return {k: v.shape for k, v in net.state_dict().items()}


def _network_of(cfg: RunConfig) -> str:
    hidden = list(cfg.algo.hidden)
    try:
        obs = EnvParams.from_config(cfg.scenario, cfg.channel, cfg.obs).obs_dim
    except ConfigError:
        return f"algo.hidden={hidden}"
    return f"algo.hidden={hidden} on observations of size {obs}"


def _check_network(learner: dict, cfg: RunConfig, path: Path) -> None:
    """The networks and the optimiser's moments of ``learner`` have the shapes of the
    network ``cfg`` builds."""
    try:
        shapes = network_shapes(cfg)
    except (ConfigError, RuntimeError, ValueError, TypeError):
        return  # the stored values are refused where they are used, naming the key
    for what in ("qnet", "target"):
        problem = shape_mismatch(shapes, learner[what], f"learner.{what}.")
        if problem:
            raise CheckpointError(f"{path}: the checkpoint's network does not fit its config "
                                  f"({_network_of(cfg)}): {problem}; the file was edited or "
                                  f"pieced together: {ANOTHER}.")
    params = list(shapes.items())
    for i, st in learner["optim"]["state"].items():
        for name in ("exp_avg", "exp_avg_sq"):
            t = st.get(name) if isinstance(st, dict) else None
            ok = isinstance(i, int) and 0 <= i < len(params) and isinstance(t, torch.Tensor) \
                and t.shape == params[i][1]
            if not ok:
                want = (f"{list(params[i][1])} (as {params[i][0]})" if isinstance(i, int)
                        and 0 <= i < len(params) else f"one of {len(params)} parameters")
                raise CheckpointError(
                    f"{path}: the optimiser state does not fit the network: learner.optim."
                    f"state.{i}.{name} is {_shape_or_kind(t)}, expected {want}; the file was "
                    f"edited or pieced together: {ANOTHER}.")


def _shape_or_kind(t: Any) -> str:
    return f"{list(t.shape)}" if isinstance(t, torch.Tensor) else _kind(t)


def shape_mismatch(expected: Mapping[str, Any], got: Mapping[str, Any], prefix: str = "") -> str:
    """The first difference between the shapes ``expected`` (tensors or sizes, keyed as
    a state dict) and the tensors ``got``, in words; "" when they fit."""
    for k, want in expected.items():  # in the network's order: the first layer first
        want = want.shape if isinstance(want, torch.Tensor) else want
        if k not in got:
            return f"{prefix}{k} is missing"
        t = got[k]
        if not isinstance(t, torch.Tensor) or t.shape != want:
            return f"{prefix}{k} is {_shape_or_kind(t)} in the checkpoint, {list(want)} here"
    extra = [k for k in got if k not in expected]
    return f"{prefix}{extra[0]} is not part of this network" if extra else ""


def load_into(module: torch.nn.Module, state_dict: Mapping[str, Any], path: Path,
              what: str) -> None:
    """``module.load_state_dict(state_dict)``, refusing (a :class:`CheckpointError`
    naming the tensor and both shapes) a ``state_dict`` of another network; ``what``
    names it in the checkpoint (``learner.qnet``)."""
    problem = shape_mismatch(module.state_dict(), state_dict, f"{what}.")
    if problem:
        raise CheckpointError(f"{path}: the checkpoint's network does not fit this config: "
                              f"{problem}. Evaluate or resume it with the settings it was "
                              f"trained with.")
    module.load_state_dict(state_dict)


def check_finite(tensors: Mapping[str, torch.Tensor], path: Path, what: str) -> None:
    """Refuse NaN or infinite values in ``tensors`` (``what`` names them in the
    checkpoint), naming the first such tensor."""
    for k, t in tensors.items():
        bad = ~torch.isfinite(t)
        if bad.any():
            n_nan = int(torch.isnan(t).sum())
            raise CheckpointError(
                f"{path}: {what}.{k} holds {n_nan} NaN and {int(bad.sum()) - n_nan} infinite "
                f"values (of {t.numel()}): the training diverged before this checkpoint was "
                f"written. Use the run's other checkpoint (best.pt or last.pt), or train "
                f"again (a lower algo.lr, or algo.grad_clip).")


def config_differences(saved: dict, current: dict) -> list[str]:
    """Settings of ``COMPAT_KEYS`` that differ between a checkpoint and a config. A
    setting the saved config lacks (it was added since the run was written) counts as
    its default, the value the run had in effect."""
    a, b = flatten(saved), flatten(current)
    defaults = default_settings()
    keys = sorted(k for k in set(a) | set(b) if k in COMPAT_KEYS)
    old = {k: a.get(k, defaults.get(k, "<absent>")) for k in keys}
    return [f"{k}: {old[k]!r} in the checkpoint, {b.get(k, '<absent>')!r} now"
            for k in keys if old[k] != b.get(k)]


def check_compatible(state: dict, cfg: RunConfig, source: Path) -> None:
    """Refuse a checkpoint written with other result-changing settings, naming them."""
    diffs = config_differences(upgrade_config(state["config"]), config_dict(cfg))
    if diffs:
        raise CheckpointError(f"{source} was written with other settings:\n  "
                              + "\n  ".join(diffs)
                              + "\nRun with the checkpoint's settings to continue it.")


def load_hydra_config(run_dir: Path) -> dict | None:
    """The run's ``.hydra/config.yaml`` in today's keys, or None when it has none."""
    path = RunFolder(run_dir).hydra_config
    if not path.is_file():
        return None
    try:
        stored = OmegaConf.to_container(OmegaConf.load(path))
        if not isinstance(stored, dict) or not stored:  # cut by a full disk, or emptied
            raise ValueError("empty, or not a mapping of settings")
        stored = upgrade_config(stored)
        merged = OmegaConf.merge(structured_run(stored), stored)
    except Exception as e:  # yaml, type and key errors all mean: not this run's config
        first = (str(e).strip().splitlines() or [type(e).__name__])[0][:160]
        raise CheckpointError(f"{path} is damaged ({first}): restore it from a copy, or "
                              f"remove it to resume from the checkpoint's own config.") from None
    return config_dict(to_container(merged))


def check_own(state: dict, run_dir: Path, source: Path) -> None:
    """Refuse a checkpoint that another run wrote: another run id, or other
    result-changing settings than the run folder's own ``.hydra/config.yaml``. A member
    of a population (``<population>/seed=<s>``) is checked against its population's
    folder (its seed aside: each member has its own)."""
    member = RunFolder(run_dir).is_member and RunFolder(run_dir.parent).identity.is_file()
    home = run_dir.parent if member else run_dir
    check_identity(state, home, source)
    started = load_hydra_config(home)
    if started is None:
        return
    saved = upgrade_config(state["config"])
    if member:
        saved = {**saved, "seed": started.get("seed")}
    diffs = config_differences(saved, started)
    if diffs:
        raise CheckpointError(f"{source} does not belong to the run in {home}: its "
                              f"settings differ from the run's own .hydra/config.yaml ("
                              + "; ".join(diffs[:3]) + (" ..." if len(diffs) > 3 else "")
                              + "). Put this run's own checkpoint back, or resume the run "
                              "it came from.")
