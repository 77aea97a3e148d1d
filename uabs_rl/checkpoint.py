"""Checkpoints: atomic save, safe load (``weights_only``), the config they were written
with, and the check that a checkpoint fits the config it is resumed or evaluated under.

A checkpoint is one dict: ``format``, ``config`` (plain types: enums as strings),
``learner`` (networks, target, optimiser, update count), ``counters``, ``rng`` and
optionally ``replay`` (``train.checkpoint_buffer``).
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf

from uabs_rl.config import RunConfig

CKPT_FORMAT = 1
# config sections a checkpoint must agree with to be resumed or evaluated
COMPAT_KEYS = ("scenario", "channel", "masking", "algo", "traces", "seed", "train.n_envs",
               "train.population")


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable or from an incompatible config."""


class Interrupted(Exception):
    """Training stopped on Ctrl-C after saving a consistent ``last`` checkpoint."""


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
    except pickle.UnpicklingError as e:
        if "weights_only" in str(e):  # torch's text advises an unsafe retry: not repeated
            raise CheckpointError(
                f"{path} holds Python objects beyond tensors and plain values, so it is "
                f"not a uabs-train checkpoint; it was refused because loading it could "
                f"run code. Use a checkpoint written by uabs-train.") from None
        raise CheckpointError(f"cannot read checkpoint {path} (UnpicklingError); the "
                              f"file is damaged or not a uabs-train checkpoint.") from None
    except Exception as e:
        raise CheckpointError(f"cannot read checkpoint {path} ({type(e).__name__}: "
                              f"{str(e).splitlines()[0][:160]}); the file is damaged or not "
                              f"a uabs-train checkpoint.") from None
    if not isinstance(state, dict) or state.get("format") != CKPT_FORMAT:
        raise CheckpointError(f"{path} is not a uabs-train checkpoint of format {CKPT_FORMAT}.")
    return state


def checkpoint_path(path: Path, which: str = "best") -> Path:
    """``<run>/checkpoints/<which>.pt`` for a run directory, ``path`` for a file."""
    return path / "checkpoints" / f"{which}.pt" if path.is_dir() else path


def config_dict(cfg: RunConfig) -> dict:
    """The run config as plain types (enums as strings), without ``resume``: what a
    checkpoint stores and what compatibility is checked on."""
    d = OmegaConf.to_container(OmegaConf.structured(cfg), enum_to_str=True)
    d.pop("resume", None)
    return d


def upgrade_config(d: Any) -> Any:
    """A stored run config (checkpoint or ``.hydra/config.yaml``) in today's keys:
    ``train.tensorboard: true|false`` became ``train.logger: tensorboard|none``."""
    train = d.get("train") if hasattr(d, "get") else None
    if train is not None and "tensorboard" in train:
        train = dict(train)
        train["logger"] = "tensorboard" if train.pop("tensorboard") else "none"
        d = {**d, "train": train}
    return d


def config_from_checkpoint(state: dict) -> RunConfig:
    """The run's config (dataclasses) as stored in a checkpoint."""
    merged = OmegaConf.merge(OmegaConf.structured(RunConfig), upgrade_config(state["config"]))
    return OmegaConf.to_object(merged)


def flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(d, dict):
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(flatten(v, f"{prefix}{k}."))
        return out
    return {prefix[:-1]: d}


def config_differences(saved: dict, current: dict) -> list[str]:
    """Settings of ``COMPAT_KEYS`` that differ between a checkpoint and a config."""
    a, b = flatten(saved), flatten(current)
    keys = sorted(k for k in set(a) | set(b) if any(
        k == c or k.startswith(c + ".") for c in COMPAT_KEYS) and not k.endswith("cache_dir")
        and not k.startswith("traces.test."))  # test traces never touch a training run
    return [f"{k}: {a.get(k, '<absent>')!r} in the checkpoint, {b.get(k, '<absent>')!r} now"
            for k in keys if a.get(k) != b.get(k)]


def check_compatible(state: dict, cfg: RunConfig, source: Path) -> None:
    """Refuse a checkpoint written with other result-changing settings, naming them."""
    diffs = config_differences(upgrade_config(state["config"]), config_dict(cfg))
    if diffs:
        raise CheckpointError(f"{source} was written with other settings:\n  "
                              + "\n  ".join(diffs)
                              + "\nRun with the checkpoint's settings to continue it.")
